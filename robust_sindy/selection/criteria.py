"""Criteria that pick ``lam``: robust BIC and blocked cross-validation; :func:`select`."""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from ..core.losses import huber, huber_psi
from ..core.statistics import correlation_time
from ..core.threads import map_threads
from ..core.validation import check_int, check_problem, loss_delta
from ..fitting import (
    HUBER_EFFICIENCY_CONSTANT,
    ConvergenceWarning,
    auto_delta,
    check_huber_method,
    fit,
)
from .lam_path import Path, path, pilot_budget
from .refit import STAGE_ROUNDS, refit_column, select_column
from .subsets import best_subsets, subset_sizes

__all__ = [
    "CRITERIA",
    "MIN_BIC_MARGIN",
    "OUT_OF_REACH_GROWTH",
    "OUT_OF_REACH_POINTS",
    "STABLE_POINTS",
    "Selection",
    "bic_from_loss",
    "bic_terms",
    "blocked_folds",
    "information_criterion",
    "score_margin",
    "select",
]

#: Criteria :func:`select` accepts.
CRITERIA = ("bic", "cv")

#: BIC difference between the chosen support and the best other candidate below which
#: the data do not strongly prefer the chosen support (6: "strong" evidence on the
#: scale of Kass and Raftery, 1995).
MIN_BIC_MARGIN = 6.0


def information_criterion(theta, xdot, coef, delta, scale=None, tau=None) -> np.ndarray | float:
    """Robust BIC per column: ``(2 sum_i rho(r_i / sigma)) / tau + k log(m / tau)``.

    ``rho`` is Huber's loss with threshold ``c = delta / sigma`` in standardised units,
    i.e. ``2 sum_i H_delta(r_i) / sigma**2``; ``k`` counts the nonzero coefficients and
    ``sigma`` is ``scale`` (default ``delta / 1.345``, the scale :func:`auto_delta`
    measured).  ``tau`` (default 1) is the correlation time of the residuals
    (:func:`correlation_time`): ``m / tau`` is the effective number of samples.  At
    independent Gaussian residuals it is the usual BIC; gross residuals add only
    linearly.  Returns (n,), or a float for a 1-D ``xdot``.
    """
    theta, y, one_d = check_problem(theta, xdot)
    n = y.shape[1]
    delta_k = loss_delta("huber", delta, n)
    coef = np.asarray(coef, dtype=float).reshape(theta.shape[1], n)
    tau = np.ones(n) if tau is None else np.broadcast_to(np.asarray(tau, float), (n,))
    sigma, penalty = bic_terms(theta.shape[0], delta_k, tau, scale)
    loss = huber(y - theta @ coef, delta_k).sum(axis=0)
    out = bic_from_loss(loss, np.count_nonzero(coef, axis=0), sigma, penalty, tau)
    return float(out[0]) if one_d else out


def bic_from_loss(loss, size, sigma, penalty, tau):
    """:func:`information_criterion` from a Huber loss and a number of terms (or a
    lower bound on it from a lower bound on the loss)."""
    return 2.0 * loss / sigma**2 / tau + size * penalty


def bic_terms(m, delta, tau, scale=None):
    """The scale ``sigma`` and the penalty per term ``log(m / tau)`` of
    :func:`information_criterion` (per column; ``delta`` and ``tau`` arrays (n,))."""
    sigma = (
        delta / HUBER_EFFICIENCY_CONSTANT
        if scale is None
        else np.broadcast_to(np.asarray(scale, float), delta.shape)
    )
    return sigma, np.log(np.maximum(m / tau, 2.0))


