"""Errors in the variables: terms the noise of the states could have selected.

The library is evaluated on measured states ``x + e``.  To first order its rows carry
the noise ``N = sum_k e_k dTheta/dx_k``, and a fit of ``xdot`` on ``Theta(x + e)`` is
biased towards ``(Theta^T Theta)^{-1} E[N^T N] xi`` (the attenuation of classical
errors-in-variables regression, spread over correlated terms): with small noise and
many samples, that bias is systematic, not random, and an information criterion reads
it as signal.  A selected term whose coefficient is not clearly larger than the bias the
other terms can give it is not identifiable from these data.

:func:`drop_biased_terms` removes such terms one at a time (the least distinguishable
first) and refits the rest.  The first-order bias of term ``j`` is
``beta_j = |sum_l M_jl xi_l|`` with ``M = (A_S^T A_S)^{-1} C_S``, ``A_S`` the selected
columns and ``C`` the expected noise Gram matrix ``sum_k sigma_k^2 G_k^T G_k`` (``G_k``
the library's derivative with respect to state ``k``, ``sigma_k`` that state's noise
level measured by the temporal screen).  The ratio ``|xi_j| / beta_j`` does not change
when any column, target or state is rescaled, so the rule is unit-free.  The signed sum
matters: in a term whose equation has large coefficients of opposite signs, their
biases cancel, and the triangle bound ``sum_l |M_jl| |xi_l|`` would drop a true term.  It assumes
the derivatives carry no noise of their own: derivatives estimated from the same noisy
states have errors correlated with ``N``, the first-order formula leaves that out, and
:class:`~robust_sindy.HuberSINDy` then uses the bound (``signed=False``).
"""

from __future__ import annotations

import numpy as np

from ..core.threads import map_threads
from .refit import refit_column
from .significance import VISIBLE, robust_t

__all__ = [
    "BIAS_MARGIN",
    "NOISE_SLACK",
    "LibraryNoise",
    "carried_noise",
    "drop_biased_terms",
    "first_order_bias",
    "library_noise",
    "noise_columns",
    "noise_gram",
    "residual_noise_factor",
    "state_noise_factors",
    "truncation_bias",
]

#: A selected term is kept only when its coefficient exceeds this many times the bias
#: that the errors in the variables can give it.
BIAS_MARGIN = 3.0

#: The states' noise is taken at its measured level unless the residuals of an
#: equation show less than ``1 / NOISE_SLACK`` of the variance it would put in them.
NOISE_SLACK = 4.0

# The median of a chi-square variable with one degree of freedom.
_MEDIAN_CHI2_1 = 0.454936423119572


