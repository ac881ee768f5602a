"""The noise floor, the choice of delta and lambda, and the penalised fit at the choice.

Three stages of :class:`~robust_sindy.HuberSINDy`, each on the samples the screens kept:

* :func:`noise_floor` -- terms that are exact combinations of earlier ones on these
  samples (:func:`~robust_sindy.selection.aliasing.aliased_columns`) are left out of the
  selection, and the selection threshold is raised to the relative noise of the
  noisiest library column (a term that contributes less than the noise of the columns
  it is built from cannot be told from errors in the variables);
* :func:`choose_delta_lam` -- ``delta`` by the robust-scale rule
  (:func:`~robust_sindy.fitting.auto_delta`) and ``lam`` per equation by the robust
  BIC (or blocked cross-validation) over a path with the selection stage at every point
  (:func:`~robust_sindy.selection.criteria.select`), on standardised columns, mapped
  back to the user's units; or the values given;
* :func:`fit_chosen` -- the penalised fit at the choice in the user's units, certified,
  then the optional threshold and the debiasing refit of the kept terms.

Read more in the user guide: :doc:`/guide/choice`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.validation import per_column
from ..fitting import FitResult, auto_delta, fit
from .aliasing import aliased_columns
from .bias import library_noise
from .criteria import Selection, select
from .lam_path import pilot_budget
from .problem import Problem
from .refit import debias

__all__ = [
    "Choice",
    "Fitted",
    "NoiseFloor",
    "choose_delta_lam",
    "fit_chosen",
    "huber_method",
    "noise_floor",
]


def huber_method(method: str) -> str:
    """The Huber method of the automatic choices: ``method``, or the fast path for a
    least-squares ``method``."""
    return method if method in ("admm", "cvxpy") else "admm"


@dataclass(frozen=True)
class NoiseFloor:
    """Outcome of :func:`noise_floor`.

    Attributes
    ----------
    aliased : ndarray of bool (p,)
        Terms left out of the selection as exact combinations of earlier ones.
    design : ndarray (m, p)
        The kept samples' standardised library with those columns zeroed: what the
        selection sees.
    library_noise : tuple (ndarray (p,), float)
        The states' noise carried through the library, per column and along its
        least-excited direction (:func:`~robust_sindy.selection.bias.library_noise`).
    selection_tol : float
        The selection threshold used: the one given, or the noise of the noisiest
        column when that is larger.
    """

    aliased: np.ndarray
    design: np.ndarray
    library_noise: tuple
    selection_tol: float


def noise_floor(kept: Problem, *, find_aliases: bool, selection_tol: float) -> NoiseFloor:
    """Aliased terms (with ``find_aliases``), the selection's design and its threshold."""
    design = kept.theta_s
    aliased = np.zeros(design.shape[1], dtype=bool)
    if find_aliases:
        aliased = aliased_columns(design)
        if aliased.any():
            design = design.copy()
            design[:, aliased] = 0.0
    noise = library_noise(kept.noise, design)
    column_noise = noise[0][~aliased]
    tol = float(
        max(selection_tol, np.max(column_noise, initial=0.0))
        if np.all(np.isfinite(column_noise))
        else selection_tol
    )
    return NoiseFloor(aliased, design, noise, tol)


@dataclass(frozen=True)
class Choice:
    """Outcome of :func:`choose_delta_lam` (user units).

    Attributes
    ----------
    delta : ndarray (n,) or the value given
    lam : ndarray (p, n), or the value given
    start : ndarray (p, n) or None
        The chosen path point's coefficients (the penalised fit's warm start).
    coef : ndarray (p, n) or None
        The selected model (None with a fixed ``lam``).
    selection : Selection or None
        Scores and candidates of the automatic choice.
    """

    delta: object
    lam: object
    start: np.ndarray | None
    coef: np.ndarray | None
    selection: Selection | None


