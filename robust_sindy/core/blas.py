"""BLAS on one thread where the products are small.

Small products (a p x p block, one pass over a library of a few thousand rows) cost
less than starting BLAS threads; :func:`one_thread` limits every BLAS library loaded
in the process to one thread for a ``with`` block.  Its :class:`threadpoolctl.ThreadpoolController`
is made once, on first use (finding the libraries costs far more than a limit with it
made).
"""

from __future__ import annotations

_CONTROLLER = None


def one_thread():
    """A context manager that runs BLAS on one thread."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")
