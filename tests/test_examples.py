"""The examples of the documentation run as they are, and say what they claim."""

import pathlib
import runpy
import warnings

import matplotlib
import pytest

matplotlib.use("Agg")

EXAMPLES = sorted((pathlib.Path(__file__).parent.parent / "examples").glob("plot_*.py"))


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_runs(path, tmp_path, monkeypatch, capsys):
    import matplotlib.pyplot as plt

    monkeypatch.chdir(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # identification warnings are part of the output
        runpy.run_path(str(path), run_name="__main__")
    plt.close("all")
    out = capsys.readouterr().out
    assert out.strip(), "the example printed nothing"
    if path.stem == "plot_first_fit":
        assert "certified: True" in out
    if path.stem == "plot_lorenz_states":
        assert "support exact: True" in out
