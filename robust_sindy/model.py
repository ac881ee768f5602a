"""HuberSINDy: the estimator users fit to time series.

From states (and optional controls) sampled in time it builds the library, obtains the
derivatives (given, or by numerical differentiation), fits the coefficients with the
Huber loss and an L1 penalty (:func:`robust_sindy.fit`), optionally thresholds them and
refits the kept terms without penalty, and then prints, predicts and simulates the
identified equations.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from numbers import Integral, Real

import numpy as np
import scipy.integrate
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import NotFittedError

from ._blas import one_thread
from ._fit import METHODS, fit
from ._scaling import Standardizer
from ._validation import as_float_array, per_column
from .differentiation import (
    choose_half_window,
    finite_difference,
    higher_order_derivative,
    local_polynomial_derivative,
    savgol_derivative,
    unresolved_derivatives,
)
from .library import BaseLibrary, PolynomialLibrary
from .selection import CRITERIA, auto_delta, screen_rows, select, threshold_refit
from .selection.aliasing import ALIAS_RTOL, aliased_columns
from .selection.bias import (
    BIAS_MARGIN,
    carried_noise,
    drop_biased_terms,
    first_order_bias,
    noise_gram,
    residual_noise_factor,
    state_noise_factors,
    truncation_bias,
)
from .selection.criteria import MIN_BIC_MARGIN
from .selection.path import pilot_budget
from .selection.refit import STAGE_ROUNDS, one_step_contributions
from .selection.screening import temporal_screen
from .selection.significance import SIGNIFICANCE, SIGNIFICANCE_ESTIMATED, VISIBLE, robust_t
from .simulate import check_time, input_function
from .solvers.chunked import is_dask

__all__ = ["Diagnostics", "HuberSINDy", "IdentificationWarning"]

#: More flagged samples than this fraction and the screen's verdict is doubtful (and
#: more samples with unresolved derivatives than this, the sampling is too coarse).
MAX_FLAGGED_FRACTION = 0.3
#: More samples left out in all (outliers and unresolved derivatives) than this
#: fraction, and what is left may not represent the trajectory.
MAX_LEFT_OUT = 0.5
#: Fewer kept samples per library term than this and the selection is doubtful.
MIN_SAMPLES_PER_TERM = 5.0
#: Condition number of the selected terms (unit-norm columns) beyond which their
#: coefficients are not identifiable from the data.
MAX_CONDITION = 1e6
#: Fits with at most this many samples run BLAS on one thread (see ``HuberSINDy.fit``).
SMALL_PROBLEM_SAMPLES = 10_000
#: Stability check: the kept samples are cut into this many contiguous blocks in time
#: and the selected terms refitted with each block left out; a term is unstable when a
#: refit changes its sign or moves it by more than ``STABILITY_TOLERANCE`` of its value.
STABILITY_BLOCKS = 4
STABILITY_TOLERANCE = 0.5
#: Noise of the library (the states' noise carried through it) relative to its signal
#: along its least-excited direction beyond which the errors in the variables decide
#: which terms are selected.
MAX_LIBRARY_NOISE = 0.15


#: Half width (samples on each side) of the robust derivatives' local quartics with
#: ``derivative_window="fixed"``: the fourth-order central difference.
FIXED_HALF_WINDOW = 2
#: The choices of ``derivative_window``.
DERIVATIVE_WINDOWS = ("auto", "fixed")


class IdentificationWarning(UserWarning):
    """The data cannot vouch for the identified model (see ``HuberSINDy.diagnostics_``)."""


@dataclass(repr=False)
class Diagnostics:
    """What a fitted :class:`HuberSINDy` can and cannot vouch for.

    Attributes
    ----------
    n_samples, n_terms : int
        Samples (all trajectories) and library terms.
    samples_per_term : float
        Samples kept after screening per library term.
    temporal_flagged_entries, temporal_flagged_samples : int
        Entries (state, sample) the temporal screen flagged, and samples with any.
    model_flagged_samples : int
        Samples the model-based screen left out of the fit as outliers.
    unresolved_samples : int
        Samples left out of the fit because their estimated derivatives are not
        resolved by the sampling (``unresolved_``; 0 with measured derivatives).
    readmitted_samples : int
        Samples flagged in time whose residuals were fine in every equation (kept).
    screening_converged : bool
    screening_restarted : bool
        Whether the model screen kept another iteration (from every sample, or from a
        forward search) over the one from the samples the temporal screen left alone
        (that start had lost the samples that alone excite some library directions,
        e.g. a fast excursion).
    flagged_fraction : float
        Fraction of the samples left out (outliers and unresolved derivatives).  A
        warning says so when the outliers or the unresolved derivatives are more than
        ``MAX_FLAGGED_FRACTION`` of the samples, or both together more than
        ``MAX_LEFT_OUT``.
    delta_over_scale : ndarray (n,)
        ``delta_`` divided by the robust residual scale of the screen's pilot.
    certified : ndarray of bool (n,)
        Whether the penalised fit of each equation passed its optimality certificate.
    condition_number : ndarray (n,)
        Of each equation's selected terms (unit-norm columns, kept samples).
    library_noise : float
        The states' noise (measured by the temporal screen, no larger than the
        residuals allow: see ``noise_factor``) carried through the library, relative to
        the library's signal, along its least-excited direction (kept samples,
        standardised columns, first-order propagation); NaN without the screen.  Near
        or above ``MAX_LIBRARY_NOISE`` the noise in the library columns themselves
        (errors in the variables, which no loss on the derivatives can remove) is large
        enough to select spurious terms or bias the coefficients.
    noise_factor : ndarray (n,)
        Of the states' noise variance that the temporal screen measured, the share each
        equation's residuals allow, capped at 1
        (:func:`robust_sindy.selection.bias.residual_noise_factor`, with the final
        coefficients): the residuals carry the states' noise through the model whatever
        else they carry, so a factor below 1 means the screen measured the noise too
        large (its local polynomials cannot follow states sampled too coarsely, and
        their truncation error counts as noise).  The errors-in-variables check uses the
        noise this factor allows.  NaN without the screen.
    unstable : ndarray of bool (n, p)
        Selected terms whose coefficient changes sign, or by more than
        ``STABILITY_TOLERANCE`` of its value, when one of ``STABILITY_BLOCKS``
        contiguous blocks of the kept samples is left out of the refit: the data do not
        pin them down (a spurious term, or a true one the data barely excite).
    bias_ratio : ndarray (n, p)
        For terms the selection chose but then dropped because their coefficient was
        within ``BIAS_MARGIN`` times the bias that the noise of the states, through the
        other selected terms, could give it (errors in the variables, see
        :mod:`robust_sindy.selection.bias`): the coefficient over that first-order bias when
        dropped; NaN for every other term (all NaN without the temporal screen or with a
        fixed ``lam``).  A ratio of at least 1 is a term that the bias alone does not
        explain, dropped only for want of margin: it may be real, and a warning says so.
    truncation_ratio : ndarray (n, p)
        For terms dropped because their coefficient was within ``BIAS_MARGIN`` times the
        bias that the truncation error of the estimated derivatives gives it (the
        difference from derivatives of two orders higher, projected on the selected
        terms, less two of its standard errors; see
        :func:`robust_sindy.selection.bias.truncation_bias`): the coefficient over that
        bias when dropped; NaN for every other term (all NaN with measured derivatives,
        other than the robust differentiation, without the screen or with a fixed
        ``lam``).  On a coarsely sampled trajectory the truncation error is systematic,
        and a regression explains it with spurious terms.  A ratio of at least 1 may be
        a real term dropped for want of margin, and a warning says so.
    below_floor : ndarray (n, p)
        Unselected terms whose relative contribution, were they added, lies between
        ``selection_tol`` and the noise floor ``selection_tol_`` that the library noise
        raised it to: the floor, not the data, left them out, so they may be real (a
        warning says so); NaN for every other term.
    bic_margin : ndarray (n,)
        Per equation, how much higher the BIC of the best other candidate support
        scored than the chosen one (``Selection.margin``); ``inf`` when there is no
        other, NaN with a fixed ``lam`` or ``criterion="cv"``.  Below
        ``MIN_BIC_MARGIN`` the data do not strongly prefer the chosen support.
    subset_size : ndarray of int (n,)
        Besides the ``lam`` path's, the criterion compares the best supports of every
        size up to this one (best-subset candidates, ``Selection.subsets``; 0: not
        searched; smaller than the budget allows where the BIC penalty of larger
        supports alone rules them out).  A larger support was compared with the path's
        candidates only.
    from_subsets : ndarray of bool (n,)
        Equations whose support came from that search: no point of the ``lam`` path
        proposed it (strongly collinear terms), and ``lam_`` and ``result_`` are those
        of the best path point.
    significance : ndarray (n, p)
        Robust t statistic of every selected term (the coefficient over its sandwich
        standard error, :func:`robust_sindy.selection.significance.robust_t`); NaN off
        the support and with a fixed ``lam``.  With estimated derivatives it leaves out
        the differentiation error, which is systematic, so it overstates how sure the
        data are.  A selected term below ``significance_level`` is not vouched for by the
        data (a warning says so).
    significance_level : float
        The bar of ``significance``: ``SIGNIFICANCE`` (5) with measured derivatives,
        ``SIGNIFICANCE_ESTIMATED`` (10) with estimated ones, whose error the statistic
        leaves out.
    pruned : ndarray (n, p)
        The robust t of each term the selection chose but the data did not vouch for
        (below ``significance_level``), when it was dropped (the weakest first, the
        rest refitted after each, while another term of the equation reaches
        ``SIGNIFICANCE_ESTIMATED``; a drop after which none does is undone); NaN for
        every other term.  A dropped term at
        ``VISIBLE`` (2) or more may be real: a warning says so.
    derivative_half_window : ndarray of int (n_states,)
        Half width, in samples, of the local quartic that estimated each state's
        derivative (chosen from the data by
        :func:`~robust_sindy.differentiation.choose_half_window`; the widest over the
        trajectories); 0 where the derivatives were measured or came from another
        ``differentiation``.
    aliased : list of str
        Library terms left out of the selection because they are exact linear
        combinations of earlier terms on the kept samples (a state that does not move,
        an exactly conserved quantity:
        :func:`robust_sindy.selection.aliasing.aliased_columns`); an equation written
        with them fits equally well, so a warning names them.
    """

    n_samples: int
    n_terms: int
    samples_per_term: float
    temporal_flagged_entries: int
    temporal_flagged_samples: int
    model_flagged_samples: int
    readmitted_samples: int
    unresolved_samples: int
    screening_converged: bool
    screening_restarted: bool
    flagged_fraction: float
    delta_over_scale: np.ndarray
    certified: np.ndarray
    condition_number: np.ndarray
    library_noise: float
    noise_factor: np.ndarray
    unstable: np.ndarray
    bias_ratio: np.ndarray
    below_floor: np.ndarray
    bic_margin: np.ndarray
    truncation_ratio: np.ndarray
    subset_size: np.ndarray
    from_subsets: np.ndarray
    significance: np.ndarray
    significance_level: float
    pruned: np.ndarray
    aliased: list[str]
    derivative_half_window: np.ndarray

    @property
    def weak(self) -> np.ndarray:
        """Selected terms within ``significance_level`` robust standard errors of zero
        (n, p)."""
        return np.nan_to_num(self.significance, nan=np.inf) < self.significance_level

    def problems(self) -> list[str]:
        """One sentence for each reason to doubt the model (empty when there is none)."""
        out = []
        if self.samples_per_term < MIN_SAMPLES_PER_TERM:
            out.append(
                f"only {self.samples_per_term:.1f} samples per library term were fitted: the "
                "selected terms are not reliable; use more data or a smaller library"
            )
        if not self.screening_converged:
            out.append(
                "the model-based screen did not converge (its flags kept changing): the "
                "samples left out may be wrong; inspect screened_ and screening_"
            )
        unresolved = self.unresolved_samples / max(self.n_samples, 1)
        outliers = self.flagged_fraction - unresolved
        if outliers > MAX_FLAGGED_FRACTION:
            out.append(
                f"{100 * outliers:.0f} % of the samples were flagged as outliers: either "
                "the data are mostly corrupted or the library cannot describe them; check "
                "the library and the data (screened_)"
            )
        if unresolved > MAX_FLAGGED_FRACTION:
            out.append(
                f"at {100 * unresolved:.0f} % of the samples the estimated derivatives are "
                "not resolved: they differ from those of a higher-order local fit by more "
                "than the noise explains (a trajectory sampled too coarsely for its fastest "
                "excursions, or errors in the states the temporal screen left unflagged); "
                "they were left out (unresolved_); sample faster, measure x_dot, or check "
                "the states"
            )
        if max(outliers, unresolved) <= MAX_FLAGGED_FRACTION and (
            self.flagged_fraction > MAX_LEFT_OUT
        ):
            out.append(
                f"{100 * self.flagged_fraction:.0f} % of the samples were left out of the "
                f"fit ({100 * outliers:.0f} % flagged as outliers, {100 * unresolved:.0f} % "
                "with unresolved derivatives): what is left may not excite every term; "
                "check the data (screened_, unresolved_), and measure x_dot or sample "
                "faster"
            )
        if self.aliased:
            out.append(
                f"the library terms {', '.join(self.aliased)} are exact linear combinations "
                "of earlier terms on these data (a state that does not move, or an exactly "
                "conserved quantity): they were left out of the selection, and the data "
                "cannot tell an equation written with them from the one found; see "
                "diagnostics_.aliased, and vary that state if its terms matter"
            )
        if not self.certified.all():
            out.append(
                f"equations {np.flatnonzero(~self.certified).tolist()} were not certified "
                "optimal (see result_)"
            )
        bad = np.flatnonzero(self.condition_number > MAX_CONDITION)
        if bad.size:
            conds = ", ".join(f"{c:.1e}" for c in self.condition_number[bad])
            out.append(
                f"equations {bad.tolist()}: the selected terms are nearly collinear on this "
                f"data (condition numbers {conds}); "
                "their coefficients are not identifiable from it. Use a longer or more "
                "exciting trajectory"
            )
        if self.library_noise > MAX_LIBRARY_NOISE:
            out.append(
                f"the noise of the states, carried through the library, is "
                f"{100 * self.library_noise:.0f} % of the library's signal along its "
                "least-excited direction: terms that differ along it cannot be told apart "
                "(errors in the variables, which measured derivatives do not remove), so "
                "the support and coefficients may be wrong. Use less noisy states, a longer "
                "or more exciting trajectory, or a smaller library"
            )
        shaky, counts = _equations_with(self.unstable)
        if shaky.size:
            out.append(
                f"equations {shaky.tolist()}: {counts} selected terms change sign or by more "
                f"than {100 * STABILITY_TOLERANCE:.0f} % when a quarter of the data is left "
                "out: the support is not reliably identified from these data (noise too "
                "large for the library, or terms the trajectory barely excites); see "
                "diagnostics_.unstable, and try more data, measured derivatives or a "
                "smaller library"
            )
        for ratio, source, name, advice in (
            (
                self.bias_ratio,
                "the noise of the states gives them through the other terms (errors in "
                "the variables)",
                "bias_ratio",
                "less noisy states, a longer trajectory or a smaller library",
            ),
            (
                self.truncation_ratio,
                "the truncation error of the estimated derivatives gives them (measured "
                "against derivatives of higher order: the sampling does not fully resolve "
                "the trajectory)",
                "truncation_ratio",
                "faster sampling or measured derivatives",
            ),
        ):
            doubtful, counts = _equations_with(np.nan_to_num(ratio) >= 1.0)
            if doubtful.size:
                out.append(
                    f"equations {doubtful.tolist()}: {counts} terms were dropped because they "
                    f"lie within {BIAS_MARGIN:g} times the bias that {source}, yet exceed "
                    "that bias: they may be real, and these data cannot decide (see "
                    f"diagnostics_.{name}); {advice} would"
                )
        floor, counts = _equations_with(np.isfinite(self.below_floor))
        if floor.size:
            out.append(
                f"equations {floor.tolist()}: {counts} terms left out would contribute more "
                "than selection_tol but less than the noise of the library columns "
                "(selection_tol_): the noise, not the data, decided them, and they may be "
                "real (see diagnostics_.below_floor); less noisy states or a smaller "
                "library would decide"
            )
        rows, counts = _equations_with(self.weak)
        if rows.size:
            low = ", ".join(f"{v:.2g}" for v in _smallest(self.significance)[rows])
            out.append(
                f"equations {rows.tolist()}: {counts} selected terms are within "
                f"{self.significance_level:g} standard errors of zero (smallest robust t "
                f"{low}): the data do not vouch for them"
                + (
                    ""
                    if self.significance_level <= SIGNIFICANCE
                    else f" (the bar is {self.significance_level:g}, not {SIGNIFICANCE:g}, "
                    "because the statistic leaves out the error of estimated derivatives)"
                )
                + "; see diagnostics_.significance, and try more data or measured derivatives"
            )
        seen, counts = _equations_with(np.nan_to_num(self.pruned) >= VISIBLE)
        if seen.size:
            estimated = self.significance_level > SIGNIFICANCE
            advice = "measured derivatives, " if estimated else ""
            high = ", ".join(f"{v:.2g}" for v in np.nanmax(self.pruned[seen], axis=1))
            out.append(
                f"equations {seen.tolist()}: {counts} selected terms were dropped because "
                f"their robust t was below {self.significance_level:g} (the bar for the "
                f"selected terms), yet at least {VISIBLE:g} (largest {high}): they may be "
                f"real, and these data cannot decide (see diagnostics_.pruned); {advice}"
                "more data or less noisy states would"
            )
        close = np.flatnonzero(self.bic_margin < MIN_BIC_MARGIN)
        if close.size:
            margins = ", ".join(f"{v:.1f}" for v in self.bic_margin[close])
            out.append(
                f"equations {close.tolist()}: another support scored within "
                f"{MIN_BIC_MARGIN:g} of the chosen one's BIC (differences {margins}): the "
                "data do not strongly prefer the selected terms; compare the candidates "
                "(selection_.candidates and selection_.scores on the path, "
                "selection_.subsets and selection_.subset_scores), and try more data or "
                "measured derivatives"
            )
        return out

    def __repr__(self) -> str:
        lines = [
            f"Diagnostics({self.n_samples} samples, {self.n_terms} terms, "
            f"{self.samples_per_term:.1f} kept samples per term)",
            f"  temporal screen: {self.temporal_flagged_entries} entries in "
            f"{self.temporal_flagged_samples} samples",
            f"  model screen: {self.model_flagged_samples} samples left out, "
            f"{self.readmitted_samples} readmitted, converged={self.screening_converged}"
            + (", restarted" if self.screening_restarted else ""),
            f"  unresolved derivatives: {self.unresolved_samples} samples left out",
            f"  left out in all: {100 * self.flagged_fraction:.1f} %",
            f"  certified: {self.certified.tolist()}",
            f"  condition numbers: {np.array2string(self.condition_number, precision=2)}",
            f"  library noise along its weakest direction: {self.library_noise:.2g}",
            "  share of the measured state noise the residuals allow: "
            + np.array2string(self.noise_factor, formatter={"float_kind": "{:.2g}".format}),
            f"  unstable terms per equation: {self.unstable.sum(axis=1).tolist()}",
            "  terms dropped as errors-in-variables bias per equation: "
            f"{np.isfinite(self.bias_ratio).sum(axis=1).tolist()}",
            "  terms dropped as derivative truncation bias per equation: "
            f"{np.isfinite(self.truncation_ratio).sum(axis=1).tolist()}",
            "  terms left out below the noise floor per equation: "
            f"{np.isfinite(self.below_floor).sum(axis=1).tolist()}",
            f"  BIC margin to the next support: {np.array2string(self.bic_margin, precision=3)}",
            f"  supports searched exhaustively up to size: {self.subset_size.tolist()}"
            + (
                " (chosen from that search: equations "
                f"{np.flatnonzero(self.from_subsets).tolist()})"
                if self.from_subsets.any()
                else ""
            ),
            "  smallest robust t per equation: "
            + np.array2string(_smallest(self.significance), precision=3),
            "  terms dropped below the significance bar per equation: "
            f"{np.isfinite(self.pruned).sum(axis=1).tolist()}",
            f"  aliased terms left out: {', '.join(self.aliased) or 'none'}",
            "  derivatives: "
            + (
                "local quartics, half windows per state "
                f"{self.derivative_half_window.tolist()} samples"
                if self.derivative_half_window.any()
                else "measured (or another differentiation)"
            ),
        ]
        problems = self.problems()
        lines += [f"  problem: {p}" for p in problems] if problems else ["  no problem found"]
        return "\n".join(lines)


#: Samples (the first ones, contiguous) on which the automatic choices are made when the
#: data are Dask arrays.
DASK_SAMPLE = 200_000
#: Samples each chunk borrows from its neighbours to differentiate Dask states.
DASK_OVERLAP = 64

_DIFFERENTIATION = {
    "robust": None,  # local polynomials, temporal outliers given no weight (see fit)
    "finite_difference": finite_difference,
    "savgol": savgol_derivative,
}


def _as_list(value, name: str, multiple: bool):
    if value is None:
        return None
    if multiple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{name} must be a list with one array per trajectory, like x")
        return list(value)
    return [value]


class HuberSINDy(BaseEstimator):
    """Sparse identification of nonlinear dynamics with the Huber loss.

    Each equation ``k`` solves ``min_xi sum_i H_delta(xdot_ik - Theta_i xi) + lam
    ||xi||_1`` (:func:`robust_sindy.fit`).  With the defaults nothing needs choosing:

    1. ``screen=True``: samples that are gross outliers in the library rows or the
       derivatives are flagged (:func:`robust_sindy.selection.screen_rows`) and left
       out;
    2. ``delta="auto"``: 1.345 robust residual scales per equation
       (:func:`robust_sindy.selection.auto_delta`);
    3. ``lam="auto"``: a warm-started ``lam`` path, the selection stage (drop terms
       below ``selection_tol`` relative contribution, refit by Huber with ``lam = 0``)
       at every point, and the point with the best robust BIC or blocked
       cross-validation score (:func:`robust_sindy.selection.select`);
    4. ``lam="auto"`` with the screen: selected terms within ``BIAS_MARGIN`` times the
       bias that the states' noise can give them through the other terms (errors in
       the variables, :mod:`robust_sindy.selection.bias`; the noise no larger than
       each equation's residuals allow, ``noise_factor_``) are dropped one at a time
       and the rest refitted (``bias_dropped_``); with derivatives estimated by the
       robust local polynomials, so are those within ``BIAS_MARGIN`` times the bias
       that their truncation error gives them, measured against derivatives two
       orders higher (``truncation_ratio_``: a coarsely sampled trajectory);
    5. ``lam="auto"``: selected terms whose robust t is below the bar
       (``SIGNIFICANCE``, or ``SIGNIFICANCE_ESTIMATED`` with estimated derivatives) are
       dropped, the weakest first, the rest refitted after each, in every equation with
       a term at ``SIGNIFICANCE_ESTIMATED`` or more (``pruned_``; a warning when a
       dropped term reached t 2).

    Fixed values turn each step into the plain estimator (``screen=False``,
    ``delta=1.0, lam=1.0`` is the paper's).  ``threshold`` and ``refit`` then act on
    the result.

    Parameters
    ----------
    library : BaseLibrary, optional
        Candidate functions of the states then the controls (default: polynomials of
        degree 2).  It is cloned and fitted; the fitted copy is ``library_``.
    delta : float, array_like (n,) or "auto"
        Huber threshold per equation.
    lam : float, array_like (n,) or "auto"
        L1 weight per equation.
    screen : bool
        Flag and leave out gross-outlier samples before fitting.
    criterion : {"bic", "cv"}
        How ``lam="auto"`` picks the point on the path.
    selection_tol : float
        Relative contribution ``|xi_j| ||theta_j|| / ||xdot_k||`` below which
        ``lam="auto"`` drops a term.  With the screen on, the threshold used
        (``selection_tol_``) is at least the relative noise of the noisiest library
        column (the states' noise, measured by the temporal screen, carried through
        the library): a term contributing less than the noise of the columns it is
        built from cannot be told from errors in the variables unless the data vouch
        for it.  A term under that floor is kept when its robust t statistic is at
        least :data:`~robust_sindy.selection.significance.SIGNIFICANCE` (measured
        derivatives, ``x_dot`` given) or ``SIGNIFICANCE_ESTIMATED`` (estimated ones).
    n_lams : int
        Points on the ``lam`` path.
    method : {"admm", "cvxpy", "stls", "ols"}
        Solver passed to :func:`robust_sindy.fit` (``lam="auto"`` needs a Huber
        method, "admm" or "cvxpy").
    threshold : float, optional
        After the fit, set coefficients with ``|xi| < threshold`` to zero.
    refit : bool
        Refit each equation on its nonzero terms with ``lam = 0`` (Huber loss, same
        ``delta``): removes the shrinkage of the L1 penalty.  Always done with
        ``lam="auto"`` (the selected model is such a refit).
    differentiation : {"robust", "finite_difference", "savgol"} or callable
        How derivatives are obtained when ``x_dot`` is not given.  ``"robust"``
        (default): entries the temporal screen flags are replaced by their local
        prediction and given no weight, then a local quartic over
        ``derivative_window`` is differentiated
        (:func:`~robust_sindy.differentiation.local_polynomial_derivative`).
        ``"finite_difference"`` (second-order)
        and ``"savgol"`` differentiate the screened, repaired states (with
        ``screen=False``, the raw ones: then a single outlier spoils the derivatives of its
        neighbours, over the whole window for ``"savgol"``).  A callable receives
        ``(x, t)`` and returns an array shaped like ``x``.
    solver : str, optional
        For ``method="cvxpy"``: ``"clarabel"`` or ``"osqp"``.
    solver_options : dict, optional
        Keyword options of :func:`robust_sindy.fit` (``max_iter``, ``tol``, ...).
    progress : bool
        Show progress bars for the ``lam`` path.
    derivative_window : {"auto", "fixed"}
        The window of ``differentiation="robust"``.  ``"auto"`` (default): 5 to 65
        samples, chosen per state and trajectory
        (:func:`~robust_sindy.differentiation.choose_half_window`: by how well a window
        predicts the states left out, widened only while the library cannot explain the
        change of the derivative), windows wider than the quartic fitted by Huber's loss
        at the noise level the temporal screen measured.  ``"fixed"``: 5 samples, the
        fourth-order central difference, whose error is a bias too small for the
        regression to mistake for terms, but which multiplies the noise of the states by
        about ``1 / dt``, so that densely sampled noisy states lose their small terms
        (a damped oscillator sampled 300 times per period with Student-t noise: the
        damping, at robust t 3, is pruned).  See ``derivative_windows_``.

    Attributes
    ----------
    coef_ : ndarray, shape (n_targets, n_features)
        Identified coefficients (rows: equations; the transpose of :func:`fit`'s Xi).
    support_ : ndarray of bool, shape (n_targets, n_features)
        ``coef_ != 0``.
    library_ : BaseLibrary
        The fitted library; ``feature_names_`` are its input names (states, controls).
    delta_ : ndarray (n_targets,)
        The Huber thresholds used (chosen ones for ``"auto"``).
    lam_ : ndarray (n_targets,) or (n_features, n_targets)
        The L1 weights used.  ``lam="auto"`` chooses one weight per equation on
        standardised library columns (``selection_.lam``); in user units that is one
        weight per coefficient, this array.
    screened_ : ndarray of bool, shape (n_samples,)
        Samples flagged by the screen and left out of the fit (all False without it):
        outliers, and the samples of ``unresolved_``.
    unresolved_ : ndarray of bool, shape (n_samples,)
        Samples whose estimated derivatives the sampling does not resolve (with
        ``differentiation="robust"`` and the screen:
        :func:`~robust_sindy.differentiation.unresolved_derivatives` of any state),
        left out of the fit: along an excursion only a few samples long the
        derivative's truncation error is systematic, and a regression would explain it
        with spurious terms.  For Dask input, found chunk by chunk (and kept in memory:
        one byte per sample).
    temporal_ : TemporalScreening or None
        The temporal screen's flags, repaired states and noise levels.
    derivative_windows_ : ndarray of int (n_states,)
        Half width, in samples, of the window each state's derivative was estimated
        over with ``differentiation="robust"`` (the widest over the trajectories; 2, the
        five-sample stencil, with ``derivative_window="fixed"``); 0 when ``x_dot`` was
        given or another ``differentiation`` was used.
    screening_ : Screening or None
        The model-based screen's details (residual scales, rounds, convergence); it
        screens the samples outside ``unresolved_``, and its masks cover all samples.
    library_noise_ : tuple (ndarray (n_features,), float)
        The states' noise carried through the library: per column relative to its
        root mean square, and along the library's least-excited direction (see
        :class:`Diagnostics`, which reports the noise the residuals allow,
        ``library_noise_allowed_``); NaN without the screen.
    library_noise_allowed_ : float
        The library noise along the least-excited direction with each state's noise
        no larger than the residuals of the equations it enters allow.
    selection_tol_ : float
        The selection stage's threshold used (see ``selection_tol``).
    diagnostics_ : Diagnostics
        What the data can and cannot vouch for; problems are also raised as
        :class:`IdentificationWarning`.
    path_ : Path or None
        The ``lam`` path of ``lam="auto"``.
    selection_ : Selection or None
        Scores and candidates of ``lam="auto"``.
    outliers_ : ndarray of bool, shape (n_samples, n_targets)
        Whether the residual of a sample under the final model exceeds ``delta_``
        (samples of all trajectories stacked in order).
    result_ : FitResult
        The penalised fit at ``lam_`` on the kept samples (before threshold and refit).
    bias_dropped_ : ndarray of bool, shape (n_targets, n_features)
        Terms dropped by step 4.
    bias_ratio_ : ndarray, shape (n_targets, n_features)
        Their coefficient over their first-order bias when dropped (NaN elsewhere).
    truncation_ratio_ : ndarray, shape (n_targets, n_features)
        For terms dropped as within ``BIAS_MARGIN`` times the bias the truncation
        error of the estimated derivatives gives them: their coefficient over that
        bias (NaN elsewhere; see ``Diagnostics.truncation_ratio``).
    noise_factor_ : ndarray, shape (n_targets,)
        Per equation, the share of the temporal screen's measured noise variance that
        its residuals allow (at most 1; see ``Diagnostics.noise_factor``).
    below_floor_ : ndarray, shape (n_targets, n_features)
        Unselected terms whose contribution if added (one Newton step,
        :func:`robust_sindy.selection.refit.one_step_contributions`) lies between
        ``selection_tol`` and the noise floor ``selection_tol_``; NaN elsewhere.
    significance_ : ndarray, shape (n_targets, n_features)
        Robust t statistic of each selected term (see :class:`Diagnostics`).
    pruned_ : ndarray, shape (n_targets, n_features)
        With ``lam="auto"``, the robust t at which each term dropped below the bar was
        dropped; NaN elsewhere (see :class:`Diagnostics`).
    aliased_ : ndarray of bool, shape (n_features,)
        Library terms left out of the selection as exact linear combinations of earlier
        ones on the kept samples (``lam="auto"`` only; see :class:`Diagnostics`).

    Examples
    --------
    >>> import numpy as np
    >>> from robust_sindy import HuberSINDy
    >>> from robust_sindy.systems import Lorenz
    >>> data = Lorenz().generate(t_end=5.0)
    >>> model = HuberSINDy(threshold=0.05, refit=True)
    >>> model = model.fit(data.x, data.t, x_dot=data.x_dot, feature_names=["x", "y", "z"])
    >>> model.print()
    (x)' = -10.000 x + 10.000 y
    (y)' = 28.000 x - 1.000 y - 1.000 x*z
    (z)' = -2.667 z + 1.000 x*y
    """

    def __init__(
        self,
        library: BaseLibrary | None = None,
        delta="auto",
        lam="auto",
        screen: bool = True,
        criterion: str = "bic",
        selection_tol: float = 0.005,
        n_lams: int = 50,
        method: str = "admm",
        threshold: float | None = None,
        refit: bool = False,
        differentiation: str | Callable = "robust",
        solver: str | None = None,
        solver_options: dict | None = None,
        progress: bool = False,
        derivative_window="auto",
    ):
        self.library = library
        self.delta = delta
        self.lam = lam
        self.screen = screen
        self.criterion = criterion
        self.selection_tol = selection_tol
        self.n_lams = n_lams
        self.method = method
        self.threshold = threshold
        self.refit = refit
        self.differentiation = differentiation
        self.solver = solver
        self.solver_options = solver_options
        self.progress = progress
        self.derivative_window = derivative_window

    # ------------------------------------------------------------------ data handling
    def _trajectories(self, x, t, x_dot, u, *, need_t: bool):
        multiple = isinstance(x, (list, tuple))
        xs = [as_float_array(a, "x", (1, 2)) for a in _as_list(x, "x", multiple)]
        xs = [a[:, None] if a.ndim == 1 else a for a in xs]
        if multiple and not xs:
            raise ValueError("x is an empty list: give at least one trajectory")
        n = xs[0].shape[1]
        for a in xs:
            if a.shape[1] != n:
                raise ValueError("x: every trajectory must have the same number of states")
        us = _matching(u, "u", xs, multiple)
        if us is not None:
            for a, b in zip(us, xs, strict=True):
                if a.shape[0] != b.shape[0]:
                    raise ValueError(f"u has {a.shape[0]} samples but x has {b.shape[0]}")
        ds = _matching(x_dot, "x_dot", xs, multiple)
        if ds is not None:
            for a, b in zip(ds, xs, strict=True):
                if a.shape != b.shape:
                    raise ValueError(f"x_dot has shape {a.shape} but x has shape {b.shape}")
        ts = None
        if need_t or ds is None:
            ts = self._times(t, xs, multiple)
        return xs, ts, ds, us

    @staticmethod
    def _times(t, xs, multiple):
        if t is None:
            raise ValueError("t is required (a time step or the sample times)")
        if not isinstance(t, (list, tuple)) and np.ndim(t) == 0:
            dt = as_float_array(t, "t", (0,))
            if dt <= 0:
                raise ValueError(f"t as a time step must be > 0; got {float(dt)}")
            return [float(dt) * np.arange(a.shape[0]) for a in xs]
        tl = _as_list(t, "t", multiple)
        if len(tl) != len(xs):
            raise ValueError(f"t has {len(tl)} trajectories but x has {len(xs)}")
        out = []
        for ti, a in zip(tl, xs, strict=True):
            ti = check_time(ti, "t", min_length=1)
            if ti.size != a.shape[0]:
                raise ValueError(f"t has {ti.size} time points but x has {a.shape[0]} samples")
            out.append(ti)
        return out

    def _inputs(self, x, u) -> np.ndarray:
        q = getattr(self, "n_control_features_", 0)
        if u is None:
            if q:
                raise ValueError(f"u is required: the model was fitted with {q} controls")
            return x
        if u.shape[1] != q:
            raise ValueError(f"u has {u.shape[1]} columns but the model was fitted with {q}")
        return np.hstack([x, u])

    def _differentiate(self, x, t, half_window=None, scale=None, library=None):
        """Derivatives of one trajectory by ``differentiation``.  ``half_window``: of
        the robust one's local quartics (by default as ``derivative_window`` says, the
        automatic choice guarded by the ``library`` matrix of ``x`` when given, as in
        ``fit``); ``scale``: the states' noise for their Huber fits (by default the
        temporal screen's of ``x``)."""
        how = self.differentiation
        if callable(how):
            out = as_float_array(how(x, t), "differentiation output", (2,))
            if out.shape != x.shape:
                raise ValueError(f"differentiation returned shape {out.shape}; expected {x.shape}")
            return out
        _check_differentiation(how)
        if _is_robust(how):
            screen = temporal_screen(x, t)
            scale = screen.scale if scale is None else scale
            return self._robust_derivative(
                screen.repaired, t, ~screen.flags, scale, library, half_window
            )[0]
        return _DIFFERENTIATION[how](x, t)

    def _robust_derivative(self, repaired, t, usable, noise, library=None, half=None):
        """``differentiation="robust"`` of repaired states (``usable``: the entries the
        temporal screen left alone; ``noise``: its noise levels) and the half windows
        used: ``half`` when given, else as ``derivative_window`` says (the automatic
        choice guarded by the ``library`` matrix when given)."""
        if half is None:
            half = np.full(repaired.shape[1], FIXED_HALF_WINDOW)
            if self.derivative_window == "auto":
                half = choose_half_window(
                    repaired, t, usable, library=library, rows=usable.all(axis=1),
                    scale=noise,
                )  # fmt: skip
        d = local_polynomial_derivative(repaired, t, half, mask=usable, scale=noise)
        return d, half

    # ------------------------------------------------------------------ fitting
    def fit(self, x, t=None, x_dot=None, u=None, feature_names=None) -> HuberSINDy:
        """Identify the equations from one trajectory or a list of trajectories.

        Up to ``SMALL_PROBLEM_SAMPLES`` samples, BLAS runs on one thread during the fit
        (:mod:`threadpoolctl`): its products are then small and the threads' start-up
        costs more than they save (1.1-1.3 times faster on 2 cores at 2000 samples).

        Parameters
        ----------
        x : array_like (m, n), or a list of them
            Measured states.
        t : float, array_like (m,), or a list of arrays
            Time step or sample times (strictly increasing); needed unless ``x_dot``
            is given.
        x_dot : array_like like ``x``, optional
            Measured derivatives; computed by ``differentiation`` when omitted.
        u : array_like (m, q), or a list of them, optional
            Control inputs (noise-free, sampled with ``x``).
        feature_names : sequence of str, optional
            Names of the states then the controls (default: the column names when ``x``
            and ``u`` are pandas DataFrames, else ``x0, x1, ..., u0, ...``).

        ``x``, ``x_dot`` and ``u`` may be pandas DataFrames (or lists of them): their
        values are used, the column names of ``x`` and ``u`` name the states and
        controls, and when ``t`` is omitted a datetime or timedelta index gives the
        sample times in seconds.
        """
        self._check_params()
        if any(
            is_dask(a) or (isinstance(a, (list, tuple)) and any(is_dask(b) for b in a))
            for a in (x, x_dot, u)
        ):
            return self._fit_dask(x, t, x_dot, u, feature_names)
        x, t, x_dot, u, frame_names = _from_frames(x, t, x_dot, u)
        if feature_names is None:
            feature_names = frame_names
        xs, ts, ds, us = self._trajectories(x, t, x_dot, u, need_t=False)
        if sum(a.shape[0] for a in xs) <= SMALL_PROBLEM_SAMPLES:
            with one_thread():
                return self._fit(xs, ts, ds, us, feature_names)
        return self._fit(xs, ts, ds, us, feature_names)

    def _fit_dask(self, x, t, x_dot, u, feature_names) -> HuberSINDy:
        """Dask arrays: choose on a sample in memory, then fit every sample out of core.

        The whole pipeline (screens, delta, lam, support) runs on the first
        ``DASK_SAMPLE`` samples; without ``x_dot`` (``t`` must then be the time step) the
        sample is fitted from its states, as in memory, and every chunk is
        differentiated by ``differentiation`` with the sample's windows and noise
        levels, each chunk with ``DASK_OVERLAP`` samples of its neighbours, its samples
        whose derivatives the sampling does not resolve left out (``unresolved_``, found
        in one pass).  Then every equation's selected terms are refitted by Huber
        (``lam = 0``, the chosen ``delta``) on all samples, chunk by chunk, in one
        batched solve (:mod:`robust_sindy.solvers.chunked`; a term outside an
        equation's support held at 0 by an L1 weight above ``delta ||A_j||_1``), leaving
        out the samples whose residual under the sample's model exceeds ``3.5``
        times the larger of the sample's robust scale and the local robust scale of the
        residuals within 25 samples, in any equation (the model screen's rule; here the
        local scale counts every sample, not only those the temporal screen left alone,
        and is capped at its largest ratio to the global scale on the sample's kept
        samples).  When more than ``MAX_FLAGGED_FRACTION`` of all samples are left out
        as gross (or with unresolved derivatives), or more than ``MAX_LEFT_OUT`` in all,
        a warning says the sample's model may not describe the rest of the data.
        A list of trajectories (``x``, and ``x_dot``, ``u`` and ``t`` when given, one
        each, or ``t`` one step for all) is sampled from its start, whole trajectories
        first; derivatives and local scales never reach across two trajectories.
        """
        import dask.array as da

        from ._scaling import robust_scale
        from .outofcore import dask_library
        from .selection.screening import local_scale

        multiple = isinstance(x, (list, tuple))
        xs = [da.asarray(a) for a in (x if multiple else [x])]
        if not xs:
            raise ValueError("x is an empty list: give at least one trajectory")
        if any(a.ndim != 2 for a in xs):
            shapes = [a.shape for a in xs]
            raise ValueError(f"with Dask, each trajectory of x must be 2-D; got shapes {shapes}")
        if any(a.shape[1] != xs[0].shape[1] for a in xs):
            raise ValueError("x: every trajectory must have the same number of states")

        def per_trajectory(value, name):
            values = _as_list(value, name, multiple)
            if values is None:
                return [None] * len(xs)
            if len(values) != len(xs):
                raise ValueError(f"{name} must be a list with one array per trajectory of x")
            return values

        us = [None if a is None else da.asarray(a) for a in per_trajectory(u, "u")]
        us = [a[:, None] if a is not None and a.ndim == 1 else a for a in us]
        for a, b in zip(us, xs, strict=True):
            if a is not None and a.shape[0] != b.shape[0]:
                raise ValueError(f"u has {a.shape[0]} samples but x has {b.shape[0]}")
        step = t is not None and not isinstance(t, (list, tuple)) and np.ndim(t) == 0
        ts = [t] * len(xs) if step or t is None else per_trajectory(t, "t")
        ds = per_trajectory(x_dot, "x_dot")
        estimate = any(d is None for d in ds)
        if estimate:
            if not step or is_dask(t):
                raise ValueError(
                    "with a Dask x, derivatives are computed out of core for a uniform time "
                    "step only: pass t as a number (the step), or pass x_dot"
                )
            dt = float(t)
            if not (np.isfinite(dt) and dt > 0):
                raise ValueError(f"t as a time step must be a finite number > 0; got {t!r}")
        else:
            ds = [da.asarray(d) for d in ds]
            ds = [d[:, None] if d.ndim == 1 else d for d in ds]
            for d, a in zip(ds, xs, strict=True):
                if d.shape != a.shape:
                    raise ValueError(f"x_dot has shape {d.shape} but x has shape {a.shape}")
        # The sample: the first DASK_SAMPLE samples, whole trajectories first.
        left, sample = DASK_SAMPLE, []
        for a, d, b, ti in zip(xs, ds, us, ts, strict=True):
            if left <= 0:
                break
            k = min(a.shape[0], left)
            left -= k
            if ti is not None and np.ndim(ti) > 0:
                ti = np.asarray(ti[:k], dtype=float)
            parts = [None if v is None else v[:k] for v in (a, d, b)]
            got = iter(da.compute(*(v for v in parts if v is not None)))
            sa, sd_, sb = (None if v is None else np.asarray(next(got), float) for v in parts)
            sample.append((sa, ti, sd_, sb))
        sx, st, sd, su = (list(v) for v in zip(*sample, strict=True))
        one = len(sample) == 1
        t_sample = None if t is None else (st[0] if step or one else [np.asarray(v) for v in st])
        # Estimated derivatives: the sample is fitted from its states, as in memory (its
        # own screens, derivatives and unresolved samples).
        self._fit(*self._trajectories(sx[0] if one else sx, t_sample,
                                      None if estimate else (sd[0] if one else sd),
                                      None if su[0] is None else (su[0] if one else su),
                                      need_t=False), feature_names)  # fmt: skip
        coef_sample = self.coef_.T.copy()
        unresolved = [np.zeros(a.shape[0], dtype=bool) for a in xs]
        if estimate:
            # Every chunk is differentiated with DASK_OVERLAP samples of its neighbours
            # on either side (the temporal screen's and the stencils' windows lie well
            # within them), by the sample's windows and noise levels, and its unresolved
            # samples are found as in memory.
            half = self.derivative_windows_ if _is_robust(self.differentiation) else None
            noise = None if self.temporal_ is None else self.temporal_.scale

            # A module-level function of an unfitted copy: the lazy results (screened_,
            # outliers_) hold it, and a fitted model is pickled with them.
            derivative = functools.partial(
                _chunk_derivative, model=clone(self), dt=dt, half=half, noise=noise
            )

            xs = [a.rechunk({1: -1}) for a in xs]
            ds = [
                a.map_overlap(
                    derivative, depth={0: DASK_OVERLAP, 1: 0}, boundary="none", dtype=float
                )
                for a in xs
            ]
            # The unresolved samples, found in one pass and kept (one byte per sample):
            # every pass of the refit recomputes the derivatives, not this check.
            *unresolved, sd = da.compute(
                *(
                    a.map_overlap(
                        functools.partial(derivative, check=True),
                        depth={0: DASK_OVERLAP, 1: 0}, boundary="none", dtype=bool,
                    )[:, 0]
                    for a in xs
                ),
                [d[: a.shape[0]] for d, a in zip(ds, sx, strict=False)],
            )  # fmt: skip
            sd = [np.asarray(v, dtype=float) for v in sd]
        # The sample's model and scales screen every sample, chunk by chunk.
        kept = ~self.screened_
        r_sample = (
            np.vstack(sd)
            - self.library_.transform(
                np.vstack([self._inputs(a, b) for a, b in zip(sx, su, strict=True)])
            )
            @ coef_sample
        )
        scale = np.maximum(robust_scale(r_sample[kept]), np.finfo(float).tiny)
        # The local scale may exceed the global one only as far as it does on the
        # sample's kept samples: where most residuals in a window are gross (a stretch
        # of corrupted data after the sample), the local scale would excuse them all.
        local_sample = np.vstack(
            [local_scale(r_sample[seg], 25) for seg in _segments(sx)]
        )  # fmt: skip
        cap = np.max(local_sample[kept] / scale, axis=0, initial=1.0) * scale
        thetas, rs_, bads = [], [], []
        for a, d, b, loose in zip(xs, ds, us, unresolved, strict=True):
            _, theta_i = dask_library(self.library_, a, b, input_names=self.library_.input_names_)
            r_i = d - theta_i @ da.from_array(coef_sample)
            # As the model screen: the larger of the global scale and the residuals' local
            # robust scale within 25 samples (residuals that grow along a fast part of the
            # trajectory are not outliers), each chunk with 25 samples of its neighbours;
            # the local scale at most ``cap``.
            local = da.map_overlap(
                functools.partial(local_scale, half_width=25), r_i, depth={0: 25, 1: 0},
                boundary="none",
                dtype=float,
            )  # fmt: skip
            thetas.append(theta_i)
            rs_.append(r_i)
            gross = (abs(r_i) > 3.5 * da.maximum(da.minimum(local, cap), scale)).any(axis=1)
            bads.append(gross | da.from_array(loose, chunks=gross.chunks))
        theta, r, bad = (da.concatenate(v, axis=0) for v in (thetas, rs_, bads))
        unresolved = np.concatenate(unresolved)
        x_dot = da.concatenate(ds, axis=0)
        m = theta.shape[0]
        k = sum(a.shape[0] for a in sx)
        keep = ~bad
        theta_k = theta * keep[:, None]
        y_k = x_dot * keep[:, None]
        # One pass for the count of samples left out and the columns' L1 norms (kept rows).
        n_flagged, l1 = da.compute(bad.sum(), abs(theta_k).sum(axis=0))
        coef = np.zeros_like(coef_sample)
        cols = np.flatnonzero((coef_sample != 0).any(axis=0))
        terms = np.flatnonzero((coef_sample != 0).any(axis=1))
        result = None
        certified = np.ones(coef.shape[1], dtype=bool)
        if cols.size:
            support = coef_sample[np.ix_(terms, cols)] != 0
            lam = np.zeros(support.shape)  # lam="auto" and refit: the selected terms, unpenalised
            if self.selection_ is None and not self.refit:
                lam_ = np.asarray(self.lam_, dtype=float)
                lam = np.broadcast_to(
                    lam_[np.ix_(terms, cols)]
                    if lam_.ndim == 2
                    else np.broadcast_to(lam_, (coef.shape[1],))[cols][None, :],
                    support.shape,
                ).copy()  # fmt: skip
            # Every equation's selected terms refitted in one batched solve (its passes
            # over the data shared by all equations): a term outside an equation's
            # support gets an L1 weight above delta ||A_j||_1, the most |A_j^T psi| can
            # be with |psi| <= delta, which holds its coefficient at exactly 0.
            delta = np.asarray(self.delta_, dtype=float)[cols]
            bound = 2.0 * delta[None, :] * np.maximum(l1[terms], np.finfo(float).tiny)[:, None]
            result = fit(theta_k[:, terms], y_k[:, cols], delta=delta,
                         lam=np.where(support, lam, bound),
                         **{key: v for key, v in (self.solver_options or {}).items()
                            if key in ("tol", "max_iter")})  # fmt: skip
            coef[np.ix_(terms, cols)] = np.where(support, np.asarray(result.coef), 0.0)
            certified[cols] = result.column_converged
        self.coef_sample_ = coef_sample.T
        self.coef_ = np.ascontiguousarray(coef.T)
        self.support_ = self.coef_ != 0
        self.screened_ = bad  # lazy (Dask): samples left out of the out-of-core refit
        self.unresolved_ = unresolved  # in memory: one byte per sample, among screened_
        self.outliers_ = abs(r) > self.delta_
        self.diagnostics_.certified = self.diagnostics_.certified & certified
        self.dask_ = {
            "sample": k,
            "samples": m,
            "flagged": int(n_flagged),
            "unresolved": int(unresolved.sum()),
            "passes": 0 if result is None else result.info["passes"],
            "refit": result,
        }
        # The sample's diagnostics speak for the sample: a model that fits the sample but
        # not the rest of the data (a regime, a sensor or a contamination that changes
        # after it) shows in what the out-of-core screen leaves out.
        left_out = int(n_flagged) / max(m, 1)
        unresolved_part = int(unresolved.sum()) / max(m, 1)
        if max(left_out - unresolved_part, unresolved_part) > MAX_FLAGGED_FRACTION or (
            left_out > MAX_LEFT_OUT
        ):
            warnings.warn(
                f"out of core, {100 * left_out:.0f} % of all samples were left out of the "
                f"refit ({100 * (left_out - unresolved_part):.0f} % with gross residuals "
                f"under the sample's model, {100 * unresolved_part:.0f} % with unresolved "
                f"derivatives), against {100 * self.diagnostics_.flagged_fraction:.0f} % "
                f"of the first {k} samples, where the model was chosen: it may not describe "
                "the rest of the data (see dask_ and screened_); fit a sample from another "
                "part of the data, or more of it (robust_sindy.model.DASK_SAMPLE)",
                IdentificationWarning,
                stacklevel=3,
            )
        if not certified.all():
            warnings.warn(
                f"the out-of-core refit of equations {np.flatnonzero(~certified).tolist()} "
                "was not certified (see dask_['refit'])",
                IdentificationWarning,
                stacklevel=3,
            )
        return self

    def _fit(self, xs, ts, ds, us, feature_names) -> HuberSINDy:
        n = xs[0].shape[1]
        q = 0 if us is None else us[0].shape[1]
        if us is not None and any(a.shape[1] != q for a in us):
            raise ValueError("u: every trajectory must have the same number of controls")
        feature_names = input_names(feature_names, n, q)
        self.n_control_features_ = q
        self.feature_names_ = feature_names
        self.library_ = clone(self.library) if self.library is not None else PolynomialLibrary()
        z = np.vstack([self._inputs(a, None if us is None else b) for a, b in _pairs(xs, us)])
        theta = self.library_.fit_transform(z, input_names=feature_names)
        m, p = theta.shape
        if m <= p:
            raise ValueError(
                f"x has {m} samples but the library has {p} terms: at least {p + 1} samples "
                "are needed to fit it (use a smaller library or more data)"
            )

        # 1. Temporal screen of the states (model-free), per trajectory and component.
        self.temporal_ = None
        entry_flags = np.zeros((m, n), dtype=bool)
        if self.screen:
            self.temporal_ = temporal_screen(xs, ts)
            entry_flags = self.temporal_.flags
        # 2. Derivatives of the (repaired) states when not measured.
        measured = ds is not None
        self.derivative_windows_ = np.zeros(n, dtype=int)
        self.unresolved_ = np.zeros(m, dtype=bool)
        reference = None  # higher-order derivatives, the reference for truncation errors
        if ds is None:
            ds, self.unresolved_, reference = self._derivatives(xs, ts, entry_flags, theta)
        y = np.vstack(ds)
        if not np.all(np.isfinite(y)):
            raise ValueError("the derivatives contain NaN or inf")

        # 3. Every decision on standardised library columns and targets.
        scaler = self.standardizer_ = Standardizer.from_data(theta, y)
        th_s, y_s = scaler.theta(theta), scaler.y(y)
        options = dict(self.solver_options or {})
        huber_method = self.method if self.method in ("admm", "cvxpy") else "admm"
        keep = np.ones(m, dtype=bool)
        noise_all = self._noise_columns(z)
        self.screening_ = None
        if self.screen:
            # Estimated derivatives the sampling does not resolve carry a systematic
            # error that the library would explain with spurious terms: left out, and
            # the model screen works on the other samples.
            keep = ~self.unresolved_
            screen = screen_rows(
                th_s[keep],
                y_s[keep],
                start=~entry_flags.any(axis=1)[keep],
                segments=_segments_of(keep, xs),
                method=huber_method,
                # The state noise carried through the model excuses residuals only
                # where it is all they contain: estimated derivatives add their own
                # errors along fast excursions, where the carried noise is largest.
                noise=[a[keep] for a in noise_all] if measured and noise_all else None,
            )
            outliers, start = np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)
            outliers[keep], start[keep] = screen.outliers, screen.start
            self.screening_ = dataclasses.replace(screen, outliers=outliers, start=start)
            keep = keep & ~outliers
        self.screened_ = ~keep
        th, yk = th_s[keep], y_s[keep]
        # Terms that are exact combinations of earlier ones on these samples (a state
        # that does not move) cannot be told apart by any data: the selection sees only
        # the first of each group.
        self.aliased_ = np.zeros(p, dtype=bool)
        if _is_auto(self.lam):
            self.aliased_ = aliased_columns(th)
            if self.aliased_.any():
                th = th.copy()
                th[:, self.aliased_] = 0.0
        # A term that contributes less than the noise of the library columns themselves
        # cannot be told from errors in the variables: the selection stage's threshold
        # is at least the relative noise of the noisiest column.
        noise = None if noise_all is None else [a[keep] for a in noise_all]
        self.library_noise_ = self._library_noise(noise, th)
        column_noise = self.library_noise_[0][~self.aliased_]
        self.selection_tol_ = float(
            max(self.selection_tol, np.max(column_noise, initial=0.0))
            if np.all(np.isfinite(column_noise))
            else self.selection_tol
        )
        self.path_ = self.selection_ = None
        if _is_auto(self.lam):
            delta_s = (
                auto_delta(th, yk, method=huber_method, **pilot_budget(huber_method))
                if _is_auto(self.delta)
                else None
            )
            if delta_s is None:
                delta_s = per_column(self.delta, "delta", y.shape[1], positive=True)
                delta_s = delta_s / scaler.y_scale
            sel = select(
                th,
                yk,
                delta_s,
                criterion=self.criterion,
                n_lams=self.n_lams,
                # Terms under the noise floor are proposed: the final selection keeps
                # those the data vouch for (a higher bar for estimated derivatives).
                tol=self.selection_tol,
                segments=_segments_of(keep, xs),
                method=self.method,
                solver=self.solver,
                progress=self.progress,
                **options,
            )
            self.selection_, self.path_ = sel, sel.path
            cols = np.arange(y.shape[1])
            delta_u = scaler.delta_to_user(sel.delta)
            lam_u = scaler.lam_to_user(sel.lam)
            start = scaler.coef_to_user(sel.path.coef[sel.index, :, cols].T)
            coef = scaler.coef_to_user(sel.coef)
        else:
            delta_u = (
                np.atleast_1d(auto_delta(th, yk, method=huber_method, **pilot_budget(huber_method)))
                * scaler.y_scale
                if _is_auto(self.delta)
                else self.delta
            )
            lam_u, start = self.lam, None
        # The penalised fit in user units (the certificates of the chosen point).
        if start is not None and self.method == "admm":
            options = {**options, "warm_start": start}
        res = fit(theta[keep], y[keep], self.method, delta_u, lam_u, solver=self.solver, **options)
        options.pop("warm_start", None)
        if start is None:
            coef = res.coef.reshape(p, -1).copy()
        self.result_ = res
        self.delta_ = res.delta
        self.lam_ = res.lam
        if self.threshold is not None:
            if not np.isfinite(self.threshold) or self.threshold < 0:
                raise ValueError(f"threshold must be a finite number >= 0; got {self.threshold}")
            coef[np.abs(coef) < self.threshold] = 0.0
        if self.refit or self.selection_ is not None:
            # lam="auto": the selection stage scored its refits with a bounded budget;
            # the chosen support is refitted here in user units with the full one.
            coef = self._refit(theta[keep], y[keep], coef, options)
        ratio = np.full(coef.shape, np.nan)
        truncation = np.full(coef.shape, np.nan)
        pruned = np.full(coef.shape, np.nan)
        delta_s = np.broadcast_to(self.delta_, (y.shape[1],)) / scaler.y_scale
        if self.selection_ is not None:
            kept = (theta[keep], y[keep], th, yk)  # user units, then standardised
            segments = _segments_of(keep, xs)
            # The estimated derivatives' truncation error, measured against the
            # reference of higher order (standardised like the targets).
            error = None if reference is None else scaler.y(y[keep] - reference[keep])
            coef, ratio, truncation = self._final_selection(
                *kept, coef, delta_s, noise, huber_method, options, segments, measured, error
            )
            bar = SIGNIFICANCE if measured else SIGNIFICANCE_ESTIMATED
            coef, pruned = self._prune(*kept, coef, delta_s, options, segments, bar)
        self.pruned_ = np.ascontiguousarray(pruned.T)
        self.bias_ratio_ = np.ascontiguousarray(ratio.T)
        self.bias_dropped_ = np.isfinite(self.bias_ratio_)
        self.truncation_ratio_ = np.ascontiguousarray(truncation.T)
        self.noise_factor_ = np.full(y.shape[1], np.nan)
        self.library_noise_allowed_ = self.library_noise_[1]
        if self.selection_ is not None and noise is not None:
            standard = scaler.coef_to_standard(coef)
            for k in range(y.shape[1]):
                c = standard[:, k]
                self.noise_factor_[k] = residual_noise_factor(
                    yk[:, k] - th @ c, carried_noise(noise, c)
                )
            state = state_noise_factors(noise, standard, self.noise_factor_)
            if np.any(state < 1):
                allowed = [np.sqrt(f) * a for f, a in zip(state, noise, strict=True)]
                self.library_noise_allowed_ = self._library_noise(allowed, th)[1]
        below = np.full(coef.shape, np.nan)
        if self.selection_ is not None and self.selection_tol_ > self.selection_tol:
            # Terms left out that the raised noise floor, not the data, decided about.
            contrib = one_step_contributions(th, yk, scaler.coef_to_standard(coef), delta_s)
            inside = (contrib >= self.selection_tol) & (contrib < self.selection_tol_)
            below[inside] = contrib[inside]
        self.below_floor_ = np.ascontiguousarray(below.T)
        tstat = np.full(coef.shape, np.nan)
        if self.selection_ is not None:
            tstat = robust_t(th, yk, scaler.coef_to_standard(coef), delta_s, _segments_of(keep, xs))
        self.significance_ = np.ascontiguousarray(tstat.T)
        self.coef_ = np.ascontiguousarray(coef.T)
        self.support_ = self.coef_ != 0
        self.outliers_ = np.abs(y - theta @ coef) > self.delta_
        self.diagnostics_ = self._diagnose(th_s[keep], y_s[keep], entry_flags, measured)
        self._warn(self.diagnostics_)
        return self

    def _derivatives(self, xs, ts, entry_flags, theta):
        """Derivatives per trajectory: of the repaired states, outliers given no weight,
        over windows the library ``theta`` cannot tell from the narrowest one (on the
        samples the temporal screen left alone), the samples whose derivatives the
        sampling does not resolve, and the higher-order derivatives of all samples
        (stacked; None unless every trajectory has them) (:meth:`_trajectory_derivative`)."""
        out, highs, windows = [], [], [np.zeros(xs[0].shape[1], dtype=int)]
        unresolved = np.zeros(sum(a.shape[0] for a in xs), dtype=bool)
        for seg, a, ti in zip(_segments(xs), xs, ts, strict=True):
            screened, noise = None, None
            if self.temporal_ is not None:
                screened = (self.temporal_.repaired[seg], ~entry_flags[seg])
                noise = self.temporal_.scale
            d, half, unresolved[seg], high = self._trajectory_derivative(
                a, ti, screened, noise, library=theta[seg]
            )
            if half is not None:
                windows.append(half)
            out.append(d)
            highs.append(high)
        self.derivative_windows_ = np.max(windows, axis=0)
        reference = None if any(h is None for h in highs) else np.vstack(highs)
        return out, unresolved, reference

    def _trajectory_derivative(
        self, x, t, screened=None, noise=None, library=None, half=None, check=True
    ):
        """One trajectory's derivatives by ``differentiation``, the half windows of the
        robust ones (None for the others), the samples (m,) whose derivatives the
        sampling does not resolve (:func:`unresolved_derivatives` of any moving state;
        with robust differentiation and the screen only), and the higher-order
        derivatives they were judged against (:func:`higher_order_derivative`; None
        where they were not).

        ``screened``: ``(repaired, usable)`` from the temporal screen of ``x``, whose
        repaired states are differentiated (robust differentiation screens ``x`` itself
        when None); ``noise``: the states' noise levels (by default that screen's);
        ``library`` and ``half``: as in :meth:`_robust_derivative`; ``check=False``: the
        unresolved samples are not looked for (all False).  A state that does
        not move (its range within ``ALIAS_RTOL`` of its magnitude: constant up to
        rounding) has derivative 0, not the rounding of its differences, which
        standardisation would blow up to unit size.
        """
        states = x if screened is None else screened[0]
        loose = np.zeros(x.shape, dtype=bool)
        high = None
        if _is_robust(self.differentiation):
            if screened is None:  # screen=False: the derivatives' own screen
                own = temporal_screen(x, t)
                repaired, usable, noise = own.repaired, ~own.flags, own.scale
            else:
                repaired, usable = screened
            d, half = self._robust_derivative(repaired, t, usable, noise, library, half)
            if self.screen and check:
                high = higher_order_derivative(repaired, t, half, mask=usable, scale=noise)
                loose = unresolved_derivatives(
                    repaired, t, d, half, mask=usable, scale=noise, high=high
                )
        else:
            d, half = self._differentiate(states, t), None
        still = np.ptp(states, axis=0) <= ALIAS_RTOL * np.max(np.abs(states), axis=0)
        d = np.array(d, dtype=float)
        d[:, still] = 0.0
        if high is not None:
            high = np.where(np.isnan(high), d, high)  # a component too short: no reference
            high[:, still] = 0.0
        return d, half, loose[:, ~still].any(axis=1), high

    def _check_params(self):
        """Every parameter checked before any work (scikit-learn style: in ``fit``)."""
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}; got {self.method!r}")
        if self.library is not None and not isinstance(self.library, BaseLibrary):
            raise ValueError(
                "library must be a robust_sindy library (e.g. PolynomialLibrary(degree=2), "
                f"CustomLibrary(...)) or None; got {self.library!r}"
            )
        thr = self.threshold
        if thr is not None and (
            isinstance(thr, bool) or not isinstance(thr, Real) or not np.isfinite(thr) or thr < 0
        ):
            raise ValueError(f"threshold must be None or a finite number >= 0; got {thr!r}")
        for name in ("refit", "progress"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False; got {getattr(self, name)!r}")
        _check_differentiation(self.differentiation)
        if self.derivative_window not in DERIVATIVE_WINDOWS:
            raise ValueError(
                f"derivative_window must be one of {DERIVATIVE_WINDOWS}; "
                f"got {self.derivative_window!r}"
            )
        if self.solver_options is not None and not isinstance(self.solver_options, dict):
            raise ValueError(f"solver_options must be a dict or None; got {self.solver_options!r}")
        n_lams = self.n_lams
        if isinstance(n_lams, bool) or not isinstance(n_lams, Integral) or n_lams < 2:
            raise ValueError(f"n_lams must be an integer >= 2; got {n_lams!r}")
        self._check_selection_params()

    def _check_selection_params(self):
        if not isinstance(self.screen, bool):
            raise ValueError(f"screen must be True or False; got {self.screen!r}")
        if isinstance(self.lam, str) and not _is_auto(self.lam):
            raise ValueError(f"lam must be a number, one per equation, or 'auto'; got {self.lam!r}")
        if _is_auto(self.lam):
            if self.method not in ("admm", "cvxpy"):
                raise ValueError(
                    f"lam='auto' needs a Huber method ('admm' or 'cvxpy'); got "
                    f"method={self.method!r}: pass a number for lam"
                )
            if self.criterion not in CRITERIA:
                raise ValueError(f"criterion must be one of {CRITERIA}; got {self.criterion!r}")
            tol = self.selection_tol
            if isinstance(tol, bool) or not np.isscalar(tol) or not np.isfinite(tol) or tol < 0:
                raise ValueError(f"selection_tol must be a finite number >= 0; got {tol!r}")

    def _refit(self, theta, y, coef, options):
        method = self.method if self.method in ("admm", "cvxpy") else "admm"
        solver = self.solver if method == "cvxpy" else None
        return threshold_refit(
            theta,
            y,
            coef,
            self.delta_,
            tol=0.0,
            max_rounds=1,
            method=method,
            solver=solver,
            **options,
        )

    def _final_selection(
        self, theta, y, th, yk, coef, delta_s, noise, method, options, segments, measured,
        error=None,
    ):  # fmt: skip
        """On the certified refit: drop the terms below ``selection_tol``, and those
        below ``selection_tol_`` whose robust t (``segments``: the samples of each
        trajectory) is below ``SIGNIFICANCE`` (``measured`` derivatives) or
        ``SIGNIFICANCE_ESTIMATED`` (estimated ones), and those within ``BIAS_MARGIN``
        of their errors-in-variables bias (with the screen; the signed first-order bias
        for measured derivatives, its triangle bound for estimated ones), refitting
        after each, and, with estimated derivatives whose truncation ``error``
        (standardised, kept samples) was measured, those within ``BIAS_MARGIN`` of the
        bias that error gives them (:func:`~robust_sindy.selection.bias.truncation_bias`),
        until none drops anything.  ``theta``, ``y`` are the
        kept samples in user units, ``th``, ``yk`` the same standardised, ``delta_s``
        and ``method`` the Huber threshold (standardised) and method of the drops.
        Returns the coefficients and the bias ratios of the terms the last two dropped
        (NaN elsewhere)."""
        scaler = self.standardizer_
        col = np.linalg.norm(th, axis=0)[:, None]
        ynorm = np.maximum(np.linalg.norm(yk, axis=0), np.finfo(float).tiny)
        gram = None if noise is None else noise_gram(noise)
        ratio = np.full(coef.shape, np.nan)
        truncation = np.full(coef.shape, np.nan)
        bar = SIGNIFICANCE if measured else SIGNIFICANCE_ESTIMATED
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
            standard = scaler.coef_to_standard(coef)
            contrib = np.abs(standard) * col / ynorm
            small = (coef != 0) & (contrib < self.selection_tol_)
            if small.any():
                # Under the noise floor, a term stays only when the data vouch for it.
                tstat = robust_t(th, yk, standard, delta_s, segments)
                small &= (contrib < self.selection_tol) | ~(tstat >= bar)
            if small.any():
                coef[small] = 0.0
                coef = self._refit(theta, y, coef, options)
            changed = bool(small.any())
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
                    coef = self._refit(theta, y, coef, options)
                    changed = True
            if not changed:
                break
        return coef, ratio, truncation

    def _prune(self, theta, y, th, yk, coef, delta_s, options, segments, bar):
        """Drop the selected term with the smallest robust t while it is below ``bar``,
        per equation, refitting after each round.  The selection's criterion reads the
        likelihood as if the residuals were the model's only error; the sandwich
        statistic also sees the errors it leaves out (noise in the library columns
        reaching the fit through high-leverage rows, heavy tails, and with estimated
        derivatives their smooth errors shared with the library), and terms the
        criterion admits that the data do not vouch for are fitted to those errors.
        Only equations with a term at ``SIGNIFICANCE_ESTIMATED`` or more are pruned, and
        only while they keep one: an equation none of whose terms is that clear is left
        as selected (the data vouch for no version of it, and a warning says so), and a
        drop after which no term is that clear any more is undone (the dropped term was
        carrying the equation).  Returns the coefficients and the t of each dropped term
        (NaN elsewhere)."""
        scaler = self.standardizer_
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
            coef = self._refit(theta, y, coef, options)
            tstat = t_of(coef)
            lost = cols[~vouched(tstat, coef)[cols]]
            coef[:, lost], tstat[:, lost] = before[:, lost], t_before[:, lost]
            pruned[weakest[lost], lost] = np.nan
            done[lost] = True
        return coef, pruned

    def _stability(self, theta_kept, y_kept) -> np.ndarray:
        """Selected terms that leaving out one block of the data changes (see Diagnostics)."""
        scaler = self.standardizer_
        coef = scaler.coef_to_standard(self.coef_.T)  # (p, n) in standardised units
        delta = np.broadcast_to(self.delta_, (coef.shape[1],)) / scaler.y_scale
        unstable = np.zeros(coef.shape, dtype=bool)
        m = theta_kept.shape[0]
        edges = np.linspace(0, m, STABILITY_BLOCKS + 1).round().astype(int)
        method = self.method if self.method in ("admm", "cvxpy") else "admm"
        for k in range(coef.shape[1]):
            sel = np.flatnonzero(coef[:, k])
            if sel.size == 0 or m < STABILITY_BLOCKS * (sel.size + 2):
                continue
            ref = coef[sel, k]
            for a, b in itertools.pairwise(edges):
                rows = np.r_[0:a, b:m]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    c = fit(
                        theta_kept[rows][:, sel],
                        y_kept[rows, k],
                        method,
                        delta[k],
                        0.0,
                        **pilot_budget(method),
                    )
                c = c.coef.ravel()
                unstable[sel, k] |= (np.sign(c) != np.sign(ref)) | (
                    np.abs(c - ref) > STABILITY_TOLERANCE * np.abs(ref)
                )
        return unstable.T

    def _noise_columns(self, z) -> list[np.ndarray] | None:
        """The noise of each state carried through the standardised library, first
        order, at every sample: ``sigma_k dTheta/dx_k / theta_scale`` per state ``k``
        (``sigma_k`` measured by the temporal screen); None without it."""
        if self.temporal_ is None or not np.all(np.isfinite(self.temporal_.scale)):
            return None
        base = z.copy()
        n = self.temporal_.scale.size
        base[:, :n] = self.temporal_.repaired
        out = []
        for k, sigma in enumerate(self.temporal_.scale):
            step = 1e-4 * max(float(np.sqrt(np.mean(base[:, k] ** 2))), np.finfo(float).tiny)
            up, down = base.copy(), base.copy()
            up[:, k] += step
            down[:, k] -= step
            grad = (self.library_.transform(up) - self.library_.transform(down)) / (2 * step)
            out.append(sigma * grad / self.standardizer_.theta_scale)
        return out

    @staticmethod
    def _library_noise(noise, theta_kept) -> tuple[np.ndarray, float]:
        """The library noise (:meth:`_noise_columns`) per column relative to its root
        mean square, and along the least-excited direction of the standardised library
        (see Diagnostics); NaN without the temporal screen, which measures the noise."""
        p = theta_kept.shape[1]
        if noise is None:
            return np.full(p, np.nan), float("nan")
        _, sing, vt = np.linalg.svd(theta_kept, full_matrices=False)
        columns = sum(np.mean(a**2, axis=0) for a in noise)
        along = sum(np.sum((a @ vt.T) ** 2, axis=0) for a in noise)
        rms = np.sqrt(np.mean(theta_kept**2, axis=0))
        columns = np.sqrt(columns) / np.where(rms > 0, rms, 1.0)
        # Exactly degenerate directions (a constant state, duplicated terms) carry no
        # signal to confuse: the condition number of the selected terms reports them.
        ok = sing > 1e-8 * sing[0]
        return columns, float(np.max(np.sqrt(along[ok]) / sing[ok]))

    def _diagnose(self, theta_kept, y_kept, entry_flags, measured: bool) -> Diagnostics:
        """What the fit can and cannot vouch for (see :class:`Diagnostics`)."""
        m, p = self.screened_.size, theta_kept.shape[1]
        cond = np.ones(self.coef_.shape[0])
        for k, row in enumerate(self.coef_):
            keep = row != 0
            if keep.sum() >= 2:
                a = theta_kept[:, keep]
                cond[k] = np.linalg.cond(a / np.maximum(np.linalg.norm(a, axis=0), 1e-300))
        s = self.screening_
        return Diagnostics(
            n_samples=m,
            n_terms=p,
            samples_per_term=float((~self.screened_).sum() / p),
            temporal_flagged_entries=int(entry_flags.sum()),
            temporal_flagged_samples=int(entry_flags.any(axis=1).sum()),
            model_flagged_samples=int((self.screened_ & ~self.unresolved_).sum()),
            readmitted_samples=int((entry_flags.any(axis=1) & ~self.screened_).sum()),
            unresolved_samples=int(self.unresolved_.sum()),
            screening_converged=True if s is None else bool(s.converged),
            screening_restarted=False if s is None else bool(s.restarted),
            flagged_fraction=float(self.screened_.mean()),
            delta_over_scale=(
                np.full(self.coef_.shape[0], np.nan)
                if s is None
                else self.delta_ / (s.scale * self.standardizer_.y_scale)
            ),
            certified=np.asarray(self.result_.column_converged, dtype=bool),
            condition_number=cond,
            library_noise=self.library_noise_allowed_,
            noise_factor=self.noise_factor_.copy(),
            unstable=self._stability(theta_kept, y_kept),
            bias_ratio=self.bias_ratio_.copy(),
            truncation_ratio=self.truncation_ratio_.copy(),
            below_floor=self.below_floor_.copy(),
            bic_margin=(
                self.selection_.margin.copy()
                if self.selection_ is not None and self.selection_.criterion == "bic"
                else np.full(self.coef_.shape[0], np.nan)
            ),
            subset_size=(
                self.selection_.subset_size.copy()
                if self.selection_ is not None
                else np.zeros(self.coef_.shape[0], dtype=int)
            ),
            from_subsets=(
                self.selection_.from_subsets.copy()
                if self.selection_ is not None
                else np.zeros(self.coef_.shape[0], dtype=bool)
            ),
            significance=self.significance_.copy(),
            significance_level=SIGNIFICANCE if measured else SIGNIFICANCE_ESTIMATED,
            pruned=self.pruned_.copy(),
            aliased=[self.get_feature_names()[j] for j in np.flatnonzero(self.aliased_)],
            derivative_half_window=self.derivative_windows_.copy(),
        )

    def _warn(self, d: Diagnostics) -> None:
        for message in d.problems():
            warnings.warn(message, IdentificationWarning, stacklevel=3)

    # ------------------------------------------------------------------ using the model
    def _check_fitted(self, what: str):
        if not hasattr(self, "coef_"):
            raise NotFittedError(f"this HuberSINDy is not fitted yet: call fit before {what}")

    def save(self, path):
        """Write the fitted model to ``path`` as portable JSON (:func:`robust_sindy.io.save_model`;
        read it back with :func:`robust_sindy.load_model`)."""
        from .io import save_model

        return save_model(self, path)

    def export_rhs(self):
        """The identified right-hand side as generated numpy code.

        Returns an :class:`~robust_sindy.export.ExportedRHS`.  ``f = model.export_rhs()``;
        ``f(t, x)`` (or ``f(t, x, u)``) gives the derivatives
        at ``x`` of shape (n,) or (m, n) without the library's per-call overhead, e.g. for
        ``scipy.integrate.solve_ivp(f, ...)``; ``f.source`` is the code, ``f.write(path)``
        saves it as a module that needs only numpy.
        """
        from .export import ExportedRHS

        self._check_fitted("export_rhs")
        n = self.coef_.shape[0]
        return ExportedRHS(
            self.library_, self.coef_, self.feature_names_[:n], self.n_control_features_
        )

    def to_sympy(self) -> list:
        """The right-hand sides as sympy expressions, one per state (needs sympy).

        Symbols are named by the states and controls (``feature_names_``); library
        functions given as Python callables appear as undefined sympy functions.
        """
        from .export import to_sympy

        self._check_fitted("to_sympy")
        return to_sympy(self.library_, self.coef_, self.library_.input_names_)

    def get_feature_names(self) -> list[str]:
        """Names of the library features (columns of ``coef_``)."""
        self._check_fitted("get_feature_names")
        return self.library_.get_feature_names()

    def equations(self, precision: int = 3) -> list[str]:
        """The right-hand sides as text, one per state, zero terms left out."""
        self._check_fitted("equations")
        names = self.get_feature_names()
        out = []
        for row in self.coef_:
            terms = []
            for c, name in zip(row, names, strict=True):
                if c == 0:
                    continue
                val = f"{abs(c):.{precision}f}"
                sign = "-" if c < 0 else "+"
                term = val if name == "1" else f"{val} {name}"
                if not terms:
                    terms.append(term if sign == "+" else f"-{term}")
                else:
                    terms.append(f"{sign} {term}")
            out.append(" ".join(terms) if terms else f"{0:.{precision}f}")
        return out

    def print(self, precision: int = 3) -> None:
        """Print ``(x)' = ...`` for every state."""
        self._check_fitted("print")
        for name, eq in zip(self.feature_names_, self.equations(precision), strict=False):
            print(f"({name})' = {eq}")

    def predict(self, x, u=None):
        """Derivatives predicted by the model at states ``x`` (and controls ``u``).

        A pandas DataFrame ``x`` gives a DataFrame with its index and columns named
        ``(state)'``; arrays give an array.
        """
        self._check_fitted("predict")
        if _is_frame(x):
            frame = x
            u = u.to_numpy(dtype=float) if _is_frame(u) else u
            out = self.predict(frame.to_numpy(dtype=float), u)
            names = self.feature_names_[: self.coef_.shape[0]]
            return type(frame)(out, index=frame.index, columns=[f"({n})'" for n in names])
        x = as_float_array(x, "x", (1, 2))
        x = x[:, None] if x.ndim == 1 else x
        if x.shape[1] != self.coef_.shape[0]:
            raise ValueError(f"x has {x.shape[1]} columns; the model has {self.coef_.shape[0]}")
        if u is not None:
            u = as_float_array(u, "u", (1, 2))
            u = u[:, None] if u.ndim == 1 else u
            if u.shape[0] != x.shape[0]:
                raise ValueError(f"u has {u.shape[0]} samples but x has {x.shape[0]}")
        return self.library_.transform(self._inputs(x, u)) @ self.coef_.T

    def score(self, x, t=None, x_dot=None, u=None) -> float:
        """Coefficient of determination R^2 of the predicted derivatives (averaged)."""
        self._check_fitted("score")
        xs, ts, ds, us = self._trajectories(x, t, x_dot, u, need_t=False)
        if sum(a.shape[0] for a in xs) < 2:
            raise ValueError(
                f"x has {sum(a.shape[0] for a in xs)} samples: a score needs at least 2"
            )
        if ds is None:
            # The derivatives fit would have computed: windows guarded by the library.
            ds = [
                self._differentiate(a, ti, library=self.library_.transform(self._inputs(a, b)))
                for (a, b), ti in zip(_pairs(xs, us), ts, strict=True)
            ]
        pred = np.vstack([self.predict(a, b) for a, b in _pairs(xs, us)])
        y = np.vstack(ds)
        ss_res = ((y - pred) ** 2).sum(axis=0)
        ss_tot = ((y - y.mean(axis=0)) ** 2).sum(axis=0)
        return float(np.mean(1.0 - ss_res / np.where(ss_tot > 0, ss_tot, 1.0)))

    def simulate(self, x0, t, u=None, *, as_frame=None, **integrator_kws):
        """Integrate the identified equations with :func:`scipy.integrate.solve_ivp`.

        ``u`` is a callable of ``t`` or an array sampled on ``t`` (interpolated
        linearly).  ``integrator_kws`` go to ``solve_ivp`` (default ``method="LSODA"``,
        ``rtol=1e-10``, ``atol=1e-10``).  Returns the states at ``t``, shape (len(t), n):
        a pandas DataFrame (index ``t``, columns the state names) when ``as_frame`` is
        true, or by default when ``x0`` is a pandas Series.  The right-hand side
        integrated is :meth:`export_rhs`.
        """
        self._check_fitted("simulate")
        if as_frame is None:
            as_frame = _is_series(x0)
        if _is_series(x0):
            x0 = x0.to_numpy(dtype=float)
        t, x0, uf = simulation_inputs(x0, t, u, self.coef_.shape[0], self.n_control_features_)
        f = self.export_rhs()
        kws = {"method": "LSODA", "rtol": 1e-10, "atol": 1e-10, **integrator_kws}
        sol = integrate(f, x0, t, uf, kws)
        if not sol.success:
            warnings.warn(f"simulate stopped early: {sol.message}", UserWarning, stacklevel=2)
        out = sol.y.T
        if as_frame:
            import pandas as pd

            return pd.DataFrame(out, index=pd.Index(t[: len(out)], name="t"), columns=f.state_names)
        return out


def _equations_with(mask: np.ndarray) -> tuple[np.ndarray, str]:
    """The equations (rows of ``mask``, (n, p)) with any term set, and how many each has."""
    rows = np.flatnonzero(mask.any(axis=1))
    return rows, ", ".join(str(int(c)) for c in mask[rows].sum(axis=1))


def _smallest(values: np.ndarray) -> np.ndarray:
    """Per row the smallest finite value (NaN for a row with none)."""
    finite = np.isfinite(values)
    low = np.min(np.where(finite, values, np.inf), axis=1)
    return np.where(finite.any(axis=1), low, np.nan)


def input_names(names, n: int, q: int) -> list[str]:
    """Names of ``n`` states then ``q`` controls: ``names`` checked, or ``x0.., u0..``."""
    if names is None:
        return [f"x{i}" for i in range(n)] + [f"u{i}" for i in range(q)]
    names = [str(s) for s in names]
    if len(names) != n + q:
        raise ValueError(
            f"feature_names has {len(names)} names but there are {n} states "
            f"and {q} controls: give one name per state, then per control"
        )
    return names


def simulation_inputs(x0, t, u, n: int, q: int):
    """``t``, ``x0`` and the input function of a simulation of ``n`` states and ``q``
    controls, checked (``u`` as :func:`robust_sindy.simulate.input_function` takes it)."""
    t = check_time(t, "t")
    x0 = as_float_array(x0, "x0", (1,))
    if x0.size != n:
        raise ValueError(f"x0 has {x0.size} values; the model has {n} states")
    uf = input_function(u, t)
    if (uf is None) != (q == 0):
        raise ValueError(
            f"u is required: the model was fitted with {q} controls"
            if q
            else "u given, but the model was fitted without controls"
        )
    if uf is not None:
        width = np.size(uf(t[0]))
        if width != q:
            raise ValueError(f"u has {width} columns but the model was fitted with {q}")
    return t, x0, uf


def integrate(f, x0, t, uf, kws: dict):
    """:func:`scipy.integrate.solve_ivp` of an exported right-hand side ``f`` on ``t``."""

    def rhs(s, state):
        # One sample as a batch of one: library callables get 1-D arrays, as in fit.
        return f(s, state[None, :], None if uf is None else uf(s)[None, :])[0]

    return scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), x0, t_eval=t, **kws)


