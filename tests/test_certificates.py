import warnings

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
    from robust_sindy.core.certificates import certify

    theta, y = random_problem(3)
    xi = np.zeros((theta.shape[1], y.shape[1]))
    xi[0, 0] = np.nan
    cert = certify(theta, y, xi, np.ones(y.shape[1]), np.ones((1, y.shape[1])))
    assert cert.kkt[0] == np.inf
    assert np.isfinite(cert.kkt[1:]).all()


def _outlier_problem():
    rng = np.random.default_rng(2)
    theta = rng.normal(size=(60, 4))
    y = theta @ [1.0, 0, -2, 0] + 0.01 * rng.normal(size=60)
    y[::10] += 30
    return theta, y


@pytest.mark.parametrize("scale", [1.0, 1e16, 1e-150, 1e150])
def test_rounding_never_certifies_the_least_squares_point_of_a_tiny_delta(scale):
    # With delta far below the residuals the optimum is a least-absolute-deviation fit;
    # the least-squares point is far from stationary, however small t * g is next to xi.
    theta, y = _outlier_problem()
    ls = np.linalg.lstsq(theta, y, rcond=None)[0]
    kkt = rs.kkt_violation(theta * scale, y * scale, ls, delta=1e-16 * scale, lam=0.0)
    assert kkt[0] > 1e-2


@pytest.mark.parametrize("seed", range(4))
def test_the_rounding_floor_forgives_rounding_only(seed):
    # The floor is what the rounding of the residuals can leave in the stationarity:
    # negligible where they carry noise, large where they are 1e-13 of terms of order
    # one, and nothing where that rounding reaches delta (a least-absolute-deviation
    # fit, whose stationarity floating point cannot resolve at all).
    from robust_sindy.core.certificates import rounding_floor

    theta, y = random_problem(seed)
    res = rs.fit(theta, y, delta=1.0, lam=1.0)
    n = y.shape[1]
    r = y - theta @ res.coef
    assert rounding_floor(theta, y, res.coef, np.ones(n), r).max() < 1e-12
    tiny = 1e-13 * np.abs(y).max()
    exact = theta @ res.coef + tiny
    assert rounding_floor(theta, exact, res.coef, np.ones(n), np.full_like(y, tiny)).min() > 1e-4
    lad = rounding_floor(theta, y, res.coef, np.full(n, 1e-17 * np.abs(y).max()), r)
    assert np.all(lad == 0.0)


def test_a_violation_within_its_floor_is_accepted_and_nothing_else_changes():
    # accept_within_floor, shared by a single fit's verdict and the walked path's: a
    # column already accepted stays so (its floor not computed: NaN); a rejected one
    # is accepted exactly when its violation is within its floor (computed here at
    # y - theta coef, or the floor given, which is not recomputed).
    from robust_sindy.core.certificates import accept_within_floor, rounding_floor

    theta, y = random_problem(0)
    coef = rs.fit(theta, y, delta=1.0, lam=1.0).coef
    n = y.shape[1]
    tiny = 1e-13 * np.abs(y).max()
    exact = theta @ coef + tiny  # residuals at the rounding level: a large floor
    floor = rounding_floor(theta, exact, coef, np.ones(n), exact - theta @ coef)
    assert floor.min() > 1e-4
    ok = np.zeros(n, dtype=bool)
    ok[0] = True
    kkt = np.where(np.arange(n) % 2 == 1, 0.5 * floor, 2.0 * floor)  # odd ones within
    accepted, found = accept_within_floor(theta, exact, coef, np.ones(n), kkt, ok)
    assert np.array_equal(accepted, ok | (np.arange(n) % 2 == 1))
    # (at residuals of the rounding level, recomputed: the same floor to within 1 %)
    assert np.isnan(found[0]) and np.allclose(found[1:], floor[1:], rtol=1e-2)
    given = np.full(n, np.nan)
    given[1:] = 1e-30  # given floors are used as they are: nothing forgiven now
    accepted, found = accept_within_floor(theta, exact, coef, np.ones(n), kkt, ok, floor=given)
    assert np.array_equal(accepted, ok) and np.array_equal(found, given, equal_nan=True)


@pytest.mark.parametrize("scale", [1e-150, 1e-50, 1e50, 1e150])
def test_fast_path_is_certified_and_invariant_at_extreme_library_scales(scale):
    theta, y = _outlier_problem()
    base = rs.fit(theta, y, delta=1.0, lam=1.0)
    res = rs.fit(theta * scale, y, delta=1.0, lam=scale)  # same problem, xi / scale
    assert res.converged and res.kkt.max() <= 1e-8
    np.testing.assert_allclose(res.coef * scale, base.coef, rtol=1e-6, atol=1e-9)


def test_every_method_reports_the_certificate_of_its_own_problem():
    theta, y = _outlier_problem()
    ols = rs.fit(theta, y, method="ols")
    stls = rs.fit(theta, y, method="stls", threshold=0.05)
    assert ols.certificate == "least-squares normal equations"
    assert stls.certificate == "STLS fixed point"
    assert ols.converged and ols.certificate_kkt.max() <= 1e-8
    assert stls.converged and stls.certificate_kkt.max() <= 1e-8
    # Their Huber-Lasso KKT (for the default delta, lam) is far from zero: it is reported
    # but it is not what their `converged` means.
    assert ols.kkt.max() > 1e-2
    # The reference is judged by its KKT certificate, not by the solver's status.
    ref = rs.fit(theta, y, method="cvxpy", delta=1.0, lam=1e300)
    assert ref.converged and np.all(ref.coef == 0)


def test_reference_is_not_converged_where_its_certificate_fails():
    theta, y = _outlier_problem()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.ConvergenceWarning)
        ref = rs.fit(theta, y, method="cvxpy", delta=1e-13, lam=0.0)
    assert ref.converged == bool(ref.kkt.max() <= 1e-5)
    if not ref.converged:
        assert ref.certificate_kkt.max() > 1e-5


@pytest.mark.parametrize("seed", range(3))
def test_the_products_of_the_rounding_bounds_read_only_a_models_terms(seed):
    # |Theta| |xi| (the scale of the rounding bounds) from the columns where xi has a
    # nonzero row: the same values as from the whole library, for an array and for the
    # solvers' equilibrated operator, on all rows or some, with columns of xi that are
    # zero, sparse or dense.
    from robust_sindy.core.certificates import _abs_product
    from robust_sindy.solvers.problem import prepare

    rng = np.random.default_rng(seed)
    m, p = 300, 40
    theta = rng.normal(size=(m, p)) * rng.uniform(0.1, 10.0, p)
    dense_xi = np.abs(rng.normal(size=(p, 3)))
    sparse_xi = np.where(rng.random((p, 1)) < 0.8, 0.0, dense_xi)
    sparse_xi[:, 0] = 0.0
    A = prepare(theta, equilibrate=True, kappa=1.0).A
    rows = np.sort(rng.choice(m, 50, replace=False))
    for lib, dense in [(theta, theta), (A, theta / A.scale)]:
        for r in (None, rows):
            for axi in (sparse_xi, dense_xi):
                want = np.abs(dense if r is None else dense[r]) @ axi
                got = _abs_product(lib, axi, r)
                assert np.allclose(got, want, rtol=1e-13, atol=0.0)
            assert np.all(_abs_product(lib, sparse_xi, r)[:, 0] == 0.0)
    assert np.all(_abs_product(theta, np.zeros((p, 2))) == 0.0)
