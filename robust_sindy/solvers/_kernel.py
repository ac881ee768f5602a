"""Compiled inner loop of the Newton fast path (Numba), for the common, regular case.

:func:`newton_kernel` runs the active-set Newton iteration of
:mod:`robust_sindy.solvers.newton` one target column at a time, in compiled loops: one
pass over the rows gives the residuals, ``psi``, the gradient, the objective and the
KKT violation together, the inlier Gram matrix is updated by the rows that changed
sides (its support block factorised by Cholesky), and the step is the full Newton
step when it passes the Armijo test, else the minimiser along the direction (Newton
steps on the monotone, piecewise-linear slope of the convex piecewise-quadratic
objective; also past the full step of a damped or reweighted direction whose slope is
still negative there: on near-least-absolute-deviation pieces such a step can be orders
of magnitude too short), with the NumPy iteration's Levenberg-Marquardt rule and its
proximal-gradient step where the direction is no descent direction (the NumPy
direction's sign correction of entering terms, which keeps such directions rare on
large correlated libraries, is not compiled).  The passes over
the library are BLAS products (on one thread); the columns, independent, run side by side
on the machine's cores (:func:`robust_sindy.core.threads.map_threads`), each computed as it
would be alone.  On small problems a step costs far less than the NumPy iteration's
calls (see the design notes).  Along a ``lam`` grid (:func:`newton_path_kernel`)
each point starts from the last one's solution and reuses its last pass and its inlier
Gram matrix: a warm point no longer pays one pass and one Gram matrix before its first
step.

A column ends when its relative KKT violation (the formula of
:func:`robust_sindy.core.certificates.kkt_from_gradient`) is below ``tol / 10``, after
dropping rounding-level entries where the proximal-gradient map gives zeros if the
violation stays below ``tol``.  Where the support's inlier Gram block is numerically
singular (a Cholesky pivot below ``1e-11`` of the block's largest diagonal entry: fewer
inliers than terms), the step is the reweighted least-squares one, as in the NumPy
iteration.  It handles only what is regular: where that block is singular too (an
ill-conditioned library), where no step makes progress, where the violation has not
halved in 20 steps, or after its step budget, it stops and says so; the caller
(:func:`robust_sindy.solvers.driver.solve`) then solves that column with the
NumPy iteration from the same start, which has eigenvalue cuts, steps from the rows
and rounding-free residuals for those pieces.  Either way :func:`robust_sindy.fit`
certifies the result in the user's units: the kernel is an accelerator, the
certificate still decides.

Numba is a dependency of the package, imported on the kernel's first use
(:mod:`robust_sindy.core.compiled`); if it is not installed, :data:`AVAILABLE` is ``False``
and the NumPy iteration does all the work.  The compiled code is cached on disk, compiled
once per installation (in the background by default: see the module).
"""

from __future__ import annotations

import numpy as np

from ..core.blas import one_thread
from ..core.compiled import AVAILABLE, Kernels
from ..core.threads import map_threads
from .problem import ARMIJO, DIRECT_GRAM, DRIFT, LM, MAX_STEP, UPDATE_ROWS

__all__ = [
    "AVAILABLE",
    "KERNEL_STATUS",
    "failure_reason",
    "newton_kernel",
    "newton_path_kernel",
    "usable",
]

#: Meaning of the kernel's status per column.
KERNEL_STATUS = {
    0: "certified (relative KKT below tol / 10 without the rounding-free residuals)",
    1: "step budget exhausted, or the KKT violation did not halve in 20 steps",
    2: "singular support block, inlier and reweighted",
    3: "no descent direction (not even the proximal-gradient one)",
    4: "no progress along the direction",
}

#: Cholesky pivots below this fraction of the support block's largest diagonal entry
#: make the block singular (the NumPy iteration's eigenvalue cut is the same 1e-11).
_PIVOT_CUT = 1e-11
_SEARCHES = 60  # iterations of the line search within its bracket
STALL = 20  # steps without halving the KKT violation after which the kernel gives up
_RELAX = 0.1  # the damping's decrease after a full step (as in the NumPy iteration)


_jit = Kernels(globals())


