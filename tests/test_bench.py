"""The quick benchmark runs every solver once and produces its table and figure."""

import csv

import numpy as np

from robust_sindy.cli import main


def test_quick_benchmark_writes_the_table_with_small_gaps(tmp_path, capsys):
    assert main(["bench", "--quick", "--out", str(tmp_path), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "Newton (fast path)" in printed
    for name in ("benchmark.md", "benchmark.csv", "benchmark.png"):
        assert (tmp_path / name).stat().st_size > 0
    with open(tmp_path / "benchmark.csv") as fh:
        rows = {r["solver"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {
        "Newton (fast path)",
        "CVXPY + Clarabel",
        "CVXPY + OSQP",
        "skglm",
        "PySINDy STLSQ",
        "ADMM (paper settings)",
    }
    for name, r in rows.items():
        assert int(r["runs"]) == 1, (name, r["note"])  # every solver ran
    fast = rows["Newton (fast path)"]
    assert float(fast["kkt"]) <= 1e-8
    assert float(fast["ratio"]) == 1.0
    assert float(fast["passes"]) > 0
    for name in ("Newton (fast path)", "CVXPY + Clarabel", "CVXPY + OSQP"):
        assert float(rows[name]["gap"]) <= 1e-7, name
    assert np.isnan(float(rows["PySINDy STLSQ"]["gap"]))  # a different problem
    report = (tmp_path / "benchmark.md").read_text()
    assert "## Whole identifications" in report and "| HuberSINDy() |" in report
    assert "## Cost of a warm-started lam path" in report