def choose_delta_lam(
    kept: Problem,
    design: np.ndarray,
    delta,
    lam,
    *,
    criterion: str,
    n_lams: int,
    selection_tol: float,
    method: str,
    solver: str | None,
    progress: bool,
    options: dict,
    start=None,
) -> Choice:
    """``delta`` and ``lam``: chosen on the standardised ``design`` (``"auto"``) or the
    values given.  With ``lam="auto"``, terms under the noise floor are proposed
    (``selection_tol`` is the threshold given, not the floor): the final selection keeps
    those the data vouch for.  ``start``, the standardised ``(delta, coef)`` of a pilot
    on nearly the same samples (the row screen's last,
    :attr:`~robust_sindy.selection.Screening.pilot`), starts
    the choice of ``delta`` (:func:`~robust_sindy.fitting.auto_delta`)."""
    scaler = kept.scaler
    y_s = kept.y_s
    pilot = huber_method(method)
    auto = isinstance(delta, str) and delta == "auto"
    if start is not None:  # no weight on the columns the design leaves out (aliases)
        start = (start[0], np.where(design.any(axis=0)[:, None], start[1], 0.0))
    if not (isinstance(lam, str) and lam == "auto"):
        delta_u = (
            np.atleast_1d(auto_delta(design, y_s, method=pilot, start=start, **pilot_budget(pilot)))
            * scaler.y_scale
            if auto
            else delta
        )
        return Choice(delta_u, lam, None, None, None)
    dense = None  # a pilot on every term at nearly delta: the start of that refit
    if auto:
        delta_s, dense = auto_delta(
            design, y_s, method=pilot, start=start, return_coef=True, **pilot_budget(pilot)
        )
    else:
        delta_s = per_column(delta, "delta", y_s.shape[1], positive=True) / scaler.y_scale
    sel = select(
        design,
        y_s,
        delta_s,
        criterion=criterion,
        n_lams=n_lams,
        tol=selection_tol,
        segments=kept.segments,
        method=method,
        solver=solver,
        progress=progress,
        dense_start=dense,
        **options,
    )
    cols = np.arange(y_s.shape[1])
    return Choice(
        scaler.delta_to_user(sel.delta),
        scaler.lam_to_user(sel.lam),
        scaler.coef_to_user(sel.path.coef[sel.index, :, cols].T),
        scaler.coef_to_user(sel.coef),
        sel,
    )


@dataclass(frozen=True)
class Fitted:
    """Outcome of :func:`fit_chosen`.

    Attributes
    ----------
    result : FitResult
        The penalised fit at the choice (before threshold and refit).
    coef : ndarray (p, n)
        The coefficients after the threshold and the refit (user units).
    """

    result: FitResult
    coef: np.ndarray


def fit_chosen(
    kept: Problem,
    choice: Choice,
    *,
    method: str,
    solver: str | None,
    options: dict,
    threshold: float | None,
    refit: bool,
) -> Fitted:
    """The penalised fit at the choice, in user units (the certificates of the chosen
    point), warm-started at the chosen path point; the selected model (``lam="auto"``)
    or the fit's coefficients, thresholded, then refitted on their support without
    penalty when ``refit`` or ``lam="auto"`` (the selection scored its refits with a
    bounded budget; the chosen support is refitted here with the full one)."""
    p = kept.theta.shape[1]
    fit_options = dict(options)
    if choice.start is not None and method == "admm":
        fit_options["warm_start"] = choice.start
    res = fit(kept.theta, kept.y, method, choice.delta, choice.lam, solver=solver, **fit_options)
    coef = (choice.coef if choice.coef is not None else res.coef.reshape(p, -1)).copy()
    if threshold is not None:
        if not np.isfinite(threshold) or threshold < 0:
            raise ValueError(f"threshold must be a finite number >= 0; got {threshold}")
        coef[np.abs(coef) < threshold] = 0.0
    if refit or choice.selection is not None:
        coef = debias(kept.theta, kept.y, coef, res.delta, method, solver, options)
    return Fitted(res, coef)
