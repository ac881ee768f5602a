"""Independent work of one fit on a Dask cluster, when one is in use.

Inside :func:`robust_sindy.parallel.scheduler` (``"local"`` or a scheduler's address),
:func:`client` gives the block's :class:`dask.distributed.Client`, and the stages that
fit groups of equations independently hand those groups to the cluster's workers with
:func:`map_tasks` (the row screen's pilots: :mod:`robust_sindy.selection.rows`); outside
such a block it gives ``None`` and every stage runs on this machine's cores
(:mod:`~robust_sindy.core.threads`).  A worker computes a group exactly as this process
would, BLAS on one thread, so the cluster changes where the work runs, not its numbers.
"""

from __future__ import annotations

import contextlib
import contextvars

import numpy as np

from .blas import one_thread

__all__ = ["client", "map_tasks", "scattered", "split", "using", "workers"]

_CLIENT: contextvars.ContextVar = contextvars.ContextVar("robust_sindy_client", default=None)


def client():
    """The Dask client of the innermost :func:`using` block (``None`` outside one)."""
    return _CLIENT.get()


@contextlib.contextmanager
def using(dask_client):
    """Within the block, :func:`client` is ``dask_client``."""
    token = _CLIENT.set(dask_client)
    try:
        yield dask_client
    finally:
        _CLIENT.reset(token)


def workers(dask_client) -> int:
    """How many workers the cluster has now (at least 1)."""
    return max(1, len(dask_client.scheduler_info().get("workers", {})))


def scattered(dask_client, array):
    """``array`` sent once to every worker (a future that tasks take as an argument)."""
    return dask_client.scatter(array, broadcast=True, hash=False)


def _one_thread_call(func, item, args):
    with one_thread():
        return func(item, *args)


def map_tasks(dask_client, func, items, *args) -> list:
    """``[func(item, *args) for item in items]``, one task per item on the cluster (``args``
    may hold :func:`scattered` futures), BLAS on one thread in each; in order."""
    futures = [dask_client.submit(_one_thread_call, func, item, args, pure=False) for item in items]
    return dask_client.gather(futures)


def split(k: int, parts: int) -> list[np.ndarray]:
    """``0, ..., k - 1`` in ``min(parts, k)`` contiguous runs whose lengths differ by at
    most one (none empty)."""
    return np.array_split(np.arange(k), max(1, min(parts, k)))
