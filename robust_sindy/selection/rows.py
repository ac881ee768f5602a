"""The row screen: samples whose residual under a robust pilot is gross in any equation.

:func:`screen_rows` flags whole samples by their residual under an unpenalised Huber
pilot, fitted on a clean start (the samples the temporal screen left alone), with
per-equation scales estimated from the inliers.  It flags by residual only, never by
leverage: a rare excursion that the model fits is the most informative sample, not an
outlier.  :func:`gross_residuals` is its rule, shared with the out-of-core refit.
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.stats

from ..core import cluster
from ..core.scaling import robust_scale
from ..core.statistics import SCALE_FLOOR, local_scale
from ..core.threads import map_threads
from ..core.validation import as_float_array, check_int, check_positive, check_problem
from ..fitting import (
    ConvergenceWarning,
    auto_delta,
    check_huber_method,
    fit,
    least_squares_start,
)
from ..solvers.driver import column_groups
from ..solvers.newton import CHOLESKY_MARGIN, conditioned_cholesky, inlier_gram
from ..solvers.problem import preparations, shared_preparation
from ..timeseries.trajectories import segments_of
from .bias import LibraryNoise, carried_noise, residual_noise_factor
from .lam_path import pilot_budget
from .problem import Problem

__all__ = [
    "GROSS_CUTOFF",
    "SCALE_WINDOW",
    "SETTLED_EVIDENCE",
    "RowScreen",
    "Screening",
    "gross_ratio",
    "screen_rows",
    "screen_samples",
]

#: Robust standard deviations beyond which a residual is gross.
GROSS_CUTOFF = 3.5
#: Half width (samples) of the window of the residuals' local robust scale.
SCALE_WINDOW = 25


def gross_ratio(r, bound, cutoff: float = GROSS_CUTOFF):
    """Each sample's largest ``|r|`` (m, n) over ``cutoff`` times its ``bound`` (> 1:
    gross in some equation).  The rule of the row screen and of the out-of-core refit
    (NumPy or Dask arrays alike)."""
    return (abs(r) / (cutoff * bound)).max(axis=1)


#: Rounds of the model-based screen in which flags may also be withdrawn.
_FREE_ROUNDS = 5

#: With correlated rows (``row_noise``), a round after the free ones that would add no
#: more flags than Gaussian residuals put beyond the cutoff, but for this probability,
#: ends the iteration without them: a fit that absorbs much of the rows' noise redraws
#: the residuals near the cutoff at every refit, and flags that only grow would collect
#: those draws round after round.
SETTLED_EVIDENCE = 1e-3


#: How many times more some library direction must be excited (mean square per sample)
#: by all the samples than by the start for the iteration from every sample to compete:
#: a start that lost a fast excursion loses a direction by orders of magnitude more
#: than one that lost scattered outliers (see the design notes).
_COMPETE_EXCITATION = 100.0


#: Fraction of the samples by which the iteration from every sample must explain more
#: than the one from the start to replace it (the screen's nominal false-positive
#: rate: smaller differences are the noise of two fits of the same model).
_COMPETE_MARGIN = 0.02


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
    swapped : ndarray of bool (m,)
        Samples kept with their ``alternative`` row (step 5 of :func:`screen_rows`).
    pilot : tuple (delta (n,), coef (p, n)) or None
        The threshold and coefficients of the last pilot (unpenalised, in the units of
        ``theta`` and ``xdot``): fitted on the samples kept when ``converged``, a start
        for another choice of ``delta`` on them
        (:func:`~robust_sindy.fitting.auto_delta`).
    """

    outliers: np.ndarray
    scale: np.ndarray
    relative_scale: np.ndarray
    start: np.ndarray
    rounds: int
    converged: bool
    restarted: bool = False
    swapped: np.ndarray | None = None
    pilot: tuple | None = None

    def __repr__(self) -> str:
        return (
            f"Screening(flagged {int(self.outliers.sum())} of {self.outliers.size} samples, "
            f"rounds={self.rounds}, converged={self.converged}, restarted={self.restarted})"
        )


