"""Polynomial flows of the dysts database, with their true coefficients.

Every continuous-time system of `dysts <https://github.com/williamgilpin/dysts>`_ with at
most four states whose right-hand side is a polynomial of degree at most three
(:func:`polynomial_systems`, or one by name: :func:`polynomial_system`), simulated
locally (:func:`simulate_system`): the systems of the zoo (:mod:`robust_sindy.zoo`) and
of the noise frontier (:mod:`robust_sindy.frontier`).

* The true coefficients come from the right-hand side itself: an exact least-squares fit
  of the full monomial library on random points (relative residual below ``1e-9``), the
  entries below ``1e-9`` of the largest set to zero; the library degree is the smallest
  that reproduces the right-hand side.
* Trajectories are integrated locally (``scipy.integrate.solve_ivp``, DOP853, tolerance
  ``1e-10``) on the identified polynomial, from the system's initial condition after a
  burn-in that depends on the seed, at ``pts_per_period`` samples per dominant period.

Needs dysts (the extra ``zoo``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from itertools import combinations_with_replacement

import numpy as np
import scipy.integrate

__all__ = [
    "LORENZ96_STEP",
    "ZooSystem",
    "lorenz96",
    "lorenz96_records",
    "monomial_factors",
    "monomial_powers",
    "monomials",
    "polynomial_system",
    "polynomial_systems",
    "simulate_system",
    "write_rows",
]


_COEF_CUT = 1e-9


@dataclass
class ZooSystem:
    """A polynomial flow: its monomials, true coefficients and sampling."""

    name: str
    n_states: int
    degree: int
    powers: list  # monomials as tuples of state indices
    coef: np.ndarray  # (p, n) true coefficients
    ic: np.ndarray
    dt: float
    _factor_cache: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def library_matrix(self, x: np.ndarray) -> np.ndarray:
        """The monomials at the states ``x`` (m, n), as :func:`monomials` forms them."""
        if self._factor_cache is None or self._factor_cache[0] is not self.powers:
            self._factor_cache = (self.powers, monomial_factors(self.powers, self.n_states))
        return monomials(x, self._factor_cache[1])

    def rhs(self, x: np.ndarray) -> np.ndarray:
        return self.library_matrix(np.atleast_2d(x)) @ self.coef


def monomial_powers(n: int, degree: int) -> list:
    """The monomials of degree at most ``degree`` in ``n`` states, as tuples of state
    indices, by degree and then lexicographically (the order of
    :class:`robust_sindy.PolynomialLibrary`)."""
    return [c for d in range(degree + 1) for c in combinations_with_replacement(range(n), d)]


def monomial_factors(powers, n_states: int) -> np.ndarray:
    """The state index of each factor of each monomial of ``powers`` (tuples of state
    indices), as an array (p, longest): ``n_states`` past a monomial's last factor, the
    index of a column of ones that :func:`monomials` appends."""
    longest = max((len(c) for c in powers), default=0)
    factors = np.full((len(powers), longest), n_states, dtype=np.intp)
    for j, combo in enumerate(powers):
        factors[j, : len(combo)] = combo
    return factors


def monomials(x: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """The monomials with the ``factors`` of :func:`monomial_factors` at the states ``x``
    (m, n_states): each the product of its factors from the left, starting from 1, all
    at once (a factor of 1 pads the shorter ones, which is exact)."""
    padded = np.ones((x.shape[0], x.shape[1] + 1))
    padded[:, : x.shape[1]] = x
    out = np.ones((x.shape[0], factors.shape[0]))
    for k in range(factors.shape[1]):
        out *= padded[:, factors[:, k]]
    return out


#: Per ``max_states``: the dysts flows that pass the checks made without evaluating
#: their right-hand sides, each with its random points (drawn in dysts' order).
_SCANS: dict = {}
#: Per ``(max_states, max_degree, name)``: the polynomial flow, or None if it is not one.
_FOUND: dict = {}


def polynomial_systems(
    max_states: int = 4, max_degree: int = 3, *, names=None, first: int | None = None
) -> list[ZooSystem]:
    """The dysts flows whose right-hand side is a polynomial (see the module docstring),
    in dysts' order.

    Evaluating a flow's right-hand side compiles it (a fraction of a second each, about
    half a minute for all of them), so only the flows asked for are evaluated: those
    named in ``names`` (an iterable of dysts names; every flow when omitted), up to the
    ``first`` polynomial ones.  Each flow is fitted on the same random points whichever
    are asked for, so its coefficients do not depend on the others asked for with it.
    """
    wanted = None if names is None else set(names)
    out = []
    for name, system, ic, x in _scan(max_states):
        if first is not None and len(out) >= first:
            break
        if wanted is not None and name not in wanted:
            continue
        key = (max_states, max_degree, name)
        if key not in _FOUND:
            _FOUND[key] = _fitted(name, system, ic, x, max_degree)
        if _FOUND[key] is not None:
            out.append(_FOUND[key])
    return out


def polynomial_system(name: str, max_states: int = 4, max_degree: int = 3) -> ZooSystem:
    """The polynomial flow ``name`` of :func:`polynomial_systems` (only it evaluated)."""
    found = polynomial_systems(max_states, max_degree, names=[name])
    if not found:
        raise ValueError(
            f"name: {name!r} is not a dysts flow with at most {max_states} states whose "
            f"right-hand side is a polynomial of degree at most {max_degree}"
        )
    return found[0]


def _scan(max_states: int) -> list:
    """``(name, system, initial condition, points)`` of the dysts flows with at most
    ``max_states`` states, without delay and autonomous (random points about the initial
    condition, from one generator in dysts' order)."""
    if max_states in _SCANS:
        return _SCANS[max_states]
    import dysts.flows as flows
    from dysts.systems import get_attractor_list

    out = []
    rng = np.random.default_rng(0)
    for name in get_attractor_list():
        try:
            system = getattr(flows, name)()
        except Exception:  # a system dysts cannot build here is not in the zoo
            continue
        n = int(system.dimension)
        if n > max_states or getattr(system, "delay", False):
            continue
        if getattr(system, "nonautonomous", False):
            continue
        ic = np.asarray(system.ic, dtype=float).ravel()
        out.append((name, system, ic, ic + rng.normal(size=(60 * n * n, n)) * (np.abs(ic) + 1.0)))
    _SCANS[max_states] = out
    return out


def _fitted(name: str, system, ic: np.ndarray, x: np.ndarray, max_degree: int):
    """The flow ``system`` (initial condition ``ic``) as a :class:`ZooSystem`, from its
    right-hand side at the points ``x``, or None if no polynomial up to ``max_degree``
    reproduces it."""
    n = x.shape[1]
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        try:
            f = np.array([np.asarray(system.rhs(v, 0.0), float) for v in x])
        except Exception:
            return None
    if f.shape != x.shape or not np.all(np.isfinite(f)):
        return None
    for degree in range(1, max_degree + 1):
        powers = monomial_powers(n, degree)
        zs = ZooSystem(name, n, degree, powers, np.zeros((len(powers), n)), ic, 0.0)
        th = zs.library_matrix(x)
        coef = np.linalg.lstsq(th, f, rcond=None)[0]
        if np.linalg.norm(th @ coef - f) <= 1e-9 * np.linalg.norm(f):
            coef[np.abs(coef) < _COEF_CUT * np.abs(coef).max()] = 0.0
            zs.coef = coef
            zs.degree = max(degree, 2)
            if zs.degree != degree:
                zs.powers = monomial_powers(n, zs.degree)
                zs.coef = np.vstack([coef, np.zeros((len(zs.powers) - len(powers), n))])
            zs.dt = float(system.period) / 100.0
            return zs
    return None


#: The sampling step of the zoo's Lorenz-96 records: about 100 samples over the
#: decorrelation time of its chaos (F = 8).
LORENZ96_STEP = 0.01


def lorenz96(n_states: int, forcing: float = 8.0) -> ZooSystem:
    """Lorenz-96 with ``n_states`` states, ``x_i' = (x_i+1 - x_i-2) x_i-1 - x_i + F``
    (indices cyclic), on the quadratic monomials: the zoo's system with many channels."""
    n = int(n_states)
    powers = monomial_powers(n, 2)
    where = {c: j for j, c in enumerate(powers)}
    coef = np.zeros((len(powers), n))
    for i in range(n):
        coef[where[tuple(sorted(((i + 1) % n, (i - 1) % n)))], i] += 1.0
        coef[where[tuple(sorted(((i - 2) % n, (i - 1) % n)))], i] -= 1.0
        coef[where[(i,)], i] = -1.0
        coef[where[()], i] = forcing
    ic = forcing + np.sin(np.arange(n))
    return ZooSystem(f"Lorenz96_{n}", n, 2, powers, coef, ic, LORENZ96_STEP)


def _l96(_t, v, forcing):
    return (np.roll(v, -1) - np.roll(v, 2)) * np.roll(v, 1) - v + forcing


def lorenz96_records(
    n_states: int, n_samples: int, seed: int = 0, forcing: float = 8.0, times=None
):
    """Times, states and exact derivatives of Lorenz-96 (``n_states``, the zoo's
    sampling step 0.01 after a seed-dependent burn-in, or at ``times``, from 0 and
    increasing, when given), and the system (:func:`robust_sindy.flows.lorenz96`: its
    true coefficients on the degree-2 monomials).  The right-hand side is evaluated
    directly, not through the library."""
    system = lorenz96(n_states)
    dt = system.dt
    burn = 5.0 + dt * n_samples * (0.5 + (seed % 7) / 7.0)
    steps = dt * np.arange(n_samples) if times is None else np.asarray(times, dtype=float)
    t_eval = burn + steps
    ic = system.ic + 1e-3 * np.random.default_rng(seed).normal(size=n_states)
    x = _integrate(lambda _t, v: _l96(_t, v, forcing), ic, t_eval, system.name)
    x_dot = np.array([_l96(0.0, v, forcing) for v in x])
    return t_eval - t_eval[0], x, x_dot, system


def simulate_system(
    system: ZooSystem, n_samples: int, seed: int, pts_per_period: int = 100, times=None
):
    """True states and derivatives: ``n_samples`` samples after a seed-dependent burn-in,
    uniformly spaced, or at ``times`` (from 0, increasing) when given."""
    dt = system.dt * 100.0 / pts_per_period
    burn = dt * n_samples * (0.5 + (seed % 7) / 7.0)

    def rhs(_t, v):
        return system.rhs(v)[0]

    t_eval = burn + (dt * np.arange(n_samples) if times is None else np.asarray(times, float))
    x = _integrate(rhs, system.ic, t_eval, system.name)
    return t_eval - t_eval[0], x, system.rhs(x)


def _integrate(rhs, ic, t_eval, name: str) -> np.ndarray:
    """States (len(t_eval), n) of ``v' = rhs(t, v)`` from ``ic`` at time 0, at the
    increasing times ``t_eval`` (DOP853, tolerances 1e-10), checked."""
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, t_eval[-1]), ic, method="DOP853", t_eval=t_eval, rtol=1e-10, atol=1e-10
    )
    if not sol.success or sol.y.shape[1] != t_eval.size or not np.all(np.isfinite(sol.y)):
        raise RuntimeError(f"{name}: integration failed ({sol.message})")
    return sol.y.T


def write_rows(rows: list[dict], path) -> None:
    """The per-case rows of a run over the flows (dicts with the same keys) as CSV at
    ``path``, its folder created."""
    import csv
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