def failure_reason() -> str | None:
    """Why the kernels cannot be compiled here, or None."""
    return _jit.broken


def usable() -> bool:
    """Whether the kernel can run (Numba installed, and no failure to compile it)."""
    return _jit.usable


@_jit
def _huber(r, delta):
    a = abs(r)
    if a <= delta:
        return 0.5 * r * r
    return delta * (a - 0.5 * delta)


@_jit
def _slope(t, r, q, x, d, lam, delta):
    """Right derivative of ``P(x + t d)`` (see ``newton.slope``), its rate of change on
    the piece at ``t`` (the squared images ``q_i^2`` of the residuals inside the
    quadratic zone: the L1 terms are piecewise constant in slope) and its rounding
    (one unit in the last place of the sum of its terms' sizes)."""
    s = 0.0
    size = 0.0
    for j in range(x.shape[0]):
        xt = x[j] + t * d[j]
        sg = np.sign(xt) if xt != 0.0 else np.sign(d[j])
        s += lam[j] * sg * d[j]
        size += abs(lam[j] * d[j])
    c = 0.0
    for i in range(r.shape[0]):
        v = r[i] - t * q[i]
        if v > delta:
            v = delta
        elif v < -delta:
            v = -delta
        else:
            c += q[i] * q[i]
        s -= v * q[i]
        size += abs(v * q[i])
    return s, c, np.finfo(np.float64).eps * size


@_jit
def _kink(x, d, a, b):
    """The coefficient whose zero crossing ``t = -x_j / d_j`` lies strictly between ``a``
    and ``b`` and nearest to ``a`` (-1 if none), and that ``t``."""
    best, at = -1, np.nan
    for j in range(x.shape[0]):
        if x[j] == 0.0 or d[j] == 0.0 or (x[j] > 0.0) == (d[j] > 0.0):
            continue
        t = -x[j] / d[j]
        if min(a, b) < t < max(a, b) and (best < 0 or abs(t - a) < abs(at - a)):
            best, at = j, t
    return best, at


@_jit
def _line_search(r, q, x, d, lam, delta, slope0, slope1):
    """Minimiser of the convex piecewise-quadratic ``P(x + t d)``, ``t > 0``, from its
    slope at 0 (``< 0``) and at 1 (NaN: not yet computed): a bracket by doubling from
    ``t = 1``, then, inside it, Newton steps on the slope, which is piecewise linear and
    nondecreasing (a step from a point of the minimiser's piece lands on it), stopped at
    the first coefficient's zero crossing on their way (where the slope jumps: the
    minimiser when the jump spans zero), and the Illinois variant of regula falsi for a
    step that leaves the bracket.  A point whose slope is within its rounding is the
    minimiser."""
    lo, s_lo = 0.0, slope0
    hi = 1.0
    c_hi = np.nan
    if np.isnan(slope1):
        s_hi, c_hi, noise = _slope(hi, r, q, x, d, lam, delta)
        if abs(s_hi) <= noise:
            return hi
    else:
        s_hi = slope1
    while s_hi < 0.0 and hi < MAX_STEP:
        lo, s_lo = hi, s_hi
        hi *= 2.0
        s_hi, c_hi, noise = _slope(hi, r, q, x, d, lam, delta)
        if abs(s_hi) <= noise:
            return hi
    if s_hi < 0.0:
        return hi
    t_last, s_last, c_last = hi, s_hi, c_hi  # the last point evaluated
    side = 0
    for _ in range(_SEARCHES):
        t = np.nan
        if c_last > 0.0:
            t = t_last - s_last / c_last
        if lo < t < hi:
            side = 0
        else:
            if s_hi - s_lo > 0.0:
                t = lo - s_lo * (hi - lo) / (s_hi - s_lo)
            else:
                t = 0.5 * (lo + hi)
            if not (lo < t < hi):
                t = 0.5 * (lo + hi)
                if not (lo < t < hi):
                    break
        j, tz = _kink(x, d, t_last, t)
        if j >= 0 and lo < tz < hi:
            # The slope on both sides of the crossing, whatever sign rounding gives
            # x_j + t d_j there.
            st, ct, noise = _slope(tz, r, q, x, d, lam, delta)
            xt = x[j] + tz * d[j]
            used = lam[j] * (np.sign(xt) if xt != 0.0 else np.sign(d[j])) * d[j]
            right = st - used + lam[j] * abs(d[j])
            left = st - used - lam[j] * abs(d[j])
            if left <= noise and -noise <= right:
                return tz
            if right < 0.0:
                lo, s_lo, st = tz, right, right
            else:
                hi, s_hi, st = tz, left, left
            side = 0
            t_last, s_last, c_last = tz, st, ct
            continue
        st, ct, noise = _slope(t, r, q, x, d, lam, delta)
        if abs(st) <= noise:
            return t
        if st < 0.0:
            lo, s_lo = t, st
            if side == -1:
                s_hi *= 0.5
            side = -1
        else:
            hi, s_hi = t, st
            if side == 1:
                s_lo *= 0.5
            side = 1
        t_last, s_last, c_last = t, st, ct
        if hi - lo <= 1e-15 * hi:
            break
    return hi if s_hi == 0.0 else 0.5 * (lo + hi)


