"""The weak form: its quadrature, its automatic support, and the estimator on its rows."""

import warnings

import numpy as np
import pytest

import robust_sindy as rs
from robust_sindy.diagnostics import kind_of
from robust_sindy.estimator import (
    MIN_INDEPENDENT_ROWS_PER_TERM,
    MIN_ROWS_PER_TERM,
    OUTLIER_EVIDENCE,
    WEAK_WITH_OUTLIERS_NOISE,
)
from robust_sindy.timeseries.temporal import noise_flag_bound, relative_noise, temporal_screen
from robust_sindy.timeseries.trajectories import Trajectories
from robust_sindy.timeseries.weak import (
    LOCAL_SAMPLES,
    MIN_SUPPORT_SAMPLES,
    WIDE_SAMPLES,
    choose_stencil,
    support_half_width,
    weak_rows,
    weight_functions,
)

LORENZ = rs.systems.Lorenz()
TRUE = LORENZ.true_coef()


def _lorenz(t_end=20.0, dt=0.01):
    return LORENZ.generate(t_end=t_end, dt=dt)


def _lorenz_at(t):
    import scipy.integrate

    return scipy.integrate.solve_ivp(
        LORENZ.rhs, (0.0, t[-1]), LORENZ.x0, t_eval=t, method="DOP853", rtol=1e-11,
        atol=1e-11,
    ).y.T  # fmt: skip


@pytest.mark.parametrize("irregular", [False, True])
def test_integration_by_parts_holds_on_the_samples(irregular):
    # -int phi' x = int phi xdot exactly; the product quadrature on 20 samples per half
    # width makes it hold to 1e-3 of the integrals, on uniform or random sample times.
    data = _lorenz()
    t, x, xdot = data.t, data.x, data.x_dot
    if irregular:
        rng = np.random.default_rng(1)
        keep = np.sort(rng.choice(t.size, 1500, replace=False))
        t, x, xdot = t[keep], x[keep], xdot[keep]
    phi, dphi, centres = weight_functions(t, 0.2)
    assert centres.min() - 0.2 >= t[0] - 1e-12 and centres.max() + 0.2 <= t[-1] + 1e-12
    lhs, rhs = -dphi @ x, phi @ xdot
    assert np.linalg.norm(lhs - rhs) <= 1e-3 * np.linalg.norm(rhs)


@pytest.mark.parametrize("seed", range(4))
def test_the_quadrature_holds_on_uniformly_random_times(seed):
    # Times drawn uniformly over the span cluster (two samples nearly coincide) and
    # leave gaps several steps long: the local least-squares fits neither swing at the
    # clusters nor fall back to straight lines across the gaps.  Every row holds
    # integration by parts to 1 % of the largest integral (a cubic through four
    # samples, with lines where it swung: up to 3 %), and no row's noise is amplified
    # more than 3 times the typical row's.
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 20.0, 2000))
    t -= t[0]
    x = _lorenz_at(t)
    xdot = np.array([LORENZ.rhs(0.0, v) for v in x])
    phi, dphi, _ = weight_functions(t, 0.2)
    lhs, rhs = -dphi @ x, phi @ xdot
    assert np.all(np.abs(lhs - rhs).max(axis=0) <= 1e-2 * np.abs(rhs).max(axis=0))
    amplification = np.linalg.norm(dphi, axis=1)
    assert amplification.max() <= 3.0 * np.median(amplification)


def _stencil_case(seed, level, irregular):
    """Lorenz on 2000 (random or uniform) times, noise ``level`` of each state's RMS: the
    choice, and the targets' error of both stencils against the clean states' integrals."""
    rng = np.random.default_rng([seed, int(irregular)])
    t = np.sort(rng.uniform(0.0, 20.0, 2000)) if irregular else np.arange(2000) * 0.01
    t = t - t[0]
    clean = _lorenz_at(t)
    x = clean + level * np.sqrt(np.mean(clean**2, axis=0)) * rng.normal(size=clean.shape)
    screen = temporal_screen(x, t)
    h = support_half_width(Trajectories.from_user(x, t), screen).half_width
    chosen, _ = choose_stencil([t], [screen.repaired], screen.scale, h)
    slopes = {w: weight_functions(t, h, samples=w)[1] for w in (LOCAL_SAMPLES, WIDE_SAMPLES)}
    truth = -slopes[LOCAL_SAMPLES] @ clean  # the narrow quadrature's error is far below
    errors = {w: np.linalg.norm(-d @ x - truth) for w, d in slopes.items()}
    return chosen, errors, (t, x, screen, h)


