"""A real flow record: the cylinder wake's POD amplitudes, with and without the physics.

``robust_sindy.datasets.load_cylinder_wake()``: the two leading oscillating modes and
the shift mode of a simulated flow past a cylinder, from the unstable steady flow to the
limit cycle of vortex shedding (3000 samples).  Its quadratic nonlinearity conserves
energy (the mean-field model of Noack et al. 2003).  For each record

* ``clean``: the amplitudes as published;
* ``glitches``: 3 % of the entries, each channel on its own, moved by 5 of its standard
  deviations (random sign);
* ``noise``: Gaussian noise of 2 % of each channel's standard deviation;

``HuberSINDy()`` with every choice automatic (degree-2 library, states only) is fitted
without constraints and with ``constraints="energy_preserving"``, and each model is
simulated from the record's first sample over the record's 300 time units.  A model is
*bounded* when the simulation stays within ten times the data's largest amplitude; the
limit cycle is compared over the last 50 time units: its radius ``sqrt(a1^2 + a2^2)``
and the shift mode's level, against the data's (2.304 and 2.245).  The contaminated
records are drawn ``--seeds`` times.

    python validation/cylinder_wake.py [--seeds 5] [--out validation/results/cylinder_wake]
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from robust_sindy import HuberSINDy
from robust_sindy.datasets import load_cylinder_wake

CASES = ("clean", "glitches", "noise")
VARIANTS = {"unconstrained": None, "energy preserving": "energy_preserving"}
#: The part of the record over which the limit cycle is measured (time units).
TAIL = 50.0
#: A simulation that leaves this multiple of the data's largest amplitude has blown up.
BLOWUP = 10.0


def contaminate(x, case: str, seed: int):
    """A copy of the states ``x`` in ``case`` (see the module docstring)."""
    x = np.array(x, dtype=float)
    if case == "clean":
        return x
    rng = np.random.default_rng(seed)
    s = x.std(axis=0)
    if case == "glitches":
        hit = rng.random(x.shape) < 0.03
        x[hit] += 5.0 * rng.choice([-1.0, 1.0], hit.sum()) * np.broadcast_to(s, x.shape)[hit]
    elif case == "noise":
        x += 0.02 * s * rng.normal(size=x.shape)
    else:
        raise ValueError(f"case must be one of {CASES}; got {case!r}")
    return x


def record(case: str, seed: int):
    """The record of ``case`` (the published amplitudes, or a contaminated copy)."""
    data = load_cylinder_wake()
    return data.t, contaminate(data.x, case, seed)


def limit_cycle(t, x):
    """Radius of the oscillating modes and level of the shift mode over the tail."""
    tail = t >= t[-1] - TAIL
    return float(np.hypot(x[tail, 0], x[tail, 1]).mean()), float(x[tail, 2].mean())


def simulate(model, x0, t, bound):
    """The model's trajectory from ``x0`` on ``t``, stopped where it leaves ``bound``."""

    def blowup(_t, v):
        return bound - np.abs(v).max()

    blowup.terminal = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return model.simulate(x0, t, events=blowup)


def run_one(case: str, seed: int, variant: str):
    t, x = record(case, seed)
    truth = load_cylinder_wake()
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = HuberSINDy(constraints=VARIANTS[variant]).fit(
            x, t=t, feature_names=list(truth.names)
        )
    seconds = time.perf_counter() - t0
    bound = BLOWUP * np.abs(truth.x).max()
    sim = simulate(model, truth.x[0], t, bound)
    bounded = len(sim) == len(t) and np.isfinite(sim).all()
    radius, level = limit_cycle(t, sim) if bounded else (np.nan, np.nan)
    d = model.diagnostics_
    return {
        "case": case, "seed": seed, "variant": variant, "seconds": seconds,
        "bounded": bool(bounded), "stopped_at": float(t[len(sim) - 1]),
        "radius": radius, "level": level,
        "terms": int(np.count_nonzero(model.coef_)),
        "energy_residual": d.energy_residual, "trapping_eigenvalue": d.trapping_eigenvalue,
        "warnings": len(caught), "model": model, "simulation": sim,
    }  # fmt: skip


