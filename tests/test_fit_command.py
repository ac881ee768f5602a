"""``robust-sindy fit``: a data file in, equations, a report, figures and a model file out."""

import json
import re
import warnings

import numpy as np
import pandas as pd
import pytest

import robust_sindy as rs
from robust_sindy.cli import main
from robust_sindy.fit_command import InputError, parse_library, read_table


@pytest.fixture(scope="module")
def lorenz_csv(tmp_path_factory):
    data = rs.systems.Lorenz().generate(t_end=4.0)
    rng = np.random.default_rng(0)
    x = data.x + 1e-3 * rng.normal(size=data.x.shape)
    x[::40, 1] += 15.0  # single-entry spikes
    frame = pd.DataFrame(x, columns=["x", "y", "z"])
    frame.insert(0, "time", data.t)
    path = tmp_path_factory.mktemp("data") / "lorenz.csv"
    frame.to_csv(path, index=False)
    return path, data


def test_fit_on_a_csv_prints_the_equations_and_writes_everything(lorenz_csv, tmp_path, capsys):
    path, _ = lorenz_csv
    out = tmp_path / "res"
    assert main(["fit", str(path), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "time 'time'" in text  # found by its name, and said so
    assert re.search(r"\(x\)' = -(9\.99\d|10\.00\d) x \+ (9\.99\d|10\.00\d) y", text)
    assert re.search(r"\(z\)' = -2\.66\d z \+ 1\.000 x\*y", text)
    assert "Diagnostics(" in text
    for name in ("model.json", "report.md", "data.png", "coefficients.png"):
        assert (out / name).stat().st_size > 0
    model = rs.load_model(out / "model.json")
    assert model.feature_names_ == ["x", "y", "z"]
    truth = rs.systems.Lorenz().true_coef()
    np.testing.assert_array_equal(model.coef_.T != 0, truth != 0)
    report = (out / "report.md").read_text()
    assert "![data](data.png)" in report and "(y)' =" in report


def test_fit_with_measured_derivatives_controls_and_a_composed_library(tmp_path, capsys):
    drone = rs.systems.Drone()
    data = drone.generate(t_end=4.0)
    names = drone.input_names
    frame = pd.DataFrame(np.hstack([data.x, data.u, data.x_dot]),
                         columns=names + [f"d{n}" for n in names[:6]])  # fmt: skip
    frame["t"] = data.t
    path = tmp_path / "drone.npz"
    np.savez(path, **{c: frame[c].to_numpy() for c in frame.columns})
    code = main([
        "fit", str(path), "--controls", ",".join(names[6:]),
        "--states", ",".join(names[:6]),
        "--derivatives", ",".join(f"d{n}" for n in names[:6]),
        "--library", "poly:1", "--terms", f"({names[6]} + {names[7]}) * sin({names[2]})",
        "--terms", f"({names[6]} + {names[7]}) * cos({names[2]})",
        "--terms", f"{names[6]} - {names[7]}", "--out", str(tmp_path / "o"), "--quiet",
    ])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert f"controls {names[6:]}" in text and "derivatives from columns" in text
    model = rs.load_model(tmp_path / "o" / "model.json")
    assert model.n_control_features_ == 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        direct = rs.HuberSINDy(library=parse_library("poly:1", [
            f"({names[6]} + {names[7]}) * sin({names[2]})",
            f"({names[6]} + {names[7]}) * cos({names[2]})", f"{names[6]} - {names[7]}",
        ])).fit(data.x, data.t, x_dot=data.x_dot, u=data.u, feature_names=names)  # fmt: skip
    np.testing.assert_allclose(model.coef_, direct.coef_, rtol=1e-12, atol=0)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--states", "x,w"], r"--states: no column 'w' in the data; its columns are"),
        (["--time", "when"], r"--time: no column 'when'"),
        (["--library", "cubic"], r"--library: unknown part 'cubic'"),
        (["--library", "poly:x"], r"needs an integer >= 0"),
        (["--terms", "__import__('os')"], r"calls '__import__'"),
        (["--terms", "sin(q)"], r"names 'q', which is not one of the inputs"),
        (["--derivatives", "x,y"], r"2 columns for 1 states \['z'\]"),
        (["--delta", "-1"], r"--delta: expected 'auto' or a finite number >= 0"),
        (["--time", "time", "--dt", "0.1"], r"give one of them"),
    ],
)
def test_bad_arguments_give_one_clear_line(lorenz_csv, tmp_path, capsys, args, message):
    path, _ = lorenz_csv
    with pytest.raises(SystemExit) as exit_:
        main(["fit", str(path), "--out", str(tmp_path / "o"), "--quiet", *args])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("robust-sindy fit: error: ") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err), err


