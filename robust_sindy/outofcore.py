"""Libraries of Dask arrays: ``Theta`` as a lazy expression of the states, chunk by chunk.

:func:`dask_library` fits a library's names and returns ``Theta`` as a Dask array with
the row chunks of the states; every pass of :func:`robust_sindy.fit` over it evaluates
the library on one chunk at a time, so ``Theta`` is never held whole.

    >>> import dask.array as da, numpy as np, robust_sindy as rs
    >>> x = da.from_array(np.random.default_rng(0).normal(size=(1000, 2)), chunks=(250, 2))
    >>> lib, theta = rs.outofcore.dask_library(rs.PolynomialLibrary(2), x)
    >>> theta.shape, theta.chunks[0], lib.get_feature_names()[:3]
    ((1000, 6), (250, 250, 250, 250), ['1', 'x0', 'x1'])
"""

from __future__ import annotations

import numpy as np
from sklearn.base import clone

from .library import BaseLibrary, PolynomialLibrary

__all__ = ["dask_library", "from_npy"]


def _read_rows(path: str, start: int, stop: int) -> np.ndarray:
    return np.array(np.load(path, mmap_mode="r")[start:stop])


def from_npy(path, chunk_rows: int = 1_000_000):
    """A ``.npy`` file (2-D) as a Dask array whose tasks each read their own rows.

    Each chunk is read from the file when its task runs and released when the task's
    consumers are done, so a pass holds about as many chunks as there are workers.
    (``dask.array.from_array`` on a ``numpy.memmap`` held copies of many chunks at
    once: 0.6 GB for a sum over 10 chunks of 24 MB, against 0.18 GB this way.)
    """
    import dask
    import dask.array as da

    path = str(path)
    head = np.load(path, mmap_mode="r")
    if head.ndim != 2:
        raise ValueError(f"{path!r} holds a {head.ndim}-D array; expected 2-D")
    m, k = head.shape
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, int) or chunk_rows < 1:
        raise ValueError(f"chunk_rows must be an integer >= 1; got {chunk_rows!r}")
    parts = [
        da.from_delayed(
            dask.delayed(_read_rows)(path, a, min(m, a + chunk_rows)),
            shape=(min(m, a + chunk_rows) - a, k),
            dtype=head.dtype,
        )
        for a in range(0, m, chunk_rows)
    ]
    return da.concatenate(parts, axis=0)


def dask_library(library: BaseLibrary | None, x, u=None, input_names=None):
    """The fitted library and ``Theta(x, u)`` as a lazy Dask array (same row chunks as ``x``).

    ``x`` (m, n) and ``u`` (m, q) are Dask arrays (or arrays, wrapped), chunked by rows
    only; ``u`` is rechunked to ``x``'s rows.
    """
    import dask.array as da

    x = da.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"x must be 2-D; got shape {x.shape}")
    x = x.rechunk({1: -1})
    z = x
    if u is not None:
        u = da.asarray(u)
        u = u[:, None] if u.ndim == 1 else u
        if u.shape[0] != x.shape[0]:
            raise ValueError(f"u has {u.shape[0]} samples but x has {x.shape[0]}")
        z = da.concatenate([x, u.rechunk({0: x.chunks[0], 1: -1})], axis=1).rechunk({1: -1})
    lib = clone(library) if library is not None else PolynomialLibrary()
    lib.fit(np.zeros((1, z.shape[1])), input_names=input_names)
    p = lib.n_output_features_
    theta = z.map_blocks(
        lib.transform,
        chunks=(z.chunks[0], (p,)),
        dtype=float,  # a bound method: picklable
    )
    return lib, theta
