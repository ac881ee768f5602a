"""The batched Newton fast path: its pieces against direct computations, batching against
column-by-column solves, and the ADMM fallback, all judged by certificates."""

import warnings

import numpy as np
import pytest
import scipy.linalg

import robust_sindy as rs
from robust_sindy.core.losses import huber_psi
from robust_sindy.selection import lambda_max
from robust_sindy.solvers import _kernel, driver
from robust_sindy.solvers import newton as nw
from robust_sindy.solvers.problem import prepare

from .conftest import (
    lorenz_library,
    mean_field_record,
    mean_field_rhs,
    mean_field_support,
    random_problem,
)


def _rel(a, b):
    return np.abs(a - b) / np.maximum(np.abs(b), 1.0)


@pytest.mark.parametrize("n_out", [0, 15, 180])
def test_inlier_gram_equals_the_gram_of_the_kept_rows(n_out):
    rng = np.random.default_rng(n_out)
    A = rng.normal(size=(200, 7)) * np.logspace(0, 3, 7)
    w = np.ones((200, 3))
    for k in range(3):
        w[rng.choice(200, size=n_out, replace=False), k] = 0.0
    w[:, 2] = np.where(w[:, 2] < 1, 10.0 ** rng.uniform(-300, 0, size=200), 1.0)  # reweighted
    M = nw.inlier_gram(A, A.T @ A, w)
    for k in range(3):
        fresh = (A * w[:, k, None]).T @ A
        np.testing.assert_allclose(M[k], fresh, rtol=0, atol=1e-12 * np.abs(fresh).max())


def test_rank_updated_inlier_grams_agree_with_fresh_ones():
    # A sequence of inlier sets changing a few rows at a time, some rows huge (whose
    # updates would leave rounding of their size): every matrix the cache returns
    # matches the Gram matrix of the kept rows formed afresh.
    rng = np.random.default_rng(0)
    A = rng.normal(size=(400, 6)) * np.logspace(0, 2, 6)
    A[:5] *= 1e6  # gross rows: moving them in or out forces a fresh matrix
    cache = nw.GramCache()
    inlier = rng.random((400, 2)) < 0.8
    for step in range(40):
        flip = rng.choice(400, size=(int(rng.integers(0, 12)), 2))
        for k in range(2):
            inlier[flip[:, k], k] ^= True
        if step % 10 == 5:  # every gross row leaves, then returns
            inlier[:5] = step % 20 == 15
        M = cache.gram(A, A.T @ A, inlier, ["a", "b"])
        for k in range(2):
            fresh = A[inlier[:, k]].T @ A[inlier[:, k]]
            d = np.sqrt(np.diag(fresh))
            np.testing.assert_allclose(M[k] / np.outer(d, d), fresh / np.outer(d, d), atol=1e-11)
    assert cache.updates > 0 and cache.fresh > 2  # both ways were taken


@pytest.mark.parametrize("n_out", [0, 15, 180])
def test_inlier_grams_on_working_sets_are_blocks_of_the_full_one(n_out):
    # Each column's matrix on its own terms (any order, any size, padded with zeros to
    # the largest) equals that block of the Gram matrix of its kept rows, whichever way
    # it is formed (the full matrix minus few outliers, or the inliers directly).
    rng = np.random.default_rng(10 + n_out)
    A = rng.normal(size=(200, 12)) * np.logspace(0, 3, 12)
    w = np.ones((200, 4))
    for k in range(4):
        w[rng.choice(200, size=n_out, replace=False), k] = 0.0
    sizes = np.array([12, 5, 1, 8])
    idx = np.stack([rng.permutation(12) for _ in range(4)])
    M = nw.inlier_gram(A, A.T @ A, w, idx, sizes)
    assert M.shape == (4, 12, 12)
    for k in range(4):
        J = idx[k, : sizes[k]]
        fresh = (A[:, J] * w[:, k, None]).T @ A[:, J]
        block = M[k, : J.size, : J.size]
        np.testing.assert_allclose(block, fresh, rtol=0, atol=1e-12 * np.abs(fresh).max())
        assert np.all(M[k, J.size :] == 0) and np.all(M[k, :, J.size :] == 0)


