import numpy as np
import pytest
from sklearn.base import clone

import robust_sindy as rs
from robust_sindy import HuberSINDy
from robust_sindy.metrics import iae, support_scores
from robust_sindy.noise import contaminate
from robust_sindy.systems import Drone, Lorenz


@pytest.fixture(scope="module")
def lorenz_data():
    return Lorenz().generate()


@pytest.fixture(scope="module")
def drone_data():
    return Drone().generate()


def _drone_model():
    # The drone's library columns are small (|theta_dot| ~ 0.2), so lam = 1 would shrink
    # them hard; noise-free data needs little penalty before threshold and refit.
    return HuberSINDy(library=Drone().library())


def test_noise_free_lorenz_exact_support_and_coefficients(lorenz_data):
    d = lorenz_data
    model = HuberSINDy(threshold=0.05, refit=True)
    model.fit(d.x, d.t, x_dot=d.x_dot, feature_names=["x", "y", "z"])
    true = Lorenz().true_coef().T
    assert np.array_equal(model.coef_ != 0, true != 0)
    np.testing.assert_allclose(model.coef_[true != 0], true[true != 0], rtol=1e-6)
    assert model.coef_.shape == (3, 10)
    assert not model.outliers_.any()


def test_noise_free_drone_exact_support_and_coefficients(drone_data):
    d = drone_data
    drone = Drone()
    model = _drone_model().fit(d.x, d.t, x_dot=d.x_dot, u=d.u, feature_names=drone.input_names)
    true = drone.true_coef(full=True).T
    assert np.array_equal(model.coef_ != 0, true != 0)
    np.testing.assert_allclose(model.coef_[true != 0], true[true != 0], rtol=1e-6)
    eqs = model.equations(precision=2)
    assert eqs[3] == "-1.00 (f1+f2)*sin(theta)"
    assert eqs[4] == "-9.81 + 1.00 (f1+f2)*cos(theta)"
    assert eqs[5] == "0.86 f1-f2"


def test_simulate_reproduces_the_trajectory_over_a_short_horizon(lorenz_data, drone_data):
    d = lorenz_data
    model = HuberSINDy(threshold=0.05, refit=True).fit(d.x, d.t, x_dot=d.x_dot)
    sim = model.simulate(d.x[0], d.t[:101])
    assert np.abs(sim - d.x[:101]).max() < 1e-3 * np.abs(d.x[:101]).max()
    d = drone_data
    drone = Drone()
    model = _drone_model().fit(d.x, d.t, x_dot=d.x_dot, u=d.u, feature_names=drone.input_names)
    sim = model.simulate(d.x[0], d.t[:201], u=d.u[:201])
    assert np.abs(sim - d.x[:201]).max() < 1e-3  # linear interpolation of sampled inputs
    sim_fn = model.simulate(d.x[0], d.t[:201], u=drone.inputs)
    assert np.abs(sim_fn - d.x[:201]).max() < 1e-6


def test_derivatives_from_the_states_and_a_time_step_are_accepted(lorenz_data):
    d = lorenz_data
    model = HuberSINDy(threshold=0.2, refit=True, formulation="strong").fit(d.x, 0.01)
    true = Lorenz().true_coef().T
    assert support_scores(true, model.coef_).recall == 1.0
    assert iae(true, model.coef_) < 0.05  # differentiation error, not the solver
    # The default local quartic is fourth-order: on exact states it beats second-order
    # finite differences and the Savitzky-Golay cubic.
    for how in ("finite_difference", "savgol"):
        other = HuberSINDy(threshold=0.2, refit=True, differentiation=how, formulation="strong")
        other.fit(d.x, 0.01)
        assert iae(true, model.coef_) < iae(true, other.coef_)
    assert model.score(d.x, 0.01) > 0.999


def test_multiple_trajectories_are_stacked():
    lorenz = Lorenz()
    a = lorenz.generate(t_end=2.0)
    b = lorenz.generate(t_end=3.0, x0=[5.0, -5.0, 25.0])
    model = HuberSINDy(threshold=0.05, refit=True)
    model.fit([a.x, b.x], [a.t, b.t], x_dot=[a.x_dot, b.x_dot])
    assert model.outliers_.shape == (a.x.shape[0] + b.x.shape[0], 3)
    np.testing.assert_allclose(model.coef_, lorenz.true_coef().T, atol=1e-6)
    pred = model.predict(b.x)
    np.testing.assert_allclose(pred, b.x_dot, atol=1e-4)


