"""Numerical derivatives for data without measured derivatives.

Examples
--------
>>> import numpy as np
>>> t = np.linspace(0.0, 1.0, 201)
>>> x = np.sin(t)[:, None]
>>> bool(np.abs(finite_difference(x, t) - np.cos(t)[:, None]).max() < 1e-4)
True
>>> bool(np.abs(savgol_derivative(x, t) - np.cos(t)[:, None]).max() < 1e-5)
True
"""

from __future__ import annotations

import numpy as np
import scipy.signal

from ._validation import as_float_array, check_int
from .simulate import check_time

__all__ = ["finite_difference", "savgol_derivative"]


def _check(x, t, min_length: int) -> tuple[np.ndarray, np.ndarray]:
    x = as_float_array(x, "x", (1, 2))
    t = check_time(t, min_length=min_length)
    if x.shape[0] != t.size:
        raise ValueError(f"x has {x.shape[0]} rows but t has {t.size} time points")
    return x, t


def finite_difference(x, t) -> np.ndarray:
    """Second-order finite differences (central inside, one-sided at the ends).

    ``t`` may be non-uniform (:func:`numpy.gradient` with coordinates).
    """
    x, t = _check(x, t, 3)
    return np.gradient(x, t, axis=0, edge_order=2)


def savgol_derivative(x, t, window_length: int = 11, polyorder: int = 3) -> np.ndarray:
    """Savitzky-Golay smoothed derivative (:func:`scipy.signal.savgol_filter`).

    Needs a uniform ``t``; ``window_length`` (odd) must not exceed the number of samples
    and ``polyorder`` must be smaller than it.
    """
    window_length = check_int(window_length, "window_length", 3)
    polyorder = check_int(polyorder, "polyorder", 1)
    x, t = _check(x, t, window_length)
    if window_length % 2 == 0:
        raise ValueError(f"window_length must be odd; got {window_length}")
    if polyorder >= window_length:
        raise ValueError(f"polyorder ({polyorder}) must be < window_length ({window_length})")
    dt = np.diff(t)
    if np.ptp(dt) > 1e-9 * dt.mean():
        raise ValueError("t must be uniformly spaced for savgol_derivative; use finite_difference")
    return scipy.signal.savgol_filter(
        x, window_length, polyorder, deriv=1, delta=float(dt.mean()), axis=0, mode="interp"
    )
