"""The Huber-Lasso on data larger than memory: a proximal Newton method over Dask row chunks.

Everything a step needs is a sum over rows, computed chunk by chunk as a Dask array
reduction (each chunk's sums packed into one row by ``map_blocks``, the rows added by
``sum``), so ``Theta`` is never materialised: a library given as a lazy Dask
expression of the states is evaluated chunk by chunk in every pass.  For each target
column ``k`` at the current ``xi``:

* one pass gives the Huber objective, the gradient ``g = -Theta^T psi(r)``, the inlier
  Gram matrix ``H = Theta_I^T Theta_I`` (samples with ``|r| <= delta``)
  and the sums the certificate needs (column norms, ``||psi||``, ``y^T psi``); where
  the inliers do not fix every term (e.g. none at the least-squares start), one more
  pass gives the Huber majoriser's ``Theta^T W Theta`` (``W = min(1, delta / |r|)``),
  and its step is taken instead;
* the step solves, in memory (``p x p``), the proximal Newton subproblem
  ``min_z g^T (z - xi) + (z - xi)^T H (z - xi) / 2 + sum lam |z|`` as a Lasso on the
  Cholesky factor of ``H`` (equilibrated; a Levenberg-Marquardt term where ``H`` is
  singular), by the in-memory fast path;
* one pass evaluates the objective at eight step lengths ``1, 1/2, ..., 1/128`` at once
  (Armijo), and the statistics of the next point if the full step is taken, so a run
  near the solution costs one pass per step.

With the inlier set fixed the model is exact, so the method ends in a few steps once
the inliers settle.  The certificate is the in-memory one (:func:`kkt_from_gradient`,
residuals below their floating-point resolution forgiven per chunk), from sums over
rows.

Under linear constraints across equations (:func:`solve_chunked_constrained`) the
passes are the same; the step is one subproblem over all equations under the
constraints, with one step length for all, and the certificate the constrained one
(:func:`robust_sindy.core.constraints.certificate_from_sums`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ..core.certificates import gap_from_sums, kkt_from_gradient, rounding_free
from ..core.losses import huber, huber_psi

__all__ = ["ChunkedRun", "is_dask", "solve_chunked", "solve_chunked_constrained"]

STEPS = 0.5 ** np.arange(8)  # step lengths tried in one pass
#: Relative constraint residual up to which a given start of
#: :func:`solve_chunked_constrained` counts as meeting the constraints.
START_RESIDUAL = 1e-10
ARMIJO = 1e-4
ROUNDING = 1e-12  # relative level below which objective changes are not resolved


def is_dask(a) -> bool:
    """Whether ``a`` is a Dask array."""
    return type(a).__module__.startswith("dask.") and hasattr(a, "to_delayed")


@dataclass
class ChunkedRun:
    coef: np.ndarray
    objective: np.ndarray
    kkt: np.ndarray
    gap: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    passes: int
    messages: list = field(default_factory=list)
    #: The constrained certificate (:func:`solve_chunked_constrained`), else None.
    certificate: object = None


def _blocks(theta, y):
    """``theta`` and ``y`` with one column chunk each and the same row chunks."""
    if theta.ndim != 2 or y.ndim != 2:
        raise ValueError("theta must be 2-D and xdot 1-D or 2-D")
    if len(theta.chunks[1]) != 1:
        theta = theta.rechunk({1: -1})
    if len(y.chunks[1]) != 1:
        y = y.rechunk({1: -1})
    if theta.chunks[0] != y.chunks[0]:
        y = y.rechunk({0: theta.chunks[0]})
    return theta, y


# ---------------------------------------------------------------- per-chunk statistics
def _stats(th, yb, xi, delta, want_gram: bool, want_majoriser: bool = False):
    """Sums over one chunk at ``xi`` (p, n): everything a step and a certificate need."""
    th = np.asarray(th, dtype=float)
    yb = np.asarray(yb, dtype=float)
    r = yb - th @ xi
    psi = huber_psi(rounding_free(r, yb, th, xi), delta)
    out = {
        "obj": huber(r, delta).sum(axis=0),
        "g": th.T @ psi,
        "psi_sq": np.einsum("ij,ij->j", psi, psi),
        "y_psi": np.einsum("ij,ij->j", yb, psi),
    }
    if want_gram:
        inl = np.abs(r) <= delta
        out["H"] = np.stack([th[inl[:, k]].T @ th[inl[:, k]] for k in range(r.shape[1])])
    if want_majoriser:
        # The Huber loss's quadratic majoriser (weights min(1, delta / |r|)): positive
        # definite with the library, for columns whose inliers do not fix every term.
        with np.errstate(divide="ignore"):
            w = np.minimum(1.0, delta / np.abs(r))
        out["M"] = np.stack([(th * w[:, [k]]).T @ th for k in range(r.shape[1])])
    return out


def _stats_and_norms(th, yb, xi, delta):
    """:func:`_stats` with the inlier Gram matrices, and the columns' sums of squares."""
    out = _stats(th, yb, xi, delta, True)
    th = np.asarray(th, dtype=float)
    out["col_sq"] = np.einsum("ij,ij->j", th, th)
    return out


