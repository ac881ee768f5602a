"""Which warnings fire on right and on wrong answers, from noisy states.

The frontier's cases (:mod:`robust_sindy.frontier`: dysts flows, 2000 samples at 100
per period, Gaussian noise of ``level`` times each state's root mean square, states
only, a degree-4 library), fitted by ``HuberSINDy()``; per noise level, the right
answers (exact support) that warned anyway, the wrong answers that did not, and the
kinds of warning on each (an :class:`~robust_sindy.IdentificationWarning`'s ``kind``,
else the warning's class).  A warning that fires on most right answers teaches users
to ignore it; a wrong answer without one is a silent failure.

    python validation/warning_rates.py --systems 20 --draw 1 --seed 0
    python validation/warning_rates.py --systems 20 --draw 7 --seed 3   # held out

``--out cases.csv`` also writes every case (system, noise level, exactness, coefficient
error and the kinds of its warnings, ``;``-separated), for questions the table does not
answer, such as which warnings fired alone.

Needs the extras ``zoo`` (dysts).  About 5 minutes per draw on 2 cores.
"""

from __future__ import annotations

import argparse
import warnings
from collections import Counter

import numpy as np
from joblib import Parallel, delayed

from robust_sindy import HuberSINDy, frontier
from robust_sindy.diagnostics import kind_of
from robust_sindy.flows import polynomial_systems, write_rows
from robust_sindy.library import PolynomialLibrary


def case(system, level: float, seed: int) -> dict | None:
    """One fit: exactness, coefficient error and the warnings' kinds."""
    try:
        t, x = frontier._noisy(system, level, seed, 2000)
    except RuntimeError:  # the trajectory could not be integrated: not a case
        return None
    true = frontier._truth(system, x.shape[1])
    model = HuberSINDy(library=PolynomialLibrary(degree=4))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t)
    exact, error = frontier._score(model.coef_.T, true)
    kinds = sorted({kind_of(c) for c in caught})
    return dict(system=system.name, level=level, exact=exact, error=error, kinds=kinds)


def run(n_systems: int, draw: int, seed: int, levels=frontier.LEVELS, jobs: int = 2):
    """Every (system, level) case of a draw, as :func:`robust_sindy.frontier.run` draws."""
    systems = polynomial_systems()
    pick = np.random.default_rng(draw).choice(len(systems), n_systems, replace=False)
    out = Parallel(n_jobs=jobs)(delayed(case)(systems[i], lv, seed) for i in pick for lv in levels)
    return [r for r in out if r is not None]


def table(rows) -> str:
    lines = [
        "| noise | exact | right, warned | wrong, silent | kinds on right answers "
        "| kinds on wrong answers |",
        "|---|---|---|---|---|---|",
    ]
    for level in sorted({r["level"] for r in rows}):
        sel = [r for r in rows if r["level"] == level]
        right = [r for r in sel if r["exact"]]
        wrong = [r for r in sel if not r["exact"]]
        silent = [f"{r['system']} ({r['error']:.2g})" for r in wrong if not r["kinds"]]

        def kinds(group):
            counts = Counter(k for r in group for k in r["kinds"]).most_common()
            return ", ".join(f"{k} {c}" for k, c in counts) or "-"

        lines.append(
            f"| {100 * level:g} % | {len(right)}/{len(sel)} "
            f"| {sum(bool(r['kinds']) for r in right)}/{len(right)} "
            f"| {len(silent)}/{len(wrong)}{' ' + ', '.join(silent) if silent else ''} "
            f"| {kinds(right)} | {kinds(wrong)} |"
        )
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--systems", type=int, default=20)
    parser.add_argument("--draw", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None, help="a CSV of every case")
    args = parser.parse_args(argv)
    rows = run(args.systems, args.draw, args.seed, jobs=args.jobs)
    if args.out:
        write_rows([{**r, "kinds": ";".join(r["kinds"])} for r in rows], args.out)
    print(table(rows))


if __name__ == "__main__":
    main()
