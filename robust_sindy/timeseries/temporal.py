"""The temporal screen: entries inconsistent with their neighbours in time.

The states are samples of a smooth trajectory: a gross error in one component (a
spike, a dropout, a burst of noise) is inconsistent with the neighbouring samples of
that component.  Each sample is predicted by a local polynomial fitted to its
neighbours in time (leave-one-out, flagged neighbours left out), and flagged when its
prediction error is gross compared with both the component's global robust scale and
the local robust scale of the errors around it (so that a fast excursion, where every
prediction is less accurate, is not mistaken for an outlier).  It needs no model, sees
errors in one component at a time, and gives a repaired trajectory (flagged entries
replaced by their prediction) to differentiate.  Where the local fits cannot follow
smooth samples at all (an excursion only a few samples long) it flags nothing: it
cannot tell an outlier there from the data's own structure.

All scales are robust scales of the data themselves, so every decision is unit-free.
The components' local fits are independent and run side by side on the machine's cores
(:func:`robust_sindy.core.threads.map_threads`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from ..core.scaling import robust_scale
from ..core.statistics import SCALE_FLOOR, running_median, smooth_local_scale
from ..core.threads import map_threads
from ..core.validation import as_float_array, check_int, check_positive
from . import _temporal_kernels

__all__ = [
    "CUTOFF",
    "HALF_WINDOW",
    "TemporalScreening",
    "fill_missing",
    "noise_flag_bound",
    "relative_noise",
    "temporal_screen",
]

#: Robust standard deviations beyond which an entry is flagged (``temporal_screen``).
CUTOFF = 3.5
#: Neighbours on each side of the local fits (``temporal_screen``, ``fill_missing``).
HALF_WINDOW = 4

#: Floor of the temporal screen's scales relative to the largest magnitude of a
#: component (about 4500 rounding units): a component constant up to rounding (a state
#: that does not move, stored as floats) must not have entries flagged by its rounding.
_ROUNDING_FLOOR = 1e-12


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


def _window_max(a: np.ndarray, h: int) -> np.ndarray:
    """Maximum of ``a`` (m, n) over the ``2h + 1`` samples centred on each sample."""
    padded = np.pad(a, ((h, h), (0, 0)), constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * h + 1, axis=0).max(axis=-1)


def clean_neighbours(flags: np.ndarray, h: int, at=None) -> np.ndarray:
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


def loo_predict(x, t, nb, degree, at=None):
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
        nb = clean_neighbours(flags[:, k], h)
        pred[:, k], factor = loo_predict(x[:, k], t, nb, degree)
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
        SCALE_FLOOR * np.maximum(x.std(axis=0), np.finfo(float).tiny),
        _ROUNDING_FLOOR * np.abs(x).max(axis=0),
    )
    # The fits see the states about their medians: a state's offset is then not
    # carried through the ridge of their systems, whose rounding an extrapolation to
    # the ends of the record would amplify above the rounding floor.
    given, centre = x, np.median(x, axis=0)
    x = x - centre

    def gross(err, columns=slice(None)):
        # The running median of the errors is the fit's smooth bias (e.g. along a fast
        # part of the trajectory); an outlier, alone or in a short group, stands out of it.
        err = err - running_median(err, _BIAS_WINDOW)
        scale = np.maximum(robust_scale(err), floor[columns])
        return np.abs(err) / (cutoff * np.maximum(scale, smooth_local_scale(err, scale_half)))

    def ratio_of(flags, columns=slice(None)):
        # Of the components ``columns`` only (every step is per component).
        err, pred = _errors(x[:, columns], t, flags[:, columns], h, degree)
        return gross(err, columns), pred, err

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
    #    resolve, the errors re-measured without them.  Each component has its own
    #    rounds: one that withdraws nothing is done, whatever the others withdraw.
    going = np.ones(x.shape[1], dtype=bool)
    for _ in range(_UNRESOLVED_ROUNDS):
        drop = flags & _unresolved(x, err, flags, h, cutoff, floor) & going
        going = drop.any(axis=0)
        if not going.any():
            break
        flags &= ~drop
        cols = np.flatnonzero(going)
        ratio, pred[:, cols], err[:, cols] = ratio_of(flags, cols)
        flags[:, cols] &= ratio > 1
    return flags, np.where(flags, pred + centre, given), _unflagged_scale(err, flags)


def temporal_screen(
    x,
    t=None,
    *,
    half_window: int = HALF_WINDOW,
    degree: int = 4,
    cutoff: float = CUTOFF,
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

    Each component goes through these steps on its own (its rounds of withdrawal
    too), so a channel's flags, repaired values and noise level do not depend on the
    other channels.

    Parameters
    ----------
    x : array_like (m, n), or a list of them
        Sampled states, one array per trajectory.  NaN marks a missing reading: a
        component with missing entries is screened on its readings at their times, and
        its missing entries are flagged and filled by the local fit of their nearest
        usable readings.
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
    xs, ts = _records(x, t)
    flags, repaired, scales = [], [], []
    skipped = 0
    for a, ti in zip(xs, ts, strict=True):
        lost = np.isnan(a)
        if a.shape[0] < 2 * h + 2:
            skipped += 1
            flags.append(lost)
            repaired.append(_fill(a, ti, lost, h, degree))
            continue
        if lost.any():
            f, r, s = _screen_with_missing(a, ti, lost, h, degree, cutoff, scale_half)
        else:
            f, r, s = _screen_one(a, ti, h, degree, cutoff, scale_half)
        flags.append(f)
        repaired.append(r)
        scales.append(s)
    n = xs[0].shape[1]
    scale = np.max(scales, axis=0) if scales else np.full(n, np.nan)
    return TemporalScreening(np.vstack(flags), np.vstack(repaired), scale, skipped)


def _records(x, t):
    """The trajectories of ``x`` (one array or a list; NaN allowed) as 2-D arrays, and
    their sample times (uniform when ``t`` is omitted), checked."""
    multiple = isinstance(x, (list, tuple))
    xs = [as_float_array(a, "x", (1, 2), allow_nan=True) for a in (x if multiple else [x])]
    xs = [a[:, None] if a.ndim == 1 else a for a in xs]
    if t is None:
        return xs, [np.arange(a.shape[0], dtype=float) for a in xs]
    ts = [as_float_array(a, "t", (1,)) for a in (t if multiple else [t])]
    if len(ts) != len(xs) or any(a.size != b.shape[0] for a, b in zip(ts, xs, strict=True)):
        raise ValueError("t must give one time per sample of x (per trajectory)")
    return xs, ts


def _screen_with_missing(x, t, lost, h, degree, cutoff, scale_half):
    """:func:`_screen_one` of a trajectory with missing entries (``lost``, NaN in ``x``):
    each component with missing entries is screened on its own readings at their
    times (a missing reading is a sample that component does not have), then its
    missing entries are flagged and filled by the local fit of their nearest usable
    readings (:func:`_fill`).  Components without missing entries are screened together
    as usual."""
    n = x.shape[1]
    flags, repaired, scale = lost.copy(), x.copy(), np.empty(n)
    full = np.flatnonzero(~lost.any(axis=0))
    if full.size:
        f, r, sc = _screen_one(x[:, full], t, h, degree, cutoff, scale_half)
        flags[:, full], repaired[:, full], scale[full] = f, r, sc

    def component(k):
        have = ~lost[:, k]
        if have.sum() < 2 * h + 2:
            return None
        return _screen_one(x[have, k : k + 1], t[have], h, degree, cutoff, scale_half)

    partial = np.flatnonzero(lost.any(axis=0))
    for k, done in zip(partial, map_threads(component, partial), strict=True):
        have = ~lost[:, k]
        if done is None:
            scale[k] = np.nan
        else:
            flags[have, k], repaired[have, k], scale[k] = done[0][:, 0], done[1][:, 0], done[2][0]
    return flags, _fill(repaired, t, flags, h, degree, only=lost), scale


def _usable(x, unusable, k, h, degree):
    """Component ``k``'s values with the ``unusable`` entries zeroed (never read: they
    are no one's neighbours) and the degree of its local fits; None with too few."""
    usable = ~unusable[:, k]
    if usable.sum() < 2:
        return None
    return np.where(usable, x[:, k], 0.0), min(degree, int(usable.sum()) - 1, 2 * h - 1)


