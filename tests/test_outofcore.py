"""Fits on Dask arrays: the same certified optimum as in memory, from sums over chunks."""

import pickle
import warnings

import numpy as np
import pytest

import robust_sindy as rs
from robust_sindy.timeseries.derivatives import differentiate
from robust_sindy.timeseries.temporal import temporal_screen

from .conftest import van_der_pol

da = pytest.importorskip("dask.array")


def _problem(m=6000, seed=0):
    system = rs.systems.Lorenz()
    data = system.generate(t_end=m * 0.01 - 0.01)
    rng = np.random.default_rng(seed)
    y = data.x_dot + 0.01 * rng.normal(size=data.x_dot.shape)
    bad = rng.uniform(size=len(y)) < 0.2
    y[bad] += 50 * rng.normal(size=(bad.sum(), 3))
    return data.x, y


@pytest.mark.parametrize("lam", [0.0, 2.0])
def test_dask_fit_of_a_lazy_library_matches_the_in_memory_fit(lam):
    x, y = _problem()
    lib, theta = rs.outofcore.dask_library(rs.PolynomialLibrary(2), da.from_array(x, chunks=700))
    assert isinstance(theta, da.Array) and theta.shape == (len(x), 10)
    res = rs.fit(theta, da.from_array(y, chunks=700), delta=0.5, lam=lam)
    ref = rs.fit(lib.transform(x), y, delta=0.5, lam=lam)
    assert res.converged and ref.converged and res.solver == "newton-chunked"
    assert res.kkt.max() <= 1e-8
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-8)
    np.testing.assert_allclose(res.coef, ref.coef, rtol=1e-6, atol=1e-8)
    np.testing.assert_array_equal(res.coef != 0, ref.coef != 0)
    assert 3 <= res.info["passes"] <= 40
    # the m-sized outputs stay lazy
    assert isinstance(res.inliers, da.Array)
    np.testing.assert_array_equal(res.inliers.compute(), ref.inliers)


def test_dask_fit_one_column_and_what_it_refuses():
    x, y = _problem(2000, seed=1)
    theta = rs.PolynomialLibrary(2).fit_transform(x)
    th, yd = da.from_array(theta, chunks=300), da.from_array(y[:, 0], chunks=300)
    res = rs.fit(th, yd, delta=0.5, lam=1.0)
    ref = rs.fit(theta, y[:, 0], delta=0.5, lam=1.0)
    assert res.coef.shape == (10,) and res.converged
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-8)
    with pytest.raises(ValueError, match="fast path only"):
        rs.fit(th, yd, method="cvxpy")
    with pytest.raises(ValueError, match="delta='auto'"):
        rs.fit(th, yd, delta="auto")
    with pytest.raises(ValueError, match="unknown option"):
        rs.fit(th, yd, rho=1.0)
    with pytest.warns(rs.ConvergenceWarning, match="did not certify"):
        out = rs.fit(th, yd, delta=0.5, lam=1.0, max_iter=1)
    assert not out.converged


def test_dask_fit_on_a_distributed_cluster():
    distributed = pytest.importorskip("distributed")
    x, y = _problem(1500, seed=2)
    theta = rs.PolynomialLibrary(2).fit_transform(x)
    ref = rs.fit(theta, y, delta=0.5, lam=1.0)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:  # fmt: skip
        with distributed.Client(cluster):
            res = rs.fit(da.from_array(theta, chunks=400), da.from_array(y, chunks=400),
                         delta=0.5, lam=1.0)  # fmt: skip
    assert res.converged
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-8)


