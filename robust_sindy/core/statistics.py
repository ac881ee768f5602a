"""Robust statistics of time-ordered values: moving-window scales and correlation times.

* :func:`local_scale` -- the robust scale in a moving window, per column;
* :func:`smooth_local_scale` -- the same where the values vary smoothly in time;
* :func:`correlation_time` -- the integrated autocorrelation time of residuals.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from .threads import map_threads

__all__ = [
    "ALIAS_RTOL",
    "SCALE_FLOOR",
    "correlation_time",
    "local_scale",
    "running_median",
    "smooth_local_scale",
]


def local_scale(values: np.ndarray, half_width: int) -> np.ndarray:
    """Robust scale (``1.4826`` median absolute value) in a moving window, per column.

    ``values`` (m, n); the window holds ``2 half_width + 1`` samples, shifted inside the
    array at its ends.  NaN entries do not count; a window with nothing else gives 0.
    """
    a = np.abs(np.asarray(values, dtype=float))
    m = a.shape[0]
    w = min(2 * half_width + 1, m)
    if w % 2 and a.ndim == 2 and not np.isnan(a).any():
        # Odd windows without NaN: the running median of each column (the same middle
        # value), the windows at the ends shifted inside.
        return 1.4826 * running_median(a, w)
    start = np.clip(np.arange(m) - half_width, 0, m - w)
    windows = np.lib.stride_tricks.sliding_window_view(a, w, axis=0)  # (m - w + 1, n, w)
    if np.isnan(a).any():
        med = np.empty(windows.shape[:-1])

        def column(k):  # each column its own sorts, side by side (the same values)
            for lo in range(0, med.shape[0], _MEDIAN_ROWS):
                med[lo : lo + _MEDIAN_ROWS, k] = _nan_median(windows[lo : lo + _MEDIAN_ROWS, k])

        cols = range(med.shape[1]) if med.ndim == 2 else [...]
        # A sort moves and compares each entry about log2(w) times: some tens of flops.
        map_threads(column, cols, flops=10.0 * w * np.log2(w + 1) * med.shape[0])
    else:
        med = np.median(windows, axis=-1)
    return 1.4826 * med[start]


_MEDIAN_ROWS = 8192  # windows sorted at a time by _nan_median (bounds its memory)


def _nan_median(windows: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (0 where all are NaN): sorted once (NaN
    sort last), the middle one or two of each window's valid values picked by count."""
    srt = np.sort(windows, axis=-1)
    count = np.sum(~np.isnan(windows), axis=-1)
    lo = np.maximum((count - 1) // 2, 0)[..., None]
    hi = np.maximum(count // 2, 0)[..., None]
    pick = np.take_along_axis(srt, lo, -1)[..., 0] + np.take_along_axis(srt, hi, -1)[..., 0]
    return np.where(count > 0, 0.5 * pick, 0.0)


#: Ratio of the local scale of the residuals' first differences to the local scale of
#: the residuals below which they count as smooth (white noise gives about ``sqrt 2``).
_SMOOTH_RATIO = 0.5


def smooth_local_scale(values: np.ndarray, half_width: int) -> np.ndarray:
    """:func:`local_scale` where the values vary smoothly in time, 0 where they do not.

    Large errors that vary smoothly from sample to sample (the bias of a local fit or
    of numerical derivatives along a fast excursion) are the data's own structure;
    large errors that jump from sample to sample are noise, however many there are in
    a row (a burst): only the former raise the local bound of the screens.
    """
    a = np.asarray(values, dtype=float)
    if a.shape[0] < 3:
        return np.zeros_like(a)
    scale = local_scale(a, half_width)
    rough = local_scale(np.diff(a, axis=0, prepend=a[:1]), half_width)
    return np.where(rough < _SMOOTH_RATIO * scale, scale, 0.0)


def running_median(a: np.ndarray, size: int) -> np.ndarray:
    """Running median of each column of ``a`` (m, n) over ``size`` samples (odd), the
    windows at the ends shifted inside the array (column by column: the one-dimensional
    filter is the fast one); an array no longer than the window has its median
    everywhere.  Padding the ends by their nearest value instead would
    make the first and the last value more than half of their windows: their own
    medians, whatever they are."""
    m, h = a.shape[0], size // 2
    if m <= size:  # one window: the whole array
        return np.broadcast_to(np.median(a, axis=0), a.shape).astype(a.dtype)
    out = np.empty_like(a)
    for k in range(a.shape[1]):
        out[:, k] = scipy.ndimage.median_filter(a[:, k], size=size, mode="nearest")
    if h > 0:
        out[:h] = np.median(a[:size], axis=0)
        out[m - h :] = np.median(a[m - size :], axis=0)
    return out


def correlation_time(residuals, segments=None, max_lag: int = 100) -> np.ndarray:
    """Integrated autocorrelation time per column of time-ordered ``residuals`` (m, n).

    ``tau = 1 + 2 sum_l rho_l``, the sum over lags until the autocorrelation first falls
    below 0.05 (at most ``max_lag``), within each trajectory of ``segments`` (slices);
    at least 1.  ``m / tau`` samples of the residuals carry as much information as
    ``m`` independent ones: residuals of numerically differentiated data are smooth in
    time, and without this correction a criterion takes their systematic part for
    signal and adds spurious terms.
    """
    r = np.asarray(residuals, dtype=float)
    r = r[:, None] if r.ndim == 1 else r
    segments = [slice(0, r.shape[0])] if segments is None else segments
    r = r - np.mean(r, axis=0)
    var = np.sum(r**2, axis=0)
    tau = np.ones(r.shape[1])
    alive = var > 0
    for lag in range(1, max_lag + 1):
        acf = np.zeros(r.shape[1])
        for seg in segments:
            a = r[seg]
            if a.shape[0] > lag:
                acf += np.einsum("ij,ij->j", a[lag:], a[:-lag])
        rho = np.where(var > 0, acf / np.where(var > 0, var, 1.0), 0.0)
        alive &= rho >= 0.05
        if not alive.any():
            break
        tau += np.where(alive, 2 * rho, 0.0)
    return tau


#: Relative floor of every scale (to the spread of what is screened): errors below
#: ``1e-4`` of a signal's spread change no identification, and on noise-free data the
#: smooth bias of the local fits must not be mistaken for an outlier.
SCALE_FLOOR = 1e-4


#: Relative distance of a column to the span of the earlier ones below which it is
#: an exact linear combination of them: far below any measurement noise (1e-10 of the
#: column's norm), far above the rounding of a constant state (about 1e-14).
ALIAS_RTOL = 1e-10