def test_cached_grams_follow_working_sets_that_grow_shrink_and_reorder():
    # Working sets that gain terms (the cached matrix is bordered), lose them (a block
    # of it is taken), or change at once, while a few rows change sides: every matrix
    # matches the one formed afresh on that set, and both the updates and fresh
    # formations are exercised.
    rng = np.random.default_rng(3)
    A = rng.normal(size=(300, 15)) * np.logspace(0, 2, 15)
    cache = nw.GramCache()
    inlier = rng.random((300, 2)) < 0.9
    J = [np.array([0, 3]), np.array([1, 2, 4])]
    for step in range(40):
        flip = rng.choice(300, size=(int(rng.integers(0, 8)), 2))
        for k in range(2):
            inlier[flip[:, k], k] ^= True
            move = rng.integers(0, 4)
            if move == 0:  # a term joins
                J[k] = np.append(J[k], rng.choice(np.setdiff1d(np.arange(15), J[k])))
            elif move == 1 and J[k].size > 1:  # a term leaves
                J[k] = np.delete(J[k], rng.integers(J[k].size))
            elif move == 2:  # reordered
                J[k] = rng.permutation(J[k])
            if step % 13 == 12:  # a new set altogether
                J[k] = rng.choice(15, size=int(rng.integers(1, 15)), replace=False)
        sizes = np.array([J[0].size, J[1].size])
        idx = np.zeros((2, sizes.max()), dtype=int)
        for k in range(2):
            idx[k, : sizes[k]] = J[k]
        M = cache.gram(A, A.T @ A, inlier, ["a", "b"], idx, sizes)
        for k in range(2):
            rows = A[inlier[:, k]][:, J[k]]
            fresh = rows.T @ rows
            d = np.sqrt(np.diag(fresh))
            got = M[k, : J[k].size, : J[k].size]
            np.testing.assert_allclose(got / np.outer(d, d), fresh / np.outer(d, d), atol=1e-11)
    assert cache.updates > 20 and cache.fresh > 2


def test_large_blocks_are_solved_by_cholesky_as_by_the_eigen_decomposition():
    # From CHOLESKY_SIZE terms a block is factorised by Cholesky when its condition
    # estimate is far from the eigenvalue cut: the same solution as the eigen-solver's.
    # A numerically singular block still goes to the eigen-solver and is reported.
    rng = np.random.default_rng(4)
    s = nw.CHOLESKY_SIZE + 12
    B = rng.normal(size=(3, 4 * s, s)) * np.logspace(0, 2, s)
    M = np.einsum("kia,kib->kab", B, B)
    M[2][:, 1] = M[2][:, 0]
    M[2][1, :] = M[2][0, :]
    b = rng.normal(size=(3, s))
    valid = np.ones((3, s), dtype=bool)
    valid[1, s - 5 :] = False  # a smaller block, still above the size
    out, deficient = nw._solve_blocks(M, b, valid)
    assert deficient.tolist() == [False, False, True]
    for k in range(2):
        n = int(valid[k].sum())
        np.testing.assert_allclose(out[k, :n], np.linalg.solve(M[k, :n, :n], b[k, :n]),
                                   rtol=1e-8)  # fmt: skip
        assert np.all(out[k, n:] == 0)
    np.testing.assert_allclose(out[2], np.linalg.pinv(M[2], rcond=1e-11, hermitian=True) @ b[2],
                               rtol=1e-6, atol=1e-12)  # fmt: skip


@pytest.mark.parametrize("seed", range(3))
def test_terms_enter_the_support_with_the_sign_that_made_them_enter(seed):
    # A warm start from a larger lam on a library of correlated terms: many terms enter
    # at once, and the joint step would give some the other sign (no descent
    # direction).  After the sign correction every entering term moves with its sign
    # and the step decreases the objective.
    from robust_sindy.core.losses import huber_psi

    theta, y = lorenz_library(seed, 3)
    prepared = prepare(theta)
    A, T = prepared.A, 1.0 / prepared.a_norms**2
    ys = y / np.abs(y).max(axis=0)
    delta = np.full(3, 0.05)
    lmax = np.atleast_1d(lambda_max(A @ np.eye(A.shape[1]), ys, delta))
    start = driver.solve(A @ np.eye(A.shape[1]), ys, delta, 0.3 * lmax).coef
    lam = np.broadcast_to(0.03 * lmax, start.shape).copy()
    r = ys - A @ start
    g = A.T @ huber_psi(r, delta)
    free = np.zeros_like(start, dtype=bool)
    d = nw.direction(A, prepared.G, T, r, delta, lam, start, g, free, np.zeros(3))
    u = start + T[:, None] * g
    entering = (start == 0) & (d != 0)
    assert entering.any()
    assert np.all(np.sign(d[entering]) == np.sign(u[entering]))
    q = A @ d
    s = np.where(start != 0, np.sign(start), np.sign(d))
    slope = (lam * s * d).sum(axis=0) - np.einsum("ij,ij->j", huber_psi(r, delta), q)
    assert np.all(slope < 0)


def test_masked_solve_solves_each_support_block_and_zeroes_the_rest():
    rng = np.random.default_rng(1)
    B = rng.normal(size=(3, 30, 6))
    M = np.einsum("kia,kib->kab", B, B)
    rhs = rng.normal(size=(6, 3))
    S = rng.uniform(size=(6, 3)) < 0.6
    S[0] = True
    d, deficient = nw.masked_solve(M, rhs, S)
    assert not deficient.any()
    for k in range(3):
        s = S[:, k]
        np.testing.assert_allclose(d[s, k], np.linalg.solve(M[k][np.ix_(s, s)], rhs[s, k]))
        assert np.all(d[~s, k] == 0)
    # A singular support block is reported (and solved in the minimum-norm sense).
    M[0][:, 1] = M[0][:, 0]
    M[0][1, :] = M[0][0, :]
    S[:2, 0] = True
    d, deficient = nw.masked_solve(M, rhs, S)
    assert deficient[0]
    s = S[:, 0]
    np.testing.assert_allclose(d[s, 0], np.linalg.pinv(M[0][np.ix_(s, s)]) @ rhs[s, 0])


