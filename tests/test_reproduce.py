"""Smoke run of the reproduction and of the command (2 seeds, short horizon)."""

import csv

import numpy as np
import pytest

from robust_sindy import reproduce as rp
from robust_sindy.cli import main


@pytest.mark.parametrize("system", ["lorenz", "drone"])
def test_run_seed_gives_every_method_with_finite_iae(system):
    run = rp.run_seed(system, seed=0, t_end=3.0)
    assert set(run["methods"]) == set(rp.METHOD_NAMES)
    true = rp.SYSTEMS[system].true_coef()
    for m in run["methods"].values():
        assert m["coef"].shape == true.shape
        assert np.isclose(m["iae"], np.abs(true - m["coef"]).sum())
    assert run["methods"]["Huber, certified"]["converged"]


def test_paper_tables_printed_totals_follow_for_stls():
    # The STLS totals printed by the paper equal the sum of its per-equation IAE.
    for system in ("lorenz", "drone"):
        printed = rp.PAPER[system]["printed_iae"]["STLS"]
        assert sum(printed[:3]) == pytest.approx(printed[3], rel=1e-5)


def test_command_writes_tables_and_figures(tmp_path, capsys):
    code = main(["reproduce", "all", "--seeds", "2", "--t-end", "3", "--jobs", "1",
                 "--out", str(tmp_path), "--quiet"])  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    assert "| Huber, auto |" in out
    for name in ("reproduce.md", "reproduce_lorenz.csv", "reproduce_drone.csv",
                 "lorenz_iae.png", "drone_coefficients.png", "drone_simulation.png"):  # fmt: skip
        assert (tmp_path / name).stat().st_size > 0
    with open(tmp_path / "reproduce_lorenz.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * len(rp.METHOD_NAMES)
    assert all(np.isfinite(float(r["iae"])) for r in rows)
    md = (tmp_path / "reproduce.md").read_text()
    for line in md.splitlines():
        if line.startswith("| **IAE** |"):
            [float(v) for v in line.strip("|").split("|")[1:]]


def test_command_rejects_bad_arguments():
    with pytest.raises(SystemExit):
        main(["reproduce", "pendulum"])
    with pytest.raises(SystemExit):
        main(["reproduce", "--seeds", "0"])
