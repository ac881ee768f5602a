"""Linear constraints on the whole coefficient matrix, and their certificate.

The coefficients ``Xi`` (p terms x n equations) enter the constraints as
``x = vec(Xi)``, column by column (equation by equation): ``x[k * p + j] = Xi[j, k]``,
which is ``Xi.ravel(order="F")`` (``cvxpy.vec`` has the same order).  The constrained
problem is

.. math::

    \\min_{\\Xi} \\sum_k \\sum_i H_{\\delta_k}(\\dot X_{ik} - \\Theta_i \\xi_k)
    + \\sum_{jk} \\lambda_{jk} |\\Xi_{jk}|
    \\quad \\text{s.t.} \\quad A_{eq} x = b_{eq}, \\; A_{ub} x \\le b_{ub} .

With ``g = vec(Theta^T psi_delta(R))`` (``R = Xdot - Theta Xi``), ``Xi`` is optimal iff
there are multipliers ``nu`` and ``mu >= 0`` with ``mu_i = 0`` for every inequality
that is not active, such that ``h = g - A_eq^T nu - A_ub^T mu`` satisfies the
conditions of the unconstrained problem with ``h`` for ``g`` (``h_j = lam_j sign(x_j)``
on the support, ``|h_j| <= lam_j`` off it), and ``x`` is feasible.

:func:`constrained_certificate` finds the multipliers that fit those conditions best
for any candidate (so it certifies the answer of any solver alike), and reports the
relative stationarity violation (the unconstrained certificate's measure, with ``h``),
the relative constraint residual and a duality gap: ``u = s psi``, ``(s nu, s mu)``
with ``s = min(1, min_j lam_j / |h_j|)`` is feasible for the Lagrange dual
``max y^T u - ||u||^2 / 2 - b_eq^T nu - b_ub^T mu`` (``|u| <= delta``, ``mu >= 0``,
``|vec(Theta^T U) - A_eq^T nu - A_ub^T mu| <= lam``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from .certificates import certify, column_norms, kkt_from_gradient

__all__ = [
    "ConstrainedCertificate",
    "LinearConstraints",
    "certificate_from_sums",
    "constrained_certificate",
]

#: Relative slack below which an inequality counts as active (its multiplier free).
ACTIVE_TOL = 1e-9


def _matrix(a, name: str, cols: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return np.zeros((0, cols))
    if a.ndim != 2 or a.shape[1] != cols:
        raise ValueError(f"{name} must have shape (r, {cols}); got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def _vector(b, name: str, rows: int) -> np.ndarray:
    b = np.asarray(b, dtype=float).reshape(-1)
    if b.shape != (rows,):
        raise ValueError(f"{name} must have shape ({rows},); got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{name} contains NaN or inf")
    return b


@dataclass(frozen=True)
class LinearConstraints:
    """``A_eq vec(Xi) = b_eq`` and ``A_ub vec(Xi) <= b_ub`` for ``Xi`` of shape
    ``(n_terms, n_equations)``, ``vec`` column by column (see the module docstring).

    Build them with the helpers of :mod:`robust_sindy.constraints`, which read the
    library's feature names, and combine them with ``+``.

    Attributes
    ----------
    n_terms, n_equations : int
    A_eq : ndarray (r_eq, n_terms * n_equations)
    b_eq : ndarray (r_eq,)
    A_ub : ndarray (r_ub, n_terms * n_equations)
    b_ub : ndarray (r_ub,)
    labels_eq, labels_ub : tuple of str
        What each row says (for reports and errors).
    """

    n_terms: int
    n_equations: int
    A_eq: np.ndarray = None
    b_eq: np.ndarray = None
    A_ub: np.ndarray = None
    b_ub: np.ndarray = None
    labels_eq: tuple = field(default=())
    labels_ub: tuple = field(default=())

    def __post_init__(self):
        p, n = int(self.n_terms), int(self.n_equations)
        if p < 1 or n < 1:
            raise ValueError(f"n_terms and n_equations must be >= 1; got {p}, {n}")
        cols = p * n
        a_eq = _matrix([] if self.A_eq is None else self.A_eq, "A_eq", cols)
        a_ub = _matrix([] if self.A_ub is None else self.A_ub, "A_ub", cols)
        b_eq = _vector([] if self.b_eq is None else self.b_eq, "b_eq", a_eq.shape[0])
        b_ub = _vector([] if self.b_ub is None else self.b_ub, "b_ub", a_ub.shape[0])
        labels_eq = tuple(self.labels_eq) or tuple(f"equality {i}" for i in range(len(b_eq)))
        labels_ub = tuple(self.labels_ub) or tuple(f"inequality {i}" for i in range(len(b_ub)))
        if len(labels_eq) != len(b_eq) or len(labels_ub) != len(b_ub):
            raise ValueError("labels_eq and labels_ub must name every row")
        for name, value in (
            ("n_terms", p), ("n_equations", n), ("A_eq", a_eq), ("b_eq", b_eq), ("A_ub", a_ub),
            ("b_ub", b_ub), ("labels_eq", labels_eq), ("labels_ub", labels_ub),
        ):  # fmt: skip
            object.__setattr__(self, name, value)

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_terms, n_equations)``: the shape of the coefficient matrix."""
        return self.n_terms, self.n_equations

    @property
    def n_rows(self) -> int:
        return self.A_eq.shape[0] + self.A_ub.shape[0]

    def __add__(self, other: LinearConstraints) -> LinearConstraints:
        if not isinstance(other, LinearConstraints):
            return NotImplemented
        if other.shape != self.shape:
            raise ValueError(
                f"constraints on coefficient matrices of shapes {self.shape} and "
                f"{other.shape} cannot be combined"
            )
        return LinearConstraints(
            self.n_terms, self.n_equations,
            np.vstack([self.A_eq, other.A_eq]), np.concatenate([self.b_eq, other.b_eq]),
            np.vstack([self.A_ub, other.A_ub]), np.concatenate([self.b_ub, other.b_ub]),
            self.labels_eq + other.labels_eq, self.labels_ub + other.labels_ub,
        )  # fmt: skip

    def check_shape(self, p: int, n: int) -> None:
        if self.shape != (p, n):
            raise ValueError(
                f"constraints are for a coefficient matrix of shape {self.shape} (terms, "
                f"equations); the problem has shape ({p}, {n})"
            )

    def tied(self) -> np.ndarray:
        """Boolean (n_terms, n_equations): the coefficients some constraint involves."""
        used = np.zeros(self.n_terms * self.n_equations, dtype=bool)
        for a in (self.A_eq, self.A_ub):
            used |= (a != 0).any(axis=0)
        return used.reshape(self.shape, order="F")

    def active(self, coef) -> np.ndarray:
        """Boolean (r_ub,): the inequalities that ``coef`` (p, n) meets with equality (or
        violates), within :data:`ACTIVE_TOL` of ``max(||a||_1 max|x|, |b|)``."""
        x = np.asarray(coef, dtype=float).ravel(order="F")
        slack = self.b_ub - self.A_ub @ x
        scale = np.maximum(
            np.abs(self.A_ub).sum(axis=1) * np.abs(x).max(initial=0.0), np.abs(self.b_ub)
        )
        return slack <= ACTIVE_TOL * np.maximum(scale, np.finfo(float).tiny)

    def residual(self, coef) -> float:
        """The largest relative violation of a constraint by ``coef`` (p, n): for each
        row, ``|a x - b|`` (equalities) or ``max(a x - b, 0)`` (inequalities) over
        ``max(||a||_1 max|x|, |b|)`` (0 when both are 0)."""
        x = np.asarray(coef, dtype=float).ravel(order="F")
        out = 0.0
        for a, b, one_sided in ((self.A_eq, self.b_eq, False), (self.A_ub, self.b_ub, True)):
            if not len(b):
                continue
            v = a @ x - b
            v = np.maximum(v, 0.0) if one_sided else np.abs(v)
            # What the row makes of coefficients of the solution's size: rounding in
            # coefficients that should be zero is not a violation.
            scale = np.maximum(np.abs(a).sum(axis=1) * np.abs(x).max(initial=0.0), np.abs(b))
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = np.where(scale > 0, v / scale, np.where(v > 0, np.inf, 0.0))
            out = max(out, float(rel.max()))
        return out

    def __repr__(self) -> str:
        return (
            f"LinearConstraints({self.A_eq.shape[0]} equalities, {self.A_ub.shape[0]} "
            f"inequalities on {self.n_terms} terms x {self.n_equations} equations)"
        )


