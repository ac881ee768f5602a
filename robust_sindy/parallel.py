"""Where parallel work runs: joblib's processes by default, or a Dask cluster on request.

``with scheduler("local"):`` starts a :class:`dask.distributed.LocalCluster` for the
block and routes joblib (seeds of ``robust-sindy reproduce`` and ``zoo``, the models of
:class:`~robust_sindy.EnsembleSINDy`) through it; ``scheduler("tcp://host:8786")``
connects to a running cluster instead; ``scheduler(None)`` changes nothing.  Inside the
block, :meth:`~robust_sindy.HuberSINDy.fit` also sends the row screen's pilot fits to
the workers, in groups of equations (:mod:`robust_sindy.core.cluster`; the same model
bit for bit).  Needs ``pip install "robust_sindy[dask]"``.
"""

from __future__ import annotations

import contextlib

from .core import cluster

__all__ = ["scheduler"]


@contextlib.contextmanager
def scheduler(address: str | None, n_workers: int | None = None):
    """Run joblib work inside the block on Dask (``"local"`` or a scheduler address)."""
    if address is None:
        yield None
        return
    if not isinstance(address, str) or not address:
        raise ValueError(f"scheduler must be 'local' or a scheduler address; got {address!r}")
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise ImportError(
            'a Dask scheduler needs dask and distributed: pip install "robust_sindy[dask]"'
        ) from None
    from joblib import parallel_config

    with contextlib.ExitStack() as stack:
        if address == "local":
            local = stack.enter_context(
                LocalCluster(n_workers=n_workers, threads_per_worker=1, dashboard_address=None)
            )
            client = stack.enter_context(Client(local))
        else:
            try:
                client = stack.enter_context(Client(address, timeout="10s"))
            except OSError as exc:
                raise ValueError(f"cannot reach the Dask scheduler at {address!r}: {exc}") from None
        stack.enter_context(parallel_config(backend="dask", n_jobs=-1))
        stack.enter_context(cluster.using(client))
        yield client
