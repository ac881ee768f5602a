"""Property-based checks of the estimator and its certificates (a short budget; the long
run is ``python validation/fuzz.py``)."""

import warnings

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import robust_sindy as rs
from robust_sindy.selection import lambda_max

SETTINGS = dict(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)


@st.composite
def problems(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    m, p = draw(st.integers(4, 60)), draw(st.integers(1, 6))
    theta = rng.normal(size=(m, p)) * 10.0 ** rng.uniform(-1, 1, size=p)
    if draw(st.booleans()) and p > 1:
        theta[:, -1] = theta[:, 0]  # a duplicated column: the optimum is not unique
    y = theta @ (rng.normal(size=p) * (rng.uniform(size=p) < 0.6))
    y += draw(st.sampled_from([0.0, 0.01])) * rng.normal(size=m)
    bad = rng.uniform(size=m) < draw(st.sampled_from([0.0, 0.2, 0.6]))
    y[bad] += rng.normal(scale=20.0, size=int(bad.sum()))
    ymax = max(float(np.abs(y).max()), 1e-3)
    delta = ymax * 10.0 ** draw(st.floats(-4, 0.5))
    lam = float(lambda_max(theta, y, delta)) * draw(st.sampled_from([0.0, 1e-3, 0.1, 0.7]))
    return theta, y, delta, lam


def _fit(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.ConvergenceWarning)
        return rs.fit(*args, **kw)


def _close(a, b):
    """Objectives equal within what a certificate at 1e-8 allows."""
    return abs(a - b) <= 1e-7 * max(abs(a), abs(b)) + 1e-12


@settings(**SETTINGS)
@given(problems(), st.floats(-100, 100), st.floats(-100, 100))
def test_certified_results_are_never_worse_than_clarabel_at_any_scale(problem, e_theta, e_y):
    theta, y, delta, lam = problem
    s_theta, s_y = 10.0**e_theta, 10.0**e_y
    fast = _fit(theta * s_theta, y * s_y, delta=delta * s_y, lam=lam * s_y * s_theta)
    ref = _fit(theta, y, method="cvxpy", delta=delta, lam=lam)
    back = rs.objective(theta, y, fast.coef * s_theta / s_y, delta=delta, lam=lam)[0]
    if fast.converged:
        assert back <= ref.objective[0] + 1e-8 * abs(ref.objective[0]) + 1e-12
    if fast.converged and ref.converged:
        assert back <= ref.objective[0] * (1 + 1e-8) + 1e-12


@settings(**SETTINGS)
@given(problems(), st.data())
def test_invariances_hold_within_the_certificate(problem, data):
    theta, y, delta, lam = problem
    base = _fit(theta, y, delta=delta, lam=lam)
    if not base.converged:
        return
    rng = np.random.default_rng(data.draw(st.integers(0, 1000)))
    m, p = theta.shape
    d = 10.0 ** rng.uniform(-3, 3, size=p)  # columns scaled: xi_j / d_j with lam_j = lam d_j
    cols = _fit(theta * d, y, delta=delta, lam=lam * d)
    c = 10.0 ** rng.uniform(-3, 3)  # targets with delta and lam: objective * c^2
    targ = _fit(theta, y * c, delta=delta * c, lam=lam * c)
    perm_r, perm_c = rng.permutation(m), rng.permutation(p)
    perm = _fit(theta[perm_r][:, perm_c], y[perm_r], delta=delta, lam=lam)
    twice = _fit(np.vstack([theta, theta]), np.concatenate([y, y]), delta=delta, lam=2 * lam)
    P = base.objective[0]
    for res, value in [
        (cols, rs.objective(theta, y, cols.coef * d, delta=delta, lam=lam)[0]),
        (targ, targ.objective[0] / c**2),
        (perm, perm.objective[0]),
        (twice, twice.objective[0] / 2),
    ]:
        if res.converged:
            assert _close(value, P), (value, P)


@settings(**SETTINGS)
@given(problems(), st.floats(-150, 150), st.floats(-150, 150), st.sampled_from(["ols", "stls"]))
def test_least_squares_certificates_hold_at_any_scale(problem, e_theta, e_y, method):
    """OLS and STLS: ``converged`` means their own certificate, checked independently here
    on the unscaled problem (numpy's least squares on all columns, or on STLS's support)."""
    theta0, y0, _, _ = problem
    s_t, s_y = 10.0**e_theta, 10.0**e_y
    kw = {} if method == "ols" else {"threshold": 0.05 * s_y / s_t}
    res = _fit(theta0 * s_t, y0 * s_y, method=method, **kw)
    assert res.certificate in ("least-squares normal equations", "STLS fixed point")
    coef = np.reshape(res.coef, -1) * s_t / s_y  # the same solution, unscaled
    if not np.all(res.converged):
        return
    support = np.ones(theta0.shape[1], bool) if method == "ols" else coef != 0
    if method == "stls":
        assert np.all(np.abs(coef[support]) >= 0.05 * (1 - 1e-9))  # stable support
    if not support.any():
        return
    ref, *_ = np.linalg.lstsq(theta0[:, support], y0, rcond=None)
    r_ref = np.linalg.norm(y0 - theta0[:, support] @ ref)
    r_got = np.linalg.norm(y0 - theta0 @ coef)
    assert r_got <= r_ref * (1 + 1e-8) + 1e-12 * np.linalg.norm(y0), (r_got, r_ref)
