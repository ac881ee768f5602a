"""What every solver returns to :func:`robust_sindy.fit`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SolverOutput:
    """Raw output of one solver run on all target columns.

    ``coef`` is (p, n) in the caller's units.  ``converged`` is the solver's own
    verdict per column; :func:`robust_sindy.fit` combines it with the
    solver-independent certificate before reporting convergence.
    """

    coef: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    messages: list[str]
    info: dict = field(default_factory=dict)