def _leverage_corrected(theta, r, keep, delta, suspect, row_noise=None, cache=None) -> np.ndarray:
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
    per term, whose good samples all have large leverage.

    With ``row_noise`` (a sparse matrix ``D``, rows x noise sources: the rows' noise is
    ``D e`` for independent ``e`` of equal scale), the rows' noise is correlated (the
    weak form's overlapping integrals share samples) and a fit absorbs much more of it
    than ``h_i``: every residual is divided by ``sqrt(F_ii / c)``, ``F_ii`` the variance
    the rows' noise leaves in it under a least-squares fit on the inliers (``(I - H) D D^T
    (I - H)`` for the inliers, that of a prediction for the other rows), ``c`` the
    median of ``diag(D D^T)`` over the kept rows (``F = I - H`` for independent rows of
    equal noise: the studentised residual); a kept suspect's is the larger of that and
    its deleted residual.

    A ``cache`` (:class:`_LeverageCache`, independent rows only) updates each column's
    leverages from the last call's by the rows whose membership changed."""
    out = r.copy()
    rows = np.flatnonzero(keep)
    if row_noise is not None:
        cache = None
    if cache is not None:
        cache.see(theta)
        a = cache.scaled[rows]
    else:
        a = theta[rows]
        norms = np.linalg.norm(a, axis=0)
        a /= np.where(norms > 0, norms, 1.0)  # a leverage does not depend on column scales
    shared: list = []  # the kept rows' Gram matrix, formed once when a column needs it
    lock = threading.Lock()

    def inliers_gram(inl):  # each column's inlier Gram matrix is formed from the shared one
        with lock:
            if not shared:
                shared.append(a.T @ a)
        return inlier_gram(a, shared[0], inl[:, None].astype(float))[0]

    if row_noise is not None:  # a sparse array (screen_rows converts it)
        unit = theta / np.where(norms > 0, norms, 1.0)
        shared_noise = scipy.sparse.csr_array(row_noise @ row_noise.T)  # C = D D^T, banded
        own = shared_noise.diagonal()
        typical = float(np.median(own[rows])) if rows.size else 1.0

    # Columns with the same inliers share their leverages (on clean data, most do).
    inliers = np.abs(r[rows]) <= np.asarray(delta)[None, :]
    groups: dict = {}
    for k in range(r.shape[1]):
        groups.setdefault(inliers[:, k].tobytes(), []).append(k)

    def group(cols):  # writes only the columns `cols` of `out`: groups run side by side
        inl = inliers[:, cols[0]]
        at = rows[inl]
        if row_noise is None:
            lev = None
            if cache is not None:
                member = np.zeros(theta.shape[0], dtype=bool)
                member[at] = True
                lev = cache.leverages(cols, member, lambda: inliers_gram(inl))
            lev = _leverages(a[inl], inliers_gram(inl)) if lev is None else lev[at]
            rest = np.maximum(1.0 - lev, np.finfo(float).eps)
            scale = np.where(suspect[at], rest, np.sqrt(rest))
            for k in cols:
                out[at, k] = r[at, k] / scale
            return
        g = inliers_gram(inl)
        # The noise a fit on the inliers leaves in each residual: in the kept inliers'
        # (I - H) C (I - H), in the other rows' (not fitted, or fitted only through
        # Huber's clipped score) that of a prediction.
        w = _hat_factor(g)  # H = (w a_in^T)^T (w a_in^T)
        q = w @ a[inl].T
        spread = np.sqrt(_correlated_share(q, shared_noise[at], at, w @ unit.T, own) / typical)
        # Kept suspects: also judged by the model fitted without them (deleted), the
        # larger of the two.
        rest = np.maximum(1.0 - np.einsum("ij,ij->j", q, q), np.finfo(float).eps)
        held = suspect[at]
        for k in cols:
            out[:, k] = r[:, k] / spread
            deleted = r[at[held], k] / rest[held]
            out[at[held], k] = np.where(
                np.abs(deleted) > np.abs(out[at[held], k]), deleted, out[at[held], k]
            )

    map_threads(group, list(groups.values()), flops=rows.size * theta.shape[1] ** 2)
    return out


#: The leverage cache's stored inverse Gram matrices (``p x p`` per target column) take
#: at most this many times the memory of the library matrix (``m x p``); the columns
#: beyond are computed afresh at every call.
LEVERAGE_CACHE_SIZE = 3.0

#: Rows changed (joined or left the inliers, cumulated since a column's last fresh
#: factorisation) beyond this share of the terms: a fresh factorisation (an update by
#: ``r`` rows costs about ``r / p`` of one, and every update adds its rounding).
LEVERAGE_UPDATE_SHARE = 0.5

#: Reciprocal condition number of an inlier Gram matrix below which its leverages are
#: not cached: an update's rounding in a leverage is about the machine epsilon over it,
#: 2e-5 here, far below what moves a residual across the screen's cutoff.  Judged as
#: :func:`~robust_sindy.solvers.newton.conditioned_cholesky` judges its cut (LAPACK's
#: 1-norm estimate at least this, or where the estimate cannot tell, the eigenvalues at
#: least this over ``CHOLESKY_MARGIN``), and never below the pseudo-inverse's cut: where
#: that fails, the pseudo-inverse decides as without the cache.
LEVERAGE_RCOND = 1e-11

#: Smallest eigenvalue magnitude (relative to the largest, at least 1) of the capacitance
#: matrix of an update: smaller, the rows changed nearly remove a direction of the Gram
#: matrix, and the column is factorised afresh.
LEVERAGE_PIVOT = 1e-6


