"""The weak form's quadrature at uniform and uniformly random sample times: how much of
the samples' noise its rows carry, and how accurately it integrates a sine.

For each stencil of the product integration (``LOCAL_SAMPLES`` samples, a polynomial of
degree ``LOCAL_DEGREE``; the library's own is 8 samples, quartic), the weights of
:func:`robust_sindy.timeseries.weak.weight_functions` on 2000 samples (step 0.01, or
uniformly random times over the same span), half width 15 steps:

* the noise variance of a target row, ``sum_i dphi_ri^2``, for unit white noise (mean
  and largest over the rows);
* the root-mean-square relative error of ``dphi @ sin(w t)`` against the integral of
  ``phi' sin(w t)`` (computed on a fine grid) at 20 and 40 samples a period.

    python validation/quadrature_noise.py [--stencils 8:4,12:4,16:4] [--seed 0]
"""

from __future__ import annotations

import argparse

import numpy as np

from robust_sindy.timeseries import weak

STEP, SAMPLES = 0.01, 2000
HALF_WIDTH = 15 * STEP  # the test functions' half width, 15 steps
PERIODS = (20, 40)  # samples a period of the sines


def _exact(centre: float, h: float, omega: float) -> float:
    """``int phi'(t) sin(omega t) dt`` over the support, on a fine grid."""
    s = np.linspace(-1.0, 1.0, 20001)
    t = centre + h * s
    _, slope = weak._bump(s, h)
    return float(np.trapezoid(slope * np.sin(omega * t), t))


def measure(t: np.ndarray, samples: int, degree: int) -> tuple[float, float, list[float]]:
    """Mean and largest row noise variance, and the relative errors at ``PERIODS``."""
    kept = weak.LOCAL_SAMPLES, weak.LOCAL_DEGREE
    weak.LOCAL_SAMPLES, weak.LOCAL_DEGREE = samples, degree
    try:
        _, dphi, centres = weak.weight_functions(t, HALF_WIDTH)
    finally:
        weak.LOCAL_SAMPLES, weak.LOCAL_DEGREE = kept
    variance = (dphi**2).sum(axis=1)
    errors = []
    for per in PERIODS:
        omega = 2.0 * np.pi / (per * STEP)
        exact = np.array([_exact(c, HALF_WIDTH, omega) for c in centres[::10]])
        found = dphi[::10] @ np.sin(omega * t)
        errors.append(float(np.sqrt(np.mean((found - exact) ** 2) / np.mean(exact**2))))
    return float(variance.mean()), float(variance.max()), errors


def _stencils(text: str, parser) -> list[tuple[int, int]]:
    """``samples:degree,...`` as pairs of integers."""
    try:
        pairs = [tuple(int(v) for v in item.split(":")) for item in text.split(",")]
        if any(len(pair) != 2 for pair in pairs):
            raise ValueError
    except ValueError:
        parser.error(f"--stencils: expected samples:degree, comma-separated; got {text!r}")
    return pairs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stencils", default="8:4,12:4,16:4",
                        help="samples:degree of the local fits, comma-separated")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    stencils = _stencils(args.stencils, parser)
    span = (SAMPLES - 1) * STEP
    uniform = np.linspace(0.0, span, SAMPLES)
    random = np.sort(np.random.default_rng(args.seed).uniform(0.0, span, SAMPLES))
    random[0], random[-1] = 0.0, span
    head = " / ".join(str(p) for p in PERIODS)
    print(f"| times | stencil | row noise variance, mean (max) | relative error at {head} "
          "samples a period |")  # fmt: skip
    print("|---|---|---|---|")
    for samples, degree in stencils:
        for name, t in (("uniform", uniform), ("random", random)):
            mean, top, errors = measure(t, samples, degree)
            shown = " / ".join(f"{e:.2g}" for e in errors)
            print(f"| {name} | {samples} samples, degree {degree} | {mean:.3f} ({top:.3f}) "
                  f"| {shown} |")  # fmt: skip


if __name__ == "__main__":
    main()
