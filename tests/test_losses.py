import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from robust_sindy import huber, huber_prox, huber_psi, soft_threshold

finite = st.floats(-1e3, 1e3, allow_nan=False)
positive = st.floats(1e-3, 1e3)


@given(v=finite, delta=positive, rho=positive)
def test_huber_prox_satisfies_its_optimality_condition(v, delta, rho):
    x = huber_prox(np.array(v), delta, rho)
    # psi_delta(x) + rho (x - v) = 0 characterises the prox of H_delta / rho.
    assert abs(huber_psi(x, delta) + rho * (x - v)) <= 1e-9 * max(1.0, abs(rho * v))


@given(v=finite, delta=positive, rho=positive)
def test_huber_prox_is_continuous_and_nonexpansive(v, delta, rho):
    pair = np.array([v, v + 1e-7 * max(1.0, abs(v))])
    a, b = huber_prox(pair, delta, rho)
    # |prox(u) - prox(v)| <= |u - v|, up to rounding at the magnitude of v.
    assert abs(b - a) <= (pair[1] - pair[0]) + 1e-13 * max(1.0, abs(v))


def test_huber_prox_breakpoint_matches_corrected_formula():
    delta, rho = 0.5, 2.0
    edge = delta * (1 + rho) / rho
    v = np.array([0.9 * edge, 1.1 * edge, -1.1 * edge])
    expected = np.array([rho * v[0] / (1 + rho), v[1] - delta / rho, v[2] + delta / rho])
    np.testing.assert_allclose(huber_prox(v, delta, rho), expected)


def test_huber_prox_differs_from_the_papers_printed_formula():
    # Paper Eq. 11 (erratum E2): outer branch sign(a) max(0, |a| - 1/rho). With delta != 1 it
    # is not the prox; our corrected form must differ from it there.
    delta, rho, v = 0.2, 1.0, 3.0
    printed = np.sign(v) * max(0.0, abs(v) - 1 / rho)
    assert not np.isclose(huber_prox(np.array(v), delta, rho), printed)


@given(v=finite, t=st.floats(0, 1e3))
def test_soft_threshold_is_the_prox_of_the_absolute_value(v, t):
    x = float(soft_threshold(np.array(v), t))
    # 0 in x - v + t * d|x|
    if x != 0:
        assert abs(x - v + t * np.sign(x)) <= 1e-9 * max(1.0, abs(v))
    else:
        assert abs(v) <= t


@given(a=finite, delta=positive)
def test_huber_value_and_derivative_agree(a, delta):
    h = 1e-6 * max(1.0, abs(a))
    numeric = (huber(np.array(a + h), delta) - huber(np.array(a - h), delta)) / (2 * h)
    assert abs(numeric - huber_psi(np.array(a), delta)) <= 1e-4 * max(1.0, delta)


def test_squared_loss_is_the_infinite_delta_limit():
    a = np.linspace(-5, 5, 11)
    np.testing.assert_allclose(huber(a, np.inf), a**2 / 2)
    np.testing.assert_allclose(huber_prox(a, np.inf, 3.0), 3.0 * a / 4.0)
