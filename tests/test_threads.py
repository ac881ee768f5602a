"""Independent compiled work in threads: the same results whatever the threads."""

import threading

import numpy as np
import pytest

from robust_sindy.core import compiled as _compiled
from robust_sindy.core import threads as _threads
from robust_sindy.core.blas import one_thread
from robust_sindy.selection import path
from robust_sindy.solvers import driver as _driver
from robust_sindy.timeseries.temporal import temporal_screen

from .conftest import random_problem


def _spy_on_threads(monkeypatch) -> list:
    """The names of the functions handed to map_threads' threads, as they run."""
    handed = []
    run = _threads._run
    monkeypatch.setattr(_threads, "_run", lambda f, i: (handed.append(f.__name__), run(f, i))[1])
    return handed


def _fit_and_screen_in_threads(monkeypatch, theta, y, start) -> list:
    """An unpenalised fast-path fit and the row screen of ``theta``, ``y`` in three
    threads, then in one (BLAS on one thread in both): ``[(fit, screen), (fit, screen)]``."""
    from robust_sindy import fit
    from robust_sindy.selection.rows import screen_rows

    out = []
    for k in (3, 1):
        monkeypatch.setattr(_threads, "threads", lambda k=k: k)
        with one_thread():
            out.append((fit(theta, y, delta=0.3, lam=0.0), screen_rows(theta, y, start=start)))
    return out


def test_map_threads_keeps_the_order_and_runs_nested_calls_inline(monkeypatch):
    monkeypatch.setattr(_threads, "MAX_THREADS", 2)
    monkeypatch.setattr(_threads, "threads", lambda: 2)
    names = []

    def inner(i):
        names.append(threading.current_thread().name)
        return i * i

    def outer(i):
        return _threads.map_threads(inner, range(i))  # inline: no deadlock, same order

    assert _threads.map_threads(outer, range(5)) == [[j * j for j in range(i)] for i in range(5)]
    assert all(name.startswith("robust_sindy") for name in names)


def test_threads_follow_omp_num_threads_and_the_module_bound(monkeypatch):
    monkeypatch.setattr(_threads, "MAX_THREADS", None)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert _threads.threads() == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert _threads.threads() >= 1
    monkeypatch.setattr(_threads, "MAX_THREADS", 1)
    assert _threads.threads() == 1
    ran_in = []
    _threads.map_threads(lambda i: ran_in.append(threading.current_thread()), range(3))
    assert ran_in == [threading.current_thread()] * 3


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="numba is not installed")
def test_path_and_temporal_screen_are_the_same_on_one_thread_and_on_several(monkeypatch):
    theta, y = random_problem(5, m=800, p=8, n=4, outliers=0.1)
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 20.0, 1500)
    x = np.column_stack([np.sin(t), np.cos(1.3 * t), np.sin(0.7 * t) ** 3])
    x = x + 1e-3 * rng.standard_normal(x.shape)
    x[rng.random(x.shape) < 0.03] += 2.0
    monkeypatch.setattr(_threads, "threads", lambda: 3)
    several = path(theta, y, 0.5), temporal_screen(x, t)
    monkeypatch.setattr(_threads, "threads", lambda: 1)
    one = path(theta, y, 0.5), temporal_screen(x, t)
    assert np.array_equal(several[0].coef, one[0].coef)
    assert np.array_equal(several[0].converged, one[0].converged)
    assert np.array_equal(several[1].flags, one[1].flags)
    assert np.array_equal(several[1].repaired, one[1].repaired)


def test_small_items_run_in_the_calling_thread(monkeypatch):
    monkeypatch.setattr(_threads, "threads", lambda: 2)
    ran_in = []
    work = _threads.THREAD_WORK
    _threads.map_threads(lambda i: ran_in.append(threading.current_thread()), range(3), work / 2)
    assert ran_in == [threading.current_thread()] * 3
    _threads.map_threads(lambda i: ran_in.append(threading.current_thread()), range(3), work)
    assert all(name.startswith("robust_sindy") for name in (t.name for t in ran_in[3:]))


def test_newton_and_the_row_screen_are_the_same_on_one_thread_and_on_several(monkeypatch):
    # Every per-column piece (inlier Gram matrices, their updates, Cholesky solves,
    # leverages) handed to threads, however small: the same numbers as in one thread
    # (BLAS on one thread in both, as in the threads: BLAS itself may round differently
    # on several).
    theta, y = random_problem(7, m=600, p=60, n=4, outliers=0.1)
    start = np.ones(600, dtype=bool)
    start[::37] = False
    monkeypatch.setattr(_threads, "THREAD_WORK", 0.0)
    monkeypatch.setattr(_driver, "USE_KERNEL", False)  # the NumPy Newton iteration
    handed = _spy_on_threads(monkeypatch)
    (f3, s3), (f1, s1) = _fit_and_screen_in_threads(monkeypatch, theta, y, start)
    assert np.array_equal(f3.coef, f1.coef)
    assert np.array_equal(s3.outliers, s1.outliers)
    assert np.array_equal(s3.scale, s1.scale)
    assert s3.outliers.sum() > 0
    # The pieces did run in threads (each module's per-column function is `column`).
    assert handed.count("column") > 100


