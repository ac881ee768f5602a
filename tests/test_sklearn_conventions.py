"""scikit-learn's estimator checks: all of them for the libraries, the API ones for HuberSINDy.

``HuberSINDy.fit(x, t, x_dot, u)`` takes time series, not scikit-learn's ``(X, y)``: the
checks that fit random ``(X, y)`` pass ``y`` as the time, which is refused (not increasing).
The checks run for it are those of the estimator API (construction, parameters, cloning,
representation, tags, errors before fit).
"""

import warnings

import pytest
from sklearn.utils import estimator_checks as ec
from sklearn.utils.estimator_checks import parametrize_with_checks

import robust_sindy as rs


@parametrize_with_checks(
    [
        rs.PolynomialLibrary(),
        rs.PolynomialLibrary(degree=3, include_bias=False),
        rs.FourierLibrary(n_frequencies=2),
        rs.CustomLibrary(["x0 * sin(x0)", "exp(-x0**2)"]),
        rs.PolynomialLibrary(degree=1) + rs.FourierLibrary(),
    ]
)
def test_libraries_pass_the_scikit_learn_checks(estimator, check):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        check(estimator)


API_CHECKS = [
    "check_estimator_cloneable",
    "check_estimator_repr",
    "check_no_attributes_set_in_init",
    "check_do_not_raise_errors_in_init_or_set_params",
    "check_mixin_order",
    "check_parameters_default_constructible",
    "check_get_params_invariance",
    "check_set_params",
    "check_estimators_unfitted",
]


@pytest.mark.parametrize("name", API_CHECKS)
def test_huber_sindy_follows_the_estimator_api(name):
    check = getattr(ec, name, None)
    if check is None:  # older scikit-learn without this check
        pytest.skip(f"{name} is not in this scikit-learn")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        check("HuberSINDy", rs.HuberSINDy())