@dataclass
class ConstrainedCertificate:
    """Outcome of :func:`constrained_certificate` (per problem, not per column).

    Attributes
    ----------
    objective : float
        The sum over the equations of the Huber losses plus the weighted L1 norm.
    kkt : float
        Relative violation of stationarity (the unconstrained certificate's measure,
        with the multipliers' term), of the constraints and of complementarity: the
        largest of the three.
    stationarity, feasibility : float
        The first two parts of ``kkt``.
    gap : float
        Duality gap of the dual point built from ``psi`` and the multipliers.
    nu, mu : ndarray
        The multipliers of the equalities and of the inequalities (``mu >= 0``, zero
        on inactive rows).
    column_objective, column_kkt : ndarray (n,)
        The objective and the stationarity violation of each equation.
    residual, psi : ndarray (m, n) or None
        The residuals and ``psi_delta`` of them (None out of core, where only sums over
        the rows are formed: :func:`certificate_from_sums`).
    """

    objective: float
    kkt: float
    stationarity: float
    feasibility: float
    gap: float
    nu: np.ndarray
    mu: np.ndarray
    column_objective: np.ndarray
    column_kkt: np.ndarray
    residual: np.ndarray | None
    psi: np.ndarray | None

    @property
    def rel_gap(self) -> float:
        return self.gap / max(abs(self.objective), np.finfo(float).tiny)


