"""Outliers in noisy states: the strong form against the weak form.

Polynomial flows of dysts drawn at random (2000 samples at 100 per period, states only,
a degree-4 library), each contaminated by a zoo family (``robust_sindy.zoo``:
``glitches``, ``spikes``, ``rows``, ``bursts``, ...) over Gaussian noise of ``level``
times each state's spread (``zoo.Contamination(base_noise=level)``), fitted by
``HuberSINDy(formulation=...)`` for each formulation asked for, on the same record.
Per family, level and formulation: the exact supports, the wrong answers without a
warning, the right answers with one, and the median relative coefficient error.  It
measures where ``formulation="auto"`` should stop keeping the strong form for records
with outliers (``robust_sindy.estimator.WEAK_WITH_OUTLIERS_NOISE``)::

    python validation/outlier_noise.py --draw 11 --seed 2 --levels 0.01,0.03,0.1 \\
        --families glitches
    python validation/outlier_noise.py --draw 11 --seed 2 --levels 0.01,0.03 \\
        --families rows,spikes,bursts
    python validation/outlier_noise.py --draw 11 --seed 2 --levels 0.02 \\
        --families rows,glitches,spikes,heavy
    python validation/outlier_noise.py --draw 13 --seed 4 --levels 0.005,0.015,0.05 \\
        --families glitches,spikes --forms auto,strong \\
        --out validation/results/outlier_noise       # held out: the rule against before

(``heavy`` ignores ``level``: Student-t noise of the zoo's scale.)  Needs the extras
``zoo`` (dysts).  About 4 seconds per fit on one core.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from robust_sindy import HuberSINDy, frontier, zoo
from robust_sindy.diagnostics import kind_of
from robust_sindy.flows import polynomial_systems, simulate_system
from robust_sindy.library import PolynomialLibrary


def draw_systems(n_systems: int, draw: int) -> list:
    """``n_systems`` polynomial flows of dysts drawn at random (``draw`` seeds the draw)."""
    systems = polynomial_systems()
    pick = np.random.default_rng(draw).choice(len(systems), n_systems, replace=False)
    return [systems[i] for i in pick]


def record(system, family: str, level: float, seed: int):
    """One record: sample times, the states as measured (``family`` over Gaussian noise
    of ``level``) and the true coefficients in the degree-4 library's order; None where
    the trajectory could not be integrated (not a case)."""
    try:
        t, x, _ = simulate_system(system, 2000, seed)
    except RuntimeError:
        return None
    rng = np.random.default_rng([seed, 91, round(level * 1e4)])
    noisy, _ = zoo.contaminate_family(x, family, rng, zoo.Contamination(base_noise=level))
    return t, noisy, frontier._truth(system, x.shape[1])


def case(system, family: str, level: float, seed: int, form: str) -> dict | None:
    """One fit: exactness, coefficient error, the warnings' kinds, the form used."""
    made = record(system, family, level, seed)
    if made is None:
        return None
    t, noisy, true = made
    model = HuberSINDy(library=PolynomialLibrary(degree=4), formulation=form)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(noisy, t)
    exact, error = frontier._score(model.coef_.T, true)
    return dict(
        system=system.name, family=family, level=level, form=form, exact=exact, error=error,
        kinds=sorted({kind_of(c) for c in caught}), used=model.diagnostics_.formulation,
    )  # fmt: skip


def run(n_systems, draw, seed, families, levels, forms, jobs=2) -> list[dict]:
    systems = draw_systems(n_systems, draw)
    cases = [
        (system, fam, lv, seed, form)
        for fam in families for system in systems for lv in levels for form in forms
    ]  # fmt: skip
    out = Parallel(n_jobs=jobs)(delayed(case)(*c) for c in cases)
    return [r for r in out if r is not None]


def table(rows, families, levels, forms) -> str:
    lines = [
        "| family | noise | formulation | exact | wrong, silent | right, warned "
        "| median rel. error | forms used |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for fam in families:
        for lv in levels:
            for form in forms:
                rr = [r for r in rows if (r["family"], r["level"], r["form"]) == (fam, lv, form)]
                if not rr:
                    continue
                right = [r for r in rr if r["exact"]]
                silent = sum(not r["exact"] and not r["kinds"] for r in rr)
                kinds = sorted({r["used"] for r in rr})
                used = ", ".join(f"{u} {sum(r['used'] == u for r in rr)}" for u in kinds)
                lines.append(
                    f"| {fam} | {100 * lv:g} % | {form} | {len(right)}/{len(rr)} | {silent} "
                    f"| {sum(bool(r['kinds']) for r in right)}/{len(right)} "
                    f"| {np.median([r['error'] for r in rr]):.2g} | {used} |"
                )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--systems", type=int, default=16)
    ap.add_argument("--draw", type=int, default=11)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--families", default="glitches,spikes,rows,bursts")
    ap.add_argument("--levels", default="0.01,0.02,0.03")
    ap.add_argument("--forms", default="strong,weak")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default=None, help="folder for outlier_noise.md")
    args = ap.parse_args(argv)
    families = args.families.split(",")
    levels = [float(v) for v in args.levels.split(",")]
    forms = args.forms.split(",")
    rows = run(args.systems, args.draw, args.seed, families, levels, forms, args.jobs)
    text = table(rows, families, levels, forms)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        command = "python validation/outlier_noise.py " + " ".join(
            f"--{k} {v}" for k, v in vars(args).items() if k not in ("jobs", "out")
        )
        (out / "outlier_noise.md").write_text(f"Command: `{command}`\n\n{text}\n")


if __name__ == "__main__":
    main()
