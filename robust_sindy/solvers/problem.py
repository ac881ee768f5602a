"""What the solvers share: the prepared library, their options and constants, their output.

* :class:`Prepared` (:func:`prepare`) -- the library's nonzero columns, equilibrated
  (:class:`ScaledColumns`, never copied), their Gram matrix and its Cholesky factor:
  computed once from ``Theta`` and reused by every column, every point of a ``lam``
  path and every solver;
* :data:`DEFAULT_OPTIONS` -- the fast path's options; :data:`PAPER_OPTIONS` the paper's;
* :class:`SolverOutput` -- what every solver returns to :func:`robust_sindy.fit`;
* :func:`shared_preparation` -- a block whose fits of the same library array share its
  preparation and the Newton iteration's inlier Gram matrices.
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from ..core.certificates import column_norms

__all__ = [
    "DEFAULT_OPTIONS",
    "KERNEL_WORK",
    "PAPER_OPTIONS",
    "Prepared",
    "ScaledColumns",
    "SolverOutput",
    "column_objective",
    "preparations",
    "prepare",
    "shared_preparation",
    "solve_sym",
    "target_scale",
]


@dataclass
class SolverOutput:
    """Raw output of one solver run on all target columns.

    ``coef`` is (p, n) in the caller's units.  ``converged`` is the solver's own
    verdict per column; :func:`robust_sindy.fit` combines it with the
    solver-independent certificate before reporting convergence.
    """

    coef: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    messages: list[str]
    info: dict = field(default_factory=dict)


EIG_CUT = 1e-11  # relative eigenvalue cut of the Newton systems


MAX_STEP = 2.0**20  # longest line-search step


ARMIJO = 1e-4


LM = 1e-2


DIRECT_GRAM = 0.5  # form M from the inlier rows when outliers carry this much of a column


#: The compiled iteration works one column at a time: it is the faster one while a
#: step's NumPy calls outweigh the passes over the library, up to about this ``m p k``
#: (see the design notes); the batched NumPy steps, whose passes serve every column at
#: once, take the larger problems.
KERNEL_WORK = 8e5


_ROWS = 8192  # rows per chunk where the equilibrated library is formed piecewise


class ScaledColumns:
    """``A = Theta[:, nz] / scale`` as an operator: products and row slices on demand,
    ``Theta`` never copied (the solvers' extra memory stays a few m x n arrays).

    ``A @ x`` is ``Theta (x / scale)``; ``A.T @ v`` is ``(Theta^T (v c)) / (scale c)``
    with ``c = 1 / max|Theta|`` (no overflow for a library of order 1e300); ``A[rows]``
    forms those rows.
    """

    def __init__(self, theta: np.ndarray, nz: np.ndarray, scale: np.ndarray):
        self.theta = theta if nz.all() else theta[:, nz]
        self.scale = scale
        top = float(np.max(np.abs(self.theta))) if self.theta.size else 1.0
        self._c = 1.0 / top if 0 < top < np.inf else 1.0
        self.shape = self.theta.shape

    @property
    def T(self) -> _Transposed:
        # Made on demand: a stored back-reference would make a cycle, and the library
        # (a copy of the samples fitted) would wait for the cyclic garbage collector.
        return _Transposed(self)

    def __matmul__(self, x):
        if x.ndim == 1:
            return self.theta @ (x / self.scale)
        # Column-major (m, k): every elementwise operation and sum over the samples
        # then runs along contiguous memory (with few target columns, several times
        # faster than along rows of length k).
        return ((x / self.scale[:, None]).T @ self.theta.T).T

    def __getitem__(self, rows):
        return self.theta[rows] / self.scale

    def block(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``A[rows][:, cols]`` (integer arrays), without forming the rows' other
        entries."""
        return self.theta[np.ix_(rows, cols)] / self.scale[cols]

    def gram(self) -> np.ndarray:
        """``A^T A``, from row chunks of ``A``."""
        G = np.zeros((self.shape[1], self.shape[1]))
        for lo in range(0, self.shape[0], _ROWS):
            block = self[lo : lo + _ROWS]
            G += block.T @ block
        return G


class _Transposed:
    def __init__(self, op: ScaledColumns):
        self.op = op

    def __matmul__(self, v):
        op = self.op
        out = op.theta.T @ (v * op._c)
        return out / ((op.scale * op._c)[:, None] if out.ndim == 2 else op.scale * op._c)


@dataclass
class Prepared:
    """What the solvers compute from ``Theta`` alone (reusable along a path)."""

    nz: np.ndarray  # nonzero columns of Theta
    scale: np.ndarray  # their equilibration scales
    A: ScaledColumns  # Theta[:, nz] / scale, as an operator
    G: np.ndarray  # A^T A
    a_norms: np.ndarray
    lipschitz: float
    equilibrate: bool
    kappa: float
    _factor: tuple | None = None
    #: What the Newton iteration keeps from one fit to the next (inside
    #: :func:`shared_preparation` only; None elsewhere).
    carry: dict | None = None

    def condition(self) -> float:
        """2-norm condition number of the equilibrated library, from its Gram matrix (whose
        rounding caps the estimate near ``1e8``: beyond that it is a lower bound)."""
        w = np.linalg.eigvalsh(self.G) if self.G.size else np.ones(1)
        return float(np.sqrt(w[-1] / w[0])) if w[0] > 0 else np.inf

    @property
    def factor(self) -> tuple:
        """Cholesky factor of ``G + kappa I`` (the ADMM's xi-update), on first use."""
        if self._factor is None:
            M = self.G + self.kappa * np.eye(self.G.shape[0])
            self._factor = scipy.linalg.cho_factor(M, check_finite=False)
        return self._factor


_SHARED: ContextVar[dict | None] = ContextVar("robust_sindy_shared_preparation", default=None)


@contextlib.contextmanager
def shared_preparation(start: dict | None = None):
    """Within the block, the fast path's fits of the same library array (the same
    object, not modified inside the block) share its preparation: the equilibration and
    Gram matrix are formed once, and the Newton iteration's inlier Gram matrices carry
    over from one fit to the next, updated by the samples that changed sides (a pilot's
    fits of one set of samples at successive thresholds).  Per thread (a context
    variable): fits in other threads prepare their own, or start from the same
    preparations ``start`` (:func:`preparations`), each block with its own inlier Gram
    matrices."""
    own = {key: (theta, replace(p, carry={})) for key, (theta, p) in (start or {}).items()}
    token = _SHARED.set(own)
    try:
        yield
    finally:
        _SHARED.reset(token)


def preparations(theta: np.ndarray, *, equilibrate: bool = True, kappa: float = 1.0) -> dict:
    """The preparation of ``theta`` (:func:`prepare`), formed once, for blocks of
    :func:`shared_preparation` in several threads to start from."""
    return {_key(theta, equilibrate, kappa): (theta, _prepare(theta, equilibrate, kappa))}


def _key(theta, equilibrate, kappa) -> tuple:
    return (id(theta), bool(equilibrate), float(kappa))


def prepare(theta: np.ndarray, *, equilibrate: bool = True, kappa: float = 1.0) -> Prepared:
    """Equilibrate ``theta`` and form its Gram matrix once (pass as ``prepared``); inside
    :func:`shared_preparation`, once per array for the whole block."""
    shared = _SHARED.get()
    key = _key(theta, equilibrate, kappa)
    if shared is not None and key in shared and shared[key][0] is theta:
        return shared[key][1]
    prepared = _prepare(theta, equilibrate, kappa)
    if shared is not None:
        prepared.carry = {}
        shared[key] = (theta, prepared)  # the reference keeps the id from being reused
    return prepared


def _prepare(theta: np.ndarray, equilibrate: bool, kappa: float) -> Prepared:
    if theta.size <= KERNEL_WORK and not theta.flags.c_contiguous:
        # The compiled iteration reads the library by rows: a small one in another
        # layout (a selection of columns, theta[:, keep], is column-major) is copied
        # once, so that the refits of the selection stage run compiled too.
        theta = np.ascontiguousarray(theta)
    norms = column_norms(theta)  # no overflow for entries near 1e200
    nz = norms > 0
    scale = norms[nz] if equilibrate else np.ones(np.count_nonzero(nz))
    A = ScaledColumns(theta, nz, scale)
    G = A.gram()
    lipschitz = max(float(np.linalg.eigvalsh(G)[-1]), np.finfo(float).tiny) if G.size else 1.0
    a_norms = norms[nz] / scale
    return Prepared(nz, scale, A, G, a_norms, lipschitz, equilibrate, kappa)


def solve_sym(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimum-norm solution of a symmetric PSD system, eigenvalues below ``1e-11`` of
    the largest treated as zero (a Cholesky factor of a numerically singular Gram matrix
    "succeeds" with a tiny pivot and returns a huge, meaningless step)."""
    w, V = np.linalg.eigh(M)
    keep = w > EIG_CUT * max(w[-1], 0.0) if w.size else w.astype(bool)
    inv = 1.0 / w[keep]
    return V[:, keep] @ ((V[:, keep].T @ b) * (inv if b.ndim == 1 else inv[:, None]))


#: Rank updates of the inlier Gram matrices: at most this fraction of the samples may
#: change sides, and the summed squares of the entries of the rows ever added or
#: removed may reach at most ``DRIFT`` times the updated diagonal, coordinate by
#: coordinate (the rounding updates leave is ``eps`` times those sums); otherwise the
#: matrix is formed afresh.
UPDATE_ROWS, DRIFT = 0.05, 1e4


def column_objective(r, x, delta, lam):
    """Objective per column with two m x n temporaries (``huber`` as ``c (r - c / 2)``)."""
    c = np.clip(r, -delta, delta)
    tmp = np.multiply(c, 0.5)
    np.subtract(r, tmp, out=tmp)
    tmp *= c
    return tmp.sum(axis=0) + (lam * np.abs(x)).sum(axis=0)


def target_scale(y, delta) -> np.ndarray:
    """Exact per-column rescaling ``y / c``, ``delta / c``, ``lam / c`` (solution
    ``xi / c``): ``c`` is max|y| when the Huber threshold is larger (the rms of y for the
    squared loss), else the geometric mean of the threshold and max|y|, so that neither
    ``y / c`` nor ``delta / c`` leaves the floating-point range (delta from 1e-300 to
    1e300 times max|y|)."""
    n = y.shape[1]
    ymax = np.max(np.abs(y), axis=0) if y.shape[0] else np.zeros(n)
    with np.errstate(over="ignore", under="ignore"):
        c = np.where(
            np.isfinite(delta),
            np.where(delta >= ymax, ymax, np.sqrt(delta) * np.sqrt(ymax)),
            column_norms(y) / np.sqrt(max(y.shape[0], 1)),
        )
    return np.where((c > 0) & np.isfinite(c), c, 1.0)


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
