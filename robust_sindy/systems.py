"""The paper's benchmark systems: vector fields, libraries and true coefficients.

Each system gives ``rhs(t, x, u)`` (vectorised over leading axes of ``x``), default
parameters and initial state, the paper's library (:meth:`library`), the true coefficient
matrix in that library's order (:meth:`true_coef`) and :meth:`generate`, which simulates
it by RK4 and returns the exact derivatives at the simulated states (README, "Experimental set-up").

Examples
--------
>>> from robust_sindy.systems import Lorenz
>>> data = Lorenz().generate()
>>> data.x.shape, data.x_dot.shape
((1001, 3), (1001, 3))
>>> Lorenz().true_coef()[:4].round(3)
array([[  0.   ,   0.   ,   0.   ],
       [-10.   ,  28.   ,   0.   ],
       [ 10.   ,  -1.   ,   0.   ],
       [  0.   ,   0.   ,  -2.667]])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .library import BaseLibrary, CustomLibrary, PolynomialLibrary
from .simulate import rk4

__all__ = ["Drone", "Lorenz", "Trajectory"]


class Trajectory(NamedTuple):
    """A simulated trajectory: times, states, exact derivatives, inputs (or ``None``)."""

    t: np.ndarray
    x: np.ndarray
    x_dot: np.ndarray
    u: np.ndarray | None


class _System:
    state_names: tuple[str, ...]
    control_names: tuple[str, ...] = ()
    #: The states whose derivatives the paper regresses (its tables' equations).
    targets: tuple[int, ...]

    @property
    def input_names(self) -> list[str]:
        """States then controls: the inputs of :meth:`library`."""
        return [*self.state_names, *self.control_names]

    def inputs(self, t) -> np.ndarray | None:
        """Control inputs at times ``t`` (``None`` for an autonomous system)."""
        return None

    def initial_state(self) -> np.ndarray:
        """The default initial state of :meth:`generate`."""
        return np.asarray(self.x0, dtype=float)

    def generate(self, t_end: float = 10.0, dt: float = 0.01, x0=None) -> Trajectory:
        """Simulate by RK4 with step ``dt`` and evaluate the exact derivatives at the
        simulated states (README, "Experimental set-up")."""
        t = np.linspace(0.0, t_end, round(t_end / dt) + 1)
        u = self.inputs(t)
        # the input signal itself (not its samples) drives the intermediate RK4 stages
        drive = None if u is None else self.inputs
        x = rk4(self.rhs, self.initial_state() if x0 is None else x0, t, drive)
        x_dot = self.rhs(t, x, u)
        return Trajectory(t, x, x_dot, u)

    def true_coef(self, full: bool = False) -> np.ndarray:
        """True coefficients (p, n) in :meth:`library` order for the paper's equations
        (``targets``), or for every state derivative with ``full=True``."""
        coef = self._true_coef_full()
        return coef if full else coef[:, list(self.targets)]

    def fitted_library(self) -> BaseLibrary:
        """:meth:`library` fitted to :attr:`input_names` (ready to ``transform``)."""
        return self.library().fit(
            np.zeros((1, len(self.input_names))), input_names=self.input_names
        )

    def feature_names(self) -> list[str]:
        return self.fitted_library().get_feature_names()


@dataclass(frozen=True)
class Lorenz(_System):
    """Lorenz system ``x' = s (y - x)``, ``y' = x (r - z) - y``, ``z' = x y - b z``.

    Defaults: ``sigma = 10``, ``rho = 28``, ``beta = 8/3``, ``x0 = (0, 1, 20)``
    (README, "Experimental set-up"; the sign of ``x y`` in ``z'`` is +, erratum E7).
    """

    sigma: float = 10.0
    rho: float = 28.0
    beta: float = 8.0 / 3.0
    x0: tuple[float, ...] = (0.0, 1.0, 20.0)
    state_names: tuple[str, ...] = ("x", "y", "z")
    targets: tuple[int, ...] = (0, 1, 2)

    def rhs(self, t, x, u=None) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        a, b, c = x[..., 0], x[..., 1], x[..., 2]
        return np.stack(
            [self.sigma * (b - a), a * (self.rho - c) - b, a * b - self.beta * c], axis=-1
        )

    def library(self) -> BaseLibrary:
        """All monomials of degree <= 2 in (x, y, z), with the bias (p = 10)."""
        return PolynomialLibrary(degree=2)

    def _true_coef_full(self) -> np.ndarray:
        coef = np.zeros((10, 3))  # 1, x, y, z, x^2, x*y, x*z, y^2, y*z, z^2
        coef[1, 0], coef[2, 0] = -self.sigma, self.sigma
        coef[1, 1], coef[2, 1], coef[6, 1] = self.rho, -1.0, -1.0
        coef[3, 2], coef[5, 2] = -self.beta, 1.0
        return coef


def _sines(t, amplitudes, freqs_hz, phases, fn):
    t = np.asarray(t, dtype=float)[..., None]
    w = 2 * np.pi * np.asarray(freqs_hz)
    return (np.asarray(amplitudes) * fn(w * t + np.asarray(phases))).sum(axis=-1)


@dataclass(frozen=True)
class Drone(_System):
    """Planar quadrotor (README, "Experimental set-up") with thrusts ``f1``, ``f2``.

    State ``(x, y, theta, x_dot, y_dot, theta_dot)``::

        x''     = -(f1 + f2) sin(theta) / mass
        y''     =  (f1 + f2) cos(theta) / mass - g
        theta'' =  arm (f1 - f2) / inertia

    Input design (the paper gives none).  Open loop, noise-free, built from sums of
    sinusoids between 0.25 and 1.7 Hz:

    * total thrust ``f1 + f2 = mass g + sum_k b_k sin(2 pi nu_k t + psi_k)``
      (hover plus 1 N of excitation in total);
    * differential thrust ``f1 - f2 = sum_k a_k cos(2 pi w_k t + phi_k)``.

    The attitude obeys ``theta'' = (arm / inertia)(f1 - f2)`` alone, so the default
    initial attitude and rate are chosen to make ``theta(t) = -(arm / inertia) sum_k a_k
    cos(2 pi w_k t + phi_k) / (2 pi w_k)^2`` exactly: a zero-mean oscillation of about
    0.1 rad that never drifts, and no stabiliser is needed.  Both ``f1 + f2`` and
    ``f1 - f2`` vary, so every library column is excited.
    """

    mass: float = 1.0
    arm: float = 0.086
    inertia: float = 0.1
    g: float = 9.81
    diff_amplitudes: tuple[float, ...] = (0.4, 0.2, 0.1)
    diff_freqs_hz: tuple[float, ...] = (0.3, 0.7, 1.5)
    diff_phases: tuple[float, ...] = (0.0, 1.0, 2.0)
    sum_amplitudes: tuple[float, ...] = (0.5, 0.3, 0.2)
    sum_freqs_hz: tuple[float, ...] = (0.25, 0.9, 1.7)
    sum_phases: tuple[float, ...] = (0.0, 0.5, 1.5)
    state_names: tuple[str, ...] = ("x", "y", "theta", "x_dot", "y_dot", "theta_dot")
    control_names: tuple[str, ...] = ("f1", "f2")
    targets: tuple[int, ...] = (3, 4, 5)
    x0: tuple[float, ...] | None = None

    def initial_state(self) -> np.ndarray:
        """``x0``, or by default ``(0, 0, theta0, 0, 0, omega0)`` consistent with the
        attitude excitation."""
        if self.x0 is not None:
            return np.asarray(self.x0, dtype=float)
        k = self.arm / self.inertia
        w = 2 * np.pi * np.asarray(self.diff_freqs_hz)
        a, phi = np.asarray(self.diff_amplitudes), np.asarray(self.diff_phases)
        theta0 = -k * np.sum(a * np.cos(phi) / w**2)
        omega0 = k * np.sum(a * np.sin(phi) / w)
        return np.array([0.0, 0.0, theta0, 0.0, 0.0, omega0])

    def inputs(self, t) -> np.ndarray:
        """Thrusts ``(f1, f2)`` at times ``t``: shape ``t.shape + (2,)``."""
        total = self.mass * self.g + _sines(
            t, self.sum_amplitudes, self.sum_freqs_hz, self.sum_phases, np.sin
        )
        diff = _sines(t, self.diff_amplitudes, self.diff_freqs_hz, self.diff_phases, np.cos)
        return np.stack([(total + diff) / 2, (total - diff) / 2], axis=-1)

    def rhs(self, t, x, u) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        theta = x[..., 2]
        total, diff = u[..., 0] + u[..., 1], u[..., 0] - u[..., 1]
        return np.stack(
            [
                x[..., 3],
                x[..., 4],
                x[..., 5],
                -total * np.sin(theta) / self.mass,
                total * np.cos(theta) / self.mass - self.g,
                self.arm * diff / self.inertia,
            ],
            axis=-1,
        )

    def library(self) -> BaseLibrary:
        """The paper's 7 functions: ``1, x_dot, y_dot, theta_dot, (f1+f2) sin(theta),
        (f1+f2) cos(theta), f1 - f2``."""
        return PolynomialLibrary(degree=1, inputs=["x_dot", "y_dot", "theta_dot"]) + (
            CustomLibrary(
                [
                    lambda th, f1, f2: (f1 + f2) * np.sin(th),
                    lambda th, f1, f2: (f1 + f2) * np.cos(th),
                    lambda f1, f2: f1 - f2,
                ],
                names=["(f1+f2)*sin(theta)", "(f1+f2)*cos(theta)", "f1-f2"],
                inputs=[["theta", "f1", "f2"], ["theta", "f1", "f2"], ["f1", "f2"]],
            )
        )

    def _true_coef_full(self) -> np.ndarray:
        coef = np.zeros((7, 6))
        coef[1, 0] = coef[2, 1] = coef[3, 2] = 1.0
        coef[4, 3] = -1.0 / self.mass
        coef[0, 4], coef[5, 4] = -self.g, 1.0 / self.mass
        coef[6, 5] = self.arm / self.inertia
        return coef
