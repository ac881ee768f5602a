"""Library terms that are exact linear combinations of earlier ones on the data."""

import warnings

import numpy as np
import pytest
import scipy.integrate
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_sindy import HuberSINDy, IdentificationWarning, PolynomialLibrary
from robust_sindy.selection.aliasing import aliased_columns


def test_a_column_in_the_span_of_earlier_ones_is_aliased_and_noise_is_not():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 3))
    combo = 2.0 * x[:, 0] - 0.5 * x[:, 2]
    theta = np.column_stack([x, combo, combo + 1e-6 * rng.normal(size=300)])
    assert aliased_columns(theta).tolist() == [False, False, False, True, False]
    # order decides which of a group stays: the first one
    assert aliased_columns(theta[:, [3, 0, 1, 2]]).tolist() == [False, False, False, True]
    # a zero column carries nothing
    assert aliased_columns(np.column_stack([x, np.zeros(300)])).tolist()[-1]


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=4, max_size=4))
def test_rescaling_columns_does_not_change_the_answer(log_scales):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 3))
    theta = np.column_stack([x, x[:, 0] + x[:, 1]])
    scaled = theta * 10.0 ** np.asarray(log_scales)
    assert aliased_columns(scaled).tolist() == [False, False, False, True]


def _oscillator_with_a_constant_state(level):
    """A damped cubic oscillator and a third state held at ``level``."""

    def rhs(_t, s):
        return [-0.1 * s[0] + 2.0 * s[1], -2.0 * s[0] - 0.1 * s[1] - 0.5 * s[0] ** 3]

    t = np.linspace(0.0, 20.0, 2001)
    sol = scipy.integrate.solve_ivp(rhs, (0, 20), [2.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-10)
    x2 = sol.y.T
    dx = np.array([rhs(0, s) for s in x2])
    x = np.column_stack([x2, np.full(t.size, level)])
    return t, x, np.column_stack([dx, np.zeros(t.size)])


@pytest.mark.parametrize("measured", [True, False])
@pytest.mark.parametrize("level", [0.3, -7.0])
def test_a_state_that_does_not_move_is_reported_and_its_terms_left_out(level, measured):
    t, x, dx = _oscillator_with_a_constant_state(level)
    model = HuberSINDy(library=PolynomialLibrary(degree=3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # estimated: the constant state's derivative is 0, not the rounding of its
        # differences blown up by standardisation
        model.fit(x, t, x_dot=dx if measured else None)
    names = model.get_feature_names()
    aliased = model.diagnostics_.aliased
    # every term with x2 is a multiple of a term without it
    assert aliased == [n for n in names if "x2" in n]
    assert model.aliased_.tolist() == ["x2" in n for n in names]
    assert not model.coef_[:, model.aliased_].any()
    messages = [str(w.message) for w in caught if issubclass(w.category, IdentificationWarning)]
    assert any("exact linear combinations" in m and "x2" in m for m in messages)
    # the oscillator is found from the remaining terms
    support = {names[j] for j in np.flatnonzero(model.coef_[0])}
    assert support == {"x0", "x1"}
    support = {names[j] for j in np.flatnonzero(model.coef_[1])}
    assert support == {"x0", "x1", "x0^3"}
    assert not model.coef_[2].any()


def test_a_library_without_exact_relations_reports_none():
    t, x, dx = _oscillator_with_a_constant_state(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", IdentificationWarning)
        model = HuberSINDy(library=PolynomialLibrary(degree=3)).fit(x[:, :2], t, x_dot=dx[:, :2])
    assert model.diagnostics_.aliased == []
    assert not model.aliased_.any()
