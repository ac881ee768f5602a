"""The weak form's candidates scored under the noise their own terms carry
(robust_sindy.selection.variables)."""

import numpy as np
import scipy.integrate
import scipy.sparse

from robust_sindy.core import threads as _threads
from robust_sindy.selection.bias import LibraryNoise
from robust_sindy.selection.variables import (
    RowNoise,
    _added_chi2,
    _added_pairs,
    gls_score,
    rescore_supports,
)

RATE = 20.0  # x0' = RATE (x1 - x0): x0 follows x1 closely, a small difference of large terms


def _follower(m=2000, dt=0.01):
    def rhs(t, v):
        drive = np.sin(t) + 0.5 * np.sin(2.3 * t)
        return [RATE * (drive - v[0])]

    t = dt * np.arange(m + 500)
    sol = scipy.integrate.solve_ivp(rhs, (0, t[-1]), [0.0], t_eval=t, rtol=1e-11, atol=1e-12)
    x0 = sol.y[0][500:]
    x1 = np.sin(t[500:]) + 0.5 * np.sin(2.3 * t[500:])
    return np.column_stack([x0, x1]), dt


def _test_functions(m, dt, half=25, step=5, power=4):
    """Weights and slopes (rows x samples) of test functions (1 - s^2)^power."""
    centres = np.arange(half, m - half, step)
    w = np.zeros((centres.size, m))
    s = np.zeros_like(w)
    for r, c in enumerate(centres):
        i = np.arange(c - half, c + half + 1)
        u = (i - c) / half
        w[r, i] = (1 - u**2) ** power * dt
        s[r, i] = -2 * power * u * (1 - u**2) ** (power - 1) / (half * dt) * dt
    return scipy.sparse.csr_array(w), scipy.sparse.csr_array(s)


def _rows(seed, level=0.01, both=False):
    """Weak rows of the follower: library (the states), target (of ``x0``'s equation,
    or of both equations with ``both``) and their noise."""
    x, dt = _follower()
    sigma = level * np.sqrt(np.mean(x**2, axis=0))
    noisy = x + sigma * np.random.default_rng(seed).normal(size=x.shape)
    w, s = _test_functions(x.shape[0], dt)
    g = w @ noisy  # the library is the states themselves: first order is exact
    b = -(s @ noisy) if both else -(s @ noisy[:, 0])
    ones = np.ones((x.shape[0], 1))
    noise = RowNoise(w, s, LibraryNoise(2, [[0], [1]], [sigma[0] * ones, sigma[1] * ones]), sigma)
    return g, b, noise


def test_the_true_support_has_the_chi_square_of_its_rows():
    """With the noise its own (large) coefficients carry counted, the residuals of the
    true model have chi-square about the number of rows (mean over seeds, within 15 %),
    and a support without one of its terms is far beyond it in every seed."""
    ratios, missing = [], []
    for seed in range(6):
        g, b, noise = _rows(seed)
        chi2, xi = gls_score(g, b, np.array([True, True]), np.array([-RATE, RATE]), noise, 0)
        ratios.append(chi2 / (g.shape[0] - 2))
        assert np.allclose(xi, [-RATE, RATE], rtol=0.1)
        short, _ = gls_score(g, b, np.array([False, True]), np.array([0.0, 1.0]), noise, 0)
        missing.append(short / g.shape[0])
    assert 0.85 < np.mean(ratios) < 1.15
    assert min(missing) > 3.0


def test_least_squares_residuals_read_the_columns_noise_as_the_models():
    """The premise: the true model's residual variance is many times the target's own
    noise (the columns' noise times coefficients of 20), so any criterion that reads
    all candidates' residuals on one scale sees the true model as a poor fit."""
    g, b, noise = _rows(0)
    r = b - g @ np.array([-RATE, RATE])
    own = np.asarray((noise.slopes @ noise.slopes.T).diagonal()) * noise.target[0] ** 2
    assert np.mean(r**2) > 5 * np.mean(own)


