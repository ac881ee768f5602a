"""Temporal screen, robust derivatives, diagnostics and data-size checks."""

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.signal

from robust_sindy import HuberSINDy, IdentificationWarning, PolynomialLibrary
from robust_sindy.core import compiled as _compiled
from robust_sindy.diagnostics import kind_of, samples_needed
from robust_sindy.selection import correlation_time
from robust_sindy.systems import Lorenz
from robust_sindy.timeseries.differentiation import local_polynomial_derivative
from robust_sindy.timeseries.temporal import temporal_screen

from .conftest import van_der_pol


def _smooth(m=1500, seed=0, noise=1e-3, t=None):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 15.0, m) if t is None else t
    x = np.column_stack([np.sin(t), np.cos(2.3 * t) + 0.3 * t, np.exp(np.sin(0.7 * t))])
    return t, x, x + noise * rng.normal(size=x.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_temporal_screen_finds_single_entry_spikes_and_nothing_else(seed):
    t, _, x = _smooth(seed=seed)
    rng = np.random.default_rng(seed + 10)
    bad = np.zeros(x.shape, dtype=bool)
    idx = rng.choice(x.size, 60, replace=False)
    bad.flat[idx] = True
    x[bad] += rng.choice([-1, 1], 60) * rng.uniform(0.2, 1.0, 60)
    s = temporal_screen(x, t)
    assert s.flags[bad].mean() >= 0.95
    assert s.flags[~bad].mean() <= 0.005
    # flagged entries are repaired to their local prediction
    assert np.abs(s.repaired[bad & s.flags] - _smooth(seed=seed)[1][bad & s.flags]).max() < 0.02


@pytest.mark.parametrize("irregular", [False, True])
def test_temporal_screen_flags_spikes_in_the_first_and_last_samples(irregular):
    """The screen takes the running median of the errors out of them (the fit's smooth
    bias); at the ends of a record that median must come from a window inside it, or
    the end's own error is its median and a spike there, however large, is never
    flagged.  Over several draws, every glitch at either end is flagged."""
    missed = []
    for seed in range(4):
        times = None
        if irregular:
            times = np.sort(np.random.default_rng(seed + 20).uniform(0.0, 15.0, 1500))
        t, _, x = _smooth(seed=seed, t=times)
        rng = np.random.default_rng(seed + 30)
        # The glitches of the zoo: 3 to 20 standard deviations of the state.
        sizes = np.exp(rng.uniform(np.log(3.0), np.log(20.0), (2, 3))) * x.std(axis=0)
        x[[0, -1]] += sizes * rng.choice([-1, 1], (2, 3))
        flags = temporal_screen(x, t).flags
        missed.append(int((~flags[[0, -1]]).sum()))
    assert missed == [0, 0, 0, 0]


def test_temporal_screen_is_quiet_on_clean_data_and_unit_free():
    t, _, x = _smooth()
    s = temporal_screen(x, t)
    assert s.flags.mean() <= 0.002
    scaled = temporal_screen(x * [1e3, 1e-3, 7.0], t * 1e-2)
    assert np.array_equal(scaled.flags, s.flags)


def _glitched_records():
    """Contaminated Lorenz states (the paper's noise model, three draws) cut into blocks
    of 100 samples, and records of three channels with glitches of 3 to 20 standard
    deviations in 5 % of the entries of each, at uniform and at random times."""
    from robust_sindy.noise import contaminate

    data = Lorenz().generate(t_end=6.0)
    for seed in range(3):
        x = contaminate(data.x, data.x_dot, rng=np.random.default_rng(seed)).x
        for lo in range(0, x.shape[0] - 99, 100):
            yield data.t[lo : lo + 100], x[lo : lo + 100]
    for seed in range(4):
        rng = np.random.default_rng([seed, 41])
        times = np.sort(rng.uniform(0.0, 15.0, 1200)) if seed % 2 else None
        t, _, x = _smooth(1200, seed, noise=0.0, t=times)
        x = x + 0.01 * x.std(axis=0) * rng.normal(size=x.shape)
        size = rng.uniform(3.0, 20.0, x.shape) * x.std(axis=0) * rng.choice([-1, 1], x.shape)
        yield t, x + (rng.random(x.shape) < 0.05) * size


def test_a_channels_screen_does_not_depend_on_the_other_channels():
    """Every step of the temporal screen, its rounds of withdrawal included, is the
    channel's own: screened with the others or alone, a channel gets the same flags,
    repaired values and noise level (66 channels of 22 records; before each channel
    had its own rounds, 6 of them differed, repaired values by up to 0.23)."""
    differ, count = [], 0
    for t, x in _glitched_records():
        differ += [(count + k + 1, k) for k in _differ_alone(x, t, temporal_screen(x, t))]
        count += x.shape[1]
    assert count == 66 and not differ, differ


def _differ_alone(x, t, together) -> list[int]:
    """The channels of ``x`` whose flags, repaired values or noise level screened alone
    differ from ``together``, the screen of all of them."""
    differ = []
    for k in range(x.shape[1]):
        alone = temporal_screen(x[:, [k]], t)
        if not (
            np.array_equal(alone.flags[:, 0], together.flags[:, k])
            and np.allclose(alone.repaired[:, 0], together.repaired[:, k], rtol=1e-12, atol=0)
            and np.isclose(alone.scale[0], together.scale[k], rtol=1e-12, atol=0)
        ):
            differ.append(k)
    return differ


def test_the_rounds_of_withdrawal_measure_only_the_channels_still_withdrawing(monkeypatch):
    """Step 4's rounds re-measure the local errors of the channels that withdrew a flag
    in the round before, not of every channel; each channel's result is still what it
    gets screened alone.  Records of 6 to 12 channels, a third of them with fast
    excursions sampled by a few samples (bumps of 1 to 2.5 samples' width), which the
    local fits do not resolve."""
    from robust_sindy.timeseries import temporal

    measured: list[int] = []
    errors = temporal._errors

    def counted(x, *args):
        measured.append(x.shape[1])
        return errors(x, *args)

    monkeypatch.setattr(temporal, "_errors", counted)
    partial = 0
    for seed in range(3):
        rng = np.random.default_rng([seed, 43])
        m, n = 1500, 6 + 3 * seed
        t = np.linspace(0.0, 30.0, m)
        x = np.sin(np.outer(t, rng.uniform(0.2, 3.0, n)) + rng.uniform(0.0, 6.0, n))
        x += 0.01 * rng.normal(size=x.shape)
        for k in rng.choice(n, n // 3, replace=False):
            for i in rng.integers(50, m - 50, 5):
                width = rng.uniform(1.0, 2.5)
                x[:, k] += 3.0 * np.exp(-0.5 * ((np.arange(m) - i) / width) ** 2)
        measured.clear()
        together = temporal_screen(x, t)
        rounds = measured[2:]  # after the candidates' and the final confirmation
        assert rounds and all(0 < c < n for c in rounds), (n, measured)
        partial += len(rounds)
        assert not _differ_alone(x, t, together)
    assert partial >= 3


def test_local_polynomial_derivative_ignores_masked_outliers():
    t, clean, x = _smooth(noise=0.0)
    true = np.column_stack(
        [np.cos(t), -2.3 * np.sin(2.3 * t) + 0.3, 0.7 * np.cos(0.7 * t) * clean[:, 2]]
    )
    d = local_polynomial_derivative(x, t)
    assert np.abs(d - true).max() < 1e-4
    x[700, 1] += 5.0
    mask = np.ones(x.shape, dtype=bool)
    mask[700, 1] = False
    assert np.abs(local_polynomial_derivative(x, t, mask=mask) - true).max() < 1e-3
    assert np.abs(local_polynomial_derivative(x, t) - true).max() > 1.0  # without the mask


def test_correlation_time_of_white_and_smooth_residuals():
    rng = np.random.default_rng(0)
    white = rng.normal(size=(5000, 1))
    assert correlation_time(white)[0] < 1.2
    smooth = np.convolve(rng.normal(size=5020), np.ones(21) / 21, mode="valid")[:, None]
    assert correlation_time(smooth)[0] > 10


def test_too_few_samples_for_the_library_is_an_error():
    x = np.random.default_rng(0).normal(size=(8, 3))
    with pytest.raises(ValueError, match="x has 8 samples but the library has 10 terms"):
        HuberSINDy().fit(x, 0.1, x_dot=x)


def _correlated(rng, shape, phi):
    """Unit-variance AR(1) noise along the first axis (correlation time (1+phi)/(1-phi))."""
    e = rng.normal(size=shape)
    return scipy.signal.lfilter([1.0], [1.0, -phi], e, axis=0) * np.sqrt(1 - phi**2)


def test_the_independent_samples_are_the_kept_ones_over_the_errors_correlation_time():
    data = Lorenz().generate(t_end=20.0)
    for seed in range(3):
        for phi in (0.0, 0.8):
            rng = np.random.default_rng(seed)
            noise = 0.02 * data.x_dot.std(axis=0) * _correlated(rng, data.x.shape, phi)
            d = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot + noise).diagnostics_
            kept = d.n_samples * (1 - d.flagged_fraction)
            ratio = d.independent_samples / (kept * (1 - phi) / (1 + phi))
            low, high = (0.9, 1.0) if phi == 0 else (0.5, 2.0)
            assert np.all((ratio > low) & (ratio <= high)), (seed, phi, ratio)


@pytest.mark.filterwarnings("ignore::robust_sindy.ConvergenceWarning")
def test_a_record_too_short_for_the_search_warns_and_says_so_in_the_diagnostics():
    # 151 samples for 35 quartic terms, derivatives whose errors are correlated over
    # about 39 samples: a handful of independent samples per equation.
    data = Lorenz().generate(t_end=1.5)
    fired = 0
    for seed in range(4):
        rng = np.random.default_rng(seed)
        x_dot = data.x_dot + 0.02 * data.x_dot.std(axis=0) * _correlated(rng, data.x.shape, 0.95)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model = HuberSINDy(library=PolynomialLibrary(degree=4)).fit(data.x, data.t, x_dot=x_dot)
        d = model.diagnostics_
        short = np.flatnonzero(d.independent_samples < d.samples_needed)
        messages = [str(w.message) for w in caught if kind_of(w) == "few samples for the search"]
        assert len(messages) == (short.size > 0)
        if short.size:
            fired += 1
            assert messages[0].startswith(f"equations {short.tolist()}: the kept samples hold")
            assert messages[0] in d.problems()
        assert "independent samples per equation" in repr(d)
    assert fired >= 3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_few_samples_per_library_term_do_not_warn_when_the_search_has_enough(seed):
    # Lorenz on a degree-5 library: 56 terms, 251 samples (fewer than 5 per term), yet
    # a search for 2 or 3 terms among 56 needs about 16 to 24 independent samples.
    rng = np.random.default_rng(seed)
    lorenz = Lorenz()
    data = lorenz.generate(t_end=10.0, dt=0.04, x0=lorenz.initial_state() + rng.normal(size=3))
    x = data.x + 0.005 * data.x.std(axis=0) * rng.normal(size=data.x.shape)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = HuberSINDy(library=PolynomialLibrary(degree=5)).fit(x, data.t, x_dot=data.x_dot)
    d = model.diagnostics_
    assert d.samples_per_term < 5
    assert d.independent_samples.min() > 2 * d.samples_needed.max()
    assert not {kind_of(w) for w in caught} & {
        "few samples for the search",
        "fewer samples than terms",
    }


def test_the_sample_rules_fire_on_exactly_the_equations_short_of_samples():
    data = Lorenz().generate(t_end=5.0)
    d = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot).diagnostics_
    assert d.problems() == []
    np.testing.assert_array_equal(d.samples_needed, samples_needed(d.selected_terms, d.n_terms))
    short = dataclasses.replace(d, independent_samples=d.samples_needed * [2.0, 0.9, 0.5])
    ((kind, message),) = short.findings()
    assert kind == "few samples for the search" and message.startswith("equations [1, 2]:")
    ((kind, _),) = dataclasses.replace(d, samples_per_term=1.0).findings()
    assert kind == "fewer samples than terms"
    # k log(p - k) with the factor of the sharp threshold; at least k; nothing to find
    # in an empty equation
    need = samples_needed([0, 1, 3, 9, 10], 10)
    np.testing.assert_allclose(need, [0.0, 2 * np.log(9), 6 * np.log(7), 9.0, 10.0])


