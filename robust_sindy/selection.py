"""Choosing delta and lambda.

* :func:`lambda_max` — per column, the smallest ``lam`` whose solution is all zeros:
  ``xi = 0`` is optimal iff ``|Theta_j^T psi_delta(xdot)| <= lam`` for every ``j``.
* :func:`auto_delta` — the robust-statistics rule ``delta = 1.345 sigma_hat`` with
  ``sigma_hat`` the MAD-based scale (:func:`robust_scale`) of the residuals of an
  unpenalised Huber pilot fit, iterated: 95 % efficiency at Gaussian residuals,
  bounded influence beyond.
* :func:`screen_rows` — flags whole samples whose pilot residual is gross in any
  well-fitted equation (errors in the library rows are bad-leverage points that no
  ``delta`` can down-weight).
* :func:`path` — a warm-started decreasing ``lam`` grid from :func:`lambda_max`, one
  factorisation for the whole path, every point certified.
* :func:`threshold_refit` — the selection stage: drop terms of small relative
  contribution, refit the rest by Huber with ``lam = 0``, until the support is stable.
* :func:`select` — runs the path, the selection stage at every point, and picks
  ``lam`` per equation by a robust BIC (:func:`information_criterion`) or by blocked
  cross-validation (:func:`blocked_folds`) scored with the Huber loss.

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

import itertools
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.stats
from tqdm import tqdm

from ._certificates import certify
from ._fit import ConvergenceWarning, _admm_options, fit
from ._losses import huber, huber_psi
from ._validation import as_float_array, check_int, check_positive, check_problem, loss_delta
from .solvers import admm

__all__ = [
    "CRITERIA",
    "HUBER_EFFICIENCY_CONSTANT",
    "Path",
    "Screening",
    "Selection",
    "auto_delta",
    "blocked_folds",
    "information_criterion",
    "lambda_max",
    "path",
    "robust_scale",
    "screen_rows",
    "select",
    "threshold_refit",
]

#: Criteria :func:`select` accepts.
CRITERIA = ("bic", "cv")
#: Rounds of the selection stage (drop, refit) before the support must be stable.
STAGE_ROUNDS = 10
#: ADMM iteration limit per path point in :func:`select` (unless ``max_iter`` is given).
PATH_MAX_ITER = 1000

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


def _check_method(method: str, what: str) -> str:
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"method must be 'admm' or 'cvxpy' for {what}; got {method!r}")
    return method


def _refit_column(theta, y, keep, delta, method, solver, options) -> np.ndarray:
    """Huber fit with ``lam = 0`` on the columns ``keep`` (zeros elsewhere)."""
    coef = np.zeros(theta.shape[1])
    if keep.any():
        coef[keep] = fit(theta[:, keep], y, method, delta, 0.0, solver=solver, **options).coef
    return coef


def _select_column(coef, tol, rounds, col, ynorm, refit, cache=None):
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
            return _refit_column(theta, y[:, k], keep, delta[k], method, solver, options)

        coef[:, k] = _select_column(coef[:, k], tol, rounds, col, ynorm[k], refit)
    return coef[:, 0] if one_d else coef


# --------------------------------------------------------------------------- screening
@dataclass(repr=False)
class Screening:
    """Outcome of :func:`screen_rows`.

    Attributes
    ----------
    outliers : ndarray of bool, shape (m,)
        Samples flagged as gross outliers (excluded from the fit).
    trusted : ndarray of bool, shape (n,)
        Equations whose residuals took part in the flagging.
    scale : ndarray, shape (n,)
        Robust residual scale per equation on the kept samples.
    relative_scale : ndarray, shape (n,)
        ``scale`` divided by the root mean square of the equation's target.
    high_leverage : ndarray of bool, shape (m,)
        Samples left out of the first pilot fit because a library value was extreme.
    rounds : int
        Pilot refits until the flags stopped changing.
    converged : bool
        False when ``max_rounds`` ended the iteration with the flags still changing.
    """

    outliers: np.ndarray
    trusted: np.ndarray
    scale: np.ndarray
    relative_scale: np.ndarray
    high_leverage: np.ndarray
    rounds: int
    converged: bool

    def __repr__(self) -> str:
        return (
            f"Screening(flagged {int(self.outliers.sum())} of {self.outliers.size} samples, "
            f"trusted equations {np.flatnonzero(self.trusted).tolist()}, "
            f"rounds={self.rounds}, converged={self.converged})"
        )


def _extreme_rows(theta: np.ndarray, cutoff: float) -> np.ndarray:
    """Rows with a library value beyond ``cutoff`` robust scales of its column's median."""
    varying = np.ptp(theta, axis=0) > 0
    if not varying.any():
        return np.zeros(theta.shape[0], dtype=bool)
    t = theta[:, varying]
    centred = t - np.median(t, axis=0)
    s = robust_scale(centred)
    s = np.where(s > 0, s, np.inf)
    return (np.abs(centred) > cutoff * s).any(axis=1)


