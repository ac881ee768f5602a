"""Scales and standardisation: what every unit-free decision goes through.

* :func:`robust_scale` -- the Gaussian scale of the bulk of a sample (MAD refined by a
  truncated variance), per column.
* :func:`fitted_scale_factor` -- how much narrower the residuals of a fit are than its
  errors.
* :class:`Standardizer` -- divides library columns and targets by their root mean
  square (a statistic that is homogeneous of degree one, so that rescaling a state, a
  derivative or the time unit changes the standardised data only by rounding), and maps
  coefficients, Huber thresholds and L1 weights back to the user's units.

Rescaling the states by a positive diagonal ``D`` and time by ``c`` multiplies each
library column and each derivative column by a fixed factor.  The Huber-Lasso is not
invariant to that (``delta`` and ``lam`` are in the target's units and ``lam`` weighs
raw coefficients), so the automatic pipeline takes every decision on standardised data;
with the mapped-back values, :func:`robust_sindy.fit` in user units returns the same
coefficients up to the scale factors.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.stats

__all__ = ["Standardizer", "fitted_scale_factor", "robust_scale"]


# The median absolute deviation of a standard normal variable, Phi^-1(3/4).
_MAD_NORMAL = float(scipy.stats.norm.ppf(0.75))


@functools.lru_cache(maxsize=16)
def _truncated_variance(c: float) -> float:
    """The variance of a standard normal variable truncated to ``[-c, c]``."""
    return float(1.0 - 2 * c * scipy.stats.norm.pdf(c) / (2 * scipy.stats.norm.cdf(c) - 1))


def fitted_scale_factor(m: int, p: int) -> float:
    """``sqrt(m / (m - p))``: the factor that brings the scale of the residuals of a
    fit of ``p`` coefficients on ``m`` samples up to that of the errors.

    A least-squares fit leaves residual ``i`` the variance ``(1 - h_ii) sigma^2`` (``h``
    the hat matrix, whose diagonal sums to ``p``): on average ``(1 - p / m)
    sigma^2``.  With a few terms per hundred samples the factor is within a percent of
    1; with four samples per term, as in a degree-2 library of 30 states fitted to
    2000 samples, the residuals' scale is 13 % short of the errors'.  At ``m <= p``
    (residuals at rounding level) it is ``sqrt(m)``.
    """
    m, p = int(m), int(p)
    return float(np.sqrt(m / max(m - p, 1)))


def robust_scale(residuals, cutoff: float = 3.0, n_iter: int = 20) -> np.ndarray:
    """Gaussian scale of the bulk of ``residuals`` (m,) or (m, n), per column.

    Starts from ``1.4826 MAD`` and refines it by the truncated variance: the mean square
    of the residuals within ``cutoff`` scales of the median, divided by its Gaussian
    expectation ``1 - 2 c phi(c) / (2 Phi(c) - 1)``, repeated until it settles.  The MAD
    alone is inflated by a fraction ``eps`` of gross outliers (by about 30 % at
    ``eps = 0.2``, since the median of ``|r|`` then sits at a higher quantile of the
    inliers); the refinement removes that bias once the outliers lie beyond ``cutoff``
    scales, and is consistent at the Gaussian.
    """
    r = np.asarray(residuals, dtype=float)
    one_d = r.ndim == 1
    r = r[:, None] if one_d else r
    c = float(cutoff)
    kappa = _truncated_variance(c)
    out = np.empty(r.shape[1])
    for k in range(r.shape[1]):
        centred = r[:, k] - np.median(r[:, k])
        # 1.4826 MAD, as scipy.stats.median_abs_deviation(scale="normal") computes it
        # (without its per-call overhead, about a millisecond: this runs tens of times
        # per identification).
        s = np.median(np.abs(centred - np.median(centred))) / _MAD_NORMAL
        for _ in range(n_iter):
            if s == 0:
                break
            inside = centred[np.abs(centred) <= c * s]
            new = np.sqrt(np.mean(inside**2) / kappa)
            done = abs(new - s) <= 1e-6 * s
            s = new
            if done:
                break
        out[k] = s
    return out[0] if one_d else out


@dataclass
class Standardizer:
    """Column scales of a library ``theta`` (p,) and of targets ``y`` (n,).

    ``theta_s = theta / theta_scale``, ``y_s = y / y_scale``; a coefficient ``xi_s`` of
    the standardised problem is ``xi = xi_s * y_scale / theta_scale`` in user units; a
    Huber threshold maps as ``delta = delta_s * y_scale`` and an L1 weight on
    standardised coefficients as ``lam_j = lam_s * y_scale * theta_scale_j`` (one weight
    per coordinate).  Zero columns keep scale 1.
    """

    theta_scale: np.ndarray
    y_scale: np.ndarray

    @classmethod
    def from_data(cls, theta: np.ndarray, y: np.ndarray) -> Standardizer:
        return cls(_rms(theta), _rms(y))

    def theta(self, theta: np.ndarray) -> np.ndarray:
        return theta / self.theta_scale

    def y(self, y: np.ndarray) -> np.ndarray:
        return y / self.y_scale

    def coef_to_user(self, coef_s: np.ndarray) -> np.ndarray:
        return coef_s * self.y_scale / self.theta_scale[:, None]

    def coef_to_standard(self, coef: np.ndarray) -> np.ndarray:
        return coef * self.theta_scale[:, None] / self.y_scale

    def delta_to_user(self, delta_s: np.ndarray) -> np.ndarray:
        return delta_s * self.y_scale

    def lam_to_user(self, lam_s: np.ndarray) -> np.ndarray:
        """Per-coordinate weights (p, n) in user units for uniform ``lam_s`` (n,)."""
        return np.outer(self.theta_scale, lam_s * self.y_scale)


def _rms(a: np.ndarray) -> np.ndarray:
    s = np.sqrt(np.mean(a**2, axis=0))
    return np.where((s > 0) & np.isfinite(s), s, 1.0)
