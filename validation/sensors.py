"""Records as sensors deliver them, on systems the zoo does not hold: a control input,
a transient, twenty channels.

The zoo (``robust-sindy zoo``) runs the sensor families (``robust_sindy.zoo``:
``missing``, ``glitches``, ``irregular``, ``jitter``, ``gaps``) on the polynomial flows of
dysts and on Lorenz-96 with 6 and 10 states.  This script runs the same families, with
the same contamination (``zoo.contaminate_family``, ``zoo.sample_times``), on

* ``DuffingForced``: a cubic oscillator driven by a control input ``u`` (states then
  ``u`` in a cubic library): a glitch or a missing reading next to a control;
* ``Hopf``: the Hopf normal form on its transient from near the origin to the limit
  cycle (a cubic library; on the cycle itself ``x^3 + x y^2 = x`` and the terms alias);
* ``Lorenz96_20``: twenty channels, where 56 % of the samples hold a glitched entry;

the glitches at uniformly random times together (``glitches+irregular``), and a
channel offline for a while (``outages``: three stretches of 5 % of the samples, each
in one channel drawn at random, NaN), with
exact derivatives and from the states alone, ``HuberSINDy()`` with its defaults
beside PySINDy's STLSQ (its default threshold, the samples with a missing entry left
out, the sample times as an array).

    python validation/sensors.py [--seeds 3] [--out validation/results/sensors]

``--systems Lorenz96_14,Lorenz96_30 --first-seed 5 --derivatives states`` runs other
channel counts (``Lorenz96_N`` for any N of at least 4; ``LorenzRing_N``, N Lorenz
systems on a ring, each driven by the next: 3 N channels; ``VanDerPolRing_N``, N Van
der Pol oscillators on a ring in a cubic library: 2 N channels; ``RosslerRing_N``, N
Rössler systems on a ring: 3 N channels; ``LotkaVolterra4``, four competing species),
seeds and derivatives;
``--families glitches --glitches 100,1000`` some of the families, with glitches of
another size (in spreads of the state).  ``sensors.csv`` holds, per fit, the kinds of
every warning with their counts (``kinds``) and their messages (``warnings``, the first
300 characters).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.integrate
from joblib import Parallel, delayed

from robust_sindy import HuberSINDy, PolynomialLibrary, zoo
from robust_sindy.diagnostics import count_kinds, kind_of
from robust_sindy.flows import (
    lorenz96,
    monomial_factors,
    monomial_powers,
    monomials,
    write_rows,
)

SYSTEMS = ("DuffingForced", "Hopf", "Lorenz96_20")
#: The zoo's sensor families, glitches at uniformly random times (a logger's own
#: time stamps and a channel's glitches together), and ``outages``: a channel offline
#: for a while, three times (:data:`OUTAGES`).
FAMILIES = (*zoo.SENSOR_FAMILIES, "glitches+irregular", "outages")
#: ``outages``: this many stretches of this fraction of the samples each, every one in a
#: channel drawn at random, not measured (NaN).
OUTAGES, OUTAGE_FRACTION = 3, 0.05


class System:
    """A polynomial right-hand side in the states (and a control ``u(t)``)."""

    def __init__(self, name, n, degree, coef, ic, dt, burn=None, forcing=None):
        self.name, self.n, self.degree, self.coef = name, n, degree, coef
        self.ic, self.dt, self.burn, self.forcing = np.asarray(ic, float), dt, burn, forcing
        self.powers = monomial_powers(n + (forcing is not None), degree)
        self._factors = monomial_factors(self.powers, n + (forcing is not None))

    def library(self, z):
        return monomials(z, self._factors)


def _system(name: str) -> System:
    if name == "DuffingForced":
        powers = monomial_powers(3, 3)  # x0, x1, u0
        at = {c: j for j, c in enumerate(powers)}
        coef = np.zeros((len(powers), 2))
        coef[at[(1,)], 0] = 1.0
        coef[at[(0,)], 1], coef[at[(1,)], 1], coef[at[(0, 0, 0)], 1] = -1.0, -0.2, -1.0
        coef[at[(2,)], 1] = 1.0

        def forcing(t):
            return 0.8 * np.sin(1.3 * t) + 0.5 * np.sin(2.9 * t + 1.0)

        return System(name, 2, 3, coef, [1.0, 0.0], 0.03, forcing=forcing)
    if name == "Hopf":
        powers = monomial_powers(2, 3)
        at = {c: j for j, c in enumerate(powers)}
        coef = np.zeros((len(powers), 2))
        mu = 0.2
        coef[at[(0,)], 0], coef[at[(1,)], 0] = mu, -1.0
        coef[at[(0, 0, 0)], 0], coef[at[(0, 1, 1)], 0] = -1.0, -1.0
        coef[at[(0,)], 1], coef[at[(1,)], 1] = 1.0, mu
        coef[at[(0, 0, 1)], 1], coef[at[(1, 1, 1)], 1] = -1.0, -1.0
        return System(name, 2, 3, coef, [0.05, 0.0], 0.02, burn=0.0)
    if name == "LotkaVolterra4":
        return _lotka_volterra4(name)
    prefix, _, size = name.partition("_")
    rings = ("LorenzRing", "VanDerPolRing", "RosslerRing")
    if prefix not in ("Lorenz96", *rings) or not size.isdigit():
        raise ValueError(
            f"unknown system {name!r}: DuffingForced, Hopf, LotkaVolterra4, Lorenz96_N, "
            "LorenzRing_N, VanDerPolRing_N or RosslerRing_N"
        )
    if prefix == "LorenzRing":
        return _lorenz_ring(name, int(size))
    if prefix == "RosslerRing":
        return _rossler_ring(name, int(size))
    if prefix == "VanDerPolRing":
        return _van_der_pol_ring(name, int(size))
    zs = lorenz96(int(size))
    return System(name, zs.n_states, 2, zs.coef, zs.ic, zs.dt)


def _ring(name: str, size: int, per: int, degree: int, terms) -> tuple[int, np.ndarray]:
    """States and coefficients (on the monomials up to ``degree``) of ``size`` systems of
    ``per`` states on a ring: ``terms(first, following, i)`` gives system ``i``'s terms
    as ``{(equation, monomial): value}``, its states from ``first`` on, the next
    system's from ``following``; at least two (a ring of one drives itself)."""
    if size < 2:
        prefix = name.partition("_")[0]
        raise ValueError(f"unknown system {name!r}: {prefix}_N needs N of at least 2")
    n = per * size
    powers = monomial_powers(n, degree)
    at = {c: j for j, c in enumerate(powers)}
    coef = np.zeros((len(powers), n))
    for i in range(size):
        for (eq, monomial), value in terms(per * i, per * ((i + 1) % size), i).items():
            coef[at[monomial], eq] = value
    return n, coef


