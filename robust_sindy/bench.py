"""Side-by-side benchmark of the fast path against the solvers people would use instead.

For each problem (the Lorenz set-up: states contaminated as in the paper, the monomial
library of a given degree, ``delta = 1``, ``lam = 1``, three target columns) every
solver runs in the same process: a warm-up, then the median of several timed runs.
Reported per run: time, ratio to the fast path, relative objective gap to the best
objective any solver found, relative KKT violation (:func:`robust_sindy.kkt_violation`),
peak memory allocated during one run after the warm-up (``tracemalloc``, numpy buffers
included; :func:`time_solver`) and, for
the fast path, its passes over ``Theta``.

Solvers: the fast path (batched Newton, ADMM fallback; default options), CVXPY +
Clarabel, CVXPY + OSQP, skglm (Huber + L1, ``alpha = lam / m``, no intercept;
optional), PySINDy's STLSQ (threshold 0.05, least squares: not the same problem, its
objective is evaluated but not compared; optional) and the ADMM with the paper's
settings.  The passes over ``Theta`` of the fast path are counted by the solver (plus
two for :func:`robust_sindy.fit`'s certificate).

:func:`run_pipeline` times whole identifications (``HuberSINDy()`` with its defaults
against PySINDy's STLSQ, SR3 with trimming and ``EnsembleOptimizer``, same library and
data) and :func:`path_cost` a 50-point warm-started lam path in units of cold fits.
"""

from __future__ import annotations

import csv
import importlib.util
import time
import tracemalloc
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .core.certificates import kkt_violation, objective
from .fitting import ConvergenceWarning, fit
from .library import PolynomialLibrary
from .noise import contaminate
from .solvers.problem import PAPER_OPTIONS
from .systems import Lorenz

__all__ = ["SOLVERS", "BenchRow", "bench_problem", "run", "time_solver"]

DELTA, LAM = 1.0, 1.0
FAST = "Newton (fast path)"
SOLVERS = (
    FAST,
    "CVXPY + Clarabel",
    "CVXPY + OSQP",
    "skglm",
    "PySINDy STLSQ",
    "ADMM (paper settings)",
)
#: Solvers that solve the Huber-Lasso problem (their objectives are compared).
HUBER_SOLVERS = (FAST, "CVXPY + Clarabel", "CVXPY + OSQP", "skglm",
                 "ADMM (paper settings)")  # fmt: skip


@dataclass
class BenchRow:
    """One solver on one problem."""

    problem: str
    m: int
    p: int
    solver: str
    time: float = np.nan  # median seconds
    runs: int = 0
    ratio: float = np.nan  # time / fast-path time
    gap: float = np.nan  # relative objective gap to the best Huber objective
    kkt: float = np.nan  # max relative KKT violation over columns
    peak_mb: float = np.nan
    passes: float = np.nan  # fast path only
    note: str = ""
    objective: np.ndarray | None = field(default=None, repr=False)  # per column


def bench_data(m: int, seed: int = 0, states: int = 3):
    """Time, contaminated states and derivatives of the Lorenz set-up (m samples).

    ``states=6`` puts two Lorenz trajectories from different initial states side by
    side (a 6-state data set with a known, block-diagonal model) for library scaling.
    """
    if states not in (3, 6):
        raise ValueError(f"states must be 3 or 6; got {states!r}")
    lorenz = Lorenz()
    rng = np.random.default_rng(seed)
    runs = [lorenz.generate(t_end=(m - 1) * 0.01)]
    if states == 6:
        runs.append(lorenz.generate(t_end=(m - 1) * 0.01, x0=[-5.0, 7.0, 30.0]))
    x = np.hstack([r.x for r in runs])
    x_dot = np.hstack([r.x_dot for r in runs])
    noisy = contaminate(x, x_dot, rng=rng)
    return runs[0].t, noisy.x, noisy.x_dot


def bench_problem(m: int, degree: int = 2, seed: int = 0, states: int = 3):
    """Library matrix (m, p) and targets (m, states) of the contaminated Lorenz set-up."""
    _, x, x_dot = bench_data(m, seed, states)
    lib = PolynomialLibrary(degree=degree).fit(x)
    return np.ascontiguousarray(lib.transform(x)), x_dot


