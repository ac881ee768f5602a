"""robust_sindy: sparse identification of nonlinear dynamics with the Huber loss.

Each column of the coefficient matrix solves

    min_xi  sum_i H_delta(xdot_i - theta_i xi) + lam * ||xi||_1

by a certified batched Newton method with an ADMM fallback (the fast path) or a CVXPY
reference; least-squares baselines
(STLS, OLS) and the Lasso (``loss="squared"``) use the same entry point, :func:`fit`.
"""

from . import (
    datasets,
    differentiation,
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
from ._certificates import duality_gap, kkt_violation, objective
from ._fit import METHODS, ConvergenceWarning, FitResult, fit
from ._losses import huber, huber_prox, huber_psi, soft_threshold
from .ensemble import EnsembleSINDy
from .io import load_model
from .library import ConcatLibrary, CustomLibrary, FourierLibrary, PolynomialLibrary
from .model import Diagnostics, HuberSINDy, IdentificationWarning
from .solvers.admm import PAPER_OPTIONS as PAPER_ADMM_OPTIONS

__version__ = "0.1.0"

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
    "PolynomialLibrary",
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