def _lorenz_ring(name: str, size: int, coupling: float = 0.5) -> System:
    """``size`` Lorenz systems (3 ``size`` states) on a ring, each driven through its
    first state by the next one's: ``x_i' = 10 (y_i - x_i) + c (x_{i+1} - x_i)``,
    ``y_i' = x_i (28 - z_i) - y_i``, ``z_i' = x_i y_i - 8/3 z_i``; at least two."""

    def terms(x, nxt, i):
        y, z = x + 1, x + 2
        return {
            (x, (y,)): 10.0, (x, (x,)): -10.0 - coupling, (x, (nxt,)): coupling,
            (y, (x,)): 28.0, (y, (x, z)): -1.0, (y, (y,)): -1.0,
            (z, (x, y)): 1.0, (z, (z,)): -8.0 / 3.0,
        }  # fmt: skip

    n, coef = _ring(name, size, 3, 2, terms)
    ic = np.ravel([[1.0 + 0.3 * i, 1.0 - 0.2 * i, 20.0 + i] for i in range(size)])
    return System(name, n, 2, coef, ic, 0.01)


def _van_der_pol_ring(name: str, size: int, mu: float = 1.0, coupling: float = 0.3) -> System:
    """``size`` Van der Pol oscillators (2 ``size`` states, a cubic library) of detuned
    frequencies on a ring, each pulled by the next one's position: ``x_i' = y_i``,
    ``y_i' = mu (1 - x_i^2) y_i - w_i^2 x_i + c (x_{i+1} - x_i)`` with
    ``w_i = 1 + 0.23 i`` (no two locked, so the neighbour is not a function of the
    oscillator's own state); at least two."""

    def terms(x, nxt, i):
        y, w = x + 1, 1.0 + 0.23 * i
        return {
            (x, (y,)): 1.0, (y, (y,)): mu, (y, (x, x, y)): -mu,
            (y, (x,)): -(w**2) - coupling, (y, (nxt,)): coupling,
        }  # fmt: skip

    n, coef = _ring(name, size, 2, 3, terms)
    ic = np.ravel([[2.0 * np.cos(1.3 * i), 2.0 * np.sin(1.3 * i)] for i in range(size)])
    return System(name, n, 3, coef, ic, 0.05)