def test_no_warning_on_a_clean_run():
    x, y = _problem(1000, seed=3)
    theta = rs.PolynomialLibrary(2).fit_transform(x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs.fit(da.from_array(theta, chunks=250), da.from_array(y, chunks=250), delta=0.5, lam=1.0)


def test_a_start_without_inliers_takes_majoriser_steps():
    """Gross errors of one sign shift the least-squares start so far that no residual is
    within delta: the inlier Gram matrix is zero, and the Huber majoriser steps in."""
    rng = np.random.default_rng(0)
    data = rs.systems.Lorenz().generate(t_end=50.0)
    x = data.x + 0.01 * rng.normal(size=data.x.shape)
    y = data.x_dot.copy()
    y[rng.uniform(size=len(y)) < 0.1] += 50.0
    theta = rs.PolynomialLibrary(2).fit_transform(x)
    start = np.linalg.lstsq(theta, y, rcond=None)[0]
    assert np.all(np.abs(y - theta @ start) > 0.5)  # no inliers at the start
    res = rs.fit(da.from_array(theta, chunks=1000), da.from_array(y, chunks=1000), delta=0.5,
                 lam=1.0)  # fmt: skip
    ref = rs.fit(theta, y, delta=0.5, lam=1.0)
    assert res.converged and ref.converged
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-8)


def test_huber_sindy_on_dask_arrays_chooses_on_a_sample_and_fits_everything(monkeypatch):
    from robust_sindy import outofcore as model_module
    from robust_sindy.noise import contaminate

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1000)
    system = rs.systems.Lorenz()
    data = system.generate(t_end=30.0)  # 3001 samples
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
    x = da.from_array(noisy.x, chunks=500)
    d = da.from_array(noisy.x_dot, chunks=500)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        model = rs.HuberSINDy().fit(x, data.t, x_dot=d)
    truth = system.true_coef().T
    np.testing.assert_array_equal(model.support_, truth != 0)
    # delta and lam chosen on the sample select what the whole data in memory selects
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        whole = rs.HuberSINDy().fit(noisy.x, data.t, x_dot=noisy.x_dot)
    np.testing.assert_array_equal(model.support_, whole.support_)
    np.testing.assert_allclose(model.delta_, whole.delta_, rtol=0.2)
    np.testing.assert_allclose(model.coef_[truth != 0], truth[truth != 0], rtol=2e-3)
    assert model.dask_["sample"] == 1000 and model.dask_["samples"] == len(data.t)
    assert model.dask_["refit"].converged and model.diagnostics_.certified.all()
    assert model.dask_["refit"].kkt.max() <= 1e-8
    flagged = model.screened_.compute()
    assert flagged.shape == (len(data.t),)
    # the samples left out are the contaminated ones (20 %), hardly any clean one
    assert (flagged & noisy.outliers).sum() >= 0.95 * noisy.outliers.sum()
    assert (flagged & ~noisy.outliers).sum() <= 0.02 * (~noisy.outliers).sum()
    with pytest.raises(ValueError, match="uniform time step only"):
        rs.HuberSINDy().fit(x, data.t)  # sample times, not a step: no derivatives


def test_huber_sindy_differentiates_dask_states_chunk_by_chunk(monkeypatch):
    from robust_sindy import outofcore as model_module

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1500)
    system = rs.systems.Lorenz()
    data = system.generate(t_end=30.0)
    rng = np.random.default_rng(1)
    x = data.x + 1e-3 * rng.normal(size=data.x.shape)
    x[rng.choice(len(x), 60, replace=False), 1] += 10.0  # single-entry spikes
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        model = rs.HuberSINDy().fit(da.from_array(x, chunks=700), 0.01)
    np.testing.assert_array_equal(model.support_, system.true_coef().T != 0)
    assert model.diagnostics_.certified.all()
    # chunk by chunk with overlap: the derivatives of the in-memory path, away from spikes,
    # with the windows chosen on the sample
    half = model.derivative_windows_
    assert np.array_equal(model.diagnostics_.derivative_half_window, half) and half.min() >= 2
    noise = temporal_screen(x[:1500], 0.01 * np.arange(1500)).scale
    whole = differentiate(x, 0.01 * np.arange(len(x)), "robust", half_window=half, scale=noise)

    def chunk(b):
        return differentiate(b, 0.01 * np.arange(len(b)), "robust", half_window=half, scale=noise)

    lazy = da.from_array(x, chunks=700).map_overlap(
        chunk,
        depth={0: model_module.DASK_OVERLAP, 1: 0}, boundary="none", dtype=float,
    ).compute()  # fmt: skip
    close = np.isclose(lazy, whole, rtol=1e-6, atol=1e-6).all(axis=1)
    assert close.mean() > 0.98


