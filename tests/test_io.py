"""Model files: JSON in, the same model out."""

import json
import warnings

import numpy as np
import pytest

import robust_sindy as rs


def _fitted(system, names=None, **kw):
    data = system.generate(t_end=5.0)
    with warnings.catch_warnings():
        # Not what is tested here (the concatenated library repeats its degree-1 terms).
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        warnings.simplefilter("ignore", rs.ConvergenceWarning)
        model = rs.HuberSINDy(**kw).fit(
            data.x, data.t, x_dot=data.x_dot, u=data.u, feature_names=names
        )
    return model, data


@pytest.mark.parametrize(
    "system, kw",
    [
        (rs.systems.Lorenz(), {}),
        (rs.systems.Drone(), dict(library=rs.PolynomialLibrary(degree=1))),
        (
            rs.systems.Lorenz(),
            dict(library=rs.PolynomialLibrary(degree=1) + rs.PolynomialLibrary(degree=2)),
        ),
        # controls with custom expression features and Fourier features
        (
            rs.systems.Drone(),
            dict(
                library=rs.PolynomialLibrary(degree=1)
                + rs.FourierLibrary(inputs=[2])
                + rs.CustomLibrary(["(u0 + u1) * sin(x2)", "(u0 + u1) * cos(x2)", "u0 - u1"])
            ),
        ),
    ],
)
def test_a_loaded_model_predicts_prints_and_simulates_like_the_saved_one(tmp_path, system, kw):
    model, data = _fitted(system, **kw)
    path = model.save(tmp_path / "model.json")
    text = path.read_text()
    assert json.loads(text)["equations"] == model.equations()  # human-readable
    loaded = rs.load_model(path)
    assert loaded.equations() == model.equations()
    assert loaded.get_feature_names() == model.get_feature_names()
    np.testing.assert_array_equal(loaded.predict(data.x, data.u), model.predict(data.x, data.u))
    t = data.t[:50]
    u = None if data.u is None else data.u[:50]
    np.testing.assert_array_equal(
        loaded.simulate(data.x[0], t, u=u), model.simulate(data.x[0], t, u=u)
    )
    assert loaded.diagnostics_summary_["n_samples"] == model.diagnostics_.n_samples


def test_what_cannot_be_saved_or_loaded_fails_clearly(tmp_path):
    model, _ = _fitted(rs.systems.Lorenz(), library=rs.CustomLibrary([np.sin]))
    with pytest.raises(ValueError, match="CustomLibrary with Python functions cannot be saved"):
        model.save(tmp_path / "m.json")
    model, _ = _fitted(rs.systems.Lorenz())
    path = model.save(tmp_path / "m.json")
    data = json.loads(path.read_text())
    data["format_version"] = 99
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"format version 99.*upgrade"):
        rs.load_model(path)
    (tmp_path / "other.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a robust-sindy model file"):
        rs.load_model(tmp_path / "other.json")
    with pytest.raises(ValueError, match="cannot read"):
        rs.load_model(tmp_path / "missing.json")
    from sklearn.exceptions import NotFittedError

    with pytest.raises(NotFittedError):
        rs.HuberSINDy().save(tmp_path / "x.json")


def test_dataframes_in_names_out():
    pd = pytest.importorskip("pandas")
    data = rs.systems.Lorenz().generate(t_end=5.0)
    index = pd.to_timedelta(data.t, unit="s")
    x = pd.DataFrame(data.x, columns=["x", "y", "z"], index=index)
    model = rs.HuberSINDy().fit(x)  # times from the index, names from the columns
    assert model.feature_names_ == ["x", "y", "z"]
    assert model.equations()[0] == "-10.000 x + 10.000 y"
    pred = model.predict(x)
    assert list(pred.columns) == ["(x)'", "(y)'", "(z)'"] and pred.index.equals(index)
    np.testing.assert_array_equal(pred.to_numpy(), model.predict(data.x))


def test_the_lynx_hare_data_ship_with_the_package():
    from robust_sindy.datasets import load_lynx_hare

    data = load_lynx_hare()
    assert data.x.shape == (21, 2) and data.names == ["hare", "lynx"]
    np.testing.assert_array_equal(data.t, np.arange(1900, 1921))
    assert data.x[0].tolist() == [30.0, 4.0] and data.x[-1].tolist() == [24.7, 8.6]
    # 21 yearly samples do not identify the lynx equation: the fit says so.
    with pytest.warns(rs.IdentificationWarning, match=r"^equations \[1\]: "):
        rs.HuberSINDy().fit(data.x, data.t, feature_names=data.names)


@pytest.mark.parametrize("system", [rs.systems.Lorenz(), rs.systems.Drone()])
def test_the_exported_right_hand_side_is_the_model(tmp_path, system):
    model, data = _fitted(system, system.input_names, library=system.library())
    f = model.export_rhs()
    want = model.predict(data.x, data.u)
    scale = abs(want).max()
    np.testing.assert_allclose(f(0.0, data.x, data.u), want, rtol=1e-12, atol=1e-12 * scale)
    u0 = None if data.u is None else data.u[3]
    np.testing.assert_allclose(f(0.0, data.x[3], u0), want[3], rtol=1e-12, atol=1e-10)
    # the written module runs with numpy and the library's Python callables only
    f.write(tmp_path / "rhs_module.py")
    scope = dict(f.callables)
    assert bool(scope) == isinstance(system, rs.systems.Drone)  # its library has lambdas
    exec((tmp_path / "rhs_module.py").read_text(), scope)
    np.testing.assert_array_equal(scope["rhs"](0.0, data.x, data.u), f(0.0, data.x, data.u))
    if data.u is not None:
        with pytest.raises(ValueError, match="u is required"):
            f(0.0, data.x)


def test_to_sympy_gives_the_equations():
    sympy = pytest.importorskip("sympy")
    model, data = _fitted(rs.systems.Lorenz())
    exprs = model.to_sympy()
    x, y, z = sympy.symbols(model.feature_names_)
    assert len(exprs) == 3
    fn = sympy.lambdify((x, y, z), exprs, "numpy")
    got = np.column_stack(fn(*data.x.T))
    np.testing.assert_allclose(got, model.predict(data.x), rtol=1e-9, atol=1e-9)
    # callables become undefined functions named like the feature
    m2, _ = _fitted(rs.systems.Lorenz(), library=rs.CustomLibrary([np.sin]))
    assert "sin" in str(m2.to_sympy()[0]) or m2.coef_[0].sum() == 0


def test_simulate_returns_a_frame_for_a_series_or_on_request():
    pd = pytest.importorskip("pandas")
    model, data = _fitted(rs.systems.Lorenz())
    x0 = pd.Series(data.x[0], index=model.feature_names_)
    out = model.simulate(x0, data.t[:20])
    assert isinstance(out, pd.DataFrame)
    assert list(out.columns) == model.feature_names_
    np.testing.assert_array_equal(out.index.to_numpy(), data.t[:20])
    np.testing.assert_array_equal(out.to_numpy(), model.simulate(data.x[0], data.t[:20]))
    assert isinstance(model.simulate(data.x[0], data.t[:20], as_frame=True), pd.DataFrame)