def test_rescoring_replaces_a_support_only_by_a_clearly_better_one():
    g, b, noise = _rows(1)
    y = b[:, None]
    # Candidates: the second term alone (the chosen one), both terms.
    pool = np.array([[[0.0], [1.0]], [[-RATE], [RATE]]])
    out = rescore_supports(g, y, np.array([[0.0], [1.0]]), [pool], noise, margin=6.0)
    assert out.switched.tolist() == [True]
    assert out.support[:, 0].tolist() == [True, True]
    assert out.chosen_score[0] - out.best_score[0] > 6.0
    # The true support chosen: nothing better to replace it with.
    stay = rescore_supports(g, y, np.array([[-RATE], [RATE]]), [pool], noise, margin=6.0)
    assert stay.switched.tolist() == [False]


def test_a_replaced_equation_measures_its_runner_up_by_the_rescoring_score():
    """The margin to the next other model of a replaced equation is read from the
    supports the rescoring fitted (the selection's BIC chose the support it replaced):
    positive, at most the chosen support's own deficit; a support that keeps the
    reported terms but changes a coefficient by more than half is another model."""
    for seed in (1, 4):
        g, b, noise = _rows(seed)
        pool = np.array([[[0.0], [1.0]], [[-RATE], [RATE]]])
        out = rescore_supports(g, b[:, None], np.array([[0.0], [1.0]]), [pool], noise, 6.0)
        assert out.switched.tolist() == [True]
        reported = out.scored[0][2][np.argmin(out.scored[0][1])][:, None]
        assert np.array_equal(reported[:, 0] != 0, [True, True])
        margin = out.rival_margin(reported)[0]
        assert 0.0 < margin <= out.chosen_score[0] - out.best_score[0]
        # Reported as the second term alone, with its coefficient near 1: the best
        # support (both terms, that coefficient near RATE) is another model.
        assert out.rival_margin(np.array([[0.0], [1.0]]))[0] == 0.0
    # The true support chosen and kept, its chi-square explained by the noise: the
    # score judges it too, and the other model (the second term alone) is far behind.
    stay = rescore_supports(g, b[:, None], np.array([[-RATE], [RATE]]), [pool], noise, 6.0)
    assert stay.trusted.tolist() == [True]
    assert stay.rival_margin(np.array([[-RATE], [RATE]]))[0] > 6.0


def test_rescoring_keeps_the_support_where_the_noise_does_not_explain_the_residuals():
    """States' noise far below what the residuals hold (quadrature error, a model the
    library misses): the score would favour every term, and it is not used."""
    g, b, noise = _rows(2)
    tiny = RowNoise(noise.weights, noise.slopes,
                    LibraryNoise(2, noise.columns.cols, [v * 1e-3 for v in noise.columns.values]),
                    noise.target * 1e-3)  # fmt: skip
    y = b[:, None]
    pool = np.array([[[0.0], [1.0]], [[-RATE], [RATE]]])
    out = rescore_supports(g, y, np.array([[0.0], [1.0]]), [pool], tiny, margin=6.0)
    assert out.switched.tolist() == [False]
    assert out.best_score[0] > 2.0 * g.shape[0]


def test_the_diagnostics_say_which_equations_were_rescored():
    from robust_sindy import HuberSINDy, PolynomialLibrary

    t = 0.02 * np.arange(1500)
    x = np.column_stack([np.sin(t), np.cos(t)]) + 0.01 * np.random.default_rng(0).normal(
        size=(t.size, 2)
    )
    weak = HuberSINDy(library=PolynomialLibrary(degree=2), formulation="weak").fit(x, t)
    assert set(weak.diagnostics_.errors_in_variables.tolist()) <= {0, 1}
    assert "supports replaced under the noise their terms carry" in str(weak.diagnostics_)
    strong = HuberSINDy(library=PolynomialLibrary(degree=2), formulation="strong").fit(x, t)
    assert strong.diagnostics_.errors_in_variables.tolist() == [-1, -1]
    assert "(weak form): not scored" in str(strong.diagnostics_)


