import numpy as np
import pytest

import robust_sindy as rs

from .conftest import random_problem


@pytest.fixture(scope="module")
def solved():
    theta, y = random_problem(3)
    res = rs.fit(theta, y, method="cvxpy", lam=5.0)
    return theta, y, res


def test_objective_matches_cvxpy_value(solved):
    import cvxpy as cp

    theta, y, res = solved
    xi = cp.Variable(theta.shape[1])
    xi.value = res.coef[:, 0]
    expr = 0.5 * cp.sum(cp.huber(y[:, 0] - theta @ xi, 1.0)) + 5.0 * cp.norm1(xi)
    assert rs.objective(theta, y, res.coef, lam=5.0)[0] == pytest.approx(expr.value, rel=1e-12)


def test_kkt_is_small_at_the_optimum_and_large_after_a_perturbation(solved):
    theta, y, res = solved
    assert rs.kkt_violation(theta, y, res.coef, lam=5.0).max() < 1e-6
    bumped = res.coef.copy()
    j = np.abs(bumped[:, 0]).argmax()
    bumped[j, 0] *= 1.001
    assert rs.kkt_violation(theta, y, bumped, lam=5.0)[0] > 1e-4


def test_duality_gap_bounds_the_suboptimality(solved):
    theta, y, res = solved
    rng = np.random.default_rng(0)
    p_star = rs.objective(theta, y, res.coef, lam=5.0)
    for _ in range(5):
        other = res.coef + 0.05 * rng.normal(size=res.coef.shape)
        gap = rs.duality_gap(theta, y, other, lam=5.0)
        excess = rs.objective(theta, y, other, lam=5.0) - p_star
        assert np.all(gap >= excess - 1e-6 * np.abs(p_star))
        assert np.all(excess > 0)


def test_kkt_is_invariant_to_column_scaling(solved):
    # Without the L1 term, rescaling columns (and coefficients inversely) leaves the problem
    # unchanged, and the relative KKT violation must not notice.
    theta, y, res = solved
    scale = 10.0 ** np.arange(-3, theta.shape[1] - 3)
    other = res.coef + 1e-3
    k1 = rs.kkt_violation(theta, y, other, lam=0.0)
    k2 = rs.kkt_violation(theta * scale, y, other / scale[:, None], lam=0.0)
    np.testing.assert_allclose(k1, k2, rtol=1e-8)


def test_non_finite_solver_output_is_never_certified():
    from robust_sindy._certificates import certify

    theta, y = random_problem(3)
    xi = np.zeros((theta.shape[1], y.shape[1]))
    xi[0, 0] = np.nan
    cert = certify(theta, y, xi, np.ones(y.shape[1]), np.ones((1, y.shape[1])))
    assert cert.kkt[0] == np.inf
    assert np.isfinite(cert.kkt[1:]).all()
