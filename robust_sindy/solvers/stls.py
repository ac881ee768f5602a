"""Conventional least-squares baselines: STLS (sequential thresholding) and OLS.

STLS (Brunton, Proctor & Kutz 2016) alternates a least-squares fit on the current
support with zeroing every coefficient whose magnitude is below ``threshold``, until
the support stops changing.  OLS is the unthresholded least-squares fit, which is what
the paper's Lorenz "conventional" column looks like (README, erratum E9).
"""

from __future__ import annotations

import numpy as np

from .problem import SolverOutput

__all__ = ["solve_ols", "solve_stls"]


def _lstsq(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(a, b, rcond=None)[0]


def solve_ols(theta: np.ndarray, y: np.ndarray) -> SolverOutput:
    """Least squares ``min ||y - Theta xi||^2`` per column (minimum norm if rank-deficient)."""
    n = y.shape[1]
    return SolverOutput(
        coef=_lstsq(theta, y),
        iterations=np.ones(n, dtype=int),
        converged=np.ones(n, dtype=bool),
        messages=["least squares"] * n,
    )


def solve_stls(
    theta: np.ndarray, y: np.ndarray, *, threshold: float = 0.05, max_sweeps: int = 5000
) -> SolverOutput:
    """Sequentially thresholded least squares, column by column.

    Parameters
    ----------
    theta : ndarray, shape (m, p)
    y : ndarray, shape (m, n)
    threshold : float
        Coefficients with ``|xi_j| < threshold`` are set to zero (paper: 0.05).
    max_sweeps : int
        Maximum number of threshold-and-refit sweeps (paper: 5000).

    A column is converged when a sweep leaves its support unchanged.
    """
    p, n = theta.shape[1], y.shape[1]
    coef = np.zeros((p, n))
    sweeps = np.zeros(n, dtype=int)
    converged = np.zeros(n, dtype=bool)
    messages = []
    for k in range(n):
        support = np.ones(p, dtype=bool)
        xi = np.zeros(p)
        for sweep in range(1, max_sweeps + 1):
            xi = np.zeros(p)
            if support.any():
                xi[support] = _lstsq(theta[:, support], y[:, k])
            new_support = np.abs(xi) >= threshold
            sweeps[k] = sweep
            if np.array_equal(new_support, support):
                converged[k] = True
                break
            support = new_support
        coef[:, k] = xi
        messages.append(
            f"support stable after {sweeps[k]} sweeps"
            if converged[k]
            else f"support still changing after {max_sweeps} sweeps"
        )
    return SolverOutput(coef=coef, iterations=sweeps, converged=converged, messages=messages)