def _fill(x, t, unusable, h, degree, only=None):
    """``x`` with the entries ``only`` (default: ``unusable``) replaced by the
    leave-one-out local polynomial (:func:`loo_predict`) of their ``2 h`` nearest
    usable entries in time."""
    only = unusable if only is None else only
    out = x.copy()
    for k in range(x.shape[1]):
        at = np.flatnonzero(only[:, k])
        fit = _usable(x, unusable, k, h, degree) if at.size else None
        if fit is not None:
            nb = clean_neighbours(unusable[:, k], h, at)
            out[at, k] = loo_predict(fit[0], t, nb, fit[1], at=at)[0]
    return out


def _reading_scale(x, t, unusable, h, degree):
    """Per component, the robust scale of the studentised leave-one-out errors of the
    usable entries (their noise level; NaN with ``2 h`` or fewer)."""
    scale = np.full(x.shape[1], np.nan)
    for k in range(x.shape[1]):
        fit = _usable(x, unusable, k, h, degree)
        if fit is not None and (~unusable[:, k]).sum() > 2 * h:
            pred, factor = loo_predict(fit[0], t, clean_neighbours(unusable[:, k], h), fit[1])
            scale[k] = robust_scale(((fit[0] - pred) / factor)[~unusable[:, k]])
    return scale