def test_clean_data_gives_diagnostics_without_problems():
    data = Lorenz().generate(t_end=5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot)
    d = model.diagnostics_
    assert d.problems() == []
    assert d.flagged_fraction <= 0.02
    assert d.certified.all()
    assert "no problem found" in repr(d)


def test_temporal_screen_sees_through_dense_row_contamination():
    # 20 % of the samples hit in every component: a least-squares local fit lets such
    # outliers hide one another; the trimmed start does not.
    t, clean, x = _smooth(m=2000, seed=3)
    rng = np.random.default_rng(4)
    rows = rng.random(x.shape[0]) < 0.2
    spread = clean.std(axis=0)
    x[rows] += 0.2 * spread * rng.normal(size=(rows.sum(), 3))
    s = temporal_screen(x, t)
    gross = np.abs(x - clean) > 10e-3 * spread  # ten noise levels and more
    assert s.flags[gross].mean() >= 0.9
    assert s.flags[~rows].mean() <= 0.01
    # the noise level is measured on the unflagged entries: the 1e-3 noise, not the
    # contamination
    np.testing.assert_allclose(s.scale, 1e-3, rtol=0.3)


def test_a_burst_of_noise_is_not_excused_as_a_fast_excursion():
    t, clean, x = _smooth(seed=5)
    rng = np.random.default_rng(6)
    x[600:640] += 0.3 * clean.std(axis=0) * rng.normal(size=(40, 3))
    s = temporal_screen(x, t)
    gross = np.abs(x - clean) > 10e-3 * clean.std(axis=0)
    # Excused as a fast excursion, nearly none would be flagged; the model-based screen
    # sees what the trimmed local fits inside a burst miss.
    assert s.flags[600:640][gross[600:640]].mean() >= 0.5


