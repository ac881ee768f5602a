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


def local_polynomial_derivative(
    x, t, half_window: int = 3, degree: int = 4, mask=None
) -> np.ndarray:
    """Derivative of a least-squares polynomial fitted around every sample.

    For sample ``i`` a polynomial of ``degree`` in relative time is fitted to the
    ``2 half_window + 1`` samples centred on it (the window shifted inside the data at
    the ends) and differentiated at ``t_i``.  On uniform samples with
    ``half_window = 2, degree = 4`` this is the fourth-order central difference;
    wider windows smooth.  Entries where ``mask`` is False (e.g. the outliers flagged
    by :func:`robust_sindy.selection.temporal_screen`) get zero weight, so an outlier
    is not smeared over its window as it is by :func:`savgol_derivative`.  ``t`` may be
    non-uniform.
    """
    half_window = check_int(half_window, "half_window", 1)
    degree = check_int(degree, "degree", 1)
    w = 2 * half_window + 1
    if degree >= w:
        raise ValueError(f"degree ({degree}) must be < 2 * half_window + 1 ({w})")
    x, t = _check(x, t, w)
    one_d = x.ndim == 1
    x2 = x[:, None] if one_d else x
    m, n = x2.shape
    weights = np.ones((m, n)) if mask is None else np.asarray(mask, dtype=float).reshape(m, -1)
    if weights.shape != (m, n):
        raise ValueError(f"mask must have the shape of x {x2.shape}; got {weights.shape}")
    start = np.clip(np.arange(m) - half_window, 0, m - w)
    idx = start[:, None] + np.arange(w)[None, :]
    tau = t[idx] - t[:, None]
    span = np.abs(tau).max(axis=1, keepdims=True)
    tau = tau / span
    v = tau[..., None] ** np.arange(degree + 1)
    wt = weights[idx]  # (m, w, n)
    # A window with too few weighted samples to fit the polynomial weighs all of them.
    wt = np.where((wt > 0).sum(axis=1, keepdims=True) > degree, wt, 1.0)
    gram = np.einsum("mjn,mja,mjb->mnab", wt, v, v)
    rhs = np.einsum("mjn,mja,mjn->mna", wt, v, x2[idx])
    ridge = 1e-12 * np.trace(gram, axis1=-2, axis2=-1)[..., None, None]
    coef = np.linalg.solve(gram + ridge * np.eye(degree + 1), rhs[..., None])[..., 0]
    out = coef[..., 1] / span  # d/dt of c1 tau at tau = 0
    return out[:, 0] if one_d else out