def _first(th, yb):
    """Sums for the start: Gram matrix, ``Theta^T y``, column sums of squares, rows."""
    th = np.asarray(th, dtype=float)
    yb = np.asarray(yb, dtype=float)
    return {
        "G": th.T @ th,
        "b": th.T @ yb,
        "col_sq": np.einsum("ij,ij->j", th, th),
        "y_sq": np.einsum("ij,ij->j", yb, yb),
        "m": np.array(float(th.shape[0])),
    }


def _trial(th, yb, xi, d, delta, next_stats: bool):
    """Objective at ``xi + s d`` for every step length ``s``; stats at the full step."""
    th = np.asarray(th, dtype=float)
    yb = np.asarray(yb, dtype=float)
    r = yb - th @ xi
    td = th @ d
    out = {"trial": np.stack([huber(r - s * td, delta).sum(axis=0) for s in STEPS])}
    if next_stats:
        out["next"] = _stats(th, yb, xi + d, delta, True)
    return out


def _add(parts):
    """Sum of dicts of arrays (nested one level)."""
    out = {}
    for part in parts:
        for key, value in part.items():
            if isinstance(value, dict):
                out[key] = _add([out.get(key, {}), value]) if key in out else dict(value)
            else:
                out[key] = out[key] + value if key in out else value
    return out


def _flatten(stats: dict, prefix=()) -> list:
    """``[(key path, array), ...]`` of a (nested) dict of arrays, in a fixed order."""
    out = []
    for key in sorted(stats):
        value = stats[key]
        if isinstance(value, dict):
            out += _flatten(value, (*prefix, key))
        else:
            out.append(((*prefix, key), np.asarray(value, dtype=float)))
    return out


def _reduce(func, theta, y, *args):
    """One pass: ``func``'s sums on every row chunk, added by a Dask array reduction.

    Each chunk's statistics are packed into one row vector (``map_blocks``) and the rows
    summed (``sum(axis=0)``, Dask's tree reduction), so no chunk outlives its task.
    """
    import dask

    p, n = theta.shape[1], y.shape[1]
    layout = [
        (key, a.shape) for key, a in _flatten(func(np.zeros((1, p)), np.zeros((1, n)), *args))
    ]
    width = sum(int(np.prod(shape)) for _, shape in layout)

    def packed(th, yb):
        parts = _flatten(func(th, yb, *args))
        return np.concatenate([a.ravel() for _, a in parts])[None, :]

    rows = theta.map_blocks(packed, y, chunks=((1,) * theta.numblocks[0], (width,)), dtype=float)
    (total,) = dask.compute(rows.sum(axis=0))
    out: dict = {}
    offset = 0
    for key, shape in layout:
        size = int(np.prod(shape))
        node = out
        for part in key[:-1]:
            node = node.setdefault(part, {})
        node[key[-1]] = total[offset : offset + size].reshape(shape)
        offset += size
    return out


# ---------------------------------------------------------------- the in-memory step
def _deficient(H, col) -> bool:
    """Whether the equilibrated inlier Gram matrix is (numerically) singular."""
    ev = np.linalg.eigvalsh(H / np.outer(col, col))
    return bool(ev[0] <= 1e-10 * max(ev[-1], 0.0) or ev[-1] <= 0)