def fill_missing(
    x, t=None, *, half_window: int = HALF_WINDOW, degree: int = 4
) -> TemporalScreening:
    """The missing entries (NaN) of sampled trajectories filled without screening: each
    by the local polynomial of degree ``degree`` of its ``2 half_window`` nearest
    readings in time (of the same component), as :func:`temporal_screen` fills them.
    Its flags are the missing entries; its scales the noise levels of the readings.
    What :class:`~robust_sindy.HuberSINDy` uses with ``screen=False``: a missing reading
    is filled, and then treated like a flagged one, even when nothing is screened."""
    xs, ts = _records(x, t)
    flags, repaired, scales = [], [], []
    for a, ti in zip(xs, ts, strict=True):
        lost = np.isnan(a)
        flags.append(lost)
        repaired.append(_fill(a, ti, lost, half_window, degree))
        scales.append(_reading_scale(a, ti, lost, half_window, degree))
    scale = np.fmax.reduce(np.array(scales), axis=0)  # NaN only where every one is
    return TemporalScreening(np.vstack(flags), np.vstack(repaired), scale, 0)


#: Samples of the running median that estimates the smooth bias of a local fit.
_BIAS_WINDOW = 7


def noise_flag_bound(entries: int, evidence: float = 1e-3, cutoff: float = CUTOFF) -> int:
    """The most entries of ``entries`` that :func:`temporal_screen` flags on Gaussian
    noise alone, but for a probability ``evidence``: each entry beyond ``cutoff``
    standard deviations with probability ``2 Q(cutoff)`` (4.7e-4 at 3.5), the count
    binomial.  More flags than this are evidence of outliers (or of excursions the
    sampling does not resolve)."""
    import scipy.stats

    rate = 2.0 * scipy.stats.norm.sf(cutoff)
    return int(scipy.stats.binom.isf(evidence, int(entries), rate))


def relative_noise(screening: TemporalScreening) -> float:
    """The states' noise relative to their size: per state, the screen's noise level
    over the standard deviation of the repaired states (flagged entries do not inflate
    it), the median over the states with a spread; NaN if none has one.  Unit-free."""
    spread = np.std(screening.repaired, axis=0)
    ok = (spread > 0) & np.isfinite(screening.scale)
    if not ok.any():
        return float("nan")
    return float(np.median(screening.scale[ok] / spread[ok]))
