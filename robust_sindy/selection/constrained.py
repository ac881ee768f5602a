"""Selection under constraints: the model made to meet linear constraints.

``HuberSINDy(constraints=...)`` first selects the terms as without constraints (the
noise floor, the choice of delta and lambda, the final selection).  Then
:func:`constrained_selection` searches again under the constraints, over all
equations at once, for the support with the best information criterion:

* **tied terms are selected together**: coefficients that share a constraint form a
  group (:func:`coefficient_groups`; e.g. energy preservation pairs ``x0*x2`` in
  ``(x0)'`` with ``x0^2`` in ``(x2)'``), and a group enters or leaves as one.  The
  search starts from the unconstrained selection with every group it touches
  (:func:`tied_closure`);
* each candidate support is refitted without penalty under the constraints at the
  chosen delta (:func:`robust_sindy.fit` with ``constraints``, on the support's
  columns; every other coefficient held at zero), certified by the constrained KKT
  conditions.  Each equation's loss is taken on its own scale,
  ``sum_k H_1(r_k / delta_k) = sum_k H_{delta_k}(r_k) / delta_k^2`` (the targets and
  coefficients divided by ``delta_k``, the constraints' rows rescaled to match): the
  criterion weighs each equation's loss by ``1 / sigma_k^2`` alike, and a coefficient
  tied across equations is then set by the equations that determine it best.  The
  plain sum ``sum_k H_{delta_k}(r_k)`` (what :func:`robust_sindy.fit` solves) weighs
  an equation by ``delta_k^2``: the one with the largest residuals in its own units
  sets the tied coefficients;
* the criterion is the robust BIC of the unconstrained selection
  (:func:`robust_sindy.selection.criteria.information_criterion`: the Huber loss on
  the scale ``delta / 1.345``, the residuals' correlation time, ``log(m / tau)`` per
  term) summed over the equations, with one parameter fewer for each independent
  equality the support's coefficients must meet;
* groups are added or removed one at a time, the best change first, while the
  criterion falls; then single members of the groups in the support are removed the
  same way (a group's constraint may need only some of its members).  A constraint
  can make a term necessary that the unconstrained selection had no reason to keep: a
  quadratic term tied to another equation's must be balanced by a linear one, which
  then pays its way.

Then the significance rounds of the unconstrained selection run under the
constraints (``_prune``): the coefficient with the smallest robust t of the model
under them (:func:`constrained_significance`) is left out while it is below the bar,
where the criterion does not prefer keeping it by ``MIN_BIC_MARGIN`` or more.
Coefficients that the constraints hold at zero on the final support (an energy-
preserving model has no ``x0^2`` in ``(x0)'``) are left out of it.

The diagnostics describe the model under the constraints: the robust t of its
coefficients, the criterion's margin to the other supports the search refitted
(:meth:`ConstrainedRefit.margins`) and the terms that leaving out a block of the data
changes (:func:`constrained_stability`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.csgraph

from ..core.constraints import LinearConstraints
from ..core.losses import huber, huber_psi
from ..core.scaling import fitted_scale_factor, robust_scale
from ..core.statistics import correlation_time
from ..fitting import HUBER_EFFICIENCY_CONSTANT, ConvergenceWarning, delta_floor, fit
from .criteria import MIN_BIC_MARGIN, bic_from_loss, bic_terms, blocked_folds, score_margin
from .lam_path import pilot_budget
from .problem import Problem
from .significance import SIGNIFICANCE_ESTIMATED, sandwich_variance

__all__ = [
    "ConstrainedRefit",
    "build_constraints",
    "coefficient_groups",
    "constrained_selection",
    "constrained_significance",
    "constrained_stability",
    "held_off_support",
    "restricted",
    "scaled_fit",
    "tied_closure",
]

#: Rounds of the constrained model's delta (as :func:`robust_sindy.auto_delta`'s: a
#: refit and the robust scale of its residuals, until delta moves by less than 1 %).
DELTA_ROUNDS = 5


def build_constraints(spec, feature_names, states, shape) -> LinearConstraints:
    """``spec`` (``"energy_preserving"``, a :class:`LinearConstraints`, or a callable
    ``spec(feature_names, states)`` returning one) for coefficients of ``shape``
    (terms, equations)."""
    from .. import constraints as named

    if isinstance(spec, str):
        if spec != "energy_preserving":
            raise ValueError(
                "constraints must be None, 'energy_preserving', a LinearConstraints or a "
                f"callable returning one; got {spec!r}"
            )
        out = named.energy_preserving(feature_names, states=states)
    elif callable(spec) and not isinstance(spec, LinearConstraints):
        out = spec(list(feature_names), list(states))
    else:
        out = spec
    if not isinstance(out, LinearConstraints):
        raise ValueError(f"constraints must give a LinearConstraints; got {type(out).__name__}")
    out.check_shape(*shape)
    return out


def tied_closure(support: np.ndarray, constraints: LinearConstraints) -> np.ndarray:
    """``support`` (p, n) grown by every coefficient of a constraint that involves a
    coefficient in it, until nothing more joins."""
    grown = support.ravel(order="F").copy()
    rows = np.vstack([constraints.A_eq, constraints.A_ub]) != 0
    while True:
        touched = rows[(rows & grown).any(axis=1)].any(axis=0)
        new = grown | touched
        if np.array_equal(new, grown):
            return grown.reshape(support.shape, order="F")
        grown = new


def coefficient_groups(constraints: LinearConstraints) -> tuple[list, np.ndarray]:
    """The coefficients linked by shared constraints (connected components of the
    coefficients and the rows that involve them), as lists of ``vec`` indices (every
    coefficient in exactly one group), and whether each group must be selected (an
    equality of its rows has a nonzero right-hand side, which zeros cannot meet)."""
    size = constraints.n_terms * constraints.n_equations
    rows = np.vstack([constraints.A_eq, constraints.A_ub]) != 0
    r = rows.shape[0]
    link = scipy.sparse.coo_matrix(rows).tocsr()
    graph = scipy.sparse.bmat([[None, link.T], [link, None]], format="csr")
    if r == 0:
        labels = np.arange(size)
    else:
        labels = scipy.sparse.csgraph.connected_components(graph, directed=False)[1][:size]
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # groups in the order of their coefficients
    groups = [np.flatnonzero(inverse == g) for g in order]
    needed = rows[: constraints.A_eq.shape[0]][constraints.b_eq != 0].any(axis=0)
    return groups, np.array([bool(needed[g].any()) for g in groups])


def held_at_zero(constraints: LinearConstraints, support: np.ndarray) -> np.ndarray:
    """Coefficients of ``support`` (p, n) that its equalities hold at zero: those whose
    unit vector lies in the span of the equalities restricted to the support, with a
    zero value there."""
    on = np.flatnonzero(support.ravel(order="F"))
    out = np.zeros(support.size, dtype=bool)
    a = constraints.A_eq[:, on]
    keep = np.abs(a).sum(axis=1) > 0
    a, b = a[keep], constraints.b_eq[keep]
    if a.shape[0]:
        # e_j = a^T w: the coefficient is fixed at w . b.
        w, *_ = np.linalg.lstsq(a.T, np.eye(on.size), rcond=None)
        fixed = np.linalg.norm(a.T @ w - np.eye(on.size), axis=0) <= 1e-9
        value = b @ w
        scale = np.abs(b).max(initial=0.0)
        out[on] = fixed & (np.abs(value) <= 1e-12 * max(scale, 1e-300))
    return out.reshape(support.shape, order="F")


@dataclass(frozen=True)
class ConstrainedRefit:
    """Outcome of :func:`constrained_selection`.

    Attributes
    ----------
    coef : ndarray (p, n)
        The refitted coefficients (user units).
    support : ndarray of bool (p, n)
        The selected terms (with those tied to them by a constraint, less those the
        constraints hold at zero).
    residual : float
        The constraints' relative residual at ``coef``.
    converged : bool
        Whether the refit was certified.
    start : ndarray of bool (p, n), optional
        Where the search started: the unconstrained selection with its tied terms.
    score : float
        The summed criterion of the support.
    evaluated : int
        The supports refitted by the search.
    delta : ndarray (n,), optional
        The Huber threshold of the refit: the constrained model's own.
    unstable : ndarray of bool (n, p), optional
        :func:`constrained_stability` of the selected terms, when it was measured.
    significance : ndarray (p, n), optional
        :func:`constrained_significance` of the selected terms, when it was measured.
    pruned : ndarray (p, n), optional
        The robust t of each coefficient the significance rounds under the
        constraints left out (NaN elsewhere; None without them).
    candidates : ndarray (L, p, n), optional
        Every support the search refitted, as its refitted coefficients (those the
        constraints hold at zero left out), in the order the search tried them.
    scores : ndarray (L,), optional
        The summed criterion of each candidate.
    chosen : int
        The index of the chosen support among the candidates: the lowest score, less
        the terms the significance rounds left out.
    constraints : LinearConstraints, optional
        The constraints the refit meets (built from the model's ``constraints``).
    status : str
        The refit's solver status (why it was not certified, when it was not).
    """

    coef: np.ndarray
    support: np.ndarray
    residual: float
    converged: bool
    start: np.ndarray | None = None
    score: float = float("nan")
    evaluated: int = 0
    delta: np.ndarray | None = None
    unstable: np.ndarray | None = None
    significance: np.ndarray | None = None
    pruned: np.ndarray | None = None
    candidates: np.ndarray | None = None
    scores: np.ndarray | None = None
    chosen: int = -1
    constraints: LinearConstraints | None = None
    status: str = ""

    def margins(self) -> tuple[np.ndarray, np.ndarray]:
        """Per equation, the summed criterion of the best other candidate minus the
        best one's: over the candidates whose support differs from the best one's in
        that equation, and over those that are another model than the one chosen there
        (they leave out one of its terms or change one of its coefficients by more
        than half; :func:`~robust_sindy.selection.criteria.score_margin`, the chosen
        model as its ``reference``: the best one less the terms the significance rounds
        left out); ``inf`` when there is none.  A candidate that changes several
        equations counts in each."""
        n = self.coef.shape[1]
        if self.candidates is None or not len(self.scores):
            return np.full(n, np.inf), np.full(n, np.inf)
        scores = np.repeat(np.asarray(self.scores, dtype=float)[:, None], n, axis=1)
        best = self.chosen
        if self.scores[best] > self.scores.min():
            best = int(np.argmin(self.scores))
        best = np.full(n, best)
        return (
            score_margin(scores, self.candidates, best),
            score_margin(
                scores, self.candidates, best, rivals=True,
                reference=self.candidates[self.chosen],
            ),
        )  # fmt: skip


def held_off_support(constraints: LinearConstraints, support) -> LinearConstraints:
    """``constraints`` with every coefficient off ``support`` (p, n) held at zero (one
    equality each, labelled "not selected")."""
    out = np.flatnonzero(~np.asarray(support, dtype=bool).ravel(order="F"))
    zeros = np.zeros((out.size, constraints.n_terms * constraints.n_equations))
    zeros[np.arange(out.size), out] = 1.0
    return constraints + LinearConstraints(
        *constraints.shape, zeros, np.zeros(out.size),
        labels_eq=tuple("not selected" for _ in out),
    )  # fmt: skip


def scaled_fit(
    theta, y, delta, constraints: LinearConstraints, *, method: str = "admm", solver=None,
    warm_start=None, **options,
):  # fmt: skip
    """The unpenalised fit of ``y`` (m, n) on ``theta`` (m, p) under ``constraints``
    with each equation's loss on the scale of its ``delta`` (n,):
    ``sum_k H_1(r_k / delta_k) = sum_k H_{delta_k}(r_k) / delta_k^2`` (see the module
    docstring), solved by :func:`robust_sindy.fit` on the targets and coefficients
    divided by ``delta_k`` (the constraints' rows rescaled to match), from
    ``warm_start`` (p, n; the fast path's), with further ``options`` for
    :func:`robust_sindy.fit` (Dask arrays are solved out of core).  Returns
    ``(coef, result)``: the
    coefficients in the units of ``y``, and the :class:`~robust_sindy.FitResult` of the
    rescaled problem with its coefficients, per-equation objectives (``H_{delta_k}``
    losses), thresholds and dual (``psi_{delta_k}(r_k)``) back in those units; its
    certificate is that of the problem solved."""
    n = y.shape[1]
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (n,))
    # xi_k = delta_k xi'_k: the rows act on the rescaled coefficients through delta.
    unit = np.repeat(delta, theta.shape[1])
    scaled = LinearConstraints(
        theta.shape[1], n, constraints.A_eq * unit, constraints.b_eq,
        constraints.A_ub * unit, constraints.b_ub,
    )  # fmt: skip
    method = method if method in ("admm", "cvxpy") else "admm"
    if method == "admm" and warm_start is not None:
        options["warm_start"] = np.asarray(warm_start, dtype=float) / delta
    result = fit(
        theta, y / delta, method=method, delta=1.0, lam=0.0,
        solver=solver if method == "cvxpy" else None, constraints=scaled, **options,
    )  # fmt: skip
    result = replace(
        result, coef=result.coef * delta, objective=result.objective * delta**2,
        delta=delta.copy(), dual=None if result.dual is None else result.dual * delta,
    )  # fmt: skip
    return result.coef, result


def restricted(constraints: LinearConstraints, support) -> tuple[np.ndarray, LinearConstraints]:
    """The library columns some equation uses on ``support`` (p, n), and
    ``constraints`` with every coefficient off the support held at zero, on those
    columns only (the rows left that bind nothing are dropped): the problem a refit on
    ``support`` solves."""
    p, n = support.shape
    cols = np.flatnonzero(support.any(axis=1))
    held = held_off_support(constraints, support)
    idx = (cols[:, None] + p * np.arange(n)[None, :]).ravel(order="F")
    rows = (held.A_eq[:, idx] != 0).any(axis=1) | (held.b_eq != 0)
    sub = LinearConstraints(
        cols.size, n, held.A_eq[rows][:, idx], held.b_eq[rows], held.A_ub[:, idx], held.b_ub,
    )  # fmt: skip
    return cols, sub


def _refit(
    kept: Problem, support, delta, constraints: LinearConstraints, method, solver, start=None,
    budget=True,
):  # fmt: skip
    """:func:`scaled_fit` on ``support`` (p, n), on the columns some equation uses
    (every other coefficient is zero), from ``start`` (p, n).  Returns
    ``(coef, result)``.  These refits only propose decisions (the search's candidates,
    the stability blocks): with ``budget``, ADMM gets the iterations of the other such
    fits (:func:`~robust_sindy.selection.lam_path.pilot_budget`), and no refit warns
    (the chosen model's certificate is reported by the diagnostics)."""
    p, n = support.shape
    coef = np.zeros((p, n))
    if not support.any():
        return coef, None
    cols, sub = restricted(constraints, support)
    warm = None if start is None else np.where(support[cols], np.asarray(start)[cols], 0.0)
    options = pilot_budget(method) if budget else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        fitted, result = scaled_fit(
            kept.theta[:, cols], kept.y, delta, sub, method=method, solver=solver,
            warm_start=warm, **options,
        )  # fmt: skip
    coef[cols] = np.where(support[cols], fitted, 0.0)
    return coef, result


def _outcome(coef, support, constraints, result, **extra) -> ConstrainedRefit:
    support = support & ~held_at_zero(constraints, support)
    coef = np.where(support, coef, 0.0)
    converged = True if result is None else bool(result.converged)
    status = "" if result is None else str(result.messages[0])
    return ConstrainedRefit(
        coef, support, constraints.residual(coef), converged, **extra, status=status
    )


def constrained_selection(
    kept: Problem, coef, delta, constraints: LinearConstraints, *, method: str, solver=None,
    bar: float | None = None,
) -> ConstrainedRefit:  # fmt: skip
    """The support with the best summed criterion under ``constraints``, from the
    unconstrained selection ``coef`` (p, n) with its tied terms, by adding or removing
    one group of tied coefficients at a time; with ``bar``, then without the terms the
    data do not vouch for under the constraints (``_prune``; see the module
    docstring)."""
    p, n = np.shape(coef)
    m = kept.theta.shape[0]
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (n,)).copy()
    groups, needed = coefficient_groups(constraints)

    def mask(indices):
        """The coefficients ``indices`` (of ``vec``) as a (p, n) mask."""
        out = np.zeros(p * n, dtype=bool)
        out[indices] = True
        return out.reshape(p, n, order="F")

    masks = [mask(g) for g in groups]
    start = tied_closure(np.asarray(coef) != 0, constraints)
    for g in (g for g, need in zip(masks, needed, strict=True) if need):
        start |= g
    # The criterion's scales, as in the unconstrained selection but for the model under
    # the constraints: delta and the correlation time of the residuals of the most
    # complete constrained model (every term, no penalty), delta from their robust
    # scale as auto_delta measures it.
    every = np.ones((p, n), dtype=bool)
    full = None
    factor = HUBER_EFFICIENCY_CONSTANT * fitted_scale_factor(*kept.theta.shape)
    for _ in range(DELTA_ROUNDS):
        full, _result = _refit(kept, every, delta, constraints, method, solver, full)
        r = kept.y - kept.theta @ full
        new = np.maximum(factor * robust_scale(r), delta_floor(kept.y))
        change = np.abs(new - delta) / delta
        delta = new
        if change.max() < 1e-2:
            break
    tau = correlation_time(huber_psi(r, delta), kept.segments)
    sigma, penalty = bic_terms(m, delta, tau)
    cache = {}

    def score(support, warm):
        key = support.tobytes()
        if key not in cache:
            refit, result = _refit(kept, support, delta, constraints, method, solver, warm)
            loss = huber(kept.y - kept.theta @ refit, delta).sum(axis=0)
            on = support.ravel(order="F")
            a = constraints.A_eq[:, on]
            tied = np.linalg.matrix_rank(a) if a.size else 0
            value = float(
                np.sum(bic_from_loss(loss, support.sum(axis=0), sigma, penalty, tau))
                - tied * penalty.mean()
            )
            cache[key] = (value, refit, result, support)
        return cache[key][0]

    current, best = start, score(start, full)

    def descend(moves):
        """The best of ``moves(current)`` while it lowers the criterion."""
        nonlocal current, best
        while True:
            # Each trial differs from the current support by one move: its refit starts
            # from the current one (the fast path's warm start).
            here = cache[current.tobytes()][1]
            trials = moves(current)
            if not trials:
                return
            values = [score(trial, here) for trial in trials]
            k = int(np.argmin(values))
            if not values[k] < best:
                return
            current, best = trials[k], values[k]

    movable = [g for g, need in zip(masks, needed, strict=True) if not need]
    descend(lambda now: [now & ~g if (now & g).any() else now | g for g in movable])
    # Then single members out of groups of two or more: a group's constraint may need
    # only some of them (Lorenz's energy row ties x1*x2 in (x0)', x0*x2 in (x1)' and
    # x0*x1 in (x2)', and the first is zero).
    tied = [
        mask(j) for g, need in zip(groups, needed, strict=True) if len(g) > 1 and not need
        for j in g
    ]  # fmt: skip
    descend(lambda now: [now & ~one for one in tied if (now & one).any()])
    pruned, value = None, best
    if bar is not None:

        def significance(support):
            _, refit, _, _ = cache[support.tobytes()]
            on = support & ~held_at_zero(constraints, support)
            found = ConstrainedRefit(refit, on, 0.0, True, delta=delta)
            return constrained_significance(kept, found, constraints), on

        def trial(support):
            value = score(support, cache[current.tobytes()][1])
            return value, *significance(support)

        current, pruned = _prune(current, (value, *significance(current)), trial, bar)
    value, refit, result, _ = cache[current.tobytes()]
    if result is not None and not result.converged:
        # The chosen model gets the solver's whole budget (the search's refits had the
        # candidates' one), from where the search left it.
        refit, result = _refit(kept, current, delta, constraints, method, solver, refit, False)
    candidates = np.array([
        np.where(held_at_zero(constraints, s), 0.0, c) for _, c, _, s in cache.values()
    ])  # fmt: skip
    return _outcome(
        refit, current, constraints, result, start=start, score=value, evaluated=len(cache),
        delta=delta, candidates=candidates, scores=np.array([v[0] for v in cache.values()]),
        chosen=list(cache).index(current.tobytes()), pruned=pruned,
    )  # fmt: skip


def _prune(current, at, trial, bar):
    """The significance rounds of the unconstrained selection
    (:func:`robust_sindy.selection.final.prune`) under the constraints: the selected
    coefficient with the smallest robust t (:func:`constrained_significance`) is left
    out while it is below ``bar``, one at a time over all equations (a constraint may
    tie it to others, which then go with it), in equations with a coefficient at
    ``SIGNIFICANCE_ESTIMATED`` or more, and only where the criterion does not prefer
    keeping it by ``MIN_BIC_MARGIN`` or more: the data vouch for the term by neither
    measure.  A drop after which its equation has no coefficient at
    ``SIGNIFICANCE_ESTIMATED`` is undone.  A term kept against the statistic stays
    in the model, and the warnings on its significance say so.  ``at = (score, t, on)``:
    the criterion, the statistic and the support (without the coefficients the
    constraints hold at zero) of ``current``; ``trial(support)`` refits a support and
    returns the same.  Returns the support and the t of each coefficient left out (NaN
    elsewhere)."""
    value, t, on = at
    pruned = np.full(t.shape, np.nan)
    spared = np.zeros(t.shape, dtype=bool)  # kept by the criterion's guard

    def vouched(t, on):
        # A coefficient the constraints fix (t = inf) is not the data's evidence.
        seen = np.where(on & np.isfinite(t), t, 0.0)
        return seen.max(axis=0) >= SIGNIFICANCE_ESTIMATED

    for _ in range(int(on.sum())):
        low = on & ~spared & (np.nan_to_num(t, nan=np.inf) < bar) & vouched(t, on)[None, :]
        if not low.any():
            break
        j, k = np.unravel_index(np.argmin(np.where(low, t, np.inf)), t.shape)
        support = current.copy()
        support[j, k] = False
        value_new, t_new, on_new = trial(support)
        if value_new - value >= MIN_BIC_MARGIN or not vouched(t_new, on_new)[k]:
            spared[j, k] = True
            continue
        gone = on & ~on_new
        pruned[gone] = t[gone]
        current, value, t, on = support, value_new, t_new, on_new
    return current, pruned


def constrained_significance(
    kept: Problem, found: ConstrainedRefit, constraints: LinearConstraints
) -> np.ndarray:
    """Robust t statistic (p, n) of every coefficient of ``found`` under
    ``constraints`` (NaN off the support): the sandwich covariance of
    :func:`~robust_sindy.selection.significance.robust_t` taken over the selected
    coefficients of all equations at once, in the directions the equalities and the
    active inequalities leave free.

    With ``beta`` the selected coefficients and ``Z`` a basis of the null space of those
    rows restricted to them, ``V = Z (Z^T H Z)^{-1} Z^T B Z (Z^T H Z)^{-1} Z^T``: ``H``
    is block diagonal (each equation's inliers), ``B`` holds the scores'
    cross-products within and across equations (the same sample's errors reach every
    equation), each block scaled by ``sqrt(tau_j tau_k)``, the correlation times of the
    two equations' scores.  A coefficient the constraints fix (no free direction moves
    it) has zero variance and the statistic ``inf``: the constraint, not the data,
    vouches for it.  Where the selected columns are rank deficient on the inliers in the
    free directions the statistic is 0."""
    support = np.asarray(found.support, dtype=bool)
    p, n = support.shape
    out = np.full(p * n, np.nan)
    on = np.flatnonzero(support.ravel(order="F"))
    if on.size == 0:
        return out.reshape(p, n, order="F")
    scaler = kept.scaler
    coef = scaler.coef_to_standard(found.coef)
    theta, delta = kept.theta_s, kept.delta_standard(found.delta)
    r = kept.y_s - theta @ coef
    psi = huber_psi(r, delta)
    tau = correlation_time(psi, kept.segments)
    eq, term = on // p, on % p
    # The objective the search minimises, sum_k H_1(r_k / delta_k): its scores and
    # curvature per equation carry 1 / delta_k^2.
    scores = theta[:, term] * (psi / delta**2)[:, eq]
    b = (scores.T @ scores) * np.sqrt(np.outer(tau[eq], tau[eq]))
    h = np.zeros((on.size, on.size))
    for k in np.unique(eq):
        q = np.flatnonzero(eq == k)
        a = theta[np.abs(r[:, k]) <= delta[k]][:, term[q]]
        h[np.ix_(q, q)] = a.T @ a / delta[k] ** 2
    # The rows that bind the selected coefficients, in the standardised units: an
    # equality, or an inequality met with equality.
    rows = np.vstack([constraints.A_eq, constraints.A_ub[constraints.active(found.coef)]])
    unit = (scaler.y_scale[None, :] / scaler.theta_scale[:, None]).ravel(order="F")
    rows = rows[:, on] * unit[on]
    rows = rows[np.abs(rows).sum(axis=1) > 0]
    free = scipy.linalg.null_space(rows) if rows.shape[0] else np.eye(on.size)
    if free.shape[1] == 0:
        out[on] = np.inf
        return out.reshape(p, n, order="F")
    var = sandwich_variance(h, b, free)
    if var is None:
        out[on] = 0.0
        return out.reshape(p, n, order="F")
    # Rounding leaves a fixed coefficient a variance of order eps times the others'.
    fixed = np.linalg.norm(free, axis=1) <= 1e-10
    beta = np.abs(coef.ravel(order="F")[on])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = beta / np.sqrt(np.maximum(var, 0.0))
    out[on] = np.where(fixed, np.inf, np.where(var > 0, t, np.inf))
    return out.reshape(p, n, order="F")


def constrained_stability(
    kept: Problem, found: ConstrainedRefit, constraints: LinearConstraints, *, blocks: int,
    tolerance: float, method: str, solver=None,
) -> np.ndarray:  # fmt: skip
    """Selected terms (n, p) of ``found`` that leaving out one of ``blocks`` contiguous
    blocks of the kept samples changes (sign, or by more than ``tolerance`` of the
    value) when its support is refitted under ``constraints`` at its delta: the
    stability check of the unconstrained model
    (:func:`robust_sindy.diagnostics.stability`), with the constraints that tie the
    equations (refitted one by one without them, tied terms swing freely)."""
    coef, support = found.coef, found.support
    m = kept.theta.shape[0]
    unstable = np.zeros(support.shape, dtype=bool)
    if not support.any() or m < blocks * (support.sum(axis=0).max() + 2):
        return unstable.T
    for _, left_out in blocked_folds(m, blocks):
        rows = np.ones(m, dtype=bool)
        rows[left_out] = False
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c, _ = _refit(kept.keep(rows), support, found.delta, constraints, method, solver, coef)
        moved = (np.sign(c) != np.sign(coef)) | (np.abs(c - coef) > tolerance * np.abs(coef))
        unstable |= support & moved
    return unstable.T