class _Leverages(NamedTuple):
    """A column's cached state: its inlier rows (m,), the inverse of their Gram matrix,
    every row's leverage under it, and the rows changed since it was factorised."""

    member: np.ndarray
    inverse: np.ndarray
    leverage: np.ndarray
    spent: int


class _LeverageCache:
    """The leverages of :func:`_leverage_corrected`, per target column, carried from one
    pilot of the row screen to the next.

    Each column keeps the inverse ``G^-1`` of its inliers' Gram matrix and every row's
    leverage ``h_i = a_i G^-1 a_i^T`` (the rows scaled by the column norms of the first
    call, kept fixed: a leverage does not depend on them).  The next call updates them by
    the ``r`` rows that joined or left the inliers, or whose row of the library changed
    (the judge of :func:`_second_chance`), by the Sherman-Morrison-Woodbury formula:
    with ``U`` those rows (r x p), ``S`` their signs (+1 joined, -1 left), ``W = G^-1
    U^T`` and the capacitance ``K = S + U W``, ``G'^-1 = G^-1 - W K^-1 W^T`` and
    ``h'_i = h_i - z_i K^-1 z_i^T`` with ``z_i = a_i W``: ``m p r`` operations instead
    of ``m p^2``.  Between two pilots of the screen a few samples change, and only the
    inliers near the threshold ``delta`` come and go.

    A column is factorised afresh when it has no entry, when the rows changed since its
    last factorisation exceed :data:`LEVERAGE_UPDATE_SHARE` of the terms, when ``K`` is
    nearly singular (:data:`LEVERAGE_PIVOT`) or when an updated inlier's leverage leaves
    ``[0, 1]``.  It is not cached when its Gram matrix is ill-conditioned
    (:data:`LEVERAGE_RCOND`; the caller's pseudo-inverse then decides, for the rest of
    the screen) or when the entries would exceed :data:`LEVERAGE_CACHE_SIZE`.  The
    leverages agree with a fresh computation to within the rounding the condition
    number allows.
    """

    def __init__(self, theta, keep):
        norms = np.linalg.norm(theta[keep], axis=0)
        self.norms = np.where(norms > 0, norms, 1.0)
        self.theta = theta
        self.scaled = theta / self.norms
        self.moved = np.zeros(0, dtype=int)
        self.changed = np.zeros(theta.shape[0], dtype=bool)  # self.moved as a mask
        self.before = np.zeros((0, theta.shape[1]))
        self.entries: dict[int, _Leverages] = {}
        self.refused: set[int] = set()
        self.capacity = int(LEVERAGE_CACHE_SIZE * theta.shape[0] / theta.shape[1])

    def see(self, theta) -> None:
        """Start a call on ``theta`` (the same samples): the rows that differ from the
        last call's are updated in every column."""
        if theta is self.theta:
            self.moved = np.zeros(0, dtype=int)
            self.changed = np.zeros(theta.shape[0], dtype=bool)
            return
        self.changed = (theta != self.theta).any(axis=1)
        self.moved = np.flatnonzero(self.changed)
        self.before = self.scaled[self.moved]
        self.theta = theta
        self.scaled = theta / self.norms

    def leverages(self, cols, member, gram):
        """Every row's leverage (m,) under the inliers ``member`` (m,) of the columns
        ``cols`` (which share them), or None where the Gram matrix is ill-conditioned;
        ``gram()`` forms that matrix when a fresh factorisation needs it."""
        if cols[0] in self.refused:
            return None
        entry = self.entries.get(cols[0])
        new = None if entry is None else self._update(entry, member)
        if new is None:
            new = self._fresh(member, gram())
        if new is None:  # ill-conditioned: this column's leverages are not cached
            self.refused.update(cols)
            for k in cols:
                self.entries.pop(k, None)
            return None
        if len(self.entries) < self.capacity or cols[0] in self.entries:
            for k in cols:
                self.entries[k] = new
        return new.leverage

    def _fresh(self, member, g):
        cut = max(LEVERAGE_RCOND / CHOLESKY_MARGIN, g.shape[0] * np.finfo(float).eps)
        c = conditioned_cholesky(g, cut)
        if c is None:
            return None
        z = scipy.linalg.solve_triangular(c, self.scaled.T, lower=True, check_finite=False)
        leverage = np.einsum("ij,ij->j", z, z)
        inverse, info = scipy.linalg.lapack.dpotri(c, lower=True)
        if info != 0:
            return None
        inverse = np.tril(inverse) + np.tril(inverse, -1).T
        return _Leverages(member.copy(), inverse, leverage, 0)

    def _update(self, entry: _Leverages, member):
        a, moved, changed = self.scaled, self.moved, self.changed
        left = np.flatnonzero(entry.member & (~member | changed))
        joined = np.flatnonzero(member & (~entry.member | changed))
        r = left.size + joined.size
        if entry.spent + r > LEVERAGE_UPDATE_SHARE * entry.inverse.shape[0]:
            return None
        inverse, leverage = entry.inverse, entry.leverage
        if r:
            old = a[left]
            if moved.size:  # a row of the library that changed leaves as it was
                at = np.minimum(np.searchsorted(moved, left), moved.size - 1)
                was = moved[at] == left
                old[was] = self.before[at[was]]
            u = np.vstack([old, a[joined]])
            sign = np.concatenate([-np.ones(left.size), np.ones(joined.size)])
            w = inverse @ u.T
            vals, vecs = np.linalg.eigh(np.diag(sign) + u @ w)
            if np.min(np.abs(vals)) <= LEVERAGE_PIVOT * max(1.0, np.max(np.abs(vals))):
                return None
            k_inv = (vecs / vals) @ vecs.T
            z = a @ w
            leverage = leverage - np.einsum("ij,ij->i", z @ k_inv, z)
            inverse = inverse - (w @ k_inv) @ w.T
            inverse = (inverse + inverse.T) / 2
        if moved.size:
            leverage = leverage.copy()
            leverage[moved] = np.einsum("ij,ij->i", a[moved] @ inverse, a[moved])
        inside = leverage[member]
        if np.any(inside < -LEVERAGE_PIVOT) or np.any(inside > 1.0 + LEVERAGE_PIVOT):
            return None
        return _Leverages(member.copy(), inverse, leverage, entry.spent + r)