@pytest.mark.parametrize("seed", range(3))
def test_the_stencil_is_the_one_whose_targets_err_less(seed):
    # At uniformly random times the narrow stencil's rows carry more of the states'
    # noise; the wider one's quadrature error is larger.  At 5 % noise the wider stencil
    # is chosen and its targets are closer to the clean states' integrals (by a margin:
    # at most 0.9 of the narrow stencil's error); at 0.1 % noise the narrow one is kept
    # and is the closer (at most 0.8 of the wider one's error); at uniform steps the
    # narrow one is kept at 0.1 % noise.
    chosen, errors, _ = _stencil_case(seed, 0.05, irregular=True)
    assert chosen.samples == WIDE_SAMPLES and chosen.ratio < 1.0
    assert errors[WIDE_SAMPLES] <= 0.9 * errors[LOCAL_SAMPLES]
    chosen, errors, _ = _stencil_case(seed, 0.001, irregular=True)
    assert chosen.samples == LOCAL_SAMPLES and chosen.ratio > 1.0
    assert errors[LOCAL_SAMPLES] <= 0.8 * errors[WIDE_SAMPLES]
    chosen, _, _ = _stencil_case(seed, 0.001, irregular=False)
    assert chosen.samples == LOCAL_SAMPLES and chosen.ratio > 1.0


def test_the_stencil_choice_is_unit_free():
    _, _, (t, _, screen, h) = _stencil_case(0, 0.02, irregular=True)
    d, c = np.array([1e-3, 10.0, 1e3]), 100.0
    one, _ = choose_stencil([t], [screen.repaired], screen.scale, h)
    other, _ = choose_stencil([t * c], [screen.repaired * d], screen.scale * d, h * c)
    assert other.samples == one.samples
    assert other.ratio == pytest.approx(one.ratio, rel=1e-6)


def test_the_support_is_unit_free_and_grows_with_the_noise():
    data = _lorenz()
    rng = np.random.default_rng(2)
    noise = rng.normal(size=data.x.shape) * np.sqrt(np.mean(data.x**2, axis=0))
    widths = []
    for level in (0.01, 0.2):
        x = data.x + level * noise
        h = support_half_width(Trajectories.from_user(x, data.t), temporal_screen(x, data.t))
        d, c = np.array([1e-3, 10.0, 1e3]), 100.0
        scaled = support_half_width(
            Trajectories.from_user(x * d, data.t * c), temporal_screen(x * d, data.t * c)
        )
        assert scaled.half_width == pytest.approx(c * h.half_width, rel=1e-9)
        assert scaled.noise_limited == h.noise_limited
        assert h.half_width >= MIN_SUPPORT_SAMPLES * 0.01 * (1 - 1e-9)
        widths.append(h.half_width)
    assert widths[1] > widths[0]


@pytest.mark.parametrize("seed", range(3))
def test_the_support_passes_the_fastest_states_band(seed):
    # A slow and a fast oscillation (periods 20 and 2, 40 samples per fast period) at
    # 2 % noise: the half width is the one the fast state asks for on its own, which is
    # narrower than the slow state's (a support set by the slow state would damp the
    # fast one's signal below its noise in every library column that holds it).
    rng = np.random.default_rng(seed)
    t = np.arange(4000) * 0.05
    x = np.column_stack([np.sin(2 * np.pi * t / 20), np.sin(2 * np.pi * t / 2)])
    x = x + 0.02 * np.sqrt(np.mean(x**2, axis=0)) * rng.normal(size=x.shape)

    def width(columns):
        v = x[:, columns]
        return support_half_width(Trajectories.from_user(v, t), temporal_screen(v, t))

    slow, fast, both = width([0]), width([1]), width([0, 1])
    assert slow.noise_limited and fast.noise_limited
    assert slow.half_width > 2 * fast.half_width
    assert both.half_width == pytest.approx(fast.half_width, rel=1e-12)


def test_weak_rows_of_several_trajectories_never_reach_across_them():
    data = _lorenz(t_end=6.0)
    a, b = data.x[:300], data.x[300:]
    ta, tb = data.t[:300], data.t[300:]
    traj = Trajectories.from_user([a, b], [ta, tb])
    theta = rs.PolynomialLibrary(2).fit_transform(np.vstack([a, b]))
    rows = weak_rows(traj, np.vstack([a, b]), theta, 0.2)
    one = weak_rows(Trajectories.from_user(a, ta), a, theta[:300], 0.2)
    assert len(rows.segments) == 2
    np.testing.assert_array_equal(rows.G[rows.segments[0]], one.G)


