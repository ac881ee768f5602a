"""Independent compiled work on the machine's cores.

The compiled kernels and BLAS release the GIL, so independent pieces of work (the path
walk of one target column, the local fits of one state, one equation's inlier Gram
matrix, Cholesky solve or leverages, a group of equations' Newton fits, one state's
library noise) run side by side in threads.  Each piece is computed exactly as it
would be alone with BLAS on one thread, so the results do not depend on the number
of threads (BLAS itself on several threads may round some products differently in the
last place).

The threads are those of the cores this process may use, at most ``OMP_NUM_THREADS``
when it is set (joblib's worker processes set it, so that parallel fits do not
oversubscribe the machine) and at most :data:`MAX_THREADS` when that is set (``1``
runs everything in the calling thread).  BLAS runs on one thread meanwhile.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

from .blas import one_thread

__all__ = ["MAX_THREADS", "THREAD_WORK", "map_threads", "threads"]

#: Upper bound on the threads (``None``: the cores, see the module's docstring).
MAX_THREADS: int | None = None

#: Floating-point operations per item below which :func:`map_threads` given ``flops``
#: runs in the calling thread: handing an item to a thread costs tens of microseconds,
#: the time of about this much arithmetic.
THREAD_WORK = 2e6

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_LOCK = threading.Lock()
_INSIDE = threading.local()


def threads() -> int:
    """How many threads :func:`map_threads` may use."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.strip().isdigit() and int(env) > 0:
        n = min(n, int(env))
    if MAX_THREADS is not None:
        n = min(n, int(MAX_THREADS))
    return max(1, n)


def _pool(size: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE
    with _LOCK:
        if _POOL is None or _POOL_SIZE < size:
            if _POOL is not None:
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(size, thread_name_prefix="robust_sindy")
            _POOL_SIZE = size
        return _POOL


def _run(func, item):
    _INSIDE.active = True
    try:
        return func(item)
    finally:
        _INSIDE.active = False


def map_threads(func, items, flops: float | None = None) -> list:
    """``[func(item) for item in items]``, the items spread over :func:`threads` threads
    (in the calling thread when there is one thread, one item, when called from one of
    these threads, or when ``flops``, the arithmetic of one item, is below
    :data:`THREAD_WORK`), BLAS on one thread meanwhile."""
    items = list(items)
    k = min(threads(), len(items))
    if k <= 1 or getattr(_INSIDE, "active", False) or (flops is not None and flops < THREAD_WORK):
        return [func(item) for item in items]
    pool = _pool(k)
    with one_thread():
        return list(pool.map(lambda item: _run(func, item), items))
