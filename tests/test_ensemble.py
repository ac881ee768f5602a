"""Robust ensembles: inclusion probabilities, aggregation, bands, and what they warn."""

import numpy as np
import pytest
from sklearn.exceptions import NotFittedError

import robust_sindy as rs
from robust_sindy.ensemble import DroppedTerms
from robust_sindy.noise import contaminate


@pytest.fixture(scope="module")
def lorenz():
    system = rs.systems.Lorenz()
    data = system.generate(t_end=6.0)
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(1))
    return system, data, noisy


pytestmark = pytest.mark.filterwarnings("ignore::robust_sindy.IdentificationWarning")


def _fit(**kw):
    return rs.EnsembleSINDy(**kw)


def test_block_ensemble_on_contaminated_lorenz(lorenz):
    system, data, noisy = lorenz
    ens = _fit(n_models=6, random_state=0).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    truth = system.true_coef().T != 0
    pi = ens.inclusion_probability_
    assert pi.shape == truth.shape and ens.coef_stack_.shape == (6, *truth.shape)
    assert pi[truth].min() == 1.0 and pi[~truth].max() <= 0.2
    np.testing.assert_array_equal(ens.support_, truth)
    np.testing.assert_allclose(ens.coef_[truth], system.true_coef().T[truth], rtol=1e-2)
    q = ens.coef_quantiles_
    assert q.shape == (3, *truth.shape) and np.all(q[0] <= q[1]) and np.all(q[1] <= q[2])
    assert ens.equations()[0].startswith("-10.0")
    np.testing.assert_allclose(ens.predict(data.x), data.x_dot, rtol=0, atol=0.05)


def test_same_random_state_same_ensemble_whatever_the_workers(lorenz):
    _, data, noisy = lorenz
    a = _fit(n_models=3, random_state=7, n_jobs=1).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    b = _fit(n_models=3, random_state=7, n_jobs=2).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    np.testing.assert_array_equal(a.coef_stack_, b.coef_stack_)


def test_rows_sampling_and_library_ensembles(lorenz):
    system, data, noisy = lorenz
    ens = _fit(n_models=5, sampling="rows", library_ensemble=True, n_drop=2, random_state=0)
    ens.fit(noisy.x, data.t)  # derivatives computed once, on the full trajectory
    assert ens.available_.shape == (5, 10) and (~ens.available_).sum() == 10
    # a term a model did not have is zero in its coefficients
    assert np.all(ens.coef_stack_.transpose(0, 2, 1)[~ens.available_] == 0)
    # The members whose library kept every true term of an equation select them: with
    # two of the ten terms dropped, the others are misspecified for some equation.
    truth = system.true_coef().T != 0
    hits = [
        ens.coef_stack_[i, k, truth[k]] != 0
        for k in range(truth.shape[0])
        for i in range(ens.available_.shape[0])
        if ens.available_[i, truth[k]].all()
    ]
    assert len(hits) >= 3 and np.mean(np.concatenate(hits)) >= 0.75


def test_uncertain_terms_are_named_in_a_warning(lorenz):
    _, data, noisy = lorenz
    ens = _fit(n_models=4, random_state=0).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    assert not ens.uncertain_.any()
    # half of the models with a spurious x0*x2 term in the first equation
    ens.coef_stack_[:2, 0, 6] = 0.01
    ens._aggregate()
    assert ens.inclusion_probability_[0, 6] == 0.5 and ens.uncertain_[0, 6]
    with pytest.warns(rs.IdentificationWarning, match=r"\(x0\)': x0\*x2 \(0\.50\)"):
        ens._warn()
    # most models warned: the ensemble says so, with the most frequent message
    ens.warned_fraction_, ens.member_warnings_ = 0.75, {"library noise": 3, "other": 1}
    with pytest.warns(
        rs.IdentificationWarning, match="75 % of the resampled fits warned.*library noise"
    ):
        ens._warn()


def test_simulate_gives_ordered_quantile_bands_and_figures(lorenz):
    import matplotlib

    matplotlib.use("Agg")
    _, data, noisy = lorenz
    ens = _fit(n_models=4, random_state=0).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    band = ens.simulate(data.x[0], data.t[:100])
    assert band.shape == (3, 100, 3)
    assert np.all(band[0] <= band[1] + 1e-12) and np.all(band[1] <= band[2] + 1e-12)
    np.testing.assert_allclose(band[1], data.x[:100], rtol=0, atol=0.05)
    ens.plot_inclusion()
    ens.plot_simulation(data.x[0], data.t[:100], data=data.x[:100])


def test_bad_parameters_and_unfitted_use(lorenz):
    _, data, noisy = lorenz
    for kw, msg in [
        (dict(n_models=1), "n_models"),
        (dict(sampling="shuffle"), "sampling"),
        (dict(block_length=3), "block_length"),
        (dict(aggregate="mode"), "aggregate"),
        (dict(inclusion_threshold=0), "inclusion_threshold"),
        (dict(estimator="HuberSINDy"), "estimator"),
        (dict(library_ensemble=True, n_drop=10), "n_drop"),
    ]:
        with pytest.raises(ValueError, match=msg):
            rs.EnsembleSINDy(**kw).fit(noisy.x, data.t, x_dot=noisy.x_dot)
    for call in (lambda e: e.print(), lambda e: e.simulate(data.x[0], data.t[:5])):
        with pytest.raises(NotFittedError):
            call(rs.EnsembleSINDy())


def test_dropped_terms_library():
    lib = DroppedTerms(rs.PolynomialLibrary(2), drop=[0, 3]).fit(np.ones((2, 2)))
    assert lib.get_feature_names() == ["x0", "x1", "x0*x1", "x1^2"]
    np.testing.assert_array_equal(lib.transform(np.array([[2.0, 3.0]])), [[2.0, 3.0, 6.0, 9.0]])


def test_ensemble_on_a_local_dask_cluster_matches_joblib(lorenz):
    pytest.importorskip("distributed")
    from robust_sindy.parallel import scheduler

    _, data, noisy = lorenz
    a = _fit(n_models=2, random_state=3).fit(noisy.x[:300], data.t[:300], x_dot=noisy.x_dot[:300])
    with scheduler("local", n_workers=1) as client:
        assert client is not None
        b = _fit(n_models=2, random_state=3).fit(
            noisy.x[:300], data.t[:300], x_dot=noisy.x_dot[:300]
        )
    np.testing.assert_array_equal(a.coef_stack_, b.coef_stack_)
    with scheduler(None) as nothing:
        assert nothing is None
    with pytest.raises(ValueError, match="scheduler must be"):
        with scheduler(""):
            pass


def test_block_sampling_never_splits_a_block(lorenz):
    _, data, noisy = lorenz
    ens = rs.EnsembleSINDy(block_length=40)
    rng = np.random.default_rng(0)
    xs, ts = [noisy.x[:250], noisy.x[250:]], [data.t[:250], data.t[250:]]
    out_x, out_t, _, _, _ = ens._resample(rng, xs, ts, None, None, None)
    assert len(out_x) == int(np.ceil(250 / 40)) + int(np.ceil((len(data.t) - 250) / 40))
    for block_x, block_t in zip(out_x, out_t, strict=True):
        assert len(block_x) == 40
        # one contiguous run of one trajectory: consecutive times, the states at them
        np.testing.assert_allclose(np.diff(block_t), 0.01, rtol=1e-9)
        start = round((block_t[0] - data.t[0]) / 0.01)
        np.testing.assert_array_equal(block_x, noisy.x[start : start + 40])
        assert (start + 40 <= 250) or (start >= 250)  # never across two trajectories
