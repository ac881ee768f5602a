"""Accuracy of identified coefficients: IAE (paper Eq. 21) and support recovery.

Examples
--------
>>> import numpy as np
>>> true = np.array([[1.0, 0.0], [0.0, 2.0]])
>>> est = np.array([[0.9, 0.0], [0.1, 2.0]])
>>> round(iae(true, est), 12)
0.2
>>> support_scores(true, est)
SupportScores(precision=0.6666666666666666, recall=1.0, exact=False)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .core.validation import as_float_array

__all__ = ["SupportScores", "iae", "max_abs_error", "support_scores"]


def _pair(true, est) -> tuple[np.ndarray, np.ndarray]:
    true = as_float_array(true, "true", (1, 2))
    est = as_float_array(est, "est", (1, 2))
    if true.shape != est.shape:
        raise ValueError(f"true has shape {true.shape} but est has shape {est.shape}")
    return true, est


def iae(true, est) -> float:
    """Integral (sum) of absolute coefficient errors, ``sum_ij |Xi_ij - Xi_hat_ij|``."""
    true, est = _pair(true, est)
    return float(np.abs(true - est).sum())


def max_abs_error(true, est) -> float:
    """Largest absolute coefficient error."""
    true, est = _pair(true, est)
    return float(np.abs(true - est).max())


class SupportScores(NamedTuple):
    """Precision and recall of the nonzero pattern, and whether it is exactly right."""

    precision: float
    recall: float
    exact: bool


def support_scores(true, est, tol: float = 0.0) -> SupportScores:
    """Compare the supports ``|Xi| > tol`` of the true and estimated coefficients.

    Precision is 1 when nothing is selected and recall is 1 when nothing is true (no
    selected term is wrong, no true term is missed).
    """
    true, est = _pair(true, est)
    t, e = np.abs(true) > tol, np.abs(est) > tol
    hits = np.count_nonzero(t & e)
    precision = hits / np.count_nonzero(e) if e.any() else 1.0
    recall = hits / np.count_nonzero(t) if t.any() else 1.0
    return SupportScores(float(precision), float(recall), bool(np.array_equal(t, e)))