def _subproblem(H, g, xi, col):
    """The factor ``L`` and target ``c`` of the Newton step's model in equilibrated
    coordinates ``u = col * z``: ``g^T (z - xi) + (z - xi)^T H (z - xi) / 2`` is
    ``||L u - c||^2 / 2`` up to a constant, with ``Ht = H / (col col^T)``, ``Ht + mu I =
    L^T L`` (``mu`` a Levenberg-Marquardt term where ``Ht`` is singular) and ``c = L (col
    xi) - L^-T (g / col)``."""
    p = H.shape[0]
    Ht = H / np.outer(col, col)
    mu = 0.0
    scale = max(float(np.trace(Ht)) / p, np.finfo(float).tiny)
    for _ in range(12):
        try:
            L = np.linalg.cholesky(Ht + mu * np.eye(p)).T
            if np.min(np.abs(np.diag(L))) > 1e-7 * math.sqrt(scale):
                break
        except np.linalg.LinAlgError:
            pass
        mu = max(mu * 100.0, 1e-12 * scale)
    # c = L u - L^-T g / col: the step's right-hand side from the gradient alone, so
    # near the optimum it is not the difference of two large numbers.
    c = L @ (col * xi) - scipy.linalg.solve_triangular(L, g / col, trans="T")
    return L, c


def _lasso_step(H, g, xi, lam, col, lasso):
    """Minimiser ``z`` of ``g^T (z - xi) + (z - xi)^T H (z - xi) / 2 + sum lam |z|``: the
    Lasso ``||L u - c||^2 / 2 + sum (lam / col) |u|`` of :func:`_subproblem`."""
    L, c = _subproblem(H, g, xi, col)
    return lasso(L, c, lam / col) / col


def _joint_step(hs, g, xi, lam, col, constraints, subproblem):
    """Minimiser ``Z`` (p, n) of ``sum_k [g_k^T (z_k - xi_k) + (z_k - xi_k)^T H_k (z_k -
    xi_k) / 2] + sum lam |Z|`` under ``constraints`` (on ``vec(Z)``): one Lasso over all
    equations, its design the block diagonal of the equations' factors
    (:func:`_subproblem`), the constraints' columns scaled to the equilibrated
    coordinates, solved in memory by ``subproblem(design, target, lam, constraints)``."""
    from ..core.constraints import LinearConstraints

    p, n = xi.shape
    parts = [_subproblem(hs[k], g[:, k], xi[:, k], col) for k in range(n)]
    scale = np.tile(col, n)  # u = scale * vec(Z)
    joint = LinearConstraints(
        p * n, 1, constraints.A_eq / scale, constraints.b_eq, constraints.A_ub / scale,
        constraints.b_ub,
    )  # fmt: skip
    u = subproblem(
        scipy.linalg.block_diag(*(L for L, _ in parts)),
        np.concatenate([c for _, c in parts]),
        (lam / col[:, None]).ravel(order="F"),
        joint,
    )
    return (np.asarray(u, dtype=float).ravel() / scale).reshape((p, n), order="F")


def _start(theta, y):
    """The blocks, the first pass's sums (:func:`_first`), and the columns' norms (zero
    norms as 1 for the equilibration, and as they are)."""
    theta, y = _blocks(theta, y)
    start = _reduce(_first, theta, y)
    col_sq = start["col_sq"]
    return theta, y, start, np.sqrt(np.where(col_sq > 0, col_sq, 1.0)), np.sqrt(col_sq)