def test_bad_files_give_one_clear_line(tmp_path, capsys):
    cases = {
        "missing.csv": None,
        "text.csv": "a,b\n1,2\nx,\n",
        "gaps.csv": "t,a,b\n0,1,2\n1,inf,3\n2,1,2\n3,1,2\n",
        "notimes.csv": "t,a,b\n0,1,2\n,1,3\n2,1,2\n3,1,2\n",
        "backwards.csv": "t,a\n0,1\n2,1\n1,1\n",
        "notime.csv": "a,b\n1,2\n3,4\n",
    }
    expect = {
        "missing.csv": "no such file",
        "text.csv": "no time",
        "gaps.csv": "column 'a' has 1 infinite values (file lines 3)",
        "notimes.csv": "column 't' has 1 missing or non-finite values (file lines 3); every",
        "backwards.csv": "must increase strictly; it does not at file line 4",
        "notime.csv": "give --time COLUMN or --dt STEP",
    }
    for name, content in cases.items():
        path = tmp_path / name
        if content is not None:
            path.write_text(content)
        with pytest.raises(SystemExit):
            main(["fit", str(path), "--out", str(tmp_path / "o"), "--quiet"])
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
        assert expect[name] in err, (name, err)


def test_cli_argument_errors_are_argparse_errors(tmp_path, capsys):
    afile = tmp_path / "a_file"
    afile.write_text("")
    for argv in (
        ["reproduce", "--jobs", "0"],
        ["reproduce", "--t-end", "nan"],
        ["reproduce", "--out", str(afile)],
        ["bench", "--skip-after", "-1"],
        ["zoo", "--seeds", "0"],
        ["fit", "data.csv", "--dt", "inf"],
    ):
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert "error: argument" in err and "Traceback" not in err, argv


def test_read_table_formats(tmp_path):
    frame = pd.DataFrame({"t": [0.0, 1.0, 2.0], "a": [1.0, 2.0, 4.0]})
    frame.to_csv(tmp_path / "f.tsv", sep="\t", index=False)
    pd.testing.assert_frame_equal(read_table(tmp_path / "f.tsv"), frame)
    np.savez(tmp_path / "f.npz", t=frame.t.to_numpy(), a=np.column_stack([frame.a, frame.a]))
    assert list(read_table(tmp_path / "f.npz").columns) == ["t", "a0", "a1"]
    pytest.importorskip("pyarrow")
    frame.to_parquet(tmp_path / "f.parquet")
    pd.testing.assert_frame_equal(read_table(tmp_path / "f.parquet"), frame)
    with pytest.raises(InputError, match="is a folder"):
        read_table(tmp_path)


def test_the_lynx_hare_example_runs(tmp_path, capsys):
    assert main(["dataset", "lynx_hare", "--out", str(tmp_path)]) == 0
    csv = tmp_path / "lynx_hare.csv"
    assert main(["fit", str(csv), "--time", "year", "--out", str(tmp_path), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "(hare)' =" in text and "(lynx)' =" in text
    # 21 yearly samples do not identify the lynx equation: the command says so
    assert "problem: equations [1]:" in text
    saved = json.loads((tmp_path / "model.json").read_text())
    assert saved["feature_names"] == ["hare", "lynx"]


def test_fit_in_the_weak_form_says_so_and_saves_the_choice(tmp_path, capsys):
    data = rs.systems.Lorenz().generate(t_end=10.0)
    rng = np.random.default_rng(2)
    x = data.x + 0.05 * np.sqrt(np.mean(data.x**2, axis=0)) * rng.normal(size=data.x.shape)
    frame = pd.DataFrame(x, columns=["x", "y", "z"])
    frame.insert(0, "time", data.t)
    path = tmp_path / "noisy.csv"
    frame.to_csv(path, index=False)
    out = tmp_path / "res"
    assert main(["fit", str(path), "--out", str(out), "--quiet", "--formulation", "weak"]) == 0
    text = capsys.readouterr().out
    assert "no derivatives (the weak form)" in text
    assert "formulation: weak form (formulation='weak')" in text
    model = rs.load_model(out / "model.json")
    assert model.get_params()["formulation"] == "weak"
    np.testing.assert_array_equal(model.coef_.T != 0, rs.systems.Lorenz().true_coef() != 0)
