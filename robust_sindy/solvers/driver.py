"""The fast path: the batched Newton method first, the ADMM for any column it cannot certify.

:func:`solve` fits every target column by the active-set Newton method
(:mod:`~robust_sindy.solvers.newton`), compiled on small problems
(:mod:`~robust_sindy.solvers._kernel`), and hands the columns it cannot certify to the
corrected ADMM (:mod:`~robust_sindy.solvers.admm`), warm-started from the Newton point.
:func:`solve_path` walks a decreasing ``lam`` grid with the compiled iteration.

On small problems (``m p k`` up to :data:`~robust_sindy.solvers.problem.KERNEL_WORK`,
e.g. a thousand samples of a library of 35 terms and three targets, and every fit along
a path at that size) a step's NumPy calls cost more than its passes over ``Theta``:
there the compiled iteration (Numba, column by column, the columns side by side on the
machine's cores: :mod:`robust_sindy.core.threads`) takes the steps first, and the
NumPy iteration solves any column it could not certify from the same start.
``USE_KERNEL = False`` switches it off.  Along a ``lam`` path the compiled iteration
walks the whole grid, each point starting from the last one's solution with its last
pass (residuals, gradient, inliers: only the objective and the KKT violation depend on
``lam``) and its inlier Gram matrix, updated by the samples that changed sides.
"""

from __future__ import annotations

import numpy as np

from ..core.certificates import accept_within_floor, certify
from ..core.losses import huber_psi
from ..core.threads import map_threads
from . import _kernel
from .admm import solve_admm
from .newton import newton
from .problem import (
    DEFAULT_OPTIONS,
    KERNEL_WORK,
    Prepared,
    SolverOutput,
    prepare,
    solve_sym,
    target_scale,
)

__all__ = [
    "FIRST_STEPS",
    "KERNEL_STEPS",
    "USE_KERNEL",
    "WARM_STEPS",
    "column_groups",
    "solve",
    "solve_path",
    "use_kernel",
]

FIRST_STEPS = 25  # the fast path's own Newton run may take 25x newton_steps


#: Whether the compiled iteration (:mod:`robust_sindy.solvers._kernel`) takes the steps
#: first, and its step budget per column.
USE_KERNEL, KERNEL_STEPS = True, 50

#: Step budget of the NumPy iteration from the previous point for a path point the
#: compiled iteration could not certify; it also stops where its violation has not
#: halved in ``_kernel.STALL`` steps (then a cold fit).
WARM_STEPS = 100


def use_kernel(A, columns: int) -> bool:
    """Whether :func:`solve` runs the compiled iteration first."""
    m, p = A.shape
    return (
        USE_KERNEL
        and _kernel.usable()
        and A.theta.flags.c_contiguous
        and m * p * columns <= KERNEL_WORK
    )


def column_groups(k: int, shape) -> list[np.ndarray]:
    """The ``k`` target columns of fits of every term of a library of ``shape`` (m, p)
    in the groups the batched Newton iteration takes them in (at most about the
    library's own memory of inlier Gram matrices per group).  Several fits of the same
    columns inside :func:`~robust_sindy.solvers.problem.shared_preparation`, run group
    by group, carry each group's matrices from one fit to the next; run fit by fit, the
    next group's let the last one's go."""
    return _newton_groups(np.arange(k), np.ones((shape[1], k)), shape)


