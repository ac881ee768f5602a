"""One fit's groups of equations on a Dask cluster: the same model as on this machine."""

import warnings

import numpy as np
import pytest

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.cli import main
from robust_sindy.core import cluster
from robust_sindy.flows import lorenz96_records
from robust_sindy.solvers.driver import column_groups


@pytest.mark.parametrize("k, parts", [(1, 3), (5, 2), (7, 3), (40, 4), (41, 2), (3, 1)])
def test_split_gives_contiguous_nearly_equal_runs(k, parts):
    runs = cluster.split(k, parts)
    assert [i for run in runs for i in run] == list(range(k))
    sizes = [len(run) for run in runs]
    assert min(sizes) >= 1 and len(runs) <= parts
    assert max(sizes) - min(sizes) <= max(sizes) // 2 + 1


@pytest.mark.parametrize("k, shape", [(40, (11900, 861)), (20, (3900, 231)), (6, (150, 28))])
def test_column_groups_are_as_few_as_the_memory_allows_and_even(k, shape):
    groups = column_groups(k, shape)
    bound = shape[0] // shape[1]  # Gram matrices of p^2 per column within m p
    sizes = [len(g) for g in groups]
    assert np.array_equal(np.concatenate(groups), np.arange(k))
    assert max(sizes) <= bound and max(sizes) - min(sizes) <= 1
    assert len(groups) == -(-k // bound)


def _records():
    # 150 samples for 28 terms: the pilots take the six equations in two groups.
    t, x, x_dot, _ = lorenz96_records(6, 150, 3)
    rng = np.random.default_rng(3)
    x_dot = x_dot.copy()
    rows = rng.choice(len(t), 12, replace=False)
    x_dot[rows] += 20.0 * rng.standard_normal((12, 6))  # corrupted rows: pilots iterate
    return t, x, x_dot


def _fit(t, x, x_dot):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return HuberSINDy(library=PolynomialLibrary(2)).fit(x, t, x_dot=x_dot)


def test_a_fit_inside_a_scheduler_sends_the_pilots_to_the_workers_with_the_same_model(
    monkeypatch,
):
    pytest.importorskip("distributed")
    from robust_sindy.parallel import scheduler

    t, x, x_dot = _records()
    here = _fit(t, x, x_dot)
    assert cluster.client() is None
    sent = []
    real = cluster.map_tasks

    def spy(dask_client, func, items, *args):
        sent.append(len(items))
        return real(dask_client, func, items, *args)

    monkeypatch.setattr(cluster, "map_tasks", spy)
    with scheduler("local", n_workers=2) as client:
        assert cluster.client() is client
        there = _fit(t, x, x_dot)
    assert cluster.client() is None
    assert sent and max(sent) == 2  # one run of groups per worker
    np.testing.assert_array_equal(there.coef_, here.coef_)
    np.testing.assert_array_equal(there.outliers_, here.outliers_)


def test_the_row_screen_on_a_cluster_gives_the_same_pilots_bit_for_bit():
    distributed = pytest.importorskip("distributed")
    from robust_sindy.selection.rows import screen_rows

    _, x, x_dot = _records()
    theta = PolynomialLibrary(2).fit_transform(x)
    here = screen_rows(theta, x_dot)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
        ) as local,
        distributed.Client(local) as client,
        cluster.using(client),
    ):
        there = screen_rows(theta, x_dot)
    assert there.rounds == here.rounds > 1
    np.testing.assert_array_equal(there.outliers, here.outliers)
    for a, b in zip(there.pilot, here.pilot, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_fit_command_names_a_bad_scheduler(tmp_path, capsys):
    data = tmp_path / "data.csv"
    data.write_text("t,x\n0,1\n1,2\n")
    with pytest.raises(SystemExit) as stop:
        main(["fit", str(data), "--scheduler", "", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert "--scheduler" in capsys.readouterr().err