def test_the_band_is_the_covariance_of_the_residual_noise():
    """The banded covariance (formed from products of the test functions) equals
    ``D D^T`` of the residual's noise factor, on and off the equation's own state."""
    noise = _rows(3)[2]
    rng = np.random.default_rng(0)
    for k in (0, 1):
        xi = rng.normal(scale=10.0, size=2)
        full = noise.covariance(xi, k).toarray()
        band = noise.band(xi, k)
        rows = full.shape[0]
        for d in range(band.shape[0]):
            assert np.allclose(band[d, : rows - d], np.diag(full, -d), rtol=1e-12, atol=0)
        assert not np.any(np.tril(full, -band.shape[0]))  # nothing outside the band


def test_the_search_reaches_a_support_no_candidate_holds():
    """The selection proposed only the second term: the stepwise search under the
    same score finds the true pair."""
    g, b, noise = _rows(4)
    pool = np.array([[[0.0], [1.0]]])
    out = rescore_supports(g, b[:, None], np.array([[0.0], [1.0]]), [pool], noise, margin=6.0)
    assert out.switched.tolist() == [True]
    assert out.support[:, 0].tolist() == [True, True]


def test_the_diagnostics_take_a_replaced_equations_margin_from_the_rescoring():
    from types import SimpleNamespace

    from robust_sindy.diagnostics import _rival_margin

    g, b, noise = _rows(1)
    y = np.column_stack([b, b])
    pool = np.array([[[0.0, -RATE], [1.0, RATE]], [[-RATE, -RATE], [RATE, RATE]]])
    out = rescore_supports(g, y, np.array([[0.0, -RATE], [1.0, RATE]]), [pool], noise, 6.0)
    assert out.switched.tolist() == [True, False]
    bic = np.array([0.0, 2.5])  # the BIC's own choice reads as a runner-up at zero
    selection = SimpleNamespace(criterion="bic", rival_margin_to=lambda reference, theta, y: bic)
    reported = np.array([[-RATE, -RATE], [RATE, RATE]])
    margin, by_noise = _rival_margin(selection, out, reported, 2, None, None)
    assert margin[0] == out.rival_margin(reported)[0] > 6.0
    # Kept, and the score puts the other model further than the BIC does: the BIC's
    # margin stands.
    assert out.trusted.tolist() == [False, True] and out.rival_margin(reported)[1] > 2.5
    assert margin[1] == 2.5
    assert by_noise.tolist() == [True, False]
    # Where the BIC puts the other model further away than the score does (here: the
    # BIC saw none), the score's margin is the one reported (HyperJha at 8 % noise:
    # `x1*x2` chosen in place of `x1`, BIC margin 3422, the score's 1.3).
    far = SimpleNamespace(
        criterion="bic", rival_margin_to=lambda reference, theta, y: np.array([0.0, np.inf])
    )
    margin, by_noise = _rival_margin(far, out, reported, 2, None, None)
    assert margin[1] == out.rival_margin(reported)[1] and by_noise.tolist() == [True, True]
    assert np.isnan(_rival_margin(None, out, reported, 2, None, None)[0]).all()


def test_the_runner_up_warning_names_the_score_its_margins_are_on():
    from types import SimpleNamespace

    from robust_sindy.diagnostics import _runner_up_score

    d = SimpleNamespace(rival_by_noise=np.array([False, True, False]), constraint_residual=np.nan)
    assert _runner_up_score(d, [0, 2]) == "BIC"
    assert "for equations [1], the score under the noise" in _runner_up_score(d, [0, 1])
    # Under constraints the margins are on the criterion summed over the equations.
    d.constraint_residual = 1e-15
    assert "summed over the equations" in _runner_up_score(d, [0, 1])