def _newton_groups(columns: np.ndarray, start: np.ndarray, shape) -> list[np.ndarray]:
    """``columns`` in groups for the batched Newton iteration, whose inlier Gram
    matrices take (columns) x w^2 for working sets of w terms: at most about the
    library's own memory (``shape`` (m, p)) per group, w taken as the most nonzero
    coefficients of a column of ``start`` (p, k).  Columns are solved independently,
    so the groups change nothing but the memory: an unpenalised fit of 40 equations
    on 861 terms would otherwise hold 40 matrices of 861^2 at once, three times the
    library at 12 000 samples.  :func:`solve` runs the groups side by side on the
    machine's cores (:func:`~robust_sindy.core.threads.map_threads`), so that up to
    that many groups' matrices are held at once."""
    if columns.size == 0:
        return []
    w = max(int(np.count_nonzero(start[:, columns], axis=0).max()), 1)
    size = max(1, (shape[0] * shape[1]) // (w * w))
    # As few groups as that allows, of nearly equal sizes (which spreads them evenly
    # over a cluster's workers: robust_sindy.core.cluster).
    return np.array_split(columns, -(-columns.size // size))


def _names(y: np.ndarray) -> list:
    """Names of the target columns ``y`` (m, k) that stay the same from one fit to the
    next: hashes of their samples' bytes.  The Newton iteration's Gram matrices kept in
    ``Prepared.carry`` are looked up by them; any of them is valid for every column (it
    is the library's, updated to the column's inliers), so a collision costs only the
    update's size."""
    return [hash(np.ascontiguousarray(y[:, k]).tobytes()) for k in range(y.shape[1])]


def solve(theta, y, delta, lam, *, prepared: Prepared | None = None, **options):
    """The fast path: batched Newton on all columns, ADMM for any it cannot certify.

    Takes the options of :func:`robust_sindy.solvers.admm.solve_admm` (the same
    ``DEFAULT_OPTIONS``).  ``polish=False`` (as in the paper's settings) means no
    Newton at all: plain ADMM.  Returns a :class:`SolverOutput` in the caller's units;
    ``info`` has ``newton_steps`` per column, ``passes`` (over ``Theta`` by the Newton
    run), ``fallback`` (columns handed to the ADMM), ``stalled`` (columns where the
    Newton steps stopped at the floating-point floor) and ``floor``: for an uncertified
    column, the relative KKT violation that the rounding of its residuals alone can leave
    (:func:`robust_sindy.core.certificates.rounding_floor`, at the returned point; NaN
    for the columns Newton certified and those the ADMM then solved).  An uncertified
    column whose violation is within its floor is returned as converged (certified to
    the floating-point floor, its message says so) without the ADMM.
    """
    opts = {**DEFAULT_OPTIONS, **options}
    if not opts["polish"]:
        return solve_admm(theta, y, delta, lam, prepared=prepared, **opts)
    m, p = theta.shape
    n = y.shape[1]
    lam = np.broadcast_to(lam, (p, n)).astype(float)
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (n,))
    equilibrate, kappa = opts["equilibrate"], opts["kappa"]
    if prepared is None or prepared.equilibrate != equilibrate or prepared.kappa != kappa:
        prepared = prepare(theta, equilibrate=equilibrate, kappa=kappa)
    nz, scale, A = prepared.nz, prepared.scale, prepared.A
    c = target_scale(y, delta)
    ys, ds = np.divide(y, c, out=np.empty(y.shape, order="F")), delta / c  # column-major
    lam_s = lam[nz] / scale[:, None] / c
    tol = opts["tol"]
    messages = [""] * n
    x = np.zeros((A.shape[1], n))
    # xi = 0 is optimal iff |A^T psi(y)| <= lam (lam >= lambda_max): exact, one pass.
    zero = np.all(np.abs(A.T @ huber_psi(ys, ds)) <= lam_s * (1 + 1e-10), axis=0)
    for k in np.flatnonzero(zero):
        messages[k] = "zero is optimal (lam >= lambda_max)"
    todo = np.flatnonzero(~zero)
    steps = np.zeros(n, dtype=int)
    converged = zero.copy()
    stalled = np.zeros(n, dtype=bool)
    passes = 1
    if todo.size:
        warm = opts["warm_start"]
        if warm is not None:
            start = warm[0][nz][:, todo] * scale[:, None] / c[todo]
        else:
            start = solve_sym(prepared.G, A.T @ ys[:, todo])
            passes += 1
        budget = FIRST_STEPS * opts["newton_steps"]
        y_todo = np.asfortranarray(ys[:, todo])
        certified = np.zeros(todo.size, dtype=bool)
        steps_todo = np.zeros(todo.size, dtype=int)
        kkt_last = np.full(todo.size, np.nan)
        run_stalled = np.zeros(todo.size, dtype=bool)
        ran = None
        if use_kernel(A, todo.size):
            # The compiled iteration takes the steps; the NumPy one below solves any
            # column it could not certify, from the same start (the point where the
            # kernel stopped, on a piece with a singular block, can be a poor one: on
            # the drone's path it cost the NumPy iteration hundreds of steps).
            ran = _kernel.newton_kernel(
                A.theta,
                A.scale,
                prepared.G,
                y_todo,
                ds[todo],
                lam_s[:, todo],
                start,
                prepared.a_norms,
                prepared.lipschitz,
                tol,
                max_steps=min(budget, KERNEL_STEPS),
            )
        if ran is not None:
            found, status, steps_todo, kernel_passes = ran
            passes += kernel_passes
            certified = status == 0
            x[:, todo[certified]] = found[:, certified]
        groups = _newton_groups(np.flatnonzero(~certified), start, A.shape)

        def run_group(rest):
            return newton(
                prepared,
                y_todo[:, rest],
                ds[todo[rest]],
                lam_s[:, todo[rest]],
                start[:, rest],
                max_steps=budget,
                tol=tol,
                names=None if prepared.carry is None else _names(y[:, todo[rest]]),
            )

        # The groups side by side on the machine's cores, each run as it would be alone
        # (the same numbers); one after another where they share the carried inlier Gram
        # matrices of prepared.carry (one cache, not for several threads at once).
        if prepared.carry is None:
            runs = map_threads(run_group, groups)
        else:
            runs = [run_group(rest) for rest in groups]
        for rest, run in zip(groups, runs, strict=True):
            x[:, todo[rest]] = run.x
            certified[rest], steps_todo[rest] = run.certified, steps_todo[rest] + run.steps
            kkt_last[rest], run_stalled[rest] = run.kkt, run.stalled
            passes += run.passes
        converged[todo], steps[todo], stalled[todo] = certified, steps_todo, run_stalled
        for i, k in enumerate(todo):
            if certified[i]:
                messages[k] = f"certified by the active-set Newton method after {steps[k]} steps"
            elif run_stalled[i]:
                messages[k] = (
                    f"stalled at relative KKT {kkt_last[i]:.1e} after {steps[k]} Newton steps: "
                    "the objective no longer changes in floating point (an ill-conditioned "
                    f"library: condition number {prepared.condition():.1e} or more)"
                )
    coef = np.zeros((p, n))
    coef[nz] = x * c / scale[:, None]
    iterations = np.zeros(n, dtype=int)
    rho = np.full(n, np.nan)
    # A threshold below the floating-point resolution of the residuals leaves only
    # least-absolute-deviation points, whose KKT conditions no method can resolve (only
    # an exact fit, which Newton certifies at once, could be certified): no fallback.
    resolution = 16 * (p + 1) * np.finfo(float).eps * (np.max(np.abs(y), axis=0) if m else 0.0)
    unresolvable = ~converged & (delta < resolution)
    for k in np.flatnonzero(unresolvable):
        messages[k] = (
            f"not certified: delta = {delta[k]:.1e} is below the floating-point resolution "
            f"of the residuals ({resolution[k]:.1e}), where the Huber fit is a "
            "least-absolute-deviation fit whose optimality cannot be resolved; returning "
            "the Newton point"
        )
    stalled |= unresolvable
    # A stall is the floor of the Gram-based steps, not necessarily of the problem: the
    # ADMM (whose finish restarts from its own iterates) still gets its chance, unless
    # the violation is within what the rounding of the residuals alone can leave (a
    # nearly exact fit whose terms cancel; checked for every uncertified column, stalled
    # or out of steps): that is the floor of the problem, which no method resolves
    # further (on such refits the ADMM spent its 20 000 iterations and ended no
    # closer).  The column is then certified to that floor.
    floor = np.full(n, np.nan)
    stuck = np.flatnonzero(~converged & ~unresolvable)
    if stuck.size:
        ys_, ds_, xs_ = y[:, stuck], delta[stuck], coef[:, stuck]
        cert = certify(theta, ys_, xs_, ds_, lam[:, stuck])
        ok, floor[stuck] = accept_within_floor(
            theta, ys_, xs_, ds_, cert.kkt, np.zeros(stuck.size, dtype=bool), cert.residual
        )
        passes += 2
        for i, k in enumerate(stuck):
            if ok[i]:
                converged[k] = True
                messages[k] = (
                    f"certified to the floating-point floor after {steps[k]} Newton steps: "
                    f"relative KKT {cert.kkt[i]:.1e} is within what the rounding of the "
                    f"residuals can leave ({floor[k]:.1e})"
                )
    fallback = ~converged & ~unresolvable
    if fallback.any():
        j = np.flatnonzero(fallback)
        rest = {k: v for k, v in opts.items() if k != "warm_start"}
        out = solve_admm(
            theta,
            y[:, j],
            delta[j],
            lam[:, j],
            prepared=prepared,
            warm_start=(coef[:, j], None),
            **rest,
        )
        coef[:, j], converged[j], iterations[j] = out.coef, out.converged, out.iterations
        rho[j] = out.info["rho"]
        floor[j] = np.nan  # the ADMM moved these columns: no floor at its point
        steps[j] += out.info["newton_steps"]
        for i, k in enumerate(j):
            messages[k] = f"Newton uncertified after {steps[k]} steps; ADMM: {out.messages[i]}"
    return SolverOutput(
        coef=coef,
        iterations=iterations,
        converged=converged,
        messages=messages,
        info={
            "newton_steps": steps,
            "passes": passes,
            "fallback": fallback,
            "stalled": stalled,
            "floor": floor,
            "rho": rho,
        },
    )


def solve_path(theta, y, delta, grid, *, prepared: Prepared, **options):
    """The fast path along a decreasing ``lam`` grid (L, n), every point warm-started.

    The first point is a :func:`solve` fit; from there the compiled iteration
    (:func:`robust_sindy.solvers._kernel.newton_path_kernel`) walks each column down its
    grid, every point starting from the last one's solution, the residuals and gradient
    of its last pass and its inlier Gram matrix (a warm start is otherwise one pass and
    one Gram matrix more per point).  A point the kernel cannot certify is tried again
    from the previous point with a fresh Gram matrix, then (unless the previous point
    has no more samples inside ``delta`` than nonzero coefficients) by the NumPy
    iteration from the previous point on a budget of ``WARM_STEPS``, else solved by
    :func:`solve` as a cold fit (least-squares start; NumPy iteration, then
    ADMM), and the kernel goes on from there.  Takes the options of :func:`solve` (not
    ``warm_start``).

    Returns ``(coef, converged, info)``: ``coef`` (L, p, n) in the caller's units,
    ``converged`` (L, n) the solvers' own verdicts (the caller certifies), ``info``
    with ``newton_steps`` (L, n), ``passes`` over ``Theta``, ``retried`` (points the
    kernel certified once more from the previous point), ``from_previous`` (L, n), the
    points the NumPy iteration certified from the previous point, and ``handed_over``
    (points solved by :func:`solve` after the first); or ``None``
    where the compiled iteration does not apply (``polish=False``, a problem too large
    for it, or Numba unavailable): then the caller solves point by point.
    """
    opts = {**DEFAULT_OPTIONS, **options, "warm_start": None}
    A = prepared.A
    L, n = grid.shape
    if (
        not opts["polish"]
        or prepared.equilibrate != opts["equilibrate"]
        or prepared.kappa != opts["kappa"]
        or not use_kernel(A, n)
    ):
        return None
    p = theta.shape[1]
    nz, scale = np.flatnonzero(prepared.nz), prepared.scale
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (n,))
    coef = np.zeros((L, p, n))
    converged = np.zeros((L, n), dtype=bool)
    steps = np.zeros((L, n), dtype=int)
    from_previous = np.zeros((L, n), dtype=bool)
    out = solve(theta, y, delta, grid[0], prepared=prepared, **opts)
    coef[0], converged[0], steps[0] = out.coef, out.converged, out.info["newton_steps"]
    passes, handed_over, retried = out.info["passes"], 0, 0
    c = target_scale(y, delta)
    ys, ds = np.divide(y, c, out=np.empty(y.shape, order="F")), delta / c
    lam_s = grid[:, None, :] / scale[None, :, None] / c[None, None, :]  # (L, p_nz, n)
    x = coef[0][nz] * scale[:, None] / c
    first = np.ones(n, dtype=np.int64)
    budget = min(FIRST_STEPS * opts["newton_steps"], KERNEL_STEPS)
    while (first < L).any():
        cols = np.flatnonzero(first < L)
        ran = _kernel.newton_path_kernel(
            A.theta,
            A.scale,
            prepared.G,
            ys[:, cols],
            ds[cols],
            lam_s[:, :, cols],
            x[:, cols],
            first[cols],
            prepared.a_norms,
            prepared.lipschitz,
            opts["tol"],
            budget,
        )
        if ran is None:
            return None  # Numba cannot compile here: the caller's point-by-point loop
        found, _, kernel_steps, stop, kernel_passes = ran
        passes += kernel_passes
        for a, k in enumerate(cols):
            done = np.arange(first[k], stop[a])
            coef[done[:, None], nz[None, :], k] = found[done, :, a] * (c[k] / scale)[None, :]
            converged[done, k] = True
            steps[done, k] = kernel_steps[done, a]
            if stop[a] == L:
                first[k] = L
                continue
            # Once more from the previous point with a fresh Gram matrix (the walk's
            # updated one can lead a hard point astray).
            i = int(stop[a])
            previous = coef[i - 1][nz, k][:, None] * (scale / c[k])[:, None]
            again = _kernel.newton_kernel(
                A.theta, A.scale, prepared.G, ys[:, [k]], ds[[k]], lam_s[i][:, [k]],
                previous, prepared.a_norms, prepared.lipschitz, opts["tol"], budget,
            )  # fmt: skip
            if again is not None:
                x_again, status_again, steps_again, passes_again = again
                passes += passes_again
                steps[i, k] = kernel_steps[i, a] + steps_again[0]
                if status_again[0] == 0:
                    coef[i, nz, k] = x_again[:, 0] * c[k] / scale
                    converged[i, k] = True
                    x[:, k] = x_again[:, 0]
                    first[k] = i + 1
                    retried += 1
                    continue
            # Then, unless the previous point is a least-absolute-deviation vertex (no
            # more samples inside delta than nonzero coefficients: the support's inlier
            # system is singular, and from there the NumPy iteration crawled for
            # hundreds of steps where a cold fit took a few dozen), the NumPy iteration
            # from the previous point on a short budget: it has eigenvalue cuts and
            # steps from the rows, which the kernel lacks (on the weak form's rows the
            # kernel stopped after 20 steps without halving its violation where this
            # certified in 1 to 50). Else, or if it fails, a cold fit.
            inside = np.abs(ys[:, k] - A @ previous[:, 0]) <= ds[k]
            passes += 1
            if np.count_nonzero(inside) > np.count_nonzero(previous):
                run = newton(
                    prepared, ys[:, [k]], ds[[k]], lam_s[i][:, [k]], previous,
                    max_steps=WARM_STEPS, tol=opts["tol"], patience=_kernel.STALL,
                )  # fmt: skip
                passes += run.passes
                steps[i, k] += run.steps[0]
                if run.certified[0]:
                    coef[i, nz, k] = run.x[:, 0] * c[k] / scale
                    converged[i, k] = from_previous[i, k] = True
                    x[:, k] = run.x[:, 0]
                    first[k] = i + 1
                    continue
            one = solve(theta, y[:, [k]], delta[[k]], grid[i, [k]], prepared=prepared, **opts)
            coef[i, :, k], converged[i, k] = one.coef[:, 0], one.converged[0]
            steps[i, k] += one.info["newton_steps"][0]
            passes += one.info["passes"]
            handed_over += 1
            x[:, k] = coef[i][nz, k] * scale / c[k]
            first[k] = i + 1
    info = {
        "newton_steps": steps,
        "passes": passes,
        "retried": retried,
        "from_previous": from_previous,
        "handed_over": handed_over,
    }
    return coef, converged, info
