"""Long-term boundedness of a quadratic model: energy preservation and a trapping region.

A model ``x' = c + L x + Q(x)`` with a quadratic part ``Q`` that conserves energy
(``x^T Q(x) = 0`` for every ``x``: no cubic term in ``d|x|^2/2 dt``) is bounded when a
shifted energy ``|x - m|^2 / 2`` decreases outside a ball: with ``y = x - m``,

.. math::

    \\frac{d}{dt} \\tfrac12 |y|^2 = y^T A_m y + y^T d_m, \\qquad
    A_m = \\operatorname{sym}(L + J_Q(m)),

(``J_Q(m)`` the Jacobian of ``Q`` at ``m``), so a centre ``m`` with ``A_m`` negative
definite gives a trapping region (Schlegel & Noack 2015, J. Fluid Mech. 765:325).
``A_m`` is affine in ``m``, so the smallest largest eigenvalue over ``m`` is a convex
problem (a semidefinite program, solved by CVXPY): negative certifies boundedness;
otherwise this test cannot decide (it is sufficient, not necessary).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..solvers.reference import solve_problem

__all__ = ["Boundedness", "boundedness", "quadratic_parts"]

#: Relative size of the cubic coefficients of the energy rate below which the quadratic
#: part counts as energy-preserving.
ENERGY_TOL = 1e-8


def quadratic_parts(coef, powers, n_states: int):
    """``(c (n,), L (n, n), q (n, n, n))`` of a model ``coef`` (n, p) whose terms are the
    monomials ``powers`` (tuples of input indices, as ``PolynomialLibrary.powers_``),
    ``Q_i(x) = sum_jk q[i, j, k] x_j x_k`` with ``q`` symmetric in ``j, k``; None when
    a term of degree above 2 or with a control input has a nonzero coefficient."""
    coef = np.asarray(coef, dtype=float)
    n = n_states
    c, lin, q = np.zeros(n), np.zeros((n, n)), np.zeros((n, n, n))
    for j, combo in enumerate(powers):
        col = coef[:, j]
        if not np.any(col):
            continue
        if len(combo) > 2 or any(i >= n for i in combo):
            return None
        if len(combo) == 0:
            c += col
        elif len(combo) == 1:
            lin[:, combo[0]] += col
        else:
            a, b = combo
            if a == b:
                q[:, a, a] += col
            else:
                q[:, a, b] += col / 2
                q[:, b, a] += col / 2
    return c, lin, q


@dataclass(frozen=True)
class Boundedness:
    """Outcome of :func:`boundedness`.

    Attributes
    ----------
    energy_residual : float
        The largest cubic coefficient of ``x^T Q(x)`` over the largest quadratic
        coefficient (0 for an energy-preserving quadratic part).
    energy_preserving : bool
        ``energy_residual <= ENERGY_TOL``.
    trapping_eigenvalue : float
        The smallest largest eigenvalue of ``A_m`` over the centres ``m`` (NaN when the
        quadratic part does not conserve energy, or the solver failed; ``-inf`` when
        it is unbounded below); negative certifies a trapping region.
    centre : ndarray (n,) or None
        The centre ``m`` that attains it.
    """

    energy_residual: float
    energy_preserving: bool
    trapping_eigenvalue: float
    centre: np.ndarray | None

    @property
    def bounded(self) -> bool:
        """A trapping region was found: every trajectory stays bounded."""
        return bool(self.energy_preserving and self.trapping_eigenvalue < 0)


def boundedness(c, lin, q) -> Boundedness:
    """Energy preservation of ``q`` and the trapping-region test (module docstring)."""
    n = lin.shape[0]
    sym = (
        q
        + q.transpose(0, 2, 1)
        + q.transpose(1, 0, 2)
        + q.transpose(1, 2, 0)
        + q.transpose(2, 0, 1)
        + q.transpose(2, 1, 0)
    ) / 6
    size = float(np.abs(q).max(initial=0.0))
    residual = float(np.abs(sym).max(initial=0.0)) / size if size > 0 else 0.0
    preserving = residual <= ENERGY_TOL
    if not preserving:
        return Boundedness(residual, False, float("nan"), None)
    import cvxpy as cp

    m = cp.Variable(n)
    # J_Q(m)[i, j] = 2 sum_k q[i, j, k] m_k, affine in m.
    jac = sum(2 * q[:, :, k] * m[k] for k in range(n)) if size > 0 else 0
    a = lin + jac
    problem = cp.Problem(cp.Minimize(cp.lambda_max((a + a.T) / 2)))
    try:
        solve_problem(problem, "CLARABEL", False, {})
    except (cp.error.SolverError, cp.error.DCPError):
        return Boundedness(residual, True, float("nan"), None)
    if problem.status == cp.UNBOUNDED:
        return Boundedness(residual, True, float("-inf"), None)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or m.value is None:
        return Boundedness(residual, True, float("nan"), None)
    centre = np.asarray(m.value, dtype=float)
    # The eigenvalue at the centre found, recomputed: the certificate, not the solver.
    mat = lin + np.einsum("ijk,k->ij", 2 * q, centre)
    top = float(np.linalg.eigvalsh((mat + mat.T) / 2).max())
    return Boundedness(residual, True, top, centre)
