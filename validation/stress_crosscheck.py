"""Stress sweep: default ADMM against CVXPY + Clarabel on 120 random hard problems.

Families drawn at random: m in {30, 100, 500, 2000}, p up to 40 (sometimes p >= m),
column scales over six decades, a bias column, an exactly collinear column pair,
Student-t (df = 2) noise, up to 30 % gross outliers, leverage outliers (whole rows
scaled), target scales 1e-3..1e4, delta 1e-3..10 times the target scale, lam from 1e-6
of lambda_max to above it, lam = 0.  Prints every column ADMM fails to certify and every
disagreement with Clarabel beyond 1e-8 relative objective; for an uncertified
problem it prints Clarabel's certificate beside ADMM's, the ratio delta / max|y| (near 0 the
problem is a least-absolute-deviation fit) and the condition number of the scaled library.

Run:  python validation/stress_crosscheck.py
"""

import time
import warnings

import numpy as np

import robust_sindy as rs
from robust_sindy.solvers.problem import DEFAULT_OPTIONS

TOL = DEFAULT_OPTIONS["tol"]  # the certificate ADMM must reach

rng = np.random.default_rng(123)
fails = 0
clarabel_uncertified = 0
worst = 0
tot_a = tot_c = 0
for trial in range(120):
    m = int(rng.choice([30, 100, 500, 2000]))
    p = int(rng.choice([3, 8, 20, 40]))
    n = int(rng.choice([1, 3, 6]))
    if p >= m:
        p = max(2, m // 3) if rng.random() < 0.7 else p  # sometimes p >= m
    th = (
        rng.normal(size=(m, p)) * 10.0 ** rng.uniform(-3, 3, size=p)
        if rng.random() < 0.5
        else rng.normal(size=(m, p))
    )
    if rng.random() < 0.3:
        th = np.column_stack([np.ones(m), th[:, 1:]])
    if rng.random() < 0.3:
        th[:, -1] = th[:, 0] * 2.0  # collinear
    coef = rng.normal(size=(p, n)) * (rng.random((p, n)) < 0.3)
    y = th @ coef + rng.standard_t(2, size=(m, n)) * 10.0 ** rng.uniform(-3, 1)
    bad = rng.random(m) < rng.uniform(0, 0.3)
    y[bad] += rng.normal(scale=10.0 ** rng.uniform(0, 4), size=(bad.sum(), n))
    if rng.random() < 0.2:
        th[bad] *= 5  # leverage outliers
    yscale = 10.0 ** rng.uniform(-3, 4)
    y *= yscale
    delta = 10.0 ** rng.uniform(-3, 1) * yscale
    lmax = np.abs(th.T @ np.clip(y, -delta, delta)).max(axis=0)
    lam = lmax * 10.0 ** rng.uniform(-6, 0.1)
    if rng.random() < 0.1:
        lam = 0.0 * lam
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.ConvergenceWarning)
        a = rs.fit(th, y, delta=delta, lam=lam)
        ta = time.perf_counter() - t0
        c = rs.fit(th, y, method="cvxpy", delta=delta, lam=lam)
    # Relative to the optimum, floored at 1e-12 of the objective at zero: when both
    # solvers fit exactly (lam = 0, p >= m) the optimum is rounding noise.
    p0 = rs.objective(th, y, np.zeros((p, n)), delta=delta, lam=lam)
    rel = np.max((a.objective - c.objective) / np.maximum(np.abs(c.objective), 1e-12 * p0))
    cond = np.linalg.cond(th / np.maximum(np.linalg.norm(th, axis=0), 1e-300))
    if not a.converged:
        fails += 1
        clarabel_uncertified += bool(c.kkt.max() > TOL)
        print(
            f"UNCERTIFIED {trial:3d} m={m} p={p} n={n} admm kkt {a.kkt.max():.1e} "
            f"clarabel kkt {c.kkt.max():.1e} rel obj (admm - clarabel) {rel:+.1e} "
            f"delta/max|y| {delta / np.abs(y).max():.1e} cond {cond:.1e}"
        )
        continue
    worst = max(worst, rel)
    tot_a += ta
    tot_c += c.solve_time
    if rel > 1e-8 or a.kkt.max() > 1e-8:
        print("DISAGREE", trial, m, p, n, rel, a.kkt.max(), c.kkt.max(), c.messages)
print(
    f"ADMM certified {120 - fails}/120; worst rel objective (admm - clarabel) on those "
    f"{worst:.1e}; time admm {tot_a:.2f} s, clarabel {tot_c:.2f} s. "
    f"Clarabel also above KKT {TOL:g} on {clarabel_uncertified}/{fails} uncertified problems."
)