def test_the_selection_is_the_same_on_one_thread_and_on_several(monkeypatch):
    """The selection stage's refits (the limits, the path's proposals, the subset
    search) run the equations side by side: the same choice, scores and candidates as
    in one thread, the refits' ConvergenceWarning filtered without leaking out."""
    import warnings

    from robust_sindy.selection import select

    theta, y = random_problem(11, m=500, p=12, n=4, outliers=0.1)
    filters = list(warnings.filters)
    out = []
    for k in (3, 1):
        monkeypatch.setattr(_threads, "threads", lambda k=k: k)
        with one_thread():
            out.append(select(theta, y, 0.5, max_iter=3))  # refits stop uncertified
    several, one = out
    assert warnings.filters == filters
    for name in ("coef", "candidates", "subsets"):
        assert np.array_equal(getattr(several, name), getattr(one, name)), name
    assert np.array_equal(several.scores, one.scores, equal_nan=True)
    assert np.array_equal(several.subset_scores, one.subset_scores, equal_nan=True)
    assert several.subsets.shape[0] > 0  # the subset search ran


def test_groups_of_equations_run_side_by_side_with_the_same_numbers(monkeypatch):
    """Where the Newton iteration takes the equations in several groups (their Gram
    matrices bounded by the library's memory), the fast path's fits and the row screen's
    pilots run the groups side by side: the same numbers as one after another."""
    theta, y = random_problem(3, m=150, p=60, n=5, outliers=0.1)
    assert len(_driver.column_groups(5, theta.shape)) >= 2
    start = np.ones(150, dtype=bool)
    start[::29] = False
    monkeypatch.setattr(_driver, "USE_KERNEL", False)  # the NumPy Newton iteration
    handed = _spy_on_threads(monkeypatch)
    (f3, s3), (f1, s1) = _fit_and_screen_in_threads(monkeypatch, theta, y, start)
    assert np.array_equal(f3.coef, f1.coef)
    assert np.array_equal(f3.converged, f1.converged)
    assert np.array_equal(s3.outliers, s1.outliers)
    assert np.array_equal(s3.scale, s1.scale)
    assert np.array_equal(s3.pilot[1], s1.pilot[1])
    assert handed.count("run_group") >= 2 and handed.count("one") >= 2  # in threads


def test_states_noise_and_local_scales_are_the_same_on_one_thread_and_on_several(monkeypatch):
    """Each state's library noise (central differences of the library) and the moving
    robust scales of residuals with entries left out run side by side: the same model
    and diagnostics as in one thread."""
    import warnings

    from robust_sindy import HuberSINDy, IdentificationWarning, PolynomialLibrary
    from robust_sindy.core.statistics import local_scale
    from robust_sindy.selection.bias import noise_columns

    rng = np.random.default_rng(2)
    values = rng.standard_normal((3000, 4))
    values[rng.random(values.shape) < 0.05] = np.nan
    t = np.linspace(0.0, 30.0, 1200)
    x = np.column_stack([np.sin(t), np.cos(t), np.sin(0.5 * t) * np.cos(t)])
    x = x + 0.01 * rng.standard_normal(x.shape)
    x[rng.choice(1200, 30, replace=False), rng.integers(0, 3, 30)] += 3.0  # glitches
    handed = _spy_on_threads(monkeypatch)
    out = []
    temporal = temporal_screen(x, t)
    library = PolynomialLibrary(degree=3).fit(x)
    coef = rng.standard_normal((library.n_output_features_, 2))
    for k in (3, 1):
        monkeypatch.setattr(_threads, "threads", lambda k=k: k)
        with one_thread():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", IdentificationWarning)
                model = HuberSINDy().fit(x, t)
            noise = noise_columns(library, x, temporal, 1.0)
            out.append(
                (local_scale(values, 12), model.coef_, model.screening_.outliers,
                 *noise.values, noise.carried(coef))
            )  # fmt: skip
    for a, b in zip(*out, strict=True):
        assert np.array_equal(a, b)
    assert np.isnan(values).any() and np.all(np.isfinite(out[0][0]))
    assert {"state", "column"} <= set(handed)