class LibraryNoise:
    """The noise that each state's measurement noise puts in the library columns, first
    order, at every sample: per state ``k`` the matrix ``N_k = sigma_k dTheta/dx_k``
    (m, p), stored on the columns that depend on that state only (``cols[k]``, with
    ``values[k]`` of shape (m, len(cols[k]))): a degree-2 polynomial library of n states
    has about 2 / n of its columns depend on each, so the noise of all states takes
    about twice the memory of the library, not n times.

    Parameters
    ----------
    p : int
        Columns of the library.
    cols : list of ndarray of int
        Per state, the columns that depend on it.
    values : list of ndarray (m, len(cols[k]))
        Per state, its noise in those columns at every sample.
    """

    def __init__(self, p: int, cols, values):
        self.p = int(p)
        self.cols = [np.asarray(c, dtype=int) for c in cols]
        self.values = [np.asarray(v, dtype=float) for v in values]
        self._finite: list[bool] | None = None  # per state, all values finite (when needed)
        if len(self.cols) != len(self.values) or any(
            v.ndim != 2 or v.shape[1] != c.size for c, v in zip(self.cols, self.values, strict=True)
        ):
            raise ValueError("noise: one (m, len(cols[k])) array of values per state's columns")

    @classmethod
    def of(cls, noise) -> LibraryNoise | None:
        """``noise`` as a :class:`LibraryNoise`: as it is, or from one dense (m, p)
        array per state (their all-zero columns left out); None stays None."""
        if noise is None or isinstance(noise, LibraryNoise):
            return noise
        arrays = [np.asarray(a, dtype=float) for a in noise]
        if not arrays or any(a.ndim != 2 or a.shape != arrays[0].shape for a in arrays):
            raise ValueError("noise must be a list of (m, p) arrays of one shape, one per state")
        cols = [np.flatnonzero(np.any(a != 0, axis=0)) for a in arrays]
        return cls(arrays[0].shape[1], cols, [a[:, c] for a, c in zip(arrays, cols, strict=True)])

    def __len__(self) -> int:
        return len(self.values)

    @property
    def shape(self) -> tuple[int, int]:
        """``(m, p)``: samples and library columns of each state's noise."""
        return (self.values[0].shape[0] if self.values else 0, self.p)

    def dense(self) -> list[np.ndarray]:
        """One (m, p) array per state."""
        out = []
        for c, v in zip(self.cols, self.values, strict=True):
            a = np.zeros((v.shape[0], self.p))
            a[:, c] = v
            out.append(a)
        return out

    def rows(self, index) -> LibraryNoise:
        """The samples ``index`` (a boolean mask or indices)."""
        return LibraryNoise(self.p, self.cols, [v[index] for v in self.values])

    def map_rows(self, transform) -> LibraryNoise:
        """``transform`` (an array (m, c) to one (r, c), column by column) applied to
        each state's values: the noise of other rows made of these samples."""
        return LibraryNoise(self.p, self.cols, [transform(v) for v in self.values])

    def terms(self, keep) -> LibraryNoise:
        """The library columns ``keep`` (a boolean mask over the p columns)."""
        keep = np.asarray(keep, dtype=bool)
        position = np.cumsum(keep) - 1
        cols, values = [], []
        for c, v in zip(self.cols, self.values, strict=True):
            on = keep[c]
            cols.append(position[c[on]])
            values.append(v[:, on])
        return LibraryNoise(int(keep.sum()), cols, values)

    def scaled(self, factors) -> LibraryNoise:
        """Each state's noise times its factor."""
        factors = np.broadcast_to(np.asarray(factors, dtype=float), (len(self),))
        return LibraryNoise(
            self.p, self.cols, [f * v for f, v in zip(factors, self.values, strict=True)]
        )

    def per_state(self, coef) -> list[np.ndarray]:
        """``N_k @ coef`` per state, (m,) or (m, n) for ``coef`` (p,) or (p, n)."""
        coef = np.asarray(coef, dtype=float)
        pairs = list(zip(self.cols, self.values, strict=True))
        width = coef.shape[1] if coef.ndim == 2 else 1
        flops = self.shape[0] * self.p * width / max(len(self), 1)  # per state, about
        return map_threads(lambda cv: cv[1] @ coef[cv[0]], pairs, flops=flops)

    def reaching(self, coef) -> list[tuple[int, np.ndarray]]:
        """``(k, N_k @ coef)`` for ``coef`` (p,), the states whose noise it can reach:
        those with a nonzero coefficient on one of their columns, or with values that
        are not all finite.  For the others ``N_k @ coef`` is exactly zero, and a
        sparse ``coef`` leaves most states out."""
        coef = np.asarray(coef, dtype=float)
        if self._finite is None:
            self._finite = [bool(np.isfinite(v).all()) for v in self.values]
        return [
            (k, v @ coef[c])
            for k, (c, v, finite) in enumerate(
                zip(self.cols, self.values, self._finite, strict=True)
            )
            if not finite or np.any(coef[c] != 0)
        ]

    def carried(self, coef) -> np.ndarray:
        """``sqrt(sum_k (N_k @ coef)^2)``: the standard deviation of the noise the
        states put in ``Theta @ coef`` at every sample, first order."""
        coef = np.asarray(coef, dtype=float)
        total = np.zeros((self.shape[0], *coef.shape[1:]))
        for part in self.per_state(coef):
            total += part**2
        return np.sqrt(total)

    def gram(self) -> np.ndarray:
        """``sum_k N_k^T N_k`` (p, p)."""
        out = np.zeros((self.p, self.p))
        for c, v in zip(self.cols, self.values, strict=True):
            out[np.ix_(c, c)] += v.T @ v
        return out

    def column_mean_square(self) -> np.ndarray:
        """``sum_k mean_i N_k[i, j]^2`` per column ``j`` (p,)."""
        out = np.zeros(self.p)
        for c, v in zip(self.cols, self.values, strict=True):
            out[c] += np.mean(v**2, axis=0)
        return out

    def along(self, directions) -> np.ndarray:
        """``sum_k |N_k d|^2`` for each row ``d`` of ``directions`` (r, p)."""
        directions = np.asarray(directions, dtype=float)
        out = np.zeros(directions.shape[0])
        for c, v in zip(self.cols, self.values, strict=True):
            out += np.sum((v @ directions[:, c].T) ** 2, axis=0)
        return out