def _check_differentiation(how) -> None:
    if not callable(how) and how not in _DIFFERENTIATION:
        raise ValueError(
            f"differentiation must be one of {tuple(_DIFFERENTIATION)} or a callable; got {how!r}"
        )


def _is_series(obj) -> bool:
    return hasattr(obj, "to_numpy") and hasattr(obj, "index") and not hasattr(obj, "columns")


def _is_frame(obj) -> bool:
    return hasattr(obj, "columns") and hasattr(obj, "to_numpy") and hasattr(obj, "index")


def _frame_times(frame):
    """Seconds from the first sample of a datetime or timedelta index, else None."""
    index = frame.index
    if getattr(index.dtype, "kind", "") not in ("m", "M"):
        return None
    seconds = (index - index[0]).to_numpy().astype("timedelta64[ns]").astype(np.int64) / 1e9
    return np.asarray(seconds, dtype=float)


def _from_frames(x, t, x_dot, u):
    """Values of pandas inputs, the names their columns give, and times from the index."""
    multiple = isinstance(x, (list, tuple))
    xl = list(x) if multiple else [x]
    if not any(_is_frame(a) for a in xl):
        return x, t, x_dot, u, None

    def values(obj):
        if obj is None:
            return None
        if isinstance(obj, (list, tuple)):
            return [a.to_numpy(dtype=float) if _is_frame(a) else a for a in obj]
        return obj.to_numpy(dtype=float) if _is_frame(obj) else obj

    names = [str(c) for c in xl[0].columns] if _is_frame(xl[0]) else None
    for a in xl:
        if _is_frame(a) and names is not None and [str(c) for c in a.columns] != names:
            raise ValueError("x: every DataFrame must have the same columns")
    ul = None if u is None else (list(u) if isinstance(u, (list, tuple)) else [u])
    if names is not None and ul is not None:
        names = names + [str(c) for c in ul[0].columns] if _is_frame(ul[0]) else None
    if t is None:
        times = [_frame_times(a) if _is_frame(a) else None for a in xl]
        if all(ti is not None for ti in times):
            t = times if multiple else times[0]
    return values(x), t, values(x_dot), values(u), names