def _hat_factor(gram):
    """``w`` (rank x p) with ``(w a^T)^T (w a^T)`` the hat matrix of ``a`` (``gram =
    a^T a``): the inverse Cholesky factor where its condition estimate allows, else the
    eigenvectors of ``gram`` above the pseudo-inverse's default cut, scaled."""
    c = conditioned_cholesky(gram, gram.shape[0] * np.finfo(float).eps)
    if c is not None:
        return scipy.linalg.solve_triangular(
            c, np.eye(gram.shape[0]), lower=True, check_finite=False
        )
    vals, vecs = np.linalg.eigh(gram)
    big = vals > max(gram.shape) * np.finfo(float).eps * max(vals.max(), 0.0)
    return (vecs[:, big] / np.sqrt(vals[big])).T


def _correlated_share(q, c_in, at, z, own) -> np.ndarray:
    """The variance that correlated noise leaves in each residual of a least-squares fit
    on the inliers ``at`` (hat matrix ``q^T q``, q: rank x inliers), the rows' noise
    ``D e`` with covariance ``C = D D^T`` (``c_in = C[at]``, sparse inliers x rows): for
    row ``i`` with ``z_i = w a_i^T`` and ``own_i = C_ii``, ``C_ii - 2 z_i^T q C[at, i] +
    z_i^T q C[at, at] q^T z_i`` (for the inliers themselves, ``diag((I - H) C (I -
    H))``).  Formed from ``C``, banded (rows share noise only where their test
    functions share samples), not from ``D``: ``q C[at, at] q^T`` costs rank² x inliers,
    where ``(q D_in)(q D_in)^T`` cost rank² x sources (the samples)."""
    qc = np.asarray((c_in.T @ q.T).T)  # q C[at, :]: rank x rows
    cross = np.einsum("ij,ij->j", z, qc)
    inner = np.einsum("ij,ij->j", z, (qc[:, at] @ q.T) @ z)
    return np.maximum(own - 2.0 * cross + inner, np.finfo(float).eps * own)


def _leverages(a, gram):
    """``a_i H^+ a_i^T`` for each row of ``a``, ``H = gram = a^T a``: by a Cholesky
    factor where its condition estimate shows that the pseudo-inverse would cut no
    eigenvalue (the same value, a fraction of the work), else by the pseudo-inverse
    (whose default cut, ``max(shape) * eps``, is the one tested)."""
    c = conditioned_cholesky(gram, gram.shape[0] * np.finfo(float).eps)
    if c is not None:
        z = scipy.linalg.solve_triangular(c, a.T, lower=True, check_finite=False)
        return np.einsum("ij,ij->j", z, z)
    return np.einsum("ij,ij->i", a @ np.linalg.pinv(gram, hermitian=True), a)


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


class _Outcome(NamedTuple):
    """One iteration of the pilots (:meth:`_Pilots.iterate`): the flags, the residual
    scale per equation, the rounds, whether the flags settled, and the last pilot's
    residuals (m, n), coefficients (p, n) and ``delta`` (n,)."""

    flags: np.ndarray
    scale: np.ndarray
    rounds: int
    converged: bool
    residuals: np.ndarray
    coef: np.ndarray
    delta: np.ndarray


