"""Side-by-side check of the fast path against the reference solvers on the Lorenz problem.

The paper's set-up: Lorenz (sigma 10, rho 28, beta 8/3) from x0 = [0, 1, 20],
RK4 with step 0.01 s for 10 s (m = 1001), degree-2 library built from states with
20 % of the rows contaminated (sigma 0.5; 1e-3 elsewhere), exact derivatives;
delta = 1, lam = 1.  For every solver: median time over repeats after a warm-up,
iterations, relative objective gap to the best objective found, relative KKT.

Run:  python validation/core_crosscheck.py [--seeds 5] [--repeats 5]
Writes validation/results/core_crosscheck.md.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import robust_sindy as rs

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from tests.conftest import lorenz_library  # noqa: E402  (one generator for tests and checks)

SOLVERS = {
    "fast path (default)": dict(method="admm"),
    "CVXPY + Clarabel": dict(method="cvxpy", solver="clarabel"),
    "ADMM (paper settings)": dict(method="admm", **rs.PAPER_ADMM_OPTIONS),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rows = []
    for seed in range(args.seeds):
        theta, y = lorenz_library(seed, degree=2)
        results = {}
        for name, kw in SOLVERS.items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", rs.ConvergenceWarning)
                rs.fit(theta, y, **kw)  # warm-up (imports, CVXPY compilation caches)
                times = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    res = rs.fit(theta, y, **kw)
                    times.append(time.perf_counter() - t0)
            results[name] = (res, statistics.median(times))
        best = np.min([r.objective for r, _ in results.values()], axis=0)
        t_fast = results["fast path (default)"][1]
        for name, (res, t) in results.items():
            rows.append(
                (
                    seed,
                    name,
                    t,
                    t / t_fast,
                    res.iterations.tolist(),
                    res.converged,
                    float(np.max((res.objective - best) / best)),
                    float(res.kkt.max()),
                )
            )
    out = HERE / "results" / "core_crosscheck.md"
    out.parent.mkdir(exist_ok=True)
    lines = [
        "# Fast path vs reference on the Lorenz problem (m = 1001, delta = 1, lam = 1)",
        "",
        f"Median of {args.repeats} timed runs after a warm-up, in one process; "
        "`python validation/core_crosscheck.py`.",
        "",
        "| seed | solver | time [ms] | time / fast path | iterations per column | converged "
        "| rel. objective gap | rel. KKT |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for seed, name, t, ratio, its, conv, gap, kkt in rows:
        lines.append(
            f"| {seed} | {name} | {1e3 * t:.1f} | {ratio:.1f} | {its} | {conv} "
            f"| {gap:.1e} | {kkt:.1e} |"
        )
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
