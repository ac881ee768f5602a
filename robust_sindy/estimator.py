"""HuberSINDy: the estimator users fit to time series.

:meth:`HuberSINDy.fit` runs the identification as a sequence of named stages, each a
function in the module that owns the decision (see :doc:`/guide/index`):

1. :meth:`Trajectories.from_user <robust_sindy.timeseries.trajectories.Trajectories.from_user>`
   -- the records, checked;
2. :class:`~robust_sindy.timeseries.missing.Missing` -- the readings not measured (NaN);
3. :func:`~robust_sindy.timeseries.temporal.temporal_screen` -- entries inconsistent
   with their neighbours in time, and the missing ones filled from theirs; then the
   library, fitted to the states' and controls' names;
4. :meth:`HuberSINDy._weak_rows` -- the formulation, and
   :func:`~robust_sindy.timeseries.derivatives.derivatives` -- the targets (the
   stages from here on run again for the weak form where outliers alone kept the
   strong form, and
   :func:`~robust_sindy.selection.forecast.forecast_contest` decides between the two
   models where they differ);
5. :class:`~robust_sindy.selection.problem.Problem` -- standardised columns;
6. :func:`~robust_sindy.selection.rows.screen_samples` -- samples with gross residuals;
7. :func:`~robust_sindy.selection.choice.noise_floor` -- aliased terms, the noise floor;
8. :func:`~robust_sindy.selection.choice.choose_delta_lam` -- delta and lambda;
9. :func:`~robust_sindy.selection.choice.fit_chosen` -- the certified fit at the choice;
10. :func:`~robust_sindy.selection.final.final_selection` -- terms the data do not
    vouch for;
11. :func:`~robust_sindy.diagnostics.diagnose` -- what the model can vouch for.

Only :meth:`HuberSINDy._set_fitted` writes the fitted attributes.
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import asdict, dataclass, replace
from numbers import Integral, Real

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.exceptions import NotFittedError

from . import io, outofcore
from .core.blas import one_thread
from .core.constraints import LinearConstraints
from .core.scaling import Standardizer
from .core.validation import as_float_array
from .diagnostics import (
    STABILITY_BLOCKS,
    STABILITY_TOLERANCE,
    Diagnostics,
    IdentificationWarning,
    diagnose,
    warn,
)
from .fitting import METHODS
from .library import BaseLibrary, PolynomialLibrary
from .selection.bias import noise_columns
from .selection.choice import (
    Choice,
    Fitted,
    NoiseFloor,
    choose_delta_lam,
    fit_chosen,
    huber_method,
    noise_floor,
)
from .selection.constrained import (
    ConstrainedRefit,
    build_constraints,
    constrained_selection,
    constrained_significance,
    constrained_stability,
)
from .selection.criteria import CRITERIA
from .selection.final import FinalSelection, final_selection, significance_bar
from .selection.forecast import FORECAST_EVIDENCE, forecast_contest
from .selection.problem import Problem
from .selection.rows import RowScreen, screen_samples
from .selection.stability import boundedness, quadratic_parts
from .selection.variables import (
    RowNoise,
    displacement_refused,
    dropped_evidence,
    rescore_weak,
)
from .simulate import integrate, simulation_inputs
from .timeseries.derivatives import (
    DERIVATIVE_WINDOWS,
    Derivatives,
    check_differentiation,
    derivatives,
    differentiate,
)
from .timeseries.missing import Missing
from .timeseries.temporal import (
    TemporalScreening,
    fill_missing,
    noise_flag_bound,
    relative_noise,
    temporal_screen,
)
from .timeseries.trajectories import Trajectories, is_frame, is_series
from .timeseries.weak import LOCAL_SAMPLES, WeakRows, support_half_width, weak_rows

__all__ = [
    "FORMULATIONS",
    "MIN_INDEPENDENT_ROWS_PER_TERM",
    "MIN_ROWS_PER_TERM",
    "OUTLIER_EVIDENCE",
    "WEAK_WITH_OUTLIERS_NOISE",
    "HuberSINDy",
    "load_model",
]

#: The choices of ``formulation``.
FORMULATIONS = ("strong", "weak", "auto")
#: ``formulation="auto"`` keeps the strong form where the temporal screen flagged more
#: entries than Gaussian noise alone would at its cutoff, beyond this probability (a
#: binomial bound on the count of all entries): outliers were found, which cost single
#: samples in the strong form, where the weak form's integrals would rest on their
#: repairs (unless the states are noisy: :data:`WEAK_WITH_OUTLIERS_NOISE`).
OUTLIER_EVIDENCE = 1e-3
#: With outliers found, ``formulation="auto"`` still takes the weak form where the
#: states' noise (the temporal screen's level, median over the states, relative to the
#: spread of the repaired states) is at least this: the strong form's derivatives of
#: noisy states then cost more than the repairs cost the weak form's integrals.  It is
#: the measured crossover (states only, degree-4 library, 16 polynomial flows with
#: glitches, spikes, whole-row contamination and bursts): at 1 % noise both forms are
#: right about as often, at 2 % and above the weak form is right more often and the
#: strong form fails silently in some cases, at 0.1 % the strong form is right more
#: often (the weak form loses whole-row contamination).
WEAK_WITH_OUTLIERS_NOISE = 0.015
#: The weak form needs more test functions than this many per library term (their
#: centres are placed closer together on short records to reach twice as many).
MIN_ROWS_PER_TERM = 2
#: ``formulation="auto"`` takes the weak form only where its rows hold more than this
#: many independent rows per library term
#: (:meth:`~robust_sindy.timeseries.weak.WeakRows.effective_rows`: overlapping test
#: functions share their samples' noise, and a support's width of record gives about
#: three independent rows however closely the centres are placed).  With no more
#: independent rows than terms, the fits on every term that the screens and the
#: selection rest on are underdetermined in effect.  On Lorenz-96 records with 8 to 30
#: states and that few independent rows, the weak form was right in 1 of 29, the
#: strong form in 12 of 28 and far closer in the others (see the design notes).
MIN_INDEPENDENT_ROWS_PER_TERM = 1.0
#: Fits with at most this many samples run BLAS on one thread: its products are then
#: small and the threads' start-up costs more than they save.
SMALL_PROBLEM_SAMPLES = 10_000


def _is_auto(value) -> bool:
    return isinstance(value, str) and value == "auto"


class _Stages:
    """With ``progress``, a bar over the stages of a fit that names the one running (a
    fit of many states spends minutes in its row screen before the path's own bar)."""

    COUNT = 6
    #: Stages of :meth:`HuberSINDy._regress` (run again for a second formulation).
    REGRESSION = 4

    def __init__(self, progress: bool):
        from tqdm import tqdm

        self.bar = tqdm(total=self.COUNT, desc="identify", disable=not progress, leave=False)
        self.started = False

    def start(self, name: str) -> None:
        if self.started:
            self.bar.update()
        self.started = True
        self.bar.set_postfix_str(name)

    def add(self, count: int) -> None:
        """``count`` more stages (a second formulation's)."""
        self.bar.total += count
        self.bar.refresh()

    def close(self) -> None:
        self.bar.update()
        self.bar.close()


@dataclass(frozen=True)
class Identification:
    """Every stage's outcome of one in-memory fit (what :meth:`HuberSINDy._set_fitted`
    turns into the fitted attributes)."""

    data: Trajectories
    library: BaseLibrary
    theta: np.ndarray
    temporal: TemporalScreening | None
    deriv: Derivatives
    problem: Problem
    rows: RowScreen
    floor: NoiseFloor
    choice: Choice
    fitted: Fitted
    final: FinalSelection
    diagnostics: Diagnostics
    weak: WeakRows | None = None
    covered: np.ndarray | None = None
    constrained: ConstrainedRefit | None = None


@dataclass(frozen=True)
class _Prepared:
    """What the stages before the formulation's choice give every formulation fitted."""

    data: Trajectories
    library: BaseLibrary
    missing: Missing
    temporal: TemporalScreening | None
    z: np.ndarray
    theta: np.ndarray
    outlying: np.ndarray
    flags: np.ndarray
    stages: _Stages


class HuberSINDy(BaseEstimator):
    """Sparse identification of nonlinear dynamics with the Huber loss.

    Each equation ``k`` solves ``min_xi sum_i H_delta(xdot_ik - Theta_i xi) + lam
    ||xi||_1`` (:func:`robust_sindy.fit`).  With the defaults nothing needs choosing:
    outlier samples are screened out (``screen``), ``delta`` is 1.345 robust residual
    scales, ``lam`` is chosen per equation by a robust BIC over a path with a selection
    stage at every point, and terms the data do not vouch for are dropped (errors in
    the variables, truncation of estimated derivatives, robust t below the bar).  Fixed
    values turn each stage into the plain estimator (``screen=False, delta=1.0,
    lam=1.0`` is the paper's); ``threshold`` and ``refit`` then act on the result.

    Read more in the user guide: :doc:`/guide/index`.

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
        Flag and leave out gross-outlier samples before fitting (temporal screen of the
        states, row screen of the regression).
    criterion : {"bic", "cv"}
        How ``lam="auto"`` picks the point on the path.
    selection_tol : float
        Relative contribution ``|xi_j| ||theta_j|| / ||xdot_k||`` below which
        ``lam="auto"`` drops a term; raised to the relative noise of the noisiest
        library column (``selection_tol_``), under which a term stays only when its
        robust t reaches the significance bar.
    n_lams : int
        Points on the ``lam`` path.
    method : {"admm", "cvxpy", "stls", "ols"}
        Solver passed to :func:`robust_sindy.fit` (``lam="auto"`` needs a Huber
        method, "admm" or "cvxpy").
    threshold : float, optional
        After the fit, set coefficients with ``|xi| < threshold`` to zero.
    refit : bool
        Refit each equation on its nonzero terms with ``lam = 0`` (Huber loss, same
        ``delta``); always done with ``lam="auto"``.
    differentiation : {"robust", "finite_difference", "savgol"} or callable
        How derivatives are obtained when ``x_dot`` is not given: ``"robust"`` local
        quartics of the repaired states, temporal outliers given no weight; the others
        differentiate the repaired states (the raw ones with ``screen=False``); a
        callable receives ``(x, t)`` and returns an array shaped like ``x``.
    solver : str, optional
        For ``method="cvxpy"``: ``"clarabel"`` or ``"osqp"``.
    solver_options : dict, optional
        Keyword options of :func:`robust_sindy.fit` (``max_iter``, ``tol``, ...).
    progress : bool
        Show progress bars: the stage a fit is in (temporal screen, formulation and
        derivatives, row screen, δ, λ and the support, final selection, diagnostics)
        and the ``lam`` path.
    derivative_window : {"auto", "fixed"}
        The window of ``differentiation="robust"``: chosen per state from the data (5
        to 65 samples), or 5 samples (the fourth-order central difference).
    formulation : {"strong", "weak", "auto"}
        The regression's rows: the samples, with derivatives measured or estimated
        (``"strong"``), or integrals of the states and the library against test
        functions, no derivative estimated (``"weak"``,
        :mod:`robust_sindy.timeseries.weak`; ``t`` is then required); ``"auto"``: the
        weak form where no ``x_dot`` is given, unless the temporal screen flagged more
        entries than Gaussian noise would (outliers: ``OUTLIER_EVIDENCE``) in states
        whose noise is below ``WEAK_WITH_OUTLIERS_NOISE`` (1.5 %) of their spread, or
        the records are too short for it: its overlapping test functions leave no more
        independent rows than the library has terms (``MIN_INDEPENDENT_ROWS_PER_TERM``;
        ``diagnostics_.formulation_reason`` says which and why).
    constraints : None, "energy_preserving", LinearConstraints or callable
        Linear constraints on the coefficients across equations
        (:mod:`robust_sindy.constraints`; a callable gets the library's feature names
        and the states' names and returns a
        :class:`~robust_sindy.LinearConstraints`).  The terms are selected as without
        them, then the selected terms and those a constraint ties to them are refitted
        under the constraints (:mod:`robust_sindy.selection.constrained`);
        ``diagnostics_.constraint_residual`` reports how well they are met.

    Attributes
    ----------
    coef_ : ndarray, shape (n_targets, n_features)
        Identified coefficients (rows: equations; the transpose of :func:`fit`'s Xi).
    support_ : ndarray of bool, shape (n_targets, n_features)
        ``coef_ != 0``.
    library_ : BaseLibrary
        The fitted library; ``feature_names_`` are its input names (states, controls).
    delta_ : ndarray (n_targets,)
        The Huber thresholds used (with ``constraints``, the constrained model's,
        ``diagnostics_.constrained_delta``).
    lam_ : ndarray (n_targets,) or (n_features, n_targets)
        The L1 weights used (with ``lam="auto"`` one weight per coefficient in user
        units: one per equation on standardised columns, ``selection_.lam``).
    screened_ : ndarray of bool, shape (n_samples,)
        Samples left out of the fit: outliers, and the samples of ``unresolved_``.
    unresolved_ : ndarray of bool, shape (n_samples,)
        Samples whose estimated derivatives the sampling does not resolve (none with
        the weak form, which estimates no derivative).
    temporal_ : TemporalScreening or None
        The temporal screen's flags, repaired states and noise levels.
    derivative_windows_ : ndarray of int (n_states,)
        Half width, in samples, of each state's robust derivative window (0 when
        ``x_dot`` was given, another ``differentiation`` or the weak form was used).
    screening_ : Screening or None
        The row screen's details; its masks cover all samples.
    standardizer_ : Standardizer
        The column scales every decision was taken on: root mean squares of the
        library of the repaired readings (of the weak form's integrals) and of the
        targets.
    library_noise_ : tuple (ndarray (n_features,), float)
        The states' noise carried through the library, per column and along its
        least-excited direction; NaN without the screen.
    library_noise_allowed_ : float
        The same along the least-excited direction, each state's noise no larger than
        the residuals allow.
    selection_tol_ : float
        The selection threshold used.
    diagnostics_ : Diagnostics
        What the data can and cannot vouch for; problems are also raised as
        :class:`IdentificationWarning`.
    path_ : Path or None
        The ``lam`` path of ``lam="auto"``.
    selection_ : Selection or None
        Scores and candidates of ``lam="auto"``.
    constrained_ : ConstrainedRefit or None
        With ``constraints``, the search under them: the supports it refitted
        (``candidates``) and their criterion (``scores``), the chosen one, its
        ``delta``, ``significance`` and ``unstable`` terms
        (:class:`~robust_sindy.selection.constrained.ConstrainedRefit`); None without.
    outliers_ : ndarray of bool, shape (n_rows, n_targets)
        Residuals under the final model beyond ``delta_``, per sample (per test
        function with the weak form).
    weak_ : WeakRows or None
        The weak form's rows (test functions, half width), when it was used.
    result_ : FitResult
        The penalised fit at ``lam_`` on the kept samples (before threshold and refit).
    bias_dropped_, bias_ratio_, truncation_ratio_, noise_factor_, below_floor_,
    significance_, pruned_, aliased_ : ndarray
        What the final selection dropped and why (see :class:`Diagnostics`).

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
        differentiation="robust",
        solver: str | None = None,
        solver_options: dict | None = None,
        progress: bool = False,
        derivative_window="auto",
        formulation="auto",
        constraints=None,
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
        self.formulation = formulation
        self.constraints = constraints

    # ------------------------------------------------------------------ fitting
    def fit(self, x, t=None, x_dot=None, u=None, feature_names=None) -> HuberSINDy:
        """Identify the equations from one trajectory or a list of trajectories.

        Parameters
        ----------
        x : array_like (m, n), or a list of them
            Measured states; NaN marks a missing reading (filled from its neighbours in
            time and counted, :mod:`robust_sindy.timeseries.missing`; also in ``x_dot``
            and ``u``).
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
        sample times in seconds.  Dask arrays are fitted out of core
        (:mod:`robust_sindy.outofcore`).
        """
        self.check_params()
        data = Trajectories.from_user(
            x, t, x_dot, u, feature_names, need_t=self.formulation != "strong"
        )
        if data.lazy:
            return self._fit_out_of_core(data)
        small = data.n_samples <= SMALL_PROBLEM_SAMPLES
        with one_thread() if small else contextlib.nullcontext():
            self._set_fitted(self._identify(data))
        warn(self.diagnostics_)
        return self

    def _identify(self, data: Trajectories, allow_weak: bool = True) -> Identification:
        """The stages of an in-memory fit (see the module docstring)."""
        names = data.feature_names()
        library = clone(self.library) if self.library is not None else PolynomialLibrary()
        missing = Missing.of(data)
        stages = _Stages(self.progress)
        stages.start("temporal screen")
        if self.screen:
            temporal = temporal_screen(data.x, data.t)
        else:  # missing readings are filled all the same (and said so)
            temporal = fill_missing(data.x, data.t) if missing.states.any() else None
        z = missing.filled_inputs(data, temporal)
        theta = library.fit_transform(z, input_names=names)
        m, p = theta.shape
        if m <= p:
            raise ValueError(
                f"x has {m} samples but the library has {p} terms: at least {p + 1} samples "
                "are needed to fit it (use a smaller library or more data)"
            )
        # Entries inconsistent with their neighbours, and missing ones filled across a
        # gap wider than the screen's window: the samples' suspects.
        outlying = np.zeros((m, data.n_states), dtype=bool)
        if temporal is not None:
            outlying = temporal.flags & ~missing.states
        flags = outlying | missing.suspect
        stages.start("formulation and derivatives")
        weak, why, contested = (
            self._weak_rows(data, temporal, library, z, missing) if allow_weak else (None, "", "")
        )
        prep = _Prepared(data, library, missing, temporal, z, theta, outlying, flags, stages)
        found = self._regress(prep, weak, why)
        if contested:
            # Outliers kept the strong form: the weak form's model is the challenger,
            # whether or not the strong form's model warns (wrong models without any
            # warning are among those it puts right; design notes, "Every record
            # challenged").
            rival, rival_why, _ = self._weak_rows(
                data, temporal, library, z, missing, outliers_decide=False
            )
            if rival is not None:
                stages.add(_Stages.REGRESSION)
                rival = self._regress(prep, rival, rival_why)
                found = self._contest(prep, found, rival, contested)
        stages.close()
        return found

    def _regress(self, prep: _Prepared, weak: WeakRows | None, why: str) -> Identification:
        """The stages after the formulation's choice: the targets, the row screen,
        delta, lambda and the support, the final selection and the diagnostics."""
        data, library, missing, temporal = prep.data, prep.library, prep.missing, prep.temporal
        z, outlying, flags, stages = prep.z, prep.outlying, prep.flags, prep.stages
        theta = prep.theta
        names = data.feature_names()
        alternative, guard, clean = None, theta, theta
        if weak is None and outlying.any():
            # A glitch need not cost its sample: the row of its repaired readings is the
            # row screen's second choice for a sample it would leave out, where most of
            # the sample's readings were not flagged (a sample most of whose readings are
            # off is a corrupted row, whose unflagged readings are suspect too).
            hit = outlying.sum(axis=1)
            touched = np.flatnonzero(hit > 0)
            repaired = z[touched].copy()
            repaired[:, : data.n_states] = np.where(
                outlying[touched], temporal.repaired[touched], repaired[:, : data.n_states]
            )
            repaired = library.transform(repaired)
            # The library of every repaired reading: the columns' scales (a glitch of
            # a thousand standard deviations would otherwise set its columns' weight in
            # the L1 penalty), and the derivatives' window guard (robust
            # differentiation only), which tests each state on that state's own usable
            # samples.
            clean = theta.copy()
            clean[touched] = repaired
            if (
                data.x_dot is None
                and self.differentiation == "robust"
                and self.derivative_window == "auto"
            ):
                guard = clean
            few = 2 * hit[touched] <= data.n_states
            if few.any():
                alternative = (touched[few], repaired[few])
        if weak is None:
            deriv = derivatives(
                data, temporal, self.differentiation, self.derivative_window, self.screen, guard
            )
            del guard
            design, segments, row_flags = theta, data.segments, flags | missing.controls_suspect
        else:
            # Integrated rows: their targets carry the states' noise, not an estimate's.
            n_rows = weak.n_rows
            deriv = Derivatives(
                weak.b, True, np.zeros(n_rows, dtype=bool), None, np.zeros(data.n_states, int)
            )
            design, segments = weak.G, weak.segments
            row_flags = weak.touched(flags | missing.controls_suspect, data)[:, None]
        if weak is None and missing.far.any():
            # Samples too far from a reading to fill are left out (below): not of the
            # columns' scales either.
            scaler = Standardizer.from_data(clean[~missing.far], deriv.y[~missing.far])
        else:
            scaler = Standardizer.from_data(design if weak is not None else clean, deriv.y)
        del clean  # a copy of the library, not needed further
        noise = noise_columns(library, z, temporal, scaler.theta_scale)
        sample_noise = noise
        if weak is not None:
            noise = weak.noise(noise, data)
        problem = Problem(design, deriv.y, scaler, segments, noise)
        pilot = huber_method(self.method)
        # A missing measured derivative: no target (the weak form uses none); a reading
        # too far to fill: no row (the weak form's test functions do not reach it).
        absent = missing.absent_rows if weak is None else np.zeros(problem.shape[0], bool)
        stages.start("row screen")
        rows = screen_samples(
            problem, row_flags, deriv.unresolved | absent, measured=deriv.measured,
            method=pilot, screen=self.screen, alternative=alternative,
            row_noise=None if weak is None else weak.target_noise(),
        )  # fmt: skip
        swapped = None if rows.screening is None else rows.screening.swapped
        if swapped is not None and swapped.any():
            theta = theta.copy()  # the library of the records, shared with a rival fit
            theta[swapped] = alternative[1][np.isin(alternative[0], np.flatnonzero(swapped))]
            problem = Problem(theta, deriv.y, scaler, segments, noise)
        if absent.any():
            rows = RowScreen(rows.keep & ~absent, rows.screening)
        kept = problem.keep(rows.keep)
        stages.start("delta, lambda and the support")
        floor = noise_floor(kept, find_aliases=_is_auto(self.lam), selection_tol=self.selection_tol)
        options = dict(self.solver_options or {})
        choice = choose_delta_lam(
            kept, floor.design, self.delta, self.lam, criterion=self.criterion,
            n_lams=self.n_lams, selection_tol=self.selection_tol, method=self.method,
            solver=self.solver, progress=self.progress, options=options,
            start=None if rows.screening is None else rows.screening.pilot,
        )  # fmt: skip
        fitted = fit_chosen(
            kept, choice, method=self.method, solver=self.solver, options=options,
            threshold=self.threshold, refit=self.refit,
        )  # fmt: skip
        rescored = row_noise = None
        if weak is not None and choice.selection is not None and sample_noise is not None:
            state_noise = temporal.scale / scaler.y_scale
            row_noise = RowNoise.of_weak(weak, rows.keep, sample_noise, state_noise)
            fitted, rescored = rescore_weak(
                kept, floor.design, choice.selection, fitted, row_noise,
                method=self.method, solver=self.solver, options=options,
            )  # fmt: skip
        stages.start("final selection")
        if choice.selection is not None:
            refuse = None
            if row_noise is not None:  # put-back terms judged as the rescoring judged

                def refuse(current, outcome, cols):
                    return displacement_refused(
                        floor.design, kept.y_s, current, outcome, row_noise, cols
                    )

            final = final_selection(
                kept, floor.design, fitted.coef, fitted.result.delta,
                selection_tol=self.selection_tol, floor_tol=floor.selection_tol,
                measured=deriv.measured,
                reference=None if deriv.reference is None else deriv.reference[rows.keep],
                method=pilot, solver=self.solver, options=options, refuse=refuse,
            )  # fmt: skip
        else:
            nan = np.full(fitted.coef.shape, np.nan)
            final = FinalSelection(fitted.coef, nan, nan.copy(), nan.copy(), nan.copy())
        dropped = None
        if rescored is not None and self.constraints is None:
            # The final selection's drops, scored as the rescoring scored the candidates.
            dropped = dropped_evidence(
                floor.design, kept.y_s, fitted.coef != 0, final.coef != 0,
                kept.scaler.coef_to_standard(fitted.coef), row_noise, tol=self.selection_tol,
            )  # fmt: skip
        refit = None
        if self.constraints is not None:
            con = build_constraints(
                self.constraints, library.get_feature_names(), names[: data.n_states],
                final.coef.shape,
            )  # fmt: skip
            refit = constrained_selection(
                kept, final.coef, fitted.result.delta, con, method=self.method,
                solver=self.solver,
                bar=None if choice.selection is None else significance_bar(deriv.measured),
            )  # fmt: skip
            refit = replace(
                refit,
                unstable=constrained_stability(
                    kept, refit, con, blocks=STABILITY_BLOCKS, tolerance=STABILITY_TOLERANCE,
                    method=self.method, solver=self.solver,
                ),
                significance=constrained_significance(kept, refit, con),
                constraints=con,
            )  # fmt: skip
            final = replace(final, coef=refit.coef)
        covered = None if weak is None else weak.covered(rows.keep)
        stages.start("diagnostics")
        report = diagnose(
            kept=kept, floor=floor, choice=choice, fitted=fitted, final=final, rows=rows,
            entry_flags=outlying, row_flags=row_flags, deriv=deriv, missing=missing,
            feature_names=library.get_feature_names(), selection_tol=self.selection_tol,
            method=pilot, weak=weak, covered=covered, formulation=why, constrained=refit,
            rescored=rescored, dropped=dropped,
            bounded=_boundedness(library, final.coef, data.n_states),
        )  # fmt: skip
        return Identification(
            data, library, theta, temporal, deriv, problem, rows, floor, choice, fitted, final,
            report, weak, covered, refit,
        )  # fmt: skip

    def _contest(
        self, prep: _Prepared, strong: Identification, weak: Identification, outliers: str
    ) -> Identification:
        """The strong form kept for the outliers alone, and the weak form's model: where
        they select other terms, the weak form's is taken if it forecasts the record
        better in significantly more windows (:func:`forecast_contest`, windows as wide
        as the weak form's test functions; where the windows only lean towards it, the
        diagnostics warn); the reason says which and why (``outliers``: what kept the
        strong form)."""
        data, reason = prep.data, strong.diagnostics.formulation_reason
        a, b = strong.final.coef, weak.final.coef
        if np.array_equal(a != 0, b != 0):
            text = f"{reason}; the weak form selects the same terms"
            return replace(strong, diagnostics=replace(strong.diagnostics, formulation_reason=text))
        n = data.n_states
        names = data.feature_names()[:n]
        differ = ", ".join(
            f"{names[k]}'" for k in range(n) if not np.array_equal(a[:, k] != 0, b[:, k] != 0)
        )
        step = max(float(np.median(np.diff(t))) for t in data.t)
        horizon = max(2, round(2 * weak.diagnostics.support_half_width / step))
        readings = np.where(prep.outlying, np.nan, np.vstack(data.x))  # NaN where missing
        states = prep.z[:, :n] if prep.temporal is None else prep.temporal.repaired
        contest = forecast_contest(
            prep.library.transform, a, b, states, readings, np.concatenate(data.t),
            data.segments, horizon, inputs=prep.z[:, n:] if data.n_controls else None,
        )  # fmt: skip
        tally = (
            f"closer to the readings in {contest.wins} of {contest.wins + contest.losses} "
            f"windows of {contest.horizon} samples (sign test p = {contest.p_value:.2g}"
        )
        record = dict(asdict(contest), equations=differ)
        if contest.challenger_better:
            shares = weak.diagnostics.formulation_reason.split("; ", 1)[-1]
            text = (
                f"weak form: {outliers}, below {100 * WEAK_WITH_OUTLIERS_NOISE:.2g} %, which "
                f"keeps the strong form, but the weak form's model selects other terms in "
                f"{differ} and forecasts the record better: {tally}, at most "
                f"{FORECAST_EVIDENCE:g}); {shares}"
            )
            found, record["chosen"] = weak, "weak"
        else:
            text = (
                f"{reason}; the weak form's model selects other terms in {differ} but does "
                f"not forecast the record better ({tally}, above {FORECAST_EVIDENCE:g}))"
            )
            found, record["chosen"] = strong, "strong"
        report = replace(found.diagnostics, formulation_reason=text, formulation_contest=record)
        return replace(found, diagnostics=report)

    def _weak_rows(
        self, data: Trajectories, temporal, library, z, missing: Missing, outliers_decide=True
    ) -> tuple[WeakRows | None, str, str]:
        """The weak form of the records, when ``formulation`` asks for it (``"auto"``:
        states only, and no more entries flagged by the temporal screen than Gaussian
        noise gives, :func:`noise_flag_bound`, or states whose noise is at least
        :data:`WEAK_WITH_OUTLIERS_NOISE` of their spread; and more independent rows than
        :data:`MIN_INDEPENDENT_ROWS_PER_TERM` per term), and why: the repaired
        states (the raw ones without the screen) integrated against test functions whose
        width the screen's noise levels set.  The third value, where the strong form was
        kept for the outliers alone (below that noise), says what the screen found: the
        weak form's rows are then built again with ``outliers_decide=False``, as the
        challenger of :meth:`_contest`."""
        if self.formulation == "strong":
            return None, "strong form (formulation='strong')", ""
        if self.formulation == "auto" and data.x_dot is not None:
            why = "strong form: the derivatives were measured (formulation='auto')"
            return None, why, ""
        # Without the screen, ``temporal`` only filled the missing readings: the choice
        # and the width are the screen's all the same.
        screen = temporal if self.screen else temporal_screen(data.x, data.t)
        outliers = ""
        if self.formulation == "auto" and outliers_decide:
            # Missing readings are not outliers: the count is of the readings.
            readings = int((~missing.states).sum())
            flagged = int((screen.flags & ~missing.states).sum())
            bound = noise_flag_bound(readings, OUTLIER_EVIDENCE)
            if flagged > bound:
                noise = relative_noise(screen)
                found = (
                    f"the temporal screen flagged {flagged} entries "
                    f"({100 * flagged / readings:.2g} %), more than Gaussian noise gives "
                    f"({bound}), and the states' noise is {100 * noise:.2g} % "
                    "of their spread"
                )
                bar = f"{100 * WEAK_WITH_OUTLIERS_NOISE:.2g} %"
                if not noise >= WEAK_WITH_OUTLIERS_NOISE:
                    kept = (
                        f"strong form: {found}, below {bar}: outliers cost single samples in "
                        "the strong form, where the weak form's integrals would rest on their "
                        "repairs (formulation='auto')"
                    )
                    return None, kept, found
                outliers = (
                    f"weak form: {found}, at least {bar}: "
                    "derivatives of states this noisy cost the strong form more than the "
                    "repairs cost the integrals"
                )
        support = support_half_width(data, screen, missing.suspect)
        states = temporal.repaired if self.screen else z[:, : data.n_states]
        inputs = z.copy()
        inputs[:, : data.n_states] = states  # the library of the repaired states
        terms = library.n_output_features_
        rows = weak_rows(
            data, states, library.transform(inputs), support.half_width,
            min_rows=2 * MIN_ROWS_PER_TERM * terms, noise=screen.scale, cut=missing.far,
        )  # fmt: skip
        if rows.n_rows <= MIN_ROWS_PER_TERM * terms:
            if self.formulation == "weak":
                raise ValueError(
                    f"the weak form has {rows.n_rows} test functions of half width "
                    f"{support.samples:.0f} samples for {terms} terms (at least "
                    f"{MIN_ROWS_PER_TERM * terms + 1} are needed): the records are too "
                    "short for it; use formulation='strong' or a smaller library"
                )
            few = (
                f"strong form: the weak form would have {rows.n_rows} test functions for "
                f"{terms} terms (formulation='auto')"
            )
            return None, few, ""
        independent = rows.effective_rows()
        quadrature = (
            f", integrated on local fits of {rows.stencil.samples} samples (the states' "
            "noise outweighs the wider fits' quadrature error)"
            if rows.stencil.samples != LOCAL_SAMPLES
            else ""
        )
        shares = (
            f"test functions of half width {support.samples:.0f} samples{quadrature}, about "
            f"{independent:.0f} independent rows for {terms} terms"
        )
        few_rows = independent <= MIN_INDEPENDENT_ROWS_PER_TERM * terms
        # What both the choice of ``auto`` and the warning when asked for say.
        underdetermined = (
            f"the weak form's {rows.n_rows} {shares}: overlapping test functions share "
            "their samples' noise, and no more independent rows than terms leave the fits "
            "on every term underdetermined"
        )
        if self.formulation == "auto" and few_rows:
            return None, f"strong form: {underdetermined} (formulation='auto')", ""
        if self.formulation == "weak":
            why = f"weak form (formulation='weak'); {rows.n_rows} {shares}"
            if few_rows:
                # Said before the fit: its selection on such rows may take long.
                warnings.warn(
                    IdentificationWarning(
                        f"{underdetermined}: the selection may keep most of the library "
                        "(and search long from there); use formulation='auto' (which "
                        "takes the strong form here), longer records or a smaller library",
                        "few independent rows",
                    ),
                    stacklevel=4,
                )
        else:
            why = (
                outliers or "weak form: states only, no outliers found by the temporal screen"
            ) + f"; {shares}, the width from the states' noise (formulation='auto')"
        return rows, why, ""

    def _set_fitted(self, found: Identification) -> None:
        """The fitted attributes, from the stages' outcomes (the only place they are set)."""
        choice, fitted, final, report = found.choice, found.fitted, found.final, found.diagnostics
        self.n_control_features_ = found.data.n_controls
        self.feature_names_ = found.data.feature_names()
        self.library_ = found.library
        self.temporal_ = found.temporal
        self.derivative_windows_ = found.deriv.windows
        self.unresolved_ = (
            found.deriv.unresolved
            if found.weak is None
            else np.zeros(found.data.n_samples, dtype=bool)
        )
        self.standardizer_ = found.problem.scaler
        self.screening_ = found.rows.screening
        self.screened_ = ~found.rows.keep if found.weak is None else ~found.covered
        self.weak_ = found.weak
        self.aliased_ = found.floor.aliased
        self.library_noise_ = found.floor.library_noise
        self.selection_tol_ = found.floor.selection_tol
        self.selection_ = choice.selection
        self.path_ = None if choice.selection is None else choice.selection.path
        self.constrained_ = found.constrained
        self.result_ = fitted.result
        # The final model's threshold: under constraints, the constrained model's own.
        self.delta_ = (
            fitted.result.delta
            if report.constrained_delta is None or np.isnan(report.constrained_delta).all()
            else report.constrained_delta
        )  # fmt: skip
        self.lam_ = fitted.result.lam
        self.pruned_ = report.pruned.copy()
        self.bias_ratio_ = report.bias_ratio.copy()
        self.bias_dropped_ = np.isfinite(self.bias_ratio_)
        self.truncation_ratio_ = report.truncation_ratio.copy()
        self.noise_factor_ = report.noise_factor.copy()
        self.library_noise_allowed_ = report.library_noise
        self.below_floor_ = report.below_floor.copy()
        self.significance_ = report.significance.copy()
        self.coef_ = np.ascontiguousarray(final.coef.T)
        self.support_ = self.coef_ != 0
        self.outliers_ = np.abs(found.problem.y - found.problem.theta @ final.coef) > self.delta_
        self.diagnostics_ = report

    def _fit_out_of_core(self, data: Trajectories) -> HuberSINDy:
        """Dask arrays: the model is chosen on a sample in memory
        (:func:`robust_sindy.outofcore.sample`, all the stages of a fit), then refitted on
        every sample out of core (:func:`robust_sindy.outofcore.refit`)."""
        if self.formulation == "weak":
            raise ValueError(
                "formulation='weak' is fitted in memory only: the out-of-core refit "
                "differentiates chunk by chunk; pass formulation='strong' or 'auto' for Dask "
                "arrays"
            )
        refused = (
            "missing readings (NaN) are handled in memory only: the out-of-core refit "
            "differentiates chunk by chunk; fit the array in memory (x.compute()) or "
            "leave out the samples with missing readings"
        )
        chosen = outofcore.sample(data)
        if Missing.of(chosen).any:
            raise ValueError(f"x, x_dot or u: {refused}")
        # The refit of every chunk is the strong form's: so is the sample's.
        self._set_fitted(self._identify(chosen, allow_weak=False))
        warn(self.diagnostics_, stacklevel=4)
        try:
            done = outofcore.refit(self, data, chosen)
        except ValueError as exc:
            if "NaN" in str(exc):
                raise ValueError(f"x, x_dot or u: {refused}") from exc
            raise
        self.coef_sample_ = self.coef_
        self.coef_ = np.ascontiguousarray(done.coef.T)
        self.support_ = self.coef_ != 0
        self.screened_ = done.screened  # lazy: samples left out of the out-of-core refit
        self.unresolved_ = done.unresolved  # in memory: one byte per sample
        self.outliers_ = done.outliers
        self.diagnostics_.certified = self.diagnostics_.certified & done.certified
        self.dask_ = done.info
        for message in done.warnings:
            warnings.warn(IdentificationWarning(message, "out of core"), stacklevel=3)
        return self

    def check_params(self) -> None:
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
        for name in ("refit", "progress", "screen"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False; got {getattr(self, name)!r}")
        check_differentiation(self.differentiation)
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}; got {self.formulation!r}")
        if self.derivative_window not in DERIVATIVE_WINDOWS:
            raise ValueError(
                f"derivative_window must be one of {DERIVATIVE_WINDOWS}; "
                f"got {self.derivative_window!r}"
            )
        if self.solver_options is not None and not isinstance(self.solver_options, dict):
            raise ValueError(f"solver_options must be a dict or None; got {self.solver_options!r}")
        cons = self.constraints
        if not (
            cons is None
            or cons == "energy_preserving"
            or isinstance(cons, LinearConstraints)
            or (callable(cons) and not isinstance(cons, str))
        ):
            raise ValueError(
                "constraints must be None, 'energy_preserving', a LinearConstraints or a "
                f"callable returning one; got {cons!r}"
            )
        n_lams = self.n_lams
        if isinstance(n_lams, bool) or not isinstance(n_lams, Integral) or n_lams < 2:
            raise ValueError(f"n_lams must be an integer >= 2; got {n_lams!r}")
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

    # ------------------------------------------------------------------ using the model
    def _check_fitted(self, what: str):
        if not hasattr(self, "coef_"):
            raise NotFittedError(f"this HuberSINDy is not fitted yet: call fit before {what}")

    def _inputs(self, x, u) -> np.ndarray:
        q = getattr(self, "n_control_features_", 0)
        if u is None:
            if q:
                raise ValueError(f"u is required: the model was fitted with {q} controls")
            return x
        if u.shape[1] != q:
            raise ValueError(f"u has {u.shape[1]} columns but the model was fitted with {q}")
        return np.hstack([x, u])

    def save(self, path):
        """Write the fitted model to ``path`` as portable JSON (:func:`robust_sindy.io.save_model`;
        read it back with :func:`robust_sindy.load_model`)."""
        self._check_fitted("save")
        return io.save_model(self, path)

    def export_rhs(self):
        """The identified right-hand side as generated numpy code.

        Returns an :class:`~robust_sindy.export.ExportedRHS`.  ``f = model.export_rhs()``;
        ``f(t, x)`` (or ``f(t, x, u)``) gives the derivatives at ``x`` of shape (n,) or
        (m, n) without the library's per-call overhead, e.g. for
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
        if is_frame(x):
            frame = x
            u = u.to_numpy(dtype=float) if is_frame(u) else u
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
        data = Trajectories.from_user(x, t, x_dot, u)
        if data.n_samples < 2:
            raise ValueError(f"x has {data.n_samples} samples: a score needs at least 2")
        # Missing readings are filled for the library and the derivatives (as fit fills
        # them) but the score is of the samples with every reading.
        pairs = [
            tuple(None if v is None else fill_missing(v, ti).repaired for v in pair)
            for pair, ti in zip(data.pairs(), data.t or [None] * len(data.x), strict=True)
        ]  # fmt: skip
        ds = data.x_dot
        if ds is None:
            # The derivatives fit would have computed: windows guarded by the library.
            ds = [
                differentiate(
                    a, ti, self.differentiation, self.derivative_window,
                    library=self.library_.transform(self._inputs(a, b)),
                )
                for (a, b), ti in zip(pairs, data.t, strict=True)
            ]  # fmt: skip
        pred = np.vstack([self.predict(a, b) for a, b in pairs])
        y = np.vstack(ds)
        measured = ~(data.missing.any(axis=1) | data.missing_controls.any(axis=1))
        measured &= np.all(np.isfinite(y), axis=1)
        y, pred = y[measured], pred[measured]
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
            as_frame = is_series(x0)
        if is_series(x0):
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


def _boundedness(library, coef, n_states: int):
    """Energy preservation and the trapping-region test of a model of degree at most 2
    in the states (:mod:`robust_sindy.selection.stability`), or None."""
    powers = getattr(library, "powers_", None)
    if powers is None:
        return None
    parts = quadratic_parts(np.asarray(coef).T, powers, n_states)
    return None if parts is None else boundedness(*parts)


def load_model(path) -> HuberSINDy:
    """Read a model file written by :meth:`HuberSINDy.save` (:func:`robust_sindy.io.save_model`).

    The returned :class:`HuberSINDy` predicts, prints and simulates like the saved one;
    its diagnostics are the dict ``diagnostics_summary_``.
    """
    saved = io.read_model(path)
    model = HuberSINDy(library=saved.library, **saved.params)
    for name, value in saved.fitted.items():
        setattr(model, name, value)
    return model
