"""What missing readings cost: the same fit with and without a share of the entries missing.

``HuberSINDy()`` (states only, defaults) on the same record twice: complete, and with
``--fraction`` of its entries (drawn uniformly over samples and channels) missing. The
two fits alternate, ``--repeats`` times each, and the medians are compared (a ratio,
measured side by side: the machine is shared). Beside the times, whether each fit
found the true support and its relative coefficient error, so that a cheap fit that
is wrong does not pass for a cheap fit.

    python validation/missing_cost.py [--systems Lorenz,Lorenz96_10] [--noise 0.001]

``--systems`` takes dysts' polynomial flows by name (``Lorenz``, ``Rossler``, ...) and
the systems of ``validation/sensors.py`` (``Lorenz96_N``, ``LorenzRing_N``,
``VanDerPolRing_N``, ``RosslerRing_N``, ``LotkaVolterra4``, ``DuffingForced``,
``Hopf``); Gaussian noise of ``--noise`` times each state's spread; ``--samples``
samples on the system's own step; ``--seed`` draws the trajectory, the noise and the
missing entries.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.flows import polynomial_system, simulate_system

sys.path.insert(0, str(Path(__file__).parent))

import sensors  # validation/sensors.py: its systems by name


def states(name: str, n_samples: int, seed: int):
    """Degree, true coefficients (terms × states), sample times, states and control (or
    None) of the system ``name``: a dysts flow, or one of ``validation/sensors.py``."""
    try:
        s = polynomial_system(name)
    except ValueError as not_a_flow:
        try:
            s, t, x, u, _, _ = sensors.make_record(name, "clean", "states", seed, n_samples)
        except ValueError as not_a_sensor_system:
            raise ValueError(f"--systems: {not_a_flow}; {not_a_sensor_system}") from None
        return s.degree, s.coef, t, x, u
    t, x, _ = simulate_system(s, n_samples, seed)
    return s.degree, s.coef, t, x, None


def fit(degree: int, data: np.ndarray, t: np.ndarray, u, coef: np.ndarray):
    """Seconds, exact support and relative coefficient error of ``HuberSINDy()``."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = HuberSINDy(library=PolynomialLibrary(degree=degree)).fit(data, t, u=u)
    seconds = time.perf_counter() - t0
    found = model.coef_.T
    exact = bool(np.array_equal(found != 0, coef != 0))
    return seconds, exact, float(np.linalg.norm(found - coef) / np.linalg.norm(coef))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--systems", default="Lorenz,Lorenz96_10")
    parser.add_argument("--noise", type=float, default=1e-3)
    parser.add_argument("--fraction", type=float, default=0.05)
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if not 0.0 < args.fraction < 1.0:
        parser.error(f"--fraction must be between 0 and 1, got {args.fraction}")
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    print(
        f"{100 * args.fraction:g} % of the entries missing, noise {100 * args.noise:g} % "
        f"of each state's spread, {args.samples} samples, seed {args.seed}, medians of "
        f"{args.repeats} alternating fits\n"
    )
    print("| system | states | complete | missing | ratio | exact (complete / missing) "
          "| rel. error (complete / missing) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for name in args.systems.split(","):
        degree, coef, t, x, u = states(name, args.samples, args.seed)
        rng = np.random.default_rng([args.seed, x.shape[1]])
        noisy = x + args.noise * x.std(axis=0) * rng.normal(size=x.shape)
        lost = noisy.copy()
        lost.flat[rng.choice(x.size, round(args.fraction * x.size), replace=False)] = np.nan
        runs = {"complete": [], "missing": []}
        for _ in range(args.repeats):
            for key, data in (("complete", noisy), ("missing", lost)):
                runs[key].append(fit(degree, data, t, u, coef))
        a, b = (float(np.median([r[0] for r in runs[k]])) for k in ("complete", "missing"))
        (_, ea, ra), (_, eb, rb) = runs["complete"][0], runs["missing"][0]
        print(
            f"| {name} | {x.shape[1]} | {a:.2f} s | {b:.2f} s | {b / a:.2f} | {ea} / {eb} "
            f"| {ra:.2g} / {rb:.2g} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