@_jit
def _row_gram(theta, scale, rows, weights):
    """``sum_a weights[a] A_i^T A_i`` over the rows ``i = rows[a]`` of ``A = theta / scale``
    (gathered, then one BLAS product)."""
    p = theta.shape[1]
    k = rows.shape[0]
    B = np.empty((k, p))
    W = np.empty((k, p))
    for a in range(k):
        i = rows[a]
        for j in range(p):
            v = theta[i, j] / scale[j]
            B[a, j] = v
            W[a, j] = weights[a] * v
    if k == 0:
        return np.zeros((p, p))
    return np.dot(W.T, B)


@_jit
def _fresh_gram(theta, scale, G, inl, M):
    """``M = A^T diag(inl) A``: from ``G`` minus the outliers while they are a minority
    carrying at most half of every column's norm, else from the inliers directly."""
    m, p = theta.shape
    outliers = np.flatnonzero(~inl)
    if 2 * outliers.shape[0] <= m:
        M[:, :] = G - _row_gram(theta, scale, outliers, np.ones(outliers.shape[0]))
        ok = True
        for j in range(p):
            if M[j, j] <= (1.0 - DIRECT_GRAM) * G[j, j]:
                ok = False
        if ok:
            return
    inliers = np.flatnonzero(inl)
    M[:, :] = _row_gram(theta, scale, inliers, np.ones(inliers.shape[0]))


@_jit
def _support_step(M, g, lam, sigma, sup, x, mu, d):
    """The Newton direction ``d`` (p,) on the support ``sup`` from the Gram matrix ``M``:
    ``(M_SS + mu I) d_S = g_S - lam_S sigma_S + M_SSbar x_Sbar``, ``d_Sbar = -x_Sbar``,
    by Cholesky; returns whether the block is numerically singular (then ``d`` is not
    set)."""
    p = x.shape[0]
    idx = np.flatnonzero(sup)
    s_n = idx.shape[0]
    B = np.empty((s_n, s_n))
    b = np.empty(s_n)
    top = 0.0
    for a_ in range(s_n):
        ja = idx[a_]
        rhs = g[ja] - lam[ja] * sigma[ja]
        for jb in range(p):
            if not sup[jb]:
                rhs += M[ja, jb] * x[jb]
        b[a_] = rhs
        for c_ in range(s_n):
            B[a_, c_] = M[ja, idx[c_]]
        top = max(top, B[a_, a_])
        B[a_, a_] += mu
    if s_n > 0 and not top > 0.0:
        return True
    for j in range(s_n):
        v = B[j, j]
        for k in range(j):
            v -= B[j, k] * B[j, k]
        if v <= _PIVOT_CUT * top:
            return True
        piv = np.sqrt(v)
        B[j, j] = piv
        for i in range(j + 1, s_n):
            w = B[i, j]
            for k in range(j):
                w -= B[i, k] * B[j, k]
            B[i, j] = w / piv
    for i in range(s_n):
        v = b[i]
        for k in range(i):
            v -= B[i, k] * b[k]
        b[i] = v / B[i, i]
    for i in range(s_n - 1, -1, -1):
        v = b[i]
        for k in range(i + 1, s_n):
            v -= B[k, i] * b[k]
        b[i] = v / B[i, i]
    for j in range(p):
        d[j] = -x[j]
    for a_ in range(s_n):
        d[idx[a_]] = b[a_]
    return False