def _available(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def _skglm(theta, y):
    from skglm import GeneralizedLinearEstimator
    from skglm.datafits import Huber
    from skglm.penalties import L1
    from skglm.solvers import AndersonCD

    m = theta.shape[0]
    coef = np.zeros((theta.shape[1], y.shape[1]))
    for k in range(y.shape[1]):
        est = GeneralizedLinearEstimator(
            datafit=Huber(DELTA),
            penalty=L1(LAM / m),
            solver=AndersonCD(tol=1e-8, fit_intercept=False, max_iter=200),
        )
        coef[:, k] = est.fit(theta, y[:, k]).coef_
    return coef


def _stlsq(theta, y):
    import pysindy as ps

    opt = ps.STLSQ(threshold=0.05)
    opt.fit(theta, y)
    return opt.coef_.T


def _runner(name: str, time_limit: float):
    if name == FAST:
        return lambda th, y: fit(th, y, delta=DELTA, lam=LAM).coef
    if name == "ADMM (paper settings)":
        return lambda th, y: fit(th, y, delta=DELTA, lam=LAM, **PAPER_OPTIONS).coef
    if name == "CVXPY + Clarabel":
        return lambda th, y: (
            fit(th, y, "cvxpy", DELTA, LAM, solver="clarabel", time_limit=time_limit).coef
        )
    if name == "CVXPY + OSQP":
        return lambda th, y: fit(
            th, y, "cvxpy", DELTA, LAM, solver="osqp", eps_abs=1e-8, eps_rel=1e-8,
            time_limit=time_limit,
        ).coef  # fmt: skip
    if name == "skglm":
        return _skglm
    if name == "PySINDy STLSQ":
        return _stlsq
    raise ValueError(f"unknown solver {name!r}; choose from {SOLVERS}")


def time_solver(f, theta, y, *, repeats: int, budget: float):
    """Warm-up, then up to ``repeats`` timed runs while ``budget`` seconds last.

    A solver whose warm-up alone takes half the budget is timed by that one run.
    Returns ``(median seconds, number of timed runs, coef of the last run, peak MB)``.
    The peak memory is that of a run after the warm-up where the warm-up took under a
    tenth of the budget (so that one-time costs -- imports, caches, compiling or
    loading compiled code -- are not counted as the solver's memory), else that of
    the warm-up.
    """

    def traced():
        tracemalloc.start()
        t0 = time.perf_counter()
        out = f(theta, y)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        return out, elapsed, peak

    coef, first, peak = traced()
    if first >= 0.5 * budget:
        return first, 1, coef, peak
    if first < 0.1 * budget:
        coef, _, peak = traced()
    times = []
    for _ in range(repeats):
        if times and sum(times) + first > budget:
            break
        t0 = time.perf_counter()
        coef = f(theta, y)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), len(times), coef, peak


def _child(conn, name, theta, y, repeats, budget, limit):
    try:
        conn.send(time_solver(_runner(name, limit), theta, y, repeats=repeats, budget=budget))
    except Exception as exc:  # reported by the parent
        conn.send(exc)
    conn.close()


def _guarded(name, theta, y, *, repeats, budget, limit):
    """``time_solver`` in a forked process, stopped after ``limit`` seconds.

    For peers without a time limit of their own (skglm): one slow configuration must
    not stall the whole benchmark.
    """
    import multiprocessing

    if multiprocessing.current_process().daemon:  # a worker that may not have children
        return _limited(name, theta, y, repeats=repeats, budget=budget, limit=limit)
    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, name, theta, y, repeats, budget, limit))
    proc.start()
    try:
        if not parent.poll(limit):
            raise TimeoutError(f"no result within {limit:.0f} s (stopped)")
        out = parent.recv()
    finally:
        proc.terminate()
        proc.join()
    if isinstance(out, Exception):
        raise out
    return out


def _limited(name, theta, y, *, repeats, budget, limit):
    """``time_solver`` in a thread of this process, given up after ``limit`` seconds
    (where no child process can be started; the thread is left to finish)."""
    import concurrent.futures

    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    job = pool.submit(time_solver, _runner(name, limit), theta, y, repeats=repeats, budget=budget)
    pool.shutdown(wait=False)
    try:
        return job.result(timeout=limit)
    except concurrent.futures.TimeoutError:
        raise TimeoutError(f"no result within {limit:.0f} s (given up)") from None


