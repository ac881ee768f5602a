"""The final selection and the pruning: terms the data do not vouch for are dropped.

Two stages of :class:`~robust_sindy.HuberSINDy` with ``lam="auto"``, on the certified
refit of the selected support:

* :func:`final_selection` -- drops, refitting after each drop until none drops
  anything: the terms below ``selection_tol``; those below the noise floor whose robust
  t is below the bar, the weakest of each equation first; those within ``BIAS_MARGIN``
  times the bias that the noise of the states gives them through the other terms
  (errors in the variables, :mod:`~robust_sindy.selection.bias`); and, with estimated
  derivatives, those within ``BIAS_MARGIN`` times the bias that the derivatives'
  truncation error gives them.
* :func:`prune` -- drops the selected term with the smallest robust t while it is below
  the bar, per equation, in equations with a term that clears
  ``SIGNIFICANCE_ESTIMATED``.
* Then the terms the selection left out are tested (:func:`missed_terms`): the one
  with the largest robust score t in an equation, at ``ADD_SIGNIFICANCE`` or more, is
  put in and both stages run again; it stays when they keep it (and, in the weak form,
  where it displaced selected terms, when the score under the noise the terms carry
  does not refuse the exchange).

Read more in the user guide: :doc:`/guide/final`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bias import (
    carried_noise,
    drop_biased_terms,
    first_order_bias,
    noise_gram,
    residual_noise_factor,
    truncation_bias,
)
from .lam_path import pilot_budget
from .problem import Problem
from .refit import STAGE_ROUNDS, debias
from .significance import SIGNIFICANCE, SIGNIFICANCE_ESTIMATED, robust_t, score_t

__all__ = [
    "ADD_SIGNIFICANCE",
    "FinalSelection",
    "final_selection",
    "missed_terms",
    "prune",
    "significance_bar",
]

#: Robust score t (:func:`~robust_sindy.selection.significance.score_t`) at which a term
#: the selection left out is tried in the model: five standard errors, as a term under
#: the noise floor must show with measured derivatives.  An L1 path can leave out a
#: true term for a few correlated ones that stand in for it (its products with the
#: squares of an oscillating state), and no drop brings it back; the tried term stays
#: only if the final selection's own tests keep it.
ADD_SIGNIFICANCE = SIGNIFICANCE


def significance_bar(measured: bool) -> float:
    """The robust t a selected term must reach: ``SIGNIFICANCE`` with measured
    derivatives, ``SIGNIFICANCE_ESTIMATED`` with estimated ones (whose systematic error
    the statistic leaves out)."""
    return SIGNIFICANCE if measured else SIGNIFICANCE_ESTIMATED


@dataclass(frozen=True)
class FinalSelection:
    """Outcome of :func:`final_selection` and :func:`prune` (arrays (p, n)).

    Attributes
    ----------
    coef : ndarray
        The coefficients kept (user units).
    bias_ratio : ndarray
        Coefficient over its errors-in-variables bias of each term dropped for it.
    truncation_ratio : ndarray
        Coefficient over its truncation bias of each term dropped for it.
    pruned : ndarray
        Robust t of each term pruned.
    added : ndarray
        Robust score t of each term the selection had left out and the final selection
        put in (:func:`missed_terms`).

    All NaN where nothing was dropped (added) for that reason.
    """

    coef: np.ndarray
    bias_ratio: np.ndarray
    truncation_ratio: np.ndarray
    pruned: np.ndarray
    added: np.ndarray


class _Refit:
    """The debiasing refit of the kept samples (user units) at the chosen ``delta``."""

    def __init__(self, kept: Problem, delta, method, solver, options):
        self.args = (kept.theta, kept.y)
        self.delta, self.method, self.solver, self.options = delta, method, solver, options

    def __call__(self, coef, cols=None):
        """The refit of every equation, or of the equations ``cols`` (the others kept)."""
        if cols is None:
            return debias(*self.args, coef, self.delta, self.method, self.solver, self.options)
        theta, y = self.args
        delta = np.broadcast_to(np.asarray(self.delta, dtype=float), (y.shape[1],))
        out = coef.copy()
        out[:, cols] = debias(
            theta, y[:, cols], coef[:, cols], delta[cols], self.method, self.solver,
            self.options,
        )  # fmt: skip
        return out


def final_selection(
    kept: Problem,
    design: np.ndarray,
    coef: np.ndarray,
    delta,
    *,
    selection_tol: float,
    floor_tol: float,
    measured: bool,
    reference: np.ndarray | None,
    method: str,
    solver: str | None,
    options: dict,
    refuse=None,
) -> FinalSelection:
    """Both stages on the kept samples (see the module docstring).

    ``design`` is the selection's standardised library, ``coef`` the selected model in
    user units, ``delta`` the chosen thresholds (user units), ``floor_tol`` the
    threshold raised to the noise floor, ``reference`` the derivatives of higher order
    of the kept samples (estimated derivatives; None otherwise), ``method`` the Huber
    method of the drops, ``refuse`` (optional) the test of :func:`missed_terms` for a
    put-back term that displaces selected ones.
    """
    coef = np.array(coef, dtype=float)  # the drops write into it; the caller's stays
    delta_s = kept.delta_standard(delta)
    refit = _Refit(kept, delta, method, solver, options)
    error = None if reference is None else kept.scaler.y(kept.y - reference)
    bar = significance_bar(measured)
    selected = coef != 0

    def stages(coef):
        coef, ratio, truncation = _drops(
            kept, design, coef, delta_s, refit, selection_tol, floor_tol, measured, error,
            bar, method,
        )  # fmt: skip
        coef, pruned = prune(kept, design, coef, delta_s, refit, bar)
        return FinalSelection(coef, ratio, truncation, pruned, np.full(coef.shape, np.nan))

    return missed_terms(
        kept, design, stages(coef), delta_s, stages, refit, ~selected, refuse=refuse
    )


def missed_terms(
    kept: Problem, th, final: FinalSelection, delta_s, stages, refit, candidates, refuse=None
) -> FinalSelection:
    """Put back terms the selection left out that the final selection's tests keep.

    Per round, in every equation, the ``candidates`` term (bool, p x n: those the
    selection left out; a term it selected and a stage dropped is not tried again) with
    the largest robust score t (:func:`~.significance.score_t` at ``final.coef``) is put
    in where that t reaches ``ADD_SIGNIFICANCE``, those equations are refitted
    (``refit(coef, cols)``) and ``stages`` (the drops and the pruning, from
    coefficients to a :class:`FinalSelection`) run again.  An equation
    keeps the outcome where the term survived it; each term is tried once, for at most
    ``STAGE_ROUNDS`` rounds.  Where the outcome also left out terms of the model it
    started from, ``refuse`` (optional: ``refuse(current, outcome, cols)``, standardised
    coefficients, a bool per equation of ``cols``; in the weak form
    :func:`~.variables.displacement_refused`) may still refuse it.  Returns the final
    selection with the terms kept in ``added`` (their score t) and the other arrays
    merged.
    """
    scaler, yk, segments = kept.scaler, kept.y_s, kept.segments
    open_ = np.array(candidates, dtype=bool)
    every = np.arange(final.coef.shape[1])
    for _ in range(STAGE_ROUNDS):
        coef = final.coef
        t = score_t(th, yk, scaler.coef_to_standard(coef), delta_s, segments)
        t = np.where(open_, t, np.nan)  # NaN on the support already
        best = np.argmax(np.nan_to_num(t, nan=-np.inf), axis=0)
        cols = np.flatnonzero(t[best, every] >= ADD_SIGNIFICANCE)
        if cols.size == 0:
            break
        open_[best[cols], cols] = False
        trial = coef.copy()
        trial[best[cols], cols] = 1.0  # a placeholder: the refit fits the support
        tried = stages(refit(trial, cols))
        kept_cols = cols[tried.coef[best[cols], cols] != 0]
        if refuse is not None and kept_cols.size:
            displaced = np.any((coef[:, kept_cols] != 0) & (tried.coef[:, kept_cols] == 0), 0)
            at = kept_cols[displaced]
            if at.size:
                no = refuse(scaler.coef_to_standard(coef), scaler.coef_to_standard(tried.coef), at)
                kept_cols = kept_cols[~np.isin(kept_cols, at[no])]
        if kept_cols.size == 0:
            continue
        merged = {}
        for name in ("bias_ratio", "truncation_ratio", "pruned", "added"):
            old, new = getattr(final, name)[:, kept_cols], getattr(tried, name)[:, kept_cols]
            merged[name] = getattr(final, name).copy()
            merged[name][:, kept_cols] = np.where(np.isnan(new), old, new)
        merged["added"][best[kept_cols], kept_cols] = t[best[kept_cols], kept_cols]
        coef = coef.copy()
        coef[:, kept_cols] = tried.coef[:, kept_cols]
        final = FinalSelection(coef, **merged)
    return final


def _drops(kept, th, coef, delta_s, refit, tol, floor_tol, measured, error, bar, method):
    """Drop the terms below ``tol``, and those below ``floor_tol`` whose robust t is below
    ``bar`` (``_floor_drops``), and those within ``BIAS_MARGIN`` of their
    errors-in-variables bias (with the screen's noise; the signed first-order bias for
    measured derivatives, its triangle bound for estimated ones), refitting after
    each, and, with estimated derivatives
    whose truncation ``error`` (standardised) was measured, those within ``BIAS_MARGIN``
    of the bias that error gives them, until none drops anything.  Returns the
    coefficients and the bias ratios of the terms the last two dropped (NaN elsewhere)."""
    scaler, yk, noise, segments = kept.scaler, kept.y_s, kept.noise, kept.segments
    gram = None if noise is None else noise_gram(noise)
    ratio = np.full(coef.shape, np.nan)
    truncation = np.full(coef.shape, np.nan)
    # Terms that the errors in the variables, or the truncation error of the
    # derivatives, could have selected are not identified: each drop records its
    # ratios in its own array.
    drops = []
    if gram is not None:

        def eiv(c, k):
            # The measured noise, brought down to what the residuals allow.
            factor = residual_noise_factor(yk[:, k] - th @ c, carried_noise(noise, c))
            return first_order_bias(th, c, factor * gram, signed=measured)

        drops.append((ratio, dict(gram=None, bias=eiv)))
    if error is not None:

        def bias(c, k):
            return truncation_bias(th, error[:, k], c, segments)

        drops.append((truncation, dict(gram=None, bias=bias)))
    for _ in range(STAGE_ROUNDS):
        coef, changed = _floor_drops(kept, th, coef, delta_s, refit, tol, floor_tol, bar)
        if not drops:
            break
        for record, how in drops:
            _, new = drop_biased_terms(
                th, yk, scaler.coef_to_standard(coef), delta_s, **how, method=method,
                **pilot_budget(method),
            )  # fmt: skip
            dropped = np.isfinite(new)
            if dropped.any():
                record[dropped] = new[dropped]
                coef[dropped] = 0.0
                coef = refit(coef)
                changed = True
        if not changed:
            break
    return coef, ratio, truncation


def _floor_drops(kept: Problem, th, coef, delta_s, refit, tol, floor_tol, bar):
    """Under the noise floor ``floor_tol`` a term stays only when the data vouch for it:
    the terms below ``tol`` are dropped, and of those under the floor whose robust t is
    below ``bar``, the weakest of each equation, refitting after each round until none
    is left.  One at a time, because terms that share a direction share its evidence:
    a true term among small ones that stand in for it (its own powers, its products
    with slowly varying states) has a low t only while they are in the model.  Returns
    the coefficients and whether anything was dropped."""
    scaler, yk, segments = kept.scaler, kept.y_s, kept.segments
    col = np.linalg.norm(th, axis=0)[:, None]
    ynorm = np.maximum(np.linalg.norm(yk, axis=0), np.finfo(float).tiny)
    delta_s = np.broadcast_to(np.asarray(delta_s, dtype=float), (yk.shape[1],))
    tstat = np.full(coef.shape, np.nan)
    stale = np.ones(coef.shape[1], dtype=bool)
    changed = False
    while True:
        standard = scaler.coef_to_standard(coef)
        contrib = np.abs(standard) * col / ynorm
        small = (coef != 0) & (contrib < floor_tol)
        tiny = small & (contrib < tol)
        need = stale & small.any(axis=0)
        if need.any():
            tstat[:, need] = robust_t(th, yk[:, need], standard[:, need], delta_s[need], segments)
        stale[:] = False
        weak = small & ~tiny & ~(tstat >= bar)
        # NaN (no statistic) counts as the weakest.
        score = np.where(weak, np.nan_to_num(tstat, nan=-np.inf), np.inf)
        cols = np.flatnonzero(weak.any(axis=0))
        drop = tiny.copy()
        drop[np.argmin(score[:, cols], axis=0), cols] = True
        if not drop.any():
            return coef, changed
        coef[drop] = 0.0
        stale = drop.any(axis=0)
        coef = refit(coef, np.flatnonzero(stale))
        changed = True


def prune(kept: Problem, th, coef, delta_s, refit, bar):
    """Drop the selected term with the smallest robust t while it is below ``bar``,
    per equation, refitting after each round.

    The selection's criterion reads the likelihood as if the residuals were the model's
    only error; the sandwich statistic also sees the errors it leaves out (noise in the
    library columns reaching the fit through high-leverage rows, heavy tails, and with
    estimated derivatives their smooth errors shared with the library), and terms the
    criterion admits that the data do not vouch for are fitted to those errors.  Only
    equations with a term at ``SIGNIFICANCE_ESTIMATED`` or more are pruned, and only
    while they keep one: an equation none of whose terms is that clear is left as
    selected (the data vouch for no version of it, and a warning says so), and a drop
    after which no term is that clear any more is undone (the dropped term was carrying
    the equation).  Returns the coefficients and the t of each dropped term (NaN
    elsewhere).
    """
    scaler, yk, segments = kept.scaler, kept.y_s, kept.segments
    pruned = np.full(coef.shape, np.nan)
    cols_all = np.arange(coef.shape[1])

    def t_of(coef):
        t = robust_t(th, yk, scaler.coef_to_standard(coef), delta_s, segments)
        return np.where(coef != 0, np.nan_to_num(t, nan=np.inf), np.inf)

    def vouched(t, coef):
        return np.where(coef != 0, t, 0.0).max(axis=0) >= SIGNIFICANCE_ESTIMATED

    tstat = t_of(coef)
    done = np.zeros(coef.shape[1], dtype=bool)
    for _ in range(coef.shape[0]):
        weakest = np.argmin(tstat, axis=0)
        low = tstat[weakest, cols_all] < bar
        cols = np.flatnonzero(low & vouched(tstat, coef) & ~done)
        if cols.size == 0:
            break
        before, t_before = coef.copy(), tstat
        pruned[weakest[cols], cols] = tstat[weakest[cols], cols]
        coef[weakest[cols], cols] = 0.0
        coef = refit(coef)
        tstat = t_of(coef)
        lost = cols[~vouched(tstat, coef)[cols]]
        coef[:, lost], tstat[:, lost] = before[:, lost], t_before[:, lost]
        pruned[weakest[lost], lost] = np.nan
        done[lost] = True
    return coef, pruned