@_jit
def _losses(theta, scale, y, delta, x, r, psi, g, inl, xs):
    """One pass at ``x``: residuals ``r``, ``psi``, the gradient ``g`` and the inliers;
    returns the Huber loss and ``||psi||`` (everything that does not depend on ``lam``)."""
    m, p = theta.shape
    for j in range(p):
        xs[j] = x[j] / scale[j]
    r[:] = y - np.dot(theta, xs)  # one BLAS product per pass
    loss = 0.0
    psi2 = 0.0
    for i in range(m):
        ri = r[i]
        if ri > delta:
            ps = delta
        elif ri < -delta:
            ps = -delta
        else:
            ps = ri
        inl[i] = abs(ri) <= delta
        loss += _huber(ri, delta)
        psi2 += ps * ps
        psi[i] = ps
    g[:] = np.dot(theta.T, psi)
    for j in range(p):
        g[j] /= scale[j]
    return loss, np.sqrt(psi2)


@_jit
def _stationarity(lam, x, g, norms, loss, psi_norm, sup, sigma):
    """From one pass's ``g``, loss and ``||psi||``: the objective at ``lam`` and the
    relative KKT violation (as ``robust_sindy.core.certificates.kkt_from_gradient``), and
    the proximal-gradient support ``sup`` with its signs ``sigma``."""
    p = x.shape[0]
    obj = loss
    for j in range(p):
        obj += lam[j] * abs(x[j])
    viol = 0.0
    for j in range(p):
        nrm = norms[j]
        t_g = g[j] / nrm / nrm
        t_l = lam[j] / nrm / nrm
        u = x[j] + t_g
        if u > t_l:
            st = abs(g[j] - lam[j])
        elif u < -t_l:
            st = abs(g[j] + lam[j])
        else:
            st = abs(x[j]) * nrm * nrm
        sc = max(lam[j], nrm * psi_norm)
        if sc > 0:
            rel = st / sc
        elif st > 0:
            rel = np.inf
        else:
            rel = 0.0
        if not rel <= viol:  # NaN counts as a violation
            viol = rel if rel == rel else np.inf
        sup[j] = (abs(u) > t_l) or (lam[j] == 0.0)
        sigma[j] = 0.0 if lam[j] == 0.0 else np.sign(u)
    return obj, viol


@_jit
def _trial(theta, scale, r, x, d, lam, delta, xs, q):
    """One pass along the direction ``d``: its image ``q = A d`` (into ``q``), the
    objective's slope at ``x`` along ``d`` and the objective at the full step ``x + d``
    (``r`` the residuals at ``x``, ``xs`` a work array)."""
    m, p = theta.shape
    for j in range(p):
        xs[j] = d[j] / scale[j]
    q[:] = np.dot(theta, xs)
    slope0 = 0.0
    full = 0.0
    for i in range(m):
        s = q[i]
        ri = r[i]
        ps = delta if ri > delta else (-delta if ri < -delta else ri)
        slope0 -= ps * s
        full += _huber(ri - s, delta)
    for j in range(p):
        sg = np.sign(x[j]) if x[j] != 0.0 else np.sign(d[j])
        slope0 += lam[j] * sg * d[j]
        full += lam[j] * abs(x[j] + d[j])
    return slope0, full


