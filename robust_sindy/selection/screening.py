"""Sample screening in two layers: temporal (model-free), then model-based.

* :func:`temporal_screen` -- the states are samples of a smooth trajectory: a gross
  error in one component (a spike, a dropout, a burst of noise) is inconsistent with the
  neighbouring samples of that component.  Each sample is predicted by a local
  polynomial fitted to its neighbours in time (leave-one-out, flagged neighbours left
  out), and flagged when its prediction error is gross compared with both the
  component's global robust scale and the local robust scale of the errors around it
  (so that a fast excursion, where every prediction is less accurate, is not mistaken
  for an outlier).  It needs no model, sees errors in one component at a time, and gives
  a repaired trajectory (flagged entries replaced by their prediction) to differentiate.
  Where the local fits cannot follow smooth samples at all (an excursion only a few
  samples long) it flags nothing: it cannot tell an outlier there from the data's own
  structure.
* :func:`screen_rows` -- flags whole samples by their residual under an unpenalised
  Huber pilot, fitted on a clean start (the temporally unflagged samples), with
  per-equation scales estimated from the inliers.  It flags by residual only, never by
  leverage: a rare excursion that the model fits is the most informative sample, not an
  outlier.

All scales are robust scales of the data themselves, so every decision is unit-free.
The components' local fits are independent and run side by side on the machine's cores
(:func:`robust_sindy._threads.map_threads`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.ndimage

from .._fit import ConvergenceWarning, fit
from .._scaling import robust_scale
from .._threads import map_threads
from .._validation import as_float_array, check_int, check_positive, check_problem
from . import _temporal_kernels
from .bias import carried_noise, residual_noise_factor
from .path import pilot_budget
from .scale import _check_method, auto_delta

__all__ = [
    "Screening",
    "TemporalScreening",
    "local_scale",
    "screen_rows",
    "smooth_local_scale",
    "temporal_screen",
]

#: Relative floor of every scale (to the spread of what is screened): errors below
#: ``1e-4`` of a signal's spread change no identification, and on noise-free data the
#: smooth bias of the local fits must not be mistaken for an outlier.
_SCALE_FLOOR = 1e-4
#: Floor of the temporal screen's scales relative to the largest magnitude of a
#: component (about 4500 rounding units): a component constant up to rounding (a state
#: that does not move, stored as floats) must not have entries flagged by its rounding.
_ROUNDING_FLOOR = 1e-12
#: Rounds of the model-based screen in which flags may also be withdrawn.
_FREE_ROUNDS = 5
#: How many times more some library direction must be excited (mean square per sample)
#: by all the samples than by the start for the iteration from every sample to compete:
#: a start that lost a fast excursion loses a direction (on the zoo's LiuChen and
#: AtmosphericRegime: 4e3 to 3e5 times), a start that lost scattered outliers does not
#: (3 to 25 times with rows or spikes contamination).
_COMPETE_EXCITATION = 100.0
#: Fraction of the samples by which the iteration from every sample must explain more
#: than the one from the start to replace it (the screen's nominal false-positive
#: rate: smaller differences are the noise of two fits of the same model).
_COMPETE_MARGIN = 0.02


@dataclass(repr=False)
class TemporalScreening:
    """Outcome of :func:`temporal_screen` (one or several trajectories, stacked).

    Attributes
    ----------
    flags : ndarray of bool, shape (m, n)
        Entries inconsistent with their neighbours in time.
    repaired : ndarray, shape (m, n)
        The states with flagged entries replaced by their local prediction.
    scale : ndarray, shape (n,)
        The noise level of each component: the robust scale of the studentised
        prediction errors of the entries left unflagged (largest over the
        trajectories).
    skipped : int
        Trajectories too short to screen (fewer than ``2 half_window + 2`` samples).
    """

    flags: np.ndarray
    repaired: np.ndarray
    scale: np.ndarray
    skipped: int

    def __repr__(self) -> str:
        rows = int(self.flags.any(axis=1).sum())
        return (
            f"TemporalScreening(flagged {int(self.flags.sum())} entries in {rows} of "
            f"{self.flags.shape[0]} samples, skipped {self.skipped} short trajectories)"
        )


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
        med = _running_median(a, w)
        h = w // 2
        med[:h] = np.median(a[:w], axis=0)
        med[m - h :] = np.median(a[m - w :], axis=0)
        return 1.4826 * med
    start = np.clip(np.arange(m) - half_width, 0, m - w)
    windows = np.lib.stride_tricks.sliding_window_view(a, w, axis=0)  # (m - w + 1, n, w)
    if np.isnan(a).any():
        med = np.empty(windows.shape[:-1])
        for lo in range(0, med.shape[0], _MEDIAN_ROWS):
            med[lo : lo + _MEDIAN_ROWS] = _nan_median(windows[lo : lo + _MEDIAN_ROWS])
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


#: Samples of the running median that estimates the smooth bias of a local fit.
_BIAS_WINDOW = 7
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


def _running_median(a: np.ndarray, size: int) -> np.ndarray:
    """Running median of each column of ``a`` (m, n) over ``size`` samples, the ends
    padded by their nearest value (column by column: the one-dimensional filter is the
    fast one)."""
    out = np.empty_like(a)
    for k in range(a.shape[1]):
        out[:, k] = scipy.ndimage.median_filter(a[:, k], size=size, mode="nearest")
    return out


def _window_max(a: np.ndarray, h: int) -> np.ndarray:
    """Maximum of ``a`` (m, n) over the ``2h + 1`` samples centred on each sample."""
    padded = np.pad(a, ((h, h), (0, 0)), constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * h + 1, axis=0).max(axis=-1)


def _clean_neighbours(flags: np.ndarray, h: int, at=None) -> np.ndarray:
    """For each sample (each of ``at``), its ``2h`` nearest unflagged other samples (h on
    each side, topped up from the other side at the ends); -1 where there are not
    enough."""
    m = flags.size
    u = np.flatnonzero(~flags)
    i = np.arange(m) if at is None else np.asarray(at)
    left_end = np.searchsorted(u, i, side="left")  # unflagged samples before i
    right_start = np.searchsorted(u, i, side="right")  # first unflagged after i
    n_right = u.size - right_start
    nl = np.minimum(h, left_end)
    nr = np.minimum(2 * h - nl, n_right)
    nl = np.minimum(2 * h - nr, left_end)
    k = np.arange(2 * h)[None, :]
    pos = np.where(
        k < nl[:, None], left_end[:, None] - nl[:, None] + k, right_start[:, None] + k - nl[:, None]
    )
    valid = k < (nl + nr)[:, None]
    return np.where(valid, u[np.clip(pos, 0, max(u.size - 1, 0))], -1)


def _loo_predict(x, t, nb, degree, at=None):
    """Leave-one-out local polynomial prediction of ``x`` (m,) from the neighbours ``nb``
    (m, 2h; -1 unused), and the factor ``sqrt(1 + sum_j w_j^2)`` by which the prediction
    error's standard deviation exceeds that of the noise.  ``at``: the samples whose
    neighbours the rows of ``nb`` are (all samples when omitted)."""
    done = _temporal_kernels.loo_predict(x, t, nb, degree, np.arange(t.size) if at is None else at)
    if done is not None:
        return done
    valid = nb >= 0
    idx = np.where(valid, nb, 0)
    here = t if at is None else t[at]
    tau = np.where(valid, t[idx] - here[:, None], 0.0)
    span = np.abs(tau).max(axis=1, keepdims=True)
    tau = tau / np.where(span > 0, span, 1.0)  # relative time: unit-free
    # The weights depend only on the pattern of relative times (with uniform sampling,
    # one pattern for every sample away from the ends and the flagged samples): each
    # distinct pattern (to 1e-9 of the span) is solved once.
    key = np.where(valid, np.round(tau * 1e9), np.iinfo(np.int64).min).astype(np.int64)
    first, inverse = _unique_rows(key)
    tau_u, valid_u = tau[first], valid[first]
    v = (tau_u[..., None] ** np.arange(degree + 1)) * valid_u[..., None]  # (u, 2h, d+1)
    gram = np.einsum("mja,mjb->mab", v, v)
    gram += 1e-12 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(degree + 1)
    # Row 0 of gram^-1 V^T: the weights of the fitted value at tau = 0.
    weights = np.linalg.solve(gram, np.swapaxes(v, 1, 2))[:, 0, :][inverse]
    pred = np.einsum("mj,mj->m", weights, x[idx])
    return pred, np.sqrt(1.0 + np.sum(weights**2, axis=1))


def _unique_rows(key: np.ndarray):
    """``(first, inverse)`` of the distinct rows of the integer array ``key`` (m, k):
    by a hash of each row (one sort of m numbers, not a lexicographic one), checked
    row by row against the representative (an exact unique on any collision)."""
    mix = np.random.default_rng(0).integers(1, 2**62, size=key.shape[1]) | 1
    with np.errstate(over="ignore"):
        digest = (key * mix).sum(axis=1)  # wraps around: a hash, not a sum
    _, first, inverse = np.unique(digest, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    if not np.array_equal(key[first][inverse], key):
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def _errors(x, t, flags, h, degree):
    """Studentised leave-one-out errors and predictions, from the nearest unflagged
    neighbours of every sample (per component)."""
    pred = np.empty_like(x)
    err = np.empty_like(x)

    def component(k):
        nb = _clean_neighbours(flags[:, k], h)
        pred[:, k], factor = _loo_predict(x[:, k], t, nb, degree)
        err[:, k] = (x[:, k] - pred[:, k]) / factor

    map_threads(component, range(x.shape[1]))
    return err, pred


#: Local high-breakdown fit of the temporal screen's first pass: half window (samples),
#: polynomial degree, number of elemental starts, concentration steps, starts kept
#: after the first step, and windows per batch (bounds the memory to a few MB).
_LTS_HALF, _LTS_DEGREE, _LTS_STARTS, _LTS_STEPS, _LTS_KEEP, _LTS_BATCH = 6, 3, 30, 3, 4, 4096
#: Ridge added to the diagonal of the trimmed fits' systems (elemental and concentrated).
_LTS_RIDGE = 1e-12


def _elemental_subsets(w: int, size: int, count: int) -> np.ndarray:
    """``count`` distinct subsets of ``size`` positions in ``range(w)`` (fixed, so the
    screen is deterministic), each with at least one position in each part of the
    window so that the elemental polynomial interpolates rather than extrapolates."""
    rng = np.random.default_rng(0)
    edges = np.linspace(0, w, size + 1).round().astype(int)
    out: set = set()
    while len(out) < count:
        out.add(tuple(int(rng.integers(edges[i], edges[i + 1])) for i in range(size)))
    return np.array(sorted(out))


def _hankel_solve(moments: np.ndarray, b: np.ndarray, ridge: float) -> np.ndarray:
    """Solve ``(H + ridge I) x = b`` for the many small Hankel systems of polynomial
    least squares, ``H_ij = moments[..., i + j]`` (the sums of ``tau^(i+j)``), by a
    Cholesky factorisation written out over the (small) order ``n``: vectorised across
    the systems, without a LAPACK call for each.  ``moments`` (..., 2n - 1), ``b`` (..., n).
    """
    n = b.shape[-1]
    mom = np.moveaxis(moments, -1, 0)
    b = np.moveaxis(b, -1, 0)
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        diag = mom[2 * j] + ridge - sum(low[j][k] ** 2 for k in range(j))
        low[j][j] = np.sqrt(np.maximum(diag, np.finfo(float).tiny))
        for i in range(j + 1, n):
            low[i][j] = (mom[i + j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    z = [None] * n
    for i in range(n):
        z[i] = (b[i] - sum(low[i][k] * z[k] for k in range(i))) / low[i][i]
    out = [None] * n
    for i in reversed(range(n)):
        out[i] = (z[i] - sum(low[k][i] * out[k] for k in range(i + 1, n))) / low[i][i]
    return np.stack(out, axis=-1)


def _lts_fitted(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Fitted value at every sample of ``x`` (m,) by a least-trimmed-squares polynomial
    in its window of ``2 _LTS_HALF + 1`` samples (shifted inside at the ends).

    Starts from elemental fits (interpolating polynomials through a few samples of the
    window), keeps the best after one concentration step (refit on the ``q`` samples
    with the smallest residuals, ``q`` just over half the window), and iterates those:
    the fit ignores up to ``w - q`` gross errors in every window, wherever they are.
    The windows run in a compiled loop (:mod:`._temporal_kernels`); where it cannot be
    compiled, in NumPy array expressions (:func:`_concentrate`), to rounding the same."""
    m, h, d = x.size, _LTS_HALF, _LTS_DEGREE
    w = min(2 * h + 1, m)
    a = d + 1
    q = (w + (a - 1) + 2) // 2 + 1
    eye = _LTS_RIDGE * np.eye(a)
    subsets = _elemental_subsets(w, a, _LTS_STARTS)
    out = np.empty(m)
    for lo in range(0, m, _LTS_BATCH):
        i = np.arange(lo, min(lo + _LTS_BATCH, m))
        first = np.clip(i - h, 0, m - w)
        idx = first[:, None] + np.arange(w)
        tau = t[idx] - t[i][:, None]
        span = np.abs(tau).max(axis=1, keepdims=True)
        tau = tau / np.where(span > 0, span, 1.0)  # relative time: unit-free
        place = i - first
        pattern = np.zeros((w, w))
        pattern[place] = tau  # one window per place (any: they agree when uniform)
        if np.abs(tau - pattern[place]).max() <= 1e-9:
            # Uniformly sampled windows: the relative times depend only on the sample's
            # place in its window, so the windows of one place share their polynomial
            # rows and elemental inverses.
            v = pattern[..., None] ** np.arange(a)  # (w places, w, a)
            which, shared = place, True
        else:
            v = tau[..., None] ** np.arange(a)  # (b, w, a)
            which, shared = np.arange(i.size), False
        fitted = _temporal_kernels.lts_windows(
            x, first, place, which, v, np.linalg.inv(v[:, subsets] + eye),
            subsets, q, _LTS_STEPS, _LTS_KEEP, _LTS_RIDGE,
        )  # fmt: skip
        if fitted is None:
            fitted = _lts_numpy(x[idx], v, which, place, subsets, shared)
        out[i] = fitted
    return out


