"""Held-out check of the zoo: another seed, other contamination parameters.

The zoo table (``robust-sindy zoo``) uses seed 0 and one set of contamination
parameters.  This check draws 16 of its systems at random (generator seed 2026, ``--draw``), uses
seed 3 and different parameters for every family, and compares ``HuberSINDy()`` with
PySINDy's STLSQ given the same data:

* ``clean``: Gaussian noise 2e-3 of each state's spread (the zoo: 1e-3);
* ``rows``: 10 % of the samples, Gaussian 1.0 of the spread (20 %, 0.2);
* ``spikes``: 2 % of the entries, one state at a time, +-3 to 5 (5 %, +-0.5 to 2);
* ``heavy``: Student-t with 3 degrees of freedom, scale 5e-3 (2, 1e-2), no base noise;
* ``bursts``: two runs of 4 % of the samples, Gaussian 0.5 (three of 2 %, 0.3);
* ``dropouts``: 10 % of the samples read as 0 (5 %).

``--pts-per-period N`` samples the trajectories N times per dominant period (the zoo:
100), e.g. 12 or 25 for coarse sampling.  ``--set NAME=VALUE`` (repeatable) replaces
one of these parameters (a field of ``robust_sindy.zoo.Contamination``;
``spikes_range`` as ``LOW,HIGH``), e.g. ``--set base_noise=0.01 --set heavy_dof=1``;
``--contamination zoo`` starts from the zoo's parameters instead of these.

Writes ``heldout.csv`` and ``heldout.md`` to the output folder.

    python validation/heldout_zoo.py [--systems 16] [--seed 3] [--draw 2026]
    [--samples 2000] [--pts-per-period 100] [--contamination heldout|zoo]
    [--set NAME=VALUE ...]
    [--out validation/results/heldout]
"""

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from robust_sindy import zoo

#: The held-out parameters (the zoo's: ``robust_sindy.zoo.ZOO_CONTAMINATION``).
HELDOUT = zoo.Contamination(
    base_noise=2e-3,
    rows_fraction=0.1,
    rows_scale=1.0,
    spikes_fraction=0.02,
    spikes_range=(3.0, 5.0),
    heavy_dof=3.0,
    heavy_scale=0.005,
    bursts=2,
    bursts_fraction=0.04,
    bursts_scale=0.5,
    dropouts_fraction=0.1,
)


def _case(system, family, derivatives, seed, samples, contamination, pts_per_period=100):
    try:
        return zoo.run_case(
            system, family, derivatives, seed, methods=("huber", "stlsq"),
            n_samples=samples, contamination=contamination, pts_per_period=pts_per_period,
        )  # fmt: skip
    except RuntimeError:  # an integration that fails is left out, as in the zoo
        return []


def contamination_with(settings, base: zoo.Contamination = HELDOUT) -> zoo.Contamination:
    """``base`` (``HELDOUT``) with the ``NAME=VALUE`` strings of ``settings`` applied."""
    fields = {f.name: f for f in dataclasses.fields(zoo.Contamination)}
    changes = {}
    for item in settings or []:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise SystemExit(
                f"--set expects NAME=VALUE with NAME one of {sorted(fields)}; got {item!r}"
            )
        try:
            if name == "spikes_range":
                low, high = (float(v) for v in value.split(","))
                changes[name] = (low, high)
            else:
                changes[name] = (int if name == "bursts" else float)(value)
        except ValueError:
            raise SystemExit(f"--set {name}: cannot read {value!r} as a number") from None
    return dataclasses.replace(base, **changes)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--systems", type=int, default=16)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--draw", type=int, default=2026, help="seed of the systems' draw")
    parser.add_argument("--samples", type=int, default=2000, help="samples per trajectory")
    parser.add_argument(
        "--pts-per-period", type=int, default=100, help="samples per dominant period"
    )
    parser.add_argument(
        "--contamination",
        choices=("heldout", "zoo"),
        default="heldout",
        help="the parameters to start from (the zoo's: robust_sindy.zoo.ZOO_CONTAMINATION)",
    )
    parser.add_argument(
        "--set", action="append", metavar="NAME=VALUE", help="replace a contamination parameter"
    )
    parser.add_argument("--out", default="validation/results/heldout")
    args = parser.parse_args(argv)
    base = HELDOUT if args.contamination == "heldout" else zoo.ZOO_CONTAMINATION
    contamination = contamination_with(args.set, base)
    systems = zoo.polynomial_systems()
    pick = np.random.default_rng(args.draw).choice(len(systems), args.systems, replace=False)
    cases = [
        (systems[i], f, d, args.seed, args.samples, contamination, args.pts_per_period)
        for i in pick
        for f in zoo.FAMILIES
        for d in zoo.DERIVATIVES
    ]
    rows = [r for rr in Parallel(n_jobs=2)(delayed(_case)(*c) for c in cases) for r in rr]
    df = pd.DataFrame(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "heldout.csv", index=False)
    rate = df.pivot_table(
        index=["family", "derivatives"], columns="method", values="exact", aggfunc="mean"
    ).reindex(zoo.FAMILIES, level=0)
    huber = df[df.method == "huber"]
    lines = [
        "# Held-out zoo check",
        "",
        f"Command: `python validation/heldout_zoo.py --systems {args.systems} "
        f"--seed {args.seed} --draw {args.draw} --samples {args.samples}"
        + (f" --pts-per-period {args.pts_per_period}" if args.pts_per_period != 100 else "")
        + (" --contamination zoo" if args.contamination == "zoo" else "")
        + "".join(f" --set {item}" for item in args.set or [])
        + "`. "
        f"Systems: {', '.join(sorted(df.system.unique()))}. "
        f"Contamination parameters: {args.contamination} (see the script's docstring"
        + (f"; changed: {', '.join(args.set)}" if args.set else "")
        + "). Cells: exact-support rate.",
        "",
        "| family | derivatives | huber | stlsq |",
        "|---|---|---|---|",
    ]
    for (family, derivatives), row in rate.iterrows():
        lines.append(
            f"| {family} | {derivatives} | {100 * row['huber']:.1f} % | "
            f"{100 * row['stlsq']:.1f} % |"
        )
    failed = huber[~huber.exact]
    lines += [
        "",
        f"HuberSINDy(): {len(failed)} failures of {len(huber)} cases, "
        f"{int((~failed.warned).sum())} without a warning; "
        f"{100 * huber[huber.exact].warned.mean():.0f} % of the successes warned.",
        "",
        "Failures per system: "
        + ", ".join(f"{k} {v}" for k, v in failed.groupby("system").size().items()),
    ]
    (out / "heldout.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