@_jit
def _iterate(theta, scale, G, y, delta, lam, x, norms, lipschitz, tol, max_steps, work, carry):
    """Newton iteration for one column at one ``lam``, in place on ``x``; returns
    (status, steps, passes).

    ``work`` holds the column's work arrays (:func:`_work`): residuals, ``psi``,
    gradient and inliers of the last pass, and the inlier Gram matrix ``M`` with the
    inlier set it was formed for.  ``carry`` is ``[Gram formed, pass valid, loss,
    ||psi||]``: on a path the next point starts from this point's solution, whose last
    pass (residuals, gradient, inliers) and Gram matrix it reuses; a pass is valid when
    it was taken at the ``x`` the iteration starts from (only the objective and the
    KKT violation depend on ``lam``).
    """
    r, q, psi, weights, g, xs, d, xd, drift, sigma, inl, old, sup, M, rows = work
    m, p = theta.shape
    passes = 0
    status = 1
    step = 0
    mu = 0.0
    tiny = np.finfo(np.float64).tiny
    ref_viol, ref_step = np.inf, 0
    for step in range(max_steps + 1):
        if step > 0 or carry[1] == 0.0:
            carry[2], carry[3] = _losses(theta, scale, y, delta, x, r, psi, g, inl, xs)
            carry[1] = 1.0
            passes += 1
        obj, viol = _stationarity(lam, x, g, norms, carry[2], carry[3], sup, sigma)
        if viol <= 0.1 * tol:
            status = 0
            # A partial step leaves rounding-level entries where the optimum has exact
            # zeros: drop those the proximal-gradient map sets to zero if the
            # certificate still holds.
            drop = False
            for j in range(p):
                xd[j] = x[j]
                if x[j] != 0.0 and not sup[j]:
                    xd[j] = 0.0
                    drop = True
            if drop:
                carry[2], carry[3] = _losses(theta, scale, y, delta, xd, r, psi, g, inl, xs)
                _, viol2 = _stationarity(lam, xd, g, norms, carry[2], carry[3], sup, sigma)
                passes += 1
                if viol2 <= tol:
                    x[:] = xd
                else:
                    carry[1] = 0.0  # the last pass was at the rejected point
            break
        if viol < 0.5 * ref_viol:
            ref_viol, ref_step = viol, step
        if step == max_steps or step - ref_step >= STALL:
            status = 1  # the budget, or no halving of the violation in STALL steps
            break
        # Inlier Gram matrix: updated by the rows that changed sides, else afresh.
        updated = False
        if carry[0] != 0.0:
            n_changed = 0
            for i in range(m):
                if inl[i] != old[i]:
                    n_changed += 1
            if n_changed <= UPDATE_ROWS * m:
                changed = np.flatnonzero(inl != old)
                sign = np.empty(changed.shape[0])
                for a in range(changed.shape[0]):
                    i = changed[a]
                    sign[a] = 1.0 if inl[i] else -1.0
                    for j in range(p):
                        v = theta[i, j] / scale[j]
                        drift[j] += v * v
                M += _row_gram(theta, scale, changed, sign)
                updated = True
                for j in range(p):
                    if drift[j] > DRIFT * M[j, j]:
                        updated = False
        if not updated:
            _fresh_gram(theta, scale, G, inl, M)
            drift[:] = 0.0
            carry[0] = 1.0
        old[:] = inl
        reweighted = False
        if _support_step(M, g, lam, sigma, sup, x, mu, d):
            # Too few inliers to fix the support's coefficients: the reweighted
            # least-squares step, whose quadratic model majorises the Huber loss.
            for i in range(m):
                weights[i] = min(1.0, delta / max(abs(r[i]), tiny))
            if _support_step(_row_gram(theta, scale, rows, weights), g, lam, sigma, sup, x, mu, d):
                status = 2
                break
            reweighted = True
        slope0, full = _trial(theta, scale, r, x, d, lam, delta, xs, q)
        passes += 1
        if not slope0 < 0.0:
            # No descent direction: the proximal-gradient step instead (one always is,
            # unless x is optimal).
            for j in range(p):
                v = x[j] + g[j] / lipschitz
                thr = lam[j] / lipschitz
                d[j] = (max(abs(v) - thr, 0.0) * np.sign(v)) - x[j]
            slope0, full = _trial(theta, scale, r, x, d, lam, delta, xs, q)
            passes += 1
            if not slope0 < 0.0:
                status = 3
                break
        if full <= obj + ARMIJO * slope0:
            t = 1.0
            if mu > 0.0 or reweighted:
                slope1, _, rounding = _slope(1.0, r, q, x, d, lam, delta)
                if slope1 < -rounding:
                    # A damped or reweighted step can stop short of the minimum along
                    # its direction (by orders of magnitude where few samples lie
                    # inside delta): the line search goes on past it.
                    t = _line_search(r, q, x, d, lam, delta, slope0, slope1)
        else:
            t = _line_search(r, q, x, d, lam, delta, slope0, np.nan)
            if not t > 0.0:
                status = 4
                break
        # Damping after a step the objective did not accept in full, relaxed after full
        # (or longer) steps (the rule of the NumPy iteration).
        mu = _RELAX * mu if t >= 1.0 else max(10.0 * mu, LM * viol)
        if mu < 1e-12:
            mu = 0.0
        for j in range(p):
            x[j] += t * d[j]
    return status, step, passes