def test_contaminated_lorenz_flags_the_corrupted_rows(lorenz_data):
    d = lorenz_data
    noisy = contaminate(d.x, rng=np.random.default_rng(0))
    model = HuberSINDy(delta="auto", lam=1.0).fit(noisy.x, d.t, x_dot=d.x_dot)
    # nearly every heavy-noise row exceeds delta in some equation; clean rows exceed it
    # about as often as Gaussian residuals exceed 1.345 sigma (18 %)
    assert model.outliers_.any(axis=1)[noisy.outliers].mean() > 0.9
    assert np.all(model.outliers_[~noisy.outliers].mean(axis=0) < 0.25)
    np.testing.assert_array_equal(model.delta_, model.result_.delta)
    stls = rs.fit(model.library_.transform(noisy.x), d.x_dot, method="stls")
    true = Lorenz().true_coef()
    assert iae(true, model.coef_.T) < iae(true, stls.coef) / 5


def test_get_params_and_clone():
    model = HuberSINDy(delta=0.5, lam=2.0, threshold=0.1, solver_options={"max_iter": 10})
    params = model.get_params()
    assert params["delta"] == 0.5 and params["lam"] == 2.0 and params["threshold"] == 0.1
    copy = clone(model)
    assert copy.get_params()["solver_options"] == {"max_iter": 10}
    assert not hasattr(copy, "coef_")
    model.set_params(lam=3.0)
    assert model.lam == 3.0


def test_print_uses_state_names(lorenz_data, capsys):
    d = lorenz_data
    model = HuberSINDy(threshold=0.05, refit=True).fit(d.x, d.t, x_dot=d.x_dot)
    model.print(precision=1)
    out = capsys.readouterr().out.splitlines()
    assert out == [
        "(x0)' = -10.0 x0 + 10.0 x1",
        "(x1)' = 28.0 x0 - 1.0 x1 - 1.0 x0*x2",
        "(x2)' = -2.7 x2 + 1.0 x0*x1",
    ]


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda m, d: m.fit(d.x, d.t[::-1]), r"t must be strictly increasing: t\[1\] = "),
        (
            lambda m, d: m.fit(d.x, np.where(np.arange(d.t.size) == 7, d.t[6], d.t)),
            r"t\[7\] = \S+ repeats t\[6\] = \S+ \(a time stamp logged twice",
        ),
        (lambda m, d: m.fit(d.x, d.t[:-1]), "t has 1000 time points"),
        (lambda m, d: m.fit(d.x, d.t, x_dot=d.x_dot[:-1]), "x_dot has shape"),
        (lambda m, d: m.fit(d.x, d.t, u=d.x[:-1]), "u has 1000 samples"),
        (lambda m, d: m.fit(np.where(d.x > 5, np.inf, d.x), d.t), "x contains inf"),
        (lambda m, d: m.fit(d.x, d.t, u=np.full((d.t.size, 1), np.nan)), "u: column 0 has 0 "),
        (lambda m, d: m.fit(d.x, np.where(d.t > 1, np.nan, d.t)), "t contains NaN"),
        (lambda m, d: m.fit(d.x, d.t, feature_names=["a", "b"]), "feature_names"),
        (lambda m, d: m.fit(d.x, -0.01), "time step"),
        (lambda m, d: m.fit(d.x), "t is required"),
        (lambda m, d: m.fit([d.x, d.x], d.t), "t must be a list"),
        (lambda m, d: m.simulate(d.x[0], d.t), "not fitted"),
        (lambda m, d: m.predict(d.x), "not fitted"),
        (lambda m, d: m.equations(), "not fitted"),
        (lambda m, d: HuberSINDy(method="lsq").fit(d.x, d.t), "method"),
        (lambda m, d: HuberSINDy(differentiation="spline").fit(d.x, d.t), "differentiation"),
        (lambda m, d: HuberSINDy(delta="robust").fit(d.x, d.t), "delta"),
    ],
)
def test_bad_input_names_the_argument(lorenz_data, call, match):
    with pytest.raises(ValueError, match=match):
        call(HuberSINDy(), lorenz_data)


