"""Best-subset candidates: exhaustive weighted least squares, and the supports a lasso
path cannot reach."""

import itertools
import math
import warnings

import numpy as np
import pytest

from robust_sindy.library import PolynomialLibrary
from robust_sindy.selection import select
from robust_sindy.selection.subsets import best_subsets, subset_sizes


def _brute_force(theta, y, w, size):
    """Every support of ``size`` columns, by weighted residual sum of squares."""
    sw = np.sqrt(w)
    out = []
    for cols in itertools.combinations(range(theta.shape[1]), size):
        a = theta[:, cols] * sw[:, None]
        b, *_ = np.linalg.lstsq(a, y * sw, rcond=None)
        out.append((float(np.sum((y * sw - a @ b) ** 2)), set(cols)))
    return sorted(out, key=lambda v: v[0])


@pytest.mark.parametrize("seed", range(4))
def test_best_subsets_are_the_brute_force_best_of_each_size(seed):
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=(60, 7)) @ (np.eye(7) + 0.6 * rng.normal(size=(7, 7)))
    y = theta @ (rng.normal(size=7) * (rng.random(7) < 0.5)) + rng.normal(size=60)
    w = rng.uniform(0.05, 1.0, 60)
    masks, largest = best_subsets(theta, y, w, per_size=2)
    assert largest == 7 and len(masks) == 2 * 6 + 1  # one support of all seven
    for size in range(1, 8):
        found = [set(np.flatnonzero(mk).tolist()) for mk in masks if mk.sum() == size]
        truth = _brute_force(theta, y, w, size)
        assert found == [s for _, s in truth[: len(found)]]


@pytest.mark.parametrize("seed", range(4))
def test_a_shared_gram_matrix_and_the_single_terms_give_the_brute_force_best(seed):
    # Huber weights (most rows at 1): the weighted Gram matrix formed from the shared
    # unweighted one by the down-weighted rows, and single terms from its diagonal only.
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=(80, 6)) @ (np.eye(6) + 0.6 * rng.normal(size=(6, 6)))
    theta[:, 4] = 0.0  # an aliased term: in no support, not in the shared matrix
    y = theta @ (rng.normal(size=6) * (rng.random(6) < 0.5)) + rng.normal(size=80)
    w = np.minimum(1.0, 0.8 / np.abs(rng.standard_t(3, size=80)))
    pool = np.flatnonzero(np.any(theta != 0, axis=0))
    gram = theta[:, pool].T @ theta[:, pool]
    masks, largest = best_subsets(theta, y, w, per_size=2, gram=gram)
    single, one = best_subsets(theta, y, w, per_size=2, max_size=1)
    assert largest == 5 and one == 1
    assert [set(np.flatnonzero(mk)) for mk in single] == [
        set(np.flatnonzero(mk)) for mk in masks if mk.sum() == 1
    ]
    for size in range(1, 6):
        found = [set(np.flatnonzero(mk).tolist()) for mk in masks if mk.sum() == size]
        truth = _brute_force(theta[:, pool], y, w, size)
        assert found == [{int(pool[j]) for j in s} for _, s in truth[: len(found)]]


def test_the_budget_bounds_the_sizes_and_zero_columns_are_left_out():
    assert subset_sizes(20, 200_000) == 7  # 137,979 supports of 1 to 7 terms
    assert sum(math.comb(20, s) for s in range(1, 9)) > 200_000
    assert subset_sizes(56, 200_000) == 3
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(50, 5))
    theta[:, 2] = 0.0  # an aliased term, zeroed by the selection
    masks, largest = best_subsets(theta, rng.normal(size=50), np.ones(50), budget=9)
    assert largest == 1 and len(masks) == 3  # 4 single terms and 6 pairs exceed 9
    assert not any(mk[2] for mk in masks)


def _narrow_range_problem(seed):
    """Cubic monomials of three states that each vary by about 10 % around their mean
    (the collinearity of a chemical system near its steady state), four true terms."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 20.0, 1000)
    z = np.column_stack(
        [
            c + a * np.sin(f * t + ph)
            for c, a, f, ph in zip(
                rng.uniform(0.3, 1.2, 3),
                rng.uniform(0.05, 0.12, 3),
                rng.uniform(0.5, 2.0, 3),
                rng.uniform(0.0, 6.0, 3),
                strict=True,
            )
        ]
    )
    theta = PolynomialLibrary(degree=3).fit_transform(z)
    xi = np.zeros(theta.shape[1])
    true = rng.choice(theta.shape[1], 4, replace=False)
    xi[true] = rng.choice([-1.0, 1.0], 4) * rng.uniform(0.3, 1.5, 4)
    return theta, theta @ xi + 1e-3 * rng.normal(size=t.size), xi != 0


@pytest.mark.parametrize("seed", [0, 5, 9])
def test_collinear_supports_the_path_never_proposes_are_found(seed):
    theta, y, true = _narrow_range_problem(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path_only = select(theta, y, subsets=False)
        sel = select(theta, y)
    # The lasso path's candidates miss the true support: it trades correlated terms.
    assert not any(np.array_equal(c[:, 0] != 0, true) for c in path_only.candidates)
    assert np.array_equal(sel.support[:, 0], true)
    # Searched up to the budget (7 of 20 terms) or to the size whose BIC penalty alone
    # exceeds the best score.
    assert sel.from_subsets[0] and 4 <= sel.subset_size[0] <= 7
    # The margin counts the subsets too: the runner-up support scores worse.
    assert sel.margin[0] > 0


@pytest.mark.parametrize("seed", range(4))
def test_the_loss_floor_never_exceeds_the_optimal_huber_loss(seed):
    import robust_sindy as rs
    from robust_sindy.selection.criteria import _loss_floor

    rng = np.random.default_rng(seed)
    a = rng.normal(size=(300, 5))
    y = a @ rng.normal(size=5) + 0.1 * rng.standard_t(2, size=300)
    y[::9] += 20.0 * rng.normal(size=y[::9].size)
    delta = 0.2
    res = rs.fit(a, y, delta=delta, lam=0.0)
    assert res.converged
    optimum = rs.objective(a, y, res.coef, delta, 0.0)[0]
    weights = rng.uniform(0.1, 1.0, 300)
    # from a weighted least-squares fit, from the optimum's residuals (tight), and from
    # a fit stopped far from the optimum: always a lower bound
    for floor in (
        _loss_floor(a, y, weights, delta),
        _loss_floor(a, y, None, delta, y - a @ res.coef),
        _loss_floor(a, y, None, delta, y - a @ (res.coef + 0.3)),
    ):
        assert floor <= optimum * (1 + 1e-12)
    assert _loss_floor(a, y, None, delta, y - a @ res.coef) >= optimum * (1 - 1e-6)
    basis = np.linalg.qr(a)[0]
    assert np.isclose(
        _loss_floor(a, y, None, delta, y - a @ res.coef, basis),
        _loss_floor(a, y, None, delta, y - a @ res.coef),
        rtol=1e-12,
    )