def noise_columns(library, z, temporal, theta_scale) -> LibraryNoise | None:
    """The noise of each state carried through the standardised library, first order,
    at every sample: ``sigma_k dTheta/dx_k / theta_scale`` per state ``k`` (``sigma_k``
    measured by the ``temporal`` screen, the derivative by central differences of the
    fitted ``library`` at its inputs ``z`` with the states repaired), on the columns
    that depend on each state; None without the screen."""
    if temporal is None or not np.all(np.isfinite(temporal.scale)):
        return None
    base = z.copy()
    n = temporal.scale.size
    base[:, :n] = temporal.repaired

    def state(k):  # each state's central difference, side by side (the same values)
        sigma = temporal.scale[k]
        step = 1e-4 * max(float(np.sqrt(np.mean(base[:, k] ** 2))), np.finfo(float).tiny)
        up, down = base.copy(), base.copy()
        up[:, k] += step
        down[:, k] -= step
        # Only the columns that can depend on the state, where the library tells them.
        cols = library.input_columns(k)
        if cols is None:
            grad = library.transform(up)
            del up
            grad -= library.transform(down)
            p = grad.shape[1]
            cols = np.arange(p)
        else:
            p = library.n_output_features_
            cols = np.asarray(cols, dtype=int)
            grad = library.transform_columns(up, cols)
            del up
            grad -= library.transform_columns(down, cols)
        nonzero = np.flatnonzero(np.any(grad != 0, axis=0))
        on = cols[nonzero]
        scale = np.broadcast_to(np.asarray(theta_scale, dtype=float), (p,))[on]
        return p, on, grad[:, nonzero] * (sigma / (2 * step)) / scale

    parts = map_threads(state, range(n))
    p = parts[0][0] if parts else 0
    return LibraryNoise(p, [on for _, on, _ in parts], [v for _, _, v in parts])


def library_noise(noise, theta_kept) -> tuple[np.ndarray, float]:
    """The library noise (:class:`LibraryNoise`, or one (m, p) array per state) per
    column relative to its root mean square, and along the least-excited direction of
    the standardised library ``theta_kept``; NaN without the temporal screen, which
    measures the noise."""
    p = theta_kept.shape[1]
    if noise is None:
        return np.full(p, np.nan), float("nan")
    noise = LibraryNoise.of(noise)
    _, sing, vt = np.linalg.svd(theta_kept, full_matrices=False)
    columns = noise.column_mean_square()
    along = noise.along(vt)
    rms = np.sqrt(np.mean(theta_kept**2, axis=0))
    columns = np.sqrt(columns) / np.where(rms > 0, rms, 1.0)
    # Exactly degenerate directions (a constant state, duplicated terms) carry no
    # signal to confuse: the condition number of the selected terms reports them.
    ok = sing > 1e-8 * sing[0]
    return columns, float(np.max(np.sqrt(along[ok]) / sing[ok]))