def test_smooth_local_scale_excuses_smooth_errors_only():
    from robust_sindy.core.statistics import smooth_local_scale

    rng = np.random.default_rng(0)
    base = rng.normal(size=(400, 1))
    smooth = base.copy()
    smooth[200:240, 0] += 50 * np.sin(np.linspace(0, np.pi, 40))  # a smooth bump
    rough = base.copy()
    rough[200:240, 0] += 50 * rng.normal(size=40)  # a burst
    assert smooth_local_scale(smooth, 20)[220, 0] > 10
    assert smooth_local_scale(rough, 20)[220, 0] == 0.0


def _lorenz_states(noise, seed=0):
    data = Lorenz().generate()
    rng = np.random.default_rng(seed)
    return data, data.x + noise * data.x.std(axis=0) * rng.normal(size=data.x.shape)


def test_library_noise_is_small_on_clean_states_and_raises_the_selection_threshold():
    data, x = _lorenz_states(1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdentificationWarning)
        model = HuberSINDy().fit(x, data.t, x_dot=data.x_dot)
    columns, weakest = model.library_noise_
    assert columns.shape == (10,) and np.all(columns < 0.01)
    assert model.diagnostics_.library_noise == weakest < 0.05
    assert model.selection_tol_ == max(model.selection_tol, columns.max())
    assert not model.diagnostics_.unstable.any()


