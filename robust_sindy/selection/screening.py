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
* :func:`screen_rows` -- flags whole samples by their residual under an unpenalised
  Huber pilot, fitted on a clean start (the temporally unflagged samples), with
  per-equation scales estimated from the inliers.  It flags by residual only, never by
  leverage: a rare excursion that the model fits is the most informative sample, not an
  outlier.

All scales are robust scales of the data themselves, so every decision is unit-free.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._fit import fit
from .._scaling import robust_scale
from .._validation import as_float_array, check_int, check_positive, check_problem
from .scale import _check_method, auto_delta

__all__ = ["Screening", "TemporalScreening", "local_scale", "screen_rows", "temporal_screen"]

#: Relative floor of every scale (to the spread of what is screened): errors below
#: ``1e-4`` of a signal's spread change no identification, and on noise-free data the
#: smooth bias of the local fits must not be mistaken for an outlier.
_SCALE_FLOOR = 1e-4
#: Rounds of the model-based screen in which flags may also be withdrawn.
_FREE_ROUNDS = 5


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
        Robust scale of the prediction errors per component (largest over the
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
    array at its ends.
    """
    a = np.abs(np.asarray(values, dtype=float))
    m = a.shape[0]
    w = min(2 * half_width + 1, m)
    start = np.clip(np.arange(m) - half_width, 0, m - w)
    windows = np.lib.stride_tricks.sliding_window_view(a, w, axis=0)  # (m - w + 1, n, w)
    med = np.median(windows, axis=-1)
    return 1.4826 * med[start]


def _window_max(a: np.ndarray, h: int) -> np.ndarray:
    """Maximum of ``a`` (m, n) over the ``2h + 1`` samples centred on each sample."""
    padded = np.pad(a, ((h, h), (0, 0)), constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * h + 1, axis=0).max(axis=-1)


def _clean_neighbours(flags: np.ndarray, h: int) -> np.ndarray:
    """For each sample, its ``2h`` nearest unflagged other samples (h on each side, topped
    up from the other side at the ends); -1 where there are not enough."""
    m = flags.size
    u = np.flatnonzero(~flags)
    i = np.arange(m)
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


def _loo_predict(x, t, nb, degree):
    """Leave-one-out local polynomial prediction of ``x`` (m,) from the neighbours ``nb``
    (m, 2h; -1 unused), and the factor ``sqrt(1 + sum_j w_j^2)`` by which the prediction
    error's standard deviation exceeds that of the noise."""
    valid = nb >= 0
    idx = np.where(valid, nb, 0)
    tau = np.where(valid, t[idx] - t[:, None], 0.0)
    span = np.abs(tau).max(axis=1, keepdims=True)
    tau = tau / np.where(span > 0, span, 1.0)  # relative time: unit-free
    v = (tau[..., None] ** np.arange(degree + 1)) * valid[..., None]  # (m, 2h, d+1)
    gram = np.einsum("mja,mjb->mab", v, v)
    gram += 1e-12 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(degree + 1)
    # Row 0 of gram^-1 V^T: the weights of the fitted value at tau = 0.
    weights = np.linalg.solve(gram, np.swapaxes(v, 1, 2))[:, 0, :]
    pred = np.einsum("mj,mj->m", weights, x[idx])
    return pred, np.sqrt(1.0 + np.sum(weights**2, axis=1))


def _errors(x, t, flags, h, degree):
    """Studentised leave-one-out errors and predictions, from the nearest unflagged
    neighbours of every sample (per component)."""
    pred = np.empty_like(x)
    err = np.empty_like(x)
    for k in range(x.shape[1]):
        nb = _clean_neighbours(flags[:, k], h)
        pred[:, k], factor = _loo_predict(x[:, k], t, nb, degree)
        err[:, k] = (x[:, k] - pred[:, k]) / factor
    return err, pred


def _screen_one(x, t, h, degree, cutoff, scale_half):
    floor = _SCALE_FLOOR * np.maximum(x.std(axis=0), np.finfo(float).tiny)

    def ratio_of(flags):
        err, pred = _errors(x, t, flags, h, degree)
        scale = np.maximum(robust_scale(err), floor)
        return np.abs(err) / (cutoff * np.maximum(scale, local_scale(err, scale_half))), pred

    def worst(ratio, among):
        # An outlier spoils its neighbours' predictions too: of the entries ``among``,
        # only the worst within each window can be flagged.
        r = np.where(among, ratio, 0.0)
        return (r > 1) & (r >= _window_max(r, h))

    none = np.zeros(x.shape, dtype=bool)
    ratio, _ = ratio_of(none)
    candidates = worst(ratio, ~none)
    # Refit without the candidates: confirm them, and find outliers they masked.
    ratio, _ = ratio_of(candidates)
    flags = (candidates & (ratio > 1)) | worst(ratio, ~candidates)
    # Final confirmation against clean neighbours; flagged entries get the prediction.
    ratio, pred = ratio_of(flags)
    flags &= ratio > 1
    return flags, np.where(flags, pred, x), robust_scale(x - pred)


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

    Per trajectory and component, every sample is predicted from its ``2 half_window``
    nearest unflagged neighbours in time by a least-squares polynomial of ``degree`` in
    relative time.  Its error, divided by the factor by which the prediction's noise
    exceeds the sample's, is gross when it exceeds ``cutoff`` times the larger of the
    component's robust scale (:func:`robust_sindy.selection.robust_scale` of all errors)
    and the local robust scale of the errors within ``scale_window`` samples
    (:func:`local_scale`: an under-resolved fast excursion, where every prediction is
    poor, is left to the model-based screen).  Three fixed passes, so the result never
    oscillates: (1) with all neighbours, the gross entries that are the worst within
    their window are candidates (a spike also spoils its neighbours' predictions);
    (2) refitted without the candidates, the candidates still gross are kept and the
    worst gross entries among the others (outliers masked by a nearby one) added;
    (3) refitted without those, the entries still gross are the flags, and their
    predictions the repaired values.

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
    """

    outliers: np.ndarray
    scale: np.ndarray
    relative_scale: np.ndarray
    start: np.ndarray
    rounds: int
    converged: bool

    def __repr__(self) -> str:
        return (
            f"Screening(flagged {int(self.outliers.sum())} of {self.outliers.size} samples, "
            f"rounds={self.rounds}, converged={self.converged})"
        )


def _segment_local_scale(r, segments, half):
    out = np.empty_like(r)
    for seg in segments:
        out[seg] = local_scale(r[seg], half) if seg.stop - seg.start > 1 else 0.0
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
) -> Screening:
    """Flag samples whose residual is gross in any equation of a robust pilot.

    1. Fit an unpenalised Huber pilot (``delta`` by :func:`auto_delta`) on the samples
       ``start`` (all by default; :class:`~robust_sindy.HuberSINDy` passes the samples
       the temporal screen left alone);
    2. measure each equation's robust residual scale ``s_k`` on the kept samples (at
       least ``1e-4`` of the target's root mean square);
    3. flag a sample when its residual is more than ``cutoff`` times the larger of
       ``s_k`` and the local robust scale of the residuals within ``scale_window``
       samples of the same trajectory (when ``segments`` are given; residuals that grow
       smoothly along a fast part of the trajectory are not outliers) in any equation;
       refit the pilot on the kept samples and repeat from 2 until the flags are stable
       (after five rounds flags are only added, so the iteration cannot oscillate).

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    start : array_like of bool (m,), optional
        Samples of the first pilot.
    segments : list of slice, optional
        The samples of each trajectory, in time order (enables the local scale).
    cutoff : float
        Robust standard deviations beyond which a residual is gross.
    scale_window : int
    max_rounds : int
    method : {"admm", "cvxpy"}
        Solver of the pilot fits.

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
    flags = None
    converged = False
    done_rounds = 0
    scale = np.zeros(y.shape[1])
    for done_rounds in range(1, rounds + 1):
        delta = np.atleast_1d(auto_delta(theta[keep], y[keep], method=method))
        coef = fit(theta[keep], y[keep], method, delta, 0.0).coef.reshape(p, -1)
        r = y - theta @ coef
        r = r - np.median(r[keep], axis=0)
        scale = np.maximum(np.atleast_1d(robust_scale(r[keep])), _SCALE_FLOOR * rms)
        bound = np.broadcast_to(scale, r.shape)
        if segments is not None:
            bound = np.maximum(bound, _segment_local_scale(r, segments, half))
        new = (np.abs(r) > cutoff * bound).any(axis=1)
        if flags is not None and done_rounds > _FREE_ROUNDS:
            new |= flags  # past the free rounds flags are only added: no oscillation
        if flags is not None and np.array_equal(new, flags):
            converged = True
            break
        flags = new
        keep = ~flags
        if keep.sum() <= p:
            break
    return Screening(flags, scale, scale / rms, first, done_rounds, converged)