@_jit
def _work(m, p):
    """Work arrays of one column (see :func:`_iterate`)."""
    return (
        np.empty(m),  # r
        np.empty(m),  # q
        np.empty(m),  # psi
        np.empty(m),  # weights
        np.empty(p),  # g
        np.empty(p),  # xs
        np.empty(p),  # d
        np.empty(p),  # xd
        np.zeros(p),  # drift
        np.zeros(p),  # sigma
        np.zeros(m, dtype=np.bool_),  # inl
        np.zeros(m, dtype=np.bool_),  # old
        np.zeros(p, dtype=np.bool_),  # sup
        np.empty((p, p)),  # M
        np.arange(m),  # rows
    )


@_jit
def _column(theta, scale, G, y, delta, lam, x, norms, lipschitz, tol, max_steps):
    """Newton iteration for one column, in place on ``x``; returns (status, steps, passes)."""
    m, p = theta.shape
    carry = np.zeros(4)
    return _iterate(
        theta, scale, G, y, delta, lam, x, norms, lipschitz, tol, max_steps, _work(m, p), carry
    )


@_jit
def _columns(theta, scale, G, yt, delta, lamt, xt, norms, lipschitz, tol, max_steps, status, steps):
    """Every column in turn; ``yt`` (k, m), ``lamt`` and ``xt`` (k, p): one row each."""
    passes = 0
    for c in range(yt.shape[0]):
        xc = xt[c].copy()
        st, sp, ps = _column(
            theta, scale, G, yt[c], delta[c], lamt[c], xc, norms, lipschitz, tol, max_steps
        )
        xt[c] = xc
        status[c] = st
        steps[c] = sp
        passes += ps
    return passes


@_jit
def _path_columns(
    theta, scale, G, yt, delta, lamt, xt, norms, lipschitz, tol, max_steps, first, status, steps,
    stop, out,
):  # fmt: skip
    """Every column in turn along its ``lam`` grid: ``lamt`` (k, L, p), ``xt`` (k, p) the
    starts at the points ``first`` (k,); the solutions go to ``out`` (k, L, p) until a
    point the iteration cannot certify (its index in ``stop``, else L)."""
    m, p = theta.shape
    L = lamt.shape[1]
    passes = 0
    for c in range(yt.shape[0]):
        x = xt[c].copy()
        work = _work(m, p)
        carry = np.zeros(4)
        stop[c] = L
        for i in range(first[c], L):
            st, sp, ps = _iterate(
                theta, scale, G, yt[c], delta[c], lamt[c, i], x, norms, lipschitz, tol,
                max_steps, work, carry,
            )  # fmt: skip
            passes += ps
            status[c, i] = st
            steps[c, i] = sp
            if st != 0:
                stop[c] = i
                break
            out[c, i] = x
    return passes


def _problem(theta, scale, G, y, delta):
    """The kernels' problem arrays: the library, its scales and Gram matrix, the targets
    as rows and the thresholds, all C-contiguous (one compiled specialisation for any
    number of columns)."""
    return (
        np.asarray(theta, dtype=float),
        np.ascontiguousarray(scale, dtype=float),
        np.ascontiguousarray(G, dtype=float),
        np.ascontiguousarray(np.asarray(y, dtype=float).T),
        np.ascontiguousarray(delta, dtype=float),
    )


def _settings(norms, lipschitz, tol, max_steps):
    """The kernels' column norms, proximal-gradient constant, tolerance and step budget."""
    return np.ascontiguousarray(norms, dtype=float), float(lipschitz), float(tol), int(max_steps)


