"""The formulation contest's level, measured on records it decides.

Where outliers keep the strong form, ``formulation="auto"`` may let the weak form's
model overturn it on the record's forecasts (a one-sided sign test over windows,
``robust_sindy.selection.forecast``).  This script fits ``HuberSINDy()`` on records with
outliers at noise levels where that happens and, for every record where the contest
ran and the two forms selected different terms, fits the other form too
(``formulation="strong"`` or ``"weak"``: the same identification the contest saw), so
that both models are scored against the truth.  It reports, per record, the windows
won, the sign test's p-value and which model is right, and, for each level tried, how
many records that level would get right and how often it would take a wrong weak-form
model over a right strong-form one::

    python validation/contest_level.py --draw 59 --seed 19 --levels 0.005,0.01 \\
        --families glitches,spikes,rows,bursts --lv4-seeds 601,602,603,604 \\
        --lv4-families glitches,spikes,glitches+irregular --lv4-levels 0.005

Records: polynomial flows of dysts drawn at random (2000 samples at 100 per period, a
degree-4 library, as ``validation/outlier_noise.py``) and ``LotkaVolterra4`` of
``validation/sensors.py`` (3000 samples, states only).  The choice the library makes is
the one at ``FORECAST_EVIDENCE``; the other levels are what the p-values would give.
Needs the extras ``zoo`` (dysts).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from robust_sindy import HuberSINDy
from robust_sindy.library import PolynomialLibrary
from robust_sindy.selection.forecast import FORECAST_EVIDENCE

sys.path.insert(0, str(Path(__file__).parent))
import outlier_noise  # validation/outlier_noise.py: the same records
import sensors  # validation/sensors.py: LotkaVolterra4

LEVELS = (1e-3, 1e-2)


def _fit(x, t, u, degree, form):
    model = HuberSINDy(library=PolynomialLibrary(degree=degree), formulation=form)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t, u=u)
    return model, bool(caught)


def _case(label, x, t, u, true, degree) -> dict:
    model, warned = _fit(x, t, u, degree, "auto")
    right = bool(np.array_equal(model.coef_.T != 0, true != 0))
    row = dict(record=label, exact=right, warned=warned, form=model.diagnostics_.formulation)
    contest = model.diagnostics_.formulation_contest
    if contest:
        other = "strong" if contest["chosen"] == "weak" else "weak"
        rival, _ = _fit(x, t, u, degree, other)
        rival_right = bool(np.array_equal(rival.coef_.T != 0, true != 0))
        strong_right, weak_right = (right, rival_right) if other == "weak" else (rival_right, right)
        row.update(
            wins=contest["wins"], windows=contest["wins"] + contest["losses"],
            p_value=contest["p_value"], strong_right=strong_right, weak_right=weak_right,
        )  # fmt: skip
    return row


def dysts_case(system, family, level, seed) -> dict | None:
    made = outlier_noise.record(system, family, level, seed)
    if made is None:
        return None
    t, noisy, true = made
    return _case(f"{system.name} {family} {level:g} {seed}", noisy, t, None, true, 4)


def lv4_case(family, level, seed) -> dict:
    s, t, _, u, _, x = sensors.make_record("LotkaVolterra4", family, "states", seed, 3000, level)
    return _case(f"LotkaVolterra4 {family} {level:g} {seed}", x, t, u, s.coef, s.degree)


def table(rows) -> str:
    contests = [r for r in rows if "p_value" in r]
    lines = [
        f"{len(rows)} records, {sum(r['exact'] for r in rows)} exact, "
        f"{sum(not r['exact'] and not r['warned'] for r in rows)} wrong without a warning, "
        f"{sum(r['exact'] and r['warned'] for r in rows)} right with one, "
        f"{len(contests)} decided by the contest (the forms' terms differ).",
        "",
        "| record | windows won | p | strong form right | weak form right |",
        "|---|---|---|---|---|",
    ]
    for r in contests:
        lines.append(
            f"| {r['record']} | {r['wins']}/{r['windows']} | {r['p_value']:.2g} "
            f"| {'yes' if r['strong_right'] else 'no'} | {'yes' if r['weak_right'] else 'no'} |"
        )
    lines += ["", "| level | right among these | a wrong weak model over a right strong one |"]
    lines.append("|---|---|---|")
    for level in sorted({*LEVELS, FORECAST_EVIDENCE}):
        take = [r["p_value"] <= level for r in contests]
        right = sum(
            r["weak_right"] if w else r["strong_right"] for r, w in zip(contests, take, strict=True)
        )
        bad = sum(
            w and r["strong_right"] and not r["weak_right"]
            for r, w in zip(contests, take, strict=True)
        )
        mark = " (the library's)" if level == FORECAST_EVIDENCE else ""
        lines.append(f"| {level:g}{mark} | {right}/{len(contests)} | {bad} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--systems", type=int, default=16)
    ap.add_argument("--draw", type=int, default=59)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--families", default="glitches,spikes,rows,bursts")
    ap.add_argument("--levels", default="0.005,0.01")
    ap.add_argument("--lv4-seeds", default="", help="LotkaVolterra4 seeds, comma-separated")
    ap.add_argument("--lv4-families", default="glitches,spikes")
    ap.add_argument("--lv4-levels", default="0.005")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default=None, help="file for the tables (markdown)")
    args = ap.parse_args(argv)
    systems = outlier_noise.draw_systems(args.systems, args.draw)
    levels = [float(v) for v in args.levels.split(",")]
    cases = [
        delayed(dysts_case)(system, fam, lv, args.seed)
        for fam in args.families.split(",") for system in systems for lv in levels
    ]  # fmt: skip
    if args.lv4_seeds:
        cases += [
            delayed(lv4_case)(fam, float(lv), int(seed))
            for fam in args.lv4_families.split(",")
            for lv in args.lv4_levels.split(",")
            for seed in args.lv4_seeds.split(",")
        ]  # fmt: skip
    rows = [r for r in Parallel(n_jobs=args.jobs)(cases) if r is not None]
    text = table(rows)
    print(text)
    if args.out:
        command = "python validation/contest_level.py " + " ".join(
            f"--{k.replace('_', '-')} {v}"
            for k, v in vars(args).items()
            if k not in ("jobs", "out") and v != ""
        )
        Path(args.out).write_text(f"Command: `{command.strip()}`\n\n{text}\n")


if __name__ == "__main__":
    main()