def _rows_with_extra(seed, level=0.01):
    """``_rows`` with two more columns, smooth signals free of noise (they depend on no
    state): the first in the target with a coefficient that leaves, when dropped, a
    quarter of the rows in chi-square; the second spurious."""
    x, dt = _follower()
    sigma = level * np.sqrt(np.mean(x**2, axis=0))
    noisy = x + sigma * np.random.default_rng(seed).normal(size=x.shape)
    t = dt * np.arange(x.shape[0])
    w, s = _test_functions(x.shape[0], dt)
    g = w @ np.column_stack([noisy, np.cos(0.37 * t + 1.0), np.sin(0.81 * t + 0.3)])
    ones = np.ones((x.shape[0], 1))
    noise = RowNoise(w, s, LibraryNoise(4, [[0], [1]], [sigma[0] * ones, sigma[1] * ones]), sigma)
    # What the column leaves in chi-square beside the other true terms, under the
    # covariance of the true model (one round: that covariance kept), to scale it.
    on, xi = np.array([True, True, False, False]), np.array([-RATE, RATE, 0.0, 0.0])
    own = gls_score(g, g[:, 2], on, xi, noise, 0, rounds=1)[0]
    coef = np.sqrt(0.25 * g.shape[0] / own)
    y = -(s @ noisy[:, 0]) + coef * g[:, 2]
    return g, y[:, None], noise, coef


def test_the_score_contests_the_drop_of_a_true_term_and_not_of_a_spurious_one():
    """Putting back a dropped true term whose loss leaves a quarter of the rows in
    chi-square lowers the score far beyond KEEP_EVIDENCE in every seed; putting back a
    spurious column dropped from the true support plus it does not (its chi-square gain
    is chi-square with one degree of freedom, against a penalty of log(rows): beyond
    KEEP_EVIDENCE with probability about 1e-4).  Where the residuals of a support
    compared are beyond what the states' noise explains (a dropped term that carried
    most of the equation; the noise taken 1000 times smaller than it is), the score
    says nothing about the drop."""
    from robust_sindy.selection.variables import KEEP_EVIDENCE, dropped_evidence

    def support(*on):
        out = np.zeros((4, 1), dtype=bool)
        out[list(on), 0] = True
        return out

    true = support(0, 1, 2)
    for seed in range(6):
        g, y, noise, coef = _rows_with_extra(seed)
        start = np.array([[-RATE], [RATE], [coef], [0.0]])
        lost = dropped_evidence(g, y, true, support(0, 1), start, noise)
        assert lost[0] > 3 * KEEP_EVIDENCE
        spurious = dropped_evidence(g, y, support(0, 1, 2, 3), true, start, noise)
        assert spurious[0] < KEEP_EVIDENCE - 5.0
        assert np.isnan(dropped_evidence(g, y, true, true, start, noise)).all()
        # The score is the rescoring's: the chi-square plus log(rows) per term (four
        # candidates: no search penalty), the fall in units of the larger support's
        # residuals where they exceed the rows.
        rows = g.shape[0]
        chi2 = [gls_score(g, y[:, 0], s[:, 0], start[:, 0], noise, 0)[0]
                for s in (support(0, 1, 2, 3), true)]  # fmt: skip
        fall = (chi2[1] - chi2[0]) / max(1.0, chi2[0] / rows)
        assert np.isclose(spurious[0], fall - np.log(rows), rtol=1e-12)
        assert np.isnan(dropped_evidence(g, y, true, support(1, 2), start, noise)).all()
        smaller = [v * 1e-3 for v in noise.columns.values]
        tiny = RowNoise(noise.weights, noise.slopes, LibraryNoise(4, noise.columns.cols, smaller),
                        noise.target * 1e-3)  # fmt: skip
        assert np.isnan(dropped_evidence(g, y, true, support(0, 1), start, tiny)).all()
        # A term that, put back, would contribute less than tol of its equation (the
        # final selection's measure, under which it drops any term) does not count.
        xi = gls_score(g, y[:, 0], true[:, 0], start[:, 0], noise, 0)[1]
        share = abs(xi[2]) * np.linalg.norm(g[:, 2]) / np.linalg.norm(y[:, 0])
        assert dropped_evidence(g, y, true, support(0, 1), start, noise, tol=share / 2) == lost
        assert np.isnan(dropped_evidence(g, y, true, support(0, 1), start, noise, tol=2 * share))