def counted_passes(theta, y) -> int:
    """Passes over ``Theta`` of one fast-path fit: those the solver counts, two per ADMM
    iteration of any fallback column, and two for the certificate of ``fit``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit(theta, y, delta=DELTA, lam=LAM)
    return int(res.info["passes"] + 2 * res.iterations.max(initial=0) + 2)


def run(
    sizes=((1_000, 2), (10_000, 2), (100_000, 2), (1_000_000, 2), (1_000, 3), (1_000, 4),
           (10_000, 3), (10_000, 4), (10_000, 5), (10_000, 2, 6), (1_000, 2, 6)),
    *,
    solvers=SOLVERS,
    repeats: int = 5,
    skip_after: float = 60.0,
    progress: bool = True,
    jobs: int = 1,
) -> list[BenchRow]:  # fmt: skip
    """Run every solver on every ``(m, degree[, states])`` problem; returns the rows.

    ``states`` is 3 (Lorenz) or 6 (two Lorenz trajectories side by side), for the
    scaling with the library size ``p``.

    CVXPY solvers get ``skip_after`` as their time limit; a solver whose time at the
    previous ``m`` of the same degree, scaled linearly in ``m``, exceeds ``skip_after``
    is skipped, with a note.  Slow solvers
    get fewer timed runs (see :func:`time_solver`); the table reports how many.

    The problems of one ``(degree, states)`` form a chain run in order of ``m`` (the
    skips look back along it); ``jobs`` other than 1 runs the chains in parallel through
    joblib (on a Dask cluster inside :func:`robust_sindy.parallel.scheduler`).  Every
    solver of a problem always runs in the same process, one after the other, so the
    ratios compare like with like; absolute times of chains run side by side share
    the machine.
    """
    from joblib import Parallel, delayed
    from tqdm import tqdm

    chains: dict[tuple, list] = {}
    for i, size in enumerate(sizes):
        m, degree, states = (*size, 3)[:3]
        chains.setdefault((degree, states), []).append((i, m, degree, states))
    if jobs == 1:
        bar = tqdm(total=len(sizes) * len(solvers), desc="bench", disable=not progress)
        done = [_chain(c, solvers, repeats, skip_after, bar) for c in chains.values()]
        bar.close()
    else:
        tasks = (delayed(_chain)(c, solvers, repeats, skip_after) for c in chains.values())
        out = Parallel(n_jobs=jobs, return_as="generator_unordered")(tasks)
        done = list(tqdm(out, total=len(chains), desc="bench chains", disable=not progress))
    blocks = sorted((b for chain in done for b in chain), key=lambda b: b[0])
    return [r for _, block in blocks for r in block]


_KERNELS_LOADED = False


def load_kernels() -> None:
    """Compile (in a fresh installation, tens of seconds) or load from the disk cache the
    compiled kernels, by one small identification, once per process, so that no timed
    or memory-traced run pays for it: under ``tracemalloc`` a first compilation took
    34 s, which :func:`time_solver` would have taken for the solver's time."""
    global _KERNELS_LOADED
    if _KERNELS_LOADED:
        return
    from .compile_kernels import warm_up

    warm_up()
    _KERNELS_LOADED = True


def _chain(problems, solvers, repeats, skip_after, bar=None) -> list[tuple[int, list]]:
    """The blocks (index, rows) of one chain of problems (see :func:`run`)."""
    load_kernels()  # in this process, before anything is timed
    last: dict[str, tuple[int, float]] = {}  # solver -> (m, seconds) at the previous m
    return [
        (i, _block(m, degree, states, solvers, repeats, skip_after, last, bar))
        for i, m, degree, states in problems
    ]


