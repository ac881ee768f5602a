"""Solver-independent optimality certificates for the Huber-Lasso problem.

For one target column ``y`` and coefficients ``xi`` the objective is

.. math::

    P(\\xi) = \\sum_i H_\\delta(y_i - \\theta_i \\xi) + \\sum_j \\lambda_j |\\xi_j| .

With ``r = y - Theta xi`` and ``g = Theta^T psi_delta(r)``, ``xi`` is optimal iff
``g_j = lam_j sign(xi_j)`` on the support and ``|g_j| <= lam_j`` off it.

* **KKT violation** -- per coordinate the proximal-gradient residual
  ``|xi_j - S(xi_j + t_j g_j, lam_j t_j)| / t_j`` with ``t_j = 1 / ||Theta_j||^2``,
  divided by ``max(lam_j, ||Theta_j|| ||psi_delta(r)||)`` and maximised over ``j``.
  It is continuous in ``xi`` (a 1e-12 where the optimum has an exact zero does not
  count as a violation) and invariant to rescaling the columns of ``Theta``.
* Residuals at the level of floating-point error (``16 (p + 1) eps`` times
  ``|y_i| + |Theta_i| |xi|`` entrywise, or in norm for a whole column) count as zero
  in ``psi``: an exact fit
  (e.g. noise-free data, ``lam = 0``) has residuals that are rounding noise, and a ratio
  of rounding noise to rounding noise would certify nothing.
* **Duality gap** -- the dual is
  ``max_u y^T u - ||u||^2 / 2`` s.t. ``|u_i| <= delta``, ``|Theta_j^T u| <= lam_j``;
  ``u = psi_delta(r) min(1, min_j lam_j / |g_j|)`` is dual feasible, so
  ``P(xi) - D(u) >= P(xi) - P*``.  When some ``lam_j = 0`` this scaling can only
  certify through ``g_j = 0``, so the gap is loose there; the KKT violation is not.

These functions are the test oracle and the stopping rule of every solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .losses import huber, huber_psi
from .validation import check_coef, check_problem, loss_delta, per_column

__all__ = ["duality_gap", "kkt_violation", "objective"]


@dataclass
class Certificate:
    """Everything one pass over ``Theta`` tells about a candidate ``Xi`` (all per column)."""

    objective: np.ndarray  # (n,)
    kkt: np.ndarray  # (n,) relative KKT violation
    gap: np.ndarray  # (n,) absolute duality gap
    residual: np.ndarray  # (m, n)
    psi: np.ndarray  # (m, n)
    grad: np.ndarray  # (p, n)  Theta^T psi

    @property
    def rel_gap(self) -> np.ndarray:
        return self.gap / np.maximum(np.abs(self.objective), np.finfo(float).tiny)


def column_norms(theta: np.ndarray) -> np.ndarray:
    """Euclidean norms of the columns of ``theta`` without overflow or underflow.

    The plain sum of squares (no temporary copy of ``theta``) where it is safely in
    range; columns whose sum of squares overflows or underflows are divided by their
    largest entry first, as BLAS ``nrm2`` does.
    """
    with np.errstate(over="ignore", under="ignore"):
        sq = np.einsum("ij,ij->j", theta, theta)
    out = np.sqrt(sq)
    if not theta.shape[0]:
        return out
    # Overflow, NaN, or a sum that underflowed (to zero or near it): rescale those.
    bad = ~((sq >= 1e4 * np.finfo(float).tiny) & (sq < np.inf))
    for j in np.flatnonzero(bad):  # rare: extreme scales or zero columns
        col = theta[:, j]
        top = np.max(np.abs(col))
        out[j] = top * np.linalg.norm(col / top) if 0 < top < np.inf else top
    return out


def kkt_from_gradient(
    xi: np.ndarray, grad: np.ndarray, lam: np.ndarray, col_norms: np.ndarray, psi_norm: np.ndarray
) -> np.ndarray:
    """Relative KKT violation per column from a precomputed gradient.

    ``xi``, ``grad`` and ``lam`` are (p, n), ``col_norms`` (p,), ``psi_norm`` (n,).
    A zero column of ``Theta`` contributes nothing unless its coefficient is nonzero
    while penalised, which is infinitely far from optimal.

    The proximal-gradient residual ``|xi - S(xi + t g, t lam)| / t`` is evaluated branch
    by branch (``|g - lam|``, ``|g + lam|`` or ``|xi| / t``) rather than as a difference:
    ``xi + t g`` rounds to ``xi`` whenever ``t |g|`` is below the last bit of ``xi``, and
    the difference would then certify a non-stationary point with a violation of 0.
    ``t = 1 / ||Theta_j||^2`` enters as two divisions by the norm (no overflow).
    """
    nrm = col_norms[:, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t_g = np.where(nrm > 0, grad / nrm / nrm, 0.0)
        t_lam = np.where(nrm > 0, lam / nrm / nrm, 0.0)
        u = xi + t_g
        step = np.where(
            u > t_lam,
            np.abs(grad - lam),
            np.where(u < -t_lam, np.abs(grad + lam), np.abs(xi) * nrm * nrm),
        )
        step = np.where(nrm > 0, step, np.where((xi != 0) & (lam > 0), np.inf, 0.0))
        scale = np.maximum(lam, nrm * psi_norm[None, :])
        rel = np.where(scale > 0, step / scale, np.where(step > 0, np.inf, 0.0))
    # Non-finite coefficients or residuals are never certified.
    rel = np.where(np.isnan(step) | np.isnan(scale), np.inf, rel)
    return rel.max(axis=0)


def gap_from_sums(obj, grad, lam, y_psi, psi_norm) -> np.ndarray:
    """Duality gap per column from the objective and sums over rows.

    The dual-feasible point is ``psi`` scaled by ``min(1, min_j lam_j / |grad_j|)``; the
    dual objective is quadratic in the scale: ``s y^T psi - s^2 ||psi||^2 / 2``.
    """
    absg = np.abs(grad)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(absg > 0, lam / absg, np.inf)
    s = np.minimum(1.0, ratio.min(axis=0))
    dual = s * y_psi - 0.5 * s**2 * psi_norm**2
    return np.maximum(obj - dual, 0.0)


_ROW_CHUNK = 4096  # rows of |Theta| formed at a time


def _abs_product(theta: np.ndarray, axi: np.ndarray, rows=None) -> np.ndarray:
    """``|Theta[rows]| @ axi`` for ``axi >= 0`` in row chunks, never forming ``|Theta|``
    whole, and reading only the columns of ``Theta`` where some entry of ``axi`` is not
    zero (a sparse model's terms: the others add nothing)."""
    idx = np.arange(theta.shape[0]) if rows is None else rows
    terms = np.flatnonzero(np.any(axi != 0, axis=1))
    out = np.zeros((idx.size, axi.shape[1]))
    if terms.size == 0:
        return out
    axi = axi[terms]
    every = terms.size == theta.shape[1]  # then whole rows, as they are stored
    for lo in range(0, idx.size, _ROW_CHUNK):
        at = idx[lo : lo + _ROW_CHUNK]
        block = theta[at] if every else gather(theta, at, terms)
        out[lo : lo + _ROW_CHUNK] = np.abs(block) @ axi
    return out


def gather(theta, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``theta[rows][:, cols]`` (integer arrays) for an array or an operator with a
    ``block`` method (the solvers' equilibrated library), without forming the rows'
    other entries."""
    if isinstance(theta, np.ndarray):
        return theta[np.ix_(rows, cols)]
    return theta.block(rows, cols)


def rounding_free(r: np.ndarray, y: np.ndarray, theta: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``r`` with residuals at the level of floating-point error set to zero.

    Computing ``r_i = y_i - Theta_i xi`` carries an error up to
    about ``p eps (|y_i| + |Theta_i| |xi|)``, and a backward-stable exact fit leaves
    residuals of about ``eps (||y|| + || |Theta| |xi| ||)`` in norm.  Entries below
    ``16 (p + 1) eps`` times the first, and whole columns below that many times the
    second, are zero as far as the data can tell; treating them as anything else makes an
    exact fit uncertifiable (its gradient would be a sum of rounding noise).
    ``|Theta_i| |xi|`` enters only up to ``max |y|``: rounding from huge cancelling
    coefficients (e.g. along collinear columns) is not forgiven, such a point is simply
    not certified.  ``|Theta| |xi|`` is evaluated only on the rows (and columns) where a
    residual could be that small, a chunk of rows at a time.
    """
    c = 16 * (xi.shape[0] + 1) * np.finfo(float).eps
    ymax = np.abs(y).max(axis=0)
    bound = 2 * c * ymax  # |y_i| + min(|Theta_i| |xi|, ymax) <= 2 ymax
    small = np.abs(r) <= bound
    # A whole column can be exact only if ||r|| <= 2 c (||y|| + sqrt(m) ymax) (the
    # entries zeroed first are each below c times their scale).
    maybe_exact = column_norms(r) <= 2 * c * (column_norms(y) + np.sqrt(r.shape[0]) * ymax)
    if not (small.any() or maybe_exact.any()):  # above every possible bound
        return r
    axi = np.abs(xi)
    r = r.copy()
    rows = np.flatnonzero(small.any(axis=1))
    if rows.size:
        scale = np.abs(y[rows]) + np.minimum(_abs_product(theta, axi, rows), ymax)
        r[rows] = np.where(np.abs(r[rows]) <= c * scale, 0.0, r[rows])
    cols = np.flatnonzero(maybe_exact)
    if cols.size:
        scale = np.abs(y[:, cols]) + np.minimum(_abs_product(theta, axi[:, cols]), ymax[cols])
        exact = column_norms(r[:, cols]) <= c * column_norms(scale)
        r[:, cols[exact]] = 0.0
    return r


def rounding_floor(theta, y, xi, delta, residual) -> np.ndarray:
    """The relative KKT violation per column (n,) that the rounding of the residuals
    alone can leave at ``xi`` (p, n): each inlier's ``r_i = y_i - Theta_i xi`` is
    computed with an error of up to about ``(p + 1) eps (|y_i| + |Theta_i| |xi|)`` (an
    outlier's ``psi`` is exactly ``+-delta``), which enters ``Theta_j^T psi`` at most as
    ``||Theta_j||`` times its norm, and the violation is relative to
    ``||Theta_j|| ||psi||`` (or more): the norm of those errors over ``||psi||``.

    Where the residuals carry noise this is far below any tolerance (1e-12 and less);
    it is large only where they are at the level of that rounding, e.g. a nearly exact
    fit whose terms cancel.  ``|Theta| |xi|`` is not capped (unlike
    :func:`rounding_free`): the floor is a bound on the arithmetic, not a verdict.  The
    bound holds only while the rounding cannot move a sample across ``delta``: where
    some residual's rounding reaches ``delta`` (a threshold below the resolution of the
    residuals, a least-absolute-deviation fit) the floor is 0, nothing forgiven.
    """
    delta = np.asarray(delta, dtype=float)[None, :]
    inlier = np.abs(residual) <= delta
    size = np.abs(y) + _abs_product(theta, np.abs(xi))
    error = (xi.shape[0] + 1) * np.finfo(float).eps * size
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = column_norms(np.where(inlier, error, 0.0)) / column_norms(
            huber_psi(residual, delta)
        )
    resolved = np.all(error < delta, axis=0)
    return np.where(resolved, np.nan_to_num(ratio, nan=0.0, posinf=0.0), 0.0)


def within_floor(kkt, floor) -> np.ndarray:
    """Whether a relative KKT violation is within its :func:`rounding_floor` (a floor
    of 0, or NaN where none was computed, forgives nothing)."""
    floor = np.nan_to_num(np.asarray(floor, dtype=float), nan=0.0)
    return (floor > 0) & (np.asarray(kkt) <= floor)


def accept_within_floor(theta, y, coef, delta, kkt, ok, residual=None, floor=None):
    """``ok`` (n,), the columns of ``coef`` (p, n) a certificate accepted, with those it
    rejected accepted where their relative KKT violation ``kkt`` is within their
    :func:`rounding_floor`; and the floors (n,): ``floor`` where given (NaN: not
    computed), else computed for the rejected columns (at the residuals ``residual``
    (m, n), else ``y - theta coef``) and NaN for the others."""
    floor = np.full(np.shape(ok), np.nan) if floor is None else np.array(floor, dtype=float)
    new = np.flatnonzero(~ok & np.isnan(floor))
    if new.size:
        xi = coef[:, new]
        r = y[:, new] - theta @ xi if residual is None else residual[:, new]
        floor[new] = rounding_floor(theta, y[:, new], xi, np.asarray(delta)[new], r)
    return ok | within_floor(kkt, floor), floor


def certify(
    theta: np.ndarray,
    y: np.ndarray,
    xi: np.ndarray,
    delta: np.ndarray,
    lam: np.ndarray,
    col_norms: np.ndarray | None = None,
) -> Certificate:
    """Objective, KKT violation and duality gap of ``xi`` (p, n) in two passes over ``theta``.

    ``delta`` is (n,) (``inf`` for the squared loss); ``lam`` broadcasts to (p, n).
    """
    lam = np.broadcast_to(lam, xi.shape)
    if col_norms is None:
        col_norms = column_norms(theta)
    # Column-major (m, n) arrays: the elementwise work and the sums over samples run
    # along contiguous memory.
    y = np.asfortranarray(y)
    r = y - ((xi.T @ theta.T).T if isinstance(theta, np.ndarray) else theta @ xi)
    psi = huber_psi(rounding_free(r, y, theta, xi), delta)
    g = theta.T @ psi
    obj = huber(r, delta).sum(axis=0) + (lam * np.abs(xi)).sum(axis=0)
    psi_norm = column_norms(psi)
    kkt = kkt_from_gradient(xi, g, lam, col_norms, psi_norm)
    gap = gap_from_sums(obj, g, lam, np.einsum("ij,ij->j", y, psi), psi_norm)
    return Certificate(objective=obj, kkt=kkt, gap=gap, residual=r, psi=psi, grad=g)


def _prepare(theta, xdot, coef, delta, lam, loss):
    theta, y, one_d = check_problem(theta, xdot)
    n = y.shape[1]
    xi = check_coef(coef, theta.shape[1], n, one_d)
    d = loss_delta(loss, delta, n)
    lam_arr = per_column(lam, "lam", n, positive=False)
    return certify(theta, y, xi, d, lam_arr[None, :])


def objective(theta, xdot, coef, delta=1.0, lam=1.0, loss: str = "huber") -> np.ndarray:
    """Objective ``P_k`` of each target column at ``coef`` (a sum over samples, not a mean).

    Parameters
    ----------
    theta : array_like, shape (m, p)
        Library matrix.
    xdot : array_like, shape (m,) or (m, n)
        Targets.
    coef : array_like, shape (p,) or (p, n)
        Coefficients, shaped like the output of :func:`robust_sindy.fit`.
    delta, lam : float or array_like of shape (n,)
        Huber threshold and L1 weight, one value or one per column.
    loss : {"huber", "squared"}
        ``"squared"`` is the Lasso objective ``sum r^2 / 2 + lam ||xi||_1``.

    Returns
    -------
    ndarray, shape (n,)

    Examples
    --------
    >>> import numpy as np
    >>> from robust_sindy import objective
    >>> objective(np.eye(2), np.array([3.0, 0.5]), np.zeros(2), delta=1.0, lam=1.0)
    array([2.625])
    """
    return _prepare(theta, xdot, coef, delta, lam, loss).objective


def kkt_violation(theta, xdot, coef, delta=1.0, lam=1.0, loss: str = "huber") -> np.ndarray:
    """Relative KKT violation of ``coef`` per target column (0 at an exact optimum).

    Same arguments as :func:`objective`.  Values around 1e-10 mean optimal to machine
    precision; scaling the largest coefficient of an optimum by 1.001 gives ~1e-4.
    """
    return _prepare(theta, xdot, coef, delta, lam, loss).kkt


def duality_gap(theta, xdot, coef, delta=1.0, lam=1.0, loss: str = "huber") -> np.ndarray:
    """Duality gap ``P(coef) - D(u) >= P(coef) - P*`` per target column.

    Same arguments as :func:`objective`.  The dual point is ``psi_delta(r)`` scaled
    into the feasible set, so the gap is zero exactly at the optimum.
    """
    return _prepare(theta, xdot, coef, delta, lam, loss).gap
