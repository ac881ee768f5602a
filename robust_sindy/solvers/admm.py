"""ADMM with an exact active-set finish: the fast path of :func:`robust_sindy.fit`.

For every target column ``y`` (all columns are iterated together) it solves

.. math::

    \\min_{\\xi}\\; \\sum_i H_\\delta(y_i - \\theta_i \\xi) + \\sum_j \\lambda_j |\\xi_j|

through the splitting ``r = y - Theta xi``, ``z = xi`` (paper Eq. 9) with scaled duals
``u_r``, ``u_z``, penalty ``rho`` on the r-block and ``kappa rho`` on the z-block:

.. math::

    (\\Theta^T\\Theta + \\kappa I)\\,\\xi &= \\Theta^T(y - r - u_r) + \\kappa(z + u_z) \\\\
    r &= \\operatorname{prox}_{H_\\delta/\\rho}(y - \\Theta\\xi - u_r) \\\\
    z &= S_{\\lambda/(\\kappa\\rho)}(\\xi - u_z) \\\\
    u_r &\\mathrel{+}= r - (y - \\Theta\\xi), \\qquad u_z \\mathrel{+}= z - \\xi

(the corrected form of the paper's Eqs. 10-14; its printed Huber prox is not a prox).
``rho`` cancels in the xi-update, so one Cholesky factor of ``Theta^T Theta + kappa I``
serves every column and every change of ``rho``.

Speed-ups, all exact (the estimator does not change):

* columns of ``Theta`` are equilibrated (``Theta D^-1``, ``D xi``, ``lam / d``);
* each column is solved in units of its Huber threshold (``y / delta``), and ``rho``
  adapts per column by residual balancing with a bounded ``sqrt(primal / dual)`` step,
  the scaled duals rescaled and no refactorisation;
* over-relaxation ``alpha``;
* a finish by the active-set Newton method (:func:`robust_sindy.solvers.newton.newton`)
  from the current iterate at iterations 10, 20, 40, 80, every 100 after, and whenever
  the residual tests pass.  Only a point whose KKT certificate is below ``tol`` ends a
  column.

This is the fallback of the fast path (:func:`robust_sindy.solvers.driver.solve`
runs the Newton method first and hands over the columns it cannot certify) and, with
``PAPER_OPTIONS``, the paper's own method.

A column is converged when its primal and dual residuals pass OSQP-style tests *and*
its relative KKT violation (or relative duality gap) is below tolerance, or when a
Newton finish produced a point with a certified KKT violation.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ..core.certificates import certify, column_norms
from ..core.losses import huber_prox, huber_psi, soft_threshold
from .newton import newton
from .problem import (
    DEFAULT_OPTIONS,
    PAPER_OPTIONS,
    Prepared,
    SolverOutput,
    column_objective,
    prepare,
)

__all__ = ["DEFAULT_OPTIONS", "PAPER_OPTIONS", "solve_admm"]


_RHO_MIN, _RHO_MAX, _MU, _TAU_MAX = 1e-10, 1e10, 10.0, 10.0
_MAX_POLISH_INTERVAL = 100


def solve_admm(
    theta: np.ndarray,
    y: np.ndarray,
    delta: np.ndarray,
    lam: np.ndarray,
    *,
    rho: float = DEFAULT_OPTIONS["rho"],
    kappa: float = DEFAULT_OPTIONS["kappa"],
    alpha: float = DEFAULT_OPTIONS["alpha"],
    equilibrate: bool = DEFAULT_OPTIONS["equilibrate"],
    adaptive_rho: bool = DEFAULT_OPTIONS["adaptive_rho"],
    polish: bool = DEFAULT_OPTIONS["polish"],
    max_iter: int = DEFAULT_OPTIONS["max_iter"],
    eps_abs: float = DEFAULT_OPTIONS["eps_abs"],
    eps_rel: float = DEFAULT_OPTIONS["eps_rel"],
    tol: float = DEFAULT_OPTIONS["tol"],
    gap_tol: float = DEFAULT_OPTIONS["gap_tol"],
    check_every: int = DEFAULT_OPTIONS["check_every"],
    newton_steps: int = DEFAULT_OPTIONS["newton_steps"],
    warm_start: tuple[np.ndarray, np.ndarray | None] | None = None,
    prepared: Prepared | None = None,
) -> SolverOutput:
    """Solve all columns of the Huber-Lasso (or Lasso, ``delta = inf``) problem by ADMM.

    Parameters
    ----------
    theta : ndarray, shape (m, p)
    y : ndarray, shape (m, n)
    delta : ndarray, shape (n,)
        Huber threshold per column; ``inf`` gives the squared loss.
    lam : ndarray, shape (n,) or (p, n)
        L1 weight per column or per coordinate and column.
    rho : float
        Initial penalty on the residual block (per column once adapted).
    kappa : float
        Relative penalty of the ``z = xi`` block; changing it refactorises (p x p).
    alpha : float in (0, 2)
        Over-relaxation; 1 is plain ADMM.
    equilibrate : bool
        Scale the columns of ``theta`` to unit norm (exact change of variables).
    adaptive_rho : bool
        Balance the primal and dual residuals of each column by updating its ``rho``.
    polish : bool
        Try the active-set Newton finish at iterations 10, 20, 40, 80, every 100
        after, and whenever the residual tests pass.
    max_iter : int
        ADMM iteration limit per column.
    eps_abs, eps_rel : float
        OSQP-style absolute and relative residual tolerances.
    tol : float
        Relative KKT violation a column must reach to be converged.
    gap_tol : float
        Relative duality gap that also certifies a column.
    check_every : int
        Residuals, rho adaptation and certificates are evaluated every so many iterations.
    newton_steps : int
        Maximum active-set Newton steps per finish attempt.
    warm_start : (coef, dual) or None
        Coefficients (p, n) and, optionally, the dual estimate ``psi_delta(r)`` (m, n)
        of an earlier solve; missing duals are derived from the coefficients.
    prepared : Prepared, optional
        :func:`robust_sindy.solvers.problem.prepare` applied to this ``theta`` (skips
        the equilibration and the factorisation when solving repeatedly on the same
        library).
    """
    m, p = theta.shape
    n = y.shape[1]
    lam = np.broadcast_to(lam, (p, n)).astype(float)
    if prepared is None or prepared.equilibrate != equilibrate or prepared.kappa != kappa:
        prepared = prepare(theta, equilibrate=equilibrate, kappa=kappa)
    nz, scale, A = prepared.nz, prepared.scale, prepared.A
    a_norms, factor = prepared.a_norms, prepared.factor
    lam_s = lam[nz] / scale[:, None]
    # Exact per-column rescaling y/c, delta/c, lam/c (solution xi/c) with c = delta, so
    # every column is solved in units of its Huber threshold (rms of y for the squared loss).
    c = np.where(np.isfinite(delta), delta, column_norms(y) / np.sqrt(max(y.shape[0], 1)))
    c = np.where(c > 0, c, 1.0)
    y = y / c
    delta = delta / c
    lam_s = lam_s / c
    ps = A.shape[1]

    rho_k = np.full(n, float(rho))
    if warm_start is not None:
        coef0, dual0 = warm_start
        xi = coef0[nz] * scale[:, None] / c
        r = y - A @ xi
        psi0 = huber_psi(r, delta) if dual0 is None else dual0 / c
        ur = -psi0 / rho_k
        uz = -(A.T @ psi0) / (kappa * rho_k)
    else:
        xi = np.zeros((ps, n))
        r = y.copy()
        ur = np.zeros((m, n))
        uz = np.zeros((ps, n))
    z = xi.copy()

    out_x = np.zeros((ps, n))
    final_rho = rho_k.copy()
    iterations = np.zeros(n, dtype=int)
    newton_total = np.zeros(n, dtype=int)
    converged = np.zeros(n, dtype=bool)
    messages = ["iteration limit reached"] * n
    active = np.arange(n)
    next_polish = check_every
    sq_mp, sq_p = np.sqrt(m + ps), np.sqrt(ps)

    def finish(k_local, x_start):
        """Newton finish on local columns; returns a mask of certified ones."""
        done = np.zeros(active.size, dtype=bool)
        if k_local.size == 0:
            return done
        cols = active[k_local]
        run = newton(
            prepared,
            y_act[:, k_local],
            delta_act[k_local],
            lam_act[:, k_local],
            x_start[:, k_local],
            max_steps=newton_steps,
            tol=tol,
        )
        x, ok = run.x, run.certified
        newton_total[cols] += run.steps
        out_x[:, cols[ok]] = x[:, ok]
        converged[cols[ok]] = True
        for k in cols[ok]:
            messages[k] = f"certified by the active-set finish after {newton_total[k]} Newton steps"
        done[k_local[ok]] = True
        # Restart ADMM from the Newton point where it is better, with consistent duals.
        j = k_local[~ok]
        rj = y_act[:, j] - A @ x[:, ~ok]
        better = column_objective(rj, x[:, ~ok], delta_act[j], lam_act[:, j]) < column_objective(
            y_act[:, j] - A @ z[:, j], z[:, j], delta_act[j], lam_act[:, j]
        )
        j, xb, rb = j[better], x[:, ~ok][:, better], rj[:, better]
        psi = huber_psi(rb, delta_act[j])
        xi[:, j] = z[:, j] = xb
        r[:, j] = rb
        ur[:, j] = -psi / rho_act[j]
        uz[:, j] = -(A.T @ psi) / (kappa * rho_act[j])
        return done

    y_act, lam_act, delta_act, rho_act = y, lam_s, delta, rho_k
    it = 0
    # xi = 0 is optimal iff |A^T psi(y)| <= lam (lam >= lambda_max): exact, one pass.
    done = np.all(np.abs(A.T @ huber_psi(y, delta)) <= lam_s * (1 + 1e-10), axis=0)
    for k in np.flatnonzero(done):
        converged[k] = True
        messages[k] = "zero is optimal (lam >= lambda_max)"
    while True:
        if done.any():
            final_rho[active[done]] = rho_act[done]
            keep = ~done
            active = active[keep]
            y_act, lam_act, delta_act = y_act[:, keep], lam_act[:, keep], delta_act[keep]
            rho_act = rho_act[keep]
            xi, z, r, ur, uz = xi[:, keep], z[:, keep], r[:, keep], ur[:, keep], uz[:, keep]
        if active.size == 0 or it >= max_iter:
            break
        check = (it + 1) % check_every == 0 or it + 1 == max_iter
        rhs = A.T @ (y_act - r - ur)
        rhs += kappa * (z + uz)
        xi = scipy.linalg.cho_solve(factor, rhs, check_finite=False)
        q = A @ xi
        if check:
            r_old, z_old = r, z
        q_hat = alpha * q + (1.0 - alpha) * (y_act - r) if alpha != 1.0 else q
        xi_hat = alpha * xi + (1.0 - alpha) * z if alpha != 1.0 else xi
        v = y_act - q_hat
        r = huber_prox(v - ur, delta_act, rho_act)
        z = soft_threshold(xi_hat - uz, lam_act / (kappa * rho_act))
        ur += r - v
        uz += z - xi_hat
        it += 1
        iterations[active] = it
        done = np.zeros(active.size, dtype=bool)
        if not check:
            continue

        prim = np.sqrt(column_norms(r + q - y_act) ** 2 + column_norms(z - xi) ** 2)
        dual_vec = A.T @ np.hstack([r - r_old, ur])
        k_act = active.size
        dual = rho_act * column_norms(dual_vec[:, :k_act] - kappa * (z - z_old))
        prim_scale = np.max(
            [
                column_norms(q),
                column_norms(r),
                column_norms(y_act),
                column_norms(xi),
                column_norms(z),
            ],
            axis=0,
        )
        dual_scale = rho_act * np.maximum(
            column_norms(dual_vec[:, k_act:]), kappa * column_norms(uz)
        )
        passed = (prim <= eps_abs * sq_mp + eps_rel * prim_scale) & (
            dual <= eps_abs * sq_p + eps_rel * dual_scale
        )
        if passed.any():
            idx = np.flatnonzero(passed)
            cert = certify(A, y_act[:, idx], z[:, idx], delta_act[idx], lam_act[:, idx], a_norms)
            ok = (cert.kkt <= tol) | (cert.rel_gap <= gap_tol)
            for j in idx[ok]:
                out_x[:, active[j]] = z[:, j]
                converged[active[j]] = True
                messages[active[j]] = "converged: residual tests and certificate passed"
            done[idx[ok]] = True
        if polish and (it >= next_polish or passed.any()):
            todo = np.flatnonzero(~done)
            if it >= next_polish:
                next_polish += min(next_polish, _MAX_POLISH_INTERVAL)
            else:
                todo = np.intersect1d(todo, np.flatnonzero(passed))
            done |= finish(todo, z)
        if adaptive_rho and not done.all():
            # Residual balancing (Boyd et al. 2011, sec. 3.4.1) per column, with the
            # step sqrt(prim / dual) bounded by _TAU_MAX (Wohlberg 2017).
            with np.errstate(divide="ignore", invalid="ignore"):
                tau = np.clip(np.sqrt(prim / dual), 1.0 / _TAU_MAX, _TAU_MAX)
            unbalanced = (prim > _MU * dual) | (dual > _MU * prim)
            factor_rho = np.where(unbalanced & np.isfinite(tau), tau, 1.0)
            new_rho = np.clip(rho_act * factor_rho, _RHO_MIN, _RHO_MAX)
            ur *= rho_act / new_rho
            uz *= rho_act / new_rho
            rho_act = new_rho

    final_rho[active] = rho_act
    for j, k in enumerate(active):  # unconverged: return the final sparse iterate
        out_x[:, k] = z[:, j]
    coef = np.zeros((p, n))
    coef[nz] = out_x * c / scale[:, None]
    return SolverOutput(
        coef=coef,
        iterations=iterations,
        converged=converged,
        messages=messages,
        info={"newton_steps": newton_total, "rho": final_rho},
    )
