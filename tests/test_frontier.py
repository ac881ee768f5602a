"""``robust-sindy frontier``: one case of the noise frontier, its table, files and errors."""

import csv

import numpy as np
import pytest

from robust_sindy import frontier
from robust_sindy.cli import main
from robust_sindy.flows import polynomial_system

pytest.importorskip("pysindy")


def test_one_case_scores_ours_and_a_peer_on_the_same_data(tmp_path):
    system = polynomial_system("Lorenz")
    rows = frontier.run_case(system, 0.01, seed=0, methods=("huber", "stlsq"))
    ours = next(r for r in rows if r["method"] == "huber")
    assert ours["formulation"] == "weak" and ours["exact"] and ours["error"] < 0.01
    assert {(r["method"], r["choice"]) for r in rows} == {
        ("huber", "default"),
        ("stlsq", "aicc"),
        ("stlsq", "oracle"),
    }
    oracle = next(r for r in rows if r["choice"] == "oracle")
    aicc = next(r for r in rows if r["choice"] == "aicc")
    # the oracle knows the truth: never worse than the threshold a user would pick
    assert (oracle["exact"], -oracle["error"]) >= (aicc["exact"], -aicc["error"])
    summary = frontier.summary(rows)
    text = frontier.table(summary)
    assert "| 1 % | 100 % / 100 %" in text and "weak form in 1 of 1" in text
    paths = frontier.write(rows, tmp_path, "robust-sindy frontier --test")
    assert [p.name for p in paths] == ["frontier.csv", "frontier.md", "frontier.png"]
    with open(paths[0]) as fh:
        assert len(list(csv.DictReader(fh))) == len(rows)


def test_the_published_table_sits_beside_the_published_rates(tmp_path):
    rows = [dict(system=f"s{i}", level=0.01, exact=i < 8, error=0.05 if i < 9 else 0.5,
                 warned=True, formulation="weak") for i in range(10)]  # fmt: skip
    rows[9]["warned"] = False  # a silent failure
    paths = frontier.write_published(rows, tmp_path, "robust-sindy frontier --published")
    text = paths[1].read_text()
    assert "| 1 % | 90 % (10 systems) | 80 % | 8 of 8 | 1 of 2 | 77 % |" in text
    assert np.isclose(frontier.PUBLISHED[0.01], 0.77)


def test_bad_levels_are_refused_with_the_option_named():
    with pytest.raises(SystemExit, match="--levels: not numbers"):
        main(["frontier", "--levels", "0.1,abc"])
    with pytest.raises(SystemExit, match="--levels must be in"):
        main(["frontier", "--levels", "-0.1"])