@pytest.mark.parametrize("seed", range(4))
def test_weak_form_identifies_lorenz_from_noisy_states(seed):
    # 2 % Gaussian noise on every state, no derivatives: the weak form finds the terms
    # (coefficient error well under 2 %), its fits certified.
    data = _lorenz()
    rng = np.random.default_rng(seed)
    x = data.x + 0.02 * np.sqrt(np.mean(data.x**2, axis=0)) * rng.normal(size=data.x.shape)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", rs.IdentificationWarning)
        model = rs.HuberSINDy(formulation="weak").fit(x, data.t)
    # Rows enough for the library: the forced weak form does not warn of too few.
    assert "few independent rows" not in [kind_of(w) for w in caught]
    coef = model.coef_.T
    assert np.linalg.norm(coef - TRUE) <= 0.02 * np.linalg.norm(TRUE)
    assert model.result_.converged and model.result_.kkt.max() <= 1e-8
    assert model.diagnostics_.formulation == "weak" and model.weak_.n_rows > 100
    assert model.screened_.shape == (x.shape[0],)


def test_weak_fit_agrees_with_the_cvxpy_reference_on_the_weak_rows():
    data = _lorenz(t_end=10.0)
    rng = np.random.default_rng(5)
    x = data.x + 0.05 * np.sqrt(np.mean(data.x**2, axis=0)) * rng.normal(size=data.x.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        model = rs.HuberSINDy(formulation="weak").fit(x, data.t)
    G, b = model.weak_.G, model.weak_.b
    keep = ~model.screening_.outliers
    fast = rs.fit(G[keep], b[keep], delta=model.delta_, lam=model.lam_)
    ref = rs.fit(G[keep], b[keep], method="cvxpy", delta=model.delta_, lam=model.lam_)
    assert fast.converged and fast.kkt.max() <= 1e-8
    assert np.all(fast.objective <= ref.objective * (1 + 1e-6))
    assert np.all(np.abs(fast.objective - ref.objective) <= 1e-5 * np.abs(ref.objective))


def test_auto_keeps_measured_derivatives_and_says_which_form_it_used():
    data = _lorenz(t_end=10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        measured = rs.HuberSINDy(formulation="auto").fit(data.x, data.t, x_dot=data.x_dot)
        rng = np.random.default_rng(3)
        noisy = data.x + 0.1 * np.sqrt(np.mean(data.x**2, axis=0)) * rng.normal(size=data.x.shape)
        states = rs.HuberSINDy(formulation="auto").fit(noisy, data.t)
    assert measured.diagnostics_.formulation == "strong"
    assert "measured" in measured.diagnostics_.formulation_reason
    assert states.diagnostics_.formulation == "weak"
    assert "noise" in states.diagnostics_.formulation_reason
    assert "formulation:" in repr(states.diagnostics_)


def test_the_fit_says_which_stencil_its_quadrature_used():
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, 15.0, 1500))
    t -= t[0]
    clean = _lorenz_at(t)
    unit = np.sqrt(np.mean(clean**2, axis=0)) * rng.normal(size=clean.shape)
    fits = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        for level in (0.001, 0.05):
            fits[level] = rs.HuberSINDy(formulation="weak").fit(clean + level * unit, t)
    quiet, loud = fits[0.001], fits[0.05]
    assert quiet.weak_.stencil.samples == LOCAL_SAMPLES
    assert "local fits of" not in quiet.diagnostics_.formulation_reason
    assert loud.weak_.stencil.samples == WIDE_SAMPLES
    assert f"local fits of {WIDE_SAMPLES} samples" in loud.diagnostics_.formulation_reason


def test_auto_keeps_the_strong_form_where_the_temporal_screen_found_outliers():
    # Gaussian noise alone: the screen flags about as many entries as its cutoff lets
    # through, and the weak form is used.  The same states at a tenth of the noise with
    # 1 % of the entries spiked: outliers found, and the strong form keeps them to
    # single samples.  Spiked at twice the noise: the states are noisy enough that
    # their derivatives would cost the strong form more, and the weak form is used.
    data = _lorenz(t_end=10.0)
    rng = np.random.default_rng(4)
    rms = np.sqrt(np.mean(data.x**2, axis=0))
    unit = rms * rng.normal(size=data.x.shape)
    hit = rng.random(data.x.shape) < 0.01
    spikes = np.where(hit, 3.0 * data.x.std(axis=0), 0.0)
    noisy = data.x + 0.02 * unit
    fits = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        for name, x in [("gaussian", noisy), ("quiet", data.x + 0.002 * unit + spikes),
                        ("loud", data.x + 0.04 * unit + spikes)]:  # fmt: skip
            fits[name] = rs.HuberSINDy().fit(x, data.t)
    bound = noise_flag_bound(noisy.size, OUTLIER_EVIDENCE)
    gaussian, quiet, loud = fits["gaussian"], fits["quiet"], fits["loud"]
    assert gaussian.temporal_.flags.sum() <= bound
    assert gaussian.diagnostics_.formulation == "weak"
    assert "no outliers found" in gaussian.diagnostics_.formulation_reason
    assert relative_noise(quiet.temporal_) < WEAK_WITH_OUTLIERS_NOISE / 3
    assert quiet.temporal_.flags.sum() > bound
    assert quiet.diagnostics_.formulation == "strong" and quiet.weak_ is None
    assert "more than Gaussian noise" in quiet.diagnostics_.formulation_reason
    assert relative_noise(loud.temporal_) > 2 * WEAK_WITH_OUTLIERS_NOISE
    assert loud.temporal_.flags.sum() > bound
    assert loud.diagnostics_.formulation == "weak" and loud.weak_ is not None
    assert "more than Gaussian noise" in loud.diagnostics_.formulation_reason
    assert "noise is" in loud.diagnostics_.formulation_reason