def blocked_folds(m: int, n_folds: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """Contiguous blocks of samples as validation sets: ``[(train, test), ...]``.

    Time series samples are not exchangeable: neighbouring samples are nearly equal,
    so shuffled folds validate on copies of the training data.  Each test set here is
    one contiguous block of ``m // n_folds`` or one more samples, in time order.
    """
    m = check_int(m, "m", 1)
    n_folds = check_int(n_folds, "n_folds", 2)
    if n_folds > m:
        raise ValueError(f"n_folds ({n_folds}) must not exceed the number of samples ({m})")
    edges = np.linspace(0, m, n_folds + 1).round().astype(int)
    idx = np.arange(m)
    return [(np.concatenate([idx[:a], idx[b:]]), idx[a:b]) for a, b in itertools.pairwise(edges)]


@dataclass(repr=False)
class Selection:
    """Outcome of :func:`select`.

    Attributes
    ----------
    coef : ndarray, shape (p, n)
        The selected model: the selection stage's refit at the chosen ``lam``.
    lam, delta : ndarray, shape (n,)
    index : ndarray of int, shape (n,)
        Chosen position on the path per column.
    scores : ndarray, shape (L, n)
        The criterion at every path point (lower is better); with
        ``criterion="bic"``, ``nan`` past the point where the column's path stopped
        (see :func:`select`).
    candidates : ndarray, shape (L, p, n)
        The selection stage's refit at every path point (zero past the stop).
    support : ndarray of bool, shape (p, n)
    path : Path
    criterion : str
    margin : ndarray, shape (n,)
        Per column, how much worse the best candidate with another support scored than
        the chosen one (:func:`score_margin`; ``inf`` when every point has the same
        support).  For ``criterion="bic"`` it is a BIC difference: below about 6 the
        data do not strongly prefer the chosen support.  With ``criterion="bic"`` it
        counts the best-subset candidates too.
    rival_margin : ndarray, shape (n,)
        The same over the candidates that are another model: they leave out a chosen
        term or change a chosen coefficient by more than half
        (``score_margin(..., rivals=True)``): below about 6 the data do not strongly
        prefer the chosen model.
    subsets : ndarray, shape (E, p, n)
        For ``criterion="bic"``, the selection stage's refit of the best few supports
        of every size up to ``subset_size`` (:func:`best_subsets`); empty otherwise.
    subset_scores : ndarray, shape (E, n)
        Their criterion.
    subset_size : ndarray of int, shape (n,)
        The largest support size searched exhaustively (0: not searched).
    from_subsets : ndarray of bool, shape (n,)
        Equations whose chosen support came from that search, not the path; ``index``
        and ``lam`` are then the best path point's.
    tau : ndarray, shape (n,)
        For ``criterion="bic"``, the correlation time of the residuals the criterion
        counted (the larger of the most complete model's and the chosen path point's;
        see :func:`select`); ones otherwise.
    """

    coef: np.ndarray
    lam: np.ndarray
    delta: np.ndarray
    index: np.ndarray
    scores: np.ndarray
    candidates: np.ndarray
    support: np.ndarray
    path: Path
    criterion: str
    margin: np.ndarray
    subsets: np.ndarray
    subset_scores: np.ndarray
    subset_size: np.ndarray
    from_subsets: np.ndarray
    rival_margin: np.ndarray
    tau: np.ndarray | None = None

    def rival_margin_to(self, reference: np.ndarray, theta=None, y=None) -> np.ndarray:
        """:attr:`rival_margin` with the model finally reported, ``reference`` (p, n,
        in the units of the candidates), in the chosen one's place
        (:func:`score_margin`; with ``reference = coef`` it is :attr:`rival_margin`).

        With the selection's design ``theta`` and derivatives ``y``, ``reference`` is
        scored too (the criterion at the selection's ``delta`` and correlation time),
        and the margin is measured from it where it scores better than the chosen
        candidate: a term the final selection put back (and the ones it made
        redundant) can make the reported model better than every candidate, and the
        chosen candidate is then a rival at the difference, not at zero."""
        pooled = np.concatenate([self.candidates, self.subsets])
        scores = np.concatenate([self.scores, self.subset_scores])
        own = None
        if theta is not None:
            n = reference.shape[1]
            tau = np.ones(n) if self.tau is None else self.tau
            every = np.ones((1, n), dtype=bool)
            own = _scores(theta, y, reference[None], every, self.delta, tau)[0]
        return score_margin(
            scores, pooled, _pick(scores), rivals=True, reference=reference, reference_score=own
        )

    def __repr__(self) -> str:
        return (
            f"Selection(criterion={self.criterion!r}, "
            f"lam={np.array2string(self.lam, precision=3)}, "
            f"terms per column={self.support.sum(axis=0).tolist()})"
        )


class _Stage:
    """The selection stage of each column, its refits shared between identical supports
    (``caches``: one dict per column, support to refit).  ``dense_start`` (p, n), when
    given, starts the fast path's refit on every nonzero column of ``theta``."""

    def __init__(self, theta, y, delta, tol, method, solver, options, dense_start=None):
        self.theta, self.y, self.delta, self.tol = theta, y, delta, tol
        self.method, self.solver, self.options = method, solver, options
        self.caches: list[dict] = [{} for _ in range(y.shape[1])]
        self.col = np.linalg.norm(theta, axis=0)
        self.ynorm = np.linalg.norm(y, axis=0)
        self.every = np.any(theta != 0, axis=0)
        self.dense_start = dense_start if method == "admm" else None
        self._basis: np.ndarray | None = None
        self._floors: dict = {}

    def refit(self, k, keep):
        """Column ``k``'s unpenalised Huber refit on the terms ``keep``."""
        key = keep.tobytes()
        if key not in self.caches[k]:
            options = self.options
            if self.dense_start is not None and np.array_equal(keep, self.every):
                options = {**options, "warm_start": self.dense_start[keep, k]}
            self.caches[k][key] = refit_column(
                self.theta, self.y[:, k], keep, self.delta[k], self.method, self.solver,
                options,
            )  # fmt: skip
        return self.caches[k][key]

    def refit_every(self):
        """Every column's refit on every nonzero column of ``theta`` (the limit of the
        path's proposals), in one fit of all the columns: they share its library, whose
        equilibration and Gram matrix are then formed once, not once per column."""
        key = self.every.tobytes()
        todo = [k for k in range(self.y.shape[1]) if key not in self.caches[k]]
        if not todo:
            return
        coef = np.zeros((self.theta.shape[1], len(todo)))
        if self.every.any():
            options = self.options
            if self.dense_start is not None:
                options = {**options, "warm_start": self.dense_start[self.every][:, todo]}
            theta = self.theta if self.every.all() else self.theta[:, self.every]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                coef[self.every] = fit(
                    theta, self.y[:, todo], self.method, self.delta[todo], 0.0,
                    solver=self.solver, **options,
                ).coef.reshape(-1, len(todo))  # fmt: skip
        for i, k in enumerate(todo):
            self.caches[k][key] = coef[:, i]

    def floor_basis(self) -> np.ndarray:
        """An orthonormal basis of the library's nonzero columns (formed once)."""
        if self._basis is None:
            self._basis = np.linalg.qr(self.theta[:, self.every])[0]
        return self._basis

    def whole_floor(self, k) -> float:
        """A lower bound on column ``k``'s Huber loss on any support: no support fits
        better than every term together (:func:`_loss_floor`, the dual bound at the
        refit on every term, valid even if that refit stopped early).  Call
        :meth:`floor_basis` once before calling this from several threads."""
        if k not in self._floors:
            r = self.y[:, k] - self.theta @ self.refit(k, self.every)
            basis = self.floor_basis()
            self._floors[k] = _loss_floor(basis, self.y[:, k], None, self.delta[k], r, basis)
        return self._floors[k]

    def column(self, k, coef):
        """The stage on column ``k`` from the coefficients ``coef`` (p,)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            return self._column(k, coef)

    def _column(self, k, coef):
        return select_column(
            coef, self.tol, STAGE_ROUNDS, self.col, self.ynorm[k],
            lambda keep: self.refit(k, keep), self.caches[k],
        )  # fmt: skip

    def side_by_side(self, work, columns) -> list:
        """``[work(k) for k in columns]``, the columns in threads: ``work(k)`` may call
        :meth:`refit` and :meth:`_column` of column ``k`` only (each column's cache is its
        own).  The refits' ``ConvergenceWarning`` is filtered here, in the calling
        thread, as :meth:`column` does: a filter set and restored in several threads at
        once would leave the process's filters in the state of whichever thread
        restored last."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            return map_threads(work, list(columns))


def _stage_all(stage: _Stage, path_coef):
    """Selection stage at every path point (L, p, n)."""
    out = np.zeros_like(path_coef)
    for k in range(path_coef.shape[2]):
        for i in range(path_coef.shape[0]):
            out[i, :, k] = stage.column(k, path_coef[i, :, k])
    return out


#: A column's path stops once its selection stage has proposed the limit (the stage of
#: the unpenalised fit) at this many consecutive points past the limit's size.
STABLE_POINTS = 2

#: ... or once it has proposed, at this many consecutive points, supports that cannot
#: score within :data:`MIN_BIC_MARGIN` of the best candidate walked and that have at
#: least :data:`OUT_OF_REACH_GROWTH` times as many terms as that candidate.
OUT_OF_REACH_POINTS = 3

#: See :data:`OUT_OF_REACH_POINTS`.
OUT_OF_REACH_GROWTH = 2.0


class _Walk:
    """The selection stage along a path as it is walked (``until`` of :func:`path`).

    As ``lam`` falls the path tends to the unpenalised fit on every term, and the
    stage's proposal to the stage of that fit (``limit``).  The points still to come
    are the densest, and by far the most expensive.  A column's path is not walked
    further once

    * its proposal has been the limit's support at :data:`STABLE_POINTS` consecutive
      points with more terms than the limit: the points to come would propose it
      again; or
    * its proposals have been out of reach at :data:`OUT_OF_REACH_POINTS` consecutive
      points: so many terms that no fit on them can score within
      :data:`MIN_BIC_MARGIN` of the best candidate walked, and at least
      :data:`OUT_OF_REACH_GROWTH` times as many as that candidate.  A score is at
      least that of the least Huber loss of any support (the dual bound of
      :func:`_loss_floor` at the unpenalised fit on every term) plus its own size's
      penalty.  Where the limit's stage keeps most of the library (the noise of
      derivatives from noisy states leaves most terms above the stage's tolerance),
      the proposals never settle on the limit: they jump from the few terms of the
      best candidates to many and grow from there towards the limit's size.  The
      bound holds for each proposal walked; that the proposals still to come are no
      smaller is what the three points and the growth stand for (in small libraries
      the proposals can step back from a size just out of reach to a better one).
      The bound is on the BIC under the first correlation time ``tau`` (that of the
      limit's residuals); the choice only raises it (:func:`_settled_scores`), and a
      proposal out of reach stays behind the best under any longer one (``tau log(m
      / tau)`` grows with ``tau`` up to ``m / e``; the rule is off beyond).

    ``candidates`` (L, p, n) and ``used`` (L, n) are the proposals at the points
    walked, ``losses`` (L, n) their Huber losses, ``tau`` (n,) the first correlation
    time."""

    def __init__(self, stage: _Stage, n_points: int, segments=None):
        theta, y = stage.theta, stage.y
        m, p = theta.shape
        n = y.shape[1]
        every = stage.every
        self.stage = stage
        stage.refit_every()
        self.limit = np.stack(
            stage.side_by_side(lambda k: stage._column(k, stage.refit(k, every)), range(n)), 1
        )
        self.tau = correlation_time(huber_psi(y - theta @ self.limit, stage.delta), segments)
        self.sigma, self.penalty = bic_terms(m, stage.delta, self.tau)
        self.best = np.full(n, np.inf)  # the best score walked (under ``tau``)
        self.best_size = np.zeros(n, dtype=int)  # and its number of terms
        self.bounded = self.tau <= m / np.e
        self.candidates = np.zeros((n_points, p, n))
        self.used = np.zeros((n_points, n), dtype=bool)
        self.losses = np.full((n_points, n), np.nan)  # the proposals' Huber losses
        self.run = np.zeros(n, dtype=int)
        self.reach = np.zeros(n, dtype=int)

    def _out_of_reach(self, k, c, loss) -> bool:
        """Whether no fit on the terms of ``c`` can score within :data:`MIN_BIC_MARGIN`
        of the best candidate of column ``k`` walked so far (``c``, of Huber loss
        ``loss``, among them), and ``c`` has at least :data:`OUT_OF_REACH_GROWTH` times
        as many terms as that candidate."""
        size = np.count_nonzero(c)
        args = (self.sigma[k], self.penalty[k], self.tau[k])
        score = bic_from_loss(loss, size, *args)
        if score < self.best[k]:
            self.best[k], self.best_size[k] = score, size
        # (A proposal no larger than the best is never out of reach: the bound at its
        # size is at most the best's score.)
        best = self.best_size[k]
        if not self.bounded[k] or size <= best or size < OUT_OF_REACH_GROWTH * best:
            return False
        bound = bic_from_loss(self.stage.whole_floor(k), size, *args)
        return bound > self.best[k] + MIN_BIC_MARGIN

    def until(self, i, coef, cols):
        done = np.zeros(cols.size, dtype=bool)
        proposed = self.stage.side_by_side(lambda k: self.stage._column(k, coef[:, k]), cols)
        for a, (k, c) in enumerate(zip(cols, proposed, strict=True)):
            self.candidates[i, :, k] = c
            self.used[i, k] = True
            on, limit = c != 0, self.limit[:, k] != 0
            past = np.count_nonzero(coef[:, k]) > np.count_nonzero(limit)
            settled = past and np.array_equal(on, limit)
            stage = self.stage
            self.losses[i, k] = _candidate_loss(stage.theta, stage.y[:, k], c, stage.delta[k])
            # First: it keeps the best score walked.
            out_of_reach = self._out_of_reach(k, c, self.losses[i, k])
            self.run[k] = self.run[k] + 1 if settled else 0
            self.reach[k] = self.reach[k] + 1 if out_of_reach else 0
            done[a] = self.run[k] >= STABLE_POINTS or self.reach[k] >= OUT_OF_REACH_POINTS
        return done


def _candidate_loss(theta, y, coef, delta) -> float:
    """The Huber loss of one column's candidate ``coef`` (p,), from its own terms'
    columns."""
    on = np.flatnonzero(coef)
    return float(huber(y - theta[:, on] @ coef[on], delta).sum())


def _losses(theta, y, candidates, used, delta) -> np.ndarray:
    """:func:`_candidate_loss` of the candidates ``used`` (L, n), ``nan`` at the others."""
    out = np.full(used.shape, np.nan)
    for i, k in zip(*np.nonzero(used), strict=True):
        out[i, k] = _candidate_loss(theta, y[:, k], candidates[i, :, k], delta[k])
    return out


def _scored(m, losses, candidates, delta, tau) -> np.ndarray:
    """The BIC (:func:`information_criterion`) of candidates (L, p, n) of Huber losses
    ``losses`` (L, n; ``nan`` where there is no candidate) on ``m`` samples."""
    sigma, penalty = bic_terms(m, delta, tau)
    return bic_from_loss(losses, np.count_nonzero(candidates, axis=1), sigma, penalty, tau)


def _scores(theta, y, candidates, used, delta, tau):
    """The BIC (:func:`information_criterion`) of the candidates ``used`` (L, n),
    ``nan`` at the others; each from its own terms' columns."""
    losses = _losses(theta, y, candidates, used, delta)
    return _scored(theta.shape[0], losses, candidates, delta, tau)


def _settled_scores(theta, y, candidates, used, delta, tau, segments, losses=None):
    """The correlation times (n,) and the BIC (:func:`_scores`) of the candidates, with
    each column's correlation time that of the residuals of the candidate it chooses.

    Starting from ``tau`` (that of the most complete model's residuals), the candidates
    are scored, and the correlation time is raised to that of the chosen candidate's
    residuals, until the choice no longer raises it.  The most complete model fits
    every column, and library columns vary slowly in time: with a few samples per
    column its residuals have lost the slow part of the errors (the correlated errors
    of numerical derivatives over wide windows above all), and a criterion that takes
    its correlation time from them counts too many independent samples and prefers
    candidates fitted to those errors.  The correlation time only grows, and a
    candidate chosen again leaves it as it is, so this ends within as many rounds as
    there are candidates.

    The choice can settle twice: a candidate fitted to the errors' slow part shortens
    its own residuals' correlation time and is chosen under it, as a candidate the
    errors do not reach is under the longer one of its own residuals.  The choice
    settled from below is the first of them; the correlation time is then raised to the
    longest of a candidate's own residuals under which that candidate is chosen
    (:func:`_longest_settled`).

    ``losses`` (L, n), the candidates' Huber losses (:func:`_losses`) where already
    known; they do not depend on the correlation time, so they are computed once.
    """
    cols = np.arange(y.shape[1])
    if losses is None:
        losses = _losses(theta, y, candidates, used, delta)
    m = theta.shape[0]
    scores = _scored(m, losses, candidates, delta, tau)
    for _ in range(candidates.shape[0]):
        chosen = candidates[_pick(scores), :, cols].T
        new = np.maximum(tau, correlation_time(huber_psi(y - theta @ chosen, delta), segments))
        if np.array_equal(new, tau):
            break
        tau = new
        scores = _scored(m, losses, candidates, delta, tau)
    longest = _longest_settled(theta, y, candidates, used, delta, tau, segments)
    if not np.array_equal(longest, tau):
        tau = longest
        scores = _scored(m, losses, candidates, delta, tau)
    return tau, scores


def _longest_settled(theta, y, candidates, used, delta, tau, segments) -> np.ndarray:
    """Per column, the longest correlation time ``t`` above ``tau`` of a candidate's own
    residuals under which the BIC (:func:`_scores` with ``t``) chooses that candidate;
    ``tau`` where there is none."""
    m = theta.shape[0]
    out = np.array(tau, dtype=float)
    for k in range(y.shape[1]):
        first: dict[bytes, int] = {}  # one candidate per support, the earliest (_pick)
        for i in np.flatnonzero(used[:, k]):
            first.setdefault(np.packbits(candidates[i, :, k] != 0).tobytes(), i)
        rows = np.fromiter(first.values(), dtype=int)
        if rows.size < 2:
            continue
        coef = candidates[rows, :, k]
        r = y[:, k, None] - theta @ coef.T
        loss = huber(r, delta[k]).sum(axis=0)
        size = np.count_nonzero(coef, axis=1)
        own = correlation_time(huber_psi(r, delta[k]), segments)
        longer = np.flatnonzero(own > tau[k])
        t = own[longer]
        sigma, penalty = bic_terms(m, np.full(t.size, delta[k]), t)
        # Every candidate scored under each longer time (columns): which chooses its own.
        score = bic_from_loss(loss[:, None], size[:, None], sigma, penalty, t)
        settled = t[_pick(score) == longer]
        if settled.size:
            out[k] = settled.max()
    return out


def _subset_candidates(stage: _Stage, reference, tau, best):
    """Best-subset candidates of every equation (see ``Selection.subsets``): supports
    ranked under the Huber weights of ``reference`` (p, n), each refitted and put
    through the selection ``stage`` (its refits shared with the path's), then scored
    by the BIC with correlation times ``tau``.

    A support is skipped when it cannot score below ``best`` (n,), the best score so
    far: its Huber loss is at least that of the unpenalised fit on every term, and at
    least the dual objective of any feasible point (:func:`_loss_floor`, for both),
    so its score at least the larger of the two loss terms plus its own size's
    penalty.  Sizes the first bound rules out are not searched at all (``subset_size``
    is then smaller than the budget allows).
    """
    theta, y, delta = stage.theta, stage.y, stage.delta
    m, p = theta.shape
    n = y.shape[1]
    # The criterion's own terms: the bounds below are on its scores.
    sigma, penalty = bic_terms(m, delta, tau)
    every = stage.every
    whole_library = theta[:, every]
    stage.floor_basis()  # shared by every equation's floor
    # Shared by every equation's search of pairs and beyond (single terms need less).
    gram = whole_library.T @ whole_library if subset_sizes(whole_library.shape[1]) > 1 else None
    found, sizes = [[] for _ in range(n)], np.zeros(n, dtype=int)

    def equation(k):  # writes only equation k's entries: the equations run side by side
        r = np.abs(y[:, k] - theta @ reference[:, k])
        weights = np.minimum(1.0, delta[k] / np.maximum(r, np.finfo(float).tiny))

        def bic(loss, size, k=k):
            return bic_from_loss(loss, size, sigma[k], penalty[k], tau[k])

        whole = stage.whole_floor(k)
        floor = bic(whole, 0)
        top = best[k]
        # Sizes whose penalty alone takes them past the best score are not searched.
        reach = np.ceil((top - floor) / penalty[k]) - 1 if np.isfinite(top) else p
        masks, sizes[k] = best_subsets(theta, y[:, k], weights, max_size=reach, gram=gram)
        for mask in masks:
            if bic(whole, mask.sum()) >= top:
                continue
            dual = _loss_floor(theta[:, mask], y[:, k], weights, delta[k])
            if bic(dual, mask.sum()) >= top:
                continue
            c = stage._column(k, stage.refit(k, mask))
            found[k].append((c, information_criterion(theta, y[:, k], c, delta[k], tau=tau[k])))
            top = min(top, found[k][-1][1])

    stage.side_by_side(equation, range(n))
    count = max((len(v) for v in found), default=0)
    cands = np.zeros((count, p, n))
    scores = np.full((count, n), np.nan)
    for k, pairs in enumerate(found):
        for i, (c, v) in enumerate(pairs):
            cands[i, :, k], scores[i, k] = c, v
    return cands, scores, sizes


def _loss_floor(a, y, weights, delta, residuals=None, basis=None) -> float:
    """A lower bound on ``min_b sum_i H_delta(y_i - a_i b)``: the dual objective
    ``y'u - |u|^2 / 2`` at a feasible ``u`` (``a'u = 0``, ``|u_i| <= delta``), the
    clipped ``residuals`` (default: of the ``weights``-weighted least-squares fit)
    projected onto the null space of ``a'`` (``basis``: an orthonormal basis of the
    columns of ``a``, when known) and scaled into the box.  It holds whether or not
    the fit that gave the residuals converged."""
    if residuals is None:
        sw = np.sqrt(weights)
        b = np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)[0]
        residuals = y - a @ b
    u = np.clip(residuals, -delta, delta)
    q = np.linalg.qr(a)[0] if basis is None else basis
    u = u - q @ (q.T @ u)
    u *= min(1.0, delta / max(np.max(np.abs(u)), np.finfo(float).tiny))
    return float(y @ u - 0.5 * u @ u)


