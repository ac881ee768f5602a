import warnings

import numpy as np
import pytest

import robust_sindy as rs
from robust_sindy.selection import lambda_max

from .conftest import random_problem


def test_clarabel_and_osqp_agree():
    theta, y = random_problem(21)
    lam = 0.1 * lambda_max(theta, y, 1.0)
    a = rs.fit(theta, y, method="cvxpy", solver="clarabel", lam=lam)
    b = rs.fit(theta, y, method="cvxpy", solver="osqp", lam=lam)
    assert a.converged and b.converged
    np.testing.assert_allclose(a.objective, b.objective, rtol=1e-7)
    np.testing.assert_allclose(a.coef, b.coef, atol=1e-5)


def test_reference_uses_the_half_huber_convention():
    # On theta = I, lam = 0 the optimum is xi = y exactly with objective 0; with lam > 0
    # each coordinate is S(y, lam) clipped by delta: |y| > delta + lam shrinks by lam ...
    # The L1 prox with the factor 0.5 forgotten would shrink by lam / 2.
    theta = np.eye(3)
    y = np.array([0.3, -2.0, 5.0])
    res = rs.fit(theta, y, method="cvxpy", delta=10.0, lam=1.0)
    np.testing.assert_allclose(res.coef, [0.0, -1.0, 4.0], atol=1e-7)


def test_unknown_solver_is_rejected():
    theta, y = random_problem(22)
    with pytest.raises(ValueError, match="solver"):
        rs.fit(theta, y, method="cvxpy", solver="gurobi-ish")


def test_cvxpys_inaccuracy_warning_gives_way_to_the_certificate():
    # CVXPY warns that a solution "may be inaccurate" whenever the solver's status is
    # inaccurate, also where the certificate accepts the point: the reference keeps
    # the status in its messages and lets the certificate decide, which warns
    # (ConvergenceWarning, with the status) exactly where it rejects the point.
    # Clarabel is stopped early to get such statuses.
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(200, 8))
    y = theta @ rng.normal(size=8) + 0.1 * rng.normal(size=200)
    statuses = []
    for max_iter in range(2, 9):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = rs.fit(theta, y, method="cvxpy", delta=1.0, lam=1.0, max_iter=max_iter)
        statuses += out.messages
        assert not [w for w in caught if "may be inaccurate" in str(w.message)]
        flagged = [w for w in caught if issubclass(w.category, rs.ConvergenceWarning)]
        assert bool(flagged) == (not out.converged)
        if flagged:  # the solver's status, in the one warning there is
            assert out.messages[0] in str(flagged[0].message)
    assert any("inaccurate" in m or "limit" in m for m in statuses)