def test_the_contested_drop_bar_keeps_its_false_alarm_rate_at_every_library_size():
    """The rescoring's search takes a spurious term as the best of the library's
    candidates: with no real term to find, each lowers the chi-square by chi-square
    with one degree of freedom, and the best of ``terms - kept`` of them beats a fixed
    bar ever more often as the library grows with the channels.  With the extended
    BIC's penalty the bar's false-alarm rate per equation stays below 1 % from four
    terms to ten thousand (without it, 18 % at the 5151 terms of 100 states, degree
    2, and 1000 rows)."""
    import scipy.stats

    from robust_sindy.selection.variables import KEEP_EVIDENCE, search_penalty

    def rate(rows, terms, kept, extra):
        bar = np.log(rows) + KEEP_EVIDENCE + extra
        return 1.0 - scipy.stats.chi2.cdf(bar, 1) ** (terms - kept)

    for rows in (50, 300, 1000, 10_000, 100_000):
        for terms in (4, 20, 35, 91, 286, 1000, 5151, 10_000):
            for kept in (1, 3, 10):
                if terms > kept:
                    assert rate(rows, terms, kept, search_penalty(rows, terms, kept)) < 0.01
    assert rate(1000, 5151, 3, 0.0) > 0.15
    # A library smaller than the root of the rows adds nothing to the BIC.
    assert search_penalty(1000, 30, 3) == 0.0 and search_penalty(1000, 35, 3) > 0.0
    assert search_penalty(1, 10, 1) == search_penalty(100, 1, 0) == 0.0


def _spurious_columns(g, w, count, seed):
    """``g`` with ``count`` more columns: smooth noise-free signals (depending on no
    state), none in the target."""
    t = np.arange(w.shape[1], dtype=float) / w.shape[1]
    rng = np.random.default_rng(1000 + seed)
    freq, phase = rng.uniform(1.0, 40.0, (2, count)), rng.uniform(0, 2 * np.pi, (2, count))
    signals = np.sin(freq[0] * t[:, None] + phase[0]) + np.cos(freq[1] * t[:, None] + phase[1])
    return np.column_stack([g, w @ signals])


def test_a_spurious_term_picked_from_many_under_understated_noise_does_not_contest_a_drop():
    """Where the noise model understates the states' noise (here by 15 to 20 %: the
    true support's chi-square 1.2 to 1.6 times the rows, as a glitched record's was),
    every fall in chi-square is inflated with it; and the term a search adds is the
    best of the library's candidates.  The best of 150 spurious columns, dropped from
    the true support plus it, is not contested in any seed (the fall read in units of
    the residuals' spread, against the extended BIC's bar; the bar on the plain fall
    was crossed in one of these seeds), and how much the noise is understated does
    not change the evidence.  A true term dropped is contested far beyond the bar in
    every seed."""
    from robust_sindy.selection.variables import KEEP_EVIDENCE, dropped_evidence

    for seed in range(8):
        g, y, noise, coef = _rows_with_extra(seed)
        g = _spurious_columns(g, noise.weights, 150, seed)
        p = g.shape[1]
        true = np.zeros((p, 1), dtype=bool)
        true[[0, 1, 2], 0] = True
        start = np.zeros((p, 1))
        start[[0, 1, 2], 0] = [-RATE, RATE, coef]
        lost = true.copy()
        lost[2, 0] = False
        found = []
        for factor in (0.8, 0.85):
            scaled = [factor * v for v in noise.columns.values]
            low = LibraryNoise(p, noise.columns.cols, scaled)
            under = RowNoise(noise.weights, noise.slopes, low, factor * noise.target)
            own = gls_score(g, y[:, 0], true[:, 0], start[:, 0], under, 0)[0]
            assert own > 1.2 * g.shape[0]  # the noise understated
            falls = []
            for j in range(4, p):
                back = true[:, 0].copy()
                back[j] = True
                falls.append(own - gls_score(g, y[:, 0], back, start[:, 0], under, 0)[0])
            best = true.copy()
            best[4 + int(np.argmax(falls)), 0] = True
            found.append(dropped_evidence(g, y, best, true, start, under)[0])
            assert found[-1] < KEEP_EVIDENCE - 5.0
        assert np.isclose(found[0], found[1], rtol=1e-6, atol=1e-6)
        # (By 15 %: by a fifth, the loss of the term would put the reported support's
        # residuals beyond what the noise explains in one seed, and the drop unscored.)
        assert dropped_evidence(g, y, true, lost, start, under)[0] > 3 * KEEP_EVIDENCE


