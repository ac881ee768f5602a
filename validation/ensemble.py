"""Robust ensembles on the paper's systems and on the zoo; joblib against Dask.

1. Lorenz and the drone, contaminated as in the paper (20 % of the rows, sigma 0.5), three
   seeds: inclusion probabilities of the true and the spurious terms (20 block-bootstrap
   models each), and figures for seed 0.
2. The zoo (its first ``--zoo N`` systems, 0 for none, default all 80; families ``heavy``
   and ``rows`` with states only):
   exact support of ``EnsembleSINDy`` (10 models) against the single ``HuberSINDy()``
   fit, on the same data.
3. 100 models of the Lorenz ensemble through joblib (2 processes) and on a
   ``LocalCluster`` (2 workers), wall time side by side.

    python validation/ensemble.py [--zoo N]

Writes ``validation/results/ensemble/ensemble.md`` and its figures.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import robust_sindy as rs
from robust_sindy.noise import contaminate

OUT = Path(__file__).parent / "results" / "ensemble"


def paper_systems(lines: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines += [
        "## The paper's systems, contaminated as in the paper",
        "",
        "| system | seed | smallest inclusion of a true term | largest inclusion of a "
        "spurious term | exact support | uncertain terms | models that warned |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in ("Lorenz", "Drone"):
        system = getattr(rs.systems, name)()
        full = name == "Drone"
        truth = system.true_coef(full=True).T != 0 if full else system.true_coef().T != 0
        for seed in range(3):
            data = system.generate(t_end=10.0)
            noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(seed))
            ens = rs.EnsembleSINDy(
                rs.HuberSINDy(library=system.library()), n_models=20, random_state=seed,
                n_jobs=2,
            )  # fmt: skip
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ens.fit(noisy.x, data.t, x_dot=noisy.x_dot, u=data.u,
                        feature_names=system.input_names)  # fmt: skip
            pi = ens.inclusion_probability_
            spurious = pi[~truth].max() if (~truth).any() else float("nan")
            lines.append(
                f"| {name} | {seed} | {pi[truth].min():.2f} | {spurious:.2f} | "
                f"{np.array_equal(ens.support_, truth)} | {int(ens.uncertain_.sum())} | "
                f"{100 * ens.warned_fraction_:.0f} % |"
            )
            print(lines[-1], flush=True)
            if seed == 0:
                ax = ens.plot_inclusion()
                ax.figure.tight_layout()
                ax.figure.savefig(OUT / f"{name.lower()}_inclusion.png", dpi=110)
                plt.close(ax.figure)
                k = 300
                u = None if data.u is None else data.u[:k]
                axes = ens.plot_simulation(data.x[0], data.t[:k], u=u, data=noisy.x[:k])
                axes[0].figure.tight_layout()
                axes[0].figure.savefig(OUT / f"{name.lower()}_band.png", dpi=110)
                plt.close(axes[0].figure)
    lines += [
        "",
        "![Lorenz inclusion](lorenz_inclusion.png) ![drone inclusion](drone_inclusion.png)",
        "",
        "![Lorenz band](lorenz_band.png)",
        "",
    ]


def _zoo_case(system, family, seed):
    from robust_sindy import zoo

    rng = np.random.default_rng([seed, zoo.FAMILIES.index(family), 1])
    t, x, _ = zoo.simulate_system(system, 2000, seed)
    noisy, _ = zoo.contaminate_family(x, family, rng)
    lib = rs.PolynomialLibrary(degree=system.degree)
    out = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        single = rs.HuberSINDy(library=lib).fit(noisy, t)
    out["single"] = bool(np.array_equal(single.coef_.T != 0, system.coef != 0))
    out["single_warned"] = bool(caught)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ens = rs.EnsembleSINDy(rs.HuberSINDy(library=lib), n_models=10, random_state=seed)
        ens.fit(noisy, t)
    out["ensemble"] = bool(np.array_equal(ens.support_.T, system.coef != 0))
    out["ensemble_warned"] = any(issubclass(w.category, rs.IdentificationWarning) for w in caught)
    return system.name, family, out


def zoo_part(lines: list[str], n_systems: int) -> None:
    from joblib import Parallel, delayed

    from robust_sindy import zoo

    systems = zoo.polynomial_systems()[:n_systems]
    n_systems = len(systems)
    cases = [(s, f) for s in systems for f in ("heavy", "rows")]
    results = Parallel(n_jobs=2)(delayed(_zoo_case)(s, f, 0) for s, f in cases)
    lines += [
        f"## The zoo: the first {n_systems} systems, states only",
        "",
        "| family | cases | single fit exact | ensemble exact | ensemble wrong and "
        "silent | single wrong and silent |",
        "|---|---|---|---|---|---|",
    ]
    for family in ("heavy", "rows"):
        rows = [r for _, f, r in results if f == family]
        lines.append(
            f"| {family} | {len(rows)} | {sum(r['single'] for r in rows)} | "
            f"{sum(r['ensemble'] for r in rows)} | "
            f"{sum(not r['ensemble'] and not r['ensemble_warned'] for r in rows)} | "
            f"{sum(not r['single'] and not r['single_warned'] for r in rows)} |"
        )
        print(lines[-1], flush=True)
    lines.append("")
    differ = [(name, f, r) for name, f, r in results if r["single"] != r["ensemble"]]
    if differ:
        lines += ["Cases where the two disagree (exact support):", ""]
        lines += [
            f"* {name}, {f}: single {'exact' if r['single'] else 'wrong'}"
            f"{' (warned)' if r['single_warned'] else ''}, ensemble "
            f"{'exact' if r['ensemble'] else 'wrong'}{' (warned)' if r['ensemble_warned'] else ''}"
            for name, f, r in differ
        ]
        lines.append("")


def cluster_timing(lines: list[str]) -> None:
    from joblib import parallel_config

    from robust_sindy.parallel import scheduler

    system = rs.systems.Lorenz()
    data = system.generate(t_end=10.0)
    noisy = contaminate(data.x, data.x_dot, rng=np.random.default_rng(0))

    def run():
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ens = rs.EnsembleSINDy(n_models=100, random_state=0).fit(
                noisy.x, data.t, x_dot=noisy.x_dot
            )
        return time.perf_counter() - t0, ens

    with parallel_config(n_jobs=2):
        t_joblib, a = run()
    with scheduler("local", n_workers=2):
        t_dask, b = run()
    lines += [
        "## 100 models: joblib against a Dask LocalCluster",
        "",
        f"Lorenz (1001 samples, contaminated as above), 100 block-bootstrap models: joblib "
        f"with 2 processes {t_joblib:.1f} s, a LocalCluster with 2 workers {t_dask:.1f} s "
        f"({t_dask / t_joblib:.2f} times joblib's); identical coefficients: "
        f"{np.array_equal(a.coef_stack_, b.coef_stack_)}.",
        "",
    ]
    print(lines[-2], flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--zoo", type=int, default=1000, help="zoo systems (0: skip; all)")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Robust ensembles",
        "",
        "Command: `python validation/ensemble.py"
        + (f" --zoo {args.zoo}" if args.zoo != 1000 else "")
        + "` (2-core shared machine).",
        "",
    ]
    paper_systems(lines)
    if args.zoo:
        zoo_part(lines, args.zoo)
    cluster_timing(lines)
    (OUT / "ensemble.md").write_text("\n".join(lines) + "\n")
    print("wrote", OUT / "ensemble.md")


if __name__ == "__main__":
    main()