def screen_rows(
    theta,
    xdot,
    *,
    cutoff: float = 3.5,
    trust: float = 10.0,
    well_fitted: float = 0.05,
    max_rounds: int = 10,
    method: str = "admm",
) -> Screening:
    """Flag samples that are gross outliers in the library rows or the targets.

    The contamination of measured states hits whole samples, and an error in a library
    row is a bad-leverage point: it pulls every fit towards it, whatever ``delta``.
    The screen:

    1. fits an unpenalised Huber pilot (``delta`` by :func:`auto_delta`) on the samples
       whose library values are all within ``cutoff`` robust scales of their column's
       median (so that the first pilot is not dragged by leverage);
    2. measures each equation's robust residual scale ``s_k`` on the kept samples
       (at least ``1e-4`` of the target's root mean square);
    3. trusts equation ``k`` when its relative scale ``s_k / rms(xdot_k)`` is at most
       ``max(trust * best, well_fitted)``, ``best`` being the smallest relative scale;
    4. flags a sample when its residual is more than ``cutoff * s_k`` from the median in
       any trusted equation, refits the pilot on the kept samples and repeats from 2
       until the flags are stable (at most ``max_rounds`` refits).

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    cutoff : float
        Robust standard deviations beyond which a residual is gross.
    trust : float
        How much worse than the best equation's relative scale a trusted one may be.
    well_fitted : float
        Equations with relative scale up to this are trusted in any case.
    max_rounds : int
    method : {"admm", "cvxpy"}
        Solver of the pilot fits.

    Returns
    -------
    Screening

    Examples
    --------
    >>> import numpy as np
    >>> from robust_sindy.noise import contaminate
    >>> from robust_sindy.systems import Lorenz
    >>> lorenz = Lorenz()
    >>> data = lorenz.generate()
    >>> noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))
    >>> theta = lorenz.fitted_library().transform(noisy.x)
    >>> s = screen_rows(theta, noisy.x_dot)
    >>> int(noisy.outliers.sum()), int((s.outliers & noisy.outliers).sum())
    (200, 200)
    """
    theta, y, _ = check_problem(theta, xdot)
    cutoff = check_positive(cutoff, "cutoff")
    trust = check_positive(trust, "trust")
    well_fitted = check_positive(well_fitted, "well_fitted")
    rounds = check_int(max_rounds, "max_rounds", 1)
    _check_method(method, "the pilot fits")
    m = theta.shape[0]
    rms = np.sqrt(np.mean(y**2, axis=0))
    rms = np.where(rms > 0, rms, 1.0)
    leverage = _extreme_rows(theta, cutoff)
    keep = ~leverage
    if keep.sum() < max(theta.shape[1] + 1, m // 2):
        keep = np.ones(m, dtype=bool)  # too little left to fit: start from everything
    flags = None
    converged = False
    done_rounds = 0
    for _ in range(rounds):
        done_rounds += 1
        delta = np.atleast_1d(auto_delta(theta[keep], y[keep], method=method))
        coef = fit(theta[keep], y[keep], method, delta, 0.0).coef.reshape(theta.shape[1], -1)
        r = y - theta @ coef
        scale = np.maximum(robust_scale(r[keep]), 1e-4 * rms)
        scale = np.atleast_1d(scale)
        rel = scale / rms
        trusted = rel <= max(trust * rel.min(), well_fitted)
        centre = np.median(r[keep], axis=0)
        new = (np.abs(r - centre)[:, trusted] > cutoff * scale[trusted]).any(axis=1)
        if flags is not None and np.array_equal(new, flags):
            converged = True
            break
        flags = new
        keep = ~flags
        if keep.sum() <= theta.shape[1]:
            break
    return Screening(flags, trusted, scale, rel, leverage, done_rounds, converged)


# --------------------------------------------------------------------------- lam path
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

    def __repr__(self) -> str:
        return (
            f"Path({self.lams.shape[0]} points x {self.lams.shape[1]} columns, "
            f"certified {int(self.converged.sum())}/{self.converged.size}, "
            f"max kkt={self.kkt.max():.1e}, solve_time={self.solve_time:.3g}s)"
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
    **options,
) -> Path:
    """Solve the Huber-Lasso along a decreasing grid of ``lam``.

    The default grid has ``n_lams`` points from ``lambda_max`` (where the solution is
    zero) down to ``eps * lambda_max``, log-spaced, per column.  With
    ``method="admm"`` the library is equilibrated and factorised once, and each point
    starts from the previous solution and its dual (``warm_start=False`` solves every
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
    _check_method(method, "the path")
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
    obj, kkt = np.zeros((L, n)), np.zeros((L, n))
    conv = np.zeros((L, n), dtype=bool)
    t0 = time.perf_counter()
    if method == "admm":
        if solver is not None:
            raise ValueError(f"solver applies to method='cvxpy' only; got solver={solver!r}")
        opts = _admm_options(options, theta, y, False, "huber")
        opts.pop("warm_start")
        prepared = admm.prepare(theta, equilibrate=opts["equilibrate"], kappa=opts["kappa"])
        col_norms = np.linalg.norm(theta, axis=0)
        previous = None
        for i in tqdm(range(L), desc="lam path", disable=not progress, leave=False):
            out = admm.solve_admm(
                theta, y, delta_k, grid[i], warm_start=previous, prepared=prepared, **opts
            )
            cert = certify(theta, y, out.coef, delta_k, grid[i][None, :], col_norms)
            coef[i], obj[i], kkt[i] = out.coef, cert.objective, cert.kkt
            conv[i] = out.converged & (
                (cert.kkt <= opts["tol"]) | (cert.rel_gap <= opts["gap_tol"])
            )
            if warm_start:
                previous = (out.coef, cert.psi)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            for i in tqdm(range(L), desc="lam path", disable=not progress, leave=False):
                res = fit(theta, y, "cvxpy", delta_k, grid[i], solver=solver, **options)
                coef[i], obj[i], kkt[i] = res.coef, res.objective, res.kkt
                conv[i] = res.column_converged
    elapsed = time.perf_counter() - t0
    if not conv.all():
        warnings.warn(
            f"{int((~conv).sum())} of {conv.size} path points were not certified "
            f"(largest relative KKT {kkt[~conv].max():.1e}); see Path.converged. "
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
    )


# --------------------------------------------------------------------------- criteria
def information_criterion(theta, xdot, coef, delta, scale=None) -> np.ndarray | float:
    """Robust BIC per column: ``2 sum_i rho(r_i / sigma) + k log m``.

    ``rho`` is Huber's loss with threshold ``c = delta / sigma`` in standardised units,
    i.e. ``2 sum_i H_delta(r_i) / sigma**2``; ``k`` counts the nonzero coefficients and
    ``sigma`` is ``scale`` (default ``delta / 1.345``, the scale :func:`auto_delta`
    measured).  At Gaussian residuals it is the usual BIC; gross residuals add only
    linearly.  Returns (n,), or a float for a 1-D ``xdot``.
    """
    theta, y, one_d = check_problem(theta, xdot)
    n = y.shape[1]
    delta_k = loss_delta("huber", delta, n)
    coef = np.asarray(coef, dtype=float).reshape(theta.shape[1], n)
    sigma = (
        delta_k / HUBER_EFFICIENCY_CONSTANT
        if scale is None
        else np.broadcast_to(np.asarray(scale, float), (n,))
    )
    loss = huber(y - theta @ coef, delta_k).sum(axis=0)
    out = 2.0 * loss / sigma**2 + np.count_nonzero(coef, axis=0) * np.log(theta.shape[0])
    return float(out[0]) if one_d else out


def blocked_folds(m: int, n_folds: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """Contiguous blocks of samples as validation sets: ``[(train, test), ...]``.

    Time series samples are not exchangeable: neighbouring samples are nearly equal,
    so shuffled folds validate on copies of the training data.  Each test set here is
    one contiguous block of ``m // n_folds`` or one more samples, in time order.
    """
    m = check_int(m, "m", 1)
    n_folds = check_int(n_folds, "n_folds", 2)
    if n_folds > m:
        raise ValueError(f"n_folds ({n_folds}) must not exceed the number of samples ({m})")
    edges = np.linspace(0, m, n_folds + 1).round().astype(int)
    idx = np.arange(m)
    return [(np.concatenate([idx[:a], idx[b:]]), idx[a:b]) for a, b in itertools.pairwise(edges)]


@dataclass(repr=False)
class Selection:
    """Outcome of :func:`select`.

    Attributes
    ----------
    coef : ndarray, shape (p, n)
        The selected model: the selection stage's refit at the chosen ``lam``.
    lam, delta : ndarray, shape (n,)
    index : ndarray of int, shape (n,)
        Chosen position on the path per column.
    scores : ndarray, shape (L, n)
        The criterion at every path point (lower is better).
    candidates : ndarray, shape (L, p, n)
        The selection stage's refit at every path point.
    support : ndarray of bool, shape (p, n)
    path : Path
    criterion : str
    """

    coef: np.ndarray
    lam: np.ndarray
    delta: np.ndarray
    index: np.ndarray
    scores: np.ndarray
    candidates: np.ndarray
    support: np.ndarray
    path: Path
    criterion: str

    def __repr__(self) -> str:
        return (
            f"Selection(criterion={self.criterion!r}, "
            f"lam={np.array2string(self.lam, precision=3)}, "
            f"terms per column={self.support.sum(axis=0).tolist()})"
        )


def _stage_all(theta, y, path_coef, delta, tol, method, solver, options):
    """Selection stage at every path point, refits shared between identical supports."""
    L, _, n = path_coef.shape
    out = np.zeros_like(path_coef)
    col = np.linalg.norm(theta, axis=0)
    ynorm = np.linalg.norm(y, axis=0)
    for k in range(n):
        cache: dict = {}

        def refit(keep, k=k):
            return _refit_column(theta, y[:, k], keep, delta[k], method, solver, options)

        for i in range(L):
            out[i, :, k] = _select_column(
                path_coef[i, :, k], tol, STAGE_ROUNDS, col, ynorm[k], refit, cache
            )
    return out


def _pick(scores: np.ndarray) -> np.ndarray:
    """Per column the lowest score; ties go to the sparsest (earliest) point."""
    best = np.nanmin(scores, axis=0)
    tie = scores <= best + 1e-9 * np.maximum(np.abs(best), 1.0)
    return np.argmax(tie, axis=0)


def select(
    theta,
    xdot,
    delta="auto",
    *,
    criterion: str = "bic",
    n_lams: int = 50,
    eps: float = 1e-4,
    tol: float = 0.005,
    n_folds: int = 5,
    method: str = "admm",
    solver: str | None = None,
    progress: bool = False,
    **options,
) -> Selection:
    """Choose ``lam`` per equation: path, selection stage, then a robust criterion.

    1. :func:`path` over ``n_lams`` values from ``lambda_max`` to ``eps lambda_max``;
    2. at every point the selection stage (:func:`threshold_refit` with ``tol``): terms
       below ``tol`` relative contribution are dropped and the rest refitted by Huber
       with ``lam = 0``;
    3. ``criterion="bic"``: :func:`information_criterion` of each refit;
       ``criterion="cv"``: the same path and stage on the training blocks of
       :func:`blocked_folds`, scored by the mean Huber loss on the held-out block
       (squared error on held-out data would be dominated by the outliers).

    The lowest score wins; ties go to the larger ``lam``.

    Parameters
    ----------
    theta : array_like, shape (m, p)
    xdot : array_like, shape (m,) or (m, n)
    delta : float, array_like (n,), or "auto"
    criterion : {"bic", "cv"}
    n_lams, eps : int, float
        The grid of :func:`path`.
    tol : float
        Relative contribution below which the selection stage drops a term.
    n_folds : int
        Blocks for ``criterion="cv"``.
    method : {"admm", "cvxpy"}
    solver : str, optional
        For ``method="cvxpy"``.
    progress : bool
        Show progress bars.
    **options
        Solver options (see :func:`robust_sindy.fit`).

    Returns
    -------
    Selection

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> theta = rng.normal(size=(500, 8))
    >>> xdot = theta @ np.array([2.0, 0, 0, -1.0, 0, 0, 0.5, 0]) + 0.05 * rng.normal(size=500)
    >>> xdot[::7] += 30.0 * rng.normal(size=xdot[::7].size)       # gross outliers
    >>> sel = select(theta, xdot)
    >>> np.flatnonzero(sel.support[:, 0]).tolist()
    [0, 3, 6]
    >>> np.round(sel.coef[[0, 3, 6], 0], 2).tolist()
    [2.0, -1.0, 0.5]
    """
    theta, y, _ = check_problem(theta, xdot)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}; got {criterion!r}")
    _check_method(method, "the selection")
    if not np.isfinite(tol) or tol < 0:
        raise ValueError(f"tol must be a finite number >= 0; got {tol!r}")
    if isinstance(delta, str) and delta == "auto":
        delta = np.atleast_1d(auto_delta(theta, y, method=method))
    delta_k = loss_delta("huber", delta, y.shape[1])
    # Path points only propose supports, so ADMM gets fewer iterations there than in a
    # single fit (its Newton finish certifies most points at once; near-LAD points on
    # exact data may need thousands); the refits keep the full budget.
    path_options = {**({"max_iter": PATH_MAX_ITER} if method == "admm" else {}), **options}
    with warnings.catch_warnings():
        # Uncertified path points only propose supports; the refits of the selection
        # stage are certified on their own, and the chosen point is checked below.
        warnings.simplefilter("ignore", ConvergenceWarning)
        full = path(
            theta,
            y,
            delta_k,
            n_lams=n_lams,
            eps=eps,
            method=method,
            solver=solver,
            progress=progress,
            **path_options,
        )
    candidates = _stage_all(theta, y, full.coef, delta_k, tol, method, solver, options)
    if criterion == "bic":
        scores = np.stack(
            [
                information_criterion(theta, y, candidates[i], delta_k)
                for i in range(len(candidates))
            ]
        )
    else:
        folds = blocked_folds(theta.shape[0], n_folds)
        scores = np.zeros(full.lams.shape)
        for train, test in tqdm(folds, desc="blocked CV", disable=not progress, leave=False):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                sub = path(
                    theta[train],
                    y[train],
                    delta_k,
                    full.lams,
                    method=method,
                    solver=solver,
                    **path_options,
                )
            cand = _stage_all(
                theta[train], y[train], sub.coef, delta_k, tol, method, solver, options
            )
            r = y[test][None, :, :] - np.einsum("mp,lpn->lmn", theta[test], cand)
            scores += huber(r, delta_k).mean(axis=1) / len(folds)
    index = _pick(scores)
    cols = np.arange(y.shape[1])
    bad = np.flatnonzero(~full.converged[index, cols])
    if bad.size:
        warnings.warn(
            f"the path point chosen for columns {bad.tolist()} was not certified (relative "
            f"KKT {', '.join(f'{v:.1e}' for v in full.kkt[index[bad], bad])}); its support "
            "may differ from the exact one. Try method='cvxpy' or a larger delta.",
            ConvergenceWarning,
            stacklevel=2,
        )
    coef = candidates[index, :, cols].T
    return Selection(
        coef=coef,
        lam=full.lams[index, cols],
        delta=delta_k,
        index=index,
        scores=scores,
        candidates=candidates,
        support=coef != 0,
        path=full,
        criterion=criterion,
    )