def _pilot_fits(theta_k, y_k, groups, start, method, budget) -> list:
    """The pilot's fits of the columns ``groups`` (a list of arrays of column indices) on
    the kept samples' ``theta_k`` and ``y_k``: ``(cols, delta, coef)`` per group.  The
    fits of delta's iteration and the pilot's own fit share the library's preparation
    and the inlier Gram matrices of their Newton steps, group by group (columns are
    fitted independently), so that each group's matrices carry over; the groups run
    side by side on the machine's cores, each in its own block, as it would alone."""

    # The library's preparation formed once for the groups' blocks (the fast path's).
    prepared = preparations(theta_k) if method == "admm" and len(groups) > 1 else None

    def one(cols):  # each group in its own block: the groups run side by side
        with shared_preparation(prepared):
            b = budget
            begin = None if start is None else (start[0][cols], start[1][:, cols])
            d, c = auto_delta(
                theta_k, y_k[:, cols], method=method, return_coef=True, start=begin, **b
            )
            if method == "admm":
                b = {**b, "warm_start": c}
            fitted = fit(theta_k, y_k[:, cols], method, d, 0.0, **b).coef
            return cols, d, fitted.reshape(theta_k.shape[1], -1)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return map_threads(one, groups)


def _pilot_task(item, theta, y) -> list:
    """One worker's share of a pilot (:func:`_pilot_fits` on the samples kept)."""
    keep, groups, start, method, budget = item
    return _pilot_fits(theta[keep], y[keep], groups, start, method, budget)