def _lotka_volterra4(name: str) -> System:
    """Four competing species, ``x_i' = r_i x_i (1 - sum_j a_ij x_j)``, with the growth
    rates and competition of Vano et al. (2006, Nonlinearity 19:2391), whose attractor
    is chaotic: every state stays positive, in a narrow band (a library whose columns
    ``x_i`` and ``x_i x_j`` are far from independent)."""
    r = np.array([1.0, 0.72, 1.53, 1.27])
    a = np.array(
        [[1.0, 1.09, 1.52, 0.0], [0.0, 1.0, 0.44, 1.36], [2.33, 0.0, 1.0, 0.47],
         [1.21, 0.51, 0.35, 1.0]]
    )  # fmt: skip
    powers = monomial_powers(4, 2)
    at = {c: j for j, c in enumerate(powers)}
    coef = np.zeros((len(powers), 4))
    for i in range(4):
        coef[at[(i,)], i] = r[i]
        for j in np.flatnonzero(a[i]):
            coef[at[tuple(sorted((i, int(j))))], i] -= r[i] * a[i, j]
    return System(name, 4, 2, coef, [0.3, 0.4, 0.3, 0.2], 0.5)


def _rossler_ring(name: str, size: int, coupling: float = 0.1) -> System:
    """``size`` Rössler systems (3 ``size`` states) on a ring, each driven through its
    first state by the next one's: ``x_i' = -y_i - z_i + c (x_{i+1} - x_i)``,
    ``y_i' = x_i + 0.2 y_i``, ``z_i' = 0.2 + z_i (x_i - 5.7)``; at least two. Two drive
    each other and synchronise: their first states differ by 2 to 4 % of their spread
    (seeds 71 and 901), so their records cannot tell one system's terms from the
    other's; from three on, neighbours differ by 15 to 45 %."""

    def terms(x, nxt, i):
        y, z = x + 1, x + 2
        return {
            (x, (y,)): -1.0, (x, (z,)): -1.0, (x, (x,)): -coupling, (x, (nxt,)): coupling,
            (y, (x,)): 1.0, (y, (y,)): 0.2,
            (z, ()): 0.2, (z, (x, z)): 1.0, (z, (z,)): -5.7,
        }  # fmt: skip

    n, coef = _ring(name, size, 3, 2, terms)
    ic = np.ravel([[1.0 + 0.5 * i, -1.0 + 0.3 * i, 0.1] for i in range(size)])
    return System(name, n, 2, coef, ic, 0.06)


def _simulate(s: System, t: np.ndarray, seed: int):
    def inputs(tt, v):
        return v[None] if s.forcing is None else np.concatenate([v, [s.forcing(tt)]])[None]

    def rhs(tt, v):
        return (s.library(inputs(tt, v)) @ s.coef)[0]

    burn = s.dt * 1000 * (0.5 + (seed % 7) / 7.0) if s.burn is None else s.burn
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, burn + t[-1]), s.ic, method="DOP853", t_eval=burn + t, rtol=1e-10,
        atol=1e-10,
    )  # fmt: skip
    x = sol.y.T
    u = None if s.forcing is None else s.forcing(burn + t)[:, None]
    z = x if u is None else np.hstack([x, u])
    return x, u, s.library(z) @ s.coef


def _pysindy(s, t, x, u, x_dot):
    import pysindy as ps

    lost = np.isnan(x).any(axis=1)
    x, t = x[~lost], t[~lost]
    u = None if u is None else u[~lost]
    x_dot = None if x_dot is None else x_dot[~lost]
    model = ps.SINDy(optimizer=ps.STLSQ(), feature_library=ps.PolynomialLibrary(degree=s.degree))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(x, t=t, x_dot=x_dot, u=u)
    return np.asarray(model.coefficients()).T


