"""robust-sindy: identify equations from a data file, reproduce the paper, benchmark, zoo.

``robust-sindy fit DATA [--time COL | --dt STEP] [--states a,b] [--controls u]
[--library poly:2] [--derivatives COLS|METHOD] [--out DIR]`` fits ``HuberSINDy`` to a
CSV/TSV/Parquet/NPZ table, prints the equations and diagnostics and writes the model file,
a report and figures (default ``./fit_results``); ``robust-sindy dataset lynx_hare`` writes
the shipped lynx-hare data as ``./lynx_hare.csv`` to try it on.
``robust-sindy reproduce [lorenz|drone|all] [--seeds N] [--out DIR] [--jobs J]``
re-runs the paper's experiments over many seeds, prints the tables and writes Markdown,
CSV and PNG files to ``DIR`` (default ``./reproduce_results``).  ``robust-sindy bench
[--quick] [--scheduler ADDRESS]`` times the fast path against the solvers people would use
instead and writes ``benchmark.md``/``.csv``/``.png`` (default ``./bench_results``).
``robust-sindy zoo`` identifies the polynomial flows of dysts under six contaminations.
No command writes into the package's committed results unless ``--out`` points there.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

import numpy as np

from . import reproduce as rp
from .diagnostics import count_kinds
from .noise import PLACEMENTS


def _progress(args) -> bool:
    """Progress bars unless ``--quiet``, and on a terminal only (not in a log)."""
    return not args.quiet and sys.stderr.isatty()


def _reproduce(args) -> int:
    from .parallel import scheduler

    with scheduler(args.scheduler):
        return _reproduce_run(args, -1 if args.scheduler else args.jobs)


def _reproduce_run(args, n_jobs) -> int:
    from joblib import Parallel, delayed
    from tqdm import tqdm

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    systems = list(rp.SYSTEMS) if args.system == "all" else [args.system]
    jobs = [(s, seed) for s in systems for seed in range(args.seeds)]
    tasks = (delayed(rp.run_seed)(s, seed, args.t_end, args.placement) for s, seed in jobs)
    runs = list(
        tqdm(
            Parallel(n_jobs=n_jobs, return_as="generator")(tasks),
            total=len(jobs),
            desc="seeds",
            disable=True if args.quiet else None,  # None: on a terminal only
        )
    )
    report = [
        "# Reproduction of the paper's tables",
        "",
        f"Command: `robust-sindy reproduce {args.system} --seeds {args.seeds} "
        f"--t-end {args.t_end} --placement {args.placement}`. Noise on the "
        f"{args.placement}; 20 % of the rows at sigma 0.5, 1e-3 elsewhere. "
        "Huber, paper ADMM and Huber, certified use delta = 1, lam = 1; Huber, auto chooses "
        "everything itself, as HuberSINDy() does: gross-outlier samples screened out, delta "
        "by the robust-scale rule, lam by the robust BIC over a 50-point path with the "
        "selection stage (relative contribution 0.005, Huber refit with lam = 0).",
        "",
    ]
    for system in systems:
        sruns = [r for r in runs if r["system"] == system]
        summary = rp.summarise(sruns)
        deltas = ", ".join(f"{d:.3g}" for d in sruns[0]["delta_auto"])
        lams = ", ".join(f"{v:.3g}" for v in sruns[0]["lam_auto"])
        flagged = np.array([r["flagged"] for r in sruns])
        hit = np.array([r["flagged_true"] for r in sruns])
        total = np.array([r["n_outliers"] for r in sruns])
        m_all = np.array([r["m"] for r in sruns])
        screening = (
            f"Screening (Huber, auto): flagged {np.median(flagged):.0f} samples per seed "
            f"(median; {flagged.min()}-{flagged.max()}); {100 * hit.sum() / total.sum():.1f} % "
            f"of the {total[0]} contaminated samples found; "
            f"{100 * (flagged - hit).sum() / max(1, (m_all - total).sum()):.1f} % of the "
            "clean samples flagged."
        )
        text = [
            f"## {system}",
            "",
            f"### Over {len(sruns)} seeds",
            "",
            rp.summary_table(summary),
            "",
            screening,
            "",
            f"### Coefficients, seed {sruns[0]['seed']} (Huber, auto: delta {deltas}; lam {lams})",
            "",
            rp.coefficient_tables(system, sruns[0]),
            "",
        ]
        print("\n".join(text[:8]))
        rp.write_csv(sruns, out / f"reproduce_{system}.csv")
        paths = rp.figures(system, sruns, out, args.t_end)
        text += [f"![{p.stem}]({p.name})" for p in paths] + [""]
        report += text
    md = out / ("reproduce.md" if args.system == "all" else f"reproduce_{args.system}.md")
    md.write_text("\n".join(report))
    print(f"wrote {md} and the CSV and PNG files beside it")
    kinds = [w[1] for r in runs for w in r["warnings"]]
    if kinds:
        fits = sum(bool(r["warnings"]) for r in runs)
        print(
            f"HuberSINDy() raised {len(kinds)} warnings in {fits} of {len(runs)} fits: "
            f"{count_kinds(kinds)}; each fit's are in the column 'warnings' of "
            + ", ".join(str(out / f"reproduce_{s}.csv") for s in systems)
        )
    return 0


def _bench(args) -> int:
    from . import bench
    from .parallel import scheduler

    if args.quick:
        sizes, repeats, pipe_sizes, path_m = ((200, 2),), 1, ((300, 3),), 300
    else:
        sizes, repeats = bench.run.__defaults__[0], args.repeats
        pipe_sizes, path_m = bench.run_pipeline.__defaults__[0], 10_000
    with scheduler(args.scheduler):
        rows = bench.run(sizes, repeats=repeats, skip_after=args.skip_after,
                         progress=_progress(args), jobs=-1 if args.scheduler else 1)  # fmt: skip
    pipelines = bench.run_pipeline(pipe_sizes, repeats=repeats, progress=_progress(args))
    cost = bench.path_cost(path_m)
    command = "robust-sindy bench" + (" --quick" if args.quick else "")
    print(bench.table(rows))
    print(bench.pipeline_table(pipelines))
    print(bench.path_table(cost))
    paths = bench.write(rows, Path(args.out), command, pipelines, cost)
    print("wrote", ", ".join(str(p) for p in paths))
    return 0


def _families(text: str) -> tuple:
    """``--families``: names of the zoo's families, comma-separated."""
    from .zoo import ALL_FAMILIES

    names = tuple(v.strip() for v in text.split(",") if v.strip())
    bad = [v for v in names if v not in ALL_FAMILIES]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown families {bad or [text]}: choose from {', '.join(ALL_FAMILIES)}"
        )
    return names


