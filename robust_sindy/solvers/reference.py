"""CVXPY formulation of the Huber-Lasso problem: the reference solver.

.. math::

    \\min_{\\xi}\\; \\tfrac12 \\sum_i \\mathrm{huber}(y_i - \\theta_i \\xi, \\delta)
    + \\lambda \\|\\xi\\|_1

CVXPY's ``huber(x, M)`` is ``2 H_M(x)``, hence the factor 1/2: without it the problem
solved is the one with ``lam / 2``.  The squared loss uses ``sum_squares / 2``.
Each column is its own problem, solved by Clarabel (interior point, default) or OSQP
(ADMM with solution polishing) at tolerances tight enough for a 1e-6 cross-check.
"""

from __future__ import annotations

import warnings
from numbers import Real

import numpy as np

from .problem import SolverOutput

__all__ = ["SETTINGS", "SOLVERS", "solve_cvxpy", "solve_problem"]

SOLVERS = ("clarabel", "osqp")

#: The reference solvers' tight default settings.
SETTINGS = {
    "clarabel": dict(tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10, max_iter=500),
    "osqp": dict(eps_abs=1e-9, eps_rel=1e-9, max_iter=400_000, polishing=True),
}


def _solver_settings(solver: str) -> dict:
    """Names and default values of the settings ``solver`` accepts."""
    if solver == "clarabel":
        import clarabel

        defaults = clarabel.DefaultSettings()
    else:
        from osqp.ext_builtin import OSQPSettings

        defaults = OSQPSettings()
    return {a: getattr(defaults, a) for a in dir(defaults) if not a.startswith("_")}


def check_options(solver: str, options: dict) -> None:
    """Reject options the reference solver would choke on, naming them, before any work.

    ``verbose`` and the solver's own settings (their names and types) are accepted;
    ``warm_start`` and the fast path's options are not.
    """
    known = _solver_settings(solver)
    for name, value in options.items():
        if name == "warm_start":
            raise ValueError("warm_start applies to method='admm' only")
        if name not in known:
            raise ValueError(
                f"unknown option {name!r} for method='cvxpy' with solver={solver!r}; valid: "
                f"'tol', 'verbose' and the solver's settings ({', '.join(sorted(known))})"
            )
        default = known[name]
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
        elif isinstance(default, float):
            ok = isinstance(value, Real) and not isinstance(value, bool)
        else:
            ok = True
        if not ok:
            raise ValueError(
                f"option {name!r} of {solver} must be of type {type(default).__name__} "
                f"(default {default!r}); got {value!r}"
            )


def solve_problem(problem, solver_name: str, verbose: bool, settings: dict) -> None:
    """``problem.solve`` without CVXPY's generic warning that a solution "may be
    inaccurate": its status (``optimal_inaccurate``, ...) stays in the caller's
    messages, and the caller's certificate decides whether the point is accepted (and
    warns, with the status, where it is not): CVXPY's warning would otherwise also
    fire on answers the certificate accepts."""
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message="Solution may be inaccurate", category=UserWarning
        )
        problem.solve(solver=solver_name, verbose=verbose, **settings)


def solve_cvxpy(
    theta: np.ndarray,
    y: np.ndarray,
    delta: np.ndarray,
    lam: np.ndarray,
    *,
    solver: str = "clarabel",
    verbose: bool = False,
    **solver_options,
) -> SolverOutput:
    """Solve each column with CVXPY.

    Parameters
    ----------
    theta, y, delta, lam
        As for :func:`robust_sindy.solvers.admm.solve_admm` (``delta = inf`` for the
        squared loss; ``lam`` of shape (n,) or (p, n)).
    solver : {"clarabel", "osqp"}
    verbose : bool
        Print the solver's log.
    **solver_options
        Passed to the solver, overriding the tight defaults
        (Clarabel: ``tol_gap_abs = tol_gap_rel = tol_feas = 1e-10``;
        OSQP: ``eps_abs = eps_rel = 1e-9``, polishing on).
    """
    import cvxpy as cp

    name = solver.upper()
    if name not in cp.installed_solvers():
        raise ImportError(
            f"solver={solver!r} is not installed for CVXPY; install it with `pip install {solver}`"
        )
    _m, p = theta.shape
    n = y.shape[1]
    lam = np.broadcast_to(lam, (p, n))
    settings = {**SETTINGS[solver], **solver_options}
    coef = np.zeros((p, n))
    iterations = np.zeros(n, dtype=int)
    converged = np.zeros(n, dtype=bool)
    messages = []
    for k in range(n):
        xi = cp.Variable(p)
        resid = y[:, k] - theta @ xi
        if np.isinf(delta[k]):
            loss = 0.5 * cp.sum_squares(resid)
        else:
            loss = 0.5 * cp.sum(cp.huber(resid, float(delta[k])))
        problem = cp.Problem(cp.Minimize(loss + lam[:, k] @ cp.abs(xi)))
        try:
            solve_problem(problem, name, verbose, settings)
        except cp.error.SolverError as exc:
            messages.append(f"{solver} failed: {exc}")
            continue
        status = problem.status
        messages.append(f"{solver}: {status}")
        if xi.value is not None:
            coef[:, k] = xi.value
        converged[k] = status == cp.OPTIMAL
        stats = problem.solver_stats
        iterations[k] = stats.num_iters if stats.num_iters is not None else 0
    return SolverOutput(coef=coef, iterations=iterations, converged=converged, messages=messages)