def test_noisy_states_in_a_large_library_warn_of_errors_in_the_variables():
    data, x = _lorenz_states(0.05)
    with pytest.warns(IdentificationWarning, match="errors in the variables"):
        model = HuberSINDy(library=PolynomialLibrary(degree=4)).fit(x, data.t, x_dot=data.x_dot)
    assert model.diagnostics_.library_noise > 0.15
    assert model.selection_tol_ > model.selection_tol


def test_a_noisy_library_warns_only_where_the_selected_terms_are_noisy():
    # 0.5 % noise on the states, degree-4 library, exact derivatives, four seeds: the
    # library's weakest direction is noisy (errors in the variables can confuse terms
    # along it).  Where the support is exact (most seeds) the selected terms are not
    # noisy and no noisy library is warned of; a wrong support warns.  The left-out
    # terms reported below the floor lie above their own column's noise.
    import dataclasses

    right = 0
    for seed in range(4):
        data, x = _lorenz_states(0.005, seed)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model = HuberSINDy(library=PolynomialLibrary(degree=4)).fit(x, data.t, x_dot=data.x_dot)
        d = model.diagnostics_
        kinds = {getattr(c.message, "kind", "") for c in caught}
        assert d.library_noise > 0.15, seed
        if model.support_.sum(axis=1).tolist() == [2, 3, 2]:
            right += 1
            assert np.all(d.support_noise < 0.15) and "noisy library" not in kinds, seed
        else:
            assert kinds, seed
        below = np.isfinite(d.below_floor)
        own = np.broadcast_to(model.library_noise_[0], below.shape)
        assert np.all(d.below_floor[below] >= own[below]), seed
    assert right >= 3
    noisy = dataclasses.replace(d, support_noise=np.array([0.1, 0.5, np.nan]))
    assert any(k == "noisy library" and m.startswith("equations [1]") for k, m in noisy.findings())