def _family_index(family: str) -> int:
    """The family's part of a case's seed: its index among the zoo's families, the
    combined ones after them."""
    if family in zoo.ALL_FAMILIES:
        return zoo.ALL_FAMILIES.index(family)
    return len(zoo.ALL_FAMILIES) + FAMILIES.index(family)


def make_record(
    name: str, family: str, derivatives: str, seed: int, n_samples: int = 2000,
    noise: float = zoo.BASE_NOISE, glitches: tuple = zoo.ZOO_CONTAMINATION.glitch_range,
):  # fmt: skip
    """One case's record: the system, the sample times, the true states, the control
    (or None), the true derivatives and the states as measured."""
    s = _system(name)
    rng = np.random.default_rng(
        [seed, _family_index(family), zoo.DERIVATIVES.index(derivatives), len(name)]
    )
    outliers, _, timing = family.partition("+")
    times = zoo.sample_times(timing or family, n_samples, s.dt, rng)
    t = s.dt * np.arange(n_samples) if times is None else times
    x, u, dx = _simulate(s, t, seed)
    params = dataclasses.replace(
        zoo.ZOO_CONTAMINATION, base_noise=noise, glitch_range=tuple(glitches)
    )
    if outliers == "outages":
        noisy, _ = zoo.contaminate_family(x, "clean", rng, params)
        length = round(OUTAGE_FRACTION * n_samples)
        for _ in range(OUTAGES):
            start = int(rng.integers(0, n_samples - length))
            noisy[start : start + length, int(rng.integers(0, s.n))] = np.nan
    else:
        noisy, _ = zoo.contaminate_family(x, outliers, rng, params)
    return s, t, x, u, dx, noisy


def run_case(
    name: str, family: str, derivatives: str, seed: int, n_samples: int = 2000,
    noise: float = zoo.BASE_NOISE, glitches: tuple = zoo.ZOO_CONTAMINATION.glitch_range,
):  # fmt: skip
    s, t, _, u, dx, noisy = make_record(name, family, derivatives, seed, n_samples, noise, glitches)
    x_dot = dx if derivatives == "exact" else None
    rows = []
    for method in ("huber", "stlsq"):
        t0 = time.perf_counter()
        warned, kinds, error = [], [], ""
        try:
            if method == "huber":
                model = HuberSINDy(library=PolynomialLibrary(degree=s.degree))
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    model.fit(noisy, t, x_dot=x_dot, u=u)
                coef, warned = model.coef_.T, [str(w.message) for w in caught]
                kinds = [kind_of(w) for w in caught]
            else:
                coef = _pysindy(s, t, noisy, u, x_dot)
        except Exception as exc:  # a failure counts as a miss, with its reason
            coef, error = np.full_like(s.coef, np.nan), f"{type(exc).__name__}: {exc}"
        finite = bool(np.all(np.isfinite(coef)))
        rows.append(
            dict(
                system=name, states=s.n, family=family, derivatives=derivatives, seed=seed,
                method=method,
                exact=finite and bool(np.array_equal(coef != 0, s.coef != 0)),
                error_rel=(
                    float(np.linalg.norm(coef - s.coef) / np.linalg.norm(s.coef))
                    if finite else math.inf
                ),
                warned=bool(warned), kinds=count_kinds(kinds),
                warnings=" | ".join(sorted(set(warned)))[:300],
                failure=error[:200], seconds=time.perf_counter() - t0,
            )
        )  # fmt: skip
    return rows