def _zoo(args) -> int:
    from . import zoo

    if args.families is None:
        args.families = zoo.ALL_FAMILIES
    from .parallel import scheduler

    jobs = -1 if args.scheduler else args.jobs
    with scheduler(args.scheduler):
        if args.quick:
            rows = zoo.run(n_systems=2, seeds=1, families=("clean", "spikes"), n_samples=600,
                           jobs=jobs, progress=_progress(args))  # fmt: skip
        else:
            rows = zoo.run(n_systems=args.systems, seeds=args.seeds, jobs=jobs,
                           families=args.families, progress=_progress(args))  # fmt: skip
    command = "robust-sindy zoo" + (" --quick" if args.quick else f" --seeds {args.seeds}")
    if not args.quick and tuple(args.families) != zoo.ALL_FAMILIES:
        command += " --families " + ",".join(args.families)
    print(zoo.table(zoo.summary(rows)))
    paths = zoo.write(rows, Path(args.out), command)
    print("wrote", ", ".join(str(p) for p in paths))
    huber = [r for r in rows if r["method"] == "huber"]
    warned = [r for r in huber if r["warned"]]
    if warned:
        print(
            f"HuberSINDy() warned in {len(warned)} of {len(huber)} cases "
            f"({sum(not r['exact'] for r in warned)} of its {sum(not r['exact'] for r in huber)} "
            f"failures, {sum(r['exact'] for r in warned)} right answers); each case's "
            f"warnings are in the column 'warnings' of {paths[0]}"
        )
    return 0


def frontier_help() -> str:
    from . import frontier

    return frontier.__doc__.split("\n\n")[0]


def _frontier(args) -> int:
    from . import frontier

    if args.quick:
        levels, n, methods = (0.01, 0.1), 2, ("huber", "stlsq", "stlsq_weak")
    else:
        levels = frontier.LEVELS if args.levels is None else _levels(args.levels)
        n, methods = args.systems, frontier.METHODS
    if args.published:
        protocol = frontier.published(jobs=args.jobs, progress=_progress(args))
        print(frontier.protocol_table(protocol))
        command = "robust-sindy frontier --published"
        paths = frontier.write_published(protocol, Path(args.out), command)
        print("wrote", ", ".join(str(p) for p in paths))
        return 0
    rows = frontier.run(n, args.draw, args.seed, levels, methods, args.jobs, _progress(args))
    command = "robust-sindy frontier" + (" --quick" if args.quick else
              f" --systems {n} --draw {args.draw} --seed {args.seed}")  # fmt: skip
    print(frontier.table(frontier.summary(rows)))
    paths = frontier.write(rows, Path(args.out), command)
    print("wrote", ", ".join(str(p) for p in paths))
    return 0


