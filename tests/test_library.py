import numpy as np
import pytest
from sklearn.base import clone

from robust_sindy import CustomLibrary, FourierLibrary, PolynomialLibrary
from robust_sindy.systems import Drone


def test_polynomial_degree_two_order_and_names():
    x = np.array([[2.0, 3.0, 5.0], [1.0, -1.0, 0.5]])
    lib = PolynomialLibrary(degree=2)
    theta = lib.fit_transform(x, input_names=["x", "y", "z"])
    assert lib.get_feature_names() == [
        "1", "x", "y", "z", "x^2", "x*y", "x*z", "y^2", "y*z", "z^2"
    ]  # fmt: skip
    a, b, c = x.T
    expected = np.column_stack([np.ones(2), a, b, c, a * a, a * b, a * c, b * b, b * c, c * c])
    np.testing.assert_array_equal(theta, expected)


def test_polynomial_degree_three_names_and_count():
    lib = PolynomialLibrary(degree=3, include_bias=False).fit(np.ones((1, 2)), input_names="ab")
    names = lib.get_feature_names()
    assert names == ["a", "b", "a^2", "a*b", "b^2", "a^3", "a^2*b", "a*b^2", "b^3"]
    assert lib.n_output_features_ == 9


def test_custom_library_applies_each_function_to_its_named_inputs():
    calls = []

    def record(a, b):
        calls.append(2)
        return a * b

    lib = CustomLibrary([record, np.cos], inputs=[["p", "r"], ["q"]])
    z = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    theta = lib.fit_transform(z, input_names=["p", "q", "r"])
    np.testing.assert_array_equal(theta, np.column_stack([z[:, 0] * z[:, 2], np.cos(z[:, 1])]))
    assert lib.get_feature_names() == ["record(p, r)", "cos(q)"]
    assert len(calls) == 1  # once, on its own inputs, not on every combination of columns


def test_custom_library_without_inputs_maps_over_columns():
    lib = CustomLibrary([np.sin]).fit(np.zeros((1, 2)), input_names=["a", "b"])
    assert lib.get_feature_names() == ["sin(a)", "sin(b)"]


def test_drone_library_is_the_papers_seven_functions():
    drone = Drone()
    data = drone.generate(t_end=1.0)
    lib = drone.library()
    theta = lib.fit_transform(np.hstack([data.x, data.u]), input_names=drone.input_names)
    assert lib.get_feature_names() == [
        "1", "x_dot", "y_dot", "theta_dot",
        "(f1+f2)*sin(theta)", "(f1+f2)*cos(theta)", "f1-f2",
    ]  # fmt: skip
    th, vx, vy, om = data.x[:, 2], data.x[:, 3], data.x[:, 4], data.x[:, 5]
    f1, f2 = data.u.T
    expected = np.column_stack(
        [np.ones(len(th)), vx, vy, om, (f1 + f2) * np.sin(th), (f1 + f2) * np.cos(th), f1 - f2]
    )
    np.testing.assert_allclose(theta, expected, rtol=1e-15)


def test_libraries_compose_and_clone():
    a = PolynomialLibrary(degree=1)
    b = CustomLibrary([np.exp], names=["exp(x)"], inputs=[["x"]])
    both = a + b + PolynomialLibrary(degree=2, include_bias=False, inputs=["y"])
    assert len(both.libraries) == 3
    theta = both.fit_transform(np.array([[0.0, 2.0]]), input_names=["x", "y"])
    np.testing.assert_array_equal(theta, [[1.0, 0.0, 2.0, 1.0, 2.0, 4.0]])
    assert both.get_feature_names() == ["1", "x", "y", "exp(x)", "y", "y^2"]
    copy = clone(both)
    assert not hasattr(copy, "input_names_")
    assert copy.get_params()["libraries"][1].names == ["exp(x)"]


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: PolynomialLibrary(degree=-1).fit(np.ones((2, 2))), "degree"),
        (lambda: PolynomialLibrary().fit(np.ones((2, 2)), input_names=["a"]), "input_names"),
        (lambda: PolynomialLibrary(inputs=["q"]).fit(np.ones((2, 2))), "inputs"),
        (lambda: PolynomialLibrary().fit(np.array([[np.nan, 1.0]])), "x contains NaN"),
        (lambda: PolynomialLibrary().transform(np.ones((2, 2))), "not fitted"),
        (
            lambda: PolynomialLibrary().fit(np.ones((2, 2))).transform(np.ones((2, 3))),
            "is expecting 2 features",
        ),
        (lambda: CustomLibrary([np.sin], names=["a", "b", "c"]).fit(np.ones((2, 2))), "names"),
        (lambda: CustomLibrary([np.sin], inputs=[["x0"], ["x1"]]).fit(np.ones((2, 2))), "inputs"),
        (lambda: CustomLibrary([]).fit(np.ones((2, 2))), "functions"),
        (
            lambda: CustomLibrary([lambda a: np.ones(3)], inputs=[[0]]).fit_transform(
                np.ones((2, 2))
            ),
            "function 0",
        ),
    ],
)
def test_bad_library_input_names_the_argument(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_a_librarys_columns_of_an_input_and_its_columns_alone():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    poly = PolynomialLibrary(degree=2).fit(x)
    names = poly.get_feature_names()
    assert [names[j] for j in poly.input_columns(1)] == ["x1", "x0*x1", "x1^2", "x1*x2"]
    both = (PolynomialLibrary(degree=1, inputs=[2]) + CustomLibrary(["sin(x0)"])).fit(x)
    assert both.input_columns(0) is None  # the custom library cannot tell
    both = (PolynomialLibrary(degree=1, inputs=[2]) + PolynomialLibrary(degree=2)).fit(x)
    np.testing.assert_array_equal(both.input_columns(2), [1, 5, 8, 10, 11])
    fourier = FourierLibrary(n_frequencies=2, inputs=[0, 2]).fit(x)
    names = fourier.get_feature_names()
    assert [names[j] for j in fourier.input_columns(2)] == [
        "sin(x2)",
        "cos(x2)",
        "sin(2*x2)",
        "cos(2*x2)",
    ]
    assert fourier.input_columns(1).size == 0
    np.testing.assert_array_equal(
        fourier.transform_columns(x, [3, 0]), fourier.transform(x)[:, [3, 0]]
    )
    full = both.transform(x)
    for cols in ([11, 0, 5, 2], [3], [], list(range(full.shape[1]))[::-1]):
        np.testing.assert_array_equal(both.transform_columns(x, cols), full[:, cols])
        np.testing.assert_array_equal(
            poly.transform_columns(x, [c for c in cols if c < 10]),
            poly.transform(x)[:, [c for c in cols if c < 10]],
        )