def test_the_warning_on_contested_drops_fires_above_keep_evidence_only():
    import dataclasses

    from robust_sindy import HuberSINDy, PolynomialLibrary
    from robust_sindy.selection.variables import KEEP_EVIDENCE

    t = 0.02 * np.arange(1500)
    x = np.column_stack([np.sin(t), np.cos(t)]) + 0.01 * np.random.default_rng(0).normal(
        size=(t.size, 2)
    )
    strong = HuberSINDy(library=PolynomialLibrary(degree=2), formulation="strong").fit(x, t)
    assert np.isnan(strong.diagnostics_.dropped_evidence).all()
    weak = HuberSINDy(library=PolynomialLibrary(degree=2), formulation="weak").fit(x, t)
    d = weak.diagnostics_
    assert d.dropped_evidence.shape == (2,)
    assert "score against the final selection's drops" in str(d)
    for value, fires in ((np.nan, False), (-3.0, False), (KEEP_EVIDENCE - 0.1, False),
                         (KEEP_EVIDENCE + 0.1, True), (250.0, True)):  # fmt: skip
        evidence = np.array([np.nan, value])
        found = [m for m in dataclasses.replace(d, dropped_evidence=evidence).problems()
                 if "prefers to keep" in m]  # fmt: skip
        assert len(found) == int(fires)
        if fires:
            assert found[0].startswith("equations [1]:") and f"{value:.3g}" in found[0]


def test_a_term_standing_in_for_another_through_a_nearly_constant_factor_is_not_silent():
    # HyperJha at 8 % noise, states only (the weak form): `x1*x2` (x2 near 24.5, spread
    # 7.9) can stand in for `-x1` in `(x1)'`.  On this draw the selection chose it, the
    # BIC put the next other model 3422 behind, and the score under the noise the terms
    # carry the true support only 1.3: the data do not decide, and the close-runner-up
    # warning says so.
    # Either the support is exact or that warning names the equation.
    import dataclasses
    import warnings

    from robust_sindy import HuberSINDy, PolynomialLibrary, zoo
    from robust_sindy.flows import polynomial_system, simulate_system

    system = polynomial_system("HyperJha")
    t, x, _ = simulate_system(system, 2000, 7)
    params = dataclasses.replace(zoo.ZOO_CONTAMINATION, base_noise=0.08)
    noisy, _ = zoo.contaminate_family(x, "clean", np.random.default_rng([7, 7, 11]), params)
    model = HuberSINDy(library=PolynomialLibrary(degree=system.degree))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(noisy, t)
    wrong = [k for k in range(4) if not np.array_equal(model.coef_[k] != 0, system.coef[:, k] != 0)]
    close = [str(w.message) for w in caught if getattr(w.message, "kind", "") == "close runner-up"]
    for k in wrong:
        assert any(f"equations [{k}" in m or f", {k}" in m for m in close), (wrong, close)
    if wrong:
        assert model.diagnostics_.rival_by_noise[wrong].all()


def _chi2_by_lstsq(gw, yw, support):
    out = []
    for j in np.flatnonzero(~support & np.any(gw != 0, axis=0)):
        on = np.flatnonzero(support | (np.arange(gw.shape[1]) == j))
        sol = np.linalg.lstsq(gw[:, on], yw, rcond=None)[0]
        r = yw - gw[:, on] @ sol
        out.append((float(r @ r), int(j)))
    return out


def _random_columns(rng, rows, terms, spare, most):
    """Columns of very different scales (the last one zero) and a random support of
    fewer than ``most`` of the first ``p - spare`` columns: rows, p, columns, support."""
    rows, p = int(rng.integers(*rows)), int(rng.integers(*terms))
    gw = rng.standard_normal((rows, p)) * np.exp(rng.normal(0.0, 2.0, p))
    gw[:, p - 1] = 0.0
    support = np.zeros(p, dtype=bool)
    support[
        rng.choice(p - spare, int(rng.integers(0, min(p - spare - 1, most))), replace=False)
    ] = True
    return rows, p, gw, support