def solve_chunked(
    theta,
    y,
    delta: np.ndarray,
    lam: np.ndarray,
    *,
    lasso,
    tol: float = 1e-8,
    max_iter: int = 50,
    progress: bool = False,
) -> ChunkedRun:
    """Solve every column of the Huber-Lasso on Dask arrays ``theta`` (m, p), ``y`` (m, n).

    ``delta`` (n,), ``lam`` (p, n).  Returns the coefficients, objective, relative KKT
    violation and duality gap per column (the in-memory certificate's definitions), and
    the passes over the data.  ``lasso(design, target, lam)`` solves the small Lasso of
    each Newton step in memory (``design`` p x p) and returns its coefficients.
    """
    from tqdm import tqdm

    theta, y, start, col, col_norms = _start(theta, y)
    p, n = theta.shape[1], y.shape[1]
    passes = 1
    xi = np.zeros((p, n))
    for k in range(n):  # least-squares (Lasso) start, from the Gram matrix
        xi[:, k] = _lasso_step(start["G"], -start["b"][:, k], np.zeros(p), lam[:, k], col, lasso)
    stats = _reduce(_stats, theta, y, xi, delta, True)
    passes += 1
    iterations = np.zeros(n, dtype=int)
    done = np.zeros(n, dtype=bool)
    bar = tqdm(total=max_iter, desc="chunked Newton", disable=not progress, leave=False)
    for _ in range(max_iter):
        kkt = kkt_from_gradient(xi, stats["g"], lam, col_norms, np.sqrt(stats["psi_sq"]))
        done = kkt <= tol
        if done.all():
            break
        d = np.zeros((p, n))
        deficient = [k for k in np.flatnonzero(~done) if _deficient(stats["H"][k], col)]
        if deficient:  # too few inliers to fix every term: the majoriser's (IRLS) step
            stats["M"] = _reduce(_stats, theta, y, xi, delta, False, True)["M"]
            passes += 1
        for k in np.flatnonzero(~done):
            H = stats["M"][k] if k in deficient else stats["H"][k]
            z = _lasso_step(H, -stats["g"][:, k], xi[:, k], lam[:, k], col, lasso)
            d[:, k] = z - xi[:, k]
            iterations[k] += 1
        trial = _reduce(_trial, theta, y, xi, d, delta, True)
        passes += 1
        pen0 = (lam * np.abs(xi)).sum(axis=0)
        f0 = stats["obj"] + pen0
        pen = np.stack([(lam * np.abs(xi + s * d)).sum(axis=0) for s in STEPS])  # STEPS[0] = 1
        f = trial["trial"] + pen
        decrease = np.einsum("pk,pk->k", -stats["g"], d) + pen[0] - pen0
        # Sums over many rows round at about 1e-13 of their size: a decrease below that
        # cannot be seen, and near the optimum the Newton step is exact (fixed inliers).
        slack = ROUNDING * np.abs(f0)
        armijo = ARMIJO * STEPS[:, None] * np.minimum(decrease, 0.0)[None, :]
        accept = f <= f0[None, :] + armijo + slack[None, :]
        step = np.zeros(n)
        for k in range(n):
            if done[k]:
                continue
            ok = np.flatnonzero(accept[:, k])
            if ok.size:
                step[k] = STEPS[ok[0]]
            elif f[:, k].min() <= f0[k]:
                step[k] = STEPS[int(np.argmin(f[:, k]))]
        if np.all(step[~done] == 1.0):
            xi = xi + d
            stats = trial["next"]
        else:
            xi = xi + step[None, :] * d
            stats = _reduce(_stats, theta, y, xi, delta, True)
            passes += 1
            if np.all(step[~done] == 0.0):
                break  # no decrease along the Newton directions: stalled
        bar.update(1)
    bar.close()
    psi_norm = np.sqrt(stats["psi_sq"])
    kkt = kkt_from_gradient(xi, stats["g"], lam, col_norms, psi_norm)
    obj = stats["obj"] + (lam * np.abs(xi)).sum(axis=0)
    gap = gap_from_sums(obj, stats["g"], lam, stats["y_psi"], psi_norm)
    converged = kkt <= tol
    messages = [
        "certified" if c else f"not certified after {it} steps (relative KKT {v:.1e})"
        for c, it, v in zip(converged, iterations, kkt, strict=True)
    ]
    return ChunkedRun(xi, obj, kkt, gap, converged, iterations, passes, messages)