def _block(m, degree, states, solvers, repeats, skip_after, last, bar) -> list[BenchRow]:
    """Every solver on one problem, side by side in this process."""
    theta, y = bench_problem(m, degree, states=states)
    label = f"Lorenz degree {degree}" if states == 3 else f"2 x Lorenz degree {degree}"
    block = []
    for name in solvers:
        row = BenchRow(label, m, theta.shape[1], name)
        block.append(row)
        if bar is not None:
            bar.set_postfix_str(f"m={m} p={theta.shape[1]} {name}")
            bar.update()
        mod = {"skglm": "skglm", "PySINDy STLSQ": "pysindy"}.get(name)
        if mod and not _available(mod):
            row.note = f"skipped: {mod} not installed (pip install 'robust-sindy[bench]')"
            continue
        prev = last.get(name)
        if prev is not None and prev[1] * m / prev[0] > skip_after:
            row.note = (
                f"skipped: {prev[1]:.3g} s at m = {prev[0]} extrapolates linearly to "
                f"over {skip_after:.0f} s"
            )
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            warnings.simplefilter("ignore", UserWarning)
            budget = max(10.0, skip_after)
            try:
                if name == "skglm":
                    t, runs, coef, peak = _guarded(
                        name, theta, y, repeats=repeats, budget=budget, limit=2 * budget
                    )
                else:
                    t, runs, coef, peak = time_solver(
                        _runner(name, skip_after), theta, y, repeats=repeats, budget=budget
                    )
            except TimeoutError as exc:
                row.note = f"stopped: {exc}"
                last[name] = (m, np.inf)
                continue
            except Exception as exc:  # a peer failing is a result, not a crash
                row.note = f"failed: {type(exc).__name__}: {exc}"[:120]
                continue
        row.time, row.runs, row.peak_mb = t, runs, peak
        row.kkt = float(np.max(kkt_violation(theta, y, coef, delta=DELTA, lam=LAM)))
        row.objective = objective(theta, y, coef, delta=DELTA, lam=LAM)
        last[name] = (m, t)
    base = block[0].time if block[0].solver == FAST else np.nan
    found = [r.objective for r in block if r.solver in HUBER_SOLVERS and r.runs
             and r.kkt < 1e-3]  # fmt: skip
    best = np.min(found, axis=0) if found else None
    for r in block:
        if not r.runs:
            continue
        r.ratio = r.time / base
        if best is not None and r.solver in HUBER_SOLVERS:
            r.gap = float(np.max((r.objective - best) / np.abs(best)))
        if r.solver == "PySINDy STLSQ":
            r.note = "least squares: a different problem; gap and KKT refer to the Huber one"
    if block[0].runs and block[0].solver == FAST:
        block[0].passes = counted_passes(theta, y)
    return block


#: Whole identifications compared by :func:`run_pipeline` (PySINDy ones optional).
PIPELINES = (
    "HuberSINDy()",
    "PySINDy STLSQ",
    "PySINDy SR3 (trimming 0.1)",
    "PySINDy EnsembleOptimizer (STLSQ)",
)


@dataclass
class PipelineRow:
    """One identification method on one data set."""

    m: int
    states: int
    p: int
    method: str
    time: float = np.nan
    runs: int = 0
    ratio: float = np.nan  # time / PySINDy STLSQ time
    exact: bool | None = None  # support equal to the true one
    note: str = ""