def _lts_numpy(xw, v, which, place, subsets, shared):
    """The trimmed fits of the windows ``xw`` (b, w) in NumPy array expressions: ``v``
    (P, w, a) the polynomial rows of the patterns ``which`` (b,) of the windows, one
    per place in the window when ``shared``, else one per window."""
    a = v.shape[-1]
    eye = _LTS_RIDGE * np.eye(a)
    out = np.empty(xw.shape[0])
    if shared:
        # One pattern per place: every product below is one matrix product for all the
        # windows of a place.
        w = xw.shape[1]
        for at in np.unique(which):
            rows = np.flatnonzero(which == at)
            inverse = np.linalg.inv(v[at][subsets] + eye)  # (K, a, a)
            # The elemental coefficients as one linear map of the window's values.
            elemental = np.zeros((w, subsets.shape[0], a))
            for j in range(a):
                elemental[subsets[:, j], np.arange(subsets.shape[0])] = inverse[:, :, j]
            coef = _times(xw[rows, None, :], elemental.reshape(w, -1))
            c = _concentrate(xw[rows], coef.reshape(rows.size, -1, a), v[at])
            out[rows] = c @ v[at][place[rows[0]]]
        return out
    coef = np.linalg.solve(v[:, subsets] + eye, xw[:, subsets][..., None])[..., 0]
    c = _concentrate(xw, coef, v)
    return np.sum(v[np.arange(xw.shape[0]), place] * c, axis=1)