def test_uneven_and_mismatched_chunks_give_the_same_fit():
    x, y = _problem(2500, seed=4)
    theta = rs.PolynomialLibrary(2).fit_transform(x)
    ref = rs.fit(theta, y, delta=0.5, lam=1.0)
    th = da.from_array(theta, chunks=((100, 900, 1, 1499), (4, 6)))  # uneven, split columns
    yd = da.from_array(y, chunks=((1250, 1250), (1, 2)))  # other row chunks than theta's
    res = rs.fit(th, yd, delta=0.5, lam=1.0)
    assert res.converged
    np.testing.assert_allclose(res.objective, ref.objective, rtol=1e-8)
    np.testing.assert_allclose(res.coef, ref.coef, rtol=1e-6, atol=1e-8)


def test_from_npy_reads_each_chunk_in_its_task(tmp_path):
    a = np.random.default_rng(0).normal(size=(1050, 3))
    np.save(tmp_path / "a.npy", a)
    lazy = rs.outofcore.from_npy(tmp_path / "a.npy", chunk_rows=200)
    assert lazy.chunks == ((200, 200, 200, 200, 200, 50), (3,))
    np.testing.assert_array_equal(lazy.compute(), a)
    np.save(tmp_path / "b.npy", a[:, 0])
    with pytest.raises(ValueError, match="expected 2-D"):
        rs.outofcore.from_npy(tmp_path / "b.npy")
    with pytest.raises(ValueError, match="chunk_rows"):
        rs.outofcore.from_npy(tmp_path / "a.npy", chunk_rows=0)


def test_huber_sindy_on_a_list_of_dask_trajectories(monkeypatch):
    from robust_sindy import outofcore as model_module

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1500)
    system = rs.systems.Lorenz()
    rng = np.random.default_rng(2)
    parts = []
    for x0 in ([-8.0, 8.0, 27.0], [5.0, -3.0, 20.0]):
        x = system.generate(x0=x0, t_end=12.0).x  # 1201 samples each
        x = x + 1e-3 * rng.normal(size=x.shape)
        x[rng.choice(len(x), 25, replace=False), 2] += 15.0  # single-entry spikes
        parts.append(x)
    lazy = [da.from_array(a, chunks=400) for a in parts]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        model = rs.HuberSINDy().fit(lazy, 0.01)
    np.testing.assert_array_equal(model.support_, system.true_coef().T != 0)
    # the sample is the whole first trajectory and the start of the second
    assert model.dask_["sample"] == 1500 and model.dask_["samples"] == 2402
    assert model.screened_.shape == (2402,) and model.diagnostics_.certified.all()
    # the whole of each trajectory in memory selects the same terms
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        whole = rs.HuberSINDy().fit(parts, 0.01)
    np.testing.assert_array_equal(model.support_, whole.support_)
    np.testing.assert_allclose(model.coef_, whole.coef_, rtol=1e-2, atol=1e-3)
    with pytest.raises(ValueError, match="x_dot has 1 trajectories but x has 2"):
        rs.HuberSINDy().fit(lazy, 0.01, x_dot=[lazy[0]])
    with pytest.raises(ValueError, match="uniform time step only"):
        rs.HuberSINDy().fit(lazy, [np.arange(1201.0), np.arange(1201.0)])


