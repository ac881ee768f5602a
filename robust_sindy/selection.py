"""Choosing delta and lambda.

* :func:`lambda_max` — per column, the smallest ``lam`` whose solution is all zeros:
  ``xi = 0`` is optimal iff ``|Theta_j^T psi_delta(xdot)| <= lam`` for every ``j``.
* :func:`auto_delta` — the robust-statistics rule ``delta = 1.345 sigma_hat`` with
  ``sigma_hat`` the MAD-based scale (:func:`robust_scale`) of the residuals of an
  unpenalised Huber pilot fit, iterated: 95 % efficiency at Gaussian residuals,
  bounded influence beyond.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> theta = rng.normal(size=(2000, 4))
>>> xdot = theta @ np.array([1.0, -2.0, 0.0, 0.5]) + 0.1 * rng.normal(size=2000)
>>> bad = rng.choice(2000, 400, replace=False)
>>> xdot[bad] += rng.normal(scale=20.0, size=400)      # 20 % gross outliers
>>> sigma = auto_delta(theta, xdot) / 1.345
>>> bool(abs(sigma - 0.1) < 0.02)
True
"""

from __future__ import annotations

import numpy as np
import scipy.stats

from ._fit import fit
from ._losses import huber_psi
from ._validation import check_int, check_problem, loss_delta

__all__ = ["HUBER_EFFICIENCY_CONSTANT", "auto_delta", "lambda_max", "robust_scale"]

#: Tuning constant of the Huber loss with 95 % efficiency at the Gaussian.
HUBER_EFFICIENCY_CONSTANT = 1.345


def lambda_max(theta, xdot, delta=1.0, loss: str = "huber") -> np.ndarray | float:
    """Smallest ``lam`` per column for which ``coef = 0`` solves the problem.

    Returns an array (n,), or a float when ``xdot`` is 1-D.
    """
    theta, y, one_d = check_problem(theta, xdot)
    d = loss_delta(loss, delta, y.shape[1])
    out = np.abs(theta.T @ huber_psi(y, d)).max(axis=0)
    return float(out[0]) if one_d else out


def robust_scale(residuals, cutoff: float = 3.0, n_iter: int = 20) -> np.ndarray:
    """Gaussian scale of the bulk of ``residuals`` (m,) or (m, n), per column.

    Starts from ``1.4826 MAD`` and refines it by the truncated variance: the mean square
    of the residuals within ``cutoff`` scales of the median, divided by its Gaussian
    expectation ``1 - 2 c phi(c) / (2 Phi(c) - 1)``, repeated until it settles.  The MAD
    alone is inflated by a fraction ``eps`` of gross outliers (by about 30 % at
    ``eps = 0.2``, since the median of ``|r|`` then sits at a higher quantile of the
    inliers); the refinement removes that bias once the outliers lie beyond ``cutoff``
    scales, and is consistent at the Gaussian.
    """
    r = np.asarray(residuals, dtype=float)
    one_d = r.ndim == 1
    r = r[:, None] if one_d else r
    c = float(cutoff)
    kappa = 1.0 - 2 * c * scipy.stats.norm.pdf(c) / (2 * scipy.stats.norm.cdf(c) - 1)
    out = np.empty(r.shape[1])
    for k in range(r.shape[1]):
        centred = r[:, k] - np.median(r[:, k])
        s = scipy.stats.median_abs_deviation(centred, scale="normal")
        for _ in range(n_iter):
            if s == 0:
                break
            inside = centred[np.abs(centred) <= c * s]
            new = np.sqrt(np.mean(inside**2) / kappa)
            done = abs(new - s) <= 1e-6 * s
            s = new
            if done:
                break
        out[k] = s
    return out[0] if one_d else out


def auto_delta(
    theta,
    xdot,
    *,
    n_iter: int = 5,
    rtol: float = 1e-2,
    floor: float = 1e-4,
    method: str = "admm",
) -> np.ndarray | float:
    """Per-column Huber threshold from the residual scale of a robust pilot fit.

    Start from the residuals of ordinary least squares; then repeat up to ``n_iter``
    times: ``delta = 1.345 * robust_scale(r)``, refit the unpenalised Huber regression
    (``lam = 0``) with that ``delta``, take its residuals ``r``; stop once ``delta``
    changes by less than ``rtol`` (relative).

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    n_iter : int
        Maximum pilot refits.
    rtol : float
        Relative change of ``delta`` that ends the iteration.
    floor : float
        ``delta`` is at least ``floor`` times the root mean square of the column.  A
        column fitted exactly (residuals at rounding level, e.g. an equation of
        noise-free inputs) has no residual scale to measure; below this floor a smaller
        ``delta`` changes no decision about gross outliers, and it would turn the pilot
        into an ill-conditioned least-absolute-deviation fit.
    method : {"admm", "cvxpy"}
        Solver of the pilot fits.

    Returns
    -------
    ndarray (n,), or float when ``xdot`` is 1-D.
    """
    theta, y, one_d = check_problem(theta, xdot)
    n_iter = check_int(n_iter, "n_iter", 1)
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"method must be 'admm' or 'cvxpy' for the pilot fit; got {method!r}")
    lower = floor * np.sqrt(np.mean(y**2, axis=0))
    lower = np.where(lower > 0, lower, 1.0)
    residual = y - theta @ np.linalg.lstsq(theta, y, rcond=None)[0]
    delta = np.maximum(HUBER_EFFICIENCY_CONSTANT * robust_scale(residual), lower)
    # Columns already fitted to the floor by least squares have nothing to refine.
    todo = np.flatnonzero(delta > lower)
    for _ in range(n_iter):
        if todo.size == 0:
            break
        res = fit(theta, y[:, todo], method=method, delta=delta[todo], lam=0.0)
        r = y[:, todo] - theta @ res.coef
        new = np.maximum(HUBER_EFFICIENCY_CONSTANT * robust_scale(r), lower[todo])
        change = np.abs(new - delta[todo]) / delta[todo]
        delta[todo] = new
        todo = todo[change >= rtol]
    return float(delta[0]) if one_d else delta


def threshold_refit(
    theta,
    xdot,
    coef,
    delta,
    *,
    tol: float = 0.005,
    max_rounds: int = 10,
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
    """
    theta, y, one_d = check_problem(theta, xdot)
    coef = np.asarray(coef, dtype=float).reshape(theta.shape[1], y.shape[1]).copy()
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (y.shape[1],))
    col = np.linalg.norm(theta, axis=0)
    ynorm = np.linalg.norm(y, axis=0)
    rounds = check_int(max_rounds, "max_rounds", 1)
    for k in range(y.shape[1]):
        keep = coef[:, k] != 0
        for _ in range(rounds):
            contribution = np.abs(coef[:, k]) * col / max(ynorm[k], np.finfo(float).tiny)
            new_keep = keep & (contribution >= tol)
            refit = np.zeros(theta.shape[1])
            if new_keep.any():
                refit[new_keep] = fit(
                    theta[:, new_keep], y[:, k], method, delta[k], 0.0, solver=solver, **options
                ).coef
            coef[:, k] = refit
            if np.array_equal(new_keep, keep):
                break
            keep = new_keep
    return coef[:, 0] if one_d else coef
