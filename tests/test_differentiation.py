"""The automatic window of the robust derivatives (choose_half_window)."""

import warnings

import numpy as np
import pytest

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.systems import Lorenz
from robust_sindy.timeseries.differentiation import choose_half_window, local_polynomial_derivative
from robust_sindy.timeseries.temporal import temporal_screen


def _sine(per_period, noise, seed=0, m=2000):
    rng = np.random.default_rng(seed)
    t = np.arange(m) * 2 * np.pi / per_period
    x = np.column_stack([np.sin(t), np.cos(0.5 * t)])
    return t, x, x + noise * rng.normal(size=x.shape)


def test_window_widens_with_noise_and_sampling_density_only():
    # Coarsely sampled: the fourth-order difference (h = 2), noisy or not.
    for noise in (1e-2, 0.0):
        t, _, x = _sine(5, noise)
        assert choose_half_window(x, t).tolist() == [2, 2], noise
    # Noise-free and dense: whatever window is chosen keeps the derivative exact.
    t, _, x = _sine(300, 0.0)
    true = np.column_stack([np.cos(t), -0.5 * np.sin(0.5 * t)])
    assert np.abs(local_polynomial_derivative(x, t, "auto") - true).max() < 1e-6
    # Densely sampled noisy states: a wider window, growing with the density.
    widths = []
    for per_period in (20, 50, 300):
        t, _, x = _sine(per_period, 1e-2)
        widths.append(int(choose_half_window(x[:, :1], t)[0]))
    assert widths[0] > 2
    assert widths == sorted(widths) and widths[-1] >= 12


def test_window_is_unit_free():
    t, _, x = _sine(100, 1e-3, seed=3)
    h = choose_half_window(x, t)
    assert np.array_equal(choose_half_window(x * [1e3, 1e-3], t * 1e-2 + 5.0), h)


def test_chosen_window_reduces_the_derivative_error():
    t, _, x = _sine(200, 1e-2, seed=1)
    true = np.column_stack([np.cos(t), -0.5 * np.sin(0.5 * t)])
    narrow = np.abs(local_polynomial_derivative(x, t) - true).std(axis=0)
    auto = np.abs(local_polynomial_derivative(x, t, "auto") - true).std(axis=0)
    assert np.all(auto < narrow / 10)


def test_masked_outliers_do_not_change_the_window():
    t, _, x = _sine(100, 1e-2, seed=2)
    bad = x.copy()
    rng = np.random.default_rng(5)
    idx = rng.choice(x.shape[0], 40, replace=False)
    bad[idx, 0] += rng.choice([-1, 1], 40) * 2.0
    mask = np.ones(x.shape, dtype=bool)
    mask[idx, 0] = False
    assert np.array_equal(choose_half_window(bad, t, mask), choose_half_window(x, t, mask))


def test_half_window_arguments():
    t, _, x = _sine(50, 1e-3)
    per_state = local_polynomial_derivative(x, t, [2, 6])
    assert np.array_equal(per_state[:, 0], local_polynomial_derivative(x[:, 0], t, 2))
    assert np.array_equal(per_state[:, 1], local_polynomial_derivative(x[:, 1], t, 6))
    with pytest.raises(ValueError, match="half_window"):
        local_polynomial_derivative(x, t, "wide")
    with pytest.raises(ValueError, match="half_window"):
        local_polynomial_derivative(x, t, 0)
    # A short trajectory keeps the narrowest window (too few samples to score wider ones).
    assert choose_half_window(x[:20], t[:20]).tolist() == [2, 2]