def noise_gram(noise_columns) -> np.ndarray:
    """``sum_k N_k^T N_k`` for the library noise per state, ``N_k = sigma_k G_k`` (m, p)
    (a :class:`LibraryNoise` or one dense array per state)."""
    return LibraryNoise.of(noise_columns).gram()


def carried_noise(noise_columns, coef) -> np.ndarray:
    """The standard deviation (m,) of the noise that the states' noise puts in an
    equation's residuals at every sample, first order: ``sqrt(sum_k (N_k xi)^2)`` for
    the library noise per state ``N_k`` (m, p) and coefficients ``xi`` (p,), or (m, n)
    for ``xi`` (p, n)."""
    return LibraryNoise.of(noise_columns).carried(coef)


def residual_noise_factor(residual, carried) -> float:
    """How much of the states' measured noise an equation's residuals allow, as a
    factor (at most 1) on the noise Gram matrix.

    ``residual`` (m,) are the equation's residuals and ``carried`` (m,) the standard
    deviation, at every sample, of the noise that the states' measured noise puts in
    them (``sqrt(sum_k (N_k xi)^2)``, first order).  The residuals contain that noise
    whatever else they contain (the errors of derivatives estimated from a sample's
    neighbours are independent of its own noise, and cannot cancel it): the median of
    ``(r / carried)^2`` is at least that of a chi-square with one degree of freedom.
    Where it is smaller than that by more than ``NOISE_SLACK``, the noise was measured
    too large (the temporal screen counts as noise the truncation error of local
    polynomials on a trajectory it cannot resolve), and the factor brings it down to
    what the residuals show.  A ratio of residuals: unit-free.
    """
    residual = np.asarray(residual, dtype=float)
    carried = np.asarray(carried, dtype=float)
    ok = carried > 0
    if not ok.any():
        return 1.0
    ratio = float(np.median((residual[ok] / carried[ok]) ** 2)) / _MEDIAN_CHI2_1
    return min(1.0, NOISE_SLACK * ratio)


def state_noise_factors(noise, coef, factors) -> np.ndarray:
    """Per state, the share of its measured noise variance that the residuals allow.

    Equation ``j`` allows ``factors[j]`` of the noise variance it carries,
    ``sum_k ||N_k xi_j||^2`` (``noise``: the library noise per state ``N_k``,
    ``coef`` (p, n) the coefficients ``xi``): state ``k``, carrying the share
    ``s_jk`` of it, can have at most ``factors[j] / s_jk`` of its own; the smallest
    bound over the equations it enters counts, capped at 1 (1 for a state no
    equation carries, whose noise no residual shows).
    """
    noise = LibraryNoise.of(noise)
    coef = np.asarray(coef, dtype=float)
    carried = np.array([np.sum(part**2, axis=0) for part in noise.per_state(coef)])  # (states, n)
    total = carried.sum(axis=0)
    out = np.ones(len(noise))
    for k in range(len(noise)):
        enters = (carried[k] > 0) & np.isfinite(factors)
        if enters.any():
            share = carried[k, enters] / total[enters]
            out[k] = min(1.0, float(np.min(factors[enters] / share)))
    return out


def first_order_bias(theta, coef, gram, signed: bool = True) -> np.ndarray:
    """Per selected term, the first-order bias ``beta = |M xi_S|`` (see the module
    docstring), or with ``signed=False`` its triangle bound ``|M| |xi_S|``.

    ``theta`` (m, p), ``coef`` (p,) and ``gram`` (p, p) in the same units; returns
    ``beta`` (p,), ``inf`` where the selected columns are rank deficient (nothing can
    be vouched for there) and 0 off the support.
    """
    sel = np.flatnonzero(coef)
    out = np.zeros(coef.shape[0])
    if sel.size == 0:
        return out
    a = theta[:, sel]
    normal = a.T @ a
    try:
        factor = np.linalg.cholesky(normal)
    except np.linalg.LinAlgError:
        out[sel] = np.inf
        return out
    m = np.linalg.solve(factor.T, np.linalg.solve(factor, gram[np.ix_(sel, sel)]))
    out[sel] = np.abs(m @ coef[sel]) if signed else np.abs(m) @ np.abs(coef[sel])
    return out


