"""The paper's contamination model (Table 1).

Gaussian noise on every component: standard deviation ``sigma1`` on most samples and
``sigma2`` on exactly ``round(frac * m)`` samples (rows) chosen at random, the same rows
for all components.  It goes on the measured states (default), on the derivatives, or
on both (same rows, independent draws).

Examples
--------
>>> import numpy as np
>>> x = np.zeros((1001, 3))
>>> data = contaminate(x, np.zeros((1001, 3)), rng=np.random.default_rng(0))
>>> int(data.outliers.sum())
200
>>> bool(np.all(data.x_dot == 0))
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .core.validation import as_float_array, check_positive

__all__ = ["PLACEMENTS", "Contaminated", "contaminate", "outlier_rows"]

PLACEMENTS = ("states", "derivatives", "both")


class Contaminated(NamedTuple):
    """Noisy states and derivatives, and the boolean mask of the heavy-noise rows."""

    x: np.ndarray
    x_dot: np.ndarray | None
    outliers: np.ndarray


def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng must be a numpy.random.Generator (np.random.default_rng(seed)); got {rng!r}"
        )
    return rng


def outlier_rows(m: int, frac: float, rng: np.random.Generator) -> np.ndarray:
    """Boolean mask with exactly ``round(frac * m)`` rows set, chosen uniformly."""
    if not 0.0 <= frac <= 1.0:
        raise ValueError(f"frac must be in [0, 1]; got {frac!r}")
    mask = np.zeros(m, dtype=bool)
    mask[_check_rng(rng).choice(m, size=round(frac * m), replace=False)] = True
    return mask


def contaminate(
    x,
    x_dot=None,
    *,
    rng: np.random.Generator,
    frac: float = 0.2,
    sigma1: float = 1e-3,
    sigma2: float = 0.5,
    placement: str = "states",
) -> Contaminated:
    """Add the two-level Gaussian noise of the paper (Table 1).

    Parameters
    ----------
    x : array-like, shape (m, n)
        Clean states.
    x_dot : array-like, shape (m, n), optional
        Clean derivatives (required unless ``placement="states"``).
    rng : numpy.random.Generator
        Source of the row choice and of the noise.
    frac : float
        Fraction of rows with the heavy noise; exactly ``round(frac * m)`` rows.
    sigma1, sigma2 : float
        Standard deviations of the light and heavy noise.
    placement : {"states", "derivatives", "both"}
        What the noise is added to.

    Returns
    -------
    Contaminated
        ``x``, ``x_dot`` (copies, noisy where requested) and ``outliers`` (m,).
    """
    rng = _check_rng(rng)
    x = as_float_array(x, "x", (1, 2))
    if placement not in PLACEMENTS:
        raise ValueError(f"placement must be one of {PLACEMENTS}; got {placement!r}")
    if x_dot is not None:
        x_dot = as_float_array(x_dot, "x_dot", (1, 2))
        if x_dot.shape != x.shape:
            raise ValueError(f"x_dot has shape {x_dot.shape} but x has shape {x.shape}")
    elif placement != "states":
        raise ValueError(f"x_dot is required for placement={placement!r}")
    s1 = check_positive(sigma1, "sigma1") if sigma1 != 0 else 0.0
    s2 = check_positive(sigma2, "sigma2")
    rows = outlier_rows(x.shape[0], frac, rng)
    scale = np.where(rows, s2, s1).reshape((-1,) + (1,) * (x.ndim - 1))

    def noisy(a):
        return a + scale * rng.standard_normal(a.shape)

    new_x = noisy(x) if placement in ("states", "both") else x.copy()
    new_dot = None if x_dot is None else (noisy(x_dot) if placement != "states" else x_dot.copy())
    return Contaminated(new_x, new_dot, rows)
