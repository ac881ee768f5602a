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

from .refit import refit_column
from .significance import VISIBLE, robust_t

__all__ = [
    "BIAS_MARGIN",
    "NOISE_SLACK",
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


def noise_columns(library, z, temporal, theta_scale) -> list[np.ndarray] | None:
    """The noise of each state carried through the standardised library, first order,
    at every sample: ``sigma_k dTheta/dx_k / theta_scale`` per state ``k`` (``sigma_k``
    measured by the ``temporal`` screen, the derivative by central differences of the
    fitted ``library`` at its inputs ``z`` with the states repaired); None without the
    screen."""
    if temporal is None or not np.all(np.isfinite(temporal.scale)):
        return None
    base = z.copy()
    n = temporal.scale.size
    base[:, :n] = temporal.repaired
    out = []
    for k, sigma in enumerate(temporal.scale):
        step = 1e-4 * max(float(np.sqrt(np.mean(base[:, k] ** 2))), np.finfo(float).tiny)
        up, down = base.copy(), base.copy()
        up[:, k] += step
        down[:, k] -= step
        grad = (library.transform(up) - library.transform(down)) / (2 * step)
        out.append(sigma * grad / theta_scale)
    return out


def library_noise(noise, theta_kept) -> tuple[np.ndarray, float]:
    """The library noise (:func:`noise_columns`) per column relative to its root mean
    square, and along the least-excited direction of the standardised library
    ``theta_kept``; NaN without the temporal screen, which measures the noise."""
    p = theta_kept.shape[1]
    if noise is None:
        return np.full(p, np.nan), float("nan")
    _, sing, vt = np.linalg.svd(theta_kept, full_matrices=False)
    columns = sum(np.mean(a**2, axis=0) for a in noise)
    along = sum(np.sum((a @ vt.T) ** 2, axis=0) for a in noise)
    rms = np.sqrt(np.mean(theta_kept**2, axis=0))
    columns = np.sqrt(columns) / np.where(rms > 0, rms, 1.0)
    # Exactly degenerate directions (a constant state, duplicated terms) carry no
    # signal to confuse: the condition number of the selected terms reports them.
    ok = sing > 1e-8 * sing[0]
    return columns, float(np.max(np.sqrt(along[ok]) / sing[ok]))


def noise_gram(noise_columns) -> np.ndarray:
    """``sum_k N_k^T N_k`` for the library noise per state, ``N_k = sigma_k G_k`` (m, p)."""
    return sum(a.T @ a for a in noise_columns)


def carried_noise(noise_columns, coef) -> np.ndarray:
    """The standard deviation (m,) of the noise that the states' noise puts in an
    equation's residuals at every sample, first order: ``sqrt(sum_k (N_k xi)^2)`` for
    the library noise per state ``N_k`` (m, p) and coefficients ``xi`` (p,)."""
    return np.sqrt(sum((a @ coef) ** 2 for a in noise_columns))


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
    carried = np.array([[np.sum((a @ c) ** 2) for c in coef.T] for a in noise])  # (n_states, n)
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