def truncation_bias(theta, error, coef, segments=None) -> np.ndarray:
    """Per selected term, the bias that an error ``error`` (m,) of the derivatives gives
    its coefficient: the least-squares projection ``b = (A_S^T A_S)^{-1} A_S^T error``
    on the selected columns ``A_S`` of ``theta`` (m, p), less ``VISIBLE`` of its
    standard errors (the sandwich ones of :func:`robust_t`, the correlation time of
    ``segments`` counted), so that only the part the data distinguish from the noise
    of ``error`` counts.

    With ``error`` the difference between the estimated derivatives and a reference of
    higher order (:func:`robust_sindy.timeseries.differentiation.higher_order_derivative`), this
    is the part of each coefficient that the estimate's truncation error explains: on a
    coarsely sampled trajectory that error is systematic and smooth, and a regression
    explains it with spurious terms.  Returns ``beta`` (p,): 0 off the support, ``inf``
    where the selected columns are rank deficient.
    """
    sel = np.flatnonzero(coef)
    out = np.zeros(coef.shape[0])
    if sel.size == 0:
        return out
    a = theta[:, sel]
    b, _, rank, _ = np.linalg.lstsq(a, error, rcond=None)
    if rank < sel.size:
        out[sel] = np.inf
        return out
    full = np.zeros(coef.shape[0])
    full[sel] = b
    t = robust_t(theta, error, full, np.inf, segments)[sel]
    with np.errstate(divide="ignore", invalid="ignore"):
        se = np.where(t > 0, np.abs(b) / t, np.inf)
    out[sel] = np.maximum(np.abs(b) - VISIBLE * np.nan_to_num(se, nan=0.0), 0.0)
    return out


def drop_biased_terms(
    theta,
    xdot,
    coef,
    delta,
    gram,
    *,
    margin: float = BIAS_MARGIN,
    signed: bool = True,
    bias=None,
    method: str = "admm",
    solver: str | None = None,
    **options,
):
    """Drop selected terms within ``margin`` times their errors-in-variables bias.

    Per column of ``coef`` (p, n): while the selected term with the smallest ratio
    ``|xi_j| / beta_j`` (:func:`first_order_bias`, ``signed`` or its bound) is below
    ``margin``, it is dropped and the others are refitted by the Huber loss with
    ``lam = 0`` (``delta`` per column; ``method``, ``solver``, ``options`` go to
    :func:`robust_sindy.fit`).  ``bias``, a function of a column's coefficients (p,)
    and its index returning ``beta`` (p,), replaces the first-order bias (``gram`` is
    then not used; e.g. :func:`truncation_bias`).  Returns the new coefficients and,
    for the dropped terms, their ratio when dropped (p, n; NaN for the others).
    """
    coef = np.array(coef, dtype=float)
    dropped = np.full(coef.shape, np.nan)
    delta = np.broadcast_to(np.asarray(delta, dtype=float), (coef.shape[1],))
    for k in range(coef.shape[1]):
        c = coef[:, k]
        while np.any(c):
            beta = first_order_bias(theta, c, gram, signed) if bias is None else bias(c, k)
            sel = np.flatnonzero(c)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.abs(c[sel]) / beta[sel]
            ratio = np.where(np.isnan(ratio), np.inf, ratio)
            worst = int(np.argmin(ratio))
            if ratio[worst] >= margin or not np.isfinite(beta[sel]).all():
                break
            dropped[sel[worst], k] = ratio[worst]
            keep = c != 0
            keep[sel[worst]] = False
            c = refit_column(theta, xdot[:, k], keep, delta[k], method, solver, options)
        coef[:, k] = c
    return coef, dropped
