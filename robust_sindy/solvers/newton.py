"""Batched active-set (semismooth) Newton: the first solver of the fast path.

For every target column ``y`` (all columns are solved together) it solves

.. math::

    \\min_{\\xi}\\; \\sum_i H_\\delta(y_i - \\theta_i \\xi) + \\sum_j \\lambda_j |\\xi_j| .

The objective is piecewise quadratic.  At the current point take, per column, the
support ``S = {|xi + T g| > T lam}`` and its signs ``sigma`` (the proximal-gradient
fixed point, ``g = Theta^T psi_delta(r)``, ``T = diag(1 / ||Theta_j||^2)``) and the
outliers ``O = {|r_i| > delta}``.  On that piece the objective is a quadratic whose
Hessian on ``S`` is the inlier Gram matrix, formed from the full Gram matrix
``G = Theta^T Theta`` (computed once) minus the outlier rows,

.. math::

    M = G_{SS} - \\Theta_{OS}^T \\Theta_{OS}, \\qquad
    M\\, d_S = g_S - \\lambda_S \\sigma_S + M_{S\\bar S}\\, \\xi_{\\bar S}, \\quad
    d_{\\bar S} = -\\xi_{\\bar S},

a ``|S| x |S|`` system per column, independent of the number of samples once the
outliers are the minority.  ``M`` is only ever formed on the column's working set
(the support and the other nonzero coefficients, :func:`working_sets`), never on the
whole library: a step of a sparse model costs its support, and a library of thousands
of terms needs no ``p x p`` matrix per column.  From one step to the next only a few
samples change sides, and ``M`` is updated by those rows, bordered by the terms that
joined the working set (:class:`GramCache`; formed afresh when many change or the
updates' rounding could matter).  A term at zero that enters ``S`` with the sign
opposite to its step is kept at zero and the system solved again: on a warm-started
path many correlated terms enter at once, and the joint step would otherwise be no
descent direction.  The step is in correction form: its right-hand side is the
gradient, computed from residuals ``y - Theta xi`` evaluated afresh at every step, so
each step also refines the previous one and an exact fit keeps residuals at rounding
level although the systems are normal equations.  When the inliers do not determine
``xi_S`` (fewer inliers than terms, a least-absolute-deviation-like piece) the step is
the iteratively-reweighted least-squares one (weights ``min(1, delta / |r_i|)``, a
quadratic majoriser of the Huber loss).  Where a Gram system is numerically singular
(an eigenvalue below ``1e-11`` of the largest), the step is recomputed from the
weighted rows by a singular value decomposition (:func:`row_direction`), whose
condition number is the square root of the Gram matrix's: in an ill-conditioned library
the cut would drop the directions along which the optimum still moves.  Every step is
safeguarded: the full step if it decreases the objective enough (Armijo), else the
exact minimiser along the direction (:func:`line_search`), and a proximal-gradient step
when the Newton direction is no descent direction.  A column ends when its relative KKT
violation (:mod:`robust_sindy.core.certificates`) is below ``tol``: the certificate decides,
not the factorisation.  The driver (:mod:`robust_sindy.solvers.driver`) hands the
columns it cannot certify within its step budget to the ADMM, warm-started from the
Newton point.

One step costs three passes over ``Theta`` for all columns together (residual,
gradient, the direction's image), ``|changed| w^2`` for the Gram update on a working
set of ``w`` terms (``|O| w^2`` when formed afresh) and a ``|S|``-sized factorisation
per column (Cholesky with a condition estimate from :data:`CHOLESKY_SIZE` terms, an
eigen-decomposition below or where the estimate comes near the cut); where that needs
a cut, a singular value decomposition of the weighted rows on the support
(``|rows| |S|^2``).

On small problems the driver runs a compiled twin of this iteration first
(:mod:`robust_sindy.solvers._kernel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from ..core.certificates import (
    column_norms,
    gather,
    kkt_from_gradient,
    rounding_floor,
    rounding_free,
    within_floor,
)
from ..core.losses import huber_psi, soft_threshold
from ..core.threads import map_threads
from .problem import (
    ARMIJO,
    DIRECT_GRAM,
    DRIFT,
    EIG_CUT,
    LM,
    MAX_STEP,
    UPDATE_ROWS,
    Prepared,
    column_objective,
)

__all__ = [
    "GramCache",
    "NewtonRun",
    "conditioned_cholesky",
    "line_search",
    "newton",
    "row_direction",
]


#: A column has stalled when its KKT violation has not halved for this many steps while
#: its objective changed by at most ``_STALL_OBJ`` relative: the floating-point floor.
#: A column already certified (KKT below ``tol``) that is only seeking the margin below
#: it stops after ``_CERTIFIED_STEPS`` steps without halving its violation.
_STALL_STEPS, _STALL_OBJ, _CERTIFIED_STEPS = 5, 1e-12, 2


# ---------------------------------------------------------------------------------------
# the line search (one column)


def slope(t, r, q, x, d, lam, delta):
    """Right derivative of ``phi(t) = P(x + t d)``; ``r = y - A x``, ``q = A d``.

    ``phi`` is convex and piecewise quadratic, so its derivative is nondecreasing.
    """
    xt = x + t * d
    s = np.where(xt != 0, np.sign(xt), np.sign(d))
    return (lam * s) @ d - huber_psi(r - t * q, delta) @ q


def line_search(r, q, x, d, lam, delta, upper: float | None = None) -> float:
    """Exact minimiser of the convex piecewise-quadratic ``phi(t)`` over ``t >= 0``.

    ``phi'(t) = a + b t`` between breakpoints (a residual entering or leaving the
    quadratic zone of the Huber loss, a coordinate crossing zero); the breakpoints are
    sorted once and the slope is accumulated segment by segment, so the minimiser is
    exact (0 if ``d`` is no descent direction, at most ``2**20``).  ``upper``, a step
    at which the slope is known to be ``>= 0``, bounds the search: only the breakpoints
    before it are sorted.
    """
    if slope(0.0, r, q, x, d, lam, delta) >= 0:
        return 0.0
    moving = q != 0
    rq, qq = r[moving], q[moving]
    absq = np.abs(qq)
    t_a = (rq - delta) / qq  # residual crosses +delta
    t_b = (rq + delta) / qq  # residual crosses -delta
    lo, hi = np.minimum(t_a, t_b), np.maximum(t_a, t_b)
    # Where delta is below the resolution of the residual the quadratic zone has no
    # width in floating point: the residual crosses it as a kink (slope jump 2 |q| delta),
    # and its huge cancelling quadratic terms must not enter the sums.
    kink = hi - lo <= 8 * np.finfo(float).eps * np.maximum(np.abs(lo), np.abs(hi))
    hi = np.where(kink, lo, hi)
    before = (-absq * delta, np.zeros_like(qq))
    quad = (np.where(kink, 0.0, -qq * rq), np.where(kink, 0.0, qq * qq))
    after = (absq * delta, np.zeros_like(qq))
    # A residual exactly at +-delta has slope continuous there, so "<= 0" is harmless.
    zone_quad = (lo <= 0) & (hi > 0)
    zone_after = hi <= 0
    a0 = np.where(zone_after, after[0], np.where(zone_quad, quad[0], before[0])).sum()
    b0 = np.where(zone_quad, quad[1], 0.0).sum()
    s0 = np.where(x != 0, np.sign(x), np.sign(d))
    a0 += (lam * s0) @ d
    smooth = ~kink
    ev_t = [lo[(lo > 0) & smooth], hi[hi > 0]]
    ev_a = [
        (quad[0] - before[0])[(lo > 0) & smooth],
        np.where(kink, after[0] - before[0], after[0] - quad[0])[hi > 0],
    ]
    ev_b = [(quad[1] - before[1])[(lo > 0) & smooth], (after[1] - quad[1])[hi > 0]]
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = np.where(d != 0, -x / d, -1.0)
    cross = tz > 0
    ev_t.append(tz[cross])
    ev_a.append((lam * np.abs(d) - lam * s0 * d)[cross])
    ev_b.append(np.zeros(int(cross.sum())))
    t_ev, e_a, e_b = np.concatenate(ev_t), np.concatenate(ev_a), np.concatenate(ev_b)
    last = np.inf
    if upper is not None:
        before_upper = t_ev <= upper
        t_ev, e_a, e_b, last = t_ev[before_upper], e_a[before_upper], e_b[before_upper], upper
    order = np.argsort(t_ev, kind="stable")
    t_ev = t_ev[order]
    ca = a0 + np.concatenate([[0.0], np.cumsum(e_a[order])])
    cb = b0 + np.concatenate([[0.0], np.cumsum(e_b[order])])
    starts = np.concatenate([[0.0], t_ev])
    ends = np.concatenate([t_ev, [last]])
    with np.errstate(invalid="ignore"):
        end_slope = np.where(np.isfinite(ends), ca + cb * ends, np.where(cb > 0, np.inf, ca))
    hit = np.flatnonzero(end_slope >= 0)
    if hit.size == 0:
        # Without a bound: the slope stays negative (the longest step); with one, the
        # accumulated slope fell short of its known sign at ``upper`` by rounding.
        return MAX_STEP if upper is None else float(upper)
    k = hit[0]
    if ca[k] + cb[k] * starts[k] >= 0 or cb[k] <= 0:
        t = starts[k]
    else:
        t = -ca[k] / cb[k]
    return float(min(max(t, 0.0), MAX_STEP))


# ---------------------------------------------------------------------------------------
# one batched Newton step


def working_sets(S: np.ndarray, x: np.ndarray):
    """Per column, the terms whose inlier Gram entries a Newton step reads: the support
    ``S`` (its block is solved) then the other nonzero coefficients (their columns of
    the Gram matrix multiply them on the right-hand side).

    Returns ``idx`` (k, w), each column's terms first (the support in order, then the
    others) padded with the rest, and the sizes ``n_s``, ``n_w`` (k,) of the support and
    of the whole set.  A step costs the working sets' sizes, not the library's.
    """
    other = (x != 0) & ~S
    key = np.where(S, 0, np.where(other, 1, 2)).T
    n_s, n_w = S.sum(axis=0), S.sum(axis=0) + other.sum(axis=0)
    w = max(int(n_w.max(initial=0)), 1)
    return np.argsort(key, axis=1, kind="stable")[:, :w], n_s, n_w


def inlier_gram(A, G: np.ndarray, w: np.ndarray, idx=None, sizes=None) -> np.ndarray:
    """``M_k = A_J^T diag(w_k) A_J`` for every column ``k`` of the row weights ``w``
    (m, k), each in ``[0, 1]``, on the terms ``J = idx[k, :sizes[k]]`` (default: every
    term); entries beyond ``sizes[k]`` are zero.

    Formed as ``G_JJ`` minus the rows with ``w < 1`` while those are few and carry little
    of any column's norm; from the rows with ``w > 0`` directly otherwise (no
    cancellation when most of the Gram matrix sits in the down-weighted rows, and
    weights as small as 1e-300 keep their value).
    """
    k_all = w.shape[1]
    if idx is None:
        idx, sizes = _every_term(k_all, A.shape[1])
    s = idx.shape[1]
    M = np.zeros((k_all, s, s))

    def column(k):  # one BLAS product per target column, side by side
        J = idx[k, : sizes[k]]
        M[k, : J.size, : J.size] = _weighted_gram(A, G, w[:, k], J, J.size)

    map_threads(column, range(k_all), flops=A.shape[0] * s * s / 2)
    return M


def _every_term(k: int, p: int):
    """``idx`` and ``sizes`` of :func:`inlier_gram` for ``k`` columns on all ``p`` terms."""
    return np.tile(np.arange(p), (k, 1)), np.full(k, p)


def _weighted_gram(A, G, w, R, tail: int) -> np.ndarray:
    """``A_R^T diag(w) A_N`` for the row weights ``w`` (m,) in ``[0, 1]`` and the last
    ``tail`` terms ``N`` of ``R``: ``G_RN`` minus the rows with ``w < 1`` while those are
    few and carry little of the norms of ``N``'s columns, else from the rows with
    ``w > 0`` directly (see :func:`inlier_gram`)."""
    first = R.size - tail
    N = R[first:]
    down = np.flatnonzero(w < 1.0)
    if 2 * down.size <= A.shape[0]:
        AR = gather(A, down, R)
        B = G[np.ix_(R, N)] - (AR * (1.0 - w[down, None])).T @ AR[:, first:]
        ratio = np.diag(B[first:]) / np.maximum(np.diag(G)[N], np.finfo(float).tiny)
        if np.min(ratio, initial=1.0) > 1.0 - DIRECT_GRAM:
            return B
    keep = np.flatnonzero(w > 0.0)
    AR = gather(A, keep, R)
    return (AR * w[keep, None]).T @ AR[:, first:]


class GramCache:
    """The inlier Gram matrix of each column's recent Newton steps on their working
    sets, with its inlier set.

    A step whose inlier set differs from the last one in a few samples updates that
    matrix by those rows (``M + A_in^T A_in - A_out^T A_out``, ``|changed| w^2``)
    instead of forming it from the outliers or the inliers (``|O| w^2`` or
    ``|I| w^2``), after bordering it with the terms that joined the working set
    (``|O| w |new|``); :data:`DRIFT` bounds the rounding the updates may accumulate.
    With a ``budget`` (entries of the stored matrices), the matrices used longest ago
    are let go once the stored ones exceed it (a cache that outlives one Newton run,
    :func:`~.problem.shared_preparation`, keeps about the library's own size, as the
    driver's groups of columns do).
    """

    def __init__(self, budget: int | None = None):
        self.entries: dict = {}
        self.updates = 0
        self.fresh = 0
        self.budget = budget

    def gram(self, A, G, inlier: np.ndarray, ids, idx=None, sizes=None) -> np.ndarray:
        """``A_J^T diag(inlier_k) A_J`` for every column ``k`` of the boolean ``inlier``
        (m, k) on its terms ``J`` (``idx``, ``sizes`` as in :func:`inlier_gram`); ``ids``
        name the columns across calls."""
        m, p = A.shape
        k_all = inlier.shape[1]
        if idx is None:
            idx, sizes = _every_term(k_all, p)
        s = idx.shape[1]
        M = np.zeros((k_all, s, s))

        def column(c):  # True where updated: each column its own entry, side by side
            key = ids[c]
            entry = self.entries.get(key)
            if entry is None:
                return False
            J = idx[c, : sizes[c]]
            old, J0, M0, drift = entry
            changed = np.flatnonzero(inlier[:, c] != old)
            where = np.full(p, -1)
            where[J0] = np.arange(J0.size)
            new = J[where[J] < 0]
            # A working set much smaller than the stored one is formed afresh.
            if changed.size > UPDATE_ROWS * m or J0.size + new.size > 2 * J.size:
                return False
            if new.size:
                J0, M0, drift = _border(A, G, old, J0, M0, drift, new)
                where = np.full(p, -1)
                where[J0] = np.arange(J0.size)
            at = where[J]
            rows = gather(A, changed, J0)
            sign = np.where(inlier[changed, c], 1.0, -1.0)
            M1 = M0 + (rows * sign[:, None]).T @ rows
            d1 = drift + np.einsum("ij,ij->j", rows, rows)
            if not np.all(d1 <= DRIFT * np.diag(M1)):
                return False
            M[c, : J.size, : J.size] = M1[np.ix_(at, at)]
            self.entries[key] = (inlier[:, c].copy(), J0, M1, d1)
            return True

        updated = map_threads(column, range(k_all), flops=UPDATE_ROWS * m * s * s)
        fresh = [c for c, done in enumerate(updated) if not done]
        self.updates += k_all - len(fresh)
        if fresh:
            M[fresh] = inlier_gram(A, G, inlier[:, fresh].astype(float), idx[fresh], sizes[fresh])
            for c in fresh:
                n = sizes[c]
                J = idx[c, :n].copy()
                self.entries[ids[c]] = (inlier[:, c].copy(), J, M[c, :n, :n].copy(), np.zeros(n))
            self.fresh += len(fresh)
        if self.budget is not None:
            self._evict([ids[c] for c in range(k_all)])
        return M

    def _evict(self, current: list) -> None:
        """Let go of the matrices used longest ago, not those of ``current`` (the
        columns of this call, in their order: the order of the entries, and so what is
        let go later, does not depend on the names' hashes), while the stored ones
        exceed the budget."""
        for key in current:  # the most recently used, moved to the end
            if key in self.entries:
                self.entries[key] = self.entries.pop(key)
        keep = set(current)
        total = sum(entry[2].size for entry in self.entries.values())
        for key in list(self.entries):
            if total <= self.budget or key in keep:
                break
            total -= self.entries.pop(key)[2].size


def _border(A, G, inlier, J0, M0, drift, new):
    """The inlier Gram matrix ``M0`` on ``J0`` bordered with the terms ``new``: their
    rows and columns formed as :func:`inlier_gram` forms a matrix afresh."""
    Jx = np.concatenate([J0, new])
    k0 = J0.size
    B = _weighted_gram(A, G, inlier.astype(float), Jx, new.size)
    Mx = np.empty((Jx.size, Jx.size))
    Mx[:k0, :k0] = M0
    Mx[:, k0:] = B
    Mx[k0:, :k0] = B[:k0].T
    return Jx, Mx, np.concatenate([drift, np.zeros(new.size)])


#: Support sizes from which a Newton system is solved by a Cholesky factorisation (with
#: a condition estimate) instead of an eigen-decomposition: several times cheaper, and
#: the same solution where no eigenvalue would be cut.
CHOLESKY_SIZE = 48


#: Margin of :func:`_cholesky_solve` between its condition estimate and the eigenvalue
#: cut (the estimate may exceed the true reciprocal condition number by a small factor).
CHOLESKY_MARGIN = 10.0


def conditioned_cholesky(M: np.ndarray, cut: float):
    """The lower Cholesky factor of the symmetric ``M`` (its upper triangle not
    cleaned) where no eigenvalue can be near the relative eigenvalue ``cut``, so that an
    eigen-solver or pseudo-inverse with that cut would cut nothing and give the same
    result; else ``None``.

    First by LAPACK's estimate of the reciprocal 1-norm condition number: at least
    :data:`CHOLESKY_MARGIN` times ``cut`` (for a symmetric matrix the 2-norm condition
    number is at most the 1-norm's).  Where the estimate cannot tell (it exceeds the
    2-norm condition number by up to the order of the matrix), by the eigenvalues
    themselves: the smallest above ``cut`` times the largest by more than ten times
    their rounding (``n eps`` of the largest), at a fraction of the cost of the
    eigen-decomposition they spare."""
    c, info = scipy.linalg.lapack.dpotrf(M, lower=True, clean=False)
    if info != 0:
        return None
    rcond, info = scipy.linalg.lapack.dpocon(c, np.abs(M).sum(axis=0).max(), uplo="L")
    if info != 0 or not np.isfinite(rcond):
        return None
    if rcond >= CHOLESKY_MARGIN * cut:
        return c
    vals = np.linalg.eigvalsh(M)
    if vals[0] > (cut + 10.0 * M.shape[0] * np.finfo(float).eps) * vals[-1]:
        return c
    return None


def _cholesky_solve(Mk: np.ndarray, b: np.ndarray):
    """``Mk^-1 b`` by Cholesky where no eigenvalue of ``Mk`` can be near the cut
    :data:`EIG_CUT` (:func:`conditioned_cholesky`), else ``None``."""
    c = conditioned_cholesky(Mk, EIG_CUT)
    if c is None:
        return None
    out, info = scipy.linalg.lapack.dpotrs(c, b[:, None], lower=True)
    return out[:, 0] if info == 0 and np.all(np.isfinite(out)) else None


def _solve_blocks(Mm: np.ndarray, b: np.ndarray, valid: np.ndarray):
    """Solve the leading blocks ``Mm[k][valid_k, valid_k] d = b[k][valid_k]`` (valid
    entries first in each row of ``valid``); returns the solutions (k, s), zero
    beyond each block, and the columns where an eigenvalue was cut."""
    k, s = valid.shape
    sizes = valid.sum(axis=1)
    # Each block is its leading sizes[j] x sizes[j] entries: the Cholesky solves read
    # only those, and only the blocks left to the eigen-solver are masked (a masked copy
    # of every block is k s^2 entries, hundreds of megabytes with many states).
    diag = np.einsum("kii->ki", Mm)
    top = np.max(np.where(valid, diag, 0.0), axis=1)
    top = np.where(top > 0, top, 1.0)
    out = np.zeros((k, s))
    deficient = np.zeros(k, dtype=bool)
    pending = np.ones(k, dtype=bool)
    if s >= CHOLESKY_SIZE:

        def column(j):  # each column its own factorisation, side by side
            n = sizes[j]
            x = _cholesky_solve(Mm[j, :n, :n] / top[j], b[j, :n] / top[j])
            if x is not None:
                out[j, :n], pending[j] = x, False

        map_threads(column, np.flatnonzero(sizes >= CHOLESKY_SIZE), flops=s**3 / 3)
    rest = np.flatnonzero(pending)
    if rest.size:
        # Padded with a multiple of the identity (the largest diagonal entry, so the
        # eigenvalue cut refers to the block's own scale) and normalised to a unit
        # diagonal maximum: the eigen-solver sees no tiny or huge entries (reweighted
        # steps with delta far below the residuals have weights ~1e-300).
        vr, tr = valid[rest], top[rest]
        Mr = np.where(vr[:, :, None] & vr[:, None, :], Mm[rest], 0.0)
        pos = np.arange(s)
        Mr[:, pos, pos] = np.where(vr, np.einsum("kii->ki", Mr), tr[:, None])
        w, V = np.linalg.eigh(Mr / tr[:, None, None])
        keep = w > EIG_CUT * np.maximum(w[:, -1:], 0.0)
        c = np.einsum("kji,kj->ki", V, np.where(vr, b[rest], 0.0))
        c = np.where(keep, c / np.where(keep, w * tr[:, None], 1.0), 0.0)
        out[rest] = np.where(vr, np.einsum("kij,kj->ki", V, c), 0.0)
        deficient[rest] = ~keep.all(axis=1)
    return out, deficient


def masked_solve(M: np.ndarray, rhs: np.ndarray, S: np.ndarray):
    """Solve ``M_k[S_k, S_k] d = rhs[S_k, k]`` for every column ``k`` (batched).

    ``M`` is (k, p, p), ``rhs`` and ``S`` (p, k).  Each column's block ``M[S, S]`` is
    gathered into the first ``|S_k|`` rows and columns of a batch as large as the
    largest support (the cost is that of the supports, not of the library).
    Returns the minimum-norm solution with eigenvalues below ``1e-11`` of the largest cut
    (``d`` zero off ``S``) and a mask of the columns where a cut was needed.
    """
    St = S.T
    k, p = St.shape
    sizes = St.sum(axis=1)
    s = max(int(sizes.max(initial=0)), 1)
    # Per column, the support's indices first (in order), then the others.
    idx = np.argsort(~St, axis=1, kind="stable")[:, :s]
    valid = np.arange(s)[None, :] < sizes[:, None]  # (k, s)
    cols = np.arange(k)[:, None]
    block, deficient = _solve_blocks(
        M[cols[:, :, None], idx[:, :, None], idx[:, None, :]], rhs.T[cols, idx], valid
    )
    return _scatter(block, idx, valid, p), deficient


def _scatter(block: np.ndarray, idx: np.ndarray, valid: np.ndarray, p: int) -> np.ndarray:
    """The blocks' solutions (k, s) at their terms ``idx`` in a (p, k) array."""
    d = np.zeros((p, block.shape[0]))
    rows, where = np.nonzero(valid)
    d[idx[rows, where], rows] = block[rows, where]
    return d


def direction(A, G, T, r, delta, lam, x, g, free, mu, cache=None, ids=None):
    """Newton directions (p, k) of the active columns at ``x`` (see the module doc).

    ``mu`` (k,) is a Levenberg-Marquardt term added to the diagonal (the columns of
    ``A`` have unit norm; see :func:`newton` for its rule): where few inliers leave the
    system nearly singular (a least-absolute-deviation-like piece), it keeps the step
    bounded; near the optimum it is zero and the step is Newton's.  ``cache``
    (:class:`GramCache`, columns named by ``ids``) updates the inlier Gram matrices of
    the previous step instead of forming them afresh.  The Gram matrices are formed on
    each column's working set only (:func:`working_sets`).

    A term at zero enters the support with the sign of its proximal-gradient point;
    where the step gives it the other sign, the objective's slope along the step counts
    its penalty with the wrong sign and the step may be no descent direction (many
    correlated terms entering at once, as on a warm-started path).  Such terms are kept
    at zero and the step solved again, until every entering term moves with its sign
    (each round leaves out at least one term).
    """
    p = A.shape[1]
    u = x + T[:, None] * g
    S = (np.abs(u) > T[:, None] * lam) | free
    sigma = np.where(free, 0.0, np.sign(u))
    lam_sigma = lam * sigma

    def solve(weights, which):
        idx, n_s, n_w = working_sets(S[:, which], x[:, which])
        s = max(int(n_s.max(initial=0)), 1)
        cols = np.arange(which.size)[:, None]
        pos = np.arange(idx.shape[1])[None, :]
        on_s = pos < n_s[:, None]
        # The right-hand side on the support: g - lam sigma + M_{S, other} x_other.
        x_other = np.where(~on_s & (pos < n_w[:, None]), x[:, which].T[cols, idx], 0.0)
        if cache is not None and weights.dtype == bool:
            M = cache.gram(A, G, weights, [ids[c] for c in which], idx, n_w)
        else:
            M = inlier_gram(A, G, weights.astype(float, copy=False), idx, n_w)
        rhs = (g[:, which] - lam_sigma[:, which]).T[cols, idx]
        rhs += np.einsum("kij,kj->ki", M, x_other)
        Mm = M[:, :s, :s].copy()
        diag = np.arange(s)
        Mm[:, diag, diag] += mu[which, None]
        block, cut = _solve_blocks(Mm, rhs[:, :s], on_s[:, :s])
        return _scatter(block, idx[:, :s], on_s[:, :s], p), cut

    everything = np.arange(r.shape[1])
    inlier = np.abs(r) <= delta
    d, deficient = solve(inlier, everything)
    entering = S & (x == 0) & ~free
    while True:
        wrong = entering & (np.sign(d) != sigma)
        again = np.flatnonzero(wrong.any(axis=0) & ~deficient)
        if not again.size:
            break
        S[:, again] &= ~wrong[:, again]
        entering[:, again] &= ~wrong[:, again]
        d[:, again], deficient[again] = solve(inlier[:, again], again)

    def from_rows(k, weights):
        return row_direction(
            A, weights, r[:, k], S[:, k], x[:, k], lam_sigma[:, k], delta[k], mu[k], d[:, k]
        )

    # Where the Gram system needed a cut, the rows themselves may still determine the
    # step: their singular values are the square roots of its eigenvalues (rare).
    for k in np.flatnonzero(deficient):
        d[:, k], deficient[k] = from_rows(k, inlier[:, k].astype(float))
    if deficient.any():
        # Too few inliers to fix the support's coefficients: the reweighted
        # least-squares step, whose quadratic model majorises the Huber loss.
        j = everything[deficient]
        absr = np.maximum(np.abs(r[:, j]), np.finfo(float).tiny)
        weights = np.minimum(1.0, delta[j] / absr)
        d[:, j], cut = solve(weights, j)
        for i in np.flatnonzero(cut):
            d[:, j[i]] = from_rows(j[i], weights[:, i])[0]
    return np.where(S, d, -x)


#: Relative singular-value cut of :func:`row_direction` (the Gram systems' eigenvalue cut
#: ``1e-11`` is a singular-value cut near ``3e-6``: rows resolve 3e4 times further).
_SVD_CUT = 1e-10


def row_direction(A, w, r, S, x, lam_sigma, delta, mu, fallback):
    """The Newton direction of one column from the weighted rows, not their Gram matrix.

    Solves ``(A_S^T W A_S + mu I) d_S = g_S - lam_S sigma_S + A_S^T W A_Sbar x_Sbar`` (the
    system of :func:`direction`, weights ``w`` (m,) in ``[0, 1]``) by a singular value
    decomposition of ``B = W^(1/2) A_S``: with ``psi = W r + e`` (``e`` the outliers'
    ``+-delta`` for 0/1 weights, zero for the reweighted step), the right-hand side is
    ``B^T b + c``, ``b = W^(1/2) (r + A_Sbar x_Sbar)``, ``c = A_S^T e - lam_S sigma_S``,
    and ``d_S = V [(s U^T b + V^T c) / (s^2 + mu)]``.  Forming the Gram matrix squares
    the condition number: in an ill-conditioned library (states far from zero, monomials
    of them nearly collinear) its eigenvalue cut drops the very directions along which
    the optimum still moves, and the iteration stalls uncertified; the rows keep them
    (singular values down to ``1e-10`` of the largest).  Returns the direction (p,) and
    whether a cut was still needed; ``fallback`` where the decomposition fails.
    """
    rows = np.flatnonzero(w > 0)
    if rows.size < np.count_nonzero(S) or not S.any():
        return fallback, True  # fewer rows than unknowns: rank-deficient whatever they are
    sw = np.sqrt(w[rows])
    top = sw.max()
    sw = sw / top  # the largest weight 1: no underflow of the squared singular values
    Ar = A[rows]
    off = np.where(S, 0.0, x)
    B = sw[:, None] * Ar[:, S]
    b = sw * (r[rows] + Ar @ off)
    e = huber_psi(r, delta) - w * r
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        c = ((A.T @ e)[S] - lam_sigma[S]) / top**2
        try:
            U, sv, Vt = np.linalg.svd(B, full_matrices=False)
        except np.linalg.LinAlgError:
            return fallback, True
        keep = sv > _SVD_CUT * sv[0]  # |S| values: at least as many rows as terms
        den = np.where(keep, sv**2 + mu / top**2, 1.0)
        coef = np.where(keep, (sv * (U.T @ b) + Vt @ c) / den, 0.0)
        d = np.zeros_like(x)
        d[S] = Vt.T @ coef
    if not np.all(np.isfinite(d)):
        return fallback, True
    return d, bool(not keep.all())


def step_lengths(A, r, x, d, g, lam, delta, lipschitz, phi0=None):
    """Step lengths (k,) along ``d`` and the directions actually taken.

    The full step where it passes the Armijo test; otherwise the exact line search; a
    proximal-gradient direction (always a descent direction unless ``x`` is optimal)
    where ``d`` is no descent direction.  ``t = 0`` means no progress is possible.
    ``phi0``, the objective at ``x``, is computed when not given.
    """
    q = A @ d
    s = np.where(x != 0, np.sign(x), np.sign(d))
    slope0 = (lam * s * d).sum(axis=0) - np.einsum("ij,ij->j", huber_psi(r, delta), q)
    phi0 = column_objective(r, x, delta, lam) if phi0 is None else phi0
    full = column_objective(r - q, x + d, delta, lam) <= phi0 + ARMIJO * slope0
    t = np.where((slope0 < 0) & full, 1.0, 0.0)
    for k in np.flatnonzero(t == 0.0):  # rare: one column at a time
        if slope0[k] >= 0:
            d[:, k] = soft_threshold(x[:, k] + g[:, k] / lipschitz, lam[:, k] / lipschitz)
            d[:, k] -= x[:, k]
            q[:, k] = A @ d[:, k]
        rk, qk, xk, dk, lk = r[:, k], q[:, k], x[:, k], d[:, k], lam[:, k]
        # Where the full step overshoots (the usual reason it failed), the minimiser
        # lies before it: only the breakpoints up to it need sorting.
        upper = 1.0 if slope(1.0, rk, qk, xk, dk, lk, delta[k]) >= 0 else None
        t[k] = line_search(rk, qk, xk, dk, lk, delta[k], upper)
    return t, d


@dataclass
class NewtonRun:
    """Outcome of :func:`newton` per column (``x`` in the units of ``prepared.A``)."""

    x: np.ndarray  # (p, k) the best certified point, or the last one
    certified: np.ndarray  # (k,) relative KKT <= tol
    stalled: np.ndarray  # (k,) stopped uncertified at the floating-point floor
    kkt: np.ndarray  # (k,) relative KKT violation of the last point evaluated
    steps: np.ndarray  # (k,)
    passes: int  # passes over A, all columns together


def newton(
    prepared: Prepared,
    y,
    delta,
    lam,
    x,
    *,
    max_steps: int,
    tol: float,
    patience: int | None = None,
    names=None,
) -> NewtonRun:
    """Run the batched Newton method on scaled columns.

    ``y`` (m, k), ``delta`` (k,), ``lam`` (p, k) and the start ``x`` (p, k) are in the
    units of ``prepared.A``.  A column stops at a relative KKT violation below
    ``tol / 10`` (a margin for the check in the caller's units), after two steps that
    did not halve the violation of a point already below ``tol``, when no step makes
    progress, or when it has stalled: its KKT violation has not halved in 5 steps while
    its objective no longer changes (1e-12 relative) or its violation is within what the
    rounding of the residuals can leave
    (:func:`~robust_sindy.core.certificates.rounding_floor`), which is where rounding
    ends what any method can certify.  The returned point is
    the best certified one (KKT <= ``tol``) or, for uncertified columns, the last.
    With ``patience``, a column also stops once its violation has not halved in that
    many steps (a bounded attempt, as the compiled iteration makes).
    ``names`` (k,), hashable, name the columns for the inlier Gram matrices that
    ``prepared.carry`` keeps between fits (:func:`~.problem.shared_preparation`).
    """
    A, G, norms = prepared.A, prepared.G, prepared.a_norms
    T = 1.0 / norms**2
    free = lam == 0
    x = np.array(x, dtype=float)
    r = y - A @ x
    passes = 1
    k_all = y.shape[1]
    best, best_g = x.copy(), np.zeros_like(x)
    best_kkt = np.full(k_all, np.inf)
    steps = np.zeros(k_all, dtype=int)
    last_kkt = np.full(k_all, np.inf)
    ref_kkt, ref_obj = np.full(k_all, np.inf), np.full(k_all, np.inf)
    ref_step = np.zeros(k_all, dtype=int)
    stalled = np.zeros(k_all, dtype=bool)
    mu = np.zeros(k_all)
    act = np.arange(k_all)
    if prepared.carry is not None and names is not None:
        cache = prepared.carry.setdefault("gram", GramCache(budget=A.shape[0] * A.shape[1]))
        ids = np.asarray(names, dtype=object)
    else:
        cache, ids = GramCache(), np.arange(k_all)
    for step in range(max_steps + 1):
        # All columns still active: views, not copies, of the m x n arrays.
        cols = slice(None) if act.size == k_all else act
        xa, ya, la, da = x[:, act], y[:, cols], lam[:, act], delta[act]
        ra = r[:, cols]
        psi = huber_psi(rounding_free(ra, ya, A, xa), da)
        g = A.T @ psi
        passes += 1
        kkt = kkt_from_gradient(xa, g, la, norms, column_norms(psi))
        del psi  # one m x n array less while the step is computed
        last_kkt[act] = kkt
        better = (kkt <= tol) & (kkt < best_kkt[act])
        best[:, act[better]], best_g[:, act[better]] = xa[:, better], g[:, better]
        best_kkt[act[better]] = kkt[better]
        steps[act] = step
        obj = column_objective(ra, xa, da, la)
        halved = kkt < 0.5 * ref_kkt[act]
        ref_kkt[act[halved]], ref_obj[act[halved]], ref_step[act[halved]] = (
            kkt[halved],
            obj[halved],
            step,
        )
        waited = step - ref_step[act]
        stuck = (waited >= _STALL_STEPS) & (ref_obj[act] - obj <= _STALL_OBJ * np.abs(obj))
        # A nearly exact fit's objective is itself rounding (relative to the terms'
        # size, not to the tiny residuals), so it can keep changing at 1e-9 while the
        # violation sits within what the rounding of the residuals can leave: that is
        # the floor too (checked every _STALL_STEPS steps without halving).
        check = ~stuck & (waited >= _STALL_STEPS) & (waited % _STALL_STEPS == 0)
        if check.any():
            at = np.flatnonzero(check)
            floor = rounding_floor(A, ya[:, at], xa[:, at], da[at], ra[:, at])
            stuck[at[within_floor(kkt[at], floor)]] = True
        stalled[act] = stuck & ~np.isfinite(best_kkt[act])
        settled = np.isfinite(best_kkt[act]) & (step - ref_step[act] >= _CERTIFIED_STEPS)
        go = (kkt > 0.1 * tol) & ~stuck & ~settled
        if patience is not None:
            go &= step - ref_step[act] < patience
        if step == max_steps or not go.any():
            break
        if not go.all():
            act, xa, ya, la, da, g = act[go], xa[:, go], ya[:, go], la[:, go], da[go], g[:, go]
            ra = r[:, act]
        d = direction(A, G, T, ra, da, la, xa, g, free[:, act], mu[act], cache, ids[act])
        t, d = step_lengths(A, ra, xa, d, g, la, da, prepared.lipschitz, obj[go])
        # Damping only after a step the objective did not accept in full, relaxed again
        # after full steps (a trust-region-like rule; undamped Newton near the optimum).
        mu[act] = np.where(t == 1.0, 0.1 * mu[act], np.maximum(10 * mu[act], LM * kkt[go]))
        mu[mu < 1e-12] = 0.0
        passes += 1
        moving = t > 0
        if not moving.any():
            break
        act = act[moving]
        x[:, act] = xa[:, moving] + t[moving] * d[:, moving]
        if act.size == k_all:
            r = y - A @ x
        else:
            r[:, act] = y[:, act] - A @ x[:, act]
        passes += 1
    certified = np.isfinite(best_kkt)
    x = np.where(certified, best, x)
    last_kkt = np.where(certified, best_kkt, last_kkt)
    # A partial line-search step leaves rounding-level entries where the optimum has
    # exact zeros; drop those the proximal-gradient map sets to zero if the certificate
    # still holds.
    zero = (np.abs(best + T[:, None] * best_g) <= T[:, None] * lam) & (best != 0) & certified
    cols = np.flatnonzero(zero.any(axis=0))
    if cols.size:
        xc = np.where(zero[:, cols], 0.0, x[:, cols])
        rc = y[:, cols] - A @ xc
        psi = huber_psi(rounding_free(rc, y[:, cols], A, xc), delta[cols])
        g = A.T @ psi
        passes += 2
        kc = kkt_from_gradient(xc, g, lam[:, cols], norms, column_norms(psi))
        ok = kc <= tol
        x[:, cols[ok]] = xc[:, ok]
        last_kkt[cols[ok]] = kc[ok]
    return NewtonRun(x, certified, stalled & ~certified, last_kkt, steps, passes)


# ---------------------------------------------------------------------------------------
# the fast path
