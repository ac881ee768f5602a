"""What a fitted model can and cannot vouch for: its diagnostics and their warnings.

:class:`Diagnostics` gathers what every stage of :class:`~robust_sindy.HuberSINDy`
measured about the data and the fit; :data:`RULES` is the table of reasons to doubt a
model, each a (kind, condition, message) rule that reads the diagnostics; a fit raises
one :class:`IdentificationWarning` per rule that applies.  :func:`diagnose` is the
stage that computes the diagnostics from the other stages' outcomes.

Read more in the user guide: :doc:`/guide/diagnostics`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .core.losses import huber_psi
from .core.statistics import correlation_time
from .fitting import fit
from .selection.bias import (
    BIAS_MARGIN,
    carried_noise,
    library_noise,
    residual_noise_factor,
    state_noise_factors,
)
from .selection.criteria import MIN_BIC_MARGIN, blocked_folds
from .selection.forecast import FORECAST_EVIDENCE, FORECAST_LEANING
from .selection.lam_path import pilot_budget
from .selection.refit import one_step_contributions
from .selection.significance import SIGNIFICANCE, SIGNIFICANCE_ESTIMATED, VISIBLE, robust_t
from .selection.variables import KEEP_EVIDENCE

__all__ = [
    "MAX_CONDITION",
    "MAX_FLAGGED_FRACTION",
    "MAX_LEFT_OUT",
    "MAX_LIBRARY_NOISE",
    "RULES",
    "SEARCH_SAMPLES_FACTOR",
    "STABILITY_BLOCKS",
    "STABILITY_TOLERANCE",
    "Diagnostics",
    "IdentificationWarning",
    "Rule",
    "count_kinds",
    "diagnose",
    "kind_of",
    "samples_needed",
    "warn",
]

#: More flagged samples than this fraction and the screen's verdict is doubtful (and
#: more samples with unresolved derivatives than this, the sampling is too coarse).
MAX_FLAGGED_FRACTION = 0.3
#: More samples left out in all (outliers and unresolved derivatives) than this
#: fraction, and what is left may not represent the trajectory.
MAX_LEFT_OUT = 0.5
#: The selection is doubtful where an equation's kept samples hold fewer independent
#: ones (their count over the correlation time of the reported model's residuals) than
#: ``SEARCH_SAMPLES_FACTOR * k * log(p - k)`` for its k selected terms among the p of
#: the library: below that sample count an L1 path fails to find the k terms of the
#: truth among p with high probability when the library's columns are independent
#: Gaussian (the sharp threshold of Wainwright 2009, IEEE Trans. Inf. Theory 55:2183,
#: is 2; the case whose threshold is known exactly); libraries of correlated monomials
#: generally need more.  A count of samples per library term alone does not decide it:
#: a sparse model is found among many terms from few samples per term where its terms
#: are few.
SEARCH_SAMPLES_FACTOR = 2.0
#: Condition number of the selected terms (unit-norm columns) beyond which their
#: coefficients are not identifiable from the data.
MAX_CONDITION = 1e6
#: Stability check: the kept samples are cut into this many contiguous blocks in time
#: and the selected terms refitted with each block left out; a term is unstable when a
#: refit changes its sign or moves it by more than ``STABILITY_TOLERANCE`` of its value.
STABILITY_BLOCKS = 4
STABILITY_TOLERANCE = 0.5
#: Noise of the library (the states' noise carried through it) relative to its signal
#: along its least-excited direction beyond which the errors in the variables decide
#: which terms are selected.
MAX_LIBRARY_NOISE = 0.15


class IdentificationWarning(UserWarning):
    """The data cannot vouch for the identified model (see ``HuberSINDy.diagnostics_``).

    ``kind`` names the rule of :data:`RULES` that raised it, or the check made
    elsewhere: ``"few independent rows"`` (``formulation="weak"`` asked for on rows that
    hold no more independent rows than the library has terms, said before the fit),
    ``"out of core"`` (the out-of-core refit); None otherwise.
    """

    def __init__(self, message: str, kind: str | None = None):
        super().__init__(message)
        self.kind = kind


@dataclass(repr=False)
class Diagnostics:
    """What a fitted :class:`HuberSINDy` can and cannot vouch for.

    Attributes
    ----------
    n_samples, n_terms : int
        Samples (all trajectories) and library terms.
    samples_per_term : float
        Samples kept after screening per library term.
    independent_samples : ndarray, shape (n,)
        Per equation, the kept samples (the weak form: test functions) over the
        correlation time of the reported model's residuals: the independent samples
        they hold.
    samples_needed : ndarray, shape (n,)
        Per equation, the independent samples an L1 path needs to find its selected
        terms among the library's in a library of independent columns
        (:func:`samples_needed`).
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
    support_noise : ndarray (n,)
        The same for each equation's selected terms only (NaN for an empty equation):
        above ``MAX_LIBRARY_NOISE`` a warning says that the selected terms cannot be
        told apart.  The whole library's weakest direction is noisy in most large
        libraries with noisy states; whether that cost a term is what ``below_floor``,
        ``bias_ratio`` and ``pruned`` report.
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
        contiguous blocks of the kept samples is left out of the refit: they rest on part
        of the record (a spurious term, a true one the rest barely excites, or terms only
        a transient tells apart).  A note of the report where a significance test judged
        the terms (``significance`` computed), a warning where none did (a given
        ``lam``).
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
        ``selection_tol`` (and the noise of the term's own column) and the noise floor
        ``selection_tol_`` that the noisiest column raised it to: the floor, not the
        data, left them out, so they may be real (a warning says so); NaN for every
        other term.
    bic_margin : ndarray (n,)
        Per equation, how much higher the BIC of the best other candidate support
        scored than the chosen one (``Selection.margin``); ``inf`` when there is no
        other, NaN with a fixed ``lam`` or ``criterion="cv"``.  Below
        ``MIN_BIC_MARGIN`` the data do not strongly prefer the chosen support.  With
        ``constraints``, over the supports the search under them refitted
        (``constrained_.candidates``, their criterion summed over the equations): those
        whose support differs in the equation
        (:meth:`~robust_sindy.selection.constrained.ConstrainedRefit.margins`).
    selected_terms : ndarray of int (n,)
        Terms selected per equation; an equation without any is warned about.
    constraint_residual : float
        With ``constraints``, their largest relative residual at the coefficients (NaN
        without); a warning says so above 1e-8, or when the constrained refit was not
        certified (``constraints_certified``).
    constraints_certified : bool
    constraints_status : str
        The constrained refit's solver status (why it was not certified, when it was
        not).
    constrained_delta : ndarray (n,)
        With ``constraints``, the Huber threshold of the model under them (measured on
        the residuals of the constrained fit on every term; NaN without).
    repaired_rows : int
        Kept samples fitted with the library row of their repaired readings (the row
        screen's step 5: a glitch costs its entry, not its sample).
    energy_residual : float
        For a model of degree at most 2 in the states (polynomial library, no control
        in a selected term), the largest cubic coefficient of ``x^T Q(x)`` over the
        largest quadratic one (0: the quadratic part conserves energy); NaN otherwise
        (:mod:`robust_sindy.selection.stability`).
    trapping_eigenvalue : float
        For an energy-preserving quadratic part, the smallest over the centres ``m`` of
        the largest eigenvalue of ``sym(L + J_Q(m))``: negative certifies a trapping
        region (every trajectory of the model stays bounded; Schlegel & Noack 2015),
        otherwise this test cannot decide; NaN where it does not apply.
    pilot_relative_scale : ndarray (n,)
        The row screen's robust residual scale of the unpenalised fit of the whole
        library over the root mean square of each equation's target (NaN without the
        screen): how much of the target no combination of the terms explains.
    rival_margin : ndarray (n,)
        The same over the candidates that are another model than the one reported:
        they leave out one of its terms, or change one of its coefficients by more than
        half (``Selection.rival_margin_to``; ``Selection.rival_margin`` judges them
        against the selection's own choice, before the final selection dropped terms
        from it).  Below ``MIN_BIC_MARGIN`` a warning says that the
        data do not strongly prefer the chosen model.  A close candidate that only adds
        a term to the chosen ones, which keep their values, is not warned about on its
        own: whether terms are missing is what ``below_floor``, ``bias_ratio`` and
        ``pruned`` report.  For an equation whose support the weak form's rescoring
        replaced (``errors_in_variables``), the margin is that of the rescoring's score
        (chi-square under the noise the terms carry plus ``log(rows)`` per term) over
        the supports it fitted; where it kept the support and the noise explains its
        chi-square, the smaller of the two margins (``rival_by_noise`` says which
        equations' margin is the rescoring's).  With ``constraints``, over the search's
        candidates, as ``bic_margin``.
    rival_by_noise : ndarray of bool (n,)
        Equations whose ``rival_margin`` is that of the weak form's score under the
        noise the terms carry.
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
        data (a warning says so).  With ``constraints``, the statistic of the model
        under them, at its ``constrained_delta``, in the directions the constraints
        leave free (:func:`~robust_sindy.selection.constrained.constrained_significance`;
        ``inf`` for a coefficient they fix).
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
        ``VISIBLE`` (2) or more may be real: a warning says so.  With ``constraints``,
        a term the search under them put back in the model is not dropped (NaN), and
        the terms their own significance rounds left out are added
        (``constrained_.pruned``).
    added : ndarray (n, p)
        The robust score t of each term the sparse selection left out that the final
        selection put back (the largest per equation at ``SIGNIFICANCE`` (5) or more,
        kept where its drops and pruning keep it:
        :func:`~robust_sindy.selection.final.missed_terms`); NaN for every other term.
    derivative_half_window : ndarray of int (n_states,)
        Half width, in samples, of the local quartic that estimated each state's
        derivative (chosen from the data by
        :func:`~robust_sindy.timeseries.differentiation.choose_half_window`; the widest over the
        trajectories); 0 where the derivatives were measured or came from another
        ``differentiation``.
    aliased : list of str
        Library terms left out of the selection because they are exact linear
        combinations of earlier terms on the kept samples (a state that does not move,
        an exactly conserved quantity:
        :func:`robust_sindy.selection.aliasing.aliased_columns`); an equation written
        with them fits equally well, so a warning names them.
    formulation : {"strong", "weak"}
        The regression's rows: samples (derivatives measured or estimated), or test
        functions of the weak form (:mod:`robust_sindy.timeseries.weak`); with the weak
        form the counts of the row screen are of test functions.
    support_half_width : float
        The weak form's half width of the test functions (time units); NaN otherwise.
    n_rows : int
        The weak form's test functions (0 otherwise).
    formulation_reason : str
        Which formulation was used, and why.
    formulation_contest : dict
        Where outliers kept the strong form and the weak form's model selected other
        terms: the two models' forecasts of the record compared
        (:func:`robust_sindy.selection.forecast.forecast_contest`): ``horizon``,
        ``windows``, ``wins`` and ``losses`` (of the weak form's model), ``p_value``,
        ``equations`` (those whose terms differ) and ``chosen``; empty otherwise.
    errors_in_variables : ndarray of int (n,)
        With the weak form, per equation: 1 where the support was replaced by one that
        scored better under the noise its own terms carry
        (:mod:`robust_sindy.selection.variables`), 0 where the chosen support stayed,
        -1 where the score was not computed (the strong form, no measured noise).
    dropped_evidence : ndarray (n,)
        With the weak form, per equation from whose support the final selection dropped
        terms (below the significance bar, under the noise floor or within their
        errors-in-variables bias): the most that putting one of them back lowers the
        score the rescoring chose the support by, where the states' noise explains the
        residuals of both supports compared (the fall in units of the residuals' spread
        where that exceeds the noise model's, less the extended BIC's penalty for the
        library's size: :func:`~robust_sindy.selection.variables.dropped_evidence`);
        NaN elsewhere.
        Above ``KEEP_EVIDENCE`` (10, "very strong" evidence) the data prefer that term,
        which may be real: a warning says so.
    missing_states : ndarray of int (n_states,)
        Missing readings (NaN) of each state, filled by the temporal screen's local fits
        (:mod:`robust_sindy.timeseries.missing`).
    missing_in_gaps : int
        Of those, the entries in gaps wider than the screen's half window: their
        samples were suspects of the row screen.
    missing_far_samples : int
        Samples at which some state or control was missing with no reading within half
        of ``GAP_STEPS`` median steps (:func:`~robust_sindy.timeseries.missing.far_from_readings`):
        not filled into the fit (left out of the strong form's rows; under no test
        function of the weak form, which they split as a gap in the record does).
    missing_controls : int
        Missing readings of the controls (filled the same way; their samples suspects).
    missing_derivative_samples : int
        Samples left out because a measured derivative was missing.
    temporal_flagged_left_out : int
        Entries flagged by the temporal screen in the samples the row screen left out
        (the strong form; all flagged entries with the weak form).
    record_samples : int
        The samples of the records (the weak form's ``n_samples`` counts its test
        functions; 0: ``n_samples``).
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
    formulation: str = "strong"
    support_half_width: float = float("nan")
    n_rows: int = 0
    formulation_reason: str = ""
    formulation_contest: dict = field(default_factory=dict)
    errors_in_variables: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    missing_states: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    missing_in_gaps: int = 0
    missing_far_samples: int = 0
    missing_controls: int = 0
    missing_derivative_samples: int = 0
    temporal_flagged_left_out: int = 0
    support_noise: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rival_margin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rival_by_noise: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    pilot_relative_scale: np.ndarray = field(default_factory=lambda: np.zeros(0))
    selected_terms: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    constraint_residual: float = float("nan")
    constraints_certified: bool = True
    constraints_status: str = ""
    constrained_delta: np.ndarray = None
    energy_residual: float = float("nan")
    trapping_eigenvalue: float = float("nan")
    dropped_evidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    repaired_rows: int = 0
    record_samples: int = 0
    independent_samples: np.ndarray = field(default_factory=lambda: np.zeros(0))
    samples_needed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    added: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def weak(self) -> np.ndarray:
        """Selected terms within ``significance_level`` robust standard errors of zero
        (n, p)."""
        return np.nan_to_num(self.significance, nan=np.inf) < self.significance_level

    def problems(self) -> list[str]:
        """One sentence for each reason to doubt the model (empty when there is none)."""
        return [message for _, message in self.findings()]

    def findings(self) -> list[tuple[str, str]]:
        """``(kind, sentence)`` for each rule of :data:`RULES` that applies and warns."""
        return self._apply(warns=True)

    def notes(self) -> list[tuple[str, str]]:
        """``(kind, sentence)`` for each rule of :data:`RULES` that applies and only
        informs (what the noise decided on most answers from noisy states, right ones
        included: reported, not warned)."""
        return self._apply(warns=False)

    def _apply(self, warns: bool) -> list[tuple[str, str]]:
        out = []
        for rule in RULES:
            if rule.warns != warns:
                continue
            evidence = rule.condition(self)
            if evidence is not None and evidence is not False:
                out.append((rule.kind, rule.message(self, evidence)))
        return out

    def __repr__(self) -> str:
        lines = [
            f"Diagnostics({self.n_samples} samples, {self.n_terms} terms, "
            f"{self.samples_per_term:.1f} kept samples per term)",
            f"  temporal screen: {self.temporal_flagged_entries} entries in "
            f"{self.temporal_flagged_samples} samples",
            f"  model screen: {self.model_flagged_samples} samples left out, "
            f"{self.readmitted_samples} readmitted, {self.repaired_rows} fitted with their "
            f"repaired readings, converged={self.screening_converged}"
            + (", restarted" if self.screening_restarted else ""),
            f"  unresolved derivatives: {self.unresolved_samples} samples left out",
            f"  left out in all: {100 * self.flagged_fraction:.1f} %",
            "  independent samples per equation: "
            + np.array2string(self.independent_samples, precision=0, floatmode="fixed")
            + "; needed for the selected terms' search: "
            + np.array2string(self.samples_needed, precision=0, floatmode="fixed"),
            f"  certified: {self.certified.tolist()}",
            f"  condition numbers: {np.array2string(self.condition_number, precision=2)}",
            f"  library noise along its weakest direction: {self.library_noise:.2g}; "
            "along the selected terms' per equation: "
            + np.array2string(self.support_noise, formatter={"float_kind": "{:.2g}".format}),
            "  share of the measured state noise the residuals allow: "
            + np.array2string(self.noise_factor, formatter={"float_kind": "{:.2g}".format}),
            f"  unstable terms per equation: {self.unstable.sum(axis=1).tolist()}",
            "  terms dropped as errors-in-variables bias per equation: "
            f"{np.isfinite(self.bias_ratio).sum(axis=1).tolist()}",
            "  terms dropped as derivative truncation bias per equation: "
            f"{np.isfinite(self.truncation_ratio).sum(axis=1).tolist()}",
            "  terms left out below the noise floor per equation: "
            f"{np.isfinite(self.below_floor).sum(axis=1).tolist()}",
            f"  BIC margin to the next support: {np.array2string(self.bic_margin, precision=3)}"
            "; to the next other model: "
            + np.array2string(self.rival_margin, precision=3)
            + (
                " (for equations "
                f"{np.flatnonzero(self.rival_by_noise).tolist()}: the score under the noise "
                "their terms carry)"
                if self.rival_by_noise.any()
                else ""
            ),
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
            "  terms put back by their score t per equation: "
            f"{np.isfinite(self.added).sum(axis=1).tolist() if self.added.size else 'none'}",
            "  the weak form's score against the final selection's drops: "
            + (
                np.array2string(self.dropped_evidence, precision=3)
                if np.isfinite(self.dropped_evidence).any()
                else "no drops scored"
            ),
            f"  aliased terms left out: {', '.join(self.aliased) or 'none'}",
            f"  formulation: {self.formulation_reason or self.formulation}",
            "  supports replaced under the noise their terms carry (weak form): "
            + (
                f"equations {np.flatnonzero(self.errors_in_variables == 1).tolist()}"
                if np.any(self.errors_in_variables == 1)
                else "none"
                if np.any(self.errors_in_variables == 0)
                else "not scored"
            ),
            "  missing readings: "
            + (
                f"states {self.missing_states.tolist()} (filled by local fits; "
                f"{self.missing_in_gaps} in gaps wider than the screen's window; "
                f"{self.missing_far_samples} samples too far from a reading to fill, left "
                "out), controls "
                f"{self.missing_controls}, samples without a measured derivative "
                f"{self.missing_derivative_samples} (left out)"
                if self.missing_states.sum()
                + self.missing_controls
                + self.missing_derivative_samples
                else "none"
            ),
            "  derivatives: "
            + (
                f"none (weak form: {self.n_rows} test functions of half width "
                f"{self.support_half_width:.3g} in time; the counts above are of them)"
                if self.formulation == "weak"
                else "local quartics, half windows per state "
                f"{self.derivative_half_window.tolist()} samples"
                if self.derivative_half_window.any()
                else "measured (or another differentiation)"
            ),
        ]
        if np.isfinite(self.energy_residual):
            lines.append(
                "  quadratic part: "
                + (
                    "energy-preserving; "
                    + (
                        "bounded (trapping region: largest eigenvalue "
                        f"{self.trapping_eigenvalue:.3g} < 0)"
                        if self.trapping_eigenvalue < 0
                        else "the trapping-region test cannot decide (largest eigenvalue "
                        f"{self.trapping_eigenvalue:.3g})"
                    )
                    if self.energy_residual <= 1e-8
                    else f"not energy-preserving (relative residual {self.energy_residual:.2g})"
                )
            )
        if np.isfinite(self.constraint_residual):
            lines.append(
                f"  constraints: relative residual {self.constraint_residual:.1e}, refit "
                + ("certified" if self.constraints_certified else "not certified")
                + ", delta "
                + np.array2string(
                    self.constrained_delta, formatter={"float_kind": lambda v: f"{v:.3g}"}
                )
            )
        problems = self.problems()
        lines += [f"  problem: {p}" for p in problems] if problems else ["  no problem found"]
        lines += [f"  note: {message}" for _, message in self.notes()]
        return "\n".join(lines)


def _equations_with(mask: np.ndarray) -> tuple[np.ndarray, str] | None:
    """The equations (rows of ``mask``, (n, p)) with any term set, and how many each
    has; None when there is none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    return rows, ", ".join(str(int(c)) for c in mask[rows].sum(axis=1))


def _smallest(values: np.ndarray) -> np.ndarray:
    """Per row the smallest finite value (NaN for a row with none)."""
    finite = np.isfinite(values)
    low = np.min(np.where(finite, values, np.inf), axis=1)
    return np.where(finite.any(axis=1), low, np.nan)


@dataclass(frozen=True)
class Rule:
    """A reason to doubt a model: ``condition(diagnostics)`` returns the evidence (None
    or False when the rule does not apply) and ``message(diagnostics, evidence)`` the
    sentence that says so; ``warns`` False for a rule that only informs (a note of the
    report, not a warning)."""

    kind: str
    condition: Callable
    message: Callable
    warns: bool = True


def _outliers(d) -> float:
    """The share of the data found corrupt, counted where the corruption is: the share
    of the entries flagged in time in the samples left out (a glitch in one channel
    costs its sample's row, so with many channels most samples may be left out over a
    few bad entries each), or the share of the samples left out with no flagged entry
    (whole rows the library cannot describe), whichever is larger."""
    n = max(d.n_samples, 1)
    # Flagged entries whose samples the row screen readmitted were not outliers (a fast
    # excursion the local fits cannot follow): only those left out count.
    # The entries are the records' (the weak form's n_samples counts its test functions).
    readings = max(d.record_samples or n, 1) * max(d.derivative_half_window.size, 1)
    entries = d.temporal_flagged_left_out / readings
    out = d.flagged_fraction - d.unresolved_samples / n
    if d.formulation == "weak":  # the counts are of test functions, not of samples
        return max(entries, out)
    # The samples the model screen left out (not those without a target or too far from
    # a reading to fill: they are not outliers), less those with a flagged entry.
    dropped_flagged = d.temporal_flagged_samples - d.readmitted_samples
    return max(entries, (d.model_flagged_samples - dropped_flagged) / n)


def _absent(d) -> str:
    """The samples left out for what was not measured, as the warning on samples left
    out names them (the strong form's counts; empty where none)."""
    if d.formulation == "weak":
        return ""
    n = max(d.n_samples, 1)
    parts = []
    if d.missing_far_samples:
        parts.append(f"{100 * d.missing_far_samples / n:.0f} % too far from a reading to fill")
    if d.missing_derivative_samples:
        parts.append(f"{100 * d.missing_derivative_samples / n:.0f} % without a measured x_dot")
    return "".join(", " + part for part in parts)


def _unresolved(d) -> float:
    return d.unresolved_samples / max(d.n_samples, 1)


def _bias_rule(kind: str, attribute: str, source: str, advice: str, warns: bool = True) -> Rule:
    return Rule(
        kind,
        lambda d: _equations_with(np.nan_to_num(getattr(d, attribute)) >= 1.0),
        lambda d, e: (
            f"equations {e[0].tolist()}: {e[1]} terms were dropped because they lie within "
            f"{BIAS_MARGIN:g} times the bias that {source}, yet exceed that bias: they may "
            f"be real, and these data cannot decide (see diagnostics_.{attribute}); "
            f"{advice} would"
        ),
        warns=warns,
    )


def _weak_message(d, e) -> str:
    rows, counts = e
    low = ", ".join(f"{v:.2g}" for v in _smallest(d.significance)[rows])
    return (
        f"equations {rows.tolist()}: {counts} selected terms are within "
        f"{d.significance_level:g} standard errors of zero (smallest robust t "
        f"{low}): the data do not vouch for them"
        + (
            ""
            if d.significance_level <= SIGNIFICANCE
            else f" (the bar is {d.significance_level:g}, not {SIGNIFICANCE:g}, "
            "because the statistic leaves out the error of estimated derivatives)"
        )
        + "; see diagnostics_.significance, and try more data or measured derivatives"
    )


def _contested(d) -> np.ndarray | None:
    """The equations whose final-selection drops the weak form's score contests."""
    over = np.flatnonzero(np.nan_to_num(d.dropped_evidence, nan=-np.inf) > KEEP_EVIDENCE)
    return over if over.size else None


def _unstable(d, judged: bool):
    """The equations with unstable terms (``_equations_with``) among those whose
    selected terms a significance test judged (their robust t computed: the automatic
    selection, or a search under constraints) when ``judged``, among the others (a
    given ``lam``) otherwise."""
    sig = d.significance
    tested = (
        np.isfinite(sig).any(axis=1)
        if sig.shape == d.unstable.shape
        else np.zeros(d.unstable.shape[0], dtype=bool)
    )
    return _equations_with(d.unstable & (tested == judged)[:, None])


def _unstable_rule(judged: bool, reading: str) -> Rule:
    """The stability check's rule for the equations whose terms a significance test
    judged (a note) or did not (a warning): ``reading`` says what it means there."""
    return Rule(
        "unstable terms",
        lambda d: _unstable(d, judged),
        lambda d, e: (
            f"equations {e[0].tolist()}: {e[1]} selected terms change sign or by more "
            f"than {100 * STABILITY_TOLERANCE:.0f} % when a quarter of the data is left "
            f"out{reading}"
        ),
        warns=not judged,
    )


def _pruned_message(d, e) -> str:
    seen, counts = e
    advice = "measured derivatives, " if d.significance_level > SIGNIFICANCE else ""
    high = ", ".join(f"{v:.2g}" for v in np.nanmax(d.pruned[seen], axis=1))
    return (
        f"equations {seen.tolist()}: {counts} selected terms were dropped because "
        f"their robust t was below {d.significance_level:g} (the bar for the "
        f"selected terms), yet at least {VISIBLE:g} (largest {high}): they may be "
        f"real, and these data cannot decide (see diagnostics_.pruned); {advice}"
        "more data or less noisy states would"
    )


def samples_needed(selected, n_terms: int) -> np.ndarray:
    """The independent samples an L1 path needs to find ``selected`` terms (k per
    equation) among ``n_terms`` (p) in a library of independent columns:
    ``SEARCH_SAMPLES_FACTOR * k * log(p - k)``, and at least k (0 for an empty
    equation; see :data:`SEARCH_SAMPLES_FACTOR`)."""
    k = np.asarray(selected, dtype=float)
    spare = np.maximum(n_terms - k, 1.0)
    return np.where(k > 0, np.maximum(SEARCH_SAMPLES_FACTOR * k * np.log(spare), k), 0.0)


def _short_search(d) -> np.ndarray | None:
    """The equations whose kept samples hold fewer independent ones than their
    selected terms' search needs."""
    if d.independent_samples.size == 0:
        return None
    rows = np.flatnonzero(d.independent_samples < d.samples_needed)
    return rows if rows.size else None


def _join(values, spec: str) -> str:
    return ", ".join(format(v, spec) for v in np.asarray(values).tolist())


#: The reasons to doubt a model, in the order their warnings are raised.
RULES: tuple[Rule, ...] = (
    Rule(
        "fewer samples than terms",
        lambda d: d.samples_per_term <= 1,
        lambda d, _: (
            f"only {d.samples_per_term:.2f} samples per library term were fitted: the "
            "fits on every term that the screens and the selection rest on are "
            "underdetermined, and the selected terms are not reliable; use more data or "
            "a smaller library"
        ),
    ),
    Rule(
        "few samples for the search",
        lambda d: _short_search(d),
        lambda d, e: (
            f"equations {e.tolist()}: the kept samples hold about "
            f"{_join(d.independent_samples[e], '.0f')} independent ones (over the "
            "correlation time of the residuals), fewer than the "
            f"{_join(d.samples_needed[e], '.0f')} that an L1 search for "
            f"{_join(d.selected_terms[e], 'd')} terms among {d.n_terms} needs in a "
            f"library of independent columns ({SEARCH_SAMPLES_FACTOR:g} k log(p - k); "
            "correlated terms need more): the selected terms are not reliable; use "
            "more data or a smaller library"
        ),
    ),
    Rule(
        "screen not converged",
        lambda d: not d.screening_converged,
        lambda d, _: (
            "the model-based screen did not converge (its flags kept changing): the "
            "samples left out may be wrong; inspect screened_ and screening_"
        ),
    ),
    Rule(
        "many outliers",
        lambda d: _outliers(d) > MAX_FLAGGED_FRACTION,
        lambda d, _: (
            f"{100 * _outliers(d):.0f} % of the data were flagged as outliers (of the "
            "entries, or of the samples without a flagged entry): either the data are "
            "mostly corrupted or the library cannot describe them; check the library and "
            "the data (screened_, temporal_.flags)"
        ),
    ),
    Rule(
        "unresolved derivatives",
        lambda d: _unresolved(d) > MAX_FLAGGED_FRACTION,
        lambda d, _: (
            f"at {100 * _unresolved(d):.0f} % of the samples the estimated derivatives are "
            "not resolved: they differ from those of a higher-order local fit by more "
            "than the noise explains (a trajectory sampled too coarsely for its fastest "
            "excursions, or errors in the states the temporal screen left unflagged); "
            "they were left out (unresolved_); sample faster, measure x_dot, or check "
            "the states"
        ),
    ),
    Rule(
        "many samples left out",
        lambda d: (
            max(_outliers(d), _unresolved(d)) <= MAX_FLAGGED_FRACTION
            and d.flagged_fraction > MAX_LEFT_OUT
        ),
        lambda d, _: (
            f"{100 * d.flagged_fraction:.0f} % of the samples were left out of the "
            f"fit ({100 * _outliers(d):.0f} % flagged as outliers, "
            f"{100 * _unresolved(d):.0f} % with unresolved derivatives{_absent(d)}): what "
            "is left may "
            "not excite every term; check the data (screened_, unresolved_), and measure "
            "x_dot or sample faster"
        ),
    ),
    Rule(
        "aliased terms",
        lambda d: bool(d.aliased),
        lambda d, _: (
            f"the library terms {', '.join(d.aliased)} are exact linear combinations "
            "of earlier terms on these data (a state that does not move, or an exactly "
            "conserved quantity): they were left out of the selection, and the data "
            "cannot tell an equation written with them from the one found; see "
            "diagnostics_.aliased, and vary that state if its terms matter"
        ),
    ),
    Rule(
        "not certified",
        lambda d: not d.certified.all(),
        lambda d, _: (
            f"equations {np.flatnonzero(~d.certified).tolist()} were not certified "
            "optimal (see result_)"
        ),
    ),
    Rule(
        "constraints not met",
        lambda d: (not d.constraints_certified) or d.constraint_residual > 1e-8,
        lambda d, _: (
            f"the constrained refit was {'' if d.constraints_certified else 'not '}"
            f"certified"
            + ("" if d.constraints_certified else f" ({d.constraints_status})")
            + f" and the constraints' relative residual is {d.constraint_residual:.1e}"
            ": check that the constraints can be met by the selected terms and those tied "
            "to them (see constrained_ and robust_sindy.selection.constrained)"
        ),
    ),
    Rule(
        "empty equations",
        lambda d: np.flatnonzero(d.selected_terms == 0).tolist() or None,
        lambda d, empty: (
            f"equations {empty} have no term: the data vouch for no library term in them"
            + (
                " (an unpenalised fit of the whole library leaves "
                + ", ".join(f"{100 * v:.0f} %" for v in d.pilot_relative_scale[empty])
                + " of their root mean square)"
                if np.isfinite(d.pilot_relative_scale[empty]).all()
                else ""
            )
            + ": the library does not describe these states' motion, or the noise hides "
            "it. Use less noisy states, more data, measured derivatives or another library"
        ),
    ),
    Rule(
        "collinear terms",
        lambda d: np.flatnonzero(d.condition_number > MAX_CONDITION).tolist() or None,
        lambda d, bad: (
            f"equations {bad}: the selected terms are nearly collinear on this data "
            "(condition numbers "
            + ", ".join(f"{c:.1e}" for c in d.condition_number[bad])
            + "); their coefficients are not identifiable from it. Use a longer or more "
            "exciting trajectory"
        ),
    ),
    Rule(
        "noisy library",
        lambda d: (
            np.flatnonzero(np.nan_to_num(d.support_noise) > MAX_LIBRARY_NOISE).tolist() or None
        ),
        lambda d, bad: (
            f"equations {bad}: the noise of the states, carried through the selected "
            "terms, is "
            + ", ".join(f"{100 * v:.0f} %" for v in d.support_noise[bad])
            + " of their signal along their least-excited direction: terms that differ "
            "along it cannot be told apart (errors in the variables, which measured "
            "derivatives do not remove), so the support and coefficients may be wrong. "
            "Use less noisy states, a longer or more exciting trajectory, or a smaller "
            "library"
        ),
    ),
    _unstable_rule(
        False,
        ", and no significance test judged them: the support is not reliably identified "
        "from these data (noise too large for the library, or terms the trajectory barely "
        "excites); see diagnostics_.unstable, and try more data, measured derivatives, a "
        "smaller library or lam='auto'",
    ),
    # A note where the significance rounds judged the terms: there it fired alone only
    # on right answers (23: the zoo and held-out zoo, a Hopf transient at 8 % noise,
    # mean-field records mostly on their limit cycle), and every one of the 18 wrong
    # answers it fired on had other warnings (see the diagnostics guide).
    _unstable_rule(
        True,
        ": they rest on part of the record (a transient that tells them apart, terms the "
        "rest barely excites, or noise too large for the library); see "
        "diagnostics_.unstable; more data, measured derivatives or a smaller library "
        "would firm them up",
    ),
    _bias_rule(
        "errors-in-variables drops",
        "bias_ratio",
        "the noise of the states gives them through the other terms (errors in the variables)",
        "less noisy states, a longer trajectory or a smaller library",
    ),
    _bias_rule(
        "truncation drops",
        "truncation_ratio",
        "the truncation error of the estimated derivatives gives them (measured against "
        "derivatives of higher order: the sampling does not fully resolve the "
        "trajectory)",
        "faster sampling or measured derivatives",
        # A note: alone, it fired only on right answers (46 of 46 over the zoo, the
        # held-out zoo and coarsely sampled flows, from the states); where the answer
        # was wrong, other rules warned (see the diagnostics guide).
        warns=False,
    ),
    Rule(
        "below the noise floor",
        lambda d: _equations_with(np.isfinite(d.below_floor)),
        lambda d, e: (
            f"equations {e[0].tolist()}: {e[1]} terms left out would contribute more "
            "than selection_tol but less than the noise of the library columns "
            "(selection_tol_): the noise, not the data, decided them, and they may be "
            "real (see diagnostics_.below_floor); less noisy states or a smaller "
            "library would decide"
        ),
        warns=False,
    ),
    Rule("weak terms", lambda d: _equations_with(d.weak), _weak_message),
    Rule(
        "formulations disagree",
        lambda d: (
            d.formulation_contest
            if d.formulation_contest.get("chosen") == "strong"
            and d.formulation_contest["p_value"] <= FORECAST_LEANING
            else None
        ),
        lambda d, c: (
            f"the weak form's model selects other terms in {c['equations']} and forecasts "
            f"the record better in {c['wins']} of {c['wins'] + c['losses']} windows (sign "
            f"test p = {c['p_value']:.2g}): short of the {FORECAST_EVIDENCE:g} that would "
            "take it, but the record does not confirm the strong form's terms either "
            "(see diagnostics_.formulation_contest); fit formulation='weak' to see the "
            "other model, and try more data or less noisy states"
        ),
    ),
    Rule(
        "drops the score contests",
        _contested,
        lambda d, e: (
            f"equations {e.tolist()}: the final selection dropped a term (below the "
            "significance bar, under the noise floor or within its errors-in-variables "
            "bias) that the weak form's score under the noise the terms carry prefers to "
            "keep, by "
            + ", ".join(f"{v:.3g}" for v in d.dropped_evidence[e])
            + f" (more than {KEEP_EVIDENCE:g}): it may be real and missing from the "
            "model (see diagnostics_.dropped_evidence, pruned and bias_ratio); less noisy "
            "states or more data would decide"
        ),
    ),
    Rule(
        "pruned terms",
        lambda d: _equations_with(np.nan_to_num(d.pruned) >= VISIBLE),
        _pruned_message,
    ),
    Rule(
        "close runner-up",
        lambda d: np.flatnonzero(d.rival_margin < MIN_BIC_MARGIN).tolist() or None,
        lambda d, close: (
            f"equations {close}: another model (without some of the reported terms, or "
            "with one of their coefficients changed by more than half) scored within "
            f"{MIN_BIC_MARGIN:g} of the best candidate's {_runner_up_score(d, close)} "
            "(differences "
            + ", ".join(_one_decimal(v) for v in d.rival_margin[close])
            + "): the data do not strongly prefer the selected terms; compare the "
            + _candidates_where(d)
            + ", and try more data or measured derivatives"
        ),
    ),
)


def _one_decimal(v: float) -> str:
    """``v`` to one decimal, without the sign of a value that rounds to zero."""
    return f"{v:.1f}" if round(v, 1) != 0 else "0.0"


def _candidates_where(d) -> str:
    """Where the close-runner-up warning's candidates are."""
    if np.isfinite(d.constraint_residual):
        return "candidates (constrained_.candidates and constrained_.scores)"
    return (
        "candidates (selection_.candidates and selection_.scores on the path, "
        "selection_.subsets and selection_.subset_scores)"
    )


def _runner_up_score(d, close) -> str:
    """The score the close-runner-up warning's margins are on: the BIC (under
    constraints, summed over the equations), or for the equations of
    ``rival_by_noise``, the score under the noise their terms carry."""
    if np.isfinite(d.constraint_residual):
        return "BIC summed over the equations, under the constraints"
    noise = [k for k in close if k < d.rival_by_noise.size and d.rival_by_noise[k]]
    if not noise:
        return "BIC"
    return f"score (BIC; for equations {noise}, the score under the noise their terms carry)"


def kind_of(caught: warnings.WarningMessage) -> str:
    """The kind of a recorded warning: the rule of an :class:`IdentificationWarning`,
    else the warning's class name."""
    return getattr(caught.message, "kind", None) or caught.category.__name__


def count_kinds(kinds) -> str:
    """``"kind (count), ..."`` for a list of warning kinds, the most frequent first."""
    counts: dict[str, int] = {}
    for kind in kinds:
        counts[kind] = counts.get(kind, 0) + 1
    return ", ".join(f"{k} ({v})" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))


def warn(diagnostics: Diagnostics, stacklevel: int = 3) -> None:
    """One :class:`IdentificationWarning` per rule that applies (``stacklevel`` counted
    from the caller)."""
    for kind, message in diagnostics.findings():
        warnings.warn(IdentificationWarning(message, kind), stacklevel=stacklevel)


def stability(kept_theta_s, kept_y_s, coef_s, delta_s, method: str) -> np.ndarray:
    """Selected terms (n, p) that leaving out one of ``STABILITY_BLOCKS`` contiguous
    blocks of the kept samples changes (sign, or by more than ``STABILITY_TOLERANCE`` of
    the value) in an unpenalised Huber refit of the standardised problem; ``coef_s``
    (p, n) and ``delta_s`` (n,) standardised."""
    unstable = np.zeros(coef_s.shape, dtype=bool)
    m = kept_theta_s.shape[0]
    for k in range(coef_s.shape[1]):
        sel = np.flatnonzero(coef_s[:, k])
        if sel.size == 0 or m < STABILITY_BLOCKS * (sel.size + 2):
            continue
        ref = coef_s[sel, k]
        for rows, _ in blocked_folds(m, STABILITY_BLOCKS):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c = fit(
                    kept_theta_s[rows][:, sel],
                    kept_y_s[rows, k],
                    method,
                    delta_s[k],
                    0.0,
                    **pilot_budget(method),
                )
            c = c.coef.ravel()
            unstable[sel, k] |= (np.sign(c) != np.sign(ref)) | (
                np.abs(c - ref) > STABILITY_TOLERANCE * np.abs(ref)
            )
    return unstable.T


def _condition_numbers(theta_kept, coef) -> np.ndarray:
    """Of each equation's selected terms (unit-norm columns), ``coef`` (n, p)."""
    cond = np.ones(coef.shape[0])
    for k, row in enumerate(coef):
        keep = row != 0
        if keep.sum() >= 2:
            a = theta_kept[:, keep]
            cond[k] = np.linalg.cond(a / np.maximum(np.linalg.norm(a, axis=0), 1e-300))
    return cond


def _rival_margin(selection, rescored, standard, n, th, yk) -> tuple[np.ndarray, np.ndarray]:
    """The score margin to the next other model (``Diagnostics.rival_margin``) and
    whether it is that of the weak form's score under the noise the terms carry
    (``Diagnostics.rival_by_noise``): the selection's BIC, except for the equations
    whose support the weak form's rescoring replaced, where that score decided
    (:meth:`~robust_sindy.selection.variables.Rescored.rival_margin`: the BIC's own
    choice, which it beat by more than the margin, would otherwise read as a runner-up
    at a difference of zero), and the smaller of the two where the rescoring kept the
    support under a score it trusts (a rival that the noise of the columns makes look
    worse to the BIC is as close as that score puts it)."""
    by_noise = np.zeros(n, dtype=bool)
    if selection is None or selection.criterion != "bic":
        return np.full(n, np.nan), by_noise
    margin = selection.rival_margin_to(standard, th, yk)
    if rescored is not None:
        noise = rescored.rival_margin(standard)
        by_noise = rescored.switched | (rescored.trusted & (noise < margin))
        margin = np.where(by_noise, noise, margin)
    return margin, by_noise


def diagnose(
    *,
    kept,
    floor,
    choice,
    fitted,
    final,
    rows,
    entry_flags,
    row_flags,
    deriv,
    feature_names,
    selection_tol: float,
    method: str,
    weak=None,
    covered=None,
    formulation: str = "",
    missing=None,
    constrained=None,
    bounded=None,
    rescored=None,
    dropped=None,
) -> Diagnostics:
    """The diagnostics of a fit from its stages' outcomes: the kept problem
    (:class:`~robust_sindy.selection.problem.Problem`), the noise floor, the choice of
    ``delta`` and ``lam``, the penalised fit, the final selection, the row screen, the
    temporal screen's entry flags, the derivatives, the library's feature names, the
    ``selection_tol`` given and the Huber ``method``; with the weak form, its rows
    (:class:`~robust_sindy.timeseries.weak.WeakRows`: the counts of the row screen are
    of test functions, ``row_flags`` their temporal suspects) and the samples ``covered``
    by the kept ones.

    Besides what the stages recorded, it measures: the share of the state noise each
    equation's residuals allow and the library noise with each state's noise so
    reduced; the terms left out below the raised noise floor; the robust t of every
    selected term; the terms that leaving out a block of the data changes; the condition
    number of each equation's selected terms."""
    coef = final.coef
    n = coef.shape[1]
    scaler, th, yk, noise = kept.scaler, floor.design, kept.y_s, kept.noise
    delta = fitted.result.delta
    delta_s = kept.delta_standard(delta)
    selection = choice.selection
    standard = scaler.coef_to_standard(coef)
    noise_factor = np.full(n, np.nan)
    allowed = floor.library_noise[1]
    support_noise = np.full(n, np.nan)
    if selection is not None and noise is not None:
        for k in range(n):
            c = standard[:, k]
            noise_factor[k] = residual_noise_factor(yk[:, k] - th @ c, carried_noise(noise, c))
        state = state_noise_factors(noise, standard, noise_factor)
        if np.any(state < 1):
            noise = noise.scaled(np.sqrt(state))
            allowed = library_noise(noise, th)[1]
        for k in range(n):
            s = coef[:, k] != 0
            if s.any():
                support_noise[k] = library_noise(noise.terms(s), th[:, s])[1]
    below = np.full(coef.shape, np.nan)
    if selection is not None and floor.selection_tol > selection_tol:
        # Terms left out that the raised noise floor, not the data, decided about: above
        # their own column's noise (below it the data cannot tell them from it either).
        contrib = one_step_contributions(th, yk, standard, delta_s)
        own = np.nan_to_num(floor.library_noise[0], nan=0.0)[:, None]
        inside = (contrib >= np.maximum(selection_tol, own)) & (contrib < floor.selection_tol)
        below[inside] = contrib[inside]
    tstat = np.full(coef.shape, np.nan)
    if constrained is not None and constrained.significance is not None:
        tstat = constrained.significance  # the model under the constraints, at its delta
    elif selection is not None:
        tstat = robust_t(th, yk, standard, delta_s, kept.segments)
    pruned = final.pruned
    bic_margin = (
        selection.margin.copy()
        if selection is not None and selection.criterion == "bic"
        else np.full(n, np.nan)
    )
    rival_margin, rival_by_noise = _rival_margin(selection, rescored, standard, n, th, yk)
    if constrained is not None and constrained.candidates is not None:
        # The search under the constraints chose the model: its candidates are the
        # alternatives, and a term it put back is not dropped.
        bic_margin, rival_margin = constrained.margins()
        rival_by_noise = np.zeros(n, dtype=bool)
        pruned = np.where(coef != 0, np.nan, pruned)
        if constrained.pruned is not None:
            pruned = np.where(np.isnan(constrained.pruned), pruned, constrained.pruned)
    keep, screening = rows.keep, rows.screening
    screened = ~keep
    absent = (  # samples without a measured derivative (strong form only)
        missing.absent_rows if missing is not None and weak is None else np.zeros_like(keep)
    )
    m, p = screened.size, th.shape[1]
    coef_t = coef.T
    selected = np.count_nonzero(coef, axis=0)
    tau = correlation_time(huber_psi(yk - th @ standard, delta_s), kept.segments)
    return Diagnostics(
        n_samples=m,
        n_terms=p,
        samples_per_term=float((keep if covered is None else covered).sum() / p),
        temporal_flagged_entries=int(entry_flags.sum()),
        temporal_flagged_samples=int(entry_flags.any(axis=1).sum()),
        model_flagged_samples=int((screened & ~deriv.unresolved & ~absent).sum()),
        readmitted_samples=int((row_flags.any(axis=1) & keep).sum()),
        unresolved_samples=int(deriv.unresolved.sum()),
        screening_converged=True if screening is None else bool(screening.converged),
        screening_restarted=False if screening is None else bool(screening.restarted),
        flagged_fraction=float(screened.mean()),
        delta_over_scale=(
            np.full(n, np.nan) if screening is None else delta / (screening.scale * scaler.y_scale)
        ),
        certified=np.asarray(fitted.result.column_converged, dtype=bool),
        condition_number=_condition_numbers(kept.theta_s, coef_t),
        library_noise=allowed,
        support_noise=support_noise,
        selected_terms=selected,
        independent_samples=yk.shape[0] / tau,
        samples_needed=samples_needed(selected, p),
        constraint_residual=float("nan") if constrained is None else constrained.residual,
        constraints_certified=True if constrained is None else constrained.converged,
        constraints_status="" if constrained is None else constrained.status,
        constrained_delta=(
            np.full(n, np.nan) if constrained is None else np.asarray(constrained.delta, float)
        ),
        repaired_rows=(
            0
            if screening is None or screening.swapped is None
            else int((screening.swapped & keep).sum())
        ),
        energy_residual=float("nan") if bounded is None else bounded.energy_residual,
        trapping_eigenvalue=float("nan") if bounded is None else bounded.trapping_eigenvalue,
        pilot_relative_scale=(
            np.full(n, np.nan) if screening is None else screening.relative_scale.copy()
        ),
        noise_factor=noise_factor,
        unstable=(
            stability(kept.theta_s, kept.y_s, standard, delta_s, method)
            if constrained is None or constrained.unstable is None
            else constrained.unstable
        ),
        bias_ratio=np.ascontiguousarray(final.bias_ratio.T),
        truncation_ratio=np.ascontiguousarray(final.truncation_ratio.T),
        below_floor=np.ascontiguousarray(below.T),
        bic_margin=bic_margin,
        rival_margin=rival_margin,
        rival_by_noise=rival_by_noise,
        subset_size=(
            selection.subset_size.copy() if selection is not None else np.zeros(n, dtype=int)
        ),
        from_subsets=(
            selection.from_subsets.copy() if selection is not None else np.zeros(n, dtype=bool)
        ),
        significance=np.ascontiguousarray(tstat.T),
        significance_level=SIGNIFICANCE if deriv.measured else SIGNIFICANCE_ESTIMATED,
        pruned=np.ascontiguousarray(pruned.T),
        added=np.ascontiguousarray(np.where(coef != 0, final.added, np.nan).T),
        aliased=[feature_names[j] for j in np.flatnonzero(floor.aliased)],
        derivative_half_window=deriv.windows.copy(),
        formulation="strong" if weak is None else "weak",
        support_half_width=float("nan") if weak is None else weak.half_width,
        n_rows=0 if weak is None else weak.n_rows,
        formulation_reason=formulation,
        errors_in_variables=(np.full(n, -1) if rescored is None else rescored.switched.astype(int)),
        dropped_evidence=np.full(n, np.nan) if dropped is None else np.asarray(dropped, float),
        temporal_flagged_left_out=int(
            entry_flags.sum()
            if weak is not None
            else entry_flags[~keep & ~deriv.unresolved & ~absent].sum()
        ),
        record_samples=int(entry_flags.shape[0]),
        **({} if missing is None else missing.summary()),
    )
