"""Loss functions and proximal operators: small pure numpy pieces every solver reuses.

The Huber loss with threshold ``delta`` is

.. math::

    H_\\delta(a) = \\begin{cases} a^2/2 & |a| \\le \\delta \\\\
                   \\delta(|a| - \\delta/2) & |a| > \\delta \\end{cases}

and the squared loss is its limit ``delta -> inf``.  Every function here accepts
``delta = np.inf`` and then acts as the squared loss, so the Lasso baseline runs
through exactly the same code.  ``delta`` and ``rho`` broadcast against the data
(a per-column array of shape ``(n,)`` against an ``(m, n)`` array).
"""

from __future__ import annotations

import numpy as np

__all__ = ["huber", "huber_prox", "huber_psi", "soft_threshold"]


def huber_psi(a: np.ndarray, delta: float | np.ndarray) -> np.ndarray:
    """Derivative of the Huber loss, ``clip(a, -delta, delta)``."""
    return np.clip(a, -delta, delta)


def huber(a: np.ndarray, delta: float | np.ndarray, *, psi: np.ndarray | None = None) -> np.ndarray:
    """Elementwise Huber loss ``H_delta(a)`` (``a**2 / 2`` when ``delta`` is inf).

    Written branch-free as ``c * (a - c / 2)`` with ``c = psi_delta(a)``, which is
    exact in both branches and never forms ``inf - inf``; ``psi`` is
    ``huber_psi(a, delta)`` when the caller has it already.
    """
    c = huber_psi(a, delta) if psi is None else psi
    return c * (a - 0.5 * c)


def huber_prox(v: np.ndarray, delta: float | np.ndarray, rho: float | np.ndarray) -> np.ndarray:
    """Proximal operator of ``H_delta / rho``, elementwise.

    .. math::

        \\operatorname{prox}_{H_\\delta/\\rho}(v) = \\arg\\min_x H_\\delta(x)
        + \\frac{\\rho}{2}(x - v)^2
        = v - \\operatorname{clip}\\Big(\\frac{v}{1+\\rho}, -\\frac{\\delta}{\\rho},
        \\frac{\\delta}{\\rho}\\Big)

    i.e. ``rho v / (1 + rho)`` when ``|v| <= delta (1 + rho) / rho`` and
    ``v - (delta / rho) sign(v)`` otherwise.  (The paper's Eq. 11 prints a different,
    discontinuous map; see the errata in the documentation.)
    """
    bound = delta / rho
    return v - np.clip(v / (1.0 + rho), -bound, bound)


def soft_threshold(v: np.ndarray, t: float | np.ndarray) -> np.ndarray:
    """Elementwise soft threshold ``sign(v) * max(|v| - t, 0)``, the prox of ``t |.|``."""
    return np.sign(v) * np.maximum(np.abs(v) - t, 0.0)
