"""``fit``: validate once, dispatch to a solver, certify the answer."""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from numbers import Real

import numpy as np

from .core.certificates import accept_within_floor, certify, within_floor
from .core.scaling import fitted_scale_factor, robust_scale
from .core.validation import (
    as_float_array,
    check_coef,
    check_int,
    check_lam,
    check_positive,
    check_problem,
    loss_delta,
)
from .solvers import chunked, driver, reference, stls
from .solvers.problem import DEFAULT_OPTIONS

__all__ = [
    "HUBER_EFFICIENCY_CONSTANT",
    "METHODS",
    "ConvergenceWarning",
    "FitResult",
    "auto_delta",
    "check_huber_method",
    "fast_path_options",
    "fast_path_verdict",
    "fit",
]

METHODS = ("admm", "cvxpy", "stls", "ols")
#: Relative KKT tolerance of the least-squares certificates (OLS, STLS).
LS_TOL = 1e-8
#: Relative KKT tolerance for the reference solvers: interior-point solutions at gap
#: tolerance 1e-10 reach about 1e-6 (their coefficients near exact zeros are not zero).
CVXPY_TOL = 1e-5


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped before it could certify optimality."""


@dataclass(repr=False)
class FitResult:
    """Outcome of :func:`fit`.

    Attributes
    ----------
    coef : ndarray, shape (p, n) or (p,)
        Coefficient matrix (the paper's Xi); (p,) when ``xdot`` was 1-D.
    objective : ndarray, shape (n,)
        ``P_k(coef)`` per target column (sum of Huber losses plus ``lam ||xi||_1``).
    converged : bool
        True only if every column was certified optimal (see ``column_converged``): its
        relative KKT violation within the tolerance (or, for the fast path, within what
        the rounding of its residuals alone can leave, ``info["floor"]``: a nearly exact
        fit that no method resolves further).
    column_converged : ndarray of bool, shape (n,)
    iterations : ndarray of int, shape (n,)
        Solver iterations per column (ADMM iterations, interior-point iterations,
        STLS sweeps).
    kkt : ndarray, shape (n,)
        Relative KKT violation of ``coef`` (see :func:`robust_sindy.kkt_violation`).
    gap : ndarray, shape (n,)
        Duality gap of ``coef`` (see :func:`robust_sindy.duality_gap`).
    solve_time : float
        Wall-clock seconds spent in the solver.
    method, solver, loss : str
    delta : ndarray, shape (n,)
        The threshold used per column (inf for the squared loss).
    lam : ndarray, shape (n,) or (p, n)
        The L1 weights used, per column or per term and column.
    inliers : ndarray of bool, shape (m, n) or (m,), or None
        For the Huber loss, ``|r| <= delta`` per sample and column.
    dual : ndarray, shape (m, n)
        ``psi_delta(r)``, the dual estimate; pass the result as ``warm_start`` to reuse it.
    messages : list of str
        The solver's word on each column.
    info : dict
        Solver-specific extras (e.g. ADMM Newton-finish steps).
    certificate : str
        What ``converged`` certifies, i.e. the problem the method solves:
        ``"huber-lasso KKT"`` (admm, cvxpy; the same as ``kkt``), ``"least-squares
        normal equations"`` (ols) or ``"STLS fixed point"`` (stls: a stable support and
        least-squares optimality on it).
    certificate_kkt : ndarray, shape (n,)
        Relative KKT violation of that problem per column (``kkt`` always refers to the
        Huber-Lasso problem that ``delta``, ``lam`` and ``loss`` define).
    """

    coef: np.ndarray
    objective: np.ndarray
    converged: bool
    column_converged: np.ndarray
    iterations: np.ndarray
    kkt: np.ndarray
    gap: np.ndarray
    solve_time: float
    method: str
    solver: str
    loss: str
    delta: np.ndarray
    lam: np.ndarray
    inliers: np.ndarray | None
    dual: np.ndarray
    messages: list[str]
    info: dict = field(default_factory=dict)
    certificate: str = "huber-lasso KKT"
    certificate_kkt: np.ndarray | None = None

    def __repr__(self) -> str:
        state = "converged" if self.converged else "NOT converged"
        return (
            f"FitResult(method={self.method!r}, solver={self.solver!r}, loss={self.loss!r}, "
            f"{state}, coef shape={self.coef.shape}, iterations={self.iterations.tolist()}, "
            f"max kkt={self.kkt.max():.2e}, solve_time={self.solve_time:.3g}s)"
        )


def fast_path_options(options: dict, theta, y, one_d: bool = False) -> dict:
    """The fast path's options (``DEFAULT_OPTIONS`` updated by ``options``), checked,
    with ``warm_start`` as a ``(coef, dual)`` pair for ``theta`` and ``y`` (or None)."""
    allowed = set(DEFAULT_OPTIONS)
    _reject_unknown(options, allowed, "admm")
    opts = {**DEFAULT_OPTIONS, **options}
    for name in ("rho", "kappa", "eps_abs", "eps_rel", "tol", "gap_tol"):
        if name in options:
            check_positive(options[name], name)
    if "alpha" in options:
        check_positive(options["alpha"], "alpha", upper=2.0)
    check_int(opts["max_iter"], "max_iter", 1)
    check_int(opts["check_every"], "check_every", 1)
    check_int(opts["newton_steps"], "newton_steps", 0)
    for name in ("equilibrate", "adaptive_rho", "polish"):
        if not isinstance(opts[name], bool):
            raise ValueError(f"{name} must be True or False; got {opts[name]!r}")
    opts["warm_start"] = _warm_start(opts["warm_start"], theta, y, one_d)
    return opts


def _warm_start(ws, theta, y, one_d):
    if ws is None:
        return None
    p, (m, n) = theta.shape[1], y.shape
    if isinstance(ws, FitResult):
        coef = check_coef(ws.coef, p, n, one_d, "warm_start.coef")
        dual = ws.dual
    elif isinstance(ws, tuple):
        if len(ws) != 2:
            raise ValueError("warm_start must be a FitResult, coef, or a (coef, dual) pair")
        coef = check_coef(ws[0], p, n, one_d, "warm_start coef")
        dual = ws[1]
    else:
        coef, dual = check_coef(ws, p, n, one_d, "warm_start"), None
    if dual is not None:
        dual = as_float_array(dual, "warm_start dual", (1, 2)).reshape(m, -1)
        if dual.shape != (m, n):
            raise ValueError(f"warm_start dual must have shape {(m, n)}; got {dual.shape}")
    return coef, dual


def _reject_unknown(options: dict, allowed: set, method: str) -> None:
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(
            f"unknown option(s) {unknown} for method={method!r}; valid: {sorted(allowed)}"
        )


def fit(
    theta,
    xdot,
    method: str = "admm",
    delta=1.0,
    lam=1.0,
    loss: str = "huber",
    solver: str | None = None,
    constraints=None,
    **options,
) -> FitResult:
    """Fit the sparse coefficient matrix of ``xdot ~ theta @ coef`` column by column.

    Each column ``k`` solves

    .. math::

        \\min_{\\xi} \\sum_i H_{\\delta_k}(\\dot X_{ik} - \\Theta_i \\xi)
        + \\lambda_k \\|\\xi\\|_1

    with the Huber loss ``H`` (``loss="huber"``) or ``a**2 / 2`` (``loss="squared"``,
    the Lasso).

    Parameters
    ----------
    theta : array_like, shape (m, p)
        Library matrix: ``p`` candidate functions evaluated at ``m`` samples.
    xdot : array_like, shape (m,) or (m, n)
        Time derivatives (targets).
    method : {"admm", "cvxpy", "stls", "ols"}
        ``"admm"`` is the fast path; ``"cvxpy"`` the reference (Clarabel or OSQP);
        ``"stls"`` and ``"ols"`` are the least-squares baselines (they ignore
        ``delta``, ``lam`` and ``loss`` when fitting; the certificates still refer to
        the problem those arguments define).
    delta : float, array_like of shape (n,), or "auto"
        Huber threshold, > 0, one value or one per column; ``"auto"`` chooses it per
        column by :func:`robust_sindy.selection.auto_delta` (reported in ``delta``).
    lam : float, array_like of shape (n,), or array_like of shape (p, n)
        L1 weight, >= 0: one value, one per column, or one per term and column
        (a weighted L1 norm ``sum_j lam_jk |xi_jk|``; for a 1-D ``xdot`` a vector of
        length ``p`` is one weight per term).
    loss : {"huber", "squared"}
    solver : {"clarabel", "osqp"}, optional
        Only for ``method="cvxpy"`` (default ``"clarabel"``).
    constraints : LinearConstraints, optional
        Linear equalities and inequalities on the whole coefficient matrix
        (:class:`robust_sindy.core.constraints.LinearConstraints`, built by the helpers of
        :mod:`robust_sindy.constraints`).  The columns are then one problem, solved by
        ``method="admm"`` (ADMM on all equations at once, then a polish: the fast path)
        or ``method="cvxpy"`` (the reference), and certified by the constrained KKT
        conditions (:func:`robust_sindy.core.constraints.constrained_certificate`):
        ``kkt`` is each equation's stationarity violation with the multipliers,
        ``certificate_kkt`` the largest of it and the constraints' relative residual,
        ``gap`` the problem's duality gap (the same in every column), and ``info``
        holds ``constraint_residual``, the multipliers ``nu`` and ``mu`` and the
        solver's own status.  ADMM options: ``rho, alpha, max_iter, eps, tol,
        check_every, polish``.  Dask arrays are solved out of core by the same
        certificate (:func:`robust_sindy.solvers.chunked.solve_chunked_constrained`;
        options ``tol, max_iter, progress`` and ``warm_start``, coefficients that meet
        the constraints).
    **options
        Solver options.  ADMM: ``rho, kappa, alpha, equilibrate, adaptive_rho, polish,
        max_iter, eps_abs, eps_rel, tol, gap_tol, check_every, newton_steps,
        warm_start`` (see :func:`robust_sindy.solvers.solve_admm`;
        ``robust_sindy.PAPER_ADMM_OPTIONS`` reproduces the paper's settings).
        CVXPY: ``tol`` (tolerance of its KKT certificate, 1e-5), ``verbose`` and settings
        passed to the solver.  STLS: ``threshold`` (0.05), ``max_sweeps`` (5000),
        ``tol``; OLS: ``tol`` (tolerance of their least-squares certificates, 1e-8).

    Returns
    -------
    FitResult

    Raises
    ------
    ValueError
        For bad input; the message names the argument.

    Warns
    -----
    ConvergenceWarning
        When a column could not be certified optimal; the best iterate is returned.

    Examples
    --------
    >>> import numpy as np
    >>> import robust_sindy as rs
    >>> rng = np.random.default_rng(0)
    >>> theta = rng.normal(size=(200, 5))
    >>> xdot = theta @ np.array([1.5, 0.0, 0.0, -2.0, 0.0])
    >>> xdot[::10] += 50.0                      # 10 % gross outliers
    >>> res = rs.fit(theta, xdot, delta=1.0, lam=20.0)
    >>> res.converged, bool(res.kkt.max() < 1e-8)
    (True, True)
    >>> np.round(res.coef, 2)
    array([ 1.38,  0.  ,  0.  , -1.93,  0.  ])
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    if constraints is not None:
        return _fit_constrained(theta, xdot, method, delta, lam, loss, solver, constraints, options)
    if chunked.is_dask(theta) or chunked.is_dask(xdot):
        return _fit_dask(theta, xdot, method, delta, lam, loss, solver, options)
    theta, y, one_d = check_problem(theta, xdot)
    delta_k, lam_k = _delta_lam(theta, y, one_d, method, delta, lam, loss, solver)

    t0 = time.perf_counter()
    out, solver_name, tol, gap_tol, opts = _solve(
        method, theta, y, delta_k, lam_k, solver, options, one_d
    )
    solve_time = time.perf_counter() - t0

    cert = certify(theta, y, out.coef, delta_k, lam_k if lam_k.ndim == 2 else lam_k[None, :])
    certificate, own_kkt = "huber-lasso KKT", cert.kkt
    if method in ("ols", "stls"):
        certificate, own_kkt = _least_squares_kkt(theta, y, out.coef, method)
    if method == "cvxpy":  # the certificate decides, not the solver's status
        column_ok = own_kkt <= tol
    else:
        column_ok = fast_path_verdict(
            theta, y, out, own_kkt, cert, delta_k, tol, gap_tol, floor=method == "admm"
        )
    if not column_ok.all():
        bad = np.flatnonzero(~column_ok).tolist()
        advice = _advice(method, solver_name, out, bad, opts, tol, delta_k, y, loss)
        warnings.warn(
            f"{method} ({solver_name}) did not certify columns {bad} "
            f"({certificate}: relative violation "
            f"{', '.join(f'{v:.1e}' for v in own_kkt[bad])}, tol {tol:g}); "
            f"returning the last iterate. Try: {advice}.",
            ConvergenceWarning,
            stacklevel=2,
        )

    return FitResult(
        coef=out.coef[:, 0].copy() if one_d else out.coef,
        objective=cert.objective,
        converged=bool(column_ok.all()),
        column_converged=column_ok,
        iterations=out.iterations,
        kkt=cert.kkt,
        gap=cert.gap,
        solve_time=solve_time,
        method=method,
        solver=solver_name,
        loss=loss,
        delta=delta_k,
        lam=lam_k,
        inliers=_inliers(cert.residual, delta_k, loss, one_d),
        dual=cert.psi,
        messages=out.messages,
        info=out.info,
        certificate=certificate,
        certificate_kkt=own_kkt,
    )


def fast_path_verdict(theta, y, out, kkt, cert, delta, tol, gap_tol, floor=True) -> np.ndarray:
    """Which columns of the solver's ``out`` its certificate ``cert`` accepts: the solver
    finished and the relative KKT violation ``kkt`` is within ``tol`` or the relative
    duality gap within ``gap_tol``; or (``floor``) the violation is within what the
    rounding of the residuals alone can leave
    (:func:`robust_sindy.core.certificates.rounding_floor`; the solver's own
    ``out.info["floor"]`` where it computed one at the same point, the others computed
    here and written there): stationary as far as floating point can tell, which in a
    convex problem is optimal as far as it can tell (a nearly exact fit whose terms
    cancel, where no method does better)."""
    ok = out.converged & ((kkt <= tol) | (cert.rel_gap <= gap_tol))
    if floor and not ok.all():
        ok, out.info["floor"] = accept_within_floor(
            theta, y, out.coef, delta, kkt, ok, cert.residual, out.info.get("floor")
        )
    return ok


def _delta_lam(theta, y, one_d, method, delta, lam, loss, solver):
    """The threshold per column (``"auto"``: :func:`auto_delta`) and the L1 weights, checked,
    and ``solver`` given only with ``method="cvxpy"``."""
    n = y.shape[1]
    if isinstance(delta, str) and delta == "auto":
        if loss != "huber":
            raise ValueError("delta='auto' applies to loss='huber' only")
        delta = np.atleast_1d(auto_delta(theta, y))
    delta_k = loss_delta(loss, delta, n)
    lam_k = check_lam(lam, theta.shape[1], n, one_d)
    if method != "cvxpy" and solver is not None:
        raise ValueError(f"solver applies to method='cvxpy' only; got solver={solver!r}")
    return delta_k, lam_k


def _reference_solver(solver, options: dict) -> tuple[str, float]:
    """The reference's solver name and certificate tolerance (``options["tol"]``, taken
    out of ``options``), the rest of ``options`` checked for that solver."""
    solver_name = "clarabel" if solver is None else solver
    if solver_name not in reference.SOLVERS:
        raise ValueError(f"solver must be one of {reference.SOLVERS}; got {solver!r}")
    tol = check_positive(options.pop("tol", CVXPY_TOL), "tol")
    reference.check_options(solver_name, options)
    return solver_name, tol


def _inliers(residual, delta_k, loss: str, one_d: bool):
    """``|r| <= delta`` per sample and column for the Huber loss (None otherwise)."""
    if loss != "huber":
        return None
    inliers = np.abs(residual) <= delta_k
    return inliers[:, 0] if one_d else inliers


def _solve(method, theta, y, delta_k, lam_k, solver, options, one_d):
    """The chosen method's run, its solver's name, its certificate's tolerances (KKT and,
    for the fast path only, a certified duality gap) and the fast path's options."""
    gap_tol, opts = 0.0, {}
    if method == "admm":
        opts = fast_path_options(options, theta, y, one_d)
        tol, gap_tol = opts["tol"], opts["gap_tol"]
        out = driver.solve(theta, y, delta_k, lam_k, **opts)
        solver_name = "newton" if opts["polish"] else "admm"
    elif method == "cvxpy":
        solver_name, tol = _reference_solver(solver, options)
        out = reference.solve_cvxpy(theta, y, delta_k, lam_k, solver=solver_name, **options)
    elif method == "stls":
        _reject_unknown(options, {"threshold", "max_sweeps", "tol"}, "stls")
        tol = check_positive(options.get("tol", LS_TOL), "tol")
        threshold = options.get("threshold", 0.05)
        if (
            isinstance(threshold, bool)
            or not isinstance(threshold, Real)
            or not np.isfinite(threshold)
            or threshold < 0
        ):
            raise ValueError(f"threshold must be a finite number >= 0; got {threshold!r}")
        sweeps = check_int(options.get("max_sweeps", 5000), "max_sweeps", 1)
        out = stls.solve_stls(theta, y, threshold=float(threshold), max_sweeps=sweeps)
        solver_name = "stls"
    else:
        _reject_unknown(options, {"tol"}, "ols")
        tol = check_positive(options.get("tol", LS_TOL), "tol")
        out = stls.solve_ols(theta, y)
        solver_name = "ols"
    return out, solver_name, tol, gap_tol, opts


def _advice(method, solver_name, out, bad, opts, tol, delta_k, y, loss) -> str:
    """What to try when columns ``bad`` were not certified."""
    stalled = out.info.get("stalled")
    if method == "admm" and stalled is not None and stalled[bad].any():
        advice = (
            f"columns {np.flatnonzero(stalled).tolist()} stopped where floating point "
            f"cannot certify tol={opts['tol']:g} (see the messages): for an "
            "ill-conditioned library rescale or centre the states before building it, "
            "drop nearly collinear terms, or pass a larger tol; for a delta below the "
            "residuals' resolution pass a larger delta"
        )
    elif method == "admm":
        advice = (
            f"increase max_iter (now {opts['max_iter']}), start from another rho "
            f"(now {opts['rho']}; e.g. 1e-4 or 10), or keep equilibrate, adaptive_rho "
            "and polish on"
        )
        ratio = delta_k[bad] / np.maximum(np.abs(y[:, bad]).max(axis=0), np.finfo(float).tiny)
        if loss == "huber" and ratio.min() < 1e-4:
            advice += (
                f"; delta is {ratio.min():.1e} of max|xdot|, which makes the problem a "
                "least-absolute-deviation fit, where ADMM converges slowly: "
                "try method='cvxpy' or a larger delta"
            )
    elif method == "cvxpy":
        other = "osqp" if solver_name == "clarabel" else "clarabel"
        statuses = ", ".join(dict.fromkeys(out.messages[k] for k in bad))
        advice = f"solver={other!r} or method='admm' (the solver's status: {statuses})"
    elif method == "stls" and not out.converged[bad].all():
        advice = "increase max_sweeps"
    else:
        advice = (
            "the least-squares solution could not be certified to "
            f"tol={tol:g} in floating point (an ill-conditioned or rank-deficient "
            "library); rescale the states, drop collinear terms, or pass a larger tol"
        )
    return advice


def _dask_problem(theta, xdot, method, delta, lam, loss, solver, options, extra=()):
    """The checks of a fit on Dask arrays: ``(theta, y (m, n), one_d, delta (n,), lam as
    given (checked), lam (p, n), tol, max_iter)``; ``extra`` option names are allowed
    beside ``tol, max_iter, progress``."""
    import dask.array as da

    if method != "admm" or loss != "huber" or solver is not None:
        raise ValueError(
            "Dask arrays are solved by the fast path only: method='admm', loss='huber' "
            f"(got method={method!r}, loss={loss!r})"
        )
    known = {"tol", "max_iter", "progress", *extra}
    _reject_unknown(options, known, "admm on Dask arrays" + (" with constraints" if extra else ""))
    tol = check_positive(options.get("tol", DEFAULT_OPTIONS["tol"]), "tol")
    max_iter = check_int(options.get("max_iter", 50), "max_iter", 1)
    theta = da.asarray(theta)
    y = da.asarray(xdot)
    if theta.ndim != 2:
        raise ValueError(f"theta must be 2-D; got shape {theta.shape}")
    one_d = y.ndim == 1
    y = y[:, None] if one_d else y
    if y.ndim != 2 or y.shape[0] != theta.shape[0]:
        raise ValueError(f"xdot has shape {xdot.shape} but theta has {theta.shape[0]} rows")
    if any(not np.issubdtype(a.dtype, np.number) for a in (theta, y)):
        raise ValueError("theta and xdot must hold real numbers")
    n, p = y.shape[1], theta.shape[1]
    if isinstance(delta, str):
        raise ValueError(
            "delta='auto' needs a robust scale of the residuals, not computed on Dask "
            "arrays: give delta (e.g. from robust_sindy.selection.auto_delta on a sample)"
        )
    delta_k = loss_delta(loss, delta, n)
    lam_k = check_lam(lam, p, n, one_d)
    lam_full = np.broadcast_to(lam_k if lam_k.ndim == 2 else lam_k[None, :], (p, n)).copy()
    return theta, y, one_d, delta_k, lam_k, lam_full, tol, max_iter


def _fit_dask(theta, xdot, method, delta, lam, loss, solver, options) -> FitResult:
    """:func:`fit` on Dask arrays chunked by rows (:mod:`robust_sindy.solvers.chunked`)."""

    theta, y, one_d, delta_k, lam_k, lam_full, tol, max_iter = _dask_problem(
        theta, xdot, method, delta, lam, loss, solver, options
    )
    t0 = time.perf_counter()
    run = chunked.solve_chunked(
        theta, y, delta_k, lam_full, lasso=_small_lasso, tol=tol, max_iter=max_iter,
        progress=bool(options.get("progress", False)),
    )  # fmt: skip
    if not run.converged.all():
        bad = np.flatnonzero(~run.converged).tolist()
        warnings.warn(
            f"admm on Dask arrays did not certify columns {bad} (relative KKT "
            f"{', '.join(f'{v:.1e}' for v in run.kkt[bad])}, tol {tol:g}); returning the "
            "last iterate. Try: a larger max_iter, or a larger delta",
            ConvergenceWarning,
            stacklevel=3,
        )
    return _dask_result(
        run, theta, y, one_d, delta_k, lam_k, t0,
        objective=run.objective, converged=bool(run.converged.all()),
        column_converged=run.converged, kkt=run.kkt, gap=run.gap,
        info={"passes": run.passes}, certificate="huber-lasso KKT", certificate_kkt=run.kkt,
    )  # fmt: skip


def _dask_result(run, theta, y, one_d, delta_k, lam_k, t0, **fields) -> FitResult:
    """The :class:`FitResult` of a chunked run (``fields``: its certificate's), with the
    inliers and the dual as lazy Dask arrays."""
    import dask.array as da

    r = y - theta @ da.from_array(run.coef)
    inliers = abs(r) <= delta_k
    return FitResult(
        coef=run.coef[:, 0].copy() if one_d else run.coef,
        iterations=run.iterations,
        solve_time=time.perf_counter() - t0,
        method="admm",
        solver="newton-chunked",
        loss="huber",
        delta=delta_k,
        lam=lam_k,
        inliers=inliers[:, 0] if one_d else inliers,
        dual=da.clip(r, -delta_k, delta_k),
        messages=run.messages,
        **fields,
    )


def _small_lasso(design, target, lam) -> np.ndarray:
    """The in-memory Lasso of a chunked Newton step (uncertified steps are judged by the
    chunked solver's own certificate)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(design, target, loss="squared", lam=lam).coef


def _least_squares_kkt(theta, y, coef, method):
    """Relative KKT violation of least squares (``delta = inf``, ``lam = 0``): on all
    columns of ``theta`` for OLS, on each column's support for STLS (its fixed point)."""
    n = y.shape[1]
    inf, zero = np.full(n, np.inf), np.zeros((1, n))
    if method == "ols":
        return "least-squares normal equations", certify(theta, y, coef, inf, zero).kkt
    kkt = np.zeros(n)
    for k in range(n):
        s = coef[:, k] != 0
        if s.any():
            kkt[k] = certify(theta[:, s], y[:, [k]], coef[s][:, [k]], inf[:1], zero[:, :1]).kkt[0]
    return "STLS fixed point", kkt


#: Tuning constant of the Huber loss with 95 % efficiency at the Gaussian.
HUBER_EFFICIENCY_CONSTANT = 1.345


def delta_floor(y, floor: float = 1e-4) -> np.ndarray:
    """The smallest threshold :func:`auto_delta` gives each column of ``y`` (m, n):
    ``floor`` times its root mean square (1 for a column of zeros)."""
    lower = floor * np.sqrt(np.mean(np.asarray(y) ** 2, axis=0))
    return np.where(lower > 0, lower, 1.0)


def least_squares_start(theta, y, floor: float = 1e-4):
    """The start of :func:`auto_delta` without one: least squares' coefficients (p, n)
    and the threshold of their residuals, ``delta`` (n,) (the threshold formula, at
    least :func:`delta_floor`).  Columns are independent: a start for a subset of the
    columns is this start's columns."""
    factor = HUBER_EFFICIENCY_CONSTANT * fitted_scale_factor(*theta.shape)
    coef = np.linalg.lstsq(theta, y, rcond=None)[0]
    delta = np.maximum(factor * robust_scale(y - theta @ coef), delta_floor(y, floor))
    return delta, coef


def auto_delta(
    theta,
    xdot,
    *,
    n_iter: int = 5,
    rtol: float = 1e-2,
    floor: float = 1e-4,
    method: str = "admm",
    return_coef: bool = False,
    start=None,
    **options,
):
    """Per-column Huber threshold from the residual scale of a robust pilot fit.

    Start from the residuals of ordinary least squares; then repeat up to ``n_iter``
    times: ``delta = 1.345 * c * robust_scale(r)``, with ``c = sqrt(m / (m - p))``
    (:func:`~robust_sindy.core.scaling.fitted_scale_factor`: the residuals of a fit of
    all ``p`` columns to ``m`` samples are that much narrower than the errors), refit
    the unpenalised Huber regression (``lam = 0``) with that ``delta``, take its
    residuals ``r``; stop once ``delta`` changes by less than ``rtol`` (relative).
    With the fast path, each refit starts from the previous one's coefficients (the
    first from least squares).

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
    return_coef : bool
        Also return the coefficients of the last pilot fit, shape (p, n) (least
        squares for the columns never refitted): a start for a fit with the ``delta``
        returned.
    start : tuple (delta, coef), optional
        A threshold per column (n,) and coefficients (p, n) to start from instead of
        least squares: those of a pilot on nearly the same samples (the iteration then
        usually ends after one refit).
    **options
        Solver options of the pilot fits (see :func:`robust_sindy.fit`).

    Returns
    -------
    delta : ndarray (n,), or float when ``xdot`` is 1-D.
    coef : ndarray (p, n)
        Only with ``return_coef``.
    """
    theta, y, one_d = check_problem(theta, xdot)
    n_iter = check_int(n_iter, "n_iter", 1)
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"method must be 'admm' or 'cvxpy' for the pilot fit; got {method!r}")
    lower = delta_floor(y, floor)
    # The residuals of a fit of every column are narrower than the errors.
    factor = HUBER_EFFICIENCY_CONSTANT * fitted_scale_factor(*theta.shape)
    if start is None:
        delta, coef = least_squares_start(theta, y, floor)
    else:
        delta = np.maximum(np.broadcast_to(np.asarray(start[0], dtype=float), lower.shape), lower)
        coef = np.array(start[1], dtype=float).reshape(theta.shape[1], y.shape[1])
    # Columns already fitted to the floor by least squares have nothing to refine.
    todo = np.flatnonzero(delta > lower)
    for _ in range(n_iter):
        if todo.size == 0:
            break
        if method == "admm":  # the previous pilot is close: a few Newton steps
            options = {**options, "warm_start": coef[:, todo]}
        res = fit(theta, y[:, todo], method=method, delta=delta[todo], lam=0.0, **options)
        coef[:, todo] = res.coef
        r = y[:, todo] - theta @ res.coef
        new = np.maximum(factor * robust_scale(r), lower[todo])
        change = np.abs(new - delta[todo]) / delta[todo]
        delta[todo] = new
        todo = todo[change >= rtol]
    out = float(delta[0]) if one_d else delta
    return (out, coef) if return_coef else out


