"""The Huber-Lasso problem over all equations at once, under linear constraints.

.. math::

    \\min_{\\Xi} \\sum_k \\sum_i H_{\\delta_k}(y_{ik} - \\theta_i \\xi_k)
    + \\sum_{jk} \\lambda_{jk} |\\Xi_{jk}|
    \\quad \\text{s.t.} \\quad A_{eq} x = b_{eq}, \\; A_{ub} x \\le b_{ub},
    \\quad x = \\operatorname{vec}(\\Xi)

(:mod:`robust_sindy.core.constraints` gives the ordering and the certificate).

**Reference** (:func:`solve_constrained_cvxpy`): the problem posed in CVXPY,
``cp.huber`` (which is ``2 H``, hence the factor 1/2), ``cp.abs`` and the
constraints on ``cp.vec(Xi)``, solved by Clarabel or OSQP.

**Fast path** (:func:`solve_constrained_admm`): first the polish below from a warm
start when one is given, then from the unconstrained fast path's answer
(:func:`robust_sindy.solvers.driver.solve`), which certifies at once when the
constraints move the optimum little; otherwise the Huber loss is the infimal
convolution ``H_delta(r) = min_w (r - w)^2 / 2 + delta |w|``, so the problem is a
least-squares problem in ``(x, w)`` with L1 terms on both.  Inequalities get slacks
``A_ub x + s = b_ub``, ``s >= 0``.  ADMM splits ``(x, s, w)`` (a least-squares step
under the equality constraints: one Cholesky factor of ``kappa Theta^T Theta + rho I``,
shared by every equation, and a Schur complement of the size of the constraints)
from copies ``(z, q, v)`` (soft-thresholding and a clip: ``v`` is nonzero exactly on
the outliers, ``z`` exactly on the support).  Then a polish: on the support, the
inliers and the active inequalities that the iteration found, the optimality
conditions are linear (an equality-constrained least-squares problem); it is solved
and the sets are updated until they no longer change, with a proximal step to the
exact minimiser along it where that point is no descent (:func:`_polish`).  The
certificate decides.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from ..core.certificates import column_norms, rounding_floor, within_floor
from ..core.constraints import LinearConstraints, constrained_certificate
from ..core.losses import huber, huber_psi, soft_threshold
from . import driver
from .newton import line_search

__all__ = [
    "FINAL_ROUNDS",
    "POLISH_ROUNDS",
    "PROX",
    "STALL_ROUNDS",
    "ConstrainedOutput",
    "solve_constrained_admm",
    "solve_constrained_cvxpy",
]

#: Rounds of an early polish (ADMM residuals above 1e-4 of the iterates' size).
POLISH_ROUNDS = 15
#: Rounds of a polish that runs to the end (from the unconstrained answer, or once
#: ADMM has converged).  Each round solves one system of the support's size; where
#: nearly every residual is beyond delta (a problem close to least absolute
#: deviations) the polish walks from piece to piece like a simplex method (up to 134
#: objective evaluations, one or two a round, on the hardest problems of the tests).
FINAL_ROUNDS = 200
#: ADMM iterations of the unconstrained fast path when its answer is only the polish's
#: start (where Newton cannot certify it, e.g. at the floating-point floor of a nearly
#: exact fit, a start needs no more).
START_MAX_ITER = 1000
#: Corrections of a settled Newton point of the polish (iterative refinement).
REFINE_ROUNDS = 2
#: Rounds in a row without a lower objective after which the polish stops (as the
#: unconstrained Newton method's stall rule); its point then goes to the certificate.
STALL_ROUNDS = 5
#: The proximal weight of the polish's fallback step, in the normalised units of
#: :func:`_normalised` (library columns of norm 1): far below the curvature of any
#: inlier, so it only bounds the directions that have none.
PROX = 1e-8


class ConstrainedOutput:
    """A solver's answer: ``coef`` (p, n), ``iterations``, ``status``, its multipliers
    (``nu``, ``mu``; None when it has none) and the constrained certificate of ``coef``
    when the solver computed it."""

    def __init__(self, coef, iterations, status, nu=None, mu=None, info=None, certificate=None):
        self.coef, self.iterations, self.status = coef, int(iterations), status
        self.nu, self.mu, self.info = nu, mu, info or {}
        self.certificate = certificate


def _normalised(theta, y, delta, lam, constraints):
    """The problem in units where the library's columns have norm 1, the targets a root
    mean square of 1 (``x = back * u``) and each constraint row (with its bound) norm 1:
    ``(theta, y, delta, lam (vec), back, (c_eq, b_eq, size_eq), (c_ub, b_ub, size_ub),
    sigma)``.  The objective is ``sigma^2`` times the original one, and a multiplier
    ``nu'`` of a normalised row is ``sigma^2 nu' / size`` in the original units."""
    p, n = theta.shape[1], y.shape[1]
    norms = column_norms(theta)
    scale = np.where(norms > 0, norms, 1.0)
    sigma = float(np.sqrt(np.mean(y**2)))
    sigma = sigma if np.isfinite(sigma) and sigma > 0 else 1.0
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (p, n))
    back = sigma / np.tile(scale, n)

    def rows(a, b):
        a = a * back
        size = np.sqrt(np.einsum("ij,ij->i", a, a) + b**2)
        size = np.where(size > 0, size, 1.0)
        return a / size[:, None], b / size, size

    return (
        theta / scale, y / sigma, np.asarray(delta, dtype=float) / sigma,
        (lam / (sigma * scale[:, None])).ravel(order="F"), back,
        rows(constraints.A_eq, constraints.b_eq), rows(constraints.A_ub, constraints.b_ub), sigma,
    )  # fmt: skip


def solve_constrained_cvxpy(
    theta, y, delta, lam, constraints: LinearConstraints, *, solver="clarabel", verbose=False,
    **solver_options,
) -> ConstrainedOutput:  # fmt: skip
    """The constrained problem posed in CVXPY (the reference), in the normalised units
    of :func:`_normalised` (the interior-point method's tolerances are absolute: in the
    user's units a problem scaled by 1e12 reads as infeasible)."""
    import cvxpy as cp

    from .reference import SETTINGS, solve_problem

    name = solver.upper()
    if name not in cp.installed_solvers():
        raise ImportError(
            f"solver={solver!r} is not installed for CVXPY; install it with `pip install {solver}`"
        )
    p, n = theta.shape[1], y.shape[1]
    ts, ys, ds, lam_s, back, (c_eq, b_eq, size_eq), (c_ub, b_ub, size_ub), sigma = _normalised(
        theta, y, delta, lam, constraints
    )
    u = cp.Variable((p, n))
    resid = ys - ts @ u
    loss = sum(
        0.5 * cp.sum_squares(resid[:, k])
        if np.isinf(ds[k])
        else 0.5 * cp.sum(cp.huber(resid[:, k], float(ds[k])))
        for k in range(n)
    )
    vec = cp.vec(u, order="F")
    cons = []
    if c_eq.shape[0]:
        cons.append(c_eq @ vec == b_eq)
    if c_ub.shape[0]:
        cons.append(c_ub @ vec <= b_ub)
    problem = cp.Problem(cp.Minimize(loss + lam_s @ cp.abs(vec)), cons)
    settings = {**SETTINGS[solver], **solver_options}
    try:
        solve_problem(problem, name, verbose, settings)
    except cp.error.SolverError as exc:
        return ConstrainedOutput(np.zeros((p, n)), 0, f"{solver} failed: {exc}")
    if u.value is None:
        return ConstrainedOutput(np.zeros((p, n)), 0, f"{solver}: {problem.status}")
    coef = (back * np.asarray(u.value, dtype=float).ravel(order="F")).reshape(p, n, order="F")
    # CVXPY's duals of "A x == b" and "A x <= b" are the multipliers of the Lagrangian
    # with "+ nu^T (A x - b)", as in the certificate.
    nu, mu = np.zeros(c_eq.shape[0]), np.zeros(c_ub.shape[0])
    duals = [np.asarray(con.dual_value, dtype=float).reshape(-1) for con in cons]
    if c_eq.shape[0]:
        nu = sigma**2 * duals.pop(0) / size_eq
    if c_ub.shape[0]:
        mu = sigma**2 * duals.pop(0) / size_ub
    stats = problem.solver_stats
    iterations = stats.num_iters if stats is not None and stats.num_iters is not None else 0
    return ConstrainedOutput(coef, iterations, f"{solver}: {problem.status}", nu, mu)


class _Factor:
    """``M^{-1}`` for ``M = I_n (x) (kappa G + rho I)`` (``G = Theta^T Theta``), and the
    pseudo-inverse of the Schur complement ``C M^{-1} C^T + diag(0, I / rho)`` of the
    constraints ``C = [A_eq; A_ub]`` (equalities first)."""

    def __init__(self, gram, rho, c, n, r_eq):
        self.rho, self.kappa = rho, rho / (1.0 + rho)
        p = gram.shape[0]
        self.chol = scipy.linalg.cho_factor(self.kappa * gram + rho * np.eye(p))
        self.p, self.n, self.c = p, n, c
        if c.shape[0]:
            minv_ct = self.solve_m(c.T)
            s = c @ minv_ct
            s[r_eq:, r_eq:] += np.eye(c.shape[0] - r_eq) / rho
            w, v = np.linalg.eigh(0.5 * (s + s.T))
            keep = w > 1e-12 * max(float(w.max(initial=0.0)), np.finfo(float).tiny)
            self.s_pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
            self.minv_ct = minv_ct

    def solve_m(self, b):
        """``M^{-1} b`` for ``b`` (p n,) or (p n, k), column-major blocks."""
        shape = b.shape
        blocks = b.reshape(self.n, self.p, -1).transpose(1, 0, 2).reshape(self.p, -1)
        out = scipy.linalg.cho_solve(self.chol, blocks)
        return out.reshape(self.p, self.n, -1).transpose(1, 0, 2).reshape(shape)


def _theta_t(theta, r):
    """``vec(Theta^T R)`` for ``R`` (m, n)."""
    return (theta.T @ r).ravel(order="F")


def _theta_x(theta, x, n):
    """``Theta Xi`` for ``x = vec(Xi)``, column-major (m, n): elementwise work against
    a per-equation ``delta`` then runs along contiguous columns (several times faster
    than along rows of ``n`` entries)."""
    return (x.reshape(-1, n, order="F").T @ theta.T).T


def _objective(theta, y, delta, lam_v, x):
    """The problem's objective at ``x`` (vec), the residuals and their Huber
    derivatives ``psi``."""
    r = y - _theta_x(theta, x, y.shape[1])
    psi = huber_psi(r, delta[None, :])
    return float(huber(r, delta[None, :], psi=psi).sum() + lam_v @ np.abs(x)), r, psi


def _inlier_system(theta, y, delta, outside, out_sign, previous=None):
    """Per equation, the Gram matrix of the inliers (n, p, p) and ``Theta_I^T y_I +
    delta Theta_O^T sign(r_O)`` (p, n): the optimality conditions with these outliers.
    ``previous`` (the Gram matrices and outliers of an earlier call) is updated by the
    rows whose status changed when they are fewer than the outliers."""
    grams = np.empty((y.shape[1], theta.shape[1], theta.shape[1]))
    full = None
    for k in range(y.shape[1]):
        if previous is not None:
            went = outside[:, k] & ~previous[1][:, k]
            came = previous[1][:, k] & ~outside[:, k]
            if went.sum() + came.sum() < outside[:, k].sum():
                a, b = theta[went], theta[came]
                grams[k] = previous[0][k] - a.T @ a + b.T @ b
                continue
        if full is None:
            full = theta.T @ theta
        out = theta[outside[:, k]]  # the full Gram matrix less the outliers' rows
        grams[k] = full - out.T @ out
    # With the squared loss (delta = inf) there are no outliers; inf * 0 off them.
    with np.errstate(invalid="ignore"):
        clipped = delta[None, :] * out_sign
    rhs = theta.T @ np.where(outside, clipped, y)
    return grams, rhs


def _newton_point(system, lam_v, c, d, support, sign, p, at=None, prox=0.0):
    """The minimiser of the objective with the outliers' and the support's signs
    fixed (``system``: :func:`_inlier_system`), on ``support``, under
    ``c[:, support] x = d`` (least squares: a singular system gets its minimum-norm
    solution); with ``prox`` > 0, of that objective plus ``prox / 2 ||x - at||^2``
    (a proximal step, bounded where the inliers leave directions without curvature).
    Returns ``(x_support, multipliers, whether it meets the stationarity)``."""
    grams, rhs_full = system
    cols, eq = support % p, support // p
    same = eq[:, None] == eq[None, :]
    h = np.where(same, grams[eq[:, None], cols[:, None], cols[None, :]], 0.0)
    rhs = rhs_full[cols, eq] - lam_v[support] * sign
    if prox:
        h = h + prox * np.eye(h.shape[0])
        rhs = rhs + prox * at
    c = c[:, support]
    kkt = np.block([[h, c.T], [c, np.zeros((c.shape[0], c.shape[0]))]])
    sol = np.linalg.lstsq(kkt, np.concatenate([rhs, d]), rcond=None)[0]
    xs, mult = sol[: support.size], sol[support.size :]
    # Where the inliers leave a direction without curvature along which the outliers'
    # pull does not vanish, the piece has no minimiser and the least-squares solution
    # does not meet its stationarity.
    parts = (h @ xs, c.T @ mult, rhs)
    miss = np.linalg.norm(parts[0] + parts[1] - parts[2])
    return xs, mult, bool(miss <= 1e-8 * sum(np.linalg.norm(v) for v in parts))


def stationarity_floor(theta, y, coef, delta, residual) -> float:
    """The relative stationarity that the rounding of the residuals alone can leave at
    ``coef`` (p, n): the largest over the equations of
    :func:`robust_sindy.core.certificates.rounding_floor`."""
    return float(rounding_floor(theta, y, coef, delta, residual).max(initial=0.0))


def _refined(theta, y, delta, lam_v, x, support, sign, grams, c, d, p, rounds=REFINE_ROUNDS):
    """Iterative refinement of a settled Newton point ``x`` (vec) of the polish: with
    the sets fixed, the correction ``dx`` on ``support`` solves the same linear
    conditions with the gradient ``Theta^T psi`` at ``x`` (from the residuals, not from
    the Gram matrices) and the constraints' residual ``d - c x`` as right-hand sides.
    Returns ``(x, multipliers, residuals, psi)`` after ``rounds`` corrections, or None
    when the system has no solution there."""
    mult = None
    for _ in range(rounds):
        _, _, psi = _objective(theta, y, delta, lam_v, x)
        grad = theta.T @ psi
        dx, mult, exact = _newton_point((grams, grad), lam_v, c, d - c @ x, support, sign, p)
        if not exact:
            return None
        x = x.copy()
        x[support] += dx
    _, r, psi = _objective(theta, y, delta, lam_v, x)
    return x, mult, r, psi


def _step(x, support, xs, c_ub, b_ub, active, free, descend):
    """The step from ``x`` to the point ``xs`` on ``support`` and its longest length
    (at most 1): up to the first penalised coefficient that crosses zero or inactive
    inequality that would be violated when it must ``descend``; otherwise (the first
    step from a start that does not meet the constraints) whole, to reach them."""
    target = np.zeros_like(x)
    target[support] = xs
    step = target - x
    alpha = 1.0
    if descend:
        old = (x[support] != 0) & ~free[support]
        cross = old & (np.sign(xs) != np.sign(x[support]))
        if cross.any():
            t = x[support][cross] / (x[support][cross] - xs[cross])
            alpha = min(alpha, float(t.min()))
        inactive = ~active
        grow = c_ub[inactive] @ step
        room = b_ub[inactive] - c_ub[inactive] @ x
        hit = grow > 0
        if hit.any():
            alpha = min(alpha, float(np.min(np.maximum(room[hit], 0.0) / grow[hit])))
    return step, alpha


def _stepped(theta, y, delta, lam_v, x, step, alpha, support):
    """``x + alpha step`` (crossing coefficients landed exactly on zero when the
    step stops short), with :func:`_objective` there."""
    trial = x + alpha * step
    if alpha < 1.0:
        trial[support[(np.abs(trial[support]) <= 1e-12 * np.abs(x[support]))]] = 0.0
    return trial, _objective(theta, y, delta, lam_v, trial)


def _sides(r, delta):
    """The outliers' sides: ``sign(r)`` where ``|r| > delta``, else 0."""
    return np.sign(r) * (np.abs(r) > delta[None, :])


def _line_search(theta, y, delta, lam_v, x, r, step, upper):
    """The exact minimiser over ``[0, upper]`` of the objective along ``step`` from
    ``x`` (residuals ``r``): :func:`robust_sindy.solvers.newton.line_search` over the
    residuals of every equation at once."""
    q = _theta_x(theta, step, y.shape[1])
    moving = q != 0
    deltas = np.broadcast_to(delta[None, :], r.shape)[moving]
    return line_search(r[moving], q[moving], x, step, lam_v, deltas, upper=upper)


def _polish(
    theta, y, delta, lam, c_eq, b_eq, c_ub, b_ub, x, active, rounds=FINAL_ROUNDS
):  # fmt: skip
    """A semismooth Newton method with working sets, from an approximate solution
    ``x`` (vec) and its ``active`` inequalities.  On the support and signs of ``x``,
    the outliers and signs of its residuals and the active inequalities, the
    optimality conditions are linear (:func:`_newton_point`); the step towards that
    point stops where a coefficient crosses zero (it leaves the support) or an
    inactive inequality would be violated (it becomes active).  Then inequalities
    with a negative multiplier are released, and the terms whose stationarity is
    violated enter with the sign of their violation (kept at zero when the solve gives
    them the other sign).  Where that point does not lower the objective, or does not
    meet the linear conditions (the inliers leave a direction without curvature), a
    proximal step (weight ``PROX``) is taken instead, to the exact minimiser along it.
    Coefficients without penalty have no sign to keep: they are always in the support
    and may cross zero.  Stops when a full Newton step changes no set (no outlier
    changes side).  Returns ``(x, nu, mu, settled)``, or None."""
    p = theta.shape[1]
    n = y.shape[1]
    lam_v = lam.ravel(order="F")
    # Rows that hold one coefficient at zero (a coefficient not selected): it is left
    # out of every system, and its multiplier is read off its stationarity at the end.
    single = (c_eq != 0).sum(axis=1) == 1
    pins = np.flatnonzero(single & (b_eq == 0))
    pinned_at = np.argmax(c_eq[pins] != 0, axis=1)
    pinned = np.zeros(x.size, dtype=bool)
    pinned[pinned_at] = True
    first_pin = np.unique(pinned_at, return_index=True)[1]  # one row per coefficient
    rows = np.setdiff1d(np.arange(c_eq.shape[0]), pins)
    c_rows, b_rows = c_eq[rows], b_eq[rows]
    r_eq = rows.size
    free = (lam_v == 0) & ~pinned  # no kink at zero: in the support, any sign
    norms = np.tile(column_norms(theta), n)
    obj, r, psi = _objective(theta, y, delta, lam_v, x)
    pulled = _sides(r, delta)
    entering = np.zeros_like(x)  # the sign each entering term must take
    # Terms that entered with neither sign: with constraints the multipliers need not
    # be unique, and another choice of them may well satisfy such a term at zero (the
    # certificate fits them over every term); they do not enter again.
    blocked = np.zeros(x.size, dtype=bool)
    best = previous = None
    # A start that already meets the constraints (e.g. a warm start) descends from the
    # first round; otherwise the first step is taken whole, to reach them.
    gap = np.concatenate([np.abs(c_eq @ x - b_eq), np.maximum(c_ub @ x - b_ub, 0.0)])
    reached = gap.max(initial=0.0) <= 1e-12 * max(1.0, np.abs(x).max(initial=0.0))
    stalled = 0

    def multipliers(mult, psi, active):
        """Every row's multiplier from a solve's (``mult``: the kept equalities',
        then the ``active`` inequalities'), the pinned rows' read off stationarity,
        and what stationarity leaves (``hh``, zero at the pinned coefficients)."""
        nu = np.zeros(c_eq.shape[0])
        nu[rows] = mult[:r_eq]
        mu = np.zeros(c_ub.shape[0])
        mu[active] = mult[r_eq:]
        hh = _theta_t(theta, psi) - c_eq.T @ nu - c_ub.T @ mu
        at = pinned_at[first_pin]
        nu[pins[first_pin]] = hh[at] / c_eq[pins[first_pin], at]
        hh[at] = 0.0
        return nu, mu, hh

    for round_ in range(rounds):
        descend = bool(round_) or reached
        outside = pulled != 0
        system = _inlier_system(theta, y, delta, outside, pulled, previous)
        previous = (system[0], outside)
        c = np.vstack([c_rows, c_ub[active]])
        d = np.concatenate([b_rows, b_ub[active]])
        turned = np.zeros(x.size, dtype=bool)
        while True:
            support = np.flatnonzero(((x != 0) | (entering != 0) | free) & ~pinned)
            sign = np.where(x[support] != 0, np.sign(x[support]), entering[support])
            xs, mult, exact = _newton_point(system, lam_v, c, d, support, sign, p)
            wrong = support[(entering[support] != 0) & (np.sign(xs) != entering[support])]
            if not wrong.size:
                break
            # The constraints' multipliers move with the support: an entering term may
            # belong on the other side. Once turned, a term that is still wrong stays
            # at zero, and the system is solved again without it.
            again = turned[wrong]
            entering[wrong[again]] = 0.0
            blocked[wrong[again]] = True
            entering[wrong[~again]] *= -1.0
            turned[wrong] = True
        step, alpha = _step(x, support, xs, c_ub, b_ub, active, free, descend)
        trial, new = _stepped(theta, y, delta, lam_v, x, step, alpha, support)
        new_obj, new_r, new_psi = new
        if descend and (not exact or new_obj > obj + 1e-13 * abs(obj)):
            # The pieces at x are not the minimiser's (and where the inliers leave a
            # direction without curvature, the Newton point is no guide at all): a
            # proximal step instead, to the exact minimiser along it (a convex
            # piecewise quadratic) within the same bounds.
            xs, mult, _ = _newton_point(system, lam_v, c, d, support, sign, p, x[support], PROX)
            exact = False  # not a settled point: the next round's Newton point decides
            step, alpha = _step(x, support, xs, c_ub, b_ub, active, free, descend)
            alpha = _line_search(theta, y, delta, lam_v, x, r, step, alpha)
            trial, new = _stepped(theta, y, delta, lam_v, x, step, alpha, support)
            new_obj, new_r, new_psi = new
            if alpha == 0.0 or new_obj > obj + 1e-13 * abs(obj):
                return None if best is None else (*best, False)
        # Rounds that no longer lower the objective: at a degenerate optimum the sets
        # can cycle (a term enters, crosses zero, leaves); the certificate decides.
        stalled = stalled + 1 if new_obj >= obj - 1e-13 * abs(obj) else 0
        x, obj, r, psi = trial, new_obj, new_r, new_psi
        entering[:] = 0.0
        nu, mu, hh = multipliers(mult, psi, active)
        scale = np.maximum(lam_v, norms * np.repeat(column_norms(psi), p))
        excess = np.where((x == 0) & ~blocked & ~free & ~pinned, (np.abs(hh) - lam_v) / scale, 0.0)
        enter = np.zeros_like(excess, dtype=bool)
        if excess.max(initial=0.0) > 1e-10:  # the most violated term enters, one a round
            enter[np.argmax(excess)] = True
        release = active & (mu < 0)
        violated = ~active & (c_ub @ x > b_ub)
        best = (x.copy(), nu, np.maximum(mu, 0.0))
        # The same outliers on the same sides (a residual may jump across the zone).
        sides = _sides(r, delta)
        same = np.array_equal(sides, pulled)
        if exact and alpha == 1.0 and same and not (enter.any() or release.any() or violated.any()):
            # Settled: the Newton point came from the inliers' Gram matrices, whose
            # rounding is the square of the library's condition; corrections solved
            # against the gradient from the residuals themselves recover the accuracy.
            refined = _refined(theta, y, delta, lam_v, x, support, sign, system[0], c, d, p)
            if refined is not None:
                x_r, mult_r, r_r, psi_r = refined
                if np.array_equal(_sides(r_r, delta), pulled):
                    nu_r, mu_r, _ = multipliers(mult_r, psi_r, active)
                    best = (x_r, nu_r, np.maximum(mu_r, 0.0))
            return (*best, True)
        if stalled >= STALL_ROUNDS:
            return (*best, False)
        entering[enter] = np.sign(hh[enter])
        active = (active & ~release) | violated
        pulled = sides
    return None if best is None else (*best, False)


def solve_constrained_admm(
    theta, y, delta, lam, constraints: LinearConstraints, *, rho=1.0, alpha=1.6,
    max_iter=20_000, eps=1e-9, tol=1e-8, check_every=10, polish=True, warm_start=None,
) -> ConstrainedOutput:  # fmt: skip
    """The constrained problem by ADMM on the Huber loss's infimal convolution, then a
    polish on the sets it found (see the module docstring); ``tol`` is the relative
    KKT violation (stationarity and constraint residual) that stops it.
    ``warm_start`` (p, n), e.g. the answer to a problem that differs a little, is the
    polish's first start; the unconstrained fast path's answer is the next.

    It runs in units where the library's columns have norm 1 and the targets a root
    mean square of 1 (``u = scale x / sigma``), with each constraint's row of unit
    norm: the same iterates whatever the units of the states, time and terms."""
    m, p = theta.shape
    n = y.shape[1]
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (p, n))
    delta = np.asarray(delta, dtype=float)
    ts, ys, ds, lam_s, back, (c_eq, b_eq, size_eq), (c_ub, b_ub, size_ub), sigma = _normalised(
        theta, y, delta, lam, constraints
    )
    ys = np.asfortranarray(ys)  # as the residuals (see _theta_x)
    r_eq, r_ub = c_eq.shape[0], c_ub.shape[0]
    c = np.vstack([c_eq, c_ub])

    def certificate(point, nu=None, mu=None):
        coef = (back * point).reshape(p, n, order="F")
        if nu is not None:  # the multipliers in the user's units
            nu, mu = sigma**2 * nu / size_eq, sigma**2 * mu / size_ub
        return coef, constrained_certificate(theta, y, coef, delta, lam, constraints, nu, mu)

    history = []
    it = 0
    status = "max_iter"
    best = last = None
    starts = []
    if polish and warm_start is not None:
        starts.append(("warm start", lambda: np.asarray(warm_start, float).ravel(order="F")))
    if polish:
        # The polish from the unconstrained fast path's answer: when the constraints
        # move the optimum little, its sets are nearly right.
        starts.append(
            (
                "unconstrained",
                lambda: driver.solve(theta, y, delta, lam, max_iter=START_MAX_ITER).coef.ravel(
                    order="F"
                ),
            )
        )
    for name, start in starts:
        free = start() / back
        slack = np.maximum(b_ub - c_ub @ free, 0.0)
        point, nu, mu, settled = _polish_point(
            ts, ys, ds, lam_s, c_eq, b_eq, c_ub, b_ub, free, slack
        )
        # An unsettled polish may still end at the optimum (at a degenerate one the
        # working sets can cycle at a constant objective): the certificate decides.
        if nu is not None:
            found = certificate(point, nu, mu)
            if best is None or found[1].kkt < best[1].kkt:
                best = found
            if best[1].kkt <= tol:
                coef, cert = best
                info = {"history": history, "rho": rho, "start": name}
                return ConstrainedOutput(coef, 0, "certified", cert.nu, cert.mu, info, cert)
            coef, cert = found
            if settled and cert.feasibility <= tol:
                # The polish settled on its sets: where what stationarity misses is the
                # rounding of the residuals themselves (a nearly exact fit), no method
                # resolves it further, and ADMM would only spend its iterations.
                floor = stationarity_floor(theta, y, coef, delta, cert.residual)
                if within_floor(cert.stationarity, floor):
                    info = {"history": history, "rho": rho, "start": name, "floor": floor}
                    status = (
                        f"certified to the floating-point floor: relative stationarity "
                        f"{cert.stationarity:.1e} is within the rounding of the residuals "
                        f"({floor:.1e})"
                    )
                    return ConstrainedOutput(coef, 0, status, cert.nu, cert.mu, info, cert)
    gram = ts.T @ ts  # the ADMM's, formed only when a start did not certify
    N = p * n
    x, z, u_x = np.zeros(N), np.zeros(N), np.zeros(N)
    s, q, u_s = np.zeros(r_ub), np.zeros(r_ub), np.zeros(r_ub)
    w, v, u_w = np.zeros((m, n)), np.zeros((m, n)), np.zeros((m, n))
    fac = _Factor(gram, rho, c, n, r_eq)
    for it in range(1, max_iter + 1):
        a_x, a_s, a_w = z - u_x, q - u_s, v - u_w
        x0 = fac.solve_m(fac.kappa * _theta_t(ts, ys - a_w) + fac.rho * a_x)
        if c.shape[0]:
            multipliers = fac.s_pinv @ (c @ x0 - np.concatenate([b_eq, b_ub - a_s]))
            x = x0 - fac.minv_ct @ multipliers
            s = a_s - multipliers[r_eq:] / fac.rho
        else:
            x = x0
        w = (ys - _theta_x(ts, x, n) + fac.rho * a_w) / (1.0 + fac.rho)
        # Over-relaxed copies: soft-thresholding, a clip, soft-thresholding.
        xh = alpha * x + (1 - alpha) * z
        sh = alpha * s + (1 - alpha) * q
        wh = alpha * w + (1 - alpha) * v
        z_old, q_old, v_old = z, q, v
        z = soft_threshold(xh + u_x, lam_s / fac.rho)
        q = np.maximum(sh + u_s, 0.0)
        v = soft_threshold(wh + u_w, ds[None, :] / fac.rho)
        u_x, u_s, u_w = u_x + xh - z, u_s + sh - q, u_w + wh - v
        if it % check_every:
            continue
        primal = np.sqrt(np.sum((x - z) ** 2) + np.sum((s - q) ** 2) + np.sum((w - v) ** 2))
        dual = fac.rho * np.sqrt(
            np.sum((z - z_old) ** 2) + np.sum((q - q_old) ** 2) + np.sum((v - v_old) ** 2)
        )
        size = max(np.sqrt(np.sum(z**2) + np.sum(v**2) + np.sum(q**2)), 1e-300)
        history.append((it, primal / size, dual / size))
        done = max(primal, dual) <= eps * size or it == max_iter
        # The polish from every new support and set of active inequalities, and at the
        # end (the polish finds the outliers itself).
        sets = (z != 0, q == 0)
        fresh = last is None or any(
            not np.array_equal(a, b) for a, b in zip(sets, last, strict=True)
        )
        last = sets
        candidates = []
        if polish and (fresh or done):
            # Far from the optimum (ADMM residuals above 1e-4) a few rounds only: the
            # polish settles there when the sets are right, and ADMM goes on when not.
            rounds = FINAL_ROUNDS if done or max(primal, dual) <= 1e-4 * size else POLISH_ROUNDS
            point, nu, mu, settled = _polish_point(
                ts, ys, ds, lam_s, c_eq, b_eq, c_ub, b_ub, z, q, rounds
            )
            if settled or done:  # an unsettled polish is not worth a certificate
                candidates.append((point, nu, mu))
        if done:
            candidates.append((z, None, None))
        for point, nu, mu in candidates:
            coef, cert = certificate(point, nu, mu)
            if best is None or cert.kkt < best[1].kkt:
                best = (coef, cert)
        if best is not None and best[1].kkt <= tol:
            status = "certified"
            break
        if done:
            status = "stopped"
            break
        # Residual balancing: keep the primal and dual residuals within 10x.
        if it % (10 * check_every) == 0 and dual > 0 and primal > 0:
            ratio = primal / dual
            if ratio > 10 or ratio < 0.1:
                factor = np.sqrt(ratio)
                u_x, u_s, u_w = u_x / factor, u_s / factor, u_w / factor
                fac = _Factor(gram, fac.rho * factor, c, n, r_eq)
    if best is None:
        best = certificate(z)
    coef, cert = best
    info = {"history": history, "rho": fac.rho}
    return ConstrainedOutput(coef, it, status, cert.nu, cert.mu, info, cert)


def _polish_point(ts, y, delta, lam_s, c_eq, b_eq, c_ub, b_ub, z, q, rounds=FINAL_ROUNDS):
    """The polish from the ADMM copy ``z`` (exactly sparse) and the inequalities whose
    slack ``q`` is zero, with its multipliers and whether it settled, or ``z``."""
    p = ts.shape[1]
    n = y.shape[1]
    lam = lam_s.reshape(p, n, order="F")
    out = _polish(ts, y, delta, lam, c_eq, b_eq, c_ub, b_ub, z.copy(), q == 0, rounds)
    return (z, None, None, False) if out is None else out
