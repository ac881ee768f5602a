"""Errors in the variables: the first-order bias and the terms it drops."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.selection.bias import BIAS_MARGIN, drop_biased_terms, first_order_bias, noise_gram
from robust_sindy.systems import Lorenz


def _problem(seed=0, m=400, p=5):
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=(m, p)) + rng.normal(size=(1, p))
    coef = np.array([1.5, 0.0, -0.7, 0.02, 0.0])[:p]
    noise = [0.1 * rng.normal(size=(m, p)) for _ in range(2)]
    return theta, coef, noise


def test_the_gram_of_noise_columns_is_the_sum_of_their_grams():
    _, _, noise = _problem()
    assert np.allclose(noise_gram(noise), noise[0].T @ noise[0] + noise[1].T @ noise[1])


def test_the_bias_is_the_absolute_first_order_bias_on_the_support():
    theta, coef, noise = _problem()
    gram = noise_gram(noise)
    beta = first_order_bias(theta, coef, gram)
    sel = np.flatnonzero(coef)
    a = theta[:, sel]
    m = np.linalg.solve(a.T @ a, gram[np.ix_(sel, sel)])
    assert np.allclose(beta[sel], np.abs(m @ coef[sel]))
    bound = first_order_bias(theta, coef, gram, signed=False)
    assert np.allclose(bound[sel], np.abs(m) @ np.abs(coef[sel]))
    assert np.all(beta <= bound + 1e-15)
    assert np.all(beta[coef == 0] == 0)
    # rank-deficient selected columns: nothing can be vouched for
    theta[:, 2] = theta[:, 0]
    assert np.all(np.isinf(first_order_bias(theta, coef, gram)[sel]))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=5, max_size=5),
    st.floats(-3, 3),
    st.integers(0, 1000),
)
def test_the_ratio_to_the_bound_is_unit_free(log_cols, log_y, seed):
    theta, coef, noise = _problem(seed)
    with np.errstate(invalid="ignore"):
        ratio = np.abs(coef) / first_order_bias(theta, coef, noise_gram(noise))
    d = 10.0 ** np.array(log_cols)
    # columns in other units: coefficients scale by 1/d (and by the target's unit)
    scaled = first_order_bias(theta * d, coef / d * 10.0**log_y, noise_gram([a * d for a in noise]))
    with np.errstate(invalid="ignore"):
        ratio_scaled = np.abs(coef / d * 10.0**log_y) / scaled
    sel = coef != 0
    assert np.allclose(ratio[sel], ratio_scaled[sel], rtol=1e-8)


def test_only_terms_within_the_margin_of_their_bias_are_dropped():
    rng = np.random.default_rng(3)
    theta, coef, noise = _problem(1, m=2000)
    y = theta @ coef + 1e-3 * rng.normal(size=2000)
    gram = noise_gram(noise)
    fitted = np.linalg.lstsq(theta[:, coef != 0], y, rcond=None)[0]
    start = np.zeros(5)
    start[coef != 0] = fitted
    with np.errstate(invalid="ignore"):
        ratio = np.abs(start) / first_order_bias(theta, start, gram)
    assert ratio[3] < BIAS_MARGIN <= min(ratio[0], ratio[2])  # the small term is within
    new, ratios = drop_biased_terms(theta, y[:, None], start[:, None], 1.0, gram)
    assert np.isfinite(ratios[:, 0]).tolist() == [False, False, False, True, False]
    assert np.isclose(ratios[3, 0], ratio[3])
    assert new[3, 0] == 0 and new[0, 0] != 0 and new[2, 0] != 0
    # without noise in the library nothing is dropped
    same, none = drop_biased_terms(theta, y[:, None], start[:, None], 1.0, 0.0 * gram)
    assert np.isnan(none).all() and np.array_equal(same != 0, start[:, None] != 0)


@pytest.mark.parametrize("subsets", [False, True])
def test_heavy_tailed_state_noise_does_not_select_bias_terms(subsets, monkeypatch):
    # Student-t noise (2 degrees of freedom) on every state, exact derivatives: the
    # noisy library biases the fit of (x)' towards x*z and y*z.  The lam path's
    # candidates carry those terms and the criterion keeps them, so the bias step
    # drops them; a best-subset candidate without them scores better still (the bias
    # step may still drop a term of the path's candidates).
    import functools

    import robust_sindy.selection.choice

    monkeypatch.setattr(
        robust_sindy.selection.choice,
        "select",
        functools.partial(robust_sindy.selection.choice.select, subsets=subsets),
    )
    data = Lorenz().generate(t_end=20.0, dt=0.01)
    rng = np.random.default_rng(0)
    x = data.x + 0.01 * data.x.std(axis=0) * rng.standard_t(2, size=data.x.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = HuberSINDy().fit(x, data.t, x_dot=data.x_dot)
    true = np.zeros((3, 10), dtype=bool)
    true[0, [1, 2]] = true[1, [1, 2, 6]] = true[2, [3, 5]] = True
    assert np.array_equal(model.support_, true)
    assert subsets or model.bias_dropped_.any()
    assert model.selection_.from_subsets.any() == subsets
    assert np.array_equal(np.isfinite(model.diagnostics_.bias_ratio), model.bias_dropped_)
    assert not (model.bias_dropped_ & model.support_).any()


def test_clean_states_drop_nothing():
    data = Lorenz().generate(t_end=10.0)
    model = HuberSINDy(library=PolynomialLibrary(degree=2)).fit(data.x, data.t, x_dot=data.x_dot)
    assert not model.bias_dropped_.any()


def test_a_dropped_term_larger_than_its_bias_is_reported():
    import dataclasses

    data = Lorenz().generate(t_end=5.0)
    d = HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot).diagnostics_
    assert d.problems() == []
    ratio = np.full((3, 10), np.nan)
    ratio[1, 4] = 0.6  # explained by the bias: dropped without a word
    assert dataclasses.replace(d, bias_ratio=ratio).problems() == []
    ratio[2, 7] = 1.8  # larger than the bias, within the margin: may be real
    (message,) = dataclasses.replace(d, bias_ratio=ratio).problems()
    assert message.startswith("equations [2]: 1 terms were dropped") and "may be real" in message


def test_one_step_contributions_are_exact_for_least_squares_and_close_for_huber():
    from robust_sindy import fit
    from robust_sindy.selection.refit import one_step_contributions

    rng = np.random.default_rng(5)
    theta = rng.normal(size=(500, 6))
    # a small missing term (the kind the check is for): one step is close to the refit
    y = theta @ np.array([2.0, 0.0, -1.0, 0.03, 0.0, 0.0]) + 0.1 * rng.standard_t(3, size=500)
    for delta, rtol in ((1e6, 1e-8), (0.15, 0.1)):
        coef = np.zeros(6)
        coef[[0, 2]] = fit(theta[:, [0, 2]], y, delta=delta, lam=0.0).coef.ravel()
        steps = one_step_contributions(theta, y[:, None], coef[:, None], delta)[:, 0]
        assert np.isnan(steps[[0, 2]]).all()
        for j in (1, 3, 4, 5):
            full = fit(theta[:, [0, 2, j]], y, delta=delta, lam=0.0).coef.ravel()[2]
            exact = abs(full) * np.linalg.norm(theta[:, j]) / np.linalg.norm(y)
            assert np.isclose(steps[j], exact, rtol=rtol, atol=1e-4 * rtol), (delta, j)


def test_biases_of_opposite_signs_cancel_and_the_bound_ignores_it():
    # Orthonormal columns, so M is the noise Gram itself: term 2 gets a * xi_0 from
    # term 0 and -a * xi_1 from term 1, which cancel when xi_0 = xi_1.
    rng = np.random.default_rng(0)
    theta = np.linalg.qr(rng.normal(size=(300, 3)))[0]
    coef = np.array([5.0, 5.0, 0.1])
    a = 0.01
    gram = np.zeros((3, 3))
    gram[2, 0], gram[2, 1] = a, -a
    gram[0, 2], gram[1, 2] = a, -a
    y = (theta @ coef)[:, None]
    assert first_order_bias(theta, coef, gram)[2] == pytest.approx(0.0, abs=1e-15)
    assert first_order_bias(theta, coef, gram, signed=False)[2] == pytest.approx(10 * a)
    kept, none = drop_biased_terms(theta, y, coef[:, None], 1.0, gram)
    assert np.all(kept[:, 0] != 0) and np.isnan(none).all()
    dropped, ratio = drop_biased_terms(theta, y, coef[:, None], 1.0, gram, signed=False)
    assert dropped[2, 0] == 0 and ratio[2, 0] == pytest.approx(1.0)


# --------------------------------------------------------------------------------------
# the truncation error of estimated derivatives


def test_truncation_bias_is_the_visible_part_of_the_projection_of_the_error():
    from robust_sindy.selection.bias import truncation_bias
    from robust_sindy.selection.significance import VISIBLE, robust_t

    rng = np.random.default_rng(4)
    theta = rng.normal(size=(600, 4))
    coef = np.array([1.0, 0.3, 0.0, 0.05])
    # An error along term 1 (a smooth one would be a truncation error), plus noise.
    error = 0.25 * theta[:, 1] + 0.01 * rng.normal(size=600)
    beta = truncation_bias(theta, error, coef)
    sel = np.flatnonzero(coef)
    b = np.linalg.lstsq(theta[:, sel], error, rcond=None)[0]
    full = np.zeros(4)
    full[sel] = b
    se = np.abs(b) / robust_t(theta, error, full, np.inf)[sel]
    assert np.allclose(beta[sel], np.maximum(np.abs(b) - VISIBLE * se, 0.0))
    assert beta[2] == 0.0 and 0.24 < beta[1] < 0.25 and beta[0] < 0.01
    # Noise alone is not a bias; collinear selected columns vouch for nothing.
    assert np.all(truncation_bias(theta, 0.01 * rng.normal(size=600), coef) < 2e-3)
    twin = np.column_stack([theta, theta[:, 0]])
    assert np.all(np.isinf(truncation_bias(twin, error, np.append(coef, 1.0))[[0, 1, 3, 4]]))
    # Unit-free: rescaling a column rescales its coefficient and its bias alike.
    scaled = theta * np.array([1.0, 1e3, 1.0, 1e-3])
    beta_s = truncation_bias(scaled, error, coef / np.array([1.0, 1e3, 1.0, 1e-3]))
    assert np.allclose(beta_s * np.array([1.0, 1e3, 1.0, 1e-3]), beta, rtol=1e-6)


def _coarse_lotka_volterra(dt, seed=0, m=1500):
    from scipy.integrate import solve_ivp

    def rhs(_t, v):
        return [2 / 3 * v[0] - 4 / 3 * v[0] * v[1], v[0] * v[1] - v[1]]

    t = dt * np.arange(m)
    sol = solve_ivp(rhs, (0, t[-1]), [1.5, 0.7], t_eval=t, rtol=1e-10, atol=1e-10, method="DOP853")
    x = sol.y.T
    x = x + 1e-3 * x.std(axis=0) * np.random.default_rng(seed).normal(size=x.shape)
    truth = np.zeros((2, 6), dtype=bool)  # 1, x, y, x^2, x y, y^2
    truth[0, [1, 4]] = truth[1, [2, 4]] = True
    return t, x, truth


def test_coarse_sampling_truncation_terms_are_dropped_not_selected_silently():
    # Lotka-Volterra sampled about 23 times per period, clean states, no derivatives:
    # the derivatives' truncation error is systematic, and without this check spurious
    # terms were selected with no warning (seeds 0-3 alike).  The strong form's check
    # (with no outliers in the states, formulation="auto" integrates instead).
    t, x, truth = _coarse_lotka_volterra(0.35, seed=0)
    model = HuberSINDy(library=PolynomialLibrary(degree=2), formulation="strong")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t)
    assert np.array_equal(model.support_, truth)
    ratio = model.truncation_ratio_
    assert np.isfinite(ratio).any() and not np.isfinite(ratio[truth]).any()
    assert np.array_equal(model.diagnostics_.truncation_ratio, ratio, equal_nan=True)
    # A dropped term above its bias is reported, as a note (not a warning: alone, such
    # drops were spurious terms on right answers).
    noted = any(kind == "truncation drops" for kind, _ in model.diagnostics_.notes())
    assert noted == bool((np.nan_to_num(ratio) >= 1).any())
    assert not any("truncation error" in str(w.message) for w in caught)
    # Densely sampled, the same system has no truncation error to speak of.
    t, x, truth = _coarse_lotka_volterra(0.065, m=2000)
    dense = HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, t)
    assert np.array_equal(dense.support_, truth) and not np.isfinite(dense.truncation_ratio_).any()


def test_measured_derivatives_have_no_truncation_check():
    t, x, _ = _coarse_lotka_volterra(0.35)
    a, b = x[:, 0], x[:, 1]
    x_dot = np.column_stack([2 / 3 * a - 4 / 3 * a * b, a * b - b])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, t, x_dot=x_dot)
    assert not np.isfinite(model.truncation_ratio_).any()


def test_the_noise_factor_is_what_the_residuals_allow_and_unit_free():
    from robust_sindy.selection.bias import NOISE_SLACK, carried_noise, residual_noise_factor

    rng = np.random.default_rng(3)
    carried = np.exp(rng.normal(size=4000))  # heteroscedastic, as through a library
    noise = carried * rng.normal(size=4000)
    # residuals that carry the noise (and more) allow all of it
    assert residual_noise_factor(noise, carried) == 1.0
    assert residual_noise_factor(3 * noise + rng.normal(size=4000), carried) == 1.0
    # residuals a thousand times smaller: the noise was measured too large
    small = residual_noise_factor(1e-3 * noise, carried)
    assert small == pytest.approx(NOISE_SLACK * 1e-6, rel=0.15)
    assert residual_noise_factor(1e-3 * noise * 7.0, carried * 7.0) == pytest.approx(small)
    assert residual_noise_factor(noise, np.zeros(4000)) == 1.0  # nothing carried
    columns = [rng.normal(size=(50, 3)), rng.normal(size=(50, 3))]
    coef = np.array([1.0, 0.0, -2.0])
    expected = np.sqrt(sum((a @ coef) ** 2 for a in columns))
    np.testing.assert_allclose(carried_noise(columns, coef), expected)


def test_coarse_clean_states_with_measured_derivatives_keep_their_terms():
    # Lorenz sampled about 10 times per period, clean states, measured derivatives: the
    # temporal screen cannot resolve the states and measures their noise ~100 times too
    # large; taken at that level, the errors-in-variables check dropped a true term
    # (seeds 0-2 alike), where least squares is right.  The residuals show the noise
    # is not there.
    from scipy.integrate import solve_ivp

    def rhs(_t, v):
        return [10 * (v[1] - v[0]), v[0] * (28 - v[2]) - v[1], v[0] * v[1] - 8 / 3 * v[2]]

    t = 0.08 * np.arange(2000)
    sol = solve_ivp(rhs, (0, t[-1] + 5), [-8, 7, 27], t_eval=t + 5, rtol=1e-10, atol=1e-10)
    x = sol.y.T
    x_dot = np.array([rhs(0, v) for v in x])
    x = x + 1e-3 * x.std(axis=0) * np.random.default_rng(0).normal(size=x.shape)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, t, x_dot=x_dot)
    truth = np.zeros((3, 10), dtype=bool)
    truth[0, [1, 2]] = truth[1, [1, 2, 6]] = truth[2, [3, 5]] = True
    assert np.array_equal(model.support_, truth) and not model.bias_dropped_.any()
    factor = model.diagnostics_.noise_factor
    assert np.array_equal(factor, model.noise_factor_) and np.all(factor < 1e-2)
    # Nor does the library noise the residuals allow raise a warning (the measured
    # noise, 200 % of the library's signal along its weakest direction, did).
    assert model.library_noise_[1] > 1.0 > 0.15 > model.diagnostics_.library_noise
    assert not any("carried through the library" in str(w.message) for w in caught)


def test_each_state_keeps_the_noise_the_equations_it_enters_allow():
    from robust_sindy.selection.bias import state_noise_factors

    rng = np.random.default_rng(0)
    g = rng.normal(size=(200, 2))
    noise = [np.column_stack([g[:, 0], 0 * g[:, 0]]), np.column_stack([0 * g[:, 1], g[:, 1]])]
    # state 0 carries all of equation 0's noise and half of equation 1's; state 1 the rest
    coef = np.array([[1.0, 1.0], [0.0, 1.0]])
    coef[1, 1] *= np.linalg.norm(g[:, 0]) / np.linalg.norm(g[:, 1])
    np.testing.assert_allclose(state_noise_factors(noise, coef, np.array([0.01, 1.0])), [0.01, 1])
    # equation 1 allows a quarter: each state at most half of it (its share is half)
    np.testing.assert_allclose(state_noise_factors(noise, coef, np.array([1.0, 0.25])), [0.5, 0.5])
    # a state that no equation carries keeps its measured noise
    coef[1, 1] = 0.0
    np.testing.assert_allclose(state_noise_factors(noise, coef, np.array([1e-3, 1e-3])), [1e-3, 1])


def test_library_noise_stored_by_columns_computes_what_the_dense_arrays_do():
    # Each state's noise stored on the columns that depend on it: every quantity the
    # selection reads is the one the dense (m, p) arrays give.
    from robust_sindy.selection.bias import LibraryNoise, carried_noise, library_noise

    rng = np.random.default_rng(3)
    m, p = 300, 12
    dense = []
    for k in range(3):
        a = np.zeros((m, p))
        on = rng.choice(p, 4 + k, replace=False)
        a[:, on] = rng.normal(size=(m, on.size))
        dense.append(a)
    noise = LibraryNoise.of(dense)
    assert len(noise) == 3 and noise.shape == (m, p)
    assert sum(c.size for c in noise.cols) == 4 + 5 + 6
    np.testing.assert_array_equal(np.stack(noise.dense()), np.stack(dense))
    coef = rng.normal(size=(p, 2))
    expected = np.sqrt(sum((a @ coef) ** 2 for a in dense))
    np.testing.assert_allclose(noise.carried(coef), expected, rtol=1e-12)
    np.testing.assert_allclose(carried_noise(noise, coef[:, 0]), expected[:, 0], rtol=1e-12)
    np.testing.assert_allclose(noise.gram(), sum(a.T @ a for a in dense), rtol=1e-12, atol=1e-12)
    theta = rng.normal(size=(m, p))
    columns, along = library_noise(noise, theta)
    columns_d, along_d = library_noise(dense, theta)
    np.testing.assert_allclose(columns, columns_d, rtol=1e-12)
    assert along == pytest.approx(along_d, rel=1e-10)
    keep = rng.random(p) < 0.5
    np.testing.assert_array_equal(
        np.stack(noise.terms(keep).dense()), np.stack([a[:, keep] for a in dense])
    )
    rows = rng.random(m) < 0.3
    np.testing.assert_array_equal(
        np.stack(noise.rows(rows).dense()), np.stack([a[rows] for a in dense])
    )
    np.testing.assert_allclose(
        np.stack(noise.scaled([1.0, 2.0, 0.5]).dense()),
        np.stack([f * a for f, a in zip([1.0, 2.0, 0.5], dense, strict=True)]),
    )
    with pytest.raises(ValueError, match="noise"):
        LibraryNoise.of([np.zeros((m, p)), np.zeros((m, p + 1))])


def test_library_noise_reaching_a_sparse_model_leaves_out_only_states_it_cannot_reach():
    # The states whose columns a sparse model does not use contribute exactly zero and
    # are left out; a state with a value that is not finite is always in (0 * nan).
    from robust_sindy.selection.bias import LibraryNoise

    rng = np.random.default_rng(4)
    m, p = 50, 10
    cols = [np.array([0, 1]), np.array([1, 2, 3]), np.array([4, 5]), np.array([6])]
    values = [rng.normal(size=(m, c.size)) for c in cols]
    values[3][7, 0] = np.nan
    noise = LibraryNoise(p, cols, values)
    coef = np.zeros(p)
    coef[[2, 8]] = [1.5, -2.0]  # state 1's column 2; column 8 is no state's
    reached = noise.reaching(coef)
    assert [k for k, _ in reached] == [1, 3]
    every = noise.per_state(coef)
    for k, g in reached:
        np.testing.assert_array_equal(g, every[k])
    assert not every[0].any() and not every[2].any()


def test_library_noise_of_a_many_state_library_takes_a_few_libraries_of_memory():
    # A degree-2 library of n states: each state enters about 2 / n of the columns, so
    # the noise of all states is about twice the library, not n times; its values are
    # sigma_k dTheta/dx_k / scale, here checked against the exact derivative.
    from types import SimpleNamespace

    from robust_sindy.selection.bias import noise_columns

    rng = np.random.default_rng(0)
    n, m = 12, 200
    x = rng.normal(size=(m, n))
    library = PolynomialLibrary(degree=2).fit(x)
    theta = library.transform(x)
    scale = np.sqrt(np.mean(theta**2, axis=0))
    sigma = rng.uniform(0.01, 0.1, size=n)
    noise = noise_columns(library, x, SimpleNamespace(scale=sigma, repaired=x), scale)
    stored = sum(v.size for v in noise.values)
    assert stored <= 2.5 * theta.size  # n Theta = 12 Theta dense
    names = library.get_feature_names()
    j = names.index("x3*x7")
    k = 3
    c = list(noise.cols[k]).index(j)
    np.testing.assert_allclose(noise.values[k][:, c], sigma[k] * x[:, 7] / scale[j], rtol=1e-6)
    assert j not in noise.cols[5]


def test_library_noise_formed_on_the_columns_of_each_state_is_the_whole_librarys():
    # The central differences formed only on the columns that hold each state (where
    # the library tells them) are bit for bit those of the whole library's, for a
    # polynomial library alone and beside a library that cannot tell (whole library).
    from types import SimpleNamespace

    from robust_sindy import CustomLibrary, FourierLibrary
    from robust_sindy.library import BaseLibrary
    from robust_sindy.selection.bias import noise_columns

    class Opaque(BaseLibrary):  # the same library, which cannot tell its columns
        def __init__(self, library):
            self.library = library

        def transform(self, x):
            return self.library.transform(x)

    rng = np.random.default_rng(1)
    x = rng.normal(size=(150, 5)) + 1.0
    sigma = rng.uniform(0.01, 0.1, size=5)
    temporal = SimpleNamespace(scale=sigma, repaired=x)
    for library in (
        PolynomialLibrary(degree=3),
        PolynomialLibrary(degree=2, inputs=[0, 2]) + PolynomialLibrary(degree=1),
        PolynomialLibrary(degree=2) + CustomLibrary(["sin(x0) * x3"]),
        PolynomialLibrary(degree=1) + FourierLibrary(n_frequencies=2, inputs=[1, 4]),
    ):
        library.fit(x)
        scale = rng.uniform(0.5, 2.0, size=library.n_output_features_)
        fast = noise_columns(library, x, temporal, scale)
        whole = noise_columns(Opaque(library), x, temporal, scale)
        assert fast.p == whole.p == library.n_output_features_
        for k in range(5):
            np.testing.assert_array_equal(fast.cols[k], whole.cols[k])
            np.testing.assert_array_equal(fast.values[k], whole.values[k])