def check_huber_method(method: str, what: str) -> str:
    """``method`` if it is a Huber method ("admm" or "cvxpy"), else a ``ValueError``
    naming ``what`` it was for."""
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"method must be 'admm' or 'cvxpy' for {what}; got {method!r}")
    return method


def _fit_constrained(theta, xdot, method, delta, lam, loss, solver, constraints, options):
    """:func:`fit` with ``constraints``: one problem over every column."""
    from .core.constraints import LinearConstraints, constrained_certificate
    from .solvers import constrained

    if not isinstance(constraints, LinearConstraints):
        raise ValueError(
            "constraints must be a LinearConstraints (see robust_sindy.constraints); "
            f"got {type(constraints).__name__}"
        )
    if method not in ("admm", "cvxpy"):
        raise ValueError(f"constraints apply to method='admm' or 'cvxpy'; got {method!r}")
    if chunked.is_dask(theta) or chunked.is_dask(xdot):
        return _fit_dask_constrained(theta, xdot, method, delta, lam, loss, solver,
                                     constraints, options)  # fmt: skip
    theta, y, one_d = check_problem(theta, xdot)
    n, p = y.shape[1], theta.shape[1]
    constraints.check_shape(p, n)
    delta_k, lam_k = _delta_lam(theta, y, one_d, method, delta, lam, loss, solver)
    lam_full = np.broadcast_to(lam_k if lam_k.ndim == 2 else lam_k[None, :], (p, n))
    t0 = time.perf_counter()
    if method == "cvxpy":
        solver_name, tol = _reference_solver(solver, options)
        out = constrained.solve_constrained_cvxpy(
            theta, y, delta_k, lam_full, constraints, solver=solver_name, **options
        )
    else:
        known = {"rho", "alpha", "max_iter", "eps", "tol", "check_every", "polish", "warm_start"}
        _reject_unknown(options, known, "admm with constraints")
        tol = check_positive(options.get("tol", 1e-8), "tol")
        warm = _warm_start(options.get("warm_start"), theta, y, one_d)
        out = constrained.solve_constrained_admm(
            theta, y, delta_k, lam_full, constraints,
            **{**options, "tol": tol, "warm_start": None if warm is None else warm[0]},
        )  # fmt: skip
        solver_name = "admm"
    solve_time = time.perf_counter() - t0
    cert = out.certificate
    if cert is None:
        cert = constrained_certificate(
            theta, y, out.coef, delta_k, lam_full, constraints, nu=out.nu, mu=out.mu
        )
    converged = bool(cert.kkt <= tol)
    if not converged and method == "admm" and cert.feasibility <= tol:
        # Stationary within what the rounding of the residuals can leave (a nearly exact
        # fit): certified to the floating-point floor, as the unconstrained fast path is.
        floor = out.info.get("floor")  # the polish's own, at the same point
        if floor is None:
            floor = constrained.stationarity_floor(theta, y, out.coef, delta_k, cert.residual)
        converged = bool(within_floor(cert.stationarity, floor))
    if not converged:
        _warn_constrained(
            f"{method} ({solver_name})", cert, f"tol {tol:g}; {out.status}",
            "a larger max_iter or another rho (e.g. 0.01 or 100), or method='cvxpy'"
            if method == "admm"
            else "the other solver, or check that the constraints can be met",
        )  # fmt: skip
    column_ok = np.full(n, converged)
    return FitResult(
        coef=out.coef[:, 0].copy() if one_d else out.coef,
        objective=cert.column_objective,
        converged=converged,
        column_converged=column_ok,
        iterations=np.full(n, out.iterations),
        kkt=cert.column_kkt,
        gap=np.full(n, cert.gap),
        solve_time=solve_time,
        method=method,
        solver=solver_name,
        loss=loss,
        delta=delta_k,
        lam=lam_k,
        inliers=_inliers(cert.residual, delta_k, loss, one_d),
        dual=cert.psi,
        messages=[out.status],
        info={
            "constraint_residual": cert.feasibility,
            "nu": cert.nu,
            "mu": cert.mu,
            "solver_status": out.status,
            **out.info,
        },
        certificate="constrained huber-lasso KKT",
        certificate_kkt=np.maximum(cert.column_kkt, cert.feasibility),
    )


