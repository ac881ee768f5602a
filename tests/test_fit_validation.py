"""Bad input raises ValueError naming the argument; nothing is coerced silently."""

import warnings

import numpy as np
import pytest

import robust_sindy as rs

THETA = np.random.default_rng(0).normal(size=(20, 4))
Y = np.random.default_rng(1).normal(size=(20, 2))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(theta=np.where(THETA > 1, np.nan, THETA)), "theta contains NaN"),
        (dict(theta=np.where(THETA > 1, np.inf, THETA)), "theta contains NaN or inf"),
        (dict(xdot=np.where(Y > 1, np.nan, Y)), "xdot contains NaN"),
        (dict(theta=THETA[:, 0]), "theta must be 2-D"),
        (dict(xdot=Y[:, :, None]), "xdot must be 1-D or 2-D"),
        (dict(xdot=Y[:-1]), "xdot has 19 rows but theta has 20"),
        (dict(theta=np.zeros((0, 4)), xdot=np.zeros((0, 2))), "theta has no rows"),
        (dict(theta=np.zeros((20, 0))), "theta has no columns"),
        (dict(theta=THETA.astype(complex)), "theta must hold real numbers"),
        (dict(theta=THETA > 0), "theta must hold real numbers"),
        (dict(theta="abc"), "theta must hold real numbers"),
        (dict(delta=0.0), "delta must be > 0"),
        (dict(delta=-1.0), "delta must be > 0"),
        (dict(delta=np.nan), "delta contains NaN"),
        (dict(delta=[1.0, 2.0, 3.0]), "delta has 3 values but xdot has 2 columns"),
        (dict(lam=-0.1), "lam must be >= 0"),
        (dict(lam=[1.0, -1.0]), "lam must be >= 0"),
        (dict(lam="auto-ish"), "lam must be a number"),
        (dict(method="newton"), "method must be one of"),
        (dict(loss="l1"), "loss must be one of"),
        (dict(solver="osqp"), "solver applies to method='cvxpy'"),
        (dict(method="cvxpy", solver="mosek-like"), "solver must be one of"),
        (dict(rho=0.0), "rho must be"),
        (dict(alpha=2.5), "alpha must be"),
        (dict(max_iter=0), "max_iter must be an integer"),
        (dict(max_iter=10.5), "max_iter must be an integer"),
        (dict(polish="yes"), "polish must be True or False"),
        (dict(rho_typo=1.0), r"unknown option\(s\) \['rho_typo'\]"),
        (dict(warm_start=np.zeros((3, 2))), "warm_start must have shape"),
        (dict(method="stls", threshold=-1.0), "threshold must be"),
        (dict(method="stls", max_sweeps=0), "max_sweeps must be"),
        (dict(method="ols", rho=1.0), "unknown option"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(kwargs, match):
    args = dict(theta=THETA, xdot=Y)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        rs.fit(args.pop("theta"), args.pop("xdot"), **args)


@pytest.mark.parametrize("func", [rs.objective, rs.kkt_violation, rs.duality_gap])
def test_certificates_validate_coef(func):
    with pytest.raises(ValueError, match="coef must be 2-D"):
        func(THETA, Y, np.zeros(4))
    with pytest.raises(ValueError, match=r"coef must have shape \(4, 2\)"):
        func(THETA, Y, np.zeros((4, 3)))
    with pytest.raises(ValueError, match="coef contains NaN"):
        func(THETA, Y, np.full((4, 2), np.nan))


def test_integer_input_is_accepted_exactly():
    theta = np.arange(40).reshape(20, 2) % 7
    res = rs.fit(theta, np.arange(20) % 5, lam=0.1)
    assert res.coef.dtype == np.float64
    assert res.converged


def test_inputs_are_not_modified():
    theta, y = THETA.copy(), Y.copy()
    rs.fit(theta, y)
    np.testing.assert_array_equal(theta, THETA)
    np.testing.assert_array_equal(y, Y)


def _lorenz_data():
    return rs.systems.Lorenz().generate(t_end=2.0)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda th, y: rs.fit(th, y, method="cvxpy", foo=1), "unknown option 'foo'"),
        (lambda th, y: rs.fit(th, y, method="cvxpy", max_iter=1.5), "'max_iter'.*type int"),
        (lambda th, y: rs.fit(th, y, method="cvxpy", warm_start=np.zeros(4)), "warm_start"),
        (lambda th, y: rs.fit(th, y, method="stls", threshold="a"), "threshold"),
        (lambda th, y: rs.fit(th, y, method="ols", tol=-1.0), "tol"),
    ],
)
def test_solver_options_are_checked_before_any_work(call, match):
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(40, 4))
    with pytest.raises(ValueError, match=match):
        call(theta, theta @ [1.0, 0, 2, 0])