def _chunk_derivative(block, model, dt, half, noise, check=False):
    """Derivatives of one Dask chunk of states (``block``, with its overlap) as
    ``model`` estimates them in memory (its own temporal screen, the sample's windows
    ``half`` and noise levels ``noise``); with ``check``, instead, its samples whose
    derivatives the sampling does not resolve, repeated across the columns."""
    tb = dt * np.arange(block.shape[0])
    screened, level = None, noise
    if model.screen:
        own = temporal_screen(block, tb)
        screened = (own.repaired, ~own.flags)
        level = own.scale if noise is None else noise
    d, _, loose, _ = model._trajectory_derivative(
        block, tb, screened, level, half=half, check=check
    )
    return np.repeat(loose[:, None], block.shape[1], axis=1) if check else d


def _matching(values, name: str, xs: list, multiple: bool) -> list | None:
    """``values`` as a list of 2-D float arrays, one per trajectory of ``xs``."""
    vs = _as_list(values, name, multiple)
    if vs is None:
        return None
    if len(vs) != len(xs):
        raise ValueError(f"{name} has {len(vs)} trajectories but x has {len(xs)}")
    vs = [as_float_array(a, name, (1, 2)) for a in vs]
    return [a[:, None] if a.ndim == 1 else a for a in vs]


def _pairs(xs, us):
    return zip(xs, [None] * len(xs) if us is None else us, strict=True)


def _slices(lengths) -> list[slice]:
    edges = np.cumsum([0, *lengths])
    return [slice(a, b) for a, b in itertools.pairwise(edges)]


def _segments(xs) -> list[slice]:
    """Each trajectory's slice of the stacked samples."""
    return _slices(len(a) for a in xs)


def _segments_of(keep: np.ndarray, xs) -> list[slice]:
    """The trajectories' slices among the kept samples."""
    return _slices(int(keep[seg].sum()) for seg in _segments(xs))


def _is_robust(value) -> bool:
    return isinstance(value, str) and value == "robust"


def _is_auto(value) -> bool:
    return isinstance(value, str) and value == "auto"