#: A candidate that keeps every chosen term but changes one of their coefficients by
#: more than this share (or its sign) is another model, not the chosen one plus a term.
RIVAL_CHANGE = 0.5


def _rival(candidate, chosen_coef) -> bool:
    """Whether ``candidate`` (p,) leaves out a term of ``chosen_coef`` (p,) or changes
    one of its coefficients by more than :data:`RIVAL_CHANGE` of it."""
    on = chosen_coef != 0
    if np.any(candidate[on] == 0):
        return True
    change = np.abs(candidate[on] - chosen_coef[on]) > RIVAL_CHANGE * np.abs(chosen_coef[on])
    return bool(np.any(change))


def score_margin(
    scores, candidates, index, rivals: bool = False, reference=None, reference_score=None
) -> np.ndarray:
    """Per column, the score of the best candidate whose support differs from the
    chosen one (``index``) minus the chosen score; ``inf`` when none differs.  With
    ``rivals``, only the candidates that are another model count: they leave out a
    chosen term, or change a chosen coefficient by more than :data:`RIVAL_CHANGE` of
    it.  A candidate that only adds terms to the chosen ones, which keep their values,
    says whether terms may be missing (what the floor, bias and significance rules
    report), not whether the chosen ones are right: with m rows, the best of the
    spurious terms a right model leaves out gains about 2 log(p) in twice the
    log-likelihood against a penalty of log m, so such candidates score close on most
    right answers from noisy states.

    ``reference`` (p, n), the model finally reported where later stages changed the
    chosen one (a term dropped as insignificant or as bias), takes the chosen
    candidate's place in deciding which candidates differ from it and are another
    model; the margin is still measured from the chosen (best) score, or from
    ``reference_score`` (n,), the reported model's own score, where that is lower.  The
    candidate without the dropped term is then the reported model, not a rival of it.

    ``scores`` (L, n), ``candidates`` (L, p, n), ``index`` (n,).
    """
    L, _, n = candidates.shape
    out = np.full(n, np.inf)
    for k in range(n):
        chosen_coef = candidates[index[k], :, k] if reference is None else reference[:, k]
        chosen = chosen_coef != 0
        other = [
            i for i in range(L)
            if np.isfinite(scores[i, k])
            and not np.array_equal(candidates[i, :, k] != 0, chosen)
            and (not rivals or _rival(candidates[i, :, k], chosen_coef))
        ]  # fmt: skip
        if other:
            base = scores[index[k], k]
            if reference_score is not None and reference_score[k] < base:
                base = reference_score[k]
            out[k] = np.min(scores[other, k]) - base
    return out