class _Pilots:
    """The unpenalised Huber pilots of :func:`screen_rows` and the iterations over them,
    on ``theta`` (m, p) and ``y`` (m, n), started from the samples ``first``."""

    def __init__(
        self, theta, y, first, segments, half, noise, cutoff, rounds, method, row_noise=None,
        cache=None,
    ):  # fmt: skip
        self.theta, self.y, self.first = theta, y, first.copy()
        self.row_noise = row_noise
        # Each pilot's leverages are updated from the last one's (independent rows).
        if cache is None and row_noise is None:
            cache = _LeverageCache(theta, first)
        self.cache = cache
        self.segments, self.half, self.noise = segments, half, noise
        self.cutoff, self.rounds, self.method = cutoff, rounds, method
        rms = np.sqrt(np.mean(y**2, axis=0))
        self.rms = np.where(rms > 0, rms, 1.0)
        # The pilots only propose flags: a bounded budget, their certificates not
        # required (the final fit of the kept samples is certified on its own).
        self.budget = pilot_budget(method)
        self._sent: tuple = (None,)  # theta and y on a cluster's workers (on_cluster)

    def on_cluster(self, dask_client) -> tuple:
        """``theta`` and ``y`` sent to the workers of ``dask_client`` (once per client)."""
        if self._sent[0] is not dask_client:
            self._sent = (
                dask_client,
                cluster.scattered(dask_client, self.theta),
                cluster.scattered(dask_client, self.y),
            )
        return self._sent[1:]

    def with_theta(self, theta) -> _Pilots:
        """The same pilots on another library matrix (of the same samples)."""
        return _Pilots(
            theta, self.y, self.first, self.segments, self.half, self.noise, self.cutoff,
            self.rounds, self.method, self.row_noise, self.cache,
        )  # fmt: skip

    def bound_of(self, r, scale, coef, with_local: bool = True):
        """Each residual's bound: the scale, the local scale of the trusted samples'
        residuals (with ``with_local``), and the state noise carried through the model (no
        more of it than the residuals themselves show)."""
        bound = np.broadcast_to(scale, r.shape)
        if with_local and self.segments is not None:
            local = _segment_local_scale(r, self.segments, self.half, self.first)
            bound = np.maximum(bound, local)
        if self.noise is not None:
            carried = carried_noise(self.noise, coef)
            factor = [residual_noise_factor(r[:, k], carried[:, k]) for k in range(r.shape[1])]
            bound = np.maximum(bound, np.sqrt(factor) * carried)
        return bound

    def pilot(self, keep, start=None):
        """The unpenalised Huber pilot on ``keep``: coefficients and residuals of every
        sample, centred on the kept ones' median, those of the kept samples corrected for
        their leverage (:func:`_leverage_corrected`), and its ``delta``.  ``start``, the
        ``(delta, coef)`` of a pilot on nearly the same samples, starts its choice of
        ``delta`` (:func:`~robust_sindy.selection.auto_delta`)."""
        theta, y, method = self.theta, self.y, self.method
        theta_k, y_k = theta[keep], y[keep]
        p, n = theta.shape[1], y.shape[1]
        delta, coef = np.zeros(n), np.zeros((p, n))
        groups = column_groups(n, theta_k.shape)
        if start is None and len(groups) > 1:  # one least-squares fit of every column
            start = least_squares_start(theta_k, y_k)
        dask_client = cluster.client()
        if dask_client is None or len(groups) < 2:
            fits = _pilot_fits(theta_k, y_k, groups, start, method, self.budget)
            del theta_k, y_k
        else:
            # On a cluster: the groups in one run per worker (the same groups, so the
            # same fits: a batched fit's iterations depend on its group's columns).
            del theta_k, y_k
            runs = cluster.split(len(groups), cluster.workers(dask_client))
            items = [(keep, [groups[i] for i in run], start, method, self.budget) for run in runs]
            done = cluster.map_tasks(dask_client, _pilot_task, items, *self.on_cluster(dask_client))
            fits = [f for out in done for f in out]
        for cols, d, c in fits:
            delta[cols], coef[:, cols] = d, c
        r = y - theta @ coef
        r = r - np.median(r[keep], axis=0)
        corrected = _leverage_corrected(
            theta, r, keep, delta, ~self.first, self.row_noise, self.cache
        )
        return coef, corrected, delta

    def _chance(self, keep) -> int:
        """The most of the samples ``keep`` that Gaussian residuals put beyond the
        cutoff in some equation, but for a probability ``SETTLED_EVIDENCE`` (binomial)."""
        per_sample = -np.expm1(self.y.shape[1] * np.log1p(-2.0 * scipy.stats.norm.sf(self.cutoff)))
        return int(scipy.stats.binom.isf(SETTLED_EVIDENCE, int(keep.sum()), per_sample))

    def scaled(self, r, scale, coef):
        """Each sample's largest residual over ``cutoff`` times its bound (> 1: gross)."""
        return gross_ratio(r, self.bound_of(r, scale, coef), self.cutoff)

    def iterate(self, keep, start=None) -> _Outcome:
        """Refit on the samples kept until the flags are stable (after the free rounds,
        or once the flags repeat an earlier round's, flags are only added: no
        oscillation).  The pilot is a function of the samples kept, so flags that repeat
        an earlier round's cycle for ever; they become the union of the cycle at once,
        and flags that leave out exactly the samples ``keep`` left out are stable at
        once (the next pilot would be the same fit).  A round on samples an earlier
        round kept reuses that round's pilot (a cycle returns to them), so the pilot
        is one fit per set of samples.  ``start``, the ``(delta, coef)`` of a pilot on
        nearly the same problem, starts the first round's choice of ``delta``; each
        later round starts from the round before."""
        p = self.theta.shape[1]
        flags, converged, done, scale = ~keep, False, 0, np.zeros(self.y.shape[1])
        history: list[np.ndarray] = []
        pilots: dict[bytes, tuple] = {}  # the pilot of each set of samples kept
        monotone = False
        for done in range(1, self.rounds + 1):
            # Delta's iteration starts from the last pilot's (the first round's from
            # ``start`` when given, else from least squares).
            key = np.packbits(keep).tobytes()
            if key not in pilots:
                pilots[key] = self.pilot(keep, start)
            coef, r, delta = pilots[key]
            start = (delta, coef)
            scale = np.maximum(np.atleast_1d(robust_scale(r[keep])), SCALE_FLOOR * self.rms)
            new = self.scaled(r, scale, coef) > 1
            if done > 1 and (monotone or done > _FREE_ROUNDS):
                if self.row_noise is not None and (new & ~flags).sum() <= self._chance(keep):
                    # Correlated rows: each refit redraws the residuals near the cutoff,
                    # and no more rows crossed it than noise alone gives.
                    converged = True
                    break
                new |= flags
            if np.array_equal(new, flags):
                converged = True
                break
            seen = [j for j, old in enumerate(history) if np.array_equal(old, new)]
            if seen:
                new = np.logical_or.reduce(history[seen[0] :])
                monotone = True
            history.append(new)
            flags = new
            keep = ~flags
            if keep.sum() <= p:
                break
        return _Outcome(flags, scale, done, converged, r, coef, delta)

    def forward(self, keep, scale0):
        """Forward search: grow the kept set from ``keep`` by the excluded samples with
        the smallest scaled residuals, 2 % of the samples at a time, refitting after
        each, until 90 % are in; return the samples explained (residual within the
        bound at ``scale0``) by the step whose model explained most."""
        m, p = self.theta.shape
        keep = keep.copy()
        step = max(p, int(np.ceil(_COMPETE_MARGIN * m)))
        best, best_n = keep.copy(), -1
        for _ in range(50):
            coef, r, _ = self.pilot(keep)
            z = self.scaled(r, scale0, coef)
            n_ok = int((z <= 1).sum())
            if n_ok > best_n:
                best, best_n = z <= 1, n_ok
            out = np.flatnonzero(~keep)
            if out.size == 0 or keep.mean() > 0.9:
                break
            keep[out[np.argsort(z[out])[:step]]] = True
        return best