def _identify(name: str, t, x, x_dot) -> np.ndarray:
    """Coefficients (n, p) of one identification method, degree-2 monomials."""
    if name == "HuberSINDy()":
        from .estimator import HuberSINDy

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # diagnostics are not timed differently
            return HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, t, x_dot=x_dot).coef_
    import pysindy as ps

    if name == "PySINDy STLSQ":
        opt = ps.STLSQ(threshold=0.05)
    elif name == "PySINDy SR3 (trimming 0.1)":
        opt = ps.SR3(reg_weight_lam=0.05, regularizer="L0", trimming_fraction=0.1)
    elif name == "PySINDy EnsembleOptimizer (STLSQ)":
        opt = ps.EnsembleOptimizer(ps.STLSQ(threshold=0.05), bagging=True, n_models=20)
    else:
        raise ValueError(f"unknown method {name!r}; choose from {PIPELINES}")
    model = ps.SINDy(optimizer=opt, feature_library=ps.PolynomialLibrary(degree=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(x, t=t, x_dot=x_dot)
    return model.coefficients()


def _true_support(states: int) -> np.ndarray:
    """True support (states, p) of ``bench_data`` in the degree-2 monomial order."""
    import re

    names = PolynomialLibrary(degree=2).fit(np.zeros((1, states))).get_feature_names()
    own = PolynomialLibrary(degree=2).fit(np.zeros((1, 3))).get_feature_names()
    true3 = Lorenz().true_coef(full=True) != 0  # (10, 3)
    truth = np.zeros((states, len(names)), dtype=bool)
    for b in range(states // 3):
        for j, term in enumerate(own):
            shifted = re.sub(r"x(\d)", lambda mt, b=b: f"x{int(mt.group(1)) + 3 * b}", term)
            truth[3 * b : 3 * b + 3, names.index(shifted)] = true3[j]
    return truth


def run_pipeline(
    sizes=((1_000, 3), (10_000, 3), (10_000, 6)), *, methods=PIPELINES, repeats: int = 3,
    progress: bool = True,
) -> list[PipelineRow]:  # fmt: skip
    """Time whole identifications on the contaminated Lorenz data (``bench_data``).

    Every method gets the same states, measured (contaminated) derivatives and a
    degree-2 monomial library; reported: median time over ``repeats`` runs after a
    warm-up, the ratio to PySINDy's STLSQ, and whether the support is exactly the
    true one (the identification quality the speed must not cost).
    """
    from tqdm import tqdm

    load_kernels()
    rows = []
    bar = tqdm(total=len(sizes) * len(methods), desc="pipelines", disable=not progress)
    for m, states in sizes:
        t, x, x_dot = bench_data(m, states=states)
        truth = _true_support(states)
        p = truth.shape[1]
        block = []
        for name in methods:
            bar.set_postfix_str(f"m={m} states={states} {name}")
            bar.update()
            row = PipelineRow(m, states, p, name)
            block.append(row)
            if name.startswith("PySINDy") and not _available("pysindy"):
                row.note = "skipped: pysindy not installed (pip install 'robust-sindy[bench]')"
                continue
            try:
                t_run, row.runs, coef, _ = time_solver(
                    lambda th, y, name=name, t=t: _identify(name, t, th, y),
                    x, x_dot, repeats=repeats, budget=120.0,
                )  # fmt: skip
            except Exception as exc:  # a peer failing is a result, not a crash
                row.note = f"failed: {type(exc).__name__}: {exc}"[:120]
                continue
            row.time = t_run
            row.exact = bool(np.array_equal(np.asarray(coef) != 0, truth))
        base = next((r.time for r in block if r.method == "PySINDy STLSQ" and r.runs), np.nan)
        for r in block:
            r.ratio = r.time / base
        rows += block
    bar.close()
    return rows


def path_cost(m: int = 10_000, degree: int = 2, n_lams: int = 50) -> dict:
    """Time of a warm-started ``n_lams``-point lam path in units of one cold fit.

    The cold-fit unit is the mean time of ``fit`` at every fifth grid value (same
    data: the contaminated Lorenz set-up, ``delta = 1``).
    """
    from .selection import path

    theta, y = bench_problem(m, degree)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        path(theta, y, DELTA, n_lams=n_lams)  # warm-up
        t0 = time.perf_counter()
        res = path(theta, y, DELTA, n_lams=n_lams)
        t_path = time.perf_counter() - t0
        cold = []
        for lam in res.lams[::5]:
            t0 = time.perf_counter()
            fit(theta, y, delta=DELTA, lam=lam)
            cold.append(time.perf_counter() - t0)
    unit = float(np.mean(cold))
    return {"m": m, "p": theta.shape[1], "points": n_lams, "path_s": t_path,
            "cold_fit_s": unit, "cold_fits": t_path / unit,
            "certified": bool(res.converged.all())}  # fmt: skip


def _fmt(v, spec):
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else format(v, spec)


def table(rows: list[BenchRow]) -> str:
    lines = [
        "| problem | m | p | solver | time [s] | runs | time / fast path | rel. objective gap "
        "| rel. KKT | peak memory [MB] | passes over Θ | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.problem} | {r.m} | {r.p} | {r.solver} | {_fmt(r.time, '.4g')} | {r.runs} | "
            f"{_fmt(r.ratio, '.3g')} | {_fmt(r.gap, '.1e')} | {_fmt(r.kkt, '.1e')} | "
            f"{_fmt(r.peak_mb, '.3g')} | {_fmt(r.passes, '.0f')} | {r.note} |"
        )
    return "\n".join(lines)


def pipeline_table(rows: list[PipelineRow]) -> str:
    lines = [
        "| m | states | p | method | time [s] | runs | time / PySINDy STLSQ | exact support "
        "| note |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        exact = "-" if r.exact is None else ("yes" if r.exact else "no")
        lines.append(
            f"| {r.m} | {r.states} | {r.p} | {r.method} | {_fmt(r.time, '.4g')} | {r.runs} | "
            f"{_fmt(r.ratio, '.3g')} | {exact} | {r.note} |"
        )
    return "\n".join(lines)


def path_table(cost: dict) -> str:
    return (
        "| m | p | points | path [s] | one cold fit [s] | path / cold fit | certified |\n"
        "|---|---|---|---|---|---|---|\n"
        f"| {cost['m']} | {cost['p']} | {cost['points']} | {cost['path_s']:.4g} | "
        f"{cost['cold_fit_s']:.4g} | {cost['cold_fits']:.3g} | {cost['certified']} |"
    )


def write(
    rows: list[BenchRow],
    out: Path,
    command: str,
    pipelines: list[PipelineRow] = (),
    cost: dict | None = None,
) -> list[Path]:
    """``benchmark.md``, ``benchmark.csv`` and ``benchmark.png`` (time against m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    theta_mb = {(r.m, r.p): r.m * r.p * 8 / 2**20 for r in rows}
    md = out / "benchmark.md"
    md.write_text(
        "# Benchmark: Huber-Lasso solvers side by side\n\n"
        f"Command: `{command}`. Lorenz set-up (states contaminated as in the paper), "
        "monomial library, delta = 1, lam = 1, three target columns; one process; median "
        "of the timed runs after a warm-up. Gap: relative objective gap to the best "
        "objective found by any Huber solver with KKT < 1e-3. Peak memory: allocated "
        "during one run after the warm-up (the warm-up itself for solvers slower than a "
        "tenth of the time budget; Θ itself is "
        + ", ".join(f"{v:.3g} MB at m = {m}, p = {p}" for (m, p), v in theta_mb.items())
        + ").\n\n"
        + table(rows)
        + "\n"
        + (
            "\n## Whole identifications\n\nContaminated Lorenz states and derivatives "
            "(6 states: two trajectories side by side), degree-2 monomials, every method "
            "with its defaults; time of one identification (median after a warm-up).\n\n"
            + pipeline_table(list(pipelines))
            + "\n"
            if pipelines
            else ""
        )
        + (
            "\n## Cost of a warm-started lam path\n\nTime of a 50-point path in units of "
            "the mean time of one cold `fit` at every fifth grid value.\n\n"
            + path_table(cost)
            + "\n"
            if cost
            else ""
        )
    )
    csv_path = out / "benchmark.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["problem", "m", "p", "solver", "time_s", "runs", "ratio", "gap", "kkt",
                    "peak_mb", "passes", "note"])  # fmt: skip
        for r in rows:
            w.writerow([r.problem, r.m, r.p, r.solver, r.time, r.runs, r.ratio, r.gap, r.kkt,
                        r.peak_mb, r.passes, r.note])  # fmt: skip
    fig, ax = plt.subplots(figsize=(7, 4.5))
    deg2 = [r for r in rows if r.problem.endswith("degree 2")]
    for name in dict.fromkeys(r.solver for r in deg2):
        pts = [(r.m, r.time) for r in deg2 if r.solver == name and r.runs]
        if pts:
            ms, ts = zip(*pts, strict=True)
            ax.loglog(ms, ts, "o-", label=name)
    ax.set_xlabel("samples m (degree-2 library, p = 10, 3 columns)")
    ax.set_ylabel("time [s]")
    ax.set_title("Huber-Lasso on the contaminated Lorenz set-up")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = out / "benchmark.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [md, csv_path, png]