def _pick(scores: np.ndarray) -> np.ndarray:
    """Per column the lowest score; ties go to the sparsest (earliest) point."""
    best = np.nanmin(scores, axis=0)
    tie = scores <= best + 1e-9 * np.maximum(np.abs(best), 1.0)
    return np.argmax(tie, axis=0)


def _cv_scores(theta, y, lams, delta_k, tol, n_folds, method, solver, progress, path_options):
    """Blocked cross-validation of the path on the grid ``lams``: the selection stage on
    the training blocks, the mean Huber loss on the held-out block."""
    folds = blocked_folds(theta.shape[0], n_folds)
    scores = np.zeros(lams.shape)
    for train, test in tqdm(folds, desc="blocked CV", disable=not progress, leave=False):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            sub = path(
                theta[train],
                y[train],
                delta_k,
                lams,
                method=method,
                solver=solver,
                **path_options,
            )
            stage = _Stage(theta[train], y[train], delta_k, tol, method, solver, path_options)
            cand = _stage_all(stage, sub.coef)
        r = y[test][None, :, :] - np.einsum("mp,lpn->lmn", theta[test], cand)
        scores += huber(r, delta_k).mean(axis=1) / len(folds)
    return scores


def _confirm_points(stage: _Stage, full: Path, index, cols, chosen, tau, options) -> np.ndarray:
    """Per column of ``cols`` whose chosen path point the path's budget left
    uncertified: whether the choice stands on the exact point.  The point is solved
    again from there with the solver's full budget (``options``); where that is
    certified, its selection stage proposes a support, scored as the best-subset
    candidates are (:func:`information_criterion` with the column's ``tau``): the choice
    stands where that proposal is the support ``chosen`` (p, n) or scores no better.
    Near-exact data (states without noise) leave nearly least-absolute-deviation
    points, which the path's budget may not finish; the candidates are scored on their
    own certified refits whatever point proposed them."""
    lam = full.lams[index[cols], cols]
    if stage.method == "admm":
        options = {**options, "warm_start": full.coef[index[cols], :, cols].T}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit(
            stage.theta, stage.y[:, cols], stage.method, stage.delta[cols], lam,
            solver=stage.solver, **options,
        )  # fmt: skip
    coef = np.asarray(res.coef, dtype=float).reshape(stage.theta.shape[1], cols.size)
    out = np.zeros(cols.size, dtype=bool)
    for i, k in enumerate(cols):
        if not res.column_converged[i]:
            continue
        proposed = stage.column(k, coef[:, i])
        if np.array_equal(proposed != 0, chosen[:, k] != 0):
            out[i] = True
            continue
        theta, y, delta = stage.theta, stage.y[:, k], stage.delta[k]
        score = information_criterion(theta, y, proposed, delta, tau=tau[k])
        own = information_criterion(theta, y, chosen[:, k], delta, tau=tau[k])
        out[i] = score >= own
    return out