def _multipliers(
    grad, xi, lam, c_eq, c_ub, active, nu0, mu0, on, norms, scale, given=False, exact=1e-10
):
    """Multipliers that best fit the stationarity conditions at ``xi``: they minimise
    the sum of squares of the certificate's per-coordinate measure (the proximal-
    gradient step of :func:`~robust_sindy.core.certificates.kkt_from_gradient`,
    continuous in ``xi``, over its ``scale``) with ``h = grad - C_eq^T nu - C_ub^T mu``
    in place of the gradient (all flattened column by column), ``mu >= 0`` and zero
    where the inequality is not ``active``.  The search starts from the better of
    ``(nu0, mu0)`` and the least-squares fit of ``h = lam sign(xi)`` on the support
    ``on``.  Multipliers ``given`` (a solver's own) that already fit the conditions to
    ``exact`` (relative, per coordinate: a hundredth of the fast path's certification
    tolerance) are returned as they are."""
    g, x, lam = grad.ravel(order="F"), xi.ravel(order="F"), lam.ravel(order="F")
    on = on.ravel(order="F")
    nrm = np.tile(norms, xi.shape[1])
    scale = scale.ravel(order="F")
    target = lam * np.sign(x)
    r_eq, r_ub = c_eq.shape[0], c_ub.shape[0]
    if r_eq + r_ub == 0:
        return np.zeros(0), np.zeros(0)
    c = np.vstack([c_eq, c_ub])
    t_lam = np.where(nrm > 0, lam / np.where(nrm > 0, nrm, 1.0) ** 2, 0.0)
    weight = np.where(scale > 0, 1.0 / np.where(scale > 0, scale, 1.0), 0.0)

    def parts(z):
        h = g - c.T @ z
        u = x + np.where(nrm > 0, h / np.where(nrm > 0, nrm, 1.0) ** 2, 0.0)
        up, down = u > t_lam, u < -t_lam
        step = np.where(up, h - lam, np.where(down, h + lam, 0.0))  # signed; 0 between
        middle = np.abs(x) * nrm**2  # independent of h
        d = np.where(up | down, step, 0.0) * weight
        return d, np.where(up | down, 0.0, middle * weight)

    def fun(z):
        d, rest = parts(z)
        return 0.5 * float(d @ d) + 0.5 * float(rest @ rest), -(c @ (d * weight))

    bounds = [(None, None)] * r_eq + [(0.0, None) if a else (0.0, 0.0) for a in active]
    z0 = np.concatenate([nu0, np.where(active, np.maximum(mu0, 0.0), 0.0)])
    if given and max(np.abs(v).max(initial=0.0) for v in parts(z0)) <= exact:
        return z0[:r_eq], z0[r_eq:]  # the given multipliers already certify: no search
    free = np.concatenate([np.ones(r_eq, dtype=bool), np.asarray(active, dtype=bool)])
    if free.any():
        # Only the multipliers that may be nonzero enter the fits: an inactive row's
        # would take a share of them and then be set to zero.  Two starts: the support's
        # conditions unweighted, and every coordinate's on the certificate's scale (the
        # measure itself where nothing is penalised).
        fits = [(on, np.ones(x.size)), (np.ones(x.size, dtype=bool), weight)]
        for rows, w in fits:
            if not rows.any():
                continue
            ls = np.zeros(r_eq + r_ub)
            a = (c[free][:, rows] * w[rows]).T
            ls[free] = np.linalg.lstsq(a, ((g - target) * w)[rows], rcond=None)[0]
            ls[r_eq:] = np.maximum(ls[r_eq:], 0.0)
            if fun(ls)[0] < fun(z0)[0]:
                z0 = ls
    res = scipy.optimize.minimize(
        fun, z0, jac=True, method="L-BFGS-B", bounds=bounds,
        options=dict(maxiter=5000, ftol=1e-30, gtol=1e-30),
    )  # fmt: skip
    z = res.x if fun(res.x)[0] <= fun(z0)[0] else z0
    return z[:r_eq], z[r_eq:]


