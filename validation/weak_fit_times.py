"""Wall-clock time of `HuberSINDy()` on twelve noisy-state records of the frontier.

Six polynomial flows (SprottJerk, LuChen, Lorenz, Rossler, Qi, Bouali2) at 1 and 5 %
noise (the frontier's records: 2000 samples, seed 0, degree-4 library), fitted one
after the other in one process. To compare two versions of the library, run it with
each on the path, alternately and on an otherwise idle machine:

    PYTHONPATH=/path/to/other/checkout python validation/weak_fit_times.py
    python validation/weak_fit_times.py
"""

from __future__ import annotations

import time
import warnings

import robust_sindy
from robust_sindy import HuberSINDy, PolynomialLibrary, frontier
from robust_sindy.flows import polynomial_systems

CASES = [
    (name, level)
    for name in ("SprottJerk", "LuChen", "Lorenz", "Rossler", "Qi", "Bouali2")
    for level in (0.01, 0.05)
]


def main() -> None:
    systems = {s.name: s for s in polynomial_systems()}
    total, times = 0.0, []
    for name, level in CASES:
        t, x = frontier._noisy(systems[name], level, 0, 2000)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            start = time.perf_counter()
            HuberSINDy(library=PolynomialLibrary(degree=4)).fit(x, t)
            seconds = time.perf_counter() - start
        total += seconds
        times.append(f"{name} {100 * level:g} %: {seconds:.2f} s")
    print(f"{robust_sindy.__file__}: {total:.1f} s in all")
    print("\n".join(times))


if __name__ == "__main__":
    main()