def select(
    theta,
    xdot,
    delta="auto",
    *,
    criterion: str = "bic",
    n_lams: int = 50,
    eps: float = 1e-4,
    tol: float = 0.005,
    n_folds: int = 5,
    segments=None,
    method: str = "admm",
    solver: str | None = None,
    progress: bool = False,
    subsets: bool = True,
    dense_start=None,
    **options,
) -> Selection:
    """Choose ``lam`` per equation: path, selection stage, then a robust criterion.

    1. :func:`path` over ``n_lams`` values from ``lambda_max`` to ``eps lambda_max``;
    2. at every point the selection stage (:func:`threshold_refit` with ``tol``): terms
       below ``tol`` relative contribution are dropped and the rest refitted by Huber
       with ``lam = 0``;
    3. ``criterion="bic"``: :func:`information_criterion` of each refit;
       ``criterion="cv"``: the same path and stage on the training blocks of
       :func:`blocked_folds`, scored by the mean Huber loss on the held-out block
       (squared error on held-out data would be dominated by the outliers).

    With ``criterion="bic"`` a column's path stops once the stage has proposed the
    support of its limit (the stage of the unpenalised fit on every term) at
    :data:`STABLE_POINTS` consecutive points denser than that support, or, at
    :data:`OUT_OF_REACH_POINTS` consecutive points, supports too large to score within
    :data:`MIN_BIC_MARGIN` of the best candidate walked (their loss is at least the
    least of any support's) and at least :data:`OUT_OF_REACH_GROWTH` times its size
    (``_Walk``): the points left are the densest and the most expensive, and as
    ``lam`` falls the proposal tends to that limit (``nan`` scores past the stop; where
    the path is solved point by point, those points are not solved at all:
    ``path.walked``).  The limit is also the most complete model: its residuals give
    the BIC its first correlation time, which the residuals of the candidate chosen
    then raise until the choice settles (``Selection.tau``): with few samples per term
    the most complete model's residuals have lost the slow part of the errors.

    4. ``criterion="bic"`` (and ``subsets``): the best few supports of every size up
       to a budget, by weighted least squares under the Huber weights of the limit
       candidate (:func:`robust_sindy.selection.subsets.best_subsets`), go through the
       same stage and criterion: a lasso path may never propose the true support of
       strongly collinear terms, and a margin among its own candidates does not show
       it.

    The lowest score wins; ties go to the larger ``lam``, then to the path.

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    delta : float, array_like (n,), or "auto"
    criterion : {"bic", "cv"}
    n_lams, eps : int, float
        The grid of :func:`path`.
    tol : float
        Relative contribution below which the selection stage drops a term.
    n_folds : int
        Blocks for ``criterion="cv"``.
    segments : list of slice, optional
        The samples of each trajectory in time order: the BIC then counts the effective
        number of samples (:func:`correlation_time` of the residuals).
    method : {"admm", "cvxpy"}
    solver : str, optional
        For ``method="cvxpy"``.
    progress : bool
        Show progress bars.
    subsets : bool
        With ``criterion="bic"``, add the best-subset candidates of every size up to
        the one :data:`robust_sindy.selection.subsets.SUBSET_BUDGET` allows
        (``Selection.subsets``).
    dense_start : array_like (p, n), optional
        Coefficients near the unpenalised fit on every term at ``delta`` (a pilot's,
        e.g. from :func:`~robust_sindy.fitting.auto_delta` with ``return_coef``): the
        fast path's start for that refit (the limit of the path's proposals).
    **options
        Solver options (see :func:`robust_sindy.fit`).

    Returns
    -------
    Selection

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> theta = rng.normal(size=(500, 8))
    >>> xdot = theta @ np.array([2.0, 0, 0, -1.0, 0, 0, 0.5, 0]) + 0.05 * rng.normal(size=500)
    >>> xdot[::7] += 30.0 * rng.normal(size=xdot[::7].size)       # gross outliers
    >>> sel = select(theta, xdot)
    >>> np.flatnonzero(sel.support[:, 0]).tolist()
    [0, 3, 6]
    >>> np.round(sel.coef[[0, 3, 6], 0], 2).tolist()
    [2.0, -1.0, 0.5]
    """
    theta, y, _ = check_problem(theta, xdot)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}; got {criterion!r}")
    check_huber_method(method, "the selection")
    if not np.isfinite(tol) or tol < 0:
        raise ValueError(f"tol must be a finite number >= 0; got {tol!r}")
    if isinstance(delta, str) and delta == "auto":
        delta = np.atleast_1d(auto_delta(theta, y, method=method))
    delta_k = loss_delta("huber", delta, y.shape[1])
    # Path points only propose supports, so ADMM gets fewer iterations there than in a
    # single fit (its Newton finish certifies most points at once; near-LAD points on
    # exact data may need thousands); the refits keep the full budget.
    path_options = {**pilot_budget(method), **options}
    # The stage's refits score candidate supports: most are wrong, their residuals far
    # beyond delta, and such near-LAD fits are the slowest to certify; they get the
    # path's budget (the refit of the support finally chosen is certified by the caller:
    # HuberSINDy refits it with the full budget).
    if dense_start is not None:
        dense_start = np.asarray(dense_start, dtype=float).reshape(theta.shape[1], y.shape[1])
    stage = _Stage(theta, y, delta_k, tol, method, solver, path_options, dense_start)
    with warnings.catch_warnings():
        # Uncertified path points only propose supports; the refits of the selection
        # stage (the limit's among them) score candidates, and the chosen point is
        # checked below.
        warnings.simplefilter("ignore", ConvergenceWarning)
        walk = _Walk(stage, n_lams, segments) if criterion == "bic" else None
        full = path(
            theta,
            y,
            delta_k,
            n_lams=n_lams,
            eps=eps,
            method=method,
            solver=solver,
            progress=progress,
            until=None if walk is None else walk.until,
            **path_options,
        )
        if walk is None:
            candidates = _stage_all(stage, full.coef)
    if criterion == "bic":
        candidates = walk.candidates
        # Correlation time of the residuals of the most complete model (the selection
        # stage of the unpenalised fit, the proposals' limit), then of the candidate
        # chosen, until the choice settles.
        densest = walk.limit
        tau, scores = _settled_scores(
            theta, y, candidates, walk.used, delta_k, walk.tau, segments, walk.losses
        )
    else:
        scores = _cv_scores(theta, y, full.lams, delta_k, tol, n_folds, method, solver, progress,
                            path_options)  # fmt: skip
    index = _pick(scores)
    cols = np.arange(y.shape[1])
    subset_coef = np.zeros((0, *candidates.shape[1:]))
    subset_scores = np.zeros((0, y.shape[1]))
    subset_size = np.zeros(y.shape[1], dtype=int)
    if subsets and criterion == "bic":
        # Supports the path's order of entry cannot reach (strongly collinear terms).
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            subset_coef, subset_scores, subset_size = _subset_candidates(
                stage, densest, tau, np.nanmin(scores, axis=0)
            )
    pooled = np.concatenate([candidates, subset_coef])
    pooled_scores = np.concatenate([scores, subset_scores])
    chosen = _pick(pooled_scores)
    from_subsets = chosen >= len(candidates)
    coef = pooled[chosen, :, cols].T
    bad = np.flatnonzero(~full.converged[index, cols] & ~from_subsets)
    if bad.size and criterion == "bic":
        bad = bad[~_confirm_points(stage, full, index, bad, coef, tau, options)]
    if bad.size:
        warnings.warn(
            f"the path point chosen for columns {bad.tolist()} was not certified (relative "
            f"KKT {', '.join(f'{v:.1e}' for v in full.kkt[index[bad], bad])}); its support "
            "may differ from the exact one. Try method='cvxpy' or a larger delta.",
            ConvergenceWarning,
            stacklevel=2,
        )
    return Selection(
        coef=coef,
        lam=full.lams[index, cols],
        delta=delta_k,
        index=index,
        scores=scores,
        candidates=candidates,
        support=coef != 0,
        path=full,
        criterion=criterion,
        margin=score_margin(pooled_scores, pooled, chosen),
        rival_margin=score_margin(pooled_scores, pooled, chosen, rivals=True),
        subsets=subset_coef,
        subset_scores=subset_scores,
        subset_size=subset_size,
        from_subsets=from_subsets,
        tau=tau if criterion == "bic" else np.ones(y.shape[1]),
    )