def test_masked_solve_batches_supports_of_every_size():
    # Blocks are gathered to the largest support's size: an empty support, a full one
    # and sizes in between, in one batch, each solved as on its own.
    rng = np.random.default_rng(2)
    p, k = 9, 5
    B = rng.normal(size=(k, 40, p)) * np.logspace(-1, 1, p)  # diagonals apart
    M = np.einsum("kia,kib->kab", B, B)
    rhs = rng.normal(size=(p, k))
    S = np.zeros((p, k), dtype=bool)
    S[:, 1] = True
    S[[2, 7], 2] = True
    S[rng.permutation(p)[:5], 3] = True
    S[4, 4] = True
    d, deficient = nw.masked_solve(M, rhs, S)
    assert not deficient.any()
    assert np.all(d[:, 0] == 0)
    for j in range(1, k):
        s = S[:, j]
        np.testing.assert_allclose(d[s, j], np.linalg.solve(M[j][np.ix_(s, s)], rhs[s, j]))
        assert np.all(d[~s, j] == 0)


@pytest.mark.parametrize(
    "problem",
    [("random", s, o) for s in range(4) for o in (0.1, 0.3)] + [("lorenz", 0, 2), ("lorenz", 1, 3)],
)
def test_batched_and_column_wise_solves_agree(problem):
    kind, seed, arg = problem
    if kind == "random":
        theta, y = random_problem(seed, n=3, outliers=arg)
    else:
        theta, y = lorenz_library(seed, arg)
    lam = 0.05 * lambda_max(theta, y, 1.0)
    joint = rs.fit(theta, y, delta=1.0, lam=lam)
    assert joint.converged and joint.kkt.max() <= 1e-8
    for k in range(3):
        alone = rs.fit(theta, y[:, k], delta=1.0, lam=lam[k])
        assert alone.converged
        assert _rel(joint.objective[k], alone.objective[0]) <= 1e-10


@pytest.mark.parametrize("degree", [2, 3])
def test_system_problem_agrees_with_clarabel_without_the_fallback(degree):
    theta, y = lorenz_library(0, degree)
    res = rs.fit(theta, y, delta=1.0, lam=1.0)
    assert res.solver == "newton" and res.converged and res.kkt.max() <= 1e-8
    assert not res.info["fallback"].any()
    ref = rs.fit(theta, y, method="cvxpy", delta=1.0, lam=1.0)
    assert np.all((res.objective - ref.objective) / np.abs(ref.objective) <= 1e-8)


def test_columns_newton_hands_over_are_certified_by_the_admm():
    theta, y = lorenz_library(1, 2)
    res = rs.fit(theta, y, delta=1.0, lam=1.0, newton_steps=0)  # Newton takes no step
    assert res.info["fallback"].all() and res.iterations.min() > 0
    assert res.converged and res.kkt.max() <= 1e-8
    fast = rs.fit(theta, y, delta=1.0, lam=1.0)
    assert np.all(_rel(res.objective, fast.objective) <= 1e-8)
    assert all("ADMM" in msg for msg in res.messages)


def test_paper_settings_are_the_plain_admm():
    theta, y = lorenz_library(0, 2, m=301)
    with pytest.warns(rs.ConvergenceWarning):  # the paper's 5000 iterations do not suffice
        res = rs.fit(theta, y, delta=1.0, lam=1.0, **rs.PAPER_ADMM_OPTIONS)
    assert res.solver == "admm" and "newton_steps" in res.info
    assert res.info["newton_steps"].sum() == 0


def test_passes_over_theta_are_counted(monkeypatch):
    theta, y = lorenz_library(0, 2)
    res = rs.fit(theta, y, delta=1.0, lam=1.0)
    steps = res.info["newton_steps"]
    if driver.use_kernel(prepare(theta).A, y.shape[1]):
        # The compiled iteration works column by column: per step one pass for the
        # residual and gradient and one for the direction's image, per column one more
        # for the certificate and one for dropping rounding-level entries.
        assert 3 <= res.info["passes"] <= np.sum(2 * steps + 2) + 2
    monkeypatch.setattr(driver, "USE_KERNEL", False)
    res = rs.fit(theta, y, delta=1.0, lam=1.0)
    # One residual, one gradient and one direction image per step for all columns
    # together, plus the start.
    assert 3 <= res.info["passes"] <= 3 * res.info["newton_steps"].max() + 6


def test_near_lad_points_are_certified_by_newton_without_the_admm():
    # The paper's contaminated Lorenz data after the model screen, delta from the data
    # (about 3e-4 of the targets' spread): at large lam nearly every residual is beyond
    # delta, a least-absolute-deviation-like problem that takes Newton tens of steps.
    # It must get them rather than hand the column to the much slower ADMM.
    from robust_sindy.noise import contaminate
    from robust_sindy.selection import auto_delta, screen_rows
    from robust_sindy.systems import Lorenz

    system = Lorenz()
    data = system.generate()
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
    theta = system.fitted_library().transform(noisy.x)
    y = noisy.x_dot[:, list(system.targets)]
    keep = ~screen_rows(theta, y).outliers
    theta, y = theta[keep], y[keep]
    delta = np.atleast_1d(auto_delta(theta, y))
    lam = lambda_max(theta, y, delta) * np.logspace(0, -4, 50)[13]
    out = driver.solve(theta, y, delta, lam)
    assert out.converged.all() and not out.info["fallback"].any()
    assert rs.kkt_violation(theta, y, out.coef, delta, lam).max() <= 1e-8