def test_effective_rows_count_the_supports_not_the_centres():
    # Centres four times closer give four times the rows but about the same number of
    # independent ones; twice the record, twice as many; time units change nothing.
    data = _lorenz(t_end=20.0)
    theta = rs.PolynomialLibrary(degree=2).fit_transform(data.x)

    def rows(t_end, min_rows, scale=1.0):
        n = round(t_end / 0.01) + 1
        traj = Trajectories.from_user(data.x[:n], scale * data.t[:n])
        return weak_rows(traj, data.x[:n], theta[:n], scale * 0.15, min_rows=min_rows)

    loose, close = rows(10.0, 0), rows(10.0, 10**6)
    assert close.n_rows > 3.5 * loose.n_rows
    assert close.effective_rows() == pytest.approx(loose.effective_rows(), rel=0.25)
    assert loose.effective_rows() < loose.n_rows / 2
    assert rows(20.0, 0).effective_rows() == pytest.approx(2 * loose.effective_rows(), rel=0.1)
    assert rows(10.0, 0, 1e3).effective_rows() == pytest.approx(loose.effective_rows(), rel=1e-9)


def _lorenz96_noisy():
    """Lorenz-96 with 10 states (66 degree-2 terms), 2000 samples, 1 % noise."""
    from robust_sindy.flows import lorenz96_records

    t, x, _, _ = lorenz96_records(10, 2000, seed=3)
    rng = np.random.default_rng(5)
    return t, x + 0.01 * np.sqrt(np.mean(x**2, axis=0)) * rng.normal(size=x.shape)


def test_auto_takes_the_strong_form_with_fewer_independent_rows_than_terms():
    # Lorenz-96 with 10 states (66 terms) at 1 % noise: on a short record the weak
    # form's overlapping test functions leave fewer independent rows than terms, and
    # the strong form is used; on a record four times as long, the weak form.
    t, x = _lorenz96_noisy()
    library = rs.PolynomialLibrary(degree=2)
    fits, independent = {}, {}
    for n in (450, 2000):
        screen = temporal_screen(x[:n], t[:n])
        traj = Trajectories.from_user(x[:n], t[:n])
        h = support_half_width(traj, screen).half_width
        theta = library.fit_transform(screen.repaired)
        # The rows the estimator builds (at least twice its minimum per term).
        min_rows = 2 * MIN_ROWS_PER_TERM * theta.shape[1]
        rows = weak_rows(traj, screen.repaired, theta, h, min_rows=min_rows)
        independent[n] = rows.effective_rows() / theta.shape[1]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rs.IdentificationWarning)
            fits[n] = rs.HuberSINDy(library=library).fit(x[:n], t[:n])
    assert independent[450] < 0.8 * MIN_INDEPENDENT_ROWS_PER_TERM
    assert fits[450].diagnostics_.formulation == "strong" and fits[450].weak_ is None
    assert "independent rows for 66 terms" in fits[450].diagnostics_.formulation_reason
    assert independent[2000] > 1.5 * MIN_INDEPENDENT_ROWS_PER_TERM
    assert fits[2000].diagnostics_.formulation == "weak"
    assert "independent rows for 66 terms" in fits[2000].diagnostics_.formulation_reason


