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
  explains it.  A sample whose nearest reading of some state (or control) is more than
  half of :data:`~robust_sindy.timeseries.trajectories.GAP_STEPS` median steps away
  (in a run of missing readings as long as a gap in the record) is not filled into the
  fit at all: the strong form leaves it out, and the weak form's test functions do not
  reach it, as they do not reach across a gap (:func:`far_from_readings`);
* a missing **control** is filled by the same local fit of its readings, and its sample
  is a suspect of the row screen;
* a missing **measured derivative** leaves its sample out of the fit (there is no
  target to fit).

Read more in the user guide: :doc:`/guide/missing`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .temporal import HALF_WINDOW, fill_missing
from .trajectories import GAP_STEPS, Trajectories, reading_steps, runs

__all__ = ["GAP_HALF_WINDOW", "Missing", "far_from_readings", "long_gaps"]

#: Half window of the temporal screen's local fits: a filled entry in a run of more
#: missing entries than this (of the channel's own steps) is far from its readings.
GAP_HALF_WINDOW = HALF_WINDOW


def _times_of(t: list | None, segments) -> list:
    """Each trajectory's sample times, or equally spaced ones where ``t`` is None."""
    if t is None:
        return [np.arange(seg.stop - seg.start, dtype=float) for seg in segments]
    return list(t)


def long_gaps(
    lost: np.ndarray, segments, longer_than: int = GAP_HALF_WINDOW, t: list | None = None
) -> np.ndarray:
    """The entries of ``lost`` (m, k) in runs (per column, within each trajectory of
    ``segments``) longer than ``longer_than`` of the column's steps: whose readings on
    either side are more than ``longer_than + 1`` steps apart in time (a run at a
    record's end counts one step beyond its last sample).  The step is that of the
    column's readings (:func:`~robust_sindy.timeseries.trajectories.reading_steps`); at
    uniform times with most readings present,
    runs of more than ``longer_than`` missing entries.  ``t``: the sample times of each
    trajectory (None: equally spaced)."""
    out = np.zeros_like(lost)
    if not lost.any():
        return out
    for seg, ts in zip(segments, _times_of(t, segments), strict=True):
        part = lost[seg]
        if not part.any():
            continue
        own = reading_steps(ts, part)
        for k in np.flatnonzero(part.any(axis=0)):
            first, stop = runs(part[:, k])
            lo = np.where(first > 0, ts[np.maximum(first - 1, 0)], ts[first] - own[k])
            hi = np.where(stop < ts.size, ts[np.minimum(stop, ts.size - 1)], ts[stop - 1] + own[k])
            wide = hi - lo > (longer_than + 1) * own[k] * (1.0 + 1e-9)
            for a, b in zip(first[wide], stop[wide], strict=True):
                out[seg.start + a : seg.start + b, k] = True
    return out


def far_from_readings(lost: np.ndarray, t: list | None, segments) -> np.ndarray:
    """The samples (m,) at which some column of ``lost`` (m, k: missing entries,
    stacked over the trajectories ``segments`` with sample times ``t``) has no reading
    within ``GAP_STEPS / 2`` median steps: in an interval between two of its readings as
    long as a gap in the record, or beyond its last reading by more than half that.  The
    step is the median interval between the column's readings (a channel read every few
    samples has its own), or the trajectory's if that is longer.  Measured in time
    (irregular times alike) and in the record's own steps: unit-free.  Without the times
    (``t`` None: measured derivatives), the samples are taken as equally spaced."""
    out = np.zeros(lost.shape[0], dtype=bool)
    if not lost.any():
        return out
    for seg, ts in zip(segments, _times_of(t, segments), strict=True):
        part = lost[seg]
        if not part.any() or ts.size < 2:
            continue
        own = reading_steps(ts, part)
        far = np.zeros(ts.size, dtype=bool)
        for k in np.flatnonzero(part.any(axis=0)):
            read = ts[~part[:, k]]
            if read.size == 0:
                far[:] = True
                continue
            at = np.searchsorted(read, ts)
            left = read[np.maximum(at - 1, 0)]
            right = read[np.minimum(at, read.size - 1)]
            nearest = np.minimum(np.abs(ts - left), np.abs(right - ts))
            far |= nearest > 0.5 * GAP_STEPS * own[k]
        out[seg] = far
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
    far : ndarray of bool (m,)
        Samples too far from a reading of some state or control to be filled
        (:func:`far_from_readings`): left out of the fit.
    """

    states: np.ndarray
    controls: np.ndarray
    derivatives: np.ndarray
    suspect: np.ndarray
    far: np.ndarray

    @classmethod
    def of(cls, data: Trajectories) -> Missing:
        states, controls = data.missing, data.missing_controls
        return cls(
            states,
            controls,
            data.missing_derivatives,
            long_gaps(states, data.segments, t=data.t),
            far_from_readings(np.hstack([states, controls]), data.t, data.segments),
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

    @property
    def absent_rows(self) -> np.ndarray:
        """Samples (m,) the strong form leaves out: a missing measured derivative, or a
        reading too far to fill."""
        return self.derivative_rows | self.far

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
            missing_far_samples=int(self.far.sum()),
            missing_controls=int(self.controls.sum()),
            missing_derivative_samples=int(self.derivative_rows.sum()),
        )