@pytest.mark.parametrize("seed", [0, 1])
def test_damped_oscillator_states_only_with_heavy_tails(seed):
    """A weakly damped linear oscillator sampled densely, Student-t noise on every
    entry, no derivatives: the fourth-order difference multiplies the noise by 1 / dt
    and the damping (5 % of the rotation) was pruned as not significant."""
    rng = np.random.default_rng(seed)
    a = np.array([[-0.1, 2.0], [-2.0, -0.1]])
    t = np.linspace(0.0, 25.0, 2500)
    w, v = np.linalg.eig(a)
    x0 = np.array([2.0 + rng.normal(), 0.0])
    x = np.real((v * np.exp(np.outer(t, w))[:, None, :]) @ np.linalg.solve(v, x0))
    noisy = x + 0.01 * x.std(axis=0) * rng.standard_t(2, size=x.shape)
    fits = {}
    for window in ("fixed", "auto"):
        model = HuberSINDy(
            library=PolynomialLibrary(degree=2), derivative_window=window, formulation="strong"
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fits[window] = model.fit(noisy, t)
    names = model.get_feature_names()
    truth = np.zeros_like(model.support_)
    truth[:, [names.index("x0"), names.index("x1")]] = True
    # The fourth-order difference multiplies the noise by 1 / dt: the damping is lost
    # (and a warning says it may be real).
    assert not np.array_equal(fits["fixed"].support_, truth)
    assert np.nanmax(fits["fixed"].diagnostics_.pruned) >= 2
    assert fits["fixed"].derivative_windows_.tolist() == [2, 2]
    model = fits["auto"]
    assert np.array_equal(model.support_, truth)
    assert np.abs(model.coef_[:, [1, 2]] - a).max() < 0.02
    assert np.all(model.derivative_windows_ > 2)
    assert np.array_equal(model.diagnostics_.derivative_half_window, model.derivative_windows_)
    # Measured derivatives: no window.
    measured = HuberSINDy(library=PolynomialLibrary(degree=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        measured.fit(noisy, t, x_dot=x @ a.T)
    assert measured.derivative_windows_.tolist() == [0, 0]
    assert "measured" in repr(measured.diagnostics_)


def test_library_guard_keeps_a_window_bias_out_of_the_regression():
    """Nearly noise-free Lorenz: the states' prediction alone widens the windows, and the
    derivative's smoothing bias then buys spurious terms; the library guard narrows the
    windows back to where a widening changes nothing the library can explain."""
    system = Lorenz()
    data = system.generate(t_end=30.0)
    rng = np.random.default_rng(1)
    x = data.x + 1e-3 * rng.normal(size=data.x.shape)
    library = PolynomialLibrary(degree=2)
    theta = library.fit_transform(x)
    by_states = choose_half_window(x, data.t)
    guarded = choose_half_window(x, data.t, library=theta)
    assert np.all(guarded <= by_states) and np.any(guarded < by_states)
    truth = system.true_coef().T != 0
    supports = []
    for half in (by_states, guarded):
        model = HuberSINDy(library=PolynomialLibrary(degree=2))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(x, data.t, x_dot=local_polynomial_derivative(x, data.t, half))
        supports.append(np.array_equal(model.support_, truth))
    assert supports == [False, True]
    # The guard is what HuberSINDy uses when it chooses the window (the strong form:
    # these states have no outliers, and formulation="auto" would integrate them).
    model = HuberSINDy(derivative_window="auto", formulation="strong")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(x, data.t)
    assert np.array_equal(model.derivative_windows_, guarded)
    assert np.array_equal(model.support_, truth)
    # score() differentiates the states it is given as fit does: guarded windows.
    screen = temporal_screen(x, data.t)
    fitted = local_polynomial_derivative(
        screen.repaired, data.t, guarded, mask=~screen.flags, scale=screen.scale
    )
    wide = local_polynomial_derivative(
        screen.repaired, data.t, by_states, mask=~screen.flags, scale=screen.scale
    )
    assert model.score(x, data.t) == model.score(x, data.t, x_dot=fitted)
    assert model.score(x, data.t) != model.score(x, data.t, x_dot=wide)
    with pytest.raises(ValueError, match="library"):
        choose_half_window(x, data.t, library=theta[:-1])
    with pytest.raises(ValueError, match="rows"):
        choose_half_window(x, data.t, library=theta, rows=np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match="derivative_window"):
        HuberSINDy(derivative_window=7).fit(x, data.t)


def test_library_guard_measures_a_window_change_against_its_own_noise():
    """Without a bias, the guard's statistic is a quadratic form in the change's noise
    whose mean, the trace of ``cov^-1 noise``, lies well below the number of columns
    when the regression's errors exceed that noise: against the chi-square of the
    number of columns, a bias as large as the gap went through.  Measured against the
    statistic's own distribution, noise alone passes at about the test's level, and a
    bias in a single direction that the chi-square of the columns let through is
    caught."""
    import scipy.stats

    from robust_sindy.timeseries.differentiation import BIAS_LEVEL, _wald_against_noise

    rng = np.random.default_rng(3)
    p = 60
    spread = rng.normal(size=(4 * p, p)) / np.sqrt(4 * p)
    noise = spread.T @ spread
    errors = rng.normal(size=(4 * p, p)) / np.sqrt(4 * p)
    cov = noise + 2.0 * errors.T @ errors  # the regression's errors twice the noise
    root = np.linalg.cholesky(noise)
    draws = 3000
    walds, bars = np.empty(draws), np.empty(draws)
    for i in range(draws):
        walds[i], bars[i] = _wald_against_noise(root @ rng.normal(size=p), cov, noise)
    mean = np.trace(np.linalg.solve(cov, noise))
    assert np.ptp(bars) == 0.0  # the bar depends on the covariances only
    assert abs(walds.mean() / mean - 1.0) < 0.05
    assert mean < 0.6 * p  # the case the chi-square of the columns misjudged
    assert np.mean(walds > bars) < 5 * BIAS_LEVEL
    # A bias along one direction worth 6 times the spread of the statistic's noise.
    direction = rng.normal(size=p)
    direction /= np.sqrt(direction @ np.linalg.solve(cov, direction))
    size = np.sqrt(6.0 * walds.std())
    caught = old = 0
    for _ in range(200):
        c = root @ rng.normal(size=p) + size * direction
        wald, bar = _wald_against_noise(c, cov, noise)
        caught += wald > bar
        old += wald > scipy.stats.chi2.ppf(1.0 - BIAS_LEVEL, p)
    assert caught >= 150 and old <= 20, (caught, old)
    # Unit-free: covariances in other units, the same decisions.
    wald, bar = _wald_against_noise(1e3 * c, 1e6 * cov, 1e6 * noise)
    assert np.isclose(wald, _wald_against_noise(c, cov, noise)[0], rtol=1e-8)
    assert np.isclose(bar, bars[0], rtol=1e-8)


def test_library_guard_tests_the_bulk_of_the_rows():
    """The rows the guard tests are those the library fits within 3.5 robust scales of
    the signed deleted residuals: a gross error leaves, also where its row of the
    library is far out too (a reading the temporal screen missed, which its own
    columns fit: its plain residual is small), and the Gaussian bulk stays (scaled by
    the absolute residuals, a fifth of the bulk used to leave over the rounds)."""
    from robust_sindy.selection import robust_scale
    from robust_sindy.timeseries.differentiation import _fitted_rows

    kept = []
    for seed in range(5):
        rng = np.random.default_rng([seed, 11])
        a = rng.normal(size=(2000, 20))
        y = a @ rng.normal(size=20) + rng.normal(size=2000)
        gross = rng.choice(2000, 40, replace=False)
        y[gross] += 30.0 * rng.choice([-1.0, 1.0], 40)
        # Ten of them far out in the library as well: leverage near 1.
        far = gross[:10]
        a[far] *= 200.0
        plain = y - a @ np.linalg.lstsq(a, y, rcond=None)[0]
        # By their plain residuals the far rows would stay.
        assert np.all(np.abs(plain[far]) < 3.5 * robust_scale(plain))
        keep, basis = _fitted_rows(a, y, np.ones(2000, dtype=bool))
        assert not keep[gross].any()
        kept.append(np.delete(keep, gross).mean())
        # The basis returned spans the library on the rows kept.
        assert basis.shape == (keep.sum(), 20)
        assert np.allclose(basis @ (basis.T @ a[keep]), a[keep])
    assert min(kept) > 0.99, kept


def test_subset_basis_is_that_of_the_rows_kept():
    """One basis of the library on all rows serves every subset: on random subsets it
    spans what an SVD of the rows kept spans, is orthonormal, and gives the same
    least-squares fit (on every row of the base where the rank is full); a column that
    lives only on rows left out drops from the rank."""
    from robust_sindy.timeseries.differentiation import (
        _fitted_rows,
        _orthonormal_basis,
        _subset_basis,
    )

    rng = np.random.default_rng(3)
    a = rng.normal(size=(600, 25)) * np.logspace(-3, 3, 25)
    a[:, 5] = 0.0
    a[:40, 5] = rng.normal(size=40)  # lives on the first 40 rows only
    y = rng.normal(size=600)
    base = np.ones(600, dtype=bool)
    base[590:] = False
    u = _orthonormal_basis(a[base])
    for draw in range(5):
        keep = base & (rng.random(600) > 0.3)
        if draw == 0:
            keep[:40] = False  # column 5 has nothing left
        q, w = _subset_basis(u, base, keep)
        assert q.shape[1] == np.linalg.matrix_rank(a[keep]) == (24 if draw == 0 else 25)
        np.testing.assert_allclose(q.T @ q, np.eye(q.shape[1]), atol=1e-10)
        np.testing.assert_allclose(q @ (q.T @ a[keep]), a[keep], atol=1e-9 * np.abs(a).max())
        coef = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
        fitted = u @ (w @ (q.T @ y[keep]))
        # On the rows kept the fit is unique; on the others only where the rank is full.
        np.testing.assert_allclose(fitted[keep[base]], a[keep] @ coef, atol=1e-9)
        if draw > 0:
            np.testing.assert_allclose(fitted, a[base] @ coef, atol=1e-9)
    # Rows outside the base have no row in its basis: refused, not fitted silently.
    with pytest.raises(ValueError, match="among the rows"):
        _fitted_rows(a, y, np.ones(600, dtype=bool), base=(u, base))


def test_library_guard_costs_a_flagged_entry_not_its_sample():
    """Glitches in one channel at a time, 15 % of the entries of ten channels: fewer
    complete samples (64 to 72) than the library has terms (66).  Testing each state
    on its own readings, with the library of the repaired ones, the fit's windows are
    those the same record without glitches gets (within one candidate step for at
    least 80 % of the states over three draws); tested on the complete samples only,
    the guard had nothing to test with, or too little, and kept the narrowest
    windows."""
    from robust_sindy.flows import lorenz96_records
    from robust_sindy.timeseries.differentiation import HALF_WINDOWS

    step = {h: i for i, h in enumerate(HALF_WINDOWS)}
    near = []
    for seed in range(3):
        t, x, _, _ = lorenz96_records(10, 300, seed)
        rng = np.random.default_rng([seed, 5])
        noisy = x + 0.01 * x.std(axis=0) * rng.normal(size=x.shape)
        hit = rng.random(x.shape) < 0.15
        glitched = noisy + hit * 10.0 * x.std(axis=0) * rng.choice([-1.0, 1.0], size=x.shape)
        assert hit.any(axis=1).mean() > 0.75  # most samples hold a glitched entry
        screen = temporal_screen(noisy, t)
        theta = PolynomialLibrary(degree=2).fit_transform(screen.repaired)
        clean = choose_half_window(
            screen.repaired, t, ~screen.flags, library=theta, scale=screen.scale
        )
        model = HuberSINDy(formulation="strong")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(glitched, t)
        got = model.derivative_windows_
        near += [abs(step[g] - step[c]) <= 1 for g, c in zip(got, clean, strict=True)]
    assert np.mean(near) >= 0.8, near


def _hopf(t, z):
    x, y = z
    r2 = x * x + y * y
    return [0.2 * x - y - x * r2, x + 0.2 * y - y * r2]


@pytest.mark.parametrize("noise", [1e-3, 1e-2])
def test_library_guard_counts_the_change_s_own_noise_at_random_times(noise):
    """At uniformly random times the narrowest window's polynomial interpolates samples
    that crowd together, and its derivative's noise is heavy-tailed.  The change to the
    next window is then mostly that noise; counted as a bias, it held the guard at the
    narrowest window, with derivative errors as large as the derivatives themselves.
    Over several draws, the guarded windows' errors stay near those of the windows the
    states' prediction chose (at most twice theirs, with 100 samples per period)."""
    from scipy.integrate import solve_ivp

    m, dt = 2000, 2 * np.pi / 100
    ratios = []
    for seed in range(4):
        rng = np.random.default_rng([seed, 17])
        t = np.sort(rng.uniform(0.0, dt * (m - 1), m))
        sol = solve_ivp(_hopf, (0.0, t[-1]), [0.1, 0.3], t_eval=t, method="DOP853",
                        rtol=1e-10, atol=1e-12)  # fmt: skip
        exact = np.array([_hopf(0.0, z) for z in sol.y.T])
        x = sol.y.T + noise * sol.y.T.std(axis=0) * rng.normal(size=(m, 2))
        screen = temporal_screen(x, t)
        theta = PolynomialLibrary(degree=3).fit_transform(screen.repaired)
        errors = []
        for library in (None, theta):
            half = choose_half_window(screen.repaired, t, ~screen.flags, library=library,
                                      scale=screen.scale)  # fmt: skip
            d = local_polynomial_derivative(
                screen.repaired, t, half, mask=~screen.flags, scale=screen.scale
            )
            errors.append(np.std(d - exact, axis=0).max())
        ratios.append(errors[1] / errors[0])
        # The same windows in other units of the states and of time, with an offset.
        xs, ts = (x + 5.0) * 1e3, t * 1e-2 + 7.0
        other = temporal_screen(xs, ts)
        theta_s = PolynomialLibrary(degree=3).fit_transform(other.repaired)
        again = choose_half_window(
            other.repaired, ts, ~other.flags, library=theta_s, scale=other.scale
        )
        assert np.array_equal(again, half)
    assert max(ratios) < 2.0, ratios


def test_wide_windows_are_fitted_robustly_given_the_noise_scale():
    t, _, x = _sine(200, 1e-3, seed=6)
    true = np.column_stack([np.cos(t), -0.5 * np.sin(0.5 * t)])
    x[1000, 0] += 0.05  # an error of 50 noise scales that no mask removes
    scale = [1e-3, 1e-3]
    plain = local_polynomial_derivative(x, t, 12)
    robust = local_polynomial_derivative(x, t, 12, scale=scale)
    near = slice(985, 1016)
    # Huber's loss bounds the error's influence (it does not remove it).
    assert (
        np.abs(plain[near, 0] - true[near, 0]).max()
        > 2 * np.abs(robust[near, 0] - true[near, 0]).max()
    )
    # The five-sample stencil interpolates: nothing to down-weight, the same numbers.
    assert np.array_equal(
        local_polynomial_derivative(x, t, 2, scale=scale), local_polynomial_derivative(x, t, 2)
    )
    with pytest.raises(ValueError, match="scale"):
        local_polynomial_derivative(x, t, 12, scale=[-1.0, 1.0])


def test_higher_order_derivative_has_the_smaller_truncation_error():
    from robust_sindy.timeseries.differentiation import (
        higher_order_derivative,
        unresolved_derivatives,
    )

    t = 0.3 * np.arange(400)  # about 21 samples per period
    x = np.column_stack([np.sin(t), 1e3 * np.cos(0.5 * t)])
    exact = np.column_stack([np.cos(t), -500 * np.sin(0.5 * t)])
    low = local_polynomial_derivative(x, t, 2)
    high = higher_order_derivative(x, t, 2)
    inner = slice(5, -5)
    for k in range(2):
        err_low = np.abs(low[inner, k] - exact[inner, k]).max()
        err_high = np.abs(high[inner, k] - exact[inner, k]).max()
        assert err_high < 0.2 * err_low
    # Time in other units: the same derivatives, rescaled.
    fast = higher_order_derivative(x, 1e-3 * t, 2)
    assert np.all(np.abs(fast - 1e3 * high) <= 1e-8 * np.abs(1e3 * high).max(axis=0))
    # The reference passed in or computed: the same unresolved samples.
    u = unresolved_derivatives(x, t, low, 2, scale=[1e-3, 1.0])
    assert np.array_equal(u, unresolved_derivatives(x, t, low, 2, scale=[1e-3, 1.0], high=high))
    # Too short for the wider window: NaN.
    assert np.isnan(higher_order_derivative(x[:6], t[:6], 2)).all()
