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
* an active-set (semismooth) Newton finish, tried first (from the least-squares
  solution or the warm start), then at iterations 10, 20, 40, 80, every 100 after, and
  whenever the residual tests pass: from the current iterate take the inlier/outlier
  partition, the support and the signs, solve
  ``Theta_IS^T Theta_IS xi_S = Theta_IS^T y_I + delta Theta_OS^T s_O - lam_S sigma_S``
  (a reweighted least-squares step when the inliers do not determine ``xi_S``), and
  safeguard with an exact line search on the true objective.  It terminates exactly
  once the sets are identified.  Only a point whose KKT certificate is below ``tol``
  ends a column.

A column is converged when its primal and dual residuals pass OSQP-style tests *and*
its relative KKT violation (or relative duality gap) is below tolerance, or when a
Newton finish produced a point with a certified KKT violation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .._certificates import certify, kkt_from_gradient, rounding_free
from .._losses import huber, huber_prox, huber_psi, soft_threshold
from ._base import SolverOutput

__all__ = ["DEFAULT_OPTIONS", "PAPER_OPTIONS", "Prepared", "prepare", "solve_admm"]

DEFAULT_OPTIONS = dict(
    rho=0.1,
    kappa=1.0,
    alpha=1.6,
    equilibrate=True,
    adaptive_rho=True,
    polish=True,
    max_iter=20000,
    eps_abs=1e-10,
    eps_rel=1e-10,
    tol=1e-8,
    gap_tol=1e-12,
    check_every=10,
    newton_steps=8,
    warm_start=None,
)

#: The paper's own settings (Table 1): rho = kappa = 1, no equilibration, no adaptation,
#: no over-relaxation, no polish, 5000 iterations, tolerance 1e-6.
PAPER_OPTIONS = dict(
    rho=1.0,
    kappa=1.0,
    alpha=1.0,
    equilibrate=False,
    adaptive_rho=False,
    polish=False,
    max_iter=5000,
    eps_abs=1e-6,
    eps_rel=1e-6,
    tol=1e-6,
    gap_tol=1e-6,
)

_RHO_MIN, _RHO_MAX, _MU, _TAU_MAX = 1e-10, 1e10, 10.0, 10.0
_MAX_STEP = 2.0**20  # longest line-search step
_FIRST_NEWTON = 5  # the first finish (before any ADMM) may take 5x newton_steps
_EIG_CUT = 1e-11  # relative eigenvalue cut of the Newton systems
_RCOND = np.sqrt(_EIG_CUT)  # the same cut on singular values
_MAX_POLISH_INTERVAL = 100


def _colnorm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->j", a, a))


def _objective(r, x, delta, lam):
    return huber(r, delta).sum() + np.abs(lam * x).sum()