def _times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a stack ``a`` (..., k) and a matrix ``b`` (k, l) shared by the
    stack as one matrix product, or a stack ``b`` (batch, k, l) matched to ``a``."""
    if b.ndim == 2:
        return (a.reshape(-1, a.shape[-1]) @ b).reshape(*a.shape[:-1], b.shape[-1])
    return a @ b


def _concentrate(xw, coef, v):
    """Concentration steps of the local trimmed fits of the windows ``xw`` (b, w) from
    the starts ``coef`` (b, K, a); ``v`` (w, a) or (b, w, a): the polynomial rows of
    the windows (shared or one set per window).  Returns the best fit (b, a)."""
    w, a = xw.shape[1], coef.shape[-1]
    q = (w + (a - 1) + 2) // 2 + 1
    vt = np.swapaxes(v, -1, -2)
    # The normal equations of a fit on a mask of the window are Hankel: the masked sums
    # of the powers tau^0 .. tau^(2a - 2), one product for all windows and starts.
    tau = v[..., 1] if a > 1 else np.zeros(v.shape[:-1])
    powers = tau[..., None] ** np.arange(2 * a - 1)  # (w, 2a - 1) or (b, w, 2a - 1)
    for step in range(_LTS_STEPS):
        r2 = (xw[:, None, :] - coef @ vt) ** 2  # (b, K, w)
        smallest = np.partition(r2, q - 1, axis=-1)
        if step == 1:  # keep the most promising starts only
            best = np.argsort(smallest[..., :q].sum(-1), axis=1)[:, :_LTS_KEEP]
            coef = np.take_along_axis(coef, best[..., None], axis=1)
            r2 = np.take_along_axis(r2, best[..., None], axis=1)
            smallest = np.take_along_axis(smallest, best[..., None], axis=1)
        # The q samples with the smallest residuals (a tie admits one more).
        mask = (r2 <= smallest[..., q - 1 : q]).astype(float)  # (b, K, w)
        coef = _hankel_solve(_times(mask, powers), _times(mask * xw[:, None, :], v), _LTS_RIDGE)
    r = xw[:, None, :] - coef @ vt
    obj = np.partition(r**2, q - 1, axis=-1)[..., :q].sum(-1)
    return coef[np.arange(xw.shape[0]), np.argmin(obj, axis=1)]


#: Rounds of withdrawing the flags in unresolved windows (each re-measures the errors).
_UNRESOLVED_ROUNDS = 10


def _unflagged_scale(err, flags) -> np.ndarray:
    """Per component, the robust scale of the errors ``err`` (m, n) left unflagged."""
    return np.array([robust_scale(err[~flags[:, k], k]) for k in range(err.shape[1])])


def _unresolved(x, err, flags, h, cutoff, floor):
    """Entries in windows the local fits do not resolve, per component: within ``h``
    samples, at least two unflagged entries whose errors are gross against the
    component's scale (the local fits cannot follow the samples there), and the
    samples of the window are smooth at the sampling resolution: the root mean square
    of their second differences is below that of their first differences (white noise
    gives ``sqrt 3`` times more, so a burst of noise, a cluster of outliers or a
    spike is not smooth; a sampled oscillation is while it has more than six samples
    per period).  Such a window (a fast excursion sampled by a few samples) is
    explained by neither an outlier nor the noise: the temporal screen cannot tell an
    outlier there from the data's own structure, and leaves it to the model-based
    screen."""
    gross = ~flags & (np.abs(err) > cutoff * np.maximum(_unflagged_scale(err, flags), floor))
    w = 2 * h + 1
    count = scipy.ndimage.uniform_filter1d(gross.astype(float), w, axis=0, mode="constant") * w
    first = np.diff(x, axis=0, prepend=x[:1])
    second = np.diff(first, axis=0, append=first[-1:])
    energy = [
        scipy.ndimage.uniform_filter1d(a**2, w, axis=0, mode="nearest") for a in (first, second)
    ]
    return (count >= 1.5) & (energy[1] < energy[0])


def _screen_one(x, t, h, degree, cutoff, scale_half):
    floor = np.maximum(
        _SCALE_FLOOR * np.maximum(x.std(axis=0), np.finfo(float).tiny),
        _ROUNDING_FLOOR * np.abs(x).max(axis=0),
    )

    def gross(err):
        # The running median of the errors is the fit's smooth bias (e.g. along a fast
        # part of the trajectory); an outlier, alone or in a short group, stands out of it.
        err = err - _running_median(err, _BIAS_WINDOW)
        scale = np.maximum(robust_scale(err), floor)
        return np.abs(err) / (cutoff * np.maximum(scale, smooth_local_scale(err, scale_half)))

    def ratio_of(flags):
        err, pred = _errors(x, t, flags, h, degree)
        return gross(err), pred, err

    if x.shape[0] > 2 * _LTS_HALF + 1:
        # 1. Candidates: gross errors from a local high-breakdown fit, which gross
        #    errors in the window (up to a third of it) cannot pull towards themselves.
        lts = np.column_stack(map_threads(lambda k: _lts_fitted(x[:, k], t), range(x.shape[1])))
        candidates = gross(x - lts) > 1
        # 2. Confirmation by leave-one-out least squares from the nearest samples that
        #    are not candidates (no entry is added here: a clean sample next to a gap of
        #    candidates is predicted over a wider span, less accurately).
        ratio, _, _ = ratio_of(candidates)
        flags = candidates & (ratio > 1)
    else:
        # Too short for the trimmed fit: candidates from all neighbours (an outlier
        # spoils its neighbours' predictions too, so only the worst of each window),
        # then refitted without them, the worst gross entries masked by them added.
        ratio, _, _ = ratio_of(np.zeros(x.shape, dtype=bool))
        candidates = (ratio > 1) & (ratio >= _window_max(ratio, h))
        ratio, _, _ = ratio_of(candidates)
        others = np.where(candidates, 0.0, ratio)
        flags = (candidates & (ratio > 1)) | ((others > 1) & (others >= _window_max(others, h)))
    # 3. Final confirmation against clean neighbours; flagged entries get the prediction.
    ratio, pred, err = ratio_of(flags)
    flags &= ratio > 1
    # 4. Flags withdrawn (never added: this ends) in windows the local fits do not
    #    resolve, the errors re-measured without them.
    for _ in range(_UNRESOLVED_ROUNDS):
        drop = flags & _unresolved(x, err, flags, h, cutoff, floor)
        if not drop.any():
            break
        flags &= ~drop
        ratio, pred, err = ratio_of(flags)
        flags &= ratio > 1
    return flags, np.where(flags, pred, x), _unflagged_scale(err, flags)


def temporal_screen(
    x,
    t=None,
    *,
    half_window: int = 4,
    degree: int = 4,
    cutoff: float = 3.5,
    scale_window: int = 20,
) -> TemporalScreening:
    """Flag entries of sampled trajectories that are inconsistent with their neighbours.

    Per trajectory and component, a sample's error is its distance to a local
    polynomial in relative time fitted around it; it is gross when it exceeds
    ``cutoff`` times the larger of the component's robust scale
    (:func:`robust_sindy.selection.robust_scale` of all errors) and, where the errors
    vary smoothly in time, their local robust scale within ``scale_window`` samples
    (:func:`smooth_local_scale`: an under-resolved fast excursion, where every fit is
    poor in the same way, is left to the model-based screen, while a burst of noise,
    whose errors jump from sample to sample, is not excused); the running median of
    the errors over 7 samples (a fit's smooth bias) is subtracted first.  Three fixed
    passes and a withdrawal, so the result never oscillates:

    1. candidates: errors from a least-trimmed-squares cubic in a window of 13
       samples, started from elemental fits and refined by concentration steps, so
       that up to a third of gross errors in a window cannot pull the fit towards
       themselves (as they do a least-squares fit: 20 % of contaminated samples would
       then hide most of each other);
    2. each sample predicted by leave-one-out least squares (``degree``) from its
       ``2 half_window`` nearest neighbours that are not candidates, the error divided
       by the factor by which the prediction's noise exceeds the sample's: the
       candidates still gross are kept (a trajectory too short for the trimmed fit
       takes its candidates from this prediction with all neighbours instead);
    3. refitted without those, the entries still gross are the flags, their
       predictions the repaired values, and the robust scale of the unflagged errors
       the component's noise level (``scale``);
    4. in a window the local fits do not resolve -- at least two unflagged entries
       within ``half_window`` samples with gross errors, on samples that are smooth at
       the sampling resolution (second differences smaller than first ones, which
       white noise, a burst or a spike do not give) -- the flags are withdrawn and the
       errors re-measured, until none is: a fast excursion sampled by a few samples is
       left to the model-based screen rather than "repaired" with a prediction that
       cannot follow it.

    Parameters
    ----------
    x : array_like (m, n), or a list of them
        Sampled states, one array per trajectory.
    t : array_like (m,), or a list of them, optional
        Sample times (strictly increasing); uniform sampling when omitted.  Only
        relative times within a window matter, so the time unit does not.
    half_window : int
        Neighbours on each side.
    degree : int
        Degree of the local polynomial (< ``2 half_window``).
    cutoff : float
        Robust standard deviations beyond which an error is gross.
    scale_window : int
        Half width, in samples, of the window of the local scale.

    Returns
    -------
    TemporalScreening

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0.0, 10.0, 1001)
    >>> x = np.column_stack([np.sin(t), np.cos(3 * t)])
    >>> x[500, 1] += 0.5                       # one spike in one component
    >>> s = temporal_screen(x, t)
    >>> np.argwhere(s.flags).tolist()
    [[500, 1]]
    >>> bool(abs(s.repaired[500, 1] - np.cos(3 * t[500])) < 1e-6)
    True
    """
    h = check_int(half_window, "half_window", 1)
    degree = check_int(degree, "degree", 0)
    if degree >= 2 * h:
        raise ValueError(f"degree ({degree}) must be < 2 * half_window ({2 * h})")
    cutoff = check_positive(cutoff, "cutoff")
    scale_half = check_int(scale_window, "scale_window", 1)
    multiple = isinstance(x, (list, tuple))
    xs = [as_float_array(a, "x", (1, 2)) for a in (x if multiple else [x])]
    xs = [a[:, None] if a.ndim == 1 else a for a in xs]
    if t is None:
        ts = [np.arange(a.shape[0], dtype=float) for a in xs]
    else:
        ts = [as_float_array(a, "t", (1,)) for a in (t if multiple else [t])]
        if len(ts) != len(xs) or any(a.size != b.shape[0] for a, b in zip(ts, xs, strict=True)):
            raise ValueError("t must give one time per sample of x (per trajectory)")
    flags, repaired, scales = [], [], []
    skipped = 0
    for a, ti in zip(xs, ts, strict=True):
        if a.shape[0] < 2 * h + 2:
            skipped += 1
            flags.append(np.zeros(a.shape, dtype=bool))
            repaired.append(a.copy())
            continue
        f, r, s = _screen_one(a, ti, h, degree, cutoff, scale_half)
        flags.append(f)
        repaired.append(r)
        scales.append(s)
    n = xs[0].shape[1]
    scale = np.max(scales, axis=0) if scales else np.full(n, np.nan)
    return TemporalScreening(np.vstack(flags), np.vstack(repaired), scale, skipped)


@dataclass(repr=False)
class Screening:
    """Outcome of :func:`screen_rows`.

    Attributes
    ----------
    outliers : ndarray of bool, shape (m,)
        Samples flagged as gross outliers (excluded from the fit).
    scale : ndarray, shape (n,)
        Robust residual scale per equation on the kept samples.
    relative_scale : ndarray, shape (n,)
        ``scale`` divided by the root mean square of the equation's target.
    start : ndarray of bool, shape (m,)
        The samples the first pilot was fitted on.
    rounds : int
        Pilot refits until the flags stopped changing.
    converged : bool
        False when ``max_rounds`` ended the iteration with the flags still changing.
    restarted : bool
        True when another iteration (from every sample, or from a forward search)
        replaced the one from ``start`` (step 4 of :func:`screen_rows`).
    """

    outliers: np.ndarray
    scale: np.ndarray
    relative_scale: np.ndarray
    start: np.ndarray
    rounds: int
    converged: bool
    restarted: bool = False

    def __repr__(self) -> str:
        return (
            f"Screening(flagged {int(self.outliers.sum())} of {self.outliers.size} samples, "
            f"rounds={self.rounds}, converged={self.converged}, restarted={self.restarted})"
        )


def _leverage_corrected(theta, r, keep, delta, suspect) -> np.ndarray:
    """Residuals ``r`` (m, n) of a Huber fit on the samples ``keep``, those of the kept
    inliers (``|r| <= delta``) divided by ``sqrt(1 - h_i)`` (studentised), or by
    ``1 - h_i`` (deleted: the residual the sample would have if the fit had not seen
    it) where ``suspect``; ``h_i = theta_i H^+ theta_i^T`` is the sample's leverage,
    ``H`` the Gram matrix of the inliers.

    A studentised residual of a good sample has the spread of the noise whatever the
    sample's leverage.  A gross error in the states puts its sample far out in library
    space, where the fit has nothing else to go by and bends to it (``h_i`` near 1, a
    small residual, even studentised): a sample with independent evidence against it
    (the temporal screen flagged it) is vouched for only by a model fitted without it.
    Deleted residuals for every sample would be too strict where there are few samples
    per term, whose good samples all have large leverage."""
    out = r.copy()
    for k in range(r.shape[1]):
        inl = keep & (np.abs(r[:, k]) <= delta[k])
        a = theta[inl]
        lev = np.einsum("ij,ji->i", a, np.linalg.pinv(a.T @ a, hermitian=True) @ a.T)
        rest = np.maximum(1.0 - lev, np.finfo(float).eps)
        out[inl, k] = r[inl, k] / np.where(suspect[inl], rest, np.sqrt(rest))
    return out


def _excitation_gain(theta: np.ndarray, start: np.ndarray) -> float:
    """Largest ratio, over directions ``v`` of the library, of ``|theta v|^2`` per sample
    on all samples to the same on the ``start`` samples (a generalised eigenvalue;
    unchanged by rescaling the columns); ``inf`` when the start spans fewer directions."""
    a = theta[start]
    g_start = a.T @ a / max(a.shape[0], 1)
    g_all = theta.T @ theta / theta.shape[0]
    norms = np.sqrt(np.maximum(np.diag(g_all), np.finfo(float).tiny))
    g_start, g_all = g_start / np.outer(norms, norms), g_all / np.outer(norms, norms)
    try:
        return float(scipy.linalg.eigh(g_all, g_start, eigvals_only=True)[-1])
    except np.linalg.LinAlgError:
        return float("inf")


def _segment_local_scale(r, segments, half, trusted):
    """Local robust scale of the residuals of the ``trusted`` samples (those the
    temporal screen left alone) around every sample, per trajectory: residuals that
    grow along a fast part of the trajectory (state noise carried through a steep
    right-hand side) raise it, a burst of corrupted samples does not."""
    out = np.zeros_like(r)
    for seg in segments:
        if seg.stop - seg.start > 1:
            out[seg] = local_scale(np.where(trusted[seg, None], r[seg], np.nan), half)
    return out


def screen_rows(
    theta,
    xdot,
    *,
    start=None,
    segments=None,
    cutoff: float = 3.5,
    scale_window: int = 25,
    max_rounds: int = 20,
    method: str = "admm",
    noise=None,
) -> Screening:
    """Flag samples whose residual is gross in any equation of a robust pilot.

    1. Fit an unpenalised Huber pilot (``delta`` by :func:`auto_delta`) on the samples
       ``start`` (all by default; :class:`~robust_sindy.HuberSINDy` passes the samples
       the temporal screen left alone);
    2. measure each equation's robust residual scale ``s_k`` on the kept samples (at
       least ``1e-4`` of the target's root mean square);
    3. flag a sample when its residual (for the samples in the fit, studentised by
       their leverage ``h_i`` among the inliers, ``r_i / sqrt(1 - h_i)``, and deleted,
       ``r_i / (1 - h_i)``, for those outside ``start``: a gross error far out in
       library space bends an unpenalised pilot to fit it) is more than ``cutoff``
       times the larger of
       ``s_k`` and the local robust scale of the residuals within ``scale_window``
       samples of the same trajectory (when ``segments`` are given; residuals that grow
       smoothly along a fast part of the trajectory are not outliers) in any equation;
       refit the pilot on the kept samples and repeat from 2 until the flags are stable
       (after five rounds flags are only added, so the iteration cannot oscillate);
    4. when ``start`` left samples out, the iteration flagged more than 2 % of the
       samples, and some library direction is excited more than 100 times more (mean
       square per sample) by all the samples than by the start, iterate again from
       every sample, and from a forward search (from the kept samples, add the 2 % of
       the samples with the smallest scaled residuals, refit, repeat until 90 % are in,
       and keep the set whose model explained most samples); keep the outcome whose
       model explains (residual within the bound) most samples, if that is more than
       2 % more than the first, all judged at the smallest of their scales: a start
       that misses a fast excursion gives a pilot that extrapolates there, a pilot
       bent by gross errors has a larger scale and explains fewer samples, and the
       forward search reaches the excursion one step at a time, before the outliers.

    With ``noise`` (the noise of the states carried through the library, one array per
    state), the bound of a sample is also at least the residual that this noise gives
    it under the pilot's model, ``sqrt(sum_k (noise_k[i] @ coef_j)^2)``: where the
    right-hand side is steep (a fast excursion) the noise of good states gives large
    residuals, which are not gross errors.  That noise is taken no larger than the
    residuals allow (:func:`~robust_sindy.selection.bias.residual_noise_factor`): a
    noise level measured too large (states sampled too coarsely for the temporal
    screen) would excuse gross errors.

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    start : array_like of bool (m,), optional
        Samples of the first pilot; the others are suspect (step 3).
    segments : list of slice, optional
        The samples of each trajectory, in time order (enables the local scale).
    cutoff : float
        Robust standard deviations beyond which a residual is gross.
    scale_window : int
    max_rounds : int
    method : {"admm", "cvxpy"}
        Solver of the pilot fits.
    noise : list of array_like (m, p), optional
        Per state, the first-order noise of every library column at every sample (the
        state's noise level times the column's derivative by that state).

    Returns
    -------
    Screening

    Examples
    --------
    >>> import numpy as np
    >>> from robust_sindy.noise import contaminate
    >>> from robust_sindy.systems import Lorenz
    >>> lorenz = Lorenz()
    >>> data = lorenz.generate()
    >>> noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
    >>> theta = lorenz.fitted_library().transform(noisy.x)
    >>> s = screen_rows(theta, noisy.x_dot)
    >>> int(noisy.outliers.sum()), int((s.outliers & noisy.outliers).sum())
    (200, 200)
    """
    theta, y, _ = check_problem(theta, xdot)
    cutoff = check_positive(cutoff, "cutoff")
    half = check_int(scale_window, "scale_window", 1)
    rounds = check_int(max_rounds, "max_rounds", 1)
    _check_method(method, "the pilot fits")
    m, p = theta.shape
    if noise is not None:
        noise = [as_float_array(a, "noise", (2,)) for a in noise]
        if any(a.shape != (m, p) for a in noise):
            raise ValueError(f"noise must be a list of arrays of shape ({m}, {p})")
    if start is None:
        keep = np.ones(m, dtype=bool)
    else:
        keep = np.asarray(start, dtype=bool).copy()
        if keep.shape != (m,):
            raise ValueError(f"start must be a boolean mask of shape ({m},); got {keep.shape}")
    if keep.sum() < max(2 * p, m // 2):
        keep = np.ones(m, dtype=bool)  # too little left to fit: start from everything
    first = keep.copy()
    rms = np.sqrt(np.mean(y**2, axis=0))
    rms = np.where(rms > 0, rms, 1.0)
    local = None if segments is None else (lambda r: _segment_local_scale(r, segments, half, first))

    def bound_of(r, scale, coef):
        bound = np.broadcast_to(scale, r.shape)
        if local is not None:
            bound = np.maximum(bound, local(r))
        if noise:
            carried = carried_noise(noise, coef)
            # No more of the measured noise than the residuals themselves show.
            factor = [residual_noise_factor(r[:, k], carried[:, k]) for k in range(r.shape[1])]
            bound = np.maximum(bound, np.sqrt(factor) * carried)
        return bound

    # The pilots only propose flags: a bounded budget, their certificates not required
    # (the final fit of the kept samples is certified on its own).
    budget = pilot_budget(method)

    def pilot(keep):
        """The unpenalised Huber pilot on ``keep``: coefficients and residuals of every
        sample, centred on the kept ones' median, those of the kept samples corrected for
        their leverage (:func:`_leverage_corrected`)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            delta = np.atleast_1d(auto_delta(theta[keep], y[keep], method=method, **budget))
            coef = fit(theta[keep], y[keep], method, delta, 0.0, **budget).coef.reshape(p, -1)
        r = y - theta @ coef
        r = r - np.median(r[keep], axis=0)
        return coef, _leverage_corrected(theta, r, keep, delta, ~first)

    def scaled(r, scale, coef):
        """Each sample's largest residual over ``cutoff`` times its bound (> 1: gross)."""
        return (np.abs(r) / (cutoff * bound_of(r, scale, coef))).max(axis=1)

    def iterate(keep):
        flags, converged, done, scale = None, False, 0, np.zeros(y.shape[1])
        for done in range(1, rounds + 1):
            coef, r = pilot(keep)
            scale = np.maximum(np.atleast_1d(robust_scale(r[keep])), _SCALE_FLOOR * rms)
            new = scaled(r, scale, coef) > 1
            if flags is not None and done > _FREE_ROUNDS:
                new |= flags  # past the free rounds flags are only added: no oscillation
            if flags is not None and np.array_equal(new, flags):
                converged = True
                break
            flags = new
            keep = ~flags
            if keep.sum() <= p:
                break
        return flags, scale, done, converged, r, coef

    def forward(keep, scale0):
        """Forward search: grow the kept set from ``keep`` by the excluded samples with
        the smallest scaled residuals, 2 % of the samples at a time, refitting after
        each, until 90 % are in; return the samples explained (residual within the
        bound at ``scale0``) by the step whose model explained most."""
        keep = keep.copy()
        step = max(p, int(np.ceil(_COMPETE_MARGIN * m)))
        best, best_n = keep.copy(), -1
        for _ in range(50):
            coef, r = pilot(keep)
            z = scaled(r, scale0, coef)
            n_ok = int((z <= 1).sum())
            if n_ok > best_n:
                best, best_n = z <= 1, n_ok
            out = np.flatnonzero(~keep)
            if out.size == 0 or keep.mean() > 0.9:
                break
            keep[out[np.argsort(z[out])[:step]]] = True
        return best

    flags, scale, done_rounds, converged, r, coef = iterate(keep)
    restarted = False
    if (
        not first.all()
        and flags.mean() > _COMPETE_MARGIN
        and _excitation_gain(theta, first) > _COMPETE_EXCITATION
    ):
        # The start may have left out the samples that excite some library directions
        # (a fast excursion the temporal screen could not follow); then its pilot
        # extrapolates there and keeps flagging good samples.  Two more iterations
        # compete, one from every sample and one from a forward search that grows the
        # kept set from the first one's: the one whose model explains most samples at
        # the smallest of the noise scales wins, by more than 2 % of the samples (a
        # pilot bent by gross errors has a larger scale and explains fewer).
        cands = [iterate(np.ones(m, dtype=bool)), iterate(forward(~flags, scale))]
        common = np.minimum.reduce([scale] + [c[1] for c in cands])
        explained = [
            int((scaled(rr, common, cc) <= 1).sum())
            for rr, cc in [(r, coef)] + [(c[4], c[5]) for c in cands]
        ]
        best = int(np.argmax(explained))
        if best > 0 and explained[best] - explained[0] > _COMPETE_MARGIN * m:
            flags, scale, done_rounds, converged = cands[best - 1][:4]
            restarted = True
    return Screening(flags, scale, scale / rms, first, done_rounds, converged, restarted)
