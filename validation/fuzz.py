"""Fuzzing the certificates: can the fast path claim an optimum it did not reach?

Each case is a random Huber-Lasso problem, possibly degenerate (duplicated or zero
columns, exact data, more terms than samples, most samples gross outliers), posed at an
extreme scale: the library multiplied by ``s_theta``, the targets and ``delta`` by ``s_y`` and
``lam`` by ``s_y s_theta`` (``s`` from 1e-150 to 1e150), which changes the solution only to
``xi s_y / s_theta`` and the objective to ``P s_y^2``.  The fast path solves the scaled
problem; CVXPY + Clarabel solves the same problem at unit scale, independently.

A failure is a fast-path result with ``converged=True`` whose objective, mapped back
to unit scale, exceeds Clarabel's by more than the allowance: 1e-8 of Clarabel's
objective plus 1e-12 of the objective at zero (for problems whose optimum is
numerically zero).  Uncertified
results are counted, not failures: saying "not certified" is allowed, lying is not.

    python validation/fuzz.py [N]          # N problems (default 10000), ~2 ms each + Clarabel

Then the same for OLS and STLS (their own certificates, numpy's least squares as the
reference), N problems each, and N / 5 problems at each extreme of delta.

Writes ``validation/results/fuzz.md``.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

import robust_sindy as rs
from robust_sindy.selection import lambda_max

RTOL = 1e-8


def make_problem(rng: np.random.Generator) -> dict:
    """A random (possibly degenerate) problem at unit scale and its scale factors."""
    m = int(rng.integers(3, 80))
    p = int(rng.integers(1, 9))
    theta = rng.normal(size=(m, p)) * 10.0 ** rng.uniform(-2, 2, size=p)
    kind = rng.choice(["plain", "duplicate", "zero column", "exact", "wide", "mostly bad"])
    if kind == "duplicate" and p > 1:
        theta[:, -1] = theta[:, 0]
    if kind == "zero column":
        theta[:, rng.integers(p)] = 0.0
    if kind == "wide":
        theta = theta[: max(2, p // 2)]
        m = theta.shape[0]
    xi = rng.normal(size=p) * (rng.uniform(size=p) < 0.5)
    y = theta @ xi
    if kind != "exact":
        y = y + 0.01 * rng.normal(size=m)
    bad = rng.uniform(size=m) < (0.7 if kind == "mostly bad" else 0.2)
    y[bad] += rng.normal(scale=30.0, size=int(bad.sum()))
    if not np.any(y):  # all-zero targets (xi = 0, exact data): give them a scale
        y = rng.normal(size=m)
    y_scale = float(np.abs(y).max())
    delta = y_scale * 10.0 ** rng.uniform(-6, 1)
    lmax = float(lambda_max(theta, y, delta)) if np.any(theta) else 1.0
    lam = 0.0 if rng.uniform() < 0.2 else lmax * 10.0 ** rng.uniform(-5, 0.3)
    e_theta, e_y = rng.uniform(-150, 150, size=2)
    while abs(e_theta + e_y) > 200:  # lam is scaled by both: keep it representable
        e_theta, e_y = rng.uniform(-150, 150, size=2)
    return {
        "theta": theta,
        "y": y,
        "delta": delta,
        "lam": lam,
        "kind": str(kind),
        "s_theta": 10.0**e_theta,
        "s_y": 10.0**e_y,
    }


def check(prob: dict) -> dict:
    """Fast path on the scaled problem against Clarabel at unit scale."""
    th, y, d, lam = prob["theta"], prob["y"], prob["delta"], prob["lam"]
    st, sy = prob["s_theta"], prob["s_y"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fast = rs.fit(th * st, y * sy, delta=d * sy, lam=lam * sy * st)
        ref = rs.fit(th, y, method="cvxpy", delta=d, lam=lam)
    obj_fast = float(rs.objective(th, y, fast.coef * st / sy, delta=d, lam=lam)[0])
    obj_ref = float(ref.objective[0])
    obj_zero = float(rs.objective(th, y, np.zeros(th.shape[1]), delta=d, lam=lam)[0])
    allowance = RTOL * abs(obj_ref) + 1e-12 * obj_zero
    excess = (obj_fast - obj_ref) / max(allowance, 1e-300)  # > 1: a failure
    return {
        "kind": prob["kind"],
        "fast_certified": fast.converged,
        "ref_certified": ref.converged,
        "excess": excess,
        "lie": bool(fast.converged and excess > 1.0),
    }


def make_extreme(rng: np.random.Generator, side: str) -> dict:
    """A problem of :func:`make_problem` with delta from 1e7 to 1e300 (``side="huge"``) or
    from 1e-300 to 1e-7 (``"tiny"``) times max|y|; the library alone is scaled (from 1e-150
    to 1e150, less where lam times the scale would leave the normal range) so that delta
    and lam stay representable."""
    prob = make_problem(rng)
    y_scale = float(np.abs(prob["y"]).max())
    exp = rng.uniform(7, 300) if side == "huge" else rng.uniform(-300, -7)
    prob["delta"] = y_scale * 10.0**exp
    lmax = (
        float(lambda_max(prob["theta"], prob["y"], prob["delta"])) if np.any(prob["theta"]) else 1.0
    )
    prob["lam"] = 0.0 if rng.uniform() < 0.2 else lmax * 10.0 ** rng.uniform(-5, 0.3)
    prob["s_y"] = 1.0
    if prob["lam"] > 0:  # lam s_theta must stay a normal number (no underflow to 0)
        e = np.log10(prob["lam"])
        prob["s_theta"] = 10.0 ** rng.uniform(max(-150, -290 - e), min(150, 290 - e))
    prob["kind"] = f"{side} delta: {prob['kind']}"
    return prob


def check_extreme(prob: dict) -> dict:
    """The fast path at an extreme delta against an independent bound.

    Huge delta: the Huber loss is ``r^2 / 2`` wherever ``|r| <= delta``, so the reference
    is CVXPY + Clarabel's Lasso (its objective evaluated as Huber).  Tiny delta: the
    Huber objective of the least-absolute-deviation solution (``min delta ||r||_1 + lam
    ||xi||_1`` by Clarabel) bounds the optimum from above.  Zero is a candidate too
    (when Clarabel fails).  A failure is a certified result above the lowest candidate's
    Huber objective by more than the allowance.
    """
    import cvxpy as cp

    th, y, d, lam = prob["theta"], prob["y"], prob["delta"], prob["lam"]
    st = prob["s_theta"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fast = rs.fit(th * st, y, delta=d, lam=lam * st)
        # Candidate points; the optimum is at most the lowest of their objectives.
        points = [np.zeros(th.shape[1])]
        if prob["kind"].startswith("huge"):
            points.append(rs.fit(th, y, method="cvxpy", loss="squared", lam=lam).coef)
        else:
            x = cp.Variable(th.shape[1])
            try:
                cp.Problem(cp.Minimize(cp.norm1(y - th @ x) + (lam / d) * cp.norm1(x))).solve(
                    solver="CLARABEL"
                )
            except cp.error.SolverError:
                pass  # no LAD point: zero remains the bound
            if x.value is not None:
                points.append(np.asarray(x.value))
    obj_fast = float(rs.objective(th, y, fast.coef * st, delta=d, lam=lam)[0])
    obj_ref = min(float(rs.objective(th, y, c, delta=d, lam=lam)[0]) for c in points)
    obj_zero = float(rs.objective(th, y, np.zeros(th.shape[1]), delta=d, lam=lam)[0])
    allowance = RTOL * abs(obj_ref) + 1e-12 * obj_zero
    excess = (obj_fast - obj_ref) / max(allowance, 1e-300)
    return {
        "kind": prob["kind"],
        "fast_certified": bool(fast.converged),
        "excess": excess,
        "lie": bool(fast.converged and excess > 1.0),
    }


def check_least_squares(prob: dict, method: str, rng: np.random.Generator) -> dict:
    """OLS or STLS on the scaled problem against numpy's least squares at unit scale.

    OLS: on all columns; STLS: on the support it returned, which must also be stable
    (no coefficient below the threshold).  A failure is ``converged=True`` with a residual
    norm above the reference's by more than 1e-8 relative (plus 1e-12 of ``|y|``), or an
    unstable STLS support.
    """
    th, y = prob["theta"], prob["y"]
    st, sy = prob["s_theta"], prob["s_y"]
    thr = float(np.abs(np.linalg.lstsq(th, y, rcond=None)[0]).max()) * 10.0 ** rng.uniform(-3, 0)
    kw = {} if method == "ols" else {"threshold": thr * sy / st}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = rs.fit(th * st, y * sy, method=method, **kw)
    coef = np.reshape(res.coef, -1) * st / sy
    support = np.ones(th.shape[1], bool) if method == "ols" else coef != 0
    certified = bool(np.all(res.converged))
    lie = False
    if certified:
        if method == "stls" and np.any(np.abs(coef[support]) < thr * (1 - 1e-9)):
            lie = True
        if support.any():
            ref = np.linalg.lstsq(th[:, support], y, rcond=None)[0]
            r_ref = np.linalg.norm(y - th[:, support] @ ref)
            r_got = np.linalg.norm(y - th @ coef)
            lie |= bool(r_got > r_ref * (1 + RTOL) + 1e-12 * np.linalg.norm(y))
    return {"kind": f"{method}: {prob['kind']}", "certified": certified, "lie": lie}


def main(n: int = 10_000, seed: int = 0) -> list[dict]:
    from tqdm import tqdm

    rng = np.random.default_rng(seed)
    rows = []
    t0 = time.perf_counter()
    for _ in tqdm(range(n), desc="fuzz", disable=not sys.stderr.isatty()):
        rows.append(check(make_problem(rng)))
    elapsed = time.perf_counter() - t0
    lies = [r for r in rows if r["lie"]]
    kinds = sorted({r["kind"] for r in rows})
    lines = [
        "# Fuzzing the certificates",
        "",
        f"Command: `python validation/fuzz.py {n}` (seed {seed}, {elapsed:.0f} s). Library "
        "and targets scaled by factors from 1e-150 to 1e150; delta from 1e-6 to 10 times "
        "max|y|; lam from 1e-5 to 2 times lambda_max, or 0. Reference: CVXPY + Clarabel "
        "on the same problem at unit scale. Allowance: 1e-8 of the reference objective plus "
        "1e-12 of the objective at zero; negative: the fast path is better.",
        "",
        "| kind | problems | fast path certified | reference certified | certified and worse "
        "than the reference (failures) | largest excess over the reference when certified, "
        "in units of the allowance |",
        "|---|---|---|---|---|---|",
    ]
    for kind in [*kinds, "all"]:
        sel = [r for r in rows if kind in ("all", r["kind"])]
        cert = [r for r in sel if r["fast_certified"]]
        worst = max((r["excess"] for r in cert), default=float("nan"))
        lines.append(
            f"| {kind} | {len(sel)} | {len(cert)} | {sum(r['ref_certified'] for r in sel)} "
            f"| {sum(r['lie'] for r in sel)} | {worst:.1e} |"
        )
    ls_rows = [
        check_least_squares(make_problem(rng), method, rng)
        for method in ("ols", "stls")
        for _ in tqdm(range(n), desc=f"fuzz {method}", disable=not sys.stderr.isatty())
    ]
    lines += [
        "",
        "## Least squares: OLS and STLS",
        "",
        f"The same generator, {n} problems per method, at the same scales. OLS certifies the "
        "normal equations, STLS its fixed point (stable support, least-squares optimal on "
        "it); the reference is numpy's least squares at unit scale on all columns (OLS) or "
        "on the returned support (STLS). A failure: certified, and a residual norm above "
        "the reference's by more than 1e-8 relative, or an STLS coefficient below its "
        "threshold.",
        "",
        "| method | problems | certified | certified and failing |",
        "|---|---|---|---|",
    ]
    for method in ("ols", "stls"):
        sel = [r for r in ls_rows if r["kind"].startswith(method)]
        lines.append(
            f"| {method} | {len(sel)} | {sum(r['certified'] for r in sel)} "
            f"| {sum(r['lie'] for r in sel)} |"
        )
    lies += [r for r in ls_rows if r["lie"]]
    n_ext = max(1, n // 5)
    ext_rows = [
        check_extreme(make_extreme(rng, side))
        for side in ("huge", "tiny")
        for _ in tqdm(range(n_ext), desc=f"fuzz {side} delta", disable=not sys.stderr.isatty())
    ]
    lines += [
        "",
        "## Extreme delta",
        "",
        f"{n_ext} problems per side from the same generator, delta from 1e7 to 1e300 times "
        "max|y| (huge) or from 1e-300 to 1e-7 (tiny), the library scaled from 1e-150 to "
        "1e150. References: huge, CVXPY + Clarabel's Lasso (the Huber loss is r^2 / 2 "
        "within delta); tiny, the Huber objective of Clarabel's least-absolute-deviation "
        "solution (an upper bound of the optimum). A failure: certified and above the "
        "reference's Huber objective by more than the allowance.",
        "",
        "| delta | problems | fast path certified | certified and failing | largest excess "
        "when certified (allowances) |",
        "|---|---|---|---|---|",
    ]
    for side in ("huge", "tiny"):
        sel = [r for r in ext_rows if r["kind"].startswith(side)]
        cert = [r for r in sel if r["fast_certified"]]
        worst = max((r["excess"] for r in cert), default=float("nan"))
        lines.append(
            f"| {side} | {len(sel)} | {len(cert)} | {sum(r['lie'] for r in sel)} | {worst:.1e} |"
        )
    lies += [r for r in ext_rows if r["lie"]]
    out = Path(__file__).parent / "results" / "fuzz.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"{len(lies)} certified results worse than the reference; wrote {out}")
    return rows


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10_000)