def test_the_searchs_ranking_of_added_terms_is_least_squares_on_each_augmented_support():
    """One factorisation of the support ranks every added term as a least-squares fit
    on the support and that term would (columns of very different scales, empty and
    rank-deficient supports, a zero column, a target nearly in the span)."""
    rng = np.random.default_rng(3)
    for trial in range(60):
        rows, p, gw, support = _random_columns(rng, (15, 300), (3, 40), spare=1, most=7)
        if trial % 4 == 0 and support.sum() >= 2:  # a support holding the same term twice
            first, second = np.flatnonzero(support)[:2]
            gw[:, second] = 3.0 * gw[:, first]
        level = 1e-6 if trial % 3 == 0 else 1.0
        yw = gw[:, :2] @ rng.standard_normal(2) + level * rng.standard_normal(rows)
        ours, reference = _added_chi2(gw, yw, support), _chi2_by_lstsq(gw, yw, support)
        assert [j for _, j in ours] == [j for _, j in reference]
        assert p - 1 not in [j for _, j in ours]
        a, b = np.array([c for c, _ in ours]), np.array([c for c, _ in reference])
        assert np.allclose(a, b, rtol=1e-6, atol=1e-9 * float(yw @ yw))


def test_the_rescoring_is_the_same_on_one_thread_and_on_several(monkeypatch):
    """The equations are scored side by side: each writes only its own entries."""
    g, y, noise = _rows(4, both=True)
    pool = np.array([[[0.0, 1.0], [1.0, 0.0]], [[-RATE, 0.0], [RATE, 1.0]]])
    chosen = np.array([[0.0, 0.0], [1.0, 1.0]])
    monkeypatch.setattr(_threads, "threads", lambda: 2)
    several = rescore_supports(g, y, chosen, [pool], noise, margin=6.0)
    monkeypatch.setattr(_threads, "threads", lambda: 1)
    one = rescore_supports(g, y, chosen, [pool], noise, margin=6.0)
    for name in ("support", "switched", "chosen_score", "best_score", "candidates", "trusted"):
        assert np.array_equal(getattr(several, name), getattr(one, name), equal_nan=True), name
    for a, b_ in zip(several.scored, one.scored, strict=True):
        assert all(np.array_equal(u, v) for u, v in zip(a, b_, strict=True))


def _pairs_by_lstsq(gw, yw, support):
    """``{(j, l): chi-square}`` of the least-squares fit on the support and each pair."""
    out = {}
    cand = np.flatnonzero(~support & np.any(gw != 0, axis=0))
    for a in range(cand.size):
        for b in range(a + 1, cand.size):
            on = np.flatnonzero(support | np.isin(np.arange(gw.shape[1]), cand[[a, b]]))
            sol = np.linalg.lstsq(gw[:, on], yw, rcond=None)[0]
            r = yw - gw[:, on] @ sol
            out[(int(cand[a]), int(cand[b]))] = float(r @ r)
    return out


