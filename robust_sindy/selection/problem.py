"""The regression every selection stage works on, in user units and standardised.

:class:`Problem` holds the library matrix and the targets of the samples in play, their
standardised twins (every decision is taken on those: SPEC §8), the trajectories'
slices among those samples, and the noise of the states carried through the
standardised library (the errors in the variables; None without the temporal screen).
:meth:`Problem.keep` restricts it to the samples the screens kept, with the same
scales, so that results on the kept samples map back to the user's units unchanged.

Read more in the user guide: :doc:`/guide/standardisation`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.scaling import Standardizer
from ..timeseries.trajectories import segments_of
from .bias import LibraryNoise

__all__ = ["Problem"]


@dataclass(frozen=True)
class Problem:
    """Library matrix and targets of some samples, in user units and standardised.

    Attributes
    ----------
    theta : ndarray (m, p)
        The library matrix (user units).
    y : ndarray (m, n)
        The targets (derivatives, user units).
    scaler : Standardizer
        The column scales (of all samples, kept or not).
    segments : list of slice
        Each trajectory's slice among these samples.
    noise : LibraryNoise or None
        Per state, the noise of the standardised library columns at every sample
        (:func:`~robust_sindy.selection.bias.noise_columns`).
    theta_s, y_s : ndarray
        ``theta`` and ``y`` standardised.
    """

    theta: np.ndarray
    y: np.ndarray
    scaler: Standardizer
    segments: list
    noise: LibraryNoise | None = None
    theta_s: np.ndarray = field(init=False, repr=False)
    y_s: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "theta_s", self.scaler.theta(self.theta))
        object.__setattr__(self, "y_s", self.scaler.y(self.y))

    @classmethod
    def standardise(cls, theta, y, segments, noise=None) -> Problem:
        """The problem of all samples, scaled by their root mean squares."""
        return cls(theta, y, Standardizer.from_data(theta, y), segments, noise)

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(m, p, n)``: samples, terms, equations."""
        return (self.theta.shape[0], self.theta.shape[1], self.y.shape[1])

    def keep(self, mask: np.ndarray) -> Problem:
        """The samples ``mask`` (bool, m), with the same scales."""
        noise = None if self.noise is None else self.noise.rows(mask)
        return Problem(
            self.theta[mask], self.y[mask], self.scaler, segments_of(mask, self.segments), noise
        )

    def delta_standard(self, delta) -> np.ndarray:
        """A Huber threshold per equation in user units, standardised."""
        return np.broadcast_to(delta, (self.y.shape[1],)) / self.scaler.y_scale
