"""Independent compiled work in threads: the same results whatever the threads."""

import threading

import numpy as np
import pytest

from robust_sindy.core import compiled as _compiled
from robust_sindy.core import threads as _threads
from robust_sindy.selection import path
from robust_sindy.timeseries.temporal import temporal_screen

from .conftest import random_problem


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