def test_the_searchs_ranking_of_added_pairs_is_least_squares_on_each_augmented_support():
    """One factorisation of the support ranks every pair of added terms as a
    least-squares fit on the support and the pair would: the best pairs returned are
    the best by brute force, with their chi-squares (columns of very different scales,
    empty supports, a zero column); a pair of one column repeated is never returned."""
    rng = np.random.default_rng(5)
    for _ in range(40):
        rows, p, gw, support = _random_columns(rng, (20, 200), (6, 25), spare=3, most=6)
        free = np.flatnonzero(~support[: p - 1])
        # a small difference of two large columns: each alone explains little
        gw[:, free[1]] = (
            gw[:, free[0]] + 1e-2 * rng.standard_normal(rows) * np.abs(gw[:, free[0]]).max()
        )
        yw = gw[:, free[0]] - gw[:, free[1]] + 1e-3 * rng.standard_normal(rows)
        reference = _pairs_by_lstsq(gw, yw, support)
        ours, ranked = _added_pairs(gw, yw, support, 3)
        assert ranked == len(reference)
        assert [(j, k) for _, j, k in ours][:1] == [min(reference, key=reference.get)]
        best = sorted(reference.values())[: len(ours)]
        assert np.allclose([c for c, _, _ in ours], best, rtol=1e-6, atol=1e-9 * float(yw @ yw))
        for chi2, j, k in ours:
            assert np.isclose(chi2, reference[(j, k)], rtol=1e-6, atol=1e-9 * float(yw @ yw))
    gw = rng.standard_normal((50, 4))
    gw[:, 3] = 2.0 * gw[:, 2]
    ours, _ = _added_pairs(gw, gw[:, 2] + gw[:, 0], np.zeros(4, dtype=bool), 6)
    assert (2, 3) not in [(j, k) for _, j, k in ours]


def _unit_noise(rows, p):
    """A noise model whose covariance is the identity: rows of unit, independent noise
    in the target only, so that the score is the least-squares chi-square."""
    weights = scipy.sparse.csr_array((rows, rows))
    slopes = scipy.sparse.csr_array(np.eye(rows))
    columns = LibraryNoise(p, [np.arange(0)], [np.zeros((rows, 0))])
    return RowNoise(weights, slopes, columns, np.array([1.0]))


def _suppressor(rng, rows=400, p=14, size=40.0):
    """Columns 0 and 1 nearly equal (a large common part), the target their difference
    (of chi-square about ``size**2``) plus unit noise: either column alone explains
    next to nothing of it, the two together all of it."""
    g = rng.standard_normal((rows, p))
    common = 1000.0 * rng.standard_normal(rows)
    apart = size / np.sqrt(rows) * rng.standard_normal(rows)
    g[:, 0], g[:, 1] = common + apart, common
    return g, apart + rng.standard_normal(rows)


def test_the_search_adds_two_terms_together_where_neither_alone_lowers_the_score(monkeypatch):
    """Where the target is a small difference of two large, nearly equal columns,
    single additions rarely lower the score: the search adds the pair, and the
    rescoring takes a support holding it, on every one of 20 draws (without pair moves
    on at most half of them)."""
    from robust_sindy.selection import variables

    found, without = 0, 0
    for seed in range(20):
        g, y = _suppressor(np.random.default_rng(seed))
        noise = _unit_noise(*g.shape)
        chosen = np.zeros((g.shape[1], 1))
        chosen[5] = 1.0  # a wrong single term
        out = rescore_supports(g, y[:, None], chosen, [chosen[None]], noise, margin=6.0)
        found += bool(out.switched[0] and out.support[:2, 0].all())
        with monkeypatch.context() as m:
            m.setattr(variables, "_added_pairs", lambda *a: ([], 0))
            alone = rescore_supports(g, y[:, None], chosen, [chosen[None]], noise, margin=6.0)
        without += bool(alone.support[:2, 0].all())
    assert found == 20
    assert without <= 10


def test_pair_moves_do_not_add_pairs_that_explain_nothing(monkeypatch):
    """On a target of pure noise, the best of the many pairs lowers the chi-square by
    about 2 log(pairs) by chance: charged for it, the search ends where it ends without
    pair moves on at least 29 of 30 draws."""
    from robust_sindy.selection import variables

    same = 0
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        g = rng.standard_normal((300, 30))
        y = rng.standard_normal(300)
        noise = _unit_noise(*g.shape)
        chosen = np.zeros((30, 1))
        chosen[0] = 1e-3
        out = rescore_supports(g, y[:, None], chosen, [chosen[None]], noise, margin=6.0)
        with monkeypatch.context() as m:
            m.setattr(variables, "_added_pairs", lambda *a: ([], 0))
            alone = rescore_supports(g, y[:, None], chosen, [chosen[None]], noise, margin=6.0)
        same += np.array_equal(out.support, alone.support)
    assert same >= 29