def newton_kernel(theta, scale, G, y, delta, lam, x, norms, lipschitz, tol, max_steps):
    """Run the compiled Newton iteration on every column of ``y`` (m, k) from ``x`` (p, k).

    ``theta`` (m, p) C-contiguous and ``scale`` (p,) define ``A = theta / scale``;
    ``G = A^T A``; ``lam`` (p, k), ``delta`` (k,) and ``x`` are in the units of ``A``;
    ``norms`` are ``A``'s column norms and ``lipschitz`` the largest eigenvalue of ``G``
    (the proximal-gradient step where the Newton direction is no descent direction).
    Returns ``(x, status, steps, passes)`` with the status codes of
    :data:`KERNEL_STATUS` (``x`` a new array), or ``None`` where the kernel cannot be
    compiled (:meth:`robust_sindy.core.compiled.Kernels.run`).
    """
    k = y.shape[1]
    status = np.zeros(k, dtype=np.int64)
    steps = np.zeros(k, dtype=np.int64)
    # Every array C-contiguous (the columns as rows), whatever the number of columns:
    # every call uses the one compiled specialisation.
    xt = np.ascontiguousarray(np.asarray(x, dtype=float).T)
    theta, scale, G, yt, delta = _problem(theta, scale, G, y, delta)
    lamt = np.ascontiguousarray(np.asarray(lam, dtype=float).T)
    settings = _settings(norms, lipschitz, tol, max_steps)

    def run(c):  # one column (a row of each array: a C-contiguous view)
        s = slice(c, c + 1)
        return _jit.run(
            "_columns", theta, scale, G, yt[s], delta[s], lamt[s], xt[s], *settings,
            status[s], steps[s],
        )  # fmt: skip

    with one_thread():  # small products: BLAS threads cost more than they save
        passes = map_threads(run, range(k))
    if any(p is None for p in passes):
        return None
    return xt.T.copy(), status, steps, int(sum(passes))


def newton_path_kernel(theta, scale, G, y, delta, lam, x, first, norms, lipschitz, tol, max_steps):
    """Run the compiled Newton iteration along a ``lam`` grid, each point warm-started
    from the last one's solution, its last pass and its inlier Gram matrix.

    ``lam`` is (L, p, k), ``x`` (p, k) the starts at the points ``first`` (k,); the other
    arguments as :func:`newton_kernel`.  Returns ``(X, status, steps, stop, passes)``:
    ``X`` (L, p, k) the solutions, certified at the points ``first[c] <= i < stop[c]``
    of column ``c``; ``status`` and ``steps`` (L, k) where the iteration ran (the status
    at ``stop`` is why that point was not certified); or ``None`` where the kernel
    cannot be compiled.
    """
    L, _, k = lam.shape
    p = x.shape[0]
    status = np.zeros((k, L), dtype=np.int64)
    steps = np.zeros((k, L), dtype=np.int64)
    stop = np.zeros(k, dtype=np.int64)
    out = np.zeros((k, L, p))
    theta, scale, G, yt, delta = _problem(theta, scale, G, y, delta)
    lamt = np.ascontiguousarray(np.transpose(np.asarray(lam, dtype=float), (2, 0, 1)))
    xt = np.ascontiguousarray(np.asarray(x, dtype=float).T)
    settings = _settings(norms, lipschitz, tol, max_steps)
    first = np.ascontiguousarray(first, dtype=np.int64)

    def run(c):  # one column (a row of each array: a C-contiguous view)
        s = slice(c, c + 1)
        return _jit.run(
            "_path_columns", theta, scale, G, yt[s], delta[s], lamt[s], xt[s], *settings,
            first[s], status[s], steps[s], stop[s], out[s],
        )  # fmt: skip

    with one_thread():  # small products: BLAS threads cost more than they save
        passes = map_threads(run, range(k))
    if any(p is None for p in passes):
        return None
    return (
        np.transpose(out, (1, 2, 0)).copy(), status.T.copy(), steps.T.copy(), stop,
        int(sum(passes)),
    )  # fmt: skip
