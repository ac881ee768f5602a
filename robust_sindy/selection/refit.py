"""The selection stage: drop terms of small relative contribution, refit the rest."""

from __future__ import annotations

import numpy as np

from ..core.losses import huber_psi
from ..core.validation import check_int, check_problem
from ..fitting import fit

__all__ = [
    "STAGE_ROUNDS",
    "added_term_sums",
    "debias",
    "one_step_contributions",
    "refit_column",
    "select_column",
    "threshold_refit",
]

#: Rounds of the selection stage (drop, refit) before the support must be stable.
STAGE_ROUNDS = 10


def refit_column(theta, y, keep, delta, method, solver, options) -> np.ndarray:
    """Huber fit with ``lam = 0`` on the columns ``keep`` (zeros elsewhere)."""
    coef = np.zeros(theta.shape[1])
    if keep.any():
        coef[keep] = fit(theta[:, keep], y, method, delta, 0.0, solver=solver, **options).coef
    return coef


def select_column(coef, tol, rounds, col, ynorm, refit, cache=None):
    """The selection stage on one column (see :func:`threshold_refit`)."""
    keep = coef != 0
    for _ in range(rounds):
        contribution = np.abs(coef) * col / max(ynorm, np.finfo(float).tiny)
        new_keep = keep & (contribution >= tol)
        key = new_keep.tobytes()
        if cache is not None and key in cache:
            coef = cache[key]
        else:
            coef = refit(new_keep)
            if cache is not None:
                cache[key] = coef
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return coef


def threshold_refit(
    theta,
    xdot,
    coef,
    delta,
    *,
    tol: float = 0.005,
    max_rounds: int = STAGE_ROUNDS,
    method: str = "admm",
    solver: str | None = None,
    **options,
) -> np.ndarray:
    """Selection stage after a penalised fit: drop small terms, refit the rest, repeat.

    A term ``j`` of equation ``k`` is dropped when its relative contribution
    ``|xi_jk| ||theta_j|| / ||xdot_k||`` is below ``tol``; the kept terms are refitted
    by the Huber loss with ``lam = 0`` (removing the L1 shrinkage), until the support
    stops changing or ``max_rounds`` is reached.  ``tol = 0`` with ``max_rounds = 1`` is a
    plain debiasing refit of the given support.  ``method``, ``solver`` and ``options``
    go to :func:`robust_sindy.fit`.  Returns the new coefficients (p, n), or (p,) for a
    1-D ``xdot``.

    The default ``tol = 0.005`` keeps terms that carry half a percent of their equation's
    signal: true terms under 2 % occur in standard chaotic systems, so 0.01 already
    loses some.
    """
    theta, y, one_d = check_problem(theta, xdot)
    coef = np.asarray(coef, dtype=float).reshape(theta.shape[1], y.shape[1]).copy()
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (y.shape[1],))
    if not np.isfinite(tol) or tol < 0:
        raise ValueError(f"tol must be a finite number >= 0; got {tol!r}")
    rounds = check_int(max_rounds, "max_rounds", 1)
    col = np.linalg.norm(theta, axis=0)
    ynorm = np.linalg.norm(y, axis=0)
    for k in range(y.shape[1]):

        def refit(keep, k=k):
            return refit_column(theta, y[:, k], keep, delta[k], method, solver, options)

        coef[:, k] = select_column(coef[:, k], tol, rounds, col, ynorm[k], refit)
    return coef[:, 0] if one_d else coef


def debias(theta, y, coef, delta, method: str, solver, options: dict) -> np.ndarray:
    """Refit every equation's nonzero terms by Huber with ``lam = 0`` (the L1 penalty's
    shrinkage removed): :func:`threshold_refit` with ``tol = 0`` and one round, by
    ``method`` when it is a Huber method (else the fast path), ``solver`` for CVXPY."""
    method = method if method in ("admm", "cvxpy") else "admm"
    solver = solver if method == "cvxpy" else None
    return threshold_refit(
        theta, y, coef, delta, tol=0.0, max_rounds=1, method=method, solver=solver, **options
    )


def added_term_sums(theta, sel, psi, w):
    """What adding each column ``theta_j`` to the selected columns ``theta[:, sel]`` of
    a Huber fit (score ``psi`` at its residuals, weights ``w``: 1 inside ``delta``, 0
    outside) has to work with, from ``theta_jp = theta_j - theta[:, sel] g_j``, the part
    of ``theta_j`` ``W``-orthogonal to the selected columns (expanded, not formed: m x p
    per column).  Returns ``g`` (s, p), ``theta_jp^T psi`` (p,), ``theta_jp^T W
    theta_jp`` (p,) and ``theta_j^T W theta_j`` (p,)."""
    tw = theta * w[:, None]
    b = tw[:, sel].T @ theta  # (s, p)
    g = np.linalg.lstsq(b[:, sel], b, rcond=None)[0] if sel.size else b
    inner = np.einsum("ij,ij->j", tw, theta)
    num = theta.T @ psi - g.T @ (theta[:, sel].T @ psi)
    return g, num, inner - np.einsum("ij,ij->j", b, g), inner


def one_step_contributions(theta, xdot, coef, delta) -> np.ndarray:
    """Relative contribution each unselected term would have if added (p, n; NaN on the
    support).

    One Newton step of the Huber fit of each column from its current solution, with the
    term ``j`` added: ``xi_j = theta_jp^T psi(r) / theta_jp^T W theta_jp`` where ``r`` is
    the residual, ``W`` the Huber weights (1 inside ``delta``, 0 outside) and
    ``theta_jp`` the part of ``theta_j`` ``W``-orthogonal to the selected columns; its
    contribution is ``|xi_j| ||theta_j|| / ||xdot||`` as in :func:`threshold_refit`.
    Terms the inliers cannot tell from the selected ones get NaN.
    """
    theta, y, _ = check_problem(theta, xdot)
    coef = np.asarray(coef, dtype=float).reshape(theta.shape[1], y.shape[1])
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (y.shape[1],))
    col = np.linalg.norm(theta, axis=0)
    out = np.full(coef.shape, np.nan)
    for k in range(y.shape[1]):
        sel = np.flatnonzero(coef[:, k])
        r = y[:, k] - theta @ coef[:, k]
        psi = huber_psi(r, delta[k])
        _, num, den, _ = added_term_sums(theta, sel, psi, (np.abs(r) <= delta[k]).astype(float))
        ok = (coef[:, k] == 0) & (den > 1e-10 * col**2)
        ynorm = max(float(np.linalg.norm(y[:, k])), np.finfo(float).tiny)
        out[ok, k] = np.abs(num[ok] / den[ok]) * col[ok] / ynorm
    return out