def screen_rows(
    theta,
    xdot,
    *,
    start=None,
    segments=None,
    cutoff: float = GROSS_CUTOFF,
    scale_window: int = SCALE_WINDOW,
    max_rounds: int = 20,
    method: str = "admm",
    noise=None,
    alternative=None,
    row_noise=None,
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
       (after five rounds flags are only added, so the iteration cannot oscillate;
       with ``row_noise``, a round that would add no more flags than Gaussian residuals
       put beyond the cutoff, ``SETTLED_EVIDENCE``, ends it without them);
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
       That comparison leaves out the local scale of each outcome's own residuals, so
       that a pilot bent by gross errors cannot excuse its residuals by the local scale
       they raise.
    5. with an ``alternative`` row for some samples (:class:`~robust_sindy.HuberSINDy`
       passes the library of the readings the temporal screen repaired), a flagged
       sample whose alternative row is not gross under the final pilot is kept with
       that row, a kept sample takes its alternative row where that row's residual is
       the smaller (both judged by a pilot fitted on the kept samples with the
       alternative rows in, at one bound: that of this pilot's residuals, which glitched
       rows crowding a sample's neighbourhood do not raise), and the iteration runs
       once more from the samples so kept: a glitch in one entry costs that entry, not
       the sample, and a moderate glitch does not stay in the fit.

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
    noise : LibraryNoise or list of array_like (m, p), optional
        Per state, the first-order noise of every library column at every sample (the
        state's noise level times the column's derivative by that state).
    alternative : tuple (ndarray of int (k,), ndarray (k, p)), optional
        Samples and another row of ``theta`` for each (step 5).
    row_noise : sparse matrix or array_like (m, s), optional
        Rows whose noise is correlated: the noise of row ``i`` is ``row_noise[i] @ e``
        for independent sources ``e`` of equal scale (the weak form's rows, integrals
        of the same samples).  Every residual is then studentised by the share of that
        noise a fit leaves in it (step 3), which for overlapping rows is far below
        ``1 - h_i``: without it, a fit that absorbs most of the noise makes the scale
        too small and good rows gross.

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
    check_huber_method(method, "the pilot fits")
    m, p = theta.shape
    if noise is not None:
        if not isinstance(noise, LibraryNoise):
            noise = LibraryNoise.of([as_float_array(a, "noise", (2,)) for a in noise])
        if noise.shape != (m, p):
            raise ValueError(f"noise must be a list of arrays of shape ({m}, {p})")
    if start is None:
        keep = np.ones(m, dtype=bool)
    else:
        keep = np.asarray(start, dtype=bool).copy()
        if keep.shape != (m,):
            raise ValueError(f"start must be a boolean mask of shape ({m},); got {keep.shape}")
    if keep.sum() < max(2 * p, m // 2):
        keep = np.ones(m, dtype=bool)  # too little left to fit: start from everything
    if row_noise is not None:
        row_noise = scipy.sparse.csr_array(row_noise)
        if row_noise.shape[0] != m:
            raise ValueError(f"row_noise must have {m} rows; got {row_noise.shape[0]}")
    pilots = _Pilots(theta, y, keep, segments, half, noise, cutoff, rounds, method, row_noise)
    first, rms = pilots.first, pilots.rms
    outcome = pilots.iterate(keep)
    flags, scale, r, coef = outcome.flags, outcome.scale, outcome.residuals, outcome.coef
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
        everything = pilots.iterate(np.ones(m, dtype=bool))
        cands = [everything, pilots.iterate(pilots.forward(~flags, scale))]
        common = np.minimum.reduce([scale] + [c.scale for c in cands])
        # Judged without the local scale of each one's own residuals: a pilot bent by
        # gross errors has large residuals on good samples too, which would raise its
        # local bound everywhere and excuse them.
        bounds = [
            (rr, pilots.bound_of(rr, common, cc, with_local=False))
            for rr, cc in [(r, coef)] + [(c.residuals, c.coef) for c in cands]
        ]
        explained = [int((gross_ratio(rr, b, cutoff) <= 1).sum()) for rr, b in bounds]
        best = int(np.argmax(explained))
        if best > 0 and explained[best] - explained[0] > _COMPETE_MARGIN * m:
            outcome = cands[best - 1]
            restarted = True
    swapped = np.zeros(m, dtype=bool)
    if alternative is not None:
        outcome, swapped = _second_chance(pilots, outcome, alternative)
    return Screening(
        outcome.flags, outcome.scale, outcome.scale / rms, first, outcome.rounds,
        outcome.converged, restarted, swapped, (outcome.delta, outcome.coef),
    )  # fmt: skip


def _second_chance(pilots: _Pilots, outcome, alternative):
    """Step 5 of :func:`screen_rows`.  A judge pilot is fitted on the samples
    ``outcome`` (an iteration's result) kept, with the ``alternative`` rows in (the
    final pilot was fitted with the samples' own rows, which bend it towards a glitched
    row it kept).  Under it, a flagged sample takes its alternative row when that row is
    not gross, a kept one when that row's residual is the smaller, both at the judge's
    bound (the own rows' residuals would raise the local scale that excuses them where
    glitched samples crowd, and with half of the samples touched the screen's start
    holds every sample); then the iteration runs again from the samples kept.  The
    judge's choice of ``delta`` starts from the iteration's last pilot, and the
    iteration's from the judge (pilots on nearly the same samples and rows)."""
    flags, scale = outcome.flags, outcome.scale
    at, rows = np.asarray(alternative[0], dtype=int), alternative[1]
    swapped = np.zeros(flags.size, dtype=bool)
    if not at.size:
        return outcome, swapped
    mixed = pilots.theta.copy()
    mixed[at] = rows
    judge = pilots.with_theta(mixed)
    coef, _, delta = judge.pilot(~flags, (outcome.delta, outcome.coef))
    r_alt = pilots.y - mixed @ coef
    centre = np.median(r_alt[~flags], axis=0)
    r_alt -= centre
    r_own = r_alt.copy()
    r_own[at] = pilots.y[at] - pilots.theta[at] @ coef - centre
    # Both rows of a sample are judged at one bound, the judge's own (the local scale
    # of its residuals, with the repaired rows in): the own rows' residuals would
    # raise the local scale that excuses them where glitched samples crowd.
    bound = judge.bound_of(r_alt, scale, coef)
    own = gross_ratio(r_own, bound, judge.cutoff)[at]
    alt = gross_ratio(r_alt, bound, judge.cutoff)[at]
    take = np.where(flags[at], alt <= 1, alt < own)
    if not take.any():
        return outcome, swapped
    swapped[at[take]] = True
    theta = pilots.theta.copy()
    theta[at[take]] = rows[take]
    outcome = pilots.with_theta(theta).iterate(~flags | swapped, (delta, coef))
    return outcome, swapped & ~outcome.flags


@dataclass(frozen=True)
class RowScreen:
    """Outcome of :func:`screen_samples`.

    Attributes
    ----------
    keep : ndarray of bool (m,)
        The samples the fit keeps.
    screening : Screening or None
        The row screen's details, its masks over all samples (None without the screen).
    """

    keep: np.ndarray
    screening: Screening | None


def screen_samples(
    problem: Problem,
    entry_flags,
    unresolved,
    *,
    measured: bool,
    method: str,
    screen: bool,
    alternative=None,
    row_noise=None,
) -> RowScreen:
    """The samples to fit: with ``screen``, those whose derivatives are resolved
    (``unresolved``: estimated derivatives the sampling does not resolve carry a
    systematic error that the library would explain with spurious terms) and that
    :func:`screen_rows` keeps, started from the samples without temporally flagged
    entries (``entry_flags``, m x n).  The state noise carried through the model excuses
    residuals only with ``measured`` derivatives: estimated ones add their own errors
    along fast excursions, where the carried noise is largest.  ``alternative`` (samples,
    and their rows in user units) is passed on to :func:`screen_rows`, whose
    ``swapped`` then marks those samples (of all) kept with it.  ``row_noise`` (sparse,
    samples x sources) makes the screen studentise for correlated rows
    (:func:`screen_rows`)."""
    m = problem.shape[0]
    if not screen:
        return RowScreen(np.ones(m, dtype=bool), None)
    keep = ~unresolved
    noise = problem.noise if measured else None
    other = None
    if alternative is not None:
        at, rows = np.asarray(alternative[0], dtype=int), alternative[1]
        usable = keep[at]
        position = np.cumsum(keep) - 1
        other = (position[at[usable]], problem.scaler.theta(rows[usable]))
    found = screen_rows(
        problem.theta_s[keep],
        problem.y_s[keep],
        start=~entry_flags.any(axis=1)[keep],
        segments=segments_of(keep, problem.segments),
        method=method,
        noise=None if noise is None else noise.rows(keep),
        alternative=other,
        row_noise=None if row_noise is None else scipy.sparse.csr_array(row_noise)[keep],
    )
    outliers, start, swapped = (np.zeros(m, dtype=bool) for _ in range(3))
    outliers[keep], start[keep], swapped[keep] = found.outliers, found.start, found.swapped
    return RowScreen(
        keep & ~outliers, replace(found, outliers=outliers, start=start, swapped=swapped)
    )
