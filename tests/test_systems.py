"""Systems, RK4, the contamination model, metrics and differentiation."""

import numpy as np
import pytest
import scipy.integrate

from robust_sindy.metrics import iae, max_abs_error, support_scores
from robust_sindy.noise import contaminate, outlier_rows
from robust_sindy.simulate import rk4
from robust_sindy.systems import Drone, Lorenz
from robust_sindy.timeseries.differentiation import finite_difference, savgol_derivative


@pytest.mark.parametrize("system", [Lorenz(), Drone()])
def test_true_coefficients_reproduce_the_vector_field(system):
    data = system.generate(t_end=2.0)
    lib = system.library()
    z = data.x if data.u is None else np.hstack([data.x, data.u])
    theta = lib.fit_transform(z, input_names=system.input_names)
    np.testing.assert_allclose(theta @ system.true_coef(full=True), data.x_dot, atol=1e-11)
    assert system.true_coef().shape == (theta.shape[1], 3)


def test_lorenz_sign_and_initial_state():
    lorenz = Lorenz()
    assert lorenz.rhs(0.0, np.array([1.0, 2.0, 3.0])) == pytest.approx([10.0, 23.0, -6.0])
    data = lorenz.generate()
    assert data.x.shape == (1001, 3)
    np.testing.assert_array_equal(data.x[0], [0.0, 1.0, 20.0])


def test_rk4_matches_an_adaptive_integrator():
    lorenz = Lorenz()
    t = np.linspace(0, 1, 101)
    x = rk4(lorenz.rhs, lorenz.x0, t)
    ref = scipy.integrate.solve_ivp(
        lorenz.rhs, (0, 1), lorenz.x0, t_eval=t, rtol=1e-12, atol=1e-12, method="DOP853"
    ).y.T
    assert np.abs(x - ref).max() < 1e-3  # step 0.01 on a chaotic flow
    finer = rk4(lorenz.rhs, lorenz.x0, t, substeps=4)
    assert np.abs(finer - ref).max() < np.abs(x - ref).max() / 100  # fourth order: 4^4 = 256


def test_rk4_inputs_as_array_or_callable_agree_for_linear_inputs():
    t = np.linspace(0, 2, 41)

    def rhs(s, x, u):
        return np.array([u[0] - x[0]])

    from_fn = rk4(rhs, [0.0], t, u=lambda s: np.array([3.0 * s]))
    from_array = rk4(rhs, [0.0], t, u=3.0 * t)
    np.testing.assert_allclose(from_fn, from_array, rtol=0, atol=1e-14)
    exact = 3.0 * (t - 1 + np.exp(-t))
    assert np.abs(from_fn[:, 0] - exact).max() < 1e-6


def test_drone_attitude_stays_bounded_and_both_thrust_combinations_vary():
    drone = Drone()
    data = drone.generate()
    theta = data.x[:, 2]
    assert np.abs(theta).max() < 0.2
    assert abs(theta.mean()) < 0.02
    total, diff = data.u.sum(axis=1), data.u[:, 0] - data.u[:, 1]
    assert total.std() > 0.3 and diff.std() > 0.2
    lib = drone.library()
    th = lib.fit_transform(np.hstack([data.x, data.u]), input_names=drone.input_names)
    assert np.linalg.cond(th / np.linalg.norm(th, axis=0)) < 1e3


def test_contamination_rows_and_scales():
    rng = np.random.default_rng(5)
    m = 20001
    x = np.zeros((m, 3))
    out = contaminate(x, rng=rng, frac=0.2, sigma1=1e-3, sigma2=0.5)
    assert out.outliers.sum() == round(0.2 * m)
    noise = out.x
    # the same rows for all components
    heavy = np.abs(noise).max(axis=1) > 0.01
    assert np.array_equal(heavy & ~out.outliers, np.zeros(m, dtype=bool))
    assert np.std(noise[out.outliers]) == pytest.approx(0.5, rel=0.02)
    assert np.std(noise[~out.outliers]) == pytest.approx(1e-3, rel=0.02)
    assert out.x_dot is None


def test_contamination_placement():
    rng = np.random.default_rng(1)
    x, xd = np.zeros((100, 2)), np.ones((100, 2))
    s = contaminate(x, xd, rng=rng, placement="states")
    assert np.all(s.x_dot == 1) and np.any(s.x != 0)
    d = contaminate(x, xd, rng=rng, placement="derivatives")
    assert np.all(d.x == 0) and np.any(d.x_dot != 1)
    b = contaminate(x, xd, rng=rng, placement="both")
    big_x = np.abs(b.x).max(axis=1) > 0.05
    big_d = np.abs(b.x_dot - 1).max(axis=1) > 0.05
    assert not np.any((big_x | big_d) & ~b.outliers)
    assert outlier_rows(1001, 0.2, rng).sum() == 200


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(rng=0), "rng"),
        (dict(rng=np.random.default_rng(0), frac=1.5), "frac"),
        (dict(rng=np.random.default_rng(0), sigma2=-1.0), "sigma2"),
        (dict(rng=np.random.default_rng(0), placement="rows"), "placement"),
        (dict(rng=np.random.default_rng(0), placement="both"), "x_dot"),
    ],
)
def test_contaminate_rejects_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        contaminate(np.zeros((10, 2)), **kwargs)


def test_metrics():
    true = np.array([[1.0, 0.0], [0.0, -2.0], [0.0, 0.0]])
    est = np.array([[1.5, 0.0], [0.0, -2.0], [0.1, 0.0]])
    assert iae(true, est) == pytest.approx(0.6)
    assert max_abs_error(true, est) == pytest.approx(0.5)
    s = support_scores(true, est)
    assert (s.precision, s.recall, s.exact) == (pytest.approx(2 / 3), 1.0, False)
    assert support_scores(true, true).exact
    with pytest.raises(ValueError, match="shape"):
        iae(true, est[:2])


def test_differentiation_orders_and_nonuniform_time():
    t = np.sort(np.random.default_rng(0).uniform(0, 2, 400))
    x = np.column_stack([np.sin(3 * t), t**2])
    d = finite_difference(x, t)
    np.testing.assert_allclose(d[:, 1], 2 * t, atol=1e-10)  # exact for quadratics
    assert np.abs(d[:, 0] - 3 * np.cos(3 * t)).max() < 0.05
    tu = np.linspace(0, 2, 401)
    errs = [
        np.abs(finite_difference(np.sin(3 * tt), tt) - 3 * np.cos(3 * tt))[1:-1].max()
        for tt in (tu, np.linspace(0, 2, 801))
    ]
    assert errs[0] / errs[1] == pytest.approx(4, rel=0.1)  # second order
    noisy = np.sin(3 * tu) + 1e-4 * np.random.default_rng(1).normal(size=tu.size)
    smooth = savgol_derivative(noisy, tu, window_length=21, polyorder=3)
    raw = finite_difference(noisy, tu)
    truth = 3 * np.cos(3 * tu)
    assert np.abs(smooth - truth).std() < np.abs(raw - truth).std() / 3
    with pytest.raises(ValueError, match="uniformly"):
        savgol_derivative(x, t)
    with pytest.raises(ValueError, match="t must be strictly increasing"):
        finite_difference(x, t[::-1])
