"""``lambda_max`` and the warm-started ``lam`` path."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from ..core.certificates import accept_within_floor, certify
from ..core.losses import huber_psi
from ..core.validation import as_float_array, check_int, check_positive, check_problem, loss_delta
from ..fitting import (
    ConvergenceWarning,
    auto_delta,
    check_huber_method,
    fast_path_options,
    fast_path_verdict,
    fit,
)
from ..solvers import driver, problem

__all__ = ["PATH_MAX_ITER", "Path", "lambda_max", "path"]

#: ADMM iteration limit per path point in :func:`select` (unless ``max_iter`` is given).
PATH_MAX_ITER = 1000


def pilot_budget(method: str) -> dict:
    """Solver options of fits that only propose a decision (path points, pilots,
    candidate refits): the iteration budget :data:`PATH_MAX_ITER` for ADMM, their
    certificates not required."""
    return {"max_iter": PATH_MAX_ITER} if method == "admm" else {}


def lambda_max(theta, xdot, delta=1.0, loss: str = "huber") -> np.ndarray | float:
    """Smallest ``lam`` per column for which ``coef = 0`` solves the problem.

    Returns an array (n,), or a float when ``xdot`` is 1-D.
    """
    theta, y, one_d = check_problem(theta, xdot)
    d = loss_delta(loss, delta, y.shape[1])
    out = np.abs(theta.T @ huber_psi(y, d)).max(axis=0)
    return float(out[0]) if one_d else out


@dataclass(repr=False)
class Path:
    """Solutions along a decreasing ``lam`` grid (:func:`path`).

    Attributes
    ----------
    lams : ndarray, shape (L, n)
        The grid per target column, decreasing.
    coef : ndarray, shape (L, p, n)
    objective, kkt : ndarray, shape (L, n)
        Objective and relative KKT violation of every point.
    n_nonzero : ndarray of int, shape (L, n)
    converged : ndarray of bool, shape (L, n)
        Whether each point is certified.
    delta, lambda_max : ndarray, shape (n,)
    solve_time : float
        Seconds for the whole path.
    walked : ndarray of bool, shape (L, n)
        The points solved: all of them, unless the caller stopped a column early
        (``until`` of :func:`path`); a point not walked has zero coefficients, ``nan``
        objective and KKT, and is not certified.
    """

    lams: np.ndarray
    coef: np.ndarray
    objective: np.ndarray
    kkt: np.ndarray
    n_nonzero: np.ndarray
    converged: np.ndarray
    delta: np.ndarray
    lambda_max: np.ndarray
    solve_time: float
    walked: np.ndarray | None = None

    def __post_init__(self):
        if self.walked is None:
            self.walked = np.ones(self.lams.shape, dtype=bool)

    def __repr__(self) -> str:
        walked = "" if self.walked.all() else f"walked {int(self.walked.sum())}, "
        kkt = np.max(self.kkt[self.walked], initial=0.0)
        return (
            f"Path({self.lams.shape[0]} points x {self.lams.shape[1]} columns, {walked}"
            f"certified {int(self.converged.sum())}/{int(self.walked.sum())}, "
            f"max kkt={kkt:.1e}, solve_time={self.solve_time:.3g}s)"
        )


def _grid(lmax, lams, n_lams, eps, n):
    if lams is None:
        n_lams = check_int(n_lams, "n_lams", 1)
        eps = check_positive(eps, "eps", upper=1.0)
        return lmax[None, :] * np.logspace(0.0, np.log10(eps), n_lams)[:, None]
    grid = as_float_array(lams, "lams", (1, 2))
    grid = np.repeat(grid[:, None], n, axis=1) if grid.ndim == 1 else grid
    if grid.shape[1] != n:
        raise ValueError(f"lams must have shape (L,) or (L, {n}); got {grid.shape}")
    if (grid < 0).any():
        raise ValueError("lams must be >= 0")
    if (np.diff(grid, axis=0) > 0).any():
        raise ValueError("lams must be decreasing down each column (the path is warm-started)")
    return grid


#: Entries of the residual blocks formed at a time when a path's points are certified
#: together (``m x points x columns``; small enough to stay in cache).
_CERTIFY_BLOCK = 2**15


def _certify_points(theta, y, coef, delta, grid, col_norms, progress):
    """Objective, relative KKT violation and relative duality gap (L, n) of every path
    point, in the user's units: the points' columns side by side, a block of points at
    a time (one product with ``Theta`` per block)."""
    L, p, n = coef.shape
    m = theta.shape[0]
    out = np.zeros((3, L, n))
    size = max(1, _CERTIFY_BLOCK // max(m * n, 1))
    with tqdm(total=L, desc="lam path", disable=not progress, leave=False) as bar:
        for lo in range(0, L, size):
            k = min(size, L - lo)
            xi = coef[lo : lo + k].transpose(1, 0, 2).reshape(p, k * n)
            yk = y if k == 1 else np.tile(y, (1, k))
            lam = grid[lo : lo + k].reshape(1, k * n)
            cert = certify(theta, yk, xi, np.tile(delta, k), lam, col_norms)
            for row, value in enumerate((cert.objective, cert.kkt, cert.rel_gap)):
                out[row, lo : lo + k] = value.reshape(k, n)
            bar.update(k)
    return out


def path(
    theta,
    xdot,
    delta=1.0,
    lams=None,
    n_lams: int = 50,
    eps: float = 1e-4,
    *,
    method: str = "admm",
    solver: str | None = None,
    warm_start: bool = True,
    progress: bool = False,
    until=None,
    **options,
) -> Path:
    """Solve the Huber-Lasso along a decreasing grid of ``lam``.

    The default grid has ``n_lams`` points from ``lambda_max`` (where the solution is
    zero) down to ``eps * lambda_max``, log-spaced, per column.  With
    ``method="admm"`` the library is equilibrated and factorised once, and each point
    starts from the previous solution: where the compiled iteration applies, it walks
    the whole grid, every point reusing the previous one's last pass and inlier Gram
    matrix (:func:`robust_sindy.solvers.driver.solve_path`), else each point is a fast
    path fit from the previous solution and its dual.  Either way every point is
    certified in the user's units, as a single fit is (``warm_start=False`` solves every
    point cold, for comparison).  ``method="cvxpy"`` solves every point with the
    reference solver.

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    delta : float, array_like (n,), or "auto"
    lams : array_like, shape (L,) or (L, n), optional
        Decreasing grid (overrides ``n_lams`` and ``eps``).
    n_lams : int
    eps : float in (0, 1)
    method : {"admm", "cvxpy"}
    solver : {"clarabel", "osqp"}, optional
        For ``method="cvxpy"``.
    warm_start : bool
    progress : bool
        Show a progress bar.
    until : callable, optional
        ``until(i, coef, cols)``, called after point ``i`` with its coefficients
        (p, n) and the columns solved there (int array), returns a boolean array over
        ``cols``: the columns it marks are not solved at later points
        (``Path.walked``).  Where the compiled iteration walks the whole grid at once,
        it is called on every point in order after the walk, with the same columns.
    **options
        Options of :func:`robust_sindy.fit` for the chosen method (not ``warm_start``).

    Returns
    -------
    Path

    Warns
    -----
    ConvergenceWarning
        When points could not be certified.
    """
    theta, y, _ = check_problem(theta, xdot)
    check_huber_method(method, "the path")
    if not isinstance(warm_start, bool):
        raise ValueError(f"warm_start must be True or False; got {warm_start!r}")
    if "warm_start" in options:
        raise ValueError("warm_start is set by path itself (True or False)")
    n = y.shape[1]
    if isinstance(delta, str) and delta == "auto":
        delta = np.atleast_1d(auto_delta(theta, y, method=method))
    delta_k = loss_delta("huber", delta, n)
    lmax = np.atleast_1d(lambda_max(theta, y, delta_k))
    grid = _grid(lmax, lams, n_lams, eps, n)
    L, p = grid.shape[0], theta.shape[1]
    coef = np.zeros((L, p, n))
    obj, kkt = np.full((L, n), np.nan), np.full((L, n), np.nan)
    conv = np.zeros((L, n), dtype=bool)
    active = np.ones(n, dtype=bool)

    def stop_after(i, cols):  # the caller's verdict on the columns solved at point i
        if until is not None and cols.size:
            active[cols[np.asarray(until(i, coef[i], cols), dtype=bool)]] = False

    t0 = time.perf_counter()
    if method == "admm":
        if solver is not None:
            raise ValueError(f"solver applies to method='cvxpy' only; got solver={solver!r}")
        opts = fast_path_options(options, theta, y)
        opts.pop("warm_start")
        prepared = problem.prepare(theta, equilibrate=opts["equilibrate"], kappa=opts["kappa"])
        col_norms = np.linalg.norm(theta, axis=0)
        # Warm-started, the compiled iteration walks the whole grid (each point from the
        # last one's solution, last pass and inlier Gram matrix); every point is then
        # certified here in the user's units, as a single fit is.
        walk = None
        if warm_start:
            walk = driver.solve_path(theta, y, delta_k, grid, prepared=prepared, **opts)

        def accepted(solved, kkt, rel_gap):  # the solver's verdict and the certificate's
            return solved & ((kkt <= opts["tol"]) | (rel_gap <= opts["gap_tol"]))

        if walk is not None:
            coef[:] = walk[0]
            obj[:], kkt[:], rel_gap = _certify_points(
                theta, y, coef, delta_k, grid, col_norms, progress
            )
            conv[:] = accepted(walk[1], kkt, rel_gap)
            # As for a single fit (fast_path_verdict, by the same helper): a violation
            # within what the rounding of the point's residuals can leave is certified.
            for i in np.flatnonzero(~conv.all(axis=1)):
                conv[i] = accept_within_floor(theta, y, coef[i], delta_k, kkt[i], conv[i])[0]
            walked = np.ones((L, n), dtype=bool)
            for i in range(L):
                stop_after(i, np.flatnonzero(active))
        else:
            walked = np.zeros((L, n), dtype=bool)
            previous = None
            psi = np.zeros_like(y)
            for i in tqdm(range(L), desc="lam path", disable=not progress, leave=False):
                cols = np.flatnonzero(active)
                if cols.size == 0:
                    break
                start = None if previous is None else (previous[:, cols], psi[:, cols])
                out = driver.solve(
                    theta, y[:, cols], delta_k[cols], grid[i, cols], warm_start=start,
                    prepared=prepared, **opts,
                )  # fmt: skip
                cert = certify(
                    theta, y[:, cols], out.coef, delta_k[cols], grid[i, cols][None, :],
                    col_norms,
                )  # fmt: skip
                coef[i][:, cols], obj[i, cols], kkt[i, cols] = out.coef, cert.objective, cert.kkt
                conv[i, cols] = fast_path_verdict(
                    theta, y[:, cols], out, cert.kkt, cert, delta_k[cols], opts["tol"],
                    opts["gap_tol"],
                )  # fmt: skip
                walked[i, cols] = True
                if warm_start:
                    previous, psi[:, cols] = coef[i], cert.psi
                stop_after(i, cols)
    else:
        walked = np.zeros((L, n), dtype=bool)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            for i in tqdm(range(L), desc="lam path", disable=not progress, leave=False):
                cols = np.flatnonzero(active)
                if cols.size == 0:
                    break
                res = fit(theta, y[:, cols], "cvxpy", delta_k[cols], grid[i, cols],
                          solver=solver, **options)  # fmt: skip
                coef[i][:, cols], obj[i, cols], kkt[i, cols] = res.coef, res.objective, res.kkt
                conv[i, cols] = res.column_converged
                walked[i, cols] = True
                stop_after(i, cols)
    elapsed = time.perf_counter() - t0
    bad = walked & ~conv
    if bad.any():
        warnings.warn(
            f"{int(bad.sum())} of {int(walked.sum())} path points were not certified "
            f"(largest relative KKT {kkt[bad].max():.1e}); see Path.converged. "
            "Try method='cvxpy' or a larger delta.",
            ConvergenceWarning,
            stacklevel=2,
        )
    return Path(
        lams=grid,
        coef=coef,
        objective=obj,
        kkt=kkt,
        n_nonzero=np.count_nonzero(coef, axis=1),
        converged=conv,
        delta=delta_k,
        lambda_max=lmax,
        solve_time=elapsed,
        walked=walked,
    )