def _levels(text: str) -> tuple[float, ...]:
    try:
        levels = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"robust-sindy frontier: error: --levels: not numbers: {text!r}") from None
    if not levels or any(not (0 <= v < 10) for v in levels):
        raise SystemExit(f"robust-sindy frontier: error: --levels must be in [0, 10); got {text!r}")
    return levels


def _fit(args, parser) -> int:
    from .parallel import scheduler

    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(scheduler(args.scheduler))
        except (ValueError, ImportError) as exc:
            parser.exit(2, f"robust-sindy fit: error: --scheduler: {exc}\n")
        return _fit_job(args, parser)


def _fit_job(args, parser) -> int:
    from . import fit_command

    try:
        fit_command.run(
            args.data,
            out=args.out,
            time=args.time,
            dt=args.dt,
            states=args.states,
            controls=args.controls,
            library=args.library,
            terms=args.terms or (),
            derivatives=args.derivatives,
            delta=args.delta,
            lam=args.lam,
            formulation=args.formulation,
            constraints=args.constraints,
            progress=_progress(args),
        )
    except fit_command.InputError as exc:
        parser.exit(2, f"robust-sindy fit: error: {exc}\n")
    return 0


def _dataset(args) -> int:
    from importlib import resources

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    target = out / f"{args.name}.csv"
    target.write_text(resources.files("robust_sindy.datasets").joinpath(target.name).read_text())
    print(f"wrote {target}")
    return 0


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1; got {text!r}")
    return value


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0; got {text!r}")
    return value


def _folder(text: str) -> str:
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file, not a folder")
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not os.access(probe, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text!r}: {str(probe)!r} is not writable")
    return text