def constrained_certificate(
    theta, y, xi, delta, lam, constraints: LinearConstraints, nu=None, mu=None
) -> ConstrainedCertificate:
    """Objective, KKT violation (with the best-fitting multipliers), constraint
    residual and duality gap of ``xi`` (p, n) for the constrained problem.

    ``delta`` (n,), ``lam`` broadcasting to (p, n); ``nu`` and ``mu`` (optional) start
    the search for the multipliers (e.g. a solver's own)."""
    p, n = xi.shape
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (p, n))
    norms = column_norms(theta)
    cert = certify(theta, y, xi, delta, lam, norms)
    return certificate_from_sums(
        xi, cert.grad, lam, norms, column_norms(cert.psi), cert.objective,
        np.einsum("ij,ij->j", y, cert.psi), constraints, nu, mu, cert.residual, cert.psi,
    )  # fmt: skip


def certificate_from_sums(
    xi, grad, lam, norms, psi_norm, objective, y_psi, constraints: LinearConstraints,
    nu=None, mu=None, residual=None, psi=None,
) -> ConstrainedCertificate:  # fmt: skip
    """:func:`constrained_certificate` from sums over the rows: ``grad = Theta^T psi``
    (p, n), the library's column norms (p,), ``||psi_k||`` (n,), each equation's
    objective (n,, its Huber loss plus its L1 term) and ``y_k^T psi_k`` (n,); what data
    out of core give in one pass (:mod:`robust_sindy.solvers.chunked`).  ``residual``
    and ``psi`` (m, n), when known, are kept in the result."""
    p, n = xi.shape
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (p, n))
    c_eq, c_ub = constraints.A_eq, constraints.A_ub
    active = constraints.active(xi)
    given = nu is not None and mu is not None
    nu0 = np.zeros(c_eq.shape[0]) if nu is None else np.asarray(nu, dtype=float)
    mu0 = np.zeros(c_ub.shape[0]) if mu is None else np.asarray(mu, dtype=float)
    # The support: coefficients whose proximal-gradient step |xi_j| / t_j is not
    # negligible on the certificate's scale (rounding where the optimum has a zero
    # would otherwise pin the multipliers to a sign it does not have).
    scale = np.maximum(lam, norms[:, None] * psi_norm[None, :])
    on = np.abs(xi) * norms[:, None] ** 2 > 1e-12 * scale
    nu, mu = _multipliers(grad, xi, lam, c_eq, c_ub, active, nu0, mu0, on, norms, scale, given)
    h = grad - (c_eq.T @ nu + c_ub.T @ mu).reshape((p, n), order="F")
    column_kkt = kkt_from_gradient(xi, h, lam, norms, psi_norm)
    stationarity = float(column_kkt.max())
    feasibility = constraints.residual(xi)
    # The dual point (s psi, s nu, s mu) with s keeping |h| within lam.
    absh = np.abs(h)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(absh > 0, lam / absh, np.inf)
    s = min(1.0, float(ratio.min()))
    linear = float(np.sum(y_psi)) - float(nu @ constraints.b_eq + mu @ constraints.b_ub)
    dual = s * linear - 0.5 * s**2 * float(psi_norm @ psi_norm)
    total = float(np.sum(objective))
    return ConstrainedCertificate(
        objective=total,
        kkt=max(stationarity, feasibility),
        stationarity=stationarity,
        feasibility=feasibility,
        gap=max(total - dual, 0.0),
        nu=nu,
        mu=mu,
        column_objective=np.asarray(objective, dtype=float),
        column_kkt=column_kkt,
        residual=residual,
        psi=psi,
    )
