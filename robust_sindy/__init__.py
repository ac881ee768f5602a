"""robust_sindy: sparse identification of nonlinear dynamics with the Huber loss.

Each column of the coefficient matrix solves

    min_xi  sum_i H_delta(xdot_i - theta_i xi) + lam * ||xi||_1

by a certified batched Newton method with an ADMM fallback (the fast path) or a CVXPY
reference; least-squares baselines
(STLS, OLS) and the Lasso (``loss="squared"``) use the same entry point, :func:`fit`.
"""

from . import (
    constraints,
    datasets,
    export,
    library,
    metrics,
    noise,
    outofcore,
    parallel,
    selection,
    simulate,
    systems,
)
from ._version import __version__
from .core.certificates import duality_gap, kkt_violation, objective
from .core.constraints import LinearConstraints
from .core.losses import huber, huber_prox, huber_psi, soft_threshold
from .diagnostics import Diagnostics, IdentificationWarning
from .ensemble import EnsembleSINDy
from .estimator import HuberSINDy, load_model
from .fitting import METHODS, ConvergenceWarning, FitResult, fit
from .library import ConcatLibrary, CustomLibrary, FourierLibrary, PolynomialLibrary
from .solvers.problem import PAPER_OPTIONS as PAPER_ADMM_OPTIONS
from .timeseries import differentiation

__all__ = [
    "METHODS",
    "PAPER_ADMM_OPTIONS",
    "ConcatLibrary",
    "ConvergenceWarning",
    "CustomLibrary",
    "Diagnostics",
    "EnsembleSINDy",
    "FitResult",
    "FourierLibrary",
    "HuberSINDy",
    "IdentificationWarning",
    "LinearConstraints",
    "PolynomialLibrary",
    "__version__",
    "constraints",
    "datasets",
    "differentiation",
    "duality_gap",
    "export",
    "fit",
    "huber",
    "huber_prox",
    "huber_psi",
    "kkt_violation",
    "library",
    "load_model",
    "metrics",
    "noise",
    "objective",
    "outofcore",
    "parallel",
    "selection",
    "simulate",
    "soft_threshold",
    "systems",
]
