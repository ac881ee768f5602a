"""BLAS on one thread where the products are small.

Small products (a p x p block, one pass over a library of a few thousand rows) cost
less than starting BLAS threads; :func:`one_thread` limits every BLAS library loaded
in the process to one thread for a ``with`` block.  Its :class:`threadpoolctl.ThreadpoolController`
is made once, on first use (finding the libraries takes about 0.3 ms; a limit with it
made, about 10 microseconds).
"""

from __future__ import annotations

_CONTROLLER = None


def one_thread():
    """A context manager that runs BLAS on one thread (e.g. at m = 1e3, p = 35 a fast-path
    fit took 8.0 ms with OpenBLAS's two threads and 2.8 ms with one)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