def _cell(values, fmt):
    values = [v for v in values if np.isfinite(v)]
    if not values:
        return "-"
    if len(values) == 1:
        return format(values[0], fmt)
    low, mid, high = (format(v, fmt) for v in (min(values), np.median(values), max(values)))
    return f"{mid} ({low} to {high})"


def table(rows, reference) -> str:
    radius0, level0 = reference
    lines = [
        f"Data: limit-cycle radius {radius0:.3f}, shift-mode level {level0:.3f} "
        f"(last {TAIL:g} time units).",
        "",
        "| record | model | bounded | within 5 % | radius | shift level | terms | "
        "energy residual | trapping eigenvalue | time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in CASES:
        for variant in VARIANTS:
            sel = [r for r in rows if r["case"] == case and r["variant"] == variant]
            if not sel:
                continue
            close = [
                r["bounded"]
                and abs(r["radius"] / radius0 - 1) <= 0.05
                and abs(r["level"] / level0 - 1) <= 0.05
                for r in sel
            ]
            blew = [r["stopped_at"] for r in sel if not r["bounded"]]
            bounded = f"{sum(r['bounded'] for r in sel)}/{len(sel)}"
            if blew:
                bounded += f" (left at t = {_cell(blew, '.0f')})"
            lines.append(
                f"| {case} | {variant} | {bounded} | {sum(close)}/{len(sel)} | "
                f"{_cell([r['radius'] for r in sel], '.3f')} | "
                f"{_cell([r['level'] for r in sel], '.3f')} | "
                f"{_cell([r['terms'] for r in sel], '.0f')} | "
                f"{_cell([r['energy_residual'] for r in sel], '.1e')} | "
                f"{_cell([r['trapping_eigenvalue'] for r in sel], '.3f')} | "
                f"{_cell([r['seconds'] for r in sel], '.1f')} s |"
            )
    return "\n".join(lines) + "\n"


def figure(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truth = load_cylinder_wake()
    fig, axes = plt.subplots(len(CASES), 2, figsize=(11, 2.6 * len(CASES)), sharex=True)
    styles = {"unconstrained": ("tab:red", "--"), "energy preserving": ("tab:blue", "-")}
    for i, case in enumerate(CASES):
        for j, (col, label) in enumerate(((0, "a1"), (2, "a_shift"))):
            ax = axes[i, j]
            ax.plot(truth.t, truth.x[:, col], color="0.6", lw=2.5, label="data")
            for variant, (color, ls) in styles.items():
                r = next(r for r in rows if r["case"] == case and r["variant"] == variant)
                sim = r["simulation"]
                ax.plot(truth.t[: len(sim)], sim[:, col], color=color, ls=ls, lw=1,
                        label=variant + ("" if r["bounded"] else " (blows up)"))  # fmt: skip
            ax.set_ylim(-3.5 if col == 0 else -0.5, 3.5 if col == 0 else 4.5)
            ax.set_title(f"{case}: {label}")
            if i == len(CASES) - 1:
                ax.set_xlabel("t")
        axes[i, 0].legend(loc="lower left", fontsize=8)
    fig.suptitle("Cylinder wake: simulated from the first sample, against the data")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", default="validation/results/cylinder_wake")
    args = parser.parse_args(argv)
    jobs = [
        (case, seed, variant)
        for case in CASES
        for seed in (range(1) if case == "clean" else range(args.seeds))
        for variant in VARIANTS
    ]
    rows = [run_one(*job) for job in tqdm(jobs, desc="cylinder wake")]
    truth = load_cylinder_wake()
    text = table(rows, limit_cycle(truth.t, truth.x))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = f"python validation/cylinder_wake.py --seeds {args.seeds}"
    figure_line = (
        "\n![The seed-0 records simulated from their first sample: data, the "
        "unconstrained and the energy-preserving models](simulation.png)\n"
    )
    (out / "table.md").write_text(f"<!-- written by `{command}` -->\n\n{text}{figure_line}")
    figure([r for r in rows if r["seed"] == 0], out / "simulation.png")
    models = [
        f"{r['case']} (seed {r['seed']}), {r['variant']}:\n"
        + "\n".join("    " + eq for eq in r["model"].equations())
        for r in rows
        if r["seed"] == 0
    ]
    (out / "models.txt").write_text("\n\n".join(models) + "\n")
    print(text)


if __name__ == "__main__":
    main()
