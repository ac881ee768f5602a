"""Few samples per library term: which answers the sample rules warn on.

Records short for their library, from two families: Lorenz-96 with 6, 10, 16 and 24
states (degree-2 monomials, 28 to 325 terms) at 1.5, 2.5 and 4 samples per term, from
the states at 0.5 and 2 % noise and, with 10 and 16 states, from exact derivatives at
1 % noise; and six three-state dysts flows (their own degree, 10 or 20 terms) at 2, 3
and 4.5 samples per term, 25 samples per period, 1 % noise, from the states and from
exact derivatives.  Noise is Gaussian, relative to each state's spread.  For each fit of
``HuberSINDy()``: exact support or not, the kinds of the warnings, and whether the rule
"fewer than 5 kept samples per library term" would have fired (``samples_per_term``).

    python validation/few_samples.py [--jobs 2] [--seed 3] [--out DIR]

About 5 minutes on two cores.  Needs the extras ``zoo`` (dysts).
"""

from __future__ import annotations

import argparse
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from robust_sindy import HuberSINDy, flows
from robust_sindy.diagnostics import kind_of
from robust_sindy.library import PolynomialLibrary

#: The kinds of the two rules on the sample count.
SAMPLE_KINDS = ("few samples for the search", "fewer samples than terms")
#: The rule these replaced: fewer kept samples per library term than this.
PER_TERM = 5.0


def cases(seed: int) -> list[tuple]:
    """``(family, system, samples, noise, seed, derivatives)`` of every fit."""
    out = []
    for n in (6, 10, 16, 24):
        p = (n + 1) * (n + 2) // 2
        for ratio in (1.5, 2.5, 4.0):
            for level in (0.005, 0.02):
                out.append(("Lorenz-96, states", n, int(ratio * p), level, seed, "states"))
    for n in (10, 16):
        p = (n + 1) * (n + 2) // 2
        for ratio in (1.5, 2.5):
            out.append(("Lorenz-96, exact derivatives", n, int(ratio * p), 0.01, seed + 1, "exact"))
    systems = [s for s in flows.polynomial_systems() if s.n_states == 3]
    for i in np.random.default_rng(61).choice(len(systems), 6, replace=False):
        s = systems[i]
        for ratio in (2.0, 3.0, 4.5):
            for deriv in ("states", "exact"):
                family = "dysts flows, " + ("states" if deriv == "states" else "exact derivatives")
                out.append((family, s.name, int(ratio * s.coef.shape[0]), 0.01, seed + 2, deriv))
    return out


def run_case(case: tuple) -> dict:
    family, name, m, level, seed, deriv = case
    rng = np.random.default_rng([seed, m])
    if family.startswith("Lorenz"):
        t, x, dx, system = flows.lorenz96_records(name, m, seed)
    else:
        system = next(s for s in flows.polynomial_systems() if s.name == name)
        t, x, dx = flows.simulate_system(system, m, seed, pts_per_period=25)
    noisy = x + level * x.std(axis=0) * rng.normal(size=x.shape)
    model = HuberSINDy(library=PolynomialLibrary(degree=system.degree))
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(noisy, t, x_dot=dx if deriv == "exact" else None)
    d = model.diagnostics_
    coef = model.coef_.T
    return dict(
        family=family, system=system.name, samples=m, noise=level,
        exact=bool(np.array_equal(coef != 0, system.coef != 0)),
        error=float(np.linalg.norm(coef - system.coef) / np.linalg.norm(system.coef)),
        kinds=sorted({kind_of(c) for c in caught}),
        per_term=d.samples_per_term,
        seconds=time.perf_counter() - start,
    )  # fmt: skip


def table(rows: list[dict]) -> str:
    lines = [
        "| records | fits | exact | right, warned | right, warned by the sample rules "
        f"| right, < {PER_TERM:g} per term | wrong, silent | wrong, warned by the sample "
        "rules | of those, by nothing else |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for family in dict.fromkeys(r["family"] for r in rows):
        sel = [r for r in rows if r["family"] == family]
        right = [r for r in sel if r["exact"]]
        wrong = [r for r in sel if not r["exact"]]
        sample = [r for r in wrong if set(r["kinds"]) & set(SAMPLE_KINDS)]
        alone = [r for r in sample if not set(r["kinds"]) - set(SAMPLE_KINDS)]
        silent = [
            f"{r['system']} at {r['samples']} ({r['error']:.2g})" for r in wrong if not r["kinds"]
        ]
        lines.append(
            f"| {family} | {len(sel)} | {len(right)} "
            f"| {sum(bool(r['kinds']) for r in right)}/{len(right)} "
            f"| {sum(bool(set(r['kinds']) & set(SAMPLE_KINDS)) for r in right)}/{len(right)} "
            f"| {sum(r['per_term'] < PER_TERM for r in right)}/{len(right)} "
            f"| {len(silent)}/{len(wrong)}{': ' + ', '.join(silent) if silent else ''} "
            f"| {len(sample)}/{len(wrong)} | {len(alone)} |"
        )  # fmt: skip
    kinds = Counter(k for r in rows if r["exact"] for k in r["kinds"]).most_common()
    return (
        "\n".join(lines)
        + "\n\nKinds on right answers: "
        + (", ".join(f"{k} {c}" for k, c in kinds) or "none")
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None, help="folder for few_samples.md")
    args = parser.parse_args(argv)
    rows = Parallel(n_jobs=args.jobs)(delayed(run_case)(c) for c in cases(args.seed))
    text = table(rows)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        command = "python validation/few_samples.py" + (
            f" --seed {args.seed}" if args.seed != 3 else ""
        )
        (out / "few_samples.md").write_text(
            f"# Few samples per library term\n\nCommand: `{command} --out {args.out}`.\n\n"
            + text
            + "\n"
        )


if __name__ == "__main__":
    main()