def test_weak_form_asked_for_on_too_few_independent_rows_warns_before_the_fit():
    # The short Lorenz-96 record above (under 0.8 independent rows per term): asked for,
    # the weak form is used, and the warning comes first (turned into an error here, it
    # stops the fit before its selection on those rows), naming the counts.
    t, x = _lorenz96_noisy()
    model = rs.HuberSINDy(library=rs.PolynomialLibrary(degree=2), formulation="weak")
    with warnings.catch_warnings():
        warnings.simplefilter("error", rs.IdentificationWarning)
        with pytest.raises(rs.IdentificationWarning, match="independent rows for 66 terms") as e:
            model.fit(x[:450], t[:450])
    assert e.value.kind == "few independent rows"
    assert "formulation='auto' (which takes the strong form here)" in str(e.value)
    assert not hasattr(model, "coef_")


def test_relative_noise_is_the_screen_s_level_over_the_repaired_spread():
    # Unit-free (each state's scale and offset), and glitches do not inflate the spread.
    t = np.linspace(0.0, 30.0, 3000)
    clean = np.column_stack([np.sin(t), 2.0 * np.cos(0.7 * t), np.sin(1.3 * t + 1.0)])
    rng = np.random.default_rng(8)
    x = clean + 0.03 * clean.std(axis=0) * rng.normal(size=clean.shape)
    glitched = x.copy()
    i, j = rng.choice(x.shape[0], 90, replace=False), rng.integers(0, 3, 90)
    glitched[i, j] += 20.0 * clean.std(axis=0)[j]
    level = relative_noise(temporal_screen(x, t))
    assert 0.025 < level < 0.035
    assert relative_noise(temporal_screen(glitched, t)) == pytest.approx(level, rel=0.1)
    scaled = relative_noise(temporal_screen(1e4 * x + np.array([5e5, -3e4, 1e3]), 1e-3 * t))
    assert scaled == pytest.approx(level, rel=1e-6)


def test_the_noise_flag_bound_holds_on_gaussian_noise():
    # The temporal screen's flags on pure Gaussian noise around smooth signals stay
    # within the bound on (nearly) every draw: a rate over 40 draws, not one draw.
    t = np.linspace(0.0, 20.0, 1500)
    signal = np.column_stack([np.sin(t), np.cos(1.3 * t), np.sin(0.7 * t) ** 2])
    over = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        x = signal + 0.05 * rng.normal(size=signal.shape)
        over += temporal_screen(x, t).flags.sum() > noise_flag_bound(x.size, 1e-3)
    assert over <= 2
    assert noise_flag_bound(6000, 1e-3) < 0.005 * 6000  # far below any outlier share


def test_bad_formulation_and_weak_form_on_dask_are_refused():
    with pytest.raises(ValueError, match="formulation must be one of"):
        rs.HuberSINDy(formulation="integral").fit(np.zeros((50, 2)), 0.1)
    da = pytest.importorskip("dask.array")
    x = da.from_array(_lorenz(t_end=3.0).x, chunks=100)
    with pytest.raises(ValueError, match="in memory only"):
        rs.HuberSINDy(formulation="weak").fit(x, 0.01)


def test_ensembles_of_weak_fits_resample_blocks_of_the_records():
    # Each member's blocks are separate trajectories: test functions never cross them.
    data = _lorenz()
    rng = np.random.default_rng(0)
    x = data.x + 0.05 * np.sqrt(np.mean(data.x**2, axis=0)) * rng.normal(size=data.x.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        ens = rs.EnsembleSINDy(
            estimator=rs.HuberSINDy(formulation="weak"), n_models=4, random_state=0
        ).fit(x, data.t)
    assert ens.n_failed_ == 0 and ens.certified_fraction_ == 1.0
    np.testing.assert_array_equal(ens.coef_.T != 0, TRUE != 0)


def test_many_outliers_counts_the_records_entries_in_the_weak_form():
    # The weak form's n_samples counts its test functions; the share of flagged entries
    # is of the records' entries (4 % glitched here), not of entries per test function.
    import dataclasses

    data = _lorenz(t_end=10.0)
    rng = np.random.default_rng(5)
    spread = data.x.std(axis=0)
    x = data.x + 0.03 * spread * rng.normal(size=data.x.shape)
    hit = rng.random(x.shape) < 0.04
    x[hit] += rng.choice([-10.0, 10.0], hit.sum()) * spread[np.nonzero(hit)[1]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = rs.HuberSINDy().fit(x, data.t).diagnostics_
    assert d.formulation == "weak" and d.n_samples < d.record_samples == x.shape[0]
    assert 0.02 < d.temporal_flagged_entries / x.size < 0.06
    assert "many outliers" not in {kind_of(w) for w in caught}
    (message,) = [
        p
        for p in dataclasses.replace(d, temporal_flagged_left_out=round(0.35 * x.size)).problems()
        if "flagged as outliers" in p
    ]
    assert message.startswith("35 % of the data were flagged as outliers")
