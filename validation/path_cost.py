"""Cost of a 50-point warm-started lam path in units of one cold fit (same data, one run).

For Lorenz and the drone (states contaminated as in the paper, seed 0, samples screened
by ``screen_rows``, delta by ``auto_delta``): the median time of 5 warm-started 50-point
paths, the same path solved cold point by point, and the mean time of one cold
``rs.fit`` over the 50 grid values.  Writes ``validation/results/path_cost.md``.

    python validation/path_cost.py
"""

import time
import warnings
from pathlib import Path

import numpy as np

import robust_sindy as rs
from robust_sindy.noise import contaminate
from robust_sindy.selection import auto_delta, path, screen_rows
from robust_sindy.systems import Drone, Lorenz


def problem(system):
    data = system.generate()
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
    z = noisy.x if data.u is None else np.hstack([noisy.x, data.u])
    theta = system.fitted_library().transform(z)
    y = noisy.x_dot[:, list(system.targets)]
    keep = ~screen_rows(theta, y).outliers
    return theta[keep], y[keep]


def median_time(f, repeats=5):
    f()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


rows = []
for name, system in [("Lorenz", Lorenz()), ("drone", Drone())]:
    theta, y = problem(system)
    delta = auto_delta(theta, y)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.ConvergenceWarning)
        warm = path(theta, y, delta)
        t_warm = median_time(lambda: path(theta, y, delta))  # noqa: B023
        t_cold_path = median_time(lambda: path(theta, y, delta, warm_start=False), 3)  # noqa: B023
        t_fit = []
        for lam in warm.lams:
            t_fit.append(median_time(lambda: rs.fit(theta, y, delta=delta, lam=lam), 3))  # noqa: B023
    mean_fit = float(np.mean(t_fit))
    rows.append((name, theta.shape, t_warm, t_cold_path, mean_fit, warm.converged.mean()))
    print(
        f"{name}: warm path {t_warm * 1e3:.1f} ms, cold path {t_cold_path * 1e3:.1f} ms, "
        f"one cold fit {mean_fit * 1e3:.2f} ms (mean over the grid) -> warm path = "
        f"{t_warm / mean_fit:.1f} cold fits; certified {100 * warm.converged.mean():.0f} %"
    )

lines = [
    "# Cost of a warm-started 50-point lam path",
    "",
    "`python validation/path_cost.py`; seed 0, states contaminated, screened samples, "
    "automatic delta; median of 5 runs after a warm-up (3 for the cold runs).",
    "",
    "| system | samples x terms | warm path [ms] | cold path [ms] | one cold fit [ms] "
    "| warm path / cold fit | points certified |",
    "|---|---|---|---|---|---|---|",
]
for name, shape, tw, tc, tf, conv in rows:
    lines.append(
        f"| {name} | {shape[0]} x {shape[1]} | {tw * 1e3:.1f} | {tc * 1e3:.1f} | "
        f"{tf * 1e3:.2f} | {tw / tf:.1f} | {100 * conv:.0f} % |"
    )
out = Path(__file__).parent / "results" / "path_cost.md"
out.write_text("\n".join(lines) + "\n")
print("wrote", out)
