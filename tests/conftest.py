"""Shared problem generators: random libraries with gross outliers and Lorenz libraries."""

from __future__ import annotations

from itertools import combinations_with_replacement

import numpy as np
import pytest


def lorenz_rhs(x: np.ndarray, sigma=10.0, rho=28.0, beta=8.0 / 3.0) -> np.ndarray:
    """Lorenz vector field for states stacked along the last axis."""
    x, y, z = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([sigma * (y - x), x * (rho - z) - y, x * y - beta * z], axis=-1)


def rk4_trajectory(x0, dt: float, m: int) -> np.ndarray:
    out = np.empty((m, len(x0)))
    out[0] = x = np.asarray(x0, dtype=float)
    for i in range(1, m):
        k1 = lorenz_rhs(x)
        k2 = lorenz_rhs(x + dt / 2 * k1)
        k3 = lorenz_rhs(x + dt / 2 * k2)
        k4 = lorenz_rhs(x + dt * k3)
        out[i] = x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return out


def monomials(x: np.ndarray, degree: int) -> np.ndarray:
    """All monomials up to ``degree`` including 1, in the order 1, x, y, z, xx, xy, ..."""
    cols = [np.ones(len(x))]
    for d in range(1, degree + 1):
        for idx in combinations_with_replacement(range(x.shape[1]), d):
            cols.append(np.prod(x[:, list(idx)], axis=1))
    return np.column_stack(cols)


LORENZ_TRUE = np.zeros((10, 3))
LORENZ_TRUE[[1, 2], 0] = [-10.0, 10.0]
LORENZ_TRUE[[1, 2, 6], 1] = [28.0, -1.0, -1.0]
LORENZ_TRUE[[3, 5], 2] = [-8.0 / 3.0, 1.0]


def lorenz_library(seed: int, degree: int = 2, m: int = 1001, noisy: bool = True):
    """SPEC section 6 set-up: states contaminated (20 % of rows at sigma 0.5), exact xdot."""
    x = rk4_trajectory([0.0, 1.0, 20.0], 0.01, m)
    xdot = lorenz_rhs(x)
    if noisy:
        rng = np.random.default_rng(seed)
        scale = np.full(m, 1e-3)
        scale[rng.choice(m, round(0.2 * m), replace=False)] = 0.5
        x = x + rng.normal(size=x.shape) * scale[:, None]
    return monomials(x, degree), xdot


def random_problem(seed: int, m=300, p=12, n=2, outliers=0.2, badly_scaled=False):
    """Sparse linear model with a fraction of gross outliers in the targets."""
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=(m, p))
    if badly_scaled:
        theta *= 10.0 ** rng.uniform(-3, 3, size=p)
    coef = np.zeros((p, n))
    for k in range(n):
        support = rng.choice(p, 3, replace=False)
        coef[support, k] = rng.uniform(1, 3, size=3) * rng.choice([-1, 1], 3)
        coef[:, k] /= np.linalg.norm(theta, axis=0) / np.sqrt(m)
    y = theta @ coef + 0.1 * rng.normal(size=(m, n))
    bad = rng.choice(m, round(outliers * m), replace=False)
    y[bad] += rng.normal(scale=30.0, size=(len(bad), n))
    return theta, y


def lambda_max(theta, y, delta):
    """Smallest lam with an all-zero solution, per column."""
    return np.abs(theta.T @ np.clip(y, -delta, delta)).max(axis=0)


@pytest.fixture(scope="session")
def lorenz2():
    return lorenz_library(seed=0, degree=2)
