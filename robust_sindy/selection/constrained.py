"""The constrained refit: the selected model made to meet linear constraints.

``HuberSINDy(constraints=...)`` selects the terms as without constraints (the noise
floor, the choice of delta and lambda, the final selection), then refits the selected
terms under the constraints, over all equations at once
(:func:`robust_sindy.fit` with ``constraints``, unpenalised, at the chosen delta):

* **tied terms are selected together**: a constraint that involves a selected
  coefficient brings in every coefficient it involves (repeated until nothing more
  joins; e.g. energy preservation pairs ``x0*x2`` in ``(x0)'`` with ``x0^2`` in
  ``(x2)'``);
* every other coefficient is held at zero (one equality each);
* the refit is certified by the constrained KKT conditions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.constraints import LinearConstraints
from ..fitting import fit
from .problem import Problem

__all__ = ["ConstrainedRefit", "build_constraints", "constrained_refit", "tied_closure"]


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


@dataclass(frozen=True)
class ConstrainedRefit:
    """Outcome of :func:`constrained_refit`.

    Attributes
    ----------
    coef : ndarray (p, n)
        The refitted coefficients (user units).
    support : ndarray of bool (p, n)
        The selected terms with those tied to them by a constraint.
    residual : float
        The constraints' relative residual at ``coef``.
    converged : bool
        Whether the refit was certified.
    """

    coef: np.ndarray
    support: np.ndarray
    residual: float
    converged: bool


def constrained_refit(
    kept: Problem, coef, delta, constraints: LinearConstraints, *, method: str, solver=None
) -> ConstrainedRefit:
    """The selected terms of ``coef`` (p, n) and those tied to them, refitted without
    penalty under ``constraints`` at ``delta`` on the kept samples."""
    support = tied_closure(np.asarray(coef) != 0, constraints)
    p, n = support.shape
    out = np.flatnonzero(~support.ravel(order="F"))
    zeros = np.zeros((out.size, p * n))
    zeros[np.arange(out.size), out] = 1.0
    held = constraints + LinearConstraints(
        p, n, zeros, np.zeros(out.size), labels_eq=tuple("not selected" for _ in out)
    )
    result = fit(
        kept.theta, kept.y, method=method if method in ("admm", "cvxpy") else "admm",
        delta=delta, lam=0.0, solver=solver if method == "cvxpy" else None, constraints=held,
    )  # fmt: skip
    coef = np.where(support, result.coef, 0.0)
    return ConstrainedRefit(coef, support, constraints.residual(coef), bool(result.converged))
