"""The derivative stage: the targets of the regression when ``x_dot`` is not measured.

:func:`derivatives` differentiates every trajectory by the estimator's
``differentiation``: ``"robust"`` (the default) differentiates the temporal screen's
repaired states, its flagged entries given no weight, by local quartics over windows
chosen from the data (:func:`~robust_sindy.timeseries.differentiation.choose_half_window`,
guarded by the library); ``"finite_difference"`` and ``"savgol"`` differentiate the
repaired states; a callable receives ``(x, t)``.  With the screen, the samples whose
robust derivatives the sampling does not resolve are found
(:func:`~robust_sindy.timeseries.differentiation.unresolved_derivatives`), and the
derivatives of two orders higher are kept as the reference for their truncation error.
A state that does not move (constant up to rounding) gets derivative 0.

Read more in the user guide: :doc:`/guide/derivatives`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.statistics import ALIAS_RTOL
from ..core.validation import as_float_array
from .differentiation import (
    choose_half_window,
    finite_difference,
    higher_order_derivative,
    local_polynomial_derivative,
    savgol_derivative,
    unresolved_derivatives,
)
from .temporal import TemporalScreening, temporal_screen
from .trajectories import Trajectories

__all__ = [
    "DERIVATIVE_WINDOWS",
    "DIFFERENTIATIONS",
    "FIXED_HALF_WINDOW",
    "Derivatives",
    "check_differentiation",
    "chunk_derivative",
    "derivatives",
    "differentiate",
    "trajectory_derivative",
]

#: Half width (samples on each side) of the robust derivatives' local quartics with
#: ``derivative_window="fixed"``: the fourth-order central difference.
FIXED_HALF_WINDOW = 2
#: The choices of ``derivative_window``.
DERIVATIVE_WINDOWS = ("auto", "fixed")

_DIFFERENTIATION = {
    "robust": None,  # local polynomials, temporal outliers given no weight
    "finite_difference": finite_difference,
    "savgol": savgol_derivative,
}
#: The named choices of ``differentiation`` (a callable is the other).
DIFFERENTIATIONS = tuple(_DIFFERENTIATION)


def check_differentiation(how) -> None:
    """A ``ValueError`` unless ``how`` is a named differentiation or a callable."""
    if not callable(how) and how not in _DIFFERENTIATION:
        raise ValueError(
            f"differentiation must be one of {DIFFERENTIATIONS} or a callable; got {how!r}"
        )


def _is_robust(how) -> bool:
    return isinstance(how, str) and how == "robust"


@dataclass(frozen=True)
class Derivatives:
    """Outcome of :func:`derivatives`.

    Attributes
    ----------
    y : ndarray (m, n)
        The derivatives of all samples, stacked (the regression's targets).
    measured : bool
        Whether they were given (``x_dot``) rather than estimated.
    unresolved : ndarray of bool (m,)
        Samples whose estimated derivatives the sampling does not resolve.
    reference : ndarray (m, n) or None
        The derivatives two orders higher, the reference for the truncation error
        (None unless every trajectory has them).
    windows : ndarray of int (n,)
        Half width of each state's robust local quartics (the widest over the
        trajectories; 0 for measured derivatives and other differentiations).
    """

    y: np.ndarray
    measured: bool
    unresolved: np.ndarray
    reference: np.ndarray | None
    windows: np.ndarray


def robust_derivative(repaired, t, usable, noise, window: str, library=None, half=None):
    """``differentiation="robust"`` of repaired states (``usable``: the entries the
    temporal screen left alone; ``noise``: its noise levels) and the half windows used:
    ``half`` when given, else as ``window`` says (``"auto"``: the automatic choice,
    guarded by the ``library`` matrix when given: each state on its own usable samples
    of those where at most half the readings are flagged or missing, since a sample
    most of whose readings are off is a corrupted row, whose other readings are suspect
    too and whose library row is mostly repairs)."""
    if half is None:
        half = np.full(repaired.shape[1], FIXED_HALF_WINDOW)
        if window == "auto":
            rows = 2 * (~usable).sum(axis=1) <= usable.shape[1]
            half = choose_half_window(repaired, t, usable, library=library, rows=rows, scale=noise)
    d = local_polynomial_derivative(repaired, t, half, mask=usable, scale=noise)
    return d, half


def differentiate(
    x, t, how, window: str = "auto", *, half_window=None, scale=None, library=None
) -> np.ndarray:
    """Derivatives of one trajectory by ``how`` (the estimator's ``differentiation``).

    The robust one screens ``x`` in time itself, and uses the half windows
    ``half_window`` or chooses them as ``window`` says (guarded by the ``library``
    matrix of ``x`` when given; a fit gives it that of the repaired states); ``scale``:
    the states' noise for its Huber fits (by default the temporal screen's).
    """
    if callable(how):
        out = as_float_array(how(x, t), "differentiation output", (2,))
        if out.shape != x.shape:
            raise ValueError(f"differentiation returned shape {out.shape}; expected {x.shape}")
        return out
    check_differentiation(how)
    if _is_robust(how):
        screen = temporal_screen(x, t)
        scale = screen.scale if scale is None else scale
        return robust_derivative(
            screen.repaired, t, ~screen.flags, scale, window, library, half_window
        )[0]
    return _DIFFERENTIATION[how](x, t)


def trajectory_derivative(
    x, t, how, window: str, check: bool, screened=None, noise=None, library=None, half=None
):
    """One trajectory's derivatives by ``how``, the half windows of the robust ones
    (None for the others), the samples (m,) whose derivatives the sampling does not
    resolve (:func:`unresolved_derivatives` of any moving state; robust differentiation
    with ``check`` only), and the higher-order derivatives they were judged against
    (:func:`higher_order_derivative`; None where they were not).

    ``screened``: ``(repaired, usable)`` from the temporal screen of ``x``, whose
    repaired states are differentiated (robust differentiation screens ``x`` itself
    when None); ``noise``: the states' noise levels (by default that screen's);
    ``library`` and ``half``: as in :func:`robust_derivative`.  A state that does not
    move (its range within ``ALIAS_RTOL`` of its magnitude: constant up to rounding) has
    derivative 0, not the rounding of its differences, which standardisation would blow
    up to unit size.
    """
    states = x if screened is None else screened[0]
    loose = np.zeros(x.shape, dtype=bool)
    high = None
    if _is_robust(how):
        if screened is None:  # screen=False: the derivatives' own screen
            own = temporal_screen(x, t)
            repaired, usable, noise = own.repaired, ~own.flags, own.scale
        else:
            repaired, usable = screened
        d, half = robust_derivative(repaired, t, usable, noise, window, library, half)
        if check:
            high = higher_order_derivative(repaired, t, half, mask=usable, scale=noise)
            loose = unresolved_derivatives(
                repaired, t, d, half, mask=usable, scale=noise, high=high
            )
    else:
        d, half = differentiate(states, t, how, window), None
    still = np.ptp(states, axis=0) <= ALIAS_RTOL * np.max(np.abs(states), axis=0)
    d = np.array(d, dtype=float)
    d[:, still] = 0.0
    if high is not None:
        high = np.where(np.isnan(high), d, high)  # a component too short: no reference
        high[:, still] = 0.0
    return d, half, loose[:, ~still].any(axis=1), high


def derivatives(
    data: Trajectories,
    temporal: TemporalScreening | None,
    how: str | Callable,
    window: str,
    check: bool,
    library: np.ndarray,
) -> Derivatives:
    """The regression's targets: the measured derivatives, or each trajectory's estimated
    ones (of the repaired states, outliers given no weight, over windows the ``library``
    matrix (of the repaired states, all samples) cannot tell from the narrowest one),
    with the samples whose derivatives the sampling does not resolve and the
    higher-order reference (:func:`trajectory_derivative`; ``check``: look for those
    samples)."""
    m, n = data.n_samples, data.n_states
    if data.x_dot is not None:
        # A missing measured derivative (NaN) has no target: its sample is left out of
        # the fit (robust_sindy.timeseries.missing); 0 only keeps the arrays finite.
        y = np.nan_to_num(np.vstack(data.x_dot), nan=0.0)
        return Derivatives(y, True, np.zeros(m, dtype=bool), None, np.zeros(n, dtype=int))
    out, highs, windows = [], [], [np.zeros(n, dtype=int)]
    unresolved = np.zeros(m, dtype=bool)
    for seg, a, ti in zip(data.segments, data.x, data.t, strict=True):
        screened, noise = None, None
        if temporal is not None:
            screened = (temporal.repaired[seg], ~temporal.flags[seg])
            noise = temporal.scale
        d, half, unresolved[seg], high = trajectory_derivative(
            a, ti, how, window, check, screened, noise, library=library[seg]
        )
        if half is not None:
            windows.append(half)
        out.append(d)
        highs.append(high)
    reference = None if any(h is None for h in highs) else np.vstack(highs)
    y = np.vstack(out)
    if not np.all(np.isfinite(y)):
        raise ValueError("the derivatives contain NaN or inf")
    return Derivatives(y, False, unresolved, reference, np.max(windows, axis=0))


def chunk_derivative(block, dt, how, window, screen, half, noise, check=False):
    """Derivatives of one Dask chunk of states (``block``, with its overlap) as a fit
    estimates them in memory (its own temporal screen when ``screen``, the windows
    ``half`` and noise levels ``noise`` of the sample the model was chosen on); with
    ``check``, instead, its samples whose derivatives the sampling does not resolve,
    repeated across the columns."""
    tb = dt * np.arange(block.shape[0])
    screened, level = None, noise
    if screen:
        own = temporal_screen(block, tb)
        screened = (own.repaired, ~own.flags)
        level = own.scale if noise is None else noise
    d, _, loose, _ = trajectory_derivative(
        block, tb, how, window, screen and check, screened, level, half=half
    )
    return np.repeat(loose[:, None], block.shape[1], axis=1) if check else d