def test_controls_are_required_after_fitting_with_them(drone_data):
    d = drone_data
    model = _drone_model().fit(d.x, d.t, x_dot=d.x_dot, u=d.u, feature_names=Drone().input_names)
    with pytest.raises(ValueError, match="u is required"):
        model.simulate(d.x[0], d.t[:10])
    with pytest.raises(ValueError, match="u is required"):
        model.predict(d.x)


def test_pysindy_interop_fits_prints_and_simulates(lorenz_data, capsys):
    ps = pytest.importorskip("pysindy")
    from robust_sindy.pysindy import HuberOptimizer

    d = lorenz_data
    opt = HuberOptimizer(delta=1.0, lam=1.0)
    assert opt.unbias is False
    model = ps.SINDy(optimizer=opt, feature_library=ps.PolynomialLibrary(degree=2))
    model.fit(d.x, t=d.t, x_dot=d.x_dot, feature_names=["x", "y", "z"])
    ours = rs.fit(model.feature_library.transform(d.x), d.x_dot, delta=1.0, lam=1.0)
    np.testing.assert_allclose(model.coefficients(), ours.coef.T, rtol=1e-8, atol=1e-10)
    assert opt.result_.converged
    model.print()
    assert "(x)' =" in capsys.readouterr().out
    sim = model.simulate(d.x[0], d.t[:51])
    assert np.abs(sim - d.x[:51]).max() < 0.05


def test_pysindy_optimizer_chooses_delta_and_lam_by_default():
    ps = pytest.importorskip("pysindy")
    from robust_sindy.noise import contaminate
    from robust_sindy.pysindy import HuberOptimizer

    lorenz = rs.systems.Lorenz()
    data = lorenz.generate(t_end=10.0)
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(1), placement="derivatives")
    opt = HuberOptimizer()  # delta="auto", lam="auto"
    model = ps.SINDy(optimizer=opt, feature_library=ps.PolynomialLibrary(degree=2))
    model.fit(data.x, t=data.t, x_dot=noisy.x_dot)
    truth = lorenz.true_coef(full=True).T != 0
    np.testing.assert_array_equal(model.coefficients() != 0, truth)
    assert opt.result_.converged


def test_pysindy_optimizer_takes_linear_constraints():
    ps = pytest.importorskip("pysindy")
    from robust_sindy import constraints as rc
    from robust_sindy.datasets import load_cylinder_wake
    from robust_sindy.pysindy import HuberOptimizer

    data = load_cylinder_wake()
    library = ps.PolynomialLibrary(degree=2).fit(data.x)
    names = library.get_feature_names(["a", "b", "s"])  # PySINDy's "a b" for products
    con = rc.energy_preserving(names)
    assert con.A_eq.shape[0] == 10
    x_dot = np.gradient(data.x, data.t, axis=0)
    for lam in ("auto", 1e-3):
        opt = HuberOptimizer(lam=lam, constraints=con)
        model = ps.SINDy(optimizer=opt, feature_library=ps.PolynomialLibrary(degree=2))
        model.fit(data.x, t=data.t, x_dot=x_dot, feature_names=["a", "b", "s"])
        coef = model.coefficients().T
        assert opt.result_.converged and opt.result_.info["constraint_residual"] <= 1e-10
        assert con.residual(coef) <= 1e-10
        np.testing.assert_array_equal(coef, opt.result_.coef)
    # Without the constraints the same fit does not conserve energy.
    free = ps.SINDy(optimizer=HuberOptimizer(), feature_library=ps.PolynomialLibrary(degree=2))
    free.fit(data.x, t=data.t, x_dot=x_dot)
    assert con.residual(free.coefficients().T) > 1e-3


def test_progress_names_the_stage_a_fit_is_in(capsys):
    from robust_sindy.systems import Lorenz

    data = Lorenz().generate(t_end=5.0)
    rs.HuberSINDy(progress=True).fit(data.x, data.t, x_dot=data.x_dot)
    err = capsys.readouterr().err
    stages = ("temporal screen", "row screen", "delta, lambda and the support", "diagnostics")
    at = [err.find(stage) for stage in stages]
    assert min(at) >= 0 and at == sorted(at)  # each named, in the order they run
    rs.HuberSINDy().fit(data.x, data.t, x_dot=data.x_dot)
    assert "identify" not in capsys.readouterr().err  # silent by default