def test_terms_fitted_to_noise_are_reported_unstable():
    data = Lorenz().generate()
    rng = np.random.default_rng(1)
    noise = rng.normal(size=data.x.shape)  # derivatives that no term explains
    with pytest.warns(IdentificationWarning, match="change sign or by more than 50 %"):
        model = HuberSINDy(lam=1e-9, delta=1.0, screen=False).fit(data.x, data.t, x_dot=noise)
    assert model.diagnostics_.unstable.any(axis=1).all()


def test_unstable_terms_warn_only_where_no_significance_test_judged_them():
    # Terms that move when a quarter of the data is left out warn when nothing else
    # judged them (a given lam: no robust t); where the significance rounds did, they
    # rest on part of the record, which the report notes (a transient that tells terms
    # apart, as on a Hopf record: on their own such notes were warnings only on right
    # answers).
    import dataclasses

    data = Lorenz().generate(t_end=5.0)
    d = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot).diagnostics_
    assert np.isfinite(d.significance).any(axis=1).all() and not d.unstable.any()
    unstable = np.zeros_like(d.unstable)
    unstable[1, np.flatnonzero(np.isfinite(d.significance[1]))[0]] = True
    judged = dataclasses.replace(d, unstable=unstable)
    assert "unstable terms" not in [k for k, _ in judged.findings()]
    (note,) = [m for k, m in judged.notes() if k == "unstable terms"]
    assert note.startswith("equations [1]: 1 selected terms") and "rest on part" in note
    untested = dataclasses.replace(judged, significance=np.full_like(d.significance, np.nan))
    (found,) = [m for k, m in untested.findings() if k == "unstable terms"]
    assert found.startswith("equations [1]: 1 selected terms") and "no significance" in found
    assert "unstable terms" not in [k for k, _ in untested.notes()]


def test_derivatives_next_to_masked_entries_keep_their_order():
    # The window of a sample is its five nearest usable samples: next to a masked entry
    # the derivative is still a quartic's (errors like the unmasked ones), not a
    # lower-order fit's.
    t = np.linspace(0.0, 10.0, 501)
    x = np.sin(3 * t)[:, None]
    true = 3 * np.cos(3 * t)[:, None]
    mask = np.ones(x.shape, dtype=bool)
    mask[100:400:7] = False
    x_bad = x.copy()
    x_bad[~mask] += 10.0
    plain = np.abs(local_polynomial_derivative(x, t) - true).max()
    masked = np.abs(local_polynomial_derivative(x_bad, t, mask=mask) - true).max()
    assert masked < 5 * plain < 1e-4


def test_the_small_hankel_cholesky_solver_matches_lapack():
    from robust_sindy.timeseries.temporal import _hankel_solve

    rng = np.random.default_rng(0)
    tau = rng.uniform(-1, 1, size=(40, 7, 9))  # sums of powers of 9 times per system
    mask = rng.random((40, 7, 9)) < 0.7
    moments = np.einsum("bkj,bkjs->bks", mask, tau[..., None] ** np.arange(7))
    a = moments[..., np.add.outer(np.arange(4), np.arange(4))] + 1e-3 * np.eye(4)
    b = rng.normal(size=(40, 7, 4))
    solved = _hankel_solve(moments, b, 1e-3)
    assert np.allclose(solved, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-8)


def test_shared_window_inverses_give_the_general_fit():
    # Uniform times share each window place's elemental inverses; times jittered
    # beyond that tolerance take the general batched solve: same fit.
    from robust_sindy.timeseries.temporal import _lts_fitted

    rng = np.random.default_rng(3)
    t = 0.01 * np.arange(1500)
    x = np.sin(3 * t) + 0.01 * rng.standard_t(2, size=t.size)
    x[rng.choice(t.size, 60, replace=False)] += 1.0
    jittered = t + 1e-7 * rng.uniform(size=t.size)
    assert np.allclose(_lts_fitted(x, t), _lts_fitted(x, jittered), atol=1e-6)


@pytest.mark.parametrize("m", [1, 2, 5, 8, 9, 40, 41, 42, 300])
def test_local_scale_is_the_windowed_median_shifted_inside_at_the_ends(m):
    from robust_sindy.core.statistics import local_scale

    a = np.random.default_rng(m).standard_t(2, size=(m, 3))
    for h in (1, 4, 20):
        w = min(2 * h + 1, m)
        start = np.clip(np.arange(m) - h, 0, m - w)
        expected = np.array([np.median(np.abs(a[s : s + w]), axis=0) for s in start])
        assert np.array_equal(local_scale(a, h), 1.4826 * expected)
        if w % 2:  # the running median, of the values themselves
            from robust_sindy.core.statistics import running_median

            expected = np.array([np.median(a[s : s + w], axis=0) for s in start])
            assert np.array_equal(running_median(a, w), expected)


