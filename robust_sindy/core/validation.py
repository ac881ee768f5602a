"""Input checks shared by every public entry point.

Each check names the argument it rejects and what was expected; nothing is coerced
silently (integers become floats, which is exact for the values a library holds;
booleans, complex numbers, strings and objects are refused).
"""

from __future__ import annotations

import numbers

import numpy as np

LOSSES = ("huber", "squared")


def as_float_array(
    value, name: str, ndims: tuple[int, ...], *, allow_nan: bool = False
) -> np.ndarray:
    """Return ``value`` as a finite float64 array with one of ``ndims`` dimensions
    (``allow_nan``: NaN entries, missing readings, are allowed; inf never is)."""
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} must be an array of floats; got {type(value).__name__}") from exc
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers; got dtype {arr.dtype}")
    if arr.ndim not in ndims:
        expected = " or ".join(f"{d}-D" for d in ndims)
        raise ValueError(f"{name} must be {expected}; got shape {arr.shape}")
    arr = np.asarray(arr, dtype=np.float64)
    if allow_nan:
        if np.isinf(arr).any():
            raise ValueError(
                f"{name} contains inf (NaN marks a missing reading; inf is not a reading)"
            )
    elif not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def check_problem(theta, xdot) -> tuple[np.ndarray, np.ndarray, bool]:
    """Validate the data; return ``theta`` (m, p), ``xdot`` as (m, n) and whether it was 1-D."""
    theta = as_float_array(theta, "theta", (2,))
    xdot = as_float_array(xdot, "xdot", (1, 2))
    m, p = theta.shape
    if m == 0:
        raise ValueError("theta has no rows (m = 0): at least one sample is needed")
    if p == 0:
        raise ValueError("theta has no columns (p = 0): the library is empty")
    if xdot.shape[0] != m:
        raise ValueError(f"xdot has {xdot.shape[0]} rows but theta has {m}: they must match")
    one_d = xdot.ndim == 1
    if one_d:
        xdot = xdot[:, None]
    if xdot.shape[1] == 0:
        raise ValueError("xdot has no columns: at least one target is needed")
    return theta, xdot, one_d


def check_loss(loss) -> str:
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}; got {loss!r}")
    return loss


def per_column(value, name: str, n: int, *, positive: bool) -> np.ndarray:
    """Broadcast a scalar or a length-``n`` sequence to a float array of shape (n,)."""
    if isinstance(value, str):
        raise ValueError(f"{name} must be a number or one number per column; got {value!r}")
    arr = as_float_array(value, name, (0, 1))
    if arr.ndim == 1 and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} values but xdot has {n} columns")
    arr = np.broadcast_to(arr, (n,)).astype(np.float64)
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0; got {value!r}")
    if not positive and np.any(arr < 0):
        raise ValueError(f"{name} must be >= 0; got {value!r}")
    return arr


def check_lam(value, p: int, n: int, one_d: bool) -> np.ndarray:
    """L1 weights: one value, one per column (n,), or one per coordinate (p, n).

    For a 1-D target a vector of length ``p > 1`` is one weight per coordinate.  Returns
    (n,) for a weight per column and (p, n) for per-coordinate weights.
    """
    if isinstance(value, str):
        raise ValueError(f"lam must be a number, one per column or one per term; got {value!r}")
    arr = as_float_array(value, "lam", (0, 1, 2))
    per_term = arr.ndim == 2 or (one_d and arr.ndim == 1 and arr.shape[0] == p and p > 1)
    if not per_term:
        return per_column(arr, "lam", n, positive=False)
    arr = arr.reshape(p, 1) if arr.ndim == 1 else arr
    if arr.shape != (p, n):
        raise ValueError(f"lam per term must have shape ({p}, {n}); got {arr.shape}")
    if np.any(arr < 0):
        raise ValueError("lam must be >= 0")
    return arr.astype(np.float64)


def loss_delta(loss: str, delta, n: int) -> np.ndarray:
    """Per-column Huber threshold; ``inf`` for the squared loss (its limit)."""
    if check_loss(loss) == "squared":
        return np.full(n, np.inf)
    return per_column(delta, "delta", n, positive=True)


def check_coef(coef, p: int, n: int, one_d: bool, name: str = "coef") -> np.ndarray:
    """Validate a coefficient matrix against a problem of size (p, n); return it as (p, n)."""
    coef = as_float_array(coef, name, (1,) if one_d else (2,))
    expected = (p,) if one_d else (p, n)
    if coef.shape != expected:
        raise ValueError(f"{name} must have shape {expected}; got {coef.shape}")
    return coef.reshape(p, n)


def check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def check_positive(value, name: str, *, upper: float | None = None) -> float:
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or value <= 0 or (upper is not None and value >= upper):
        bound = f" and < {upper}" if upper is not None else ""
        raise ValueError(f"{name} must be a finite number > 0{bound}; got {value!r}")
    return float(value)


def check_time(t, name: str = "t", *, min_length: int = 2) -> np.ndarray:
    """Return ``t`` as a strictly increasing 1-D float array, or raise naming ``name``."""
    t = as_float_array(t, name, (1,))
    if t.size < min_length:
        raise ValueError(f"{name} must hold at least {min_length} time points; got {t.size}")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.argmax(steps <= 0)) + 1
        what = "repeats" if steps[i - 1] == 0 else "comes before"
        raise ValueError(
            f"{name} must be strictly increasing: {name}[{i}] = {float(t[i])!r} {what} "
            f"{name}[{i - 1}] = {float(t[i - 1])!r}"
            + (
                " (a time stamp logged twice: drop or merge the duplicated samples)"
                if what == "repeats"
                else " (sort the samples by time, or pass each record as its own trajectory)"
            )
        )
    return t
