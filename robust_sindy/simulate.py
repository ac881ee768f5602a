"""Fixed-step integration (classical RK4) and input signals.

Examples
--------
>>> import numpy as np
>>> t = np.linspace(0.0, 1.0, 101)
>>> x = rk4(lambda t, x, u: -x, [1.0], t)
>>> float(abs(x[-1, 0] - np.exp(-1.0))) < 1e-9
True
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ._validation import as_float_array

__all__ = ["check_time", "input_function", "rk4"]


def check_time(t, name: str = "t", *, min_length: int = 2) -> np.ndarray:
    """Return ``t`` as a strictly increasing 1-D float array, or raise naming ``name``."""
    t = as_float_array(t, name, (1,))
    if t.size < min_length:
        raise ValueError(f"{name} must hold at least {min_length} time points; got {t.size}")
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{name} must be strictly increasing")
    return t


def input_function(u, t: np.ndarray, name: str = "u") -> Callable[[float], np.ndarray] | None:
    """Turn inputs into a function of time.

    ``u`` is ``None``, a callable of ``t`` returning a 1-D array (or a scalar for one
    input), or an array of shape (len(t), q) or (len(t),) sampled on ``t``, interpolated
    linearly between samples (and held constant outside ``t``).
    """
    if u is None:
        return None
    if callable(u):
        return lambda s: np.atleast_1d(np.asarray(u(s), dtype=float))
    arr = as_float_array(u, name, (1, 2))
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.shape[0] != t.size:
        raise ValueError(f"{name} has {arr.shape[0]} rows but t has {t.size} time points")
    cols = range(arr.shape[1])
    return lambda s: np.array([np.interp(s, t, arr[:, j]) for j in cols])


def rk4(
    rhs: Callable,
    x0,
    t,
    u=None,
    *,
    substeps: int = 1,
) -> np.ndarray:
    """Integrate ``x' = rhs(t, x, u)`` by classical RK4 on the grid ``t``.

    Parameters
    ----------
    rhs : callable
        ``rhs(t, x, u)`` with ``x`` of shape (n,) and ``u`` of shape (q,) or ``None``.
    x0 : array-like, shape (n,)
    t : array-like, shape (m,)
        Strictly increasing output times; each interval is one step (or ``substeps``).
    u : None, callable of t, or array (m, q)
        Inputs; arrays are interpolated linearly at the intermediate stages.
    substeps : int
        RK4 steps per output interval.

    Returns
    -------
    ndarray, shape (m, n)
    """
    t = check_time(t, min_length=1)
    x = as_float_array(x0, "x0", (1,))
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1; got {substeps!r}")
    uf = input_function(u, t)

    def f(s, y):
        return np.asarray(rhs(s, y, None if uf is None else uf(s)), dtype=float)

    out = np.empty((t.size, x.size))
    out[0] = x
    for k in range(t.size - 1):
        h = (t[k + 1] - t[k]) / substeps
        s = t[k]
        for _ in range(substeps):
            k1 = f(s, x)
            k2 = f(s + h / 2, x + h / 2 * k1)
            k3 = f(s + h / 2, x + h / 2 * k2)
            k4 = f(s + h, x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            s = s + h
        out[k + 1] = x
    return out