@pytest.mark.parametrize("m", [1, 2, 5, 9, 41, 300])
def test_local_scale_ignores_nan_as_nanmedian_does(m):
    from robust_sindy.core.statistics import local_scale

    rng = np.random.default_rng(m)
    a = rng.standard_t(2, size=(m, 3))
    a[rng.random((m, 3)) < 0.3] = np.nan
    a[: min(m, 3), 0] = np.nan  # windows with nothing left give 0
    for h in (1, 4, 20):
        w = min(2 * h + 1, m)
        start = np.clip(np.arange(m) - h, 0, m - w)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
            expected = [np.nanmedian(np.abs(a[s : s + w]), axis=0) for s in start]
        assert np.array_equal(local_scale(a, h), 1.4826 * np.nan_to_num(np.array(expected)))


def test_unique_rows_groups_rows_as_numpy_unique_does():
    from robust_sindy.timeseries.temporal import _unique_rows

    key = np.random.default_rng(0).integers(-2, 3, size=(2000, 8))
    first, inverse = _unique_rows(key)
    assert np.array_equal(key[first][inverse], key)
    assert first.size == np.unique(key, axis=0).shape[0]


def _pulses(seed=0, m=1500):
    """Smooth states with two pulses only a few samples wide (sharp, but smooth at the
    sampling resolution), a spike and a burst of noise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 15.0, m)
    dt = t[1] - t[0]
    pulses = 3 * np.exp(-0.5 * ((t - 5) / (1.5 * dt)) ** 2)
    pulses += 2 * np.exp(-0.5 * ((t - 11) / (2 * dt)) ** 2)
    clean = np.column_stack([np.sin(t) + pulses, np.cos(1.3 * t)])
    x = clean + 1e-3 * rng.normal(size=clean.shape)
    x[300, 0] += 0.5
    x[900:920] += 0.3 * rng.normal(size=(20, 2))
    near = (np.abs(t - 5) < 10 * dt) | (np.abs(t - 11) < 10 * dt)
    return t, clean, x, near


@pytest.mark.parametrize("seed", [0, 1])
def test_temporal_screen_leaves_an_unresolved_excursion_alone(seed):
    # The local fits cannot follow a pulse a few samples wide; the screen must not
    # "repair" it with their predictions, yet still flag the spike and the burst.
    t, clean, x, near = _pulses(seed)
    s = temporal_screen(x, t)
    assert not s.flags[near].any()
    assert s.flags[300, 0]
    gross = np.abs(x - clean) > 10e-3 * clean.std(axis=0)
    assert s.flags[900:920][gross[900:920]].mean() >= 0.5
    assert s.flags[~near].sum() <= 60  # the spike, the burst, its edges


def test_unresolved_derivatives_mark_the_excursions_only_and_are_unit_free():
    from robust_sindy.timeseries.differentiation import unresolved_derivatives

    t, _, x, near = _pulses(2)
    s = temporal_screen(x, t)
    d = local_polynomial_derivative(s.repaired, t, 2, mask=~s.flags, scale=s.scale)
    u = unresolved_derivatives(s.repaired, t, d, 2, mask=~s.flags, scale=s.scale)
    assert u[near, 0].sum() >= 10
    burst = np.zeros(t.size, dtype=bool)
    burst[890:930] = True
    assert u[~near & ~burst].sum() <= 5
    # Resolved states with a fifth of the entries masked: the windows widened by the
    # gaps are not mistaken for unresolved ones.
    rng = np.random.default_rng(3)
    y = np.column_stack([np.sin(t), np.cos(1.3 * t)]) + 1e-3 * rng.normal(size=(t.size, 2))
    mask = rng.random(y.shape) > 0.2
    dy = local_polynomial_derivative(y, t, 2, mask=mask, scale=[1e-3, 1e-3])
    uy = unresolved_derivatives(y, t, dy, 2, mask=mask, scale=[1e-3, 1e-3])
    assert uy.mean() <= 0.005
    c, tau = np.array([1e3, 1e-2]), 1e-2
    scaled = unresolved_derivatives(
        y * c, t * tau, dy * c / tau, 2, mask=mask, scale=1e-3 * c
    )  # fmt: skip
    assert np.array_equal(scaled, uy)
    with pytest.raises(ValueError, match="derivative"):
        unresolved_derivatives(y, t, dy[:-1], 2)
    with pytest.raises(ValueError, match="cutoff"):
        unresolved_derivatives(y, t, dy, 2, cutoff=0.0)
    with pytest.raises(ValueError, match="half_window"):
        unresolved_derivatives(y, t, dy, 0)


@pytest.mark.parametrize("seed", [101, 102])
def test_relaxation_jumps_states_only_are_left_out_not_explained(seed):
    # Van der Pol with mu = 5: each relaxation jump takes a few samples, where the
    # estimated derivative's truncation error is systematic.  Fitted, it selects spurious
    # cubic terms at robust t well above the bar; left out, the model is exact.
    t, x = van_der_pol(5.0, seed)
    model = HuberSINDy(library=PolynomialLibrary(degree=3), formulation="strong")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        # The weak form estimates no derivative: nothing to leave out, and exact too.
        weak = HuberSINDy(library=PolynomialLibrary(degree=3), formulation="weak").fit(x, t)
    assert np.array_equal(weak.support_, model.support_), weak.equations()
    assert not weak.unresolved_.any() and weak.unresolved_.shape == (x.shape[0],)
    names = model.get_feature_names()
    true = np.zeros((2, len(names)), dtype=bool)
    true[0, names.index("x1")] = True
    true[1, [names.index(v) for v in ("x0", "x1", "x0^2*x1")]] = True
    assert np.array_equal(model.support_, true), model.equations()
    d = model.diagnostics_
    assert d.unresolved_samples == model.unresolved_.sum() > 0
    assert d.temporal_flagged_entries <= 0.02 * x.size
    assert model.screened_[model.unresolved_].all()
    assert "unresolved derivatives" in repr(d)
    assert not any("sampling does not resolve" in str(w.message) for w in caught)


def test_samples_left_out_are_reported_by_cause():
    import dataclasses

    data = Lorenz().generate(t_end=5.0)
    d = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot).diagnostics_
    m = d.n_samples

    def problems(left_out, unresolved, far=0.0):
        return dataclasses.replace(
            d, flagged_fraction=left_out, unresolved_samples=round(unresolved * m),
            missing_far_samples=round(far * m),
            model_flagged_samples=round((left_out - unresolved - far) * m),
        ).problems()  # fmt: skip

    assert problems(0.2, 0.1) == [] and problems(0.45, 0.2) == []
    (message,) = problems(0.4, 0.05)
    assert message.startswith("35 % of the data were flagged as outliers")
    # Samples left out over flagged entries count by their entries: 45 % of the samples
    # with a glitch in one of ten channels is 4.5 % of the entries, no doubt; 35 % of the
    # entries is.
    by_entries = dataclasses.replace(
        d, derivative_half_window=np.zeros(10, dtype=int), flagged_fraction=0.45,
        temporal_flagged_samples=round(0.45 * m), readmitted_samples=0,
        temporal_flagged_left_out=round(0.045 * 10 * m),
    )  # fmt: skip
    assert by_entries.problems() == []
    (message,) = dataclasses.replace(
        by_entries, temporal_flagged_left_out=round(0.35 * 10 * m)
    ).problems()
    assert message.startswith("35 % of the data were flagged as outliers (of the entries")
    (message,) = problems(0.45, 0.4)
    assert message.startswith("at 40 % of the samples the estimated derivatives")
    (message,) = problems(0.55, 0.27)
    assert message.startswith("55 % of the samples were left out of the fit (28 % flagged")
    # Samples too far from a reading to fill are not outliers, and are named.
    assert problems(0.4, 0.05, far=0.3) == []
    (message,) = problems(0.6, 0.05, far=0.4)
    assert message.startswith("60 % of the samples were left out of the fit (15 % flagged")
    assert "40 % too far from a reading to fill" in message


def test_a_state_noise_measured_too_large_does_not_excuse_gross_errors():
    from robust_sindy.selection import screen_rows

    rng = np.random.default_rng(4)
    m, p = 800, 4
    theta = rng.normal(size=(m, p))
    xi = np.array([1.0, -2.0, 0.5, 0.0])
    noise_col = [1e-3 * rng.normal(size=(m, p))]  # the library noise of one state
    y = theta @ xi + noise_col[0] @ xi * rng.normal(size=m)
    bad = rng.choice(m, 80, replace=False)
    y[bad] += rng.choice([-1.0, 1.0], 80) * rng.uniform(0.05, 0.2, 80)
    caught = screen_rows(theta, y, noise=noise_col).outliers
    assert set(bad) <= set(np.flatnonzero(caught))
    # The same noise measured 1000 times too large: the residuals show it is not there,
    # and it excuses nothing (taken at its face value it would excuse every error).
    too_large = screen_rows(theta, y, noise=[1e3 * noise_col[0]]).outliers
    assert np.array_equal(too_large, caught)


def _numpy_only(monkeypatch):
    """Make the temporal screen's compiled kernels report that they cannot run."""
    from robust_sindy.timeseries import _temporal_kernels

    monkeypatch.setattr(_temporal_kernels, "lts_windows", lambda *a, **k: None)
    monkeypatch.setattr(_temporal_kernels, "loo_predict", lambda *a, **k: None)


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("seed", range(6))
def test_compiled_local_fits_agree_with_the_numpy_ones(seed, monkeypatch):
    # Trimmed fits and leave-one-out predictions: compiled, then the NumPy array
    # code on the same data (uniform and irregular times, gross errors, any units).
    from robust_sindy.timeseries.temporal import _lts_fitted, clean_neighbours, loo_predict

    rng = np.random.default_rng(seed)
    m = int(rng.integers(14, 2500))
    t = np.sort(rng.uniform(0, 10, m)) if seed % 2 else np.linspace(0, rng.uniform(0.1, 100), m)
    x = np.sin(t * rng.uniform(0.5, 3)) * 10.0 ** rng.uniform(-5, 5)
    x = x + 1e-3 * np.abs(x).max() * rng.standard_t(2, m)
    bad = rng.random(m) < 0.1
    x[bad] += np.abs(x).max() * rng.normal(size=bad.sum())
    flags = rng.random(m) < 0.2
    nb = clean_neighbours(flags, 4)
    compiled = (_lts_fitted(x, t), *loo_predict(x, t, nb, 4))
    _numpy_only(monkeypatch)
    numpy = (_lts_fitted(x, t), *loo_predict(x, t, nb, 4))
    for a, b in zip(compiled, numpy, strict=True):
        assert np.abs(a - b).max() <= 1e-9 * np.abs(b).max()


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="numba is not installed")
def test_temporal_screen_flags_the_same_entries_without_the_kernels(monkeypatch):
    t, _, x = _smooth(seed=4, noise=1e-3)
    rng = np.random.default_rng(4)
    spikes = rng.random(x.shape) < 0.03
    x = x + spikes * rng.choice([-1.0, 1.0], x.shape) * 0.5
    compiled = temporal_screen(x, t)
    _numpy_only(monkeypatch)
    numpy = temporal_screen(x, t)
    assert np.array_equal(compiled.flags, numpy.flags)
    assert np.allclose(compiled.repaired, numpy.repaired, rtol=1e-9, atol=0)
    assert compiled.flags[spikes].mean() > 0.9