def _add_scheduler(parser, what: str = "the seeds", jobs: bool = True) -> None:
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help=f"run {what} on Dask: 'local' (a LocalCluster) or a scheduler address "
        '(needs pip install "robust-sindy[dask]"' + ("; --jobs is then ignored)" if jobs else ")"),
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="robust-sindy",
        description=__doc__.splitlines()[0],
        epilog="Run 'robust-sindy COMMAND --help' for a command's options.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    fit = sub.add_parser(
        "fit",
        help="identify equations from a data file (CSV, TSV, Parquet, NPZ)",
        description="Fit HuberSINDy to the columns of a table: print the equations and "
        "diagnostics, write model.json, report.md, data.png and coefficients.png.",
    )
    fit.add_argument("data", help="the data file: .csv, .tsv, .txt, .parquet or .npz")
    fit.add_argument(
        "--time", help="the time column (default: a column named t or time)", metavar="COL"
    )
    fit.add_argument("--dt", type=_positive, help="uniform time step, instead of a time column")
    fit.add_argument(
        "--states",
        metavar="A,B,...",
        help="state columns (default: every other numeric column)",
    )
    fit.add_argument("--controls", metavar="U1,U2", help="control (input) columns")
    fit.add_argument(
        "--library",
        default="poly:2",
        help="candidate terms: poly[:DEGREE] and trig[:FREQUENCIES] joined by '+', "
        "e.g. poly:3 or poly:2+trig (default poly:2)",
    )
    fit.add_argument(
        "--terms",
        action="append",
        metavar="EXPR",
        help="an extra candidate term, an expression of the columns such as 'sin(a)*b' "
        "(repeatable)",
    )
    fit.add_argument(
        "--derivatives",
        metavar="COLS|METHOD",
        help="measured derivative columns (one per state, in order), or how to "
        "differentiate the states: robust (default), finite_difference, savgol",
    )
    fit.add_argument("--delta", default="auto", help="Huber threshold (default: automatic)")
    fit.add_argument("--lam", default="auto", help="L1 weight (default: automatic)")
    fit.add_argument(
        "--formulation",
        choices=("auto", "strong", "weak"),
        default="auto",
        help="rows of the regression: samples with derivatives (strong), integrals "
        "against test functions (weak), or chosen from the data (auto, the default)",
    )
    fit.add_argument(
        "--constraints",
        choices=("energy_preserving",),
        default=None,
        help="refit the selected terms under linear constraints across equations: "
        "energy_preserving (the quadratic terms conserve |x|^2)",
    )
    fit.add_argument(
        "--out", type=_folder, default="fit_results", help="output folder (./fit_results)"
    )
    fit.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_scheduler(fit, "the row screen's pilot fits, in groups of equations", jobs=False)
    data = sub.add_parser(
        "dataset",
        help="write a data set shipped with the package as CSV (lynx_hare: Hudson's Bay "
        "Company pelts, 1900-1920)",
    )
    data.add_argument("name", choices=["lynx_hare"], help="the data set")
    data.add_argument("--out", type=_folder, default=".", help="folder (default: here)")
    rep = sub.add_parser("reproduce", help="re-run the paper's experiments over many seeds")
    rep.add_argument("system", nargs="?", default="all", choices=[*rp.SYSTEMS, "all"])
    rep.add_argument("--seeds", type=_count, default=20, help="number of seeds (default 20)")
    rep.add_argument(
        "--out",
        type=_folder,
        default="reproduce_results",
        help="folder for the Markdown, CSV and PNG files (./reproduce_results; "
        "--out validation/results refreshes the committed ones)",
    )
    rep.add_argument("--jobs", type=_count, default=2, help="parallel processes (default 2)")
    rep.add_argument("--t-end", type=_positive, default=10.0, help="simulated seconds (10)")
    rep.add_argument(
        "--placement",
        default="states",
        choices=PLACEMENTS,
        help="where the outliers go: on the measured states (the paper's set-up, "
        "default), on the derivatives, or both",
    )
    rep.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_scheduler(rep)
    ben = sub.add_parser(
        "bench",
        help="time the fast path against CVXPY, OSQP, skglm and PySINDy, whole "
        "identifications against PySINDy, and the cost of a lam path",
    )
    ben.add_argument("--quick", action="store_true", help="tiny sizes, one timed run each")
    ben.add_argument(
        "--out", type=_folder, default="bench_results", help="output folder (./bench_results)"
    )
    ben.add_argument("--repeats", type=_count, default=5, help="timed runs per solver (5)")
    ben.add_argument(
        "--skip-after",
        type=_positive,
        default=60.0,
        help="skip a solver at larger sizes after (60 s)",
    )
    ben.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_scheduler(ben, "the problem sizes (one library size per worker, its solvers side by side)")
    zoo_ = sub.add_parser(
        "zoo",
        help="identify the polynomial flows of dysts under six contaminations "
        '(needs pip install "robust-sindy[zoo]")',
    )
    zoo_.add_argument("--quick", action="store_true", help="two systems, two families")
    zoo_.add_argument("--seeds", type=_count, default=1, help="seeds per case (default 1)")
    zoo_.add_argument("--systems", type=_count, default=None, help="only the first N systems")
    zoo_.add_argument(
        "--out", type=_folder, default="zoo_results", help="output folder (./zoo_results)"
    )
    zoo_.add_argument(
        "--families",
        type=_families,
        default=None,
        help="comma-separated families (default: all; see robust_sindy.zoo.ALL_FAMILIES)",
    )
    zoo_.add_argument("--jobs", type=_count, default=2, help="parallel processes (default 2)")
    zoo_.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_scheduler(zoo_)
    fro = sub.add_parser(
        "frontier",
        help="identification from noisy states against the noise level, beside the peers",
        description=frontier_help(),
    )
    fro.add_argument("--quick", action="store_true", help="two systems, two noise levels")
    fro.add_argument("--systems", type=_count, default=20, help="systems drawn (default 20)")
    fro.add_argument("--draw", type=int, default=1, help="seed of the systems' draw (1)")
    fro.add_argument("--seed", type=int, default=0, help="seed of the trajectories and noise")
    fro.add_argument(
        "--levels", default=None, help="noise levels, comma-separated (0.001,0.01,0.05,0.1,0.2)"
    )
    fro.add_argument(
        "--published",
        action="store_true",
        help="run the published protocol instead (every system; slow)",
    )
    fro.add_argument("--out", type=_folder, default="frontier_results", help="output folder")
    fro.add_argument("--jobs", type=_count, default=2, help="parallel processes (default 2)")
    fro.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.command == "fit":
        return _fit(args, fit)
    if args.command == "dataset":
        return _dataset(args)
    if args.command == "zoo":
        return _zoo(args)
    if args.command == "bench":
        return _bench(args)
    if args.command == "reproduce":
        return _reproduce(args)
    if args.command == "frontier":
        return _frontier(args)
    return 2  # pragma: no cover - argparse enforces the sub-command


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