def table(rows: list[dict], families=FAMILIES) -> str:
    systems = list(dict.fromkeys(r["system"] for r in rows))
    lines = [
        "| system | states | derivatives | "
        + " | ".join(families)
        + " | failures warned | right but warned |",
        "|" + "---|" * (len(families) + 5),
    ]
    for name in systems:
        for der in zoo.DERIVATIVES:
            cells = []
            for fam in families:
                got = {
                    m: [r["exact"] for r in rows if (r["system"], r["derivatives"], r["family"],
                                                     r["method"]) == (name, der, fam, m)]
                    for m in ("huber", "stlsq")
                }  # fmt: skip
                if not got["huber"]:
                    cells.append("-")
                    continue
                cells.append(
                    f"{sum(got['huber'])}/{len(got['huber'])} "
                    f"(STLSQ {sum(got['stlsq'])}/{len(got['stlsq'])})"
                )
            ours = [
                r for r in rows
                if (r["system"], r["derivatives"], r["method"]) == (name, der, "huber")
            ]  # fmt: skip
            if not ours:
                continue
            wrong = [r for r in ours if not r["exact"]]
            right = [r for r in ours if r["exact"]]
            share = [
                f"{sum(r['warned'] for r in g)}/{len(g)}" if g else "-" for g in (wrong, right)
            ]
            states = ours[0]["states"]
            lines.append(f"| {name} | {states} | {der} | " + " | ".join(cells + share) + " |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--systems", default=",".join(SYSTEMS), help="comma-separated")
    parser.add_argument("--derivatives", default="exact,states", help="comma-separated")
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument(
        "--noise", type=float, default=zoo.BASE_NOISE,
        help="Gaussian noise on every reading, relative to each state's spread",
    )  # fmt: skip
    parser.add_argument(
        "--families", default=",".join(FAMILIES), help="comma-separated (default: all)"
    )
    parser.add_argument(
        "--glitches", default="{:g},{:g}".format(*zoo.ZOO_CONTAMINATION.glitch_range),
        help="the glitches' smallest and largest size, in spreads of the state (LO,HI)",
    )  # fmt: skip
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default="validation/results/sensors")
    args = parser.parse_args(argv)
    families = args.families.split(",")
    for fam in families:
        if fam not in FAMILIES:
            parser.error(f"--families: {fam!r} is not one of {', '.join(FAMILIES)}")
    try:
        glitches = tuple(float(v) for v in args.glitches.split(","))
    except ValueError:
        glitches = ()
    if len(glitches) != 2 or not 0 < glitches[0] <= glitches[1] < math.inf:
        parser.error(f"--glitches: expected LO,HI with 0 < LO <= HI; got {args.glitches!r}")
    systems = args.systems.split(",")
    for name in systems:
        try:
            _system(name)  # an unknown name fails here, before any case runs
        except ValueError as exc:
            parser.error(f"--systems: {exc}")
    derivatives = args.derivatives.split(",")
    for der in derivatives:
        if der not in zoo.DERIVATIVES:
            parser.error(f"--derivatives: {der!r} is not one of {', '.join(zoo.DERIVATIVES)}")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    cases = [
        (name, fam, der, seed, args.samples, args.noise, glitches) for name in systems
        for fam in families for der in derivatives for seed in seeds
    ]  # fmt: skip
    from tqdm import tqdm

    out = Parallel(n_jobs=args.jobs, return_as="generator")(delayed(run_case)(*c) for c in cases)
    rows = [r for chunk in tqdm(out, total=len(cases), desc="sensor cases") for r in chunk]
    folder = Path(args.out)
    write_rows(rows, folder / "sensors.csv")
    text = [
        "# Sensor families on a control input, a transient and twenty channels"
        if systems == list(SYSTEMS)
        else f"# Sensor families on {', '.join(systems)}",
        "",
        f"Command: `python validation/sensors.py {' '.join(argv or sys.argv[1:])}`. "
        f"{args.samples} samples, Gaussian noise {100 * args.noise:.3g} % of each "
        "state's spread; "
        "families and contamination of `robust_sindy.zoo` (`SENSOR_FAMILIES`), and "
        "`glitches+irregular`: the glitches at uniformly random times; `outages`: "
        f"{OUTAGES} stretches of {100 * OUTAGE_FRACTION:g} % of the samples, each in one "
        "channel, not measured"
        + (
            ""
            if glitches == zoo.ZOO_CONTAMINATION.glitch_range
            else f" (glitches of {glitches[0]:g} to {glitches[1]:g} spreads)"
        )
        + ". Cells: "
        "exact support of `HuberSINDy()` over the seeds (PySINDy STLSQ at its default "
        "threshold, given the same records). The last columns: of the cases "
        "`HuberSINDy()` got wrong, how many warned; of those it got right, how many "
        "warned anyway.",
        "",
        table(rows, families),
        "",
    ]
    (folder / "sensors.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
