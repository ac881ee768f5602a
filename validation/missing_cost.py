"""What missing readings cost: the same fit with and without 5 % of the entries missing.

``HuberSINDy()`` (states only, defaults) on dysts' Lorenz (3 states) and Lorenz-96 with
10 states, 2000 samples, noise 1e-3 of each state's spread; the two fits alternate,
three times each, and the medians are compared (a ratio, measured side by side: the
machine is shared).

    python validation/missing_cost.py
"""

import time
import warnings

import numpy as np

from robust_sindy import HuberSINDy, PolynomialLibrary, zoo
from robust_sindy.flows import lorenz96, simulate_system


def main():
    systems = {s.name: s for s in zoo.polynomial_systems()}
    for s in (systems["Lorenz"], lorenz96(10)):
        t, x, _ = simulate_system(s, 2000, 0)
        rng = np.random.default_rng(0)
        noisy = x + 1e-3 * x.std(axis=0) * rng.normal(size=x.shape)
        lost = noisy.copy()
        lost.flat[rng.choice(x.size, round(0.05 * x.size), replace=False)] = np.nan
        seconds = {"complete": [], "missing": []}
        for _ in range(3):
            for key, data in (("complete", noisy), ("missing", lost)):
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    HuberSINDy(library=PolynomialLibrary(degree=s.degree)).fit(data, t)
                seconds[key].append(time.perf_counter() - t0)
        a, b = np.median(seconds["complete"]), np.median(seconds["missing"])
        print(f"{s.name}: complete {a:.2f} s, 5 % missing {b:.2f} s, ratio {b / a:.2f}")


if __name__ == "__main__":
    main()