def test_a_state_constant_up_to_rounding_has_no_flags():
    # A state that does not move, stored as floats with rounding-level wobble: its
    # scale is rounding, and none of its entries may be flagged by it (in any units).
    t, x, _ = _smooth(seed=5)
    rng = np.random.default_rng(5)
    for level in (1e-8, 1.0, 1e8):
        still = -13.72884 * level * (1.0 + 1e-15 * rng.choice([-1, 0, 1], t.size))
        s = temporal_screen(np.column_stack([x[:, 0], still]), t)
        assert not s.flags[:, 1].any()
        assert np.all(s.repaired[:, 1] == still)


def test_the_screen_runs_where_its_kernels_cannot_compile(monkeypatch):
    from robust_sindy.timeseries import _temporal_kernels

    t, _, x = _smooth(seed=6)
    reference = temporal_screen(x, t)
    monkeypatch.setattr(_temporal_kernels._jit, "broken", "numba cannot compile here")
    assert (
        _temporal_kernels.loo_predict(x[:, 0], t, np.zeros((t.size, 2), int), 1, np.arange(t.size))
        is None
    )
    again = temporal_screen(x, t)
    assert np.array_equal(again.flags, reference.flags)
    assert np.allclose(again.repaired, reference.repaired, rtol=1e-9, atol=0)
