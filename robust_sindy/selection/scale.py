"""Residual scale and the automatic Huber threshold."""

from __future__ import annotations

import numpy as np

from .._fit import fit
from .._scaling import robust_scale
from .._validation import check_int, check_problem

__all__ = ["HUBER_EFFICIENCY_CONSTANT", "auto_delta", "robust_scale"]

#: Tuning constant of the Huber loss with 95 % efficiency at the Gaussian.
HUBER_EFFICIENCY_CONSTANT = 1.345


def auto_delta(
    theta,
    xdot,
    *,
    n_iter: int = 5,
    rtol: float = 1e-2,
    floor: float = 1e-4,
    method: str = "admm",
    **options,
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
    **options
        Solver options of the pilot fits (see :func:`robust_sindy.fit`).

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
        res = fit(theta, y[:, todo], method=method, delta=delta[todo], lam=0.0, **options)
        r = y[:, todo] - theta @ res.coef
        new = np.maximum(HUBER_EFFICIENCY_CONSTANT * robust_scale(r), lower[todo])
        change = np.abs(new - delta[todo]) / delta[todo]
        delta[todo] = new
        todo = todo[change >= rtol]
    return float(delta[0]) if one_d else delta


def _check_method(method: str, what: str) -> str:
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"method must be 'admm' or 'cvxpy' for {what}; got {method!r}")
    return method