@pytest.mark.parametrize(
    "params, match",
    [
        (dict(threshold="a"), "threshold"),
        (dict(library="poly"), "library must be"),
        (dict(refit="yes"), "refit"),
        (dict(differentiation="spline"), "differentiation"),
        (dict(n_lams=1.5), "n_lams"),
        (dict(solver_options=[1]), "solver_options"),
    ],
)
def test_estimator_parameters_are_checked_in_fit_before_any_work(params, match):
    data = _lorenz_data()
    with pytest.raises(ValueError, match=match):
        rs.HuberSINDy(**params).fit(data.x, data.t)


def test_a_custom_function_that_is_not_finite_is_named():
    data = _lorenz_data()
    lib = rs.CustomLibrary([np.log], names=["log(x)", "log(y)", "log(z)"])
    with pytest.raises(ValueError, match=r"'log\(x\)'.*finite"):
        rs.HuberSINDy(library=lib).fit(data.x, data.t)


def test_not_fitted_is_scikit_learns_error():
    from sklearn.exceptions import NotFittedError

    for call in (
        lambda m: m.print(),
        lambda m: m.equations(),
        lambda m: m.predict(np.ones((2, 3))),
        lambda m: m.score(np.ones((5, 3)), 0.1),
        lambda m: m.simulate(np.ones(3), np.arange(3.0)),
        lambda m: m.save("never_written.json"),
        lambda m: m.get_feature_names(),
        lambda m: m.export_rhs(),
        lambda m: m.to_sympy(),
    ):
        with pytest.raises(NotFittedError):
            call(rs.HuberSINDy())


def test_trajectories_of_different_lengths_with_their_own_times():
    data = _lorenz_data()
    model = rs.HuberSINDy().fit([data.x, data.x[:120]], t=[data.t, data.t[:120]])
    assert model.coef_.shape == (3, 10)
    with pytest.raises(ValueError, match="t has 40 time points but x has 120"):
        rs.HuberSINDy().fit([data.x, data.x[:120]], t=[data.t, data.t[:40]])


def test_simulate_and_score_name_their_bad_inputs():
    data = rs.systems.Drone().generate(t_end=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)  # short data, not the point
        model = rs.HuberSINDy(library=rs.PolynomialLibrary(degree=1)).fit(
            data.x, data.t, x_dot=data.x_dot, u=data.u
        )
    with pytest.raises(ValueError, match="u has 3 columns but the model was fitted with 2"):
        model.simulate(data.x[0], data.t[:10], u=np.zeros((10, 3)))
    with pytest.raises(ValueError, match="x has 0 samples"):
        model.score(data.x[:0], x_dot=data.x_dot[:0], u=data.u[:0])


@pytest.mark.parametrize("delta", [1e-300, 1e-100, 1e-16])
def test_a_delta_far_below_the_residuals_is_solved_but_never_falsely_certified(delta):
    rng = np.random.default_rng(2)
    theta = rng.normal(size=(60, 4))
    y = theta @ [1.0, 0, -2, 0] + 0.01 * rng.normal(size=60)
    y[::10] += 30
    with pytest.warns(rs.ConvergenceWarning):
        res = rs.fit(theta, y, delta=delta, lam=0.0, max_iter=200)
    # The least-absolute-deviation limit is reached (better than the true coefficients)...
    assert res.objective[0] <= rs.objective(theta, y, [1.0, 0, -2, 0], delta=delta, lam=0.0)[0]
    # ... but its KKT conditions cannot be resolved in floating point: not certified.
    assert not res.converged and res.kkt[0] > 1e-8


@pytest.mark.parametrize("rel", [1e10, 1e100, 1e300])
def test_a_delta_far_above_the_residuals_is_the_lasso_and_certified(rel):
    """With delta beyond every residual the Huber loss is the squared loss / 2 (the Lasso);
    the fast path certifies and agrees with the squared-loss solve."""
    rng = np.random.default_rng(3)
    theta = rng.normal(size=(80, 5))
    y = theta @ [1.5, 0, -2, 0, 0.3] + 0.1 * rng.normal(size=80)
    lam = 2.0
    res = rs.fit(theta, y, delta=rel * np.abs(y).max(), lam=lam)
    lasso = rs.fit(theta, y, delta=1.0, lam=lam, loss="squared")
    assert res.converged and res.kkt[0] <= 1e-8
    np.testing.assert_allclose(res.coef, lasso.coef, rtol=1e-7, atol=1e-9)
