"""Shared problem generators: random libraries with gross outliers and Lorenz libraries."""

from __future__ import annotations

import os

# The tests check what the compiled kernels do: compiled in the test process on first
# use, not in the background (see robust_sindy.core.compiled).
os.environ.setdefault("ROBUST_SINDY_KERNELS", "wait")

import numpy as np
import pytest

from robust_sindy import PolynomialLibrary
from robust_sindy.noise import contaminate
from robust_sindy.systems import Lorenz

LORENZ_TRUE = Lorenz().true_coef()


def lorenz_library(seed: int, degree: int = 2, m: int = 1001, noisy: bool = True):
    """The paper's set-up: states contaminated (20 % of rows at sigma 0.5), exact xdot."""
    data = Lorenz().generate(t_end=(m - 1) * 0.01)
    x = data.x
    if noisy:
        x = contaminate(x, rng=np.random.default_rng(seed)).x
    return PolynomialLibrary(degree=degree).fit_transform(x), data.x_dot


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


@pytest.fixture(scope="session")
def lorenz2():
    return lorenz_library(seed=0, degree=2)


def van_der_pol(mu, seed, m=2000, dt=0.05):
    """Times and states of Van der Pol's oscillator after a burn-in of 100 time units,
    noise 1e-3 of each state's spread."""
    import scipy.integrate

    rng = np.random.default_rng(seed)

    def rhs(_, v):
        return [v[1], mu * v[1] - mu * v[0] ** 2 * v[1] - v[0]]

    t = 100.0 + dt * np.arange(m)
    ic = np.array([2.0, 0.0]) * (1 + 0.05 * rng.normal(size=2))
    sol = scipy.integrate.solve_ivp(rhs, (0, t[-1]), ic, t_eval=t, rtol=1e-10, atol=1e-12)
    x = sol.y.T
    return t - t[0], x + 1e-3 * x.std(axis=0) * rng.normal(size=x.shape)


def mean_field_rhs(_, v):
    """The mean-field model of a wake (growth 0.2, frequency 2, coupling 0.5, damping 1):
    a limit cycle of radius 0.894 at the shift level 0.4, energy-preserving."""
    a, b, c = v
    return [0.2 * a - 2 * b - 0.5 * a * c, 2 * a + 0.2 * b - 0.5 * b * c,
            -c + 0.5 * (a * a + b * b)]  # fmt: skip


def mean_field_record(t_end: float, samples: int):
    """Times and exact states of :func:`mean_field_rhs` from (0.01, 0, 0)."""
    import scipy.integrate

    t = np.linspace(0, t_end, samples)
    sol = scipy.integrate.solve_ivp(
        mean_field_rhs, (0, t_end), [0.01, 0, 0], t_eval=t, rtol=1e-10, atol=1e-12
    )
    return t, sol.y.T


def mean_field_support(model) -> np.ndarray:
    """The true support of :func:`mean_field_rhs` in a fitted model's terms (n, p)."""
    names = model.get_feature_names()
    truth = np.zeros((3, len(names)), dtype=bool)
    for k, terms in enumerate([("x0", "x1", "x0*x2"), ("x0", "x1", "x1*x2"),
                               ("x2", "x0^2", "x1^2")]):  # fmt: skip
        truth[k, [names.index(v) for v in terms]] = True
    return truth
