"""Choosing delta and lambda.

* :func:`lambda_max` — per column, the smallest ``lam`` whose solution is all zeros:
  ``xi = 0`` is optimal iff ``|Theta_j^T psi_delta(xdot)| <= lam`` for every ``j``.
* :func:`auto_delta` — the robust-statistics rule ``delta = 1.345 sigma_hat`` with
  ``sigma_hat`` the MAD-based scale (:func:`robust_scale`) of the residuals of an
  unpenalised Huber pilot fit, iterated: 95 % efficiency at Gaussian residuals,
  bounded influence beyond.
* :func:`screen_rows` — flags whole samples whose pilot residual is gross in any
  well-fitted equation (errors in the library rows are bad-leverage points that no
  ``delta`` can down-weight).
* :func:`path` — a warm-started decreasing ``lam`` grid from :func:`lambda_max`, one
  factorisation for the whole path, every point certified.
* :func:`aliased_columns` — library columns that are exact linear combinations of
  earlier ones on the data (a state that does not move): left out of the selection.
* :func:`threshold_refit` — the selection stage: drop terms of small relative
  contribution, refit the rest by Huber with ``lam = 0``, until the support is stable.
* :func:`select` — runs the path, the selection stage at every point, and picks
  ``lam`` per equation by a robust BIC (:func:`information_criterion`) or by blocked
  cross-validation (:func:`blocked_folds`) scored with the Huber loss;
  :func:`score_margin` is how much worse the best other support scored.  The BIC
  also scores best-subset candidates (:func:`best_subsets`: the best supports of every
  size up to a budget, by weighted least squares), which a lasso path on strongly
  collinear terms may never propose.
* :func:`robust_t` — the robust t statistic of selected terms (sandwich standard
  errors from the residuals, corrected for their correlation time): with measured
  derivatives, a term under the noise floor stays when it reaches
  :data:`SIGNIFICANCE`.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> theta = rng.normal(size=(2000, 4))
>>> xdot = theta @ np.array([1.0, -2.0, 0.0, 0.5]) + 0.1 * rng.normal(size=2000)
>>> bad = rng.choice(2000, 400, replace=False)
>>> xdot[bad] += rng.normal(scale=20.0, size=400)      # 20 % gross outliers
>>> sigma = auto_delta(theta, xdot) / 1.345
>>> bool(abs(sigma - 0.1) < 0.02)
True
"""

from ..core.scaling import robust_scale
from ..core.statistics import correlation_time
from ..fitting import HUBER_EFFICIENCY_CONSTANT, auto_delta
from .aliasing import ALIAS_RTOL, aliased_columns
from .criteria import (
    CRITERIA,
    MIN_BIC_MARGIN,
    Selection,
    blocked_folds,
    information_criterion,
    score_margin,
    select,
)
from .lam_path import PATH_MAX_ITER, Path, lambda_max, path
from .refit import STAGE_ROUNDS, threshold_refit
from .rows import Screening, screen_rows
from .significance import SIGNIFICANCE, robust_t
from .subsets import SUBSET_BUDGET, best_subsets

__all__ = [
    "ALIAS_RTOL",
    "CRITERIA",
    "HUBER_EFFICIENCY_CONSTANT",
    "MIN_BIC_MARGIN",
    "PATH_MAX_ITER",
    "SIGNIFICANCE",
    "STAGE_ROUNDS",
    "SUBSET_BUDGET",
    "Path",
    "Screening",
    "Selection",
    "aliased_columns",
    "auto_delta",
    "best_subsets",
    "blocked_folds",
    "correlation_time",
    "information_criterion",
    "lambda_max",
    "path",
    "robust_scale",
    "robust_t",
    "score_margin",
    "screen_rows",
    "select",
    "threshold_refit",
]
