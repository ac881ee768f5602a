"""Missing readings: NaN in the states, controls or measured derivatives.

A NaN entry means "not measured".  Nothing is invented silently; each kind is handled
where it is needed, and :class:`Missing` records what was missing for the diagnostics:

* a missing **state** is a sample its component does not have: the temporal screen
  screens each component on its own readings at their times and fills the missing
  entries by the local polynomial of the nearest usable readings
  (:func:`~robust_sindy.timeseries.temporal.temporal_screen`, or
  :func:`~robust_sindy.timeseries.temporal.fill_missing` without the screen).  The
  robust derivatives give the filled entries no weight, like flagged ones; the library
  and the weak form's integrals use the filled values.  A filled entry inside a gap
  wider than the screen's half window (the fit then reaches far from it) makes its
  sample (test function) a suspect of the row screen, which keeps it only if the model
  explains it;
* a missing **control** is filled by the same local fit of its readings, and its sample
  is a suspect of the row screen;
* a missing **measured derivative** leaves its sample out of the fit (there is no
  target to fit).

Read more in the user guide: :doc:`/guide/missing`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from .temporal import HALF_WINDOW, fill_missing
from .trajectories import Trajectories

__all__ = ["GAP_HALF_WINDOW", "Missing", "long_gaps"]

#: Half window of the temporal screen's local fits: a filled entry in a run of more
#: missing entries than this is far from its readings.
GAP_HALF_WINDOW = HALF_WINDOW


def long_gaps(lost: np.ndarray, segments, longer_than: int = GAP_HALF_WINDOW) -> np.ndarray:
    """The entries of ``lost`` (m, k) in runs (per column, within each trajectory of
    ``segments``) of more than ``longer_than`` consecutive missing entries."""
    out = np.zeros_like(lost)
    if not lost.any():
        return out
    for seg in segments:
        for k in range(lost.shape[1]):
            runs, count = scipy.ndimage.label(lost[seg, k])
            if not count:
                continue
            sizes = np.bincount(runs)[1:]
            out[seg, k] = np.isin(runs, 1 + np.flatnonzero(sizes > longer_than))
    return out


@dataclass(frozen=True)
class Missing:
    """What the records did not measure (stacked masks over all samples).

    Attributes
    ----------
    states : ndarray of bool (m, n)
        Missing entries of the states.
    controls : ndarray of bool (m, q)
        Missing entries of the controls.
    derivatives : ndarray of bool (m, n)
        Missing entries of the measured derivatives.
    suspect : ndarray of bool (m, n)
        Missing state entries in gaps wider than the screen's half window.
    """

    states: np.ndarray
    controls: np.ndarray
    derivatives: np.ndarray
    suspect: np.ndarray

    @classmethod
    def of(cls, data: Trajectories) -> Missing:
        states = data.missing
        return cls(
            states,
            data.missing_controls,
            data.missing_derivatives,
            long_gaps(states, data.segments),
        )

    @property
    def any(self) -> bool:
        return bool(self.states.any() or self.controls.any() or self.derivatives.any())

    @property
    def controls_suspect(self) -> np.ndarray:
        """Samples (m, 1) with a missing control (filled: suspects of the row screen)."""
        return self.controls.any(axis=1, keepdims=True)

    @property
    def derivative_rows(self) -> np.ndarray:
        """Samples (m,) with a missing measured derivative (left out of the fit)."""
        return self.derivatives.any(axis=1)

    def filled_inputs(self, data: Trajectories, temporal) -> np.ndarray:
        """The library's inputs (states, then controls) with the missing states taken
        from ``temporal`` (the screen's fills) and the missing controls filled by the
        same local fit of their readings."""
        z = data.inputs()
        n = data.n_states
        if self.states.any():
            z[:, :n] = np.where(self.states, temporal.repaired, z[:, :n])
        if self.controls.any():
            z[:, n:] = fill_missing(data.u, data.t).repaired
        return z

    def summary(self) -> dict:
        """Counts for the diagnostics."""
        return dict(
            missing_states=self.states.sum(axis=0).astype(int),
            missing_in_gaps=int(self.suspect.sum()),
            missing_controls=int(self.controls.sum()),
            missing_derivative_samples=int(self.derivative_rows.sum()),
        )