def test_dask_states_leave_out_the_derivatives_the_sampling_does_not_resolve(monkeypatch):
    # Van der Pol with mu = 4.5, clean states only: each relaxation jump takes a few
    # samples.  Out of core the sample is fitted from its states as in memory, and the
    # samples of every chunk whose derivatives the sampling does not resolve are left
    # out of the refit, as the in-memory fit leaves them out.
    from robust_sindy import outofcore as model_module

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1500)
    t, x = van_der_pol(4.5, 103, m=3000)
    dt = t[1] - t[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)  # the sample's close calls
        model = rs.HuberSINDy(library=rs.PolynomialLibrary(3)).fit(da.from_array(x, chunks=700), dt)
    names = model.get_feature_names()
    true = np.zeros((2, len(names)), dtype=bool)
    true[0, names.index("x1")] = True
    true[1, [names.index(v) for v in ("x0", "x1", "x0^2*x1")]] = True
    assert np.array_equal(model.support_, true), model.equations()
    unresolved, screened = model.unresolved_, model.screened_.compute()
    assert unresolved.shape == (3000,) and model.dask_["unresolved"] == unresolved.sum() > 0
    assert screened[unresolved].all()
    # a fitted model pickles with its lazy results (their graph holds no local function)
    again = pickle.loads(pickle.dumps(model))
    np.testing.assert_array_equal(again.screened_.compute(), screened)
    np.testing.assert_array_equal(again.coef_, model.coef_)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        # in memory in the strong form too (Dask data are fitted in it)
        whole = rs.HuberSINDy(library=rs.PolynomialLibrary(3), formulation="strong").fit(x, dt)
    assert np.array_equal(whole.support_, true)
    # the same jumps, found chunk by chunk: nearly every sample left out in memory
    assert (unresolved & whole.unresolved_).sum() >= 0.9 * whole.unresolved_.sum()


def test_dask_fit_warns_when_the_rest_of_the_data_is_not_like_the_sample(monkeypatch):
    # The model is chosen on the first samples; when most of the rest is corrupted (a
    # sensor that fails after them), the out-of-core screen leaves much of the data out,
    # and the sample's clean diagnostics must not speak for it.
    from robust_sindy import outofcore as model_module

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1500)
    data = rs.systems.Lorenz().generate(t_end=29.99)  # 3000 samples
    rng = np.random.default_rng(3)
    x = data.x + 1e-3 * rng.normal(size=data.x.shape)

    def fit(x_dot):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model = rs.HuberSINDy().fit(
                da.from_array(x, chunks=500), 0.01, x_dot=da.from_array(x_dot, chunks=500)
            )
        return model, [str(w.message) for w in caught if "out of core" in str(w.message)]

    x_dot = data.x_dot.copy()
    bad = np.zeros(len(x), dtype=bool)
    bad[1500:] = rng.uniform(size=1500) < 0.7
    x_dot[bad] += 50.0 * rng.normal(size=(bad.sum(), 3))
    model, warned = fit(x_dot)
    assert np.array_equal(model.support_, rs.systems.Lorenz().true_coef().T != 0)
    assert model.diagnostics_.flagged_fraction < 0.05  # the sample is clean
    assert model.dask_["flagged"] > 0.3 * len(x)
    assert len(warned) == 1 and "may not describe the rest of the data" in warned[0]
    # the same corruption spread evenly: the sample shows it, out of core adds nothing
    x_dot = data.x_dot.copy()
    bad = rng.uniform(size=len(x)) < 0.2
    x_dot[bad] += 50.0 * rng.normal(size=(bad.sum(), 3))
    model, warned = fit(x_dot)
    assert model.dask_["flagged"] < 0.3 * len(x) and not warned


def test_dask_library_and_fit_with_control_inputs(monkeypatch):
    # States and inputs come in separate arrays, so their concatenation has two column
    # blocks: the library must see one block of all inputs per row chunk.
    from robust_sindy import outofcore as model_module

    monkeypatch.setattr(model_module, "DASK_SAMPLE", 1500)
    drone = rs.systems.Drone()
    data = drone.generate(t_end=30.0, dt=0.01)
    x = data.x + 1e-3 * data.x.std(axis=0) * np.random.default_rng(4).normal(size=data.x.shape)
    _, theta = rs.outofcore.dask_library(
        drone.library(), da.from_array(x, chunks=700), da.from_array(data.u, chunks=500),
        input_names=drone.input_names,
    )  # fmt: skip
    expected = drone.library().fit_transform(np.hstack([x, data.u]), input_names=drone.input_names)
    np.testing.assert_allclose(theta.compute(), expected)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rs.IdentificationWarning)
        model = rs.HuberSINDy(library=drone.library()).fit(
            da.from_array(x, chunks=700), 0.01, u=da.from_array(data.u, chunks=700),
            feature_names=drone.input_names,
        )  # fmt: skip
    np.testing.assert_array_equal(model.support_, drone.true_coef(full=True).T != 0)