def _warn_constrained(who: str, cert, detail: str, advice: str, depth: int = 0) -> None:
    """The warning of a constrained problem ``who`` did not certify (``cert``, its
    certificate; ``detail`` after its figures; ``advice``, what to try), raised for the
    caller of :func:`fit` (``depth``: calls between :func:`_fit_constrained` and the
    caller of this function)."""
    warnings.warn(
        f"{who} did not certify the constrained problem (relative stationarity "
        f"{cert.stationarity:.1e}, constraint residual {cert.feasibility:.1e}, {detail}); "
        f"returning the last iterate. Try: {advice}.",
        ConvergenceWarning,
        stacklevel=4 + depth,
    )


def _constrained_subproblem(design, target, lam, constraints) -> np.ndarray:
    """The in-memory constrained Lasso of a chunked Newton step under constraints (an
    uncertified step is judged by the chunked solver's own certificate)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(design, target, loss="squared", lam=lam, constraints=constraints).coef


def _fit_dask_constrained(
    theta, xdot, method, delta, lam, loss, solver, constraints, options
) -> FitResult:  # fmt: skip
    """:func:`fit` with ``constraints`` on Dask arrays chunked by rows
    (:func:`robust_sindy.solvers.chunked.solve_chunked_constrained`)."""

    theta, y, one_d, delta_k, lam_k, lam_full, tol, max_iter = _dask_problem(
        theta, xdot, method, delta, lam, loss, solver, options, extra=("warm_start",)
    )
    n, p = y.shape[1], theta.shape[1]
    constraints.check_shape(p, n)
    warm = options.get("warm_start")
    if warm is not None:  # coefficients only: a dual of every row is not kept out of core
        warm = warm.coef if isinstance(warm, FitResult) else warm
        warm = warm[0] if isinstance(warm, tuple) else warm
        warm = check_coef(warm, p, n, one_d, "warm_start").reshape(p, n)
    t0 = time.perf_counter()
    run = chunked.solve_chunked_constrained(
        theta, y, delta_k, lam_full, constraints, subproblem=_constrained_subproblem,
        tol=tol, max_iter=max_iter, progress=bool(options.get("progress", False)), start=warm,
    )  # fmt: skip
    cert = run.certificate
    converged = bool(cert.kkt <= tol)
    if not converged:
        _warn_constrained(
            "admm on Dask arrays", cert, f"tol {tol:g}",
            "a larger max_iter, or check that the constraints can be met", depth=1,
        )  # fmt: skip
    return _dask_result(
        run,
        theta,
        y,
        one_d,
        delta_k,
        lam_k,
        t0,
        objective=cert.column_objective,
        converged=converged,
        column_converged=np.full(n, converged),
        kkt=cert.column_kkt,
        gap=np.full(n, cert.gap),
        info={
            "passes": run.passes,
            "constraint_residual": cert.feasibility,
            "nu": cert.nu,
            "mu": cert.mu,
            "solver_status": run.messages[0],
        },
        certificate="constrained huber-lasso KKT",
        certificate_kkt=np.maximum(cert.column_kkt, cert.feasibility),
    )