def _solve_sym(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimum-norm solution of a small symmetric PSD system.

    Eigenvalues below ``1e-11`` of the largest are treated as zero: a Cholesky factor
    of a numerically singular Gram matrix (duplicated library columns, too few inliers)
    "succeeds" with a tiny pivot and returns a huge, meaningless step.
    """
    w, V = np.linalg.eigh(M)
    keep = w > _EIG_CUT * max(w[-1], 0.0) if w.size else w.astype(bool)
    inv = 1.0 / w[keep]
    return V[:, keep] @ ((V[:, keep].T @ b) * (inv if b.ndim == 1 else inv[:, None]))


def _lstsq(a: np.ndarray, b: np.ndarray):
    """Least squares by QR with column pivoting (LAPACK gelsy), rank cut at ``_RCOND``."""
    return scipy.linalg.lstsq(a, b, cond=_RCOND, lapack_driver="gelsy", check_finite=False)


def _slope(t, r, q, x, d, lam, delta):
    """Right derivative of ``phi(t) = P(x + t d)``; ``r = y - A x``, ``q = A d``.

    ``phi`` is convex and piecewise quadratic, so its derivative is nondecreasing.
    """
    xt = x + t * d
    s = np.where(xt != 0, np.sign(xt), np.sign(d))
    return (lam * s) @ d - huber_psi(r - t * q, delta) @ q


def _line_search(r, q, x, d, lam, delta) -> float:
    """Exact minimiser of the convex piecewise-quadratic ``phi(t)`` over ``t >= 0``.

    ``phi'(t) = a + b t`` between breakpoints (a residual entering or leaving the
    quadratic zone of the Huber loss, a coordinate crossing zero); the breakpoints are
    sorted once and the slope is accumulated segment by segment, so the minimiser is
    exact (0 if ``d`` is no descent direction, at most ``_MAX_STEP``).
    """
    if _slope(0.0, r, q, x, d, lam, delta) >= 0:
        return 0.0
    # Slope at t = 0+ split into a + b t, and the jumps of (a, b) at later breakpoints.
    moving = q != 0
    rq, qq = r[moving], q[moving]
    absq = np.abs(qq)
    t_a = (rq - delta) / qq  # residual crosses +delta
    t_b = (rq + delta) / qq  # residual crosses -delta
    lo, hi = np.minimum(t_a, t_b), np.maximum(t_a, t_b)
    before = (-absq * delta, np.zeros_like(qq))
    quad = (-qq * rq, qq * qq)
    after = (absq * delta, np.zeros_like(qq))
    # A residual exactly at +-delta has slope continuous there, so "<= 0" is harmless.
    zone_quad = (lo <= 0) & (hi > 0)
    zone_after = hi <= 0
    a0 = np.where(zone_after, after[0], np.where(zone_quad, quad[0], before[0])).sum()
    b0 = np.where(zone_quad, quad[1], 0.0).sum()
    s0 = np.where(x != 0, np.sign(x), np.sign(d))
    a0 += (lam * s0) @ d
    ev_t = [lo[lo > 0], hi[hi > 0]]
    ev_a = [(quad[0] - before[0])[lo > 0], (after[0] - quad[0])[hi > 0]]
    ev_b = [(quad[1] - before[1])[lo > 0], (after[1] - quad[1])[hi > 0]]
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = np.where(d != 0, -x / d, -1.0)
    cross = tz > 0
    ev_t.append(tz[cross])
    ev_a.append((lam * np.abs(d) - lam * s0 * d)[cross])
    ev_b.append(np.zeros(int(cross.sum())))
    t_ev = np.concatenate(ev_t)
    order = np.argsort(t_ev, kind="stable")
    t_ev = t_ev[order]
    ca = a0 + np.concatenate([[0.0], np.cumsum(np.concatenate(ev_a)[order])])
    cb = b0 + np.concatenate([[0.0], np.cumsum(np.concatenate(ev_b)[order])])
    starts = np.concatenate([[0.0], t_ev])
    ends = np.concatenate([t_ev, [np.inf]])
    with np.errstate(invalid="ignore"):
        end_slope = np.where(np.isfinite(ends), ca + cb * ends, np.where(cb > 0, np.inf, ca))
    hit = np.flatnonzero(end_slope >= 0)
    if hit.size == 0:
        return _MAX_STEP
    k = hit[0]
    if ca[k] + cb[k] * starts[k] >= 0 or cb[k] <= 0:
        t = starts[k]
    else:
        t = -ca[k] / cb[k]
    return float(min(max(t, 0.0), _MAX_STEP))


def _phi(t, r, q, x, d, lam, delta) -> float:
    return float(huber(r - t * q, delta).sum() + lam @ np.abs(x + t * d))


def _step_length(r, q, x, d, lam, delta) -> float:
    """The full step if it decreases the objective enough (Armijo, 1e-4), else exact."""
    s0 = _slope(0.0, r, q, x, d, lam, delta)
    if s0 >= 0:
        return 0.0
    if _phi(1.0, r, q, x, d, lam, delta) <= _phi(0.0, r, q, x, d, lam, delta) + 1e-4 * s0:
        return 1.0
    return _line_search(r, q, x, d, lam, delta)


def newton_finish(A, G, y, lam, delta, x, *, max_steps, tol, col_norms, lipschitz, abs_a=None):
    """Semismooth Newton on one column, globalised by an exact line search.

    ``A`` (m, p), ``G = A^T A``, ``y`` (m,), ``lam`` (p,), scalar ``delta``,
    ``lipschitz`` the largest eigenvalue of ``G``.

    The Newton step is that of the proximal-gradient fixed point
    ``x = S(x + T g, T lam)`` (``T = diag(1 / ||A_j||^2)``): the support is
    ``S = {|x + T g| > T lam}`` with signs ``sign(x + T g)``, the inlier/outlier
    partition is that of the current residual, and the step solves
    ``A_IS^T A_IS xi_S = A_IS^T y_I + delta A_OS^T s_O - lam_S sigma_S`` (coordinates
    off ``S`` go to exactly zero).  Once the sets are right this is the exact optimum.
    When the step is no descent direction, a proximal-gradient step (always one)
    is taken instead.  Returns ``(x, certified, steps)``.
    """
    x = x.copy()
    free = lam == 0
    T = 1.0 / col_norms**2
    r = y - A @ x
    best = None
    abs_a = (lambda: np.abs(A)) if abs_a is None else abs_a

    def gradient_and_kkt(x, r):
        psi = huber_psi(rounding_free(r, y, abs_a, x), delta)
        g = A.T @ psi
        scale = np.atleast_1d(np.linalg.norm(psi))
        return g, kkt_from_gradient(x[:, None], g[:, None], lam[:, None], col_norms, scale)[0]

    for step in range(max_steps + 1):
        g, kkt = gradient_and_kkt(x, r)
        if kkt <= tol and (best is None or kkt < best[1]):
            best = (x, kkt, step, g)
        if kkt <= 0.1 * tol:  # a margin, so the check in the caller's units passes too
            break
        if step == max_steps:
            break
        u = x + T * g
        S = (np.abs(u) > T * lam) | free
        sigma = np.where(free, 0.0, np.sign(u))
        out = np.abs(r) > delta
        AS = A[:, S]
        inl = ~out
        AI = AS[inl]
        n_s = AS.shape[1]
        # The inlier least-squares part by an orthogonal factorisation (residuals of an
        # exact fit stay at rounding level), the linear terms through the Gram matrix.
        if AI.size:
            step_s, _, rank, _ = _lstsq(AI, y[inl])
        else:
            step_s, rank = np.zeros(n_s), 0
        b = -lam[S] * sigma[S]
        if rank < n_s:
            # Too few inliers to fix the support's coefficients (the loss is linear along
            # some direction, as in least-absolute-deviation fits): take the
            # iteratively-reweighted least-squares step instead, whose quadratic model
            # majorises the Huber loss (weights min(1, delta / |r_i|)).
            sw = np.sqrt(np.minimum(1.0, delta / np.maximum(np.abs(r), np.finfo(float).tiny)))
            AW = AS * sw[:, None]
            step_s = _lstsq(AW, sw * y)[0]
            if np.any(b):
                step_s += _solve_sym(AW.T @ AW, b)
        else:
            if out.any():
                b += delta * (AS[out].T @ np.sign(r[out]))
            if np.any(b):
                if 2 * np.count_nonzero(out) < A.shape[0]:
                    AO = AS[out]
                    M = G[np.ix_(S, S)] - AO.T @ AO
                else:
                    M = AI.T @ AI
                step_s += _solve_sym(M, b)
        cand = np.zeros_like(x)
        cand[S] = step_s
        d = cand - x
        q = A @ d
        t = _step_length(r, q, x, d, lam, delta)
        if t == 0.0:
            d = soft_threshold(x + g / lipschitz, lam / lipschitz) - x
            q = A @ d
            t = _line_search(r, q, x, d, lam, delta)
            if t == 0.0:
                break
        if t == 1.0:
            x = x + d
            r = y - A @ x
        else:
            x = x + t * d
            r = r - t * q
    if best is None:
        return x, False, step
    x, _, step, g = best
    # A partial line-search step leaves rounding-level entries where the optimum has
    # exact zeros; drop those the proximal-gradient map sets to zero if the certificate
    # still holds.
    zero = (np.abs(x + T * g) <= T * lam) & (x != 0)
    if zero.any():
        xc = np.where(zero, 0.0, x)
        if gradient_and_kkt(xc, y - A @ xc)[1] <= tol:
            x = xc
    return x, True, step


@dataclass
class Prepared:
    """What ADMM and its finish compute from ``Theta`` alone (reusable along a path)."""

    nz: np.ndarray  # nonzero columns of Theta
    scale: np.ndarray  # their equilibration scales
    A: np.ndarray  # Theta[:, nz] / scale
    G: np.ndarray  # A^T A
    a_norms: np.ndarray
    lipschitz: float
    factor: tuple  # Cholesky factor of G + kappa I
    equilibrate: bool
    kappa: float
    _abs_a: np.ndarray | None = None

    def abs_a(self) -> np.ndarray:
        """``|A|``, computed on first use (only certificates of near-exact fits need it)."""
        if self._abs_a is None:
            self._abs_a = np.abs(self.A)
        return self._abs_a


def prepare(theta: np.ndarray, *, equilibrate: bool = True, kappa: float = 1.0) -> Prepared:
    """Equilibrate ``theta`` and factorise once; pass as ``prepared`` to :func:`solve_admm`."""
    norms = _colnorm(theta)
    nz = norms > 0
    scale = norms[nz] if equilibrate else np.ones(np.count_nonzero(nz))
    A = theta[:, nz] / scale
    G = A.T @ A
    lipschitz = max(float(np.linalg.eigvalsh(G)[-1]), np.finfo(float).tiny) if G.size else 1.0
    factor = scipy.linalg.cho_factor(G + kappa * np.eye(A.shape[1]), check_finite=False)
    return Prepared(nz, scale, A, G, _colnorm(A), lipschitz, factor, equilibrate, kappa)


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
        Try the active-set Newton finish before any ADMM iteration, then at iterations
        10, 20, 40, 80, every 100 after, and whenever the residual tests pass.
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
        :func:`prepare` applied to this ``theta`` (skips the equilibration and the
        factorisation when solving repeatedly on the same library).
    """
    m, p = theta.shape
    n = y.shape[1]
    lam = np.broadcast_to(lam, (p, n)).astype(float)
    if prepared is None or prepared.equilibrate != equilibrate or prepared.kappa != kappa:
        prepared = prepare(theta, equilibrate=equilibrate, kappa=kappa)
    nz, scale, A, G = prepared.nz, prepared.scale, prepared.A, prepared.G
    a_norms, abs_a, lipschitz, factor = (
        prepared.a_norms,
        prepared.abs_a,  # a method: |A| is formed only if needed
        prepared.lipschitz,
        prepared.factor,
    )
    lam_s = lam[nz] / scale[:, None]
    # Exact per-column rescaling y/c, delta/c, lam/c (solution xi/c) with c = delta, so
    # every column is solved in units of its Huber threshold (rms of y for the squared loss).
    c = np.where(np.isfinite(delta), delta, np.sqrt(np.mean(y**2, axis=0)))
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

    def finish(cols, k_local, x_start, max_steps=newton_steps):
        """Newton finish on local columns; returns a mask of certified ones."""
        done = np.zeros(len(cols), dtype=bool)
        for j in k_local:
            k = cols[j]
            x, ok, steps = newton_finish(
                A,
                G,
                y_act[:, j],
                lam_act[:, j],
                delta_act[j],
                x_start[:, j],
                max_steps=max_steps,
                tol=tol,
                col_norms=a_norms,
                lipschitz=lipschitz,
                abs_a=abs_a,
            )
            newton_total[k] += steps
            if ok:
                out_x[:, k] = x
                converged[k] = True
                messages[k] = f"certified by the active-set finish after {steps} Newton steps"
                done[j] = True
                continue
            rj = y_act[:, j] - A @ x
            rz = y_act[:, j] - A @ z[:, j]
            if _objective(rj, x, delta_act[j], lam_act[:, j]) < _objective(
                rz, z[:, j], delta_act[j], lam_act[:, j]
            ):
                # Restart ADMM from the better point with consistent duals.
                psi = huber_psi(rj, delta_act[j])
                xi[:, j] = z[:, j] = x
                r[:, j] = rj
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
    if polish:
        # Newton first: from the warm start, or from the (minimum-norm)
        # least-squares solution; most problems are finished here without ADMM.
        start = z if warm_start is not None else _solve_sym(G, A.T @ y)
        todo = np.flatnonzero(~done)
        done |= finish(active, todo, start, _FIRST_NEWTON * newton_steps)
        next_polish = check_every
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

        prim = np.sqrt(_colnorm(r + q - y_act) ** 2 + _colnorm(z - xi) ** 2)
        dual_vec = A.T @ np.hstack([r - r_old, ur])
        k_act = active.size
        dual = rho_act * _colnorm(dual_vec[:, :k_act] - kappa * (z - z_old))
        prim_scale = np.max(
            [_colnorm(q), _colnorm(r), _colnorm(y_act), _colnorm(xi), _colnorm(z)], axis=0
        )
        dual_scale = rho_act * np.maximum(_colnorm(dual_vec[:, k_act:]), kappa * _colnorm(uz))
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
            done |= finish(active, todo, z)
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
