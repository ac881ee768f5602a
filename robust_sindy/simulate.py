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
import scipy.integrate

from .core.validation import as_float_array, check_time

__all__ = ["input_function", "integrate", "rk4", "rk4_batch", "simulation_inputs"]


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


def rk4_batch(rhs: Callable, x0, t, u=None, *, substeps=1) -> np.ndarray:
    """Integrate ``x' = rhs(x, u)`` by classical RK4 from many starts at once.

    Each start ``i`` has its own grid ``t[i]`` (irregular sampling) and inputs
    ``u[i]``, interpolated linearly inside each interval.  Nothing is checked for
    divergence: a start whose solution overflows carries inf or NaN from then on (the
    caller reads them as a forecast that failed).

    Parameters
    ----------
    rhs : callable
        ``rhs(x, u)`` with ``x`` of shape (k, n) and ``u`` of shape (k, q) or ``None``,
        returning (k, n).
    x0 : ndarray, shape (k, n)
    t : ndarray, shape (k, s)
        Increasing output times of each start (columns: the steps).
    u : ndarray (k, s, q), optional
        Inputs at the output times.
    substeps : int or sequence of int (s - 1,)
        RK4 steps per output interval (one number for every interval, or one per
        column of intervals).

    Returns
    -------
    ndarray, shape (k, s, n)

    Examples
    --------
    >>> t = np.array([[0.0, 0.5, 1.0], [1.0, 1.2, 1.5]])
    >>> x = rk4_batch(lambda x, u: -x, np.ones((2, 1)), t, substeps=20)
    >>> bool(np.allclose(x[:, -1, 0], np.exp(-np.array([1.0, 0.5]))))
    True
    """
    x = np.array(x0, dtype=float)
    t = np.asarray(t, dtype=float)
    out = np.empty((x.shape[0], t.shape[1], x.shape[1]))
    out[:, 0] = x

    def inputs(j, a):
        return None if u is None else (1.0 - a) * u[:, j - 1] + a * u[:, j]

    counts = np.broadcast_to(np.asarray(substeps, dtype=int), (t.shape[1] - 1,))
    with np.errstate(all="ignore"):
        for j in range(1, t.shape[1]):
            steps = int(counts[j - 1])
            h = ((t[:, j] - t[:, j - 1]) / steps)[:, None]
            for s in range(steps):
                a0, a1 = s / steps, (s + 1) / steps
                um = inputs(j, (a0 + a1) / 2)
                k1 = rhs(x, inputs(j, a0))
                k2 = rhs(x + h / 2 * k1, um)
                k3 = rhs(x + h / 2 * k2, um)
                k4 = rhs(x + h * k3, inputs(j, a1))
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            out[:, j] = x
    return out


def simulation_inputs(x0, t, u, n: int, q: int):
    """``t``, ``x0`` and the input function of a simulation of ``n`` states and ``q``
    controls, checked (``u`` as :func:`robust_sindy.simulate.input_function` takes it)."""
    t = check_time(t, "t")
    x0 = as_float_array(x0, "x0", (1,))
    if x0.size != n:
        raise ValueError(f"x0 has {x0.size} values; the model has {n} states")
    uf = input_function(u, t)
    if (uf is None) != (q == 0):
        raise ValueError(
            f"u is required: the model was fitted with {q} controls"
            if q
            else "u given, but the model was fitted without controls"
        )
    if uf is not None:
        width = np.size(uf(t[0]))
        if width != q:
            raise ValueError(f"u has {width} columns but the model was fitted with {q}")
    return t, x0, uf


def integrate(f, x0, t, uf, kws: dict):
    """:func:`scipy.integrate.solve_ivp` of an exported right-hand side ``f`` on ``t``."""

    def rhs(s, state):
        # One sample as a batch of one: library callables get 1-D arrays, as in fit.
        return f(s, state[None, :], None if uf is None else uf(s)[None, :])[0]

    return scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), x0, t_eval=t, **kws)