def solve_chunked_constrained(
    theta,
    y,
    delta: np.ndarray,
    lam: np.ndarray,
    constraints,
    *,
    subproblem,
    tol: float = 1e-8,
    max_iter: int = 50,
    progress: bool = False,
    start=None,
) -> ChunkedRun:
    """The Huber-Lasso of every column at once under linear ``constraints`` across
    equations (a :class:`~robust_sindy.core.constraints.LinearConstraints` on
    ``vec(Xi)``), on Dask arrays ``theta`` (m, p), ``y`` (m, n).

    The passes are those of :func:`solve_chunked`; the step is one proximal Newton
    subproblem over all equations under the constraints (:func:`_joint_step`: the
    equations' quadratic models side by side, a Lasso under linear constraints solved
    in memory by ``subproblem(design, target, lam, constraints)``), first from the
    least-squares model (the Gram matrix), whose answer meets the constraints; every
    later point is on the segment between two such points, so it meets them too.  The
    step length is common to all equations (the constraints tie them), by Armijo on
    the total objective.  The certificate is the constrained one from sums over the
    rows (:func:`~robust_sindy.core.constraints.certificate_from_sums`): ``kkt`` holds
    each equation's stationarity violation with the multipliers' term, and the
    problem's constraint residual is in the messages.  Returns a :class:`ChunkedRun`
    whose ``gap`` is the problem's duality gap on every column, with the certificate as
    ``certificate``.  ``start`` (p, n), a point that meets the constraints (relative
    residual at most :data:`START_RESIDUAL`; e.g. the answer on a sample of the rows),
    replaces the least-squares start; a point that does not is not used.
    """
    from tqdm import tqdm

    from ..core.constraints import certificate_from_sums

    theta, y = _blocks(theta, y)
    p, n = theta.shape[1], y.shape[1]
    given = None if start is None else np.asarray(start, dtype=float).reshape(p, n)
    if given is not None and constraints.residual(given) <= START_RESIDUAL:
        xi = given.copy()  # the start's sums and the columns' norms in one pass
        stats = _reduce(_stats_and_norms, theta, y, xi, delta)
        passes = 1
        col_sq = stats["col_sq"]
        col = np.sqrt(np.where(col_sq > 0, col_sq, 1.0))
    else:
        theta, y, first, col, _ = _start(theta, y)
        col_sq = first["col_sq"]
        zero = np.zeros((p, n))
        xi = _joint_step([first["G"]] * n, -first["b"], zero, lam, col, constraints, subproblem)
        stats = _reduce(_stats, theta, y, xi, delta, True)
        passes = 2
    col_norms = np.sqrt(col_sq)
    steps = 0

    def certificate(stats, xi):
        obj = stats["obj"] + (lam * np.abs(xi)).sum(axis=0)
        return certificate_from_sums(
            xi, stats["g"], lam, col_norms, np.sqrt(stats["psi_sq"]), obj, stats["y_psi"],
            constraints,
        )  # fmt: skip

    bar = tqdm(total=max_iter, desc="chunked Newton (constrained)", disable=not progress,
               leave=False)  # fmt: skip
    cert = certificate(stats, xi)
    majorise = False
    for _ in range(max_iter):
        if cert.kkt <= tol:
            break
        deficient = [k for k in range(n) if majorise or _deficient(stats["H"][k], col)]
        if deficient:  # the majoriser's (IRLS) model: too few inliers, or a failed step
            stats["M"] = _reduce(_stats, theta, y, xi, delta, False, True)["M"]
            passes += 1
        hs = [stats["M"][k] if k in deficient else stats["H"][k] for k in range(n)]
        d = _joint_step(hs, -stats["g"], xi, lam, col, constraints, subproblem) - xi
        steps += 1
        trial = _reduce(_trial, theta, y, xi, d, delta, True)
        passes += 1
        pen0 = float((lam * np.abs(xi)).sum())
        f0 = float(stats["obj"].sum()) + pen0
        pen = np.array([(lam * np.abs(xi + s * d)).sum() for s in STEPS])
        f = trial["trial"].sum(axis=1) + pen
        decrease = float(np.einsum("pk,pk->", -stats["g"], d)) + pen[0] - pen0
        slack = ROUNDING * abs(f0)
        ok = np.flatnonzero(f <= f0 + ARMIJO * STEPS * min(decrease, 0.0) + slack)
        if ok.size:
            step = STEPS[ok[0]]
        elif f.min() <= f0:
            step = STEPS[int(np.argmin(f))]
        elif not majorise:
            # The inliers' model overshoots far from the optimum (many residuals beyond
            # delta, a step that moves them all): the majoriser's step decreases the
            # objective, so it is taken until a Newton step is accepted again.
            majorise = True
            continue
        else:
            break  # no decrease along the majoriser's direction either: stalled
        majorise = False
        if step == 1.0:
            xi, stats = xi + d, trial["next"]
        else:
            xi = xi + step * d
            stats = _reduce(_stats, theta, y, xi, delta, True)
            passes += 1
        cert = certificate(stats, xi)
        bar.update(1)
    bar.close()
    kkt = np.maximum(cert.column_kkt, cert.feasibility)
    converged = np.full(n, cert.kkt <= tol)
    status = (
        "certified"
        if cert.kkt <= tol
        else f"not certified after {steps} steps (relative stationarity "
        f"{cert.stationarity:.1e}, constraint residual {cert.feasibility:.1e})"
    )
    run = ChunkedRun(
        xi, cert.column_objective, kkt, np.full(n, cert.gap), converged,
        np.full(n, steps), passes, [status] * n,
    )  # fmt: skip
    run.certificate = cert
    return run