def _limit_cycle_terms(equation: int, error: float):
    """A mean-field model's record on its limit cycle and one equation's own three
    terms: targets of order one that the terms meet up to a smooth error of ``error``
    (as a high-order derivative leaves), with the shift mode nearly constant, so that
    ``x0`` and ``x0*x2`` (or ``x2`` and the squares) are nearly one direction."""
    t, x = mean_field_record(300, 3000)
    a, b, c = x.T
    terms = [np.column_stack(v) for v in ([a, b, a * c], [a, b, b * c], [c, a * a, b * b])]
    y = np.array([mean_field_rhs(0, v)[equation] for v in x]) + error * np.sin(3 * t)
    return terms[equation], y


@pytest.mark.parametrize("equation, error", [(0, 1e-9), (1, 3e-9), (2, 1e-9), (0, 1e-8)])
def test_a_nearly_exact_fit_is_certified_to_the_floating_point_floor(equation, error):
    # Terms of order one that cancel to 1e-9 of themselves: the residuals' rounding
    # leaves the stationarity at about 1e-7, which no method resolves.  The fast path
    # used to hand such a column to the ADMM, which ran its 20 000 iterations and warned;
    # it is now certified to that floor, with no worse an objective than least squares.
    theta, y = _limit_cycle_terms(equation, error)
    delta = 1e-4 * np.sqrt(np.mean(y**2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = rs.fit(theta, y, delta=delta, lam=0.0)
    assert res.converged and res.iterations.max() == 0
    assert not res.info["fallback"].any()
    ls = np.linalg.lstsq(theta, y, rcond=None)[0]
    assert np.abs(y - theta @ ls).max() < delta  # every sample an inlier: least squares
    assert res.objective[0] <= rs.objective(theta, y, ls, delta, 0.0)[0] * (1 + 1e-8)


@pytest.mark.parametrize("t_end", [100.0, 300.0])
def test_an_exact_record_needs_no_admm(t_end, monkeypatch):
    # Exact states of a mean-field model, partly or mostly on its limit cycle: the
    # screen's pilots and the refits fit to about 1e-9 of their terms.  Every column is
    # certified by Newton or to the floating-point floor; none goes to the ADMM (which
    # ran its 1000 or 20 000 iterations on six to eight of them, and the model warned).
    calls = []
    original = driver.solve_admm

    def counted(*args, **kwargs):
        calls.append(args[1].shape)
        return original(*args, **kwargs)

    monkeypatch.setattr(driver, "solve_admm", counted)
    t, x = mean_field_record(t_end, 3000)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = rs.HuberSINDy().fit(x, t)
    np.testing.assert_array_equal(model.support_, mean_field_support(model))
    assert calls == []
    assert not [w for w in caught if issubclass(w.category, rs.ConvergenceWarning)]


def _offset_cubic(seed, m=1500):
    """Cubic monomials of three states 1 +- 0.02: columns nearly collinear (condition
    number near 3e6, 1e13 for their Gram matrix), two sparse columns, 10 % outliers."""
    rng = np.random.default_rng(seed)
    x = 1.0 + 0.02 * rng.standard_normal((m, 3))
    theta = rs.PolynomialLibrary(degree=3).fit(x).transform(x)
    coef = np.zeros((theta.shape[1], 2))
    coef[[1, 5, 9], 0] = [1.0, -2.0, 0.5]
    coef[[2, 7], 1] = [0.7, 1.5]
    y = theta @ coef + 1e-3 * rng.standard_normal((m, 2))
    bad = rng.choice(m, m // 10, replace=False)
    y[bad] += 0.2 * rng.standard_normal((bad.size, 2))
    return theta, y


@pytest.mark.parametrize("seed", [0, 1])
def test_an_ill_conditioned_library_is_certified_by_newton_itself(seed):
    # The Gram systems' eigenvalue cut drops the directions along which the optimum
    # still moves; steps from the rows themselves keep them, so Newton certifies in
    # tens of steps where it used to stall and hand the column to an ADMM that ran out
    # of iterations (uncertified).
    theta, y = _offset_cubic(seed)
    assert prepare(theta).condition() > 1e6
    res = rs.fit(theta, y, delta=1.5e-3, lam=0.0)
    assert res.converged and res.kkt.max() <= 1e-8
    assert not res.info["fallback"].any()
    assert all(msg.startswith("certified by the active-set Newton") for msg in res.messages)
    ref = rs.fit(theta, y, method="cvxpy", delta=1.5e-3, lam=0.0)
    assert np.all((res.objective - ref.objective) / np.abs(ref.objective) <= 1e-8)


def test_row_direction_is_the_gram_direction_where_both_resolve():
    # Well conditioned: the step from the rows' singular values is the one from the
    # Gram system, for the inlier piece (outliers' +-delta in the right-hand side), the
    # reweighted step, off-support coordinates and a Levenberg-Marquardt term alike.
    theta, y = random_problem(3, n=1, outliers=0.2)
    prepared = prepare(theta)
    A, G, T = prepared.A, prepared.G, 1.0 / prepared.a_norms**2
    p = G.shape[0]
    rng = np.random.default_rng(0)
    x = rng.normal(size=p)
    x[:2] = 0.0
    r = y[:, 0] - A @ x
    delta = float(np.median(np.abs(r)))
    g = A.T @ huber_psi(r, delta)
    lam = np.full(p, 0.1 * np.abs(g).max())
    S = np.abs(x + T * g) > T * lam
    sigma = np.sign(x + T * g)
    off = np.where(S, 0.0, x)
    for w in [(np.abs(r) <= delta).astype(float), np.minimum(1.0, delta / np.abs(r))]:
        for mu in [0.0, 1e-2]:
            M = (A[np.arange(r.size)] * w[:, None]).T @ A[np.arange(r.size)]
            rhs = g - lam * sigma + M @ off
            expect = np.zeros(p)
            expect[S] = np.linalg.solve(M[np.ix_(S, S)] + mu * np.eye(S.sum()), rhs[S])
            d, cut = nw.row_direction(A, w, r, S, x, lam * sigma, delta, mu, None)
            assert not cut
            np.testing.assert_allclose(d, expect, rtol=1e-9, atol=1e-12 * np.abs(expect).max())


def _kernel_cases():
    """(theta, y, fit keyword arguments) for the compiled iteration's comparison."""
    cases = {}
    for seed, out in [(0, 0.1), (1, 0.3), (2, 0.0)]:
        theta, y = random_problem(seed, n=3, outliers=out)
        cases[f"random-{seed}"] = (theta, y, {"delta": 1.0, "lam": 0.05 * lambda_max(theta, y)})
    theta, y = lorenz_library(0, 3)
    cases["lorenz-3"] = (theta, y, {"delta": 1.0, "lam": 1.0})
    theta, y = random_problem(4, n=2, badly_scaled=True)
    weights = np.random.default_rng(4).uniform(0.0, 2.0, size=(theta.shape[1], 2))
    weights[:3, 0] = 0.0  # unpenalised terms
    cases["weighted-lam"] = (theta, y, {"delta": 0.5, "lam": weights * lambda_max(theta, y)[0]})
    theta, y = random_problem(5, n=2)
    cases["squared"] = (theta, y, {"loss": "squared", "lam": 0.1 * lambda_max(theta, y)})
    cases["no-equilibration"] = (theta, y, {"delta": 1.0, "lam": 5.0, "equilibrate": False})
    theta, y = _offset_cubic(0)  # singular inlier blocks: the NumPy steps finish
    cases["ill-conditioned"] = (theta, y, {"delta": 1.5e-3, "lam": 0.0})
    theta, y = random_problem(6, n=2, outliers=0.3)
    cases["near-lad"] = (theta, y, {"delta": 1e-4, "lam": 0.2 * lambda_max(theta, y, 1e-4)})
    return cases


_KERNEL_CASES = _kernel_cases()


def _record_kernel_statuses(monkeypatch) -> list:
    """A list that gets the per-column status of every call of the compiled iteration
    (fits; a path walk hands a point it cannot certify over to such a fit)."""
    statuses = []
    original = _kernel.newton_kernel

    def spy(*args, **kw):
        out = original(*args, **kw)
        statuses.append(out[1])
        return out

    monkeypatch.setattr(_kernel, "newton_kernel", spy)
    return statuses


@pytest.mark.skipif(not _kernel.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("name", sorted(_KERNEL_CASES))
def test_compiled_and_numpy_iterations_reach_the_same_certified_optimum(name, monkeypatch):
    theta, y, kwargs = _KERNEL_CASES[name]
    statuses = _record_kernel_statuses(monkeypatch)
    compiled = rs.fit(theta, y, **kwargs)
    assert statuses, "the compiled iteration did not run"
    monkeypatch.setattr(driver, "USE_KERNEL", False)
    plain = rs.fit(theta, y, **kwargs)
    assert len(statuses) == 1  # not called with the switch off
    for res in (compiled, plain):
        assert res.converged and res.kkt.max() <= 1e-8
    assert np.all(_rel(compiled.objective, plain.objective) <= 1e-10)
    # The kernel certifies every column itself, the near-least-absolute-deviation one
    # too (its damped and reweighted steps go on past t = 1 along their direction).
    assert np.all(statuses[0] == 0)


@pytest.mark.skipif(not _kernel.AVAILABLE, reason="numba is not installed")
def test_columns_the_compiled_iteration_leaves_are_solved_by_the_numpy_steps(monkeypatch):
    theta, y = lorenz_library(0, 3)
    reference = rs.fit(theta, y, delta=1.0, lam=1.0)
    monkeypatch.setattr(driver, "KERNEL_STEPS", 2)  # the kernel's budget: two steps
    statuses = _record_kernel_statuses(monkeypatch)
    res = rs.fit(theta, y, delta=1.0, lam=1.0)
    assert np.all(statuses[0] == 1)  # out of steps: every column handed over
    assert res.converged and res.kkt.max() <= 1e-8 and not res.info["fallback"].any()
    assert np.all(_rel(res.objective, reference.objective) <= 1e-10)
    # The steps reported are the kernel's and then the NumPy iteration's.
    assert np.all(res.info["newton_steps"] > 2)


def test_the_compiled_iteration_takes_only_the_small_problems():
    theta, _ = random_problem(0, m=300, p=12, n=3)
    prepared = prepare(theta)
    assert driver.use_kernel(prepared.A, 3) == _kernel.AVAILABLE
    big = prepare(np.ones((100_000, 10)))
    assert not driver.use_kernel(big.A, 3)  # the batched NumPy passes serve every column
    # A small library in column order (a selection of columns, theta[:, keep]) is
    # copied once in row order and goes to the kernel too; a large one is not copied.
    fortran = prepare(np.asfortranarray(theta))
    assert fortran.A.theta.flags.c_contiguous
    assert driver.use_kernel(fortran.A, 3) == _kernel.AVAILABLE
    large = np.asfortranarray(np.ones((100_000, 10)))
    assert prepare(large).A.theta is large


@pytest.mark.skipif(not _kernel.AVAILABLE, reason="numba is not installed")
def test_a_kernel_that_cannot_compile_warns_once_and_numpy_does_the_work(monkeypatch):
    from numba.core.errors import TypingError

    def broken():
        raise TypingError("no implementation for this NumPy")

    theta, y = random_problem(0, n=2)
    reference = rs.fit(theta, y, delta=1.0, lam=5.0)
    monkeypatch.setattr(_kernel._jit, "broken", None)  # restored afterwards
    monkeypatch.setattr(_kernel._jit, "compile", broken)
    with pytest.warns(RuntimeWarning, match="could not be compiled"):
        first = rs.fit(theta, y, delta=1.0, lam=5.0)
    assert not _kernel.usable()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # once only
        again = rs.fit(theta, y, delta=1.0, lam=5.0)
    for res in (first, again):
        assert res.converged
        assert np.all(_rel(res.objective, reference.objective) <= 1e-10)


@pytest.mark.skipif(not _kernel.AVAILABLE, reason="numba is not installed")
def test_the_compiled_iteration_certifies_nearly_every_column_of_the_automatic_pipeline(
    monkeypatch,
):
    # The pipeline's near-least-absolute-deviation path points start with few samples
    # inside delta: their reweighted and damped steps stop far short of the minimum
    # along their direction, and the line search must go on past t = 1 (without it the
    # kernel handed 14 of about 70 columns to the NumPy steps on the first record); the
    # refits of column selections (column-major) run compiled too.  A rate over three
    # records: a hard path point the kernel stalls on is handed to the NumPy iteration
    # (0 to 3 of about 70 columns a record, measured; the single record asserted before
    # gave 0 or 1 depending on the library's scales).
    from robust_sindy.bench import bench_data

    statuses = _record_kernel_statuses(monkeypatch)
    for seed in range(3):
        t, x, x_dot = bench_data(1000, seed=seed, states=3)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rs.HuberSINDy().fit(x, t=t, x_dot=x_dot)
    columns = sum(s.size for s in statuses)
    assert len(statuses) > 60 and columns > 150
    assert sum(int(np.count_nonzero(s)) for s in statuses) <= 0.05 * columns


def _heavy_tailed(seed, m, p, n):
    """A library (m, p) of Gaussian columns and n targets on it with Student-t (2
    degrees of freedom) noise of scale 0.1."""
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=(m, p))
    return theta, theta @ rng.normal(size=(p, n)) + 0.1 * rng.standard_t(2, size=(m, n))


def test_columns_in_groups_reach_the_optimum_of_one_batch(monkeypatch):
    # Many columns of an unpenalised fit on many terms: the batched Newton iteration
    # takes them in groups whose Gram matrices fit in the library's own memory; the
    # columns are independent, so the answer is the one batch's.
    p, n = 40, 12
    theta, y = _heavy_tailed(5, 300, p, n)
    monkeypatch.setattr(driver, "USE_KERNEL", False)
    groups = driver._newton_groups(np.arange(n), np.ones((p, n)), theta.shape)
    assert len(groups) == 2 and np.array_equal(np.concatenate(groups), np.arange(n))
    grouped = rs.fit(theta, y, delta=0.1, lam=0.0)
    monkeypatch.setattr(driver, "_newton_groups", lambda cols, start, shape: [cols])
    single = rs.fit(theta, y, delta=0.1, lam=0.0)
    assert grouped.converged and single.converged
    np.testing.assert_allclose(grouped.coef, single.coef, rtol=0, atol=1e-9)


def test_the_scaled_library_holds_no_reference_cycle():
    # A cycle would keep each fit's copy of the library alive until the cyclic garbage
    # collector ran: at 40 states, gigabytes of copies between collections.
    import gc
    import weakref

    from robust_sindy.solvers.problem import ScaledColumns

    op = ScaledColumns(np.ones((5, 3)), np.ones(3, dtype=bool), np.ones(3))
    np.testing.assert_allclose(op.T @ np.ones(5), 5.0)
    alive = weakref.ref(op)
    gc.disable()
    try:
        del op
        assert alive() is None  # freed by reference counting alone
    finally:
        gc.enable()


@pytest.mark.parametrize("seed", range(3))
def test_cholesky_is_taken_where_the_eigenvalues_show_nothing_would_be_cut(seed):
    # A dense matrix whose smallest eigenvalue is 6 times above the cut, where the
    # 1-norm condition estimate cannot tell (it is below its margin): its Cholesky
    # factor, and the solution of the uncut eigen-decomposition (to the rounding that
    # a condition number of 2e10 leaves).  Ten times below the cut: no factor, and the
    # eigen-solver cuts.
    rng = np.random.default_rng(seed)
    p = 200
    q, _ = np.linalg.qr(rng.normal(size=(p, p)))
    b = rng.normal(size=p)
    for smallest, factored in [(6 * nw.EIG_CUT, True), (nw.EIG_CUT / 10, False)]:
        vals = np.geomspace(1.0, smallest, p)
        m = (q * vals) @ q.T
        m = (m + m.T) / 2
        c, _ = scipy.linalg.lapack.dpotrf(m, lower=True, clean=False)
        rcond, _ = scipy.linalg.lapack.dpocon(c, np.abs(m).sum(axis=0).max(), uplo="L")
        assert rcond < nw.CHOLESKY_MARGIN * nw.EIG_CUT  # the estimate cannot tell
        assert (nw.conditioned_cholesky(m, nw.EIG_CUT) is not None) == factored
        valid = np.ones((1, p), dtype=bool)
        x, deficient = nw._solve_blocks(m[None].copy(), b[None], valid)
        assert bool(deficient[0]) != factored
        if factored:
            w, v = np.linalg.eigh(m)
            exact = v @ ((v.T @ b) / w)
            assert np.linalg.norm(x[0] - exact) <= 1e-5 * np.linalg.norm(exact)


def _line_problem(seed):
    """A line search's data ``(r, q, x, d, lam, delta)`` with ``d`` a descent direction:
    mixed column scales and heavy-tailed residuals; every third draw with ``delta``
    far below the residuals (near least absolute deviations), every third with a large
    penalty on a coefficient the direction drives through zero early (the minimiser
    then sits on that crossing, a jump of the slope)."""
    rng = np.random.default_rng(seed)
    m, p = int(rng.integers(20, 400)), int(rng.integers(2, 12))
    A = rng.normal(size=(m, p)) * 10.0 ** rng.uniform(-2, 2, size=p)
    y = rng.standard_t(2, size=m) * 10.0 ** rng.uniform(-3, 3)
    x = rng.normal(size=p) * (rng.random(p) < 0.7) * np.std(y) / np.linalg.norm(A, axis=0)
    d = rng.normal(size=p) * np.std(y) / np.linalg.norm(A, axis=0)
    r, q = y - A @ x, A @ d
    delta = float(np.median(np.abs(r))) * (1e-3 if seed % 3 == 1 else rng.uniform(0.2, 3))
    scale = float(np.abs(q).sum()) * delta
    lam = rng.uniform(0, 1, size=p) * scale / np.abs(d).max()
    if seed % 3 == 2:
        j = int(rng.integers(p))
        x[j] = -0.1 * d[j]  # crosses zero at t = 0.1
        lam[j] = 100.0 * scale / abs(d[j])
        r = y - A @ x
    if nw.slope(0.0, r, q, x, d, lam, delta) > 0:
        d, q = -d, -q
        if seed % 3 == 2:
            x[j] = -0.1 * d[j]
            r = y - A @ x
    return r, q, x, d, lam, delta


@pytest.mark.skipif(not _kernel.AVAILABLE, reason="numba is not installed")
def test_the_compiled_line_search_finds_the_exact_minimiser_along_the_direction():
    from robust_sindy.core.losses import huber

    kinks = searched = 0
    for seed in range(90):
        r, q, x, d, lam, delta = _line_problem(seed)
        slope0 = nw.slope(0.0, r, q, x, d, lam, delta)
        if not slope0 < 0:
            continue

        def phi(t, r=r, q=q, x=x, d=d, lam=lam, delta=delta):
            return huber(r - t * q, delta).sum() + lam @ np.abs(x + t * d)

        exact = nw.line_search(r, q, x, d, lam, delta)  # breakpoints sorted
        t = _kernel._jit.run("_line_search", r, q, x, d, lam, delta, slope0, np.nan)
        assert t is not None, "the kernels did not compile"
        searched += 1
        assert phi(t) <= phi(exact) + 1e-12 * max(abs(phi(exact)), abs(phi(0.0)))
        kinks += seed % 3 == 2 and bool(np.isclose(exact, 0.1, rtol=1e-9))
    assert searched >= 60  # most draws give a descent direction (69 of 90 here)
    assert kinks >= 20  # the crossing draws did put the minimiser on the crossing (30)


def _count_preparations(monkeypatch) -> list:
    """Every preparation of a library (solvers.problem._prepare) made from now on."""
    from robust_sindy.solvers import problem

    prepared = []
    real = problem._prepare

    def counted(*args):
        prepared.append(real(*args))
        return prepared[-1]

    monkeypatch.setattr(problem, "_prepare", counted)
    return prepared


def test_fits_in_a_shared_preparation_share_the_library_and_its_inlier_grams(monkeypatch):
    # Inside shared_preparation the fits of one library array prepare it once, and the
    # Newton steps of a later fit update the inlier Gram matrices the earlier fit left
    # (its columns named by their targets) instead of forming them afresh; the fits
    # reach the same certified optima as without the block.  Outside it, or for
    # another array with the same values, every fit prepares its own.
    from robust_sindy.solvers import problem

    monkeypatch.setattr(driver, "USE_KERNEL", False)  # the NumPy iteration keeps them
    theta, y = _heavy_tailed(7, 3000, 12, 3)
    prepared = _count_preparations(monkeypatch)
    deltas = [np.full(3, 0.2), np.full(3, 0.195), np.full(3, 0.19)]  # as delta settles
    alone = [rs.fit(theta, y, "admm", d, 0.0) for d in deltas]
    assert len(prepared) == 3 and all(p.carry is None for p in prepared)
    with problem.shared_preparation():
        shared = [rs.fit(theta, y, "admm", deltas[0], 0.0)]
        for d in deltas[1:]:  # each from the last, as delta's iteration runs
            shared.append(rs.fit(theta, y, "admm", d, 0.0, warm_start=shared[-1].coef))
        rs.fit(theta.copy(), y, "admm", deltas[0], 0.0)
    assert len(prepared) == 5  # one for theta, one for its copy
    cache = prepared[3].carry["gram"]
    assert cache.fresh == 3 and cache.updates > 0  # three columns formed once
    for a, b in zip(alone, shared, strict=True):
        assert a.converged and b.converged
        np.testing.assert_allclose(b.coef, a.coef, rtol=1e-6, atol=1e-9)
    assert problem._SHARED.get() is None  # the block left nothing behind


def test_blocks_started_from_one_preparation_share_it_and_keep_their_own_grams(monkeypatch):
    # Blocks of shared_preparation started from preparations(theta) (in the row screen's
    # pilots, one per group of equations, side by side in threads) prepare the library
    # once between them, each carrying its own inlier Gram matrices, and fit as a block
    # of its own would, bit for bit.
    from robust_sindy.core import threads
    from robust_sindy.solvers import problem

    monkeypatch.setattr(driver, "USE_KERNEL", False)  # the NumPy iteration keeps them
    theta, y = _heavy_tailed(3, 2000, 10, 4)
    prepared = _count_preparations(monkeypatch)

    def group(cols, start=None):
        with problem.shared_preparation(start):
            fits = [rs.fit(theta, y[:, cols], "admm", d, 0.0).coef for d in (0.2, 0.19)]
            block = problem._SHARED.get()
            return fits, next(iter(block.values()))[1]

    groups = [[0, 1], [2, 3]]
    own = [group(cols) for cols in groups]
    assert len(prepared) == 2  # a block of its own prepares the library itself
    start = problem.preparations(theta)
    monkeypatch.setattr(threads, "threads", lambda: 2)
    shared = threads.map_threads(lambda cols: group(cols, start), groups)
    assert len(prepared) == 3  # once for both blocks
    (_, pa), (_, pb) = shared
    assert pa.G is pb.G and pa.carry is not pb.carry and pa.carry and pb.carry
    assert not next(iter(start.values()))[1].carry  # the start itself carries nothing
    for (f_own, _), (f_shared, _) in zip(own, shared, strict=True):
        for a, b in zip(f_own, f_shared, strict=True):
            assert np.array_equal(a, b)


def test_a_gram_cache_with_a_budget_lets_go_of_the_matrices_used_longest_ago():
    # Named columns two at a time, 20 x 20 matrices (400 entries each) and a budget of
    # 1000 entries: after each call at most the two matrices of that call and none
    # older beyond the budget stay, and every matrix returned is the inlier Gram
    # matrix, whether it was updated from a stored one or formed afresh.
    rng = np.random.default_rng(2)
    A = rng.normal(size=(400, 20))
    G = A.T @ A
    cache = nw.GramCache(budget=1000)
    inl = rng.random((400, 6)) > 0.2
    for _ in range(3):
        for pair in ([0, 1], [2, 3], [4, 5], [0, 1]):
            inl[rng.integers(400, size=3), pair[0]] ^= True  # a few samples change sides
            M = cache.gram(A, G, inl[:, pair], [f"c{k}" for k in pair])
            for i, k in enumerate(pair):
                w = inl[:, k].astype(float)
                np.testing.assert_allclose(M[i], (A * w[:, None]).T @ A, atol=1e-9)
            stored = sum(entry[2].size for entry in cache.entries.values())
            assert {f"c{k}" for k in pair} <= set(cache.entries)
            assert stored <= 1000
            assert list(cache.entries)[-2:] == [f"c{k}" for k in pair]  # the newest
    assert cache.updates > 0  # the pair [0, 1] came back while still stored
