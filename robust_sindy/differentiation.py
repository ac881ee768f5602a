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

__all__ = [
    "finite_difference",
    "local_polynomial_derivative",
    "savgol_derivative",
]


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


def _nearest_usable(usable: np.ndarray, size: int) -> np.ndarray:
    """For each sample, the indices (ascending) of the ``size`` usable samples nearest
    to it in index (itself included when usable); on an all-usable array these are the
    centred windows, shifted inside at the ends."""
    m = usable.size
    u = np.flatnonzero(usable)
    i = np.arange(m)
    pos = np.searchsorted(u, i)
    cand = pos[:, None] + np.arange(-size, size)[None, :]
    valid = (cand >= 0) & (cand < u.size)
    idx = u[np.clip(cand, 0, u.size - 1)]
    # distance, ties broken towards the earlier sample; invalid candidates last
    dist = np.where(valid, 2.0 * np.abs(idx - i[:, None]) + (idx > i[:, None]), np.inf)
    best = np.argsort(dist, axis=1, kind="stable")[:, :size]
    return np.sort(np.take_along_axis(idx, best, axis=1), axis=1)


def _local_fit(x2, t, usable, half_window, degree):
    """Per sample and component: the derivative of the least-squares polynomial through
    the ``2 half_window + 1`` usable samples nearest to it."""
    m, n = x2.shape
    size = 2 * half_window + 1
    out = np.empty((m, n))
    for k in range(n):
        ok = usable[:, k] if usable[:, k].sum() >= size else np.ones(m, dtype=bool)
        idx = _nearest_usable(ok, size)
        tau = t[idx] - t[:, None]
        span = np.abs(tau).max(axis=1, keepdims=True)
        tau = tau / np.where(span > 0, span, 1.0)
        v = tau[..., None] ** np.arange(degree + 1)  # (m, size, d+1)
        gram = np.einsum("mja,mjb->mab", v, v)
        rhs = np.einsum("mja,mj->ma", v, x2[idx, k])
        ridge = 1e-12 * np.trace(gram, axis1=-2, axis2=-1)[..., None, None]
        coef = np.linalg.solve(gram + ridge * np.eye(degree + 1), rhs[..., None])[..., 0]
        out[:, k] = coef[:, 1] / span[:, 0]  # d/dt of c1 tau at tau = 0
    return out


def local_polynomial_derivative(x, t, half_window: int = 2, degree: int = 4, mask=None):
    """Derivative of a least-squares polynomial fitted around every sample.

    For sample ``i`` a polynomial of ``degree`` in relative time is fitted to the
    ``2 half_window + 1`` samples centred on it (the window shifted inside the data at
    the ends) and differentiated at ``t_i``.  With the defaults
    (``half_window = 2, degree = 4``) on uniform samples this is the fourth-order
    central difference: its error is a systematic ``O(dt^4)`` bias that a regression on
    a library would otherwise explain with spurious terms.  Wider windows average the
    noise away at the price of that bias (on a trajectory sampled at 100 samples per
    period, a 7-sample quartic already puts percent-level errors on its fast
    excursions).  Entries where ``mask`` is False (e.g. the outliers flagged by
    :func:`robust_sindy.selection.temporal_screen`) are left out: the window of a
    sample is then its ``2 half_window + 1`` nearest samples that are not, so an
    outlier is not smeared over its window as it is by :func:`savgol_derivative`, and
    the derivatives next to it keep their order.  ``t`` may be non-uniform.
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
    usable = np.ones((m, n), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if usable.shape != (m, n) and usable.size == m * n:
        usable = usable.reshape(m, n)
    if usable.shape != (m, n):
        raise ValueError(f"mask must have the shape of x {x2.shape}; got {usable.shape}")
    out = _local_fit(x2, t, usable, half_window, degree)
    return out[:, 0] if one_d else out
