"""The zoo: automatic identification on the polynomial flows of the ``dysts`` database.

Every polynomial flow of dysts (:mod:`robust_sindy.flows`) is identified from a
simulated trajectory under several kinds of contamination, with exact derivatives and
from the states alone, by :class:`~robust_sindy.HuberSINDy` with its defaults and by the
estimators people would use instead (PySINDy's STLSQ, SR3 with trimming, and a bagged
STLSQ ensemble), all given the same data.  Noise is relative to each state's standard
deviation ``s_k``; every family has the base noise ``1e-3 s_k`` on every entry (see
:data:`FAMILIES`).

Systems with many states: :func:`run_scaling` times whole identifications on
Lorenz-96 with 10 to 100 states (libraries of hundreds to thousands of terms) against
PySINDy's STLSQ (threshold 0.1, its default) on the same records (exact derivatives,
degree-2 monomials; ``clean``: the base noise, ``rows``: the ``rows`` family), side by
side in one process on one BLAS thread, with the ratio of the times, optionally the
peak memory against the library's own size, and whether each found exactly the true
support.

Needs the optional extra ``zoo`` (``pip install "robust-sindy[zoo]"``: dysts, and
pysindy for the peers).
"""

from __future__ import annotations

import math
import time
import tracemalloc
import warnings
from dataclasses import dataclass

import numpy as np

from .flows import (
    LORENZ96_STEP,
    ZooSystem,
    lorenz96,
    lorenz96_records,
    polynomial_systems,
    simulate_system,
    write_rows,
)

__all__ = [
    "ALL_FAMILIES",
    "CHANNELS",
    "DERIVATIVES",
    "FAMILIES",
    "METHODS",
    "SENSOR_FAMILIES",
    "TIME_FAMILIES",
    "ZOO_CONTAMINATION",
    "Contamination",
    "ScalingRow",
    "ZooSystem",
    "contaminate_family",
    "polynomial_systems",
    "run_case",
    "run_scaling",
    "sample_times",
    "scaling_table",
    "simulate_system",
]

#: Contamination families (all relative to each state's standard deviation ``s``):
#:
#: * ``clean``: only the base noise ``1e-3 s`` on every entry;
#: * ``rows``: 20 % of the samples (whole rows) get Gaussian noise ``0.2 s``;
#: * ``spikes``: 5 % of the entries (one state at a time) get a spike of ``+-(0.5 to 2) s``;
#: * ``heavy``: Student-t noise with 2 degrees of freedom, scale ``0.01 s``, on every entry;
#: * ``bursts``: three contiguous bursts of 2 % of the samples each, Gaussian ``0.3 s``;
#: * ``dropouts``: 5 % of the samples (whole rows) read as 0.
FAMILIES = ("clean", "rows", "spikes", "heavy", "bursts", "dropouts")
#: Records as sensors deliver them (base noise on every entry, as above):
#:
#: * ``missing``: 5 % of the entries (one state at a time) not measured (NaN);
#: * ``glitches``: 4 % of the entries (one state at a time) off by ``+-(3 to 20) s``
#:   (log-uniform);
#: * ``irregular``: the same number of samples at uniformly random times over the span;
#: * ``jitter``: each sample time off its grid by up to 40 % of the step;
#: * ``gaps``: three stretches of 5 % of the samples each not recorded.
#:
#: PySINDy's estimators are given the same records (the sample times as an array; the
#: samples with a missing entry left out, as it cannot take NaN).
SENSOR_FAMILIES = ("missing", "glitches", "irregular", "jitter", "gaps")
#: Every family of the zoo, in the order of its table.
ALL_FAMILIES = FAMILIES + SENSOR_FAMILIES
#: States of the Lorenz-96 systems on which the sensor families are also run (many
#: channels: a glitch or a missing reading in one of them costs its entry, not the
#: sample).
CHANNELS = (6, 10)
#: The families that change the sample times rather than the values.
TIME_FAMILIES = ("irregular", "jitter", "gaps")
#: ``exact``: the true derivatives at the true states; ``states``: none given.
DERIVATIVES = ("exact", "states")
#: Methods compared (``huber`` is ``HuberSINDy()`` with its defaults).
METHODS = ("huber", "stlsq", "sr3_trim", "ensemble")

BASE_NOISE = 1e-3


@dataclass(frozen=True)
class Contamination:
    """Parameters of the contamination families (fractions of samples or entries;
    amplitudes relative to each state's standard deviation).  The defaults are the
    zoo's (:data:`FAMILIES`); held-out checks pass others."""

    base_noise: float = BASE_NOISE
    rows_fraction: float = 0.2
    rows_scale: float = 0.2
    spikes_fraction: float = 0.05
    spikes_range: tuple[float, float] = (0.5, 2.0)
    heavy_dof: float = 2.0
    heavy_scale: float = 0.01
    bursts: int = 3
    bursts_fraction: float = 0.02
    bursts_scale: float = 0.3
    dropouts_fraction: float = 0.05
    missing_fraction: float = 0.05
    glitch_fraction: float = 0.04
    glitch_range: tuple[float, float] = (3.0, 20.0)
    jitter: float = 0.4
    gaps: int = 3
    gap_fraction: float = 0.05


#: The zoo's contamination.
ZOO_CONTAMINATION = Contamination()


def _entries(rng: np.random.Generator, fraction: float, m: int, n: int):
    """Row and column indices of ``round(fraction m n)`` distinct entries of an (m, n)
    array, drawn at random: contamination one state at a time."""
    flat = rng.choice(m * n, round(fraction * m * n), replace=False)
    return np.unravel_index(flat, (m, n))


def contaminate_family(
    x: np.ndarray, family: str, rng: np.random.Generator, params: Contamination = ZOO_CONTAMINATION
):
    """Measured states for ``family`` and the mask of contaminated entries (m, n);
    ``params`` sets the fractions and amplitudes (the zoo's by default)."""
    if family not in ALL_FAMILIES:
        raise ValueError(f"family must be one of {ALL_FAMILIES}; got {family!r}")
    m, n = x.shape
    s = x.std(axis=0)
    s = np.where(s > 0, s, 1.0)
    bad = np.zeros((m, n), dtype=bool)
    if family == "heavy":
        return x + params.heavy_scale * s * rng.standard_t(params.heavy_dof, size=(m, n)), bad
    noisy = x + params.base_noise * s * rng.normal(size=(m, n))
    if family == "rows":
        rows = rng.choice(m, round(params.rows_fraction * m), replace=False)
        noisy[rows] += params.rows_scale * s * rng.normal(size=(rows.size, n))
        bad[rows] = True
    elif family == "spikes":
        i, j = _entries(rng, params.spikes_fraction, m, n)
        k = i.size
        noisy[i, j] += rng.choice([-1.0, 1.0], k) * rng.uniform(*params.spikes_range, k) * s[j]
        bad[i, j] = True
    elif family == "bursts":
        length = max(1, round(params.bursts_fraction * m))
        for start in rng.choice(m - length, params.bursts, replace=False):
            sl = slice(start, start + length)
            noisy[sl] += params.bursts_scale * s * rng.normal(size=(length, n))
            bad[sl] = True
    elif family == "dropouts":
        rows = rng.choice(m, round(params.dropouts_fraction * m), replace=False)
        noisy[rows] = 0.0
        bad[rows] = True
    elif family in ("missing", "glitches"):
        fraction = params.missing_fraction if family == "missing" else params.glitch_fraction
        i, j = _entries(rng, fraction, m, n)
        k = i.size
        if family == "missing":
            noisy[i, j] = np.nan
        else:
            lo, hi = np.log(params.glitch_range[0]), np.log(params.glitch_range[1])
            noisy[i, j] += rng.choice([-1.0, 1.0], k) * np.exp(rng.uniform(lo, hi, k)) * s[j]
        bad[i, j] = True
    return noisy, bad


def sample_times(
    family: str, n_samples: int, dt: float, rng: np.random.Generator,
    params: Contamination = ZOO_CONTAMINATION,
) -> np.ndarray | None:  # fmt: skip
    """The sample times (from 0) of a family of :data:`TIME_FAMILIES` with ``n_samples``
    samples at the nominal step ``dt``; None for the others (the uniform grid)."""
    if family not in TIME_FAMILIES:
        return None
    if family == "irregular":
        t = np.sort(rng.uniform(0.0, dt * (n_samples - 1), n_samples))
    elif family == "jitter":
        t = dt * (np.arange(n_samples) + rng.uniform(-params.jitter, params.jitter, n_samples))
    else:
        length = round(params.gap_fraction * n_samples)
        total = n_samples + params.gaps * length
        kept = np.ones(total, dtype=bool)
        # Gaps that neither touch nor overlap: one start in each of `gaps` equal parts.
        part = total // params.gaps
        for g in range(params.gaps):
            start = g * part + 1 + int(rng.integers(0, part - length - 1))
            kept[start : start + length] = False
        t = dt * np.flatnonzero(kept)[:n_samples]
    return t - t[0]


def _fit_method(method, system, t, x, x_dot, seed=0):
    """Coefficients (p, n) found by ``method`` (``x_dot`` None: from the states);
    ``seed`` seeds the draws of PySINDy's ensembles, which use NumPy's global random
    state (restored afterwards), so that every run of a case gives the same result."""
    from .estimator import HuberSINDy
    from .library import PolynomialLibrary

    if method == "huber":
        model = HuberSINDy(library=PolynomialLibrary(degree=system.degree))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model.fit(x, t, x_dot=x_dot)
        return model.coef_.T, [str(w.message) for w in caught]
    import pysindy as ps

    lost = np.isnan(x).any(axis=1)
    if lost.any():  # PySINDy takes no NaN: the samples with a missing entry left out
        x, t = x[~lost], t[~lost]
        x_dot = None if x_dot is None else x_dot[~lost]
    optimizers = {
        "stlsq": lambda: ps.STLSQ(),
        "sr3_trim": lambda: ps.SR3(
            reg_weight_lam=0.1, regularizer="L0", trimming_fraction=0.2, max_iter=200
        ),
        "ensemble": lambda: ps.EnsembleOptimizer(ps.STLSQ(), bagging=True, n_models=20),
    }
    model = ps.SINDy(
        optimizer=optimizers[method](),
        feature_library=ps.PolynomialLibrary(degree=system.degree),
    )
    state = np.random.get_state()  # noqa: NPY002 (the legacy state PySINDy draws from)
    np.random.seed(seed)  # noqa: NPY002 (the legacy state PySINDy draws from)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(x, t=t, x_dot=x_dot)
    finally:
        np.random.set_state(state)  # noqa: NPY002 (the legacy state PySINDy draws from)
    coef = np.asarray(model.coefficients()).T
    return coef, []


def run_case(
    system: ZooSystem,
    family: str,
    derivatives: str,
    seed: int,
    methods=METHODS,
    n_samples: int = 2000,
    contamination: Contamination = ZOO_CONTAMINATION,
    pts_per_period: int = 100,
) -> list[dict]:
    """Identify ``system`` under one contamination case with every method; one row each
    (``contamination``, ``pts_per_period``: other parameters for held-out checks)."""
    rng = np.random.default_rng([seed, ALL_FAMILIES.index(family), DERIVATIVES.index(derivatives)])
    times = sample_times(family, n_samples, system.dt * 100.0 / pts_per_period, rng, contamination)
    t, x, dx = simulate_system(system, n_samples, seed, pts_per_period, times=times)
    noisy, bad = contaminate_family(x, family, rng, contamination)
    x_dot = dx if derivatives == "exact" else None
    peer_seed = int(rng.integers(2**31))
    true = system.coef
    rows = []
    for method in methods:
        t0 = time.perf_counter()
        try:
            coef, warned = _fit_method(method, system, t, noisy, x_dot, peer_seed)
            error = ""
        except Exception as exc:  # a peer that fails counts as a miss, with its reason
            coef, warned, error = np.full_like(true, np.nan), [], f"{type(exc).__name__}: {exc}"
        elapsed = time.perf_counter() - t0
        finite = np.all(np.isfinite(coef))
        rows.append(
            dict(
                system=system.name,
                states=system.n_states,
                family=family,
                derivatives=derivatives,
                seed=seed,
                method=method,
                exact=bool(finite and np.array_equal(coef != 0, true != 0)),
                iae=float(np.abs(coef - true).sum()) if finite else math.inf,
                n_true=int((true != 0).sum()),
                n_found=int((coef != 0).sum()) if finite else -1,
                warned=len(warned) > 0,
                warnings=" | ".join(sorted(set(warned)))[:300],
                error=error[:300],
                contaminated=float(bad.any(axis=1).mean()),
                seconds=elapsed,
            )
        )
    return rows


def run(
    n_systems: int | None = None,
    seeds: int = 1,
    families=ALL_FAMILIES,
    derivatives=DERIVATIVES,
    methods=METHODS,
    n_samples: int = 2000,
    jobs: int = 2,
    progress: bool = True,
) -> list[dict]:
    """Every case of the zoo (or the first ``n_systems`` systems); one row per method."""
    from joblib import Parallel, delayed
    from tqdm import tqdm

    systems = polynomial_systems(first=n_systems)
    cases = [
        (s, f, d, seed) for s in systems for f in families for d in derivatives
        for seed in range(seeds)
    ]  # fmt: skip
    if n_systems is None:  # many channels: the sensor families on Lorenz-96
        cases += [
            (lorenz96(n), f, d, seed) for n in CHANNELS for f in families
            if f in SENSOR_FAMILIES for d in derivatives for seed in range(seeds)
        ]  # fmt: skip

    def one(system, family, deriv, seed):
        try:
            return run_case(system, family, deriv, seed, methods, n_samples)
        except RuntimeError:  # the trajectory could not be integrated: not a case
            return []

    tasks = (delayed(one)(*c) for c in cases)
    out = Parallel(n_jobs=jobs, return_as="generator")(tasks)
    rows = []
    for r in tqdm(out, total=len(cases), desc="zoo cases", disable=not progress):
        rows.extend(r)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Exact-support rate, median IAE and warning rates per (family, derivatives, method)."""
    keys = sorted({(r["family"], r["derivatives"], r["method"]) for r in rows},
                  key=lambda k: (ALL_FAMILIES.index(k[0]), DERIVATIVES.index(k[1]),
                                 METHODS.index(k[2])))  # fmt: skip
    out = []
    for fam, der, met in keys:
        sel = [r for r in rows if (r["family"], r["derivatives"], r["method"]) == (fam, der, met)]
        exact = np.array([r["exact"] for r in sel])
        warned = np.array([r["warned"] for r in sel])
        out.append(
            dict(
                family=fam,
                derivatives=der,
                method=met,
                cases=len(sel),
                exact=float(exact.mean()),
                median_iae=float(np.median([r["iae"] for r in sel])),
                failures_warned=float(warned[~exact].mean()) if (~exact).any() else math.nan,
                successes_warned=float(warned[exact].mean()) if exact.any() else math.nan,
                median_seconds=float(np.median([r["seconds"] for r in sel])),
            )
        )
    return out


def table(summ: list[dict]) -> str:
    """Markdown: exact-support rate per family and derivatives (rows) and method (columns)."""
    methods = [m for m in METHODS if any(s["method"] == m for s in summ)]
    head = (
        "| family | derivatives | "
        + " | ".join(methods)
        + " | huber: failures warned | huber: right but warned |"
    )
    lines = [head, "|" + "---|" * (len(methods) + 4)]
    cells = {(s["family"], s["derivatives"], s["method"]): s for s in summ}
    for fam in ALL_FAMILIES:
        for der in DERIVATIVES:
            if (fam, der, methods[0]) not in cells:
                continue
            row = [
                f"{100 * cells[(fam, der, m)]['exact']:.0f} % "
                f"({cells[(fam, der, m)]['median_iae']:.2g})"
                for m in methods
            ]
            huber = cells.get((fam, der, "huber"), {})
            shares = [huber.get(k, math.nan) for k in ("failures_warned", "successes_warned")]
            w = " | ".join("-" if math.isnan(v) else f"{100 * v:.0f} %" for v in shares)
            lines.append(f"| {fam} | {der} | " + " | ".join(row) + f" | {w} |")
    return "\n".join(lines)


def write(rows: list[dict], out, command: str) -> list:
    """``zoo.csv`` (every case), ``zoo.md`` (the table) and ``zoo.png`` in ``out``."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    write_rows(rows, out / "zoo.csv")
    many = [r for r in rows if int(r.get("states", 0)) > 4]
    rows = [r for r in rows if int(r.get("states", 0)) <= 4]
    summ = summary(rows)
    n_sys = len({r["system"] for r in rows})
    n_seeds = len({r["seed"] for r in rows})
    text = [
        "# The zoo: polynomial flows of dysts",
        "",
        f"Command: `{command}`. {n_sys} systems, {n_seeds} seed(s), 2000 samples at 100 "
        "per period. Cells: exact-support rate (median IAE). Families and methods: "
        "`robust_sindy.zoo`. The last columns: of the cases HuberSINDy() got wrong, the "
        "share in which it raised a warning; of those it got right, the share in which it "
        "warned anyway.",
        "",
        table(summ),
        "",
        "![zoo](zoo.png)",
        "",
    ]
    if many:
        names = sorted({r["system"] for r in many}, key=lambda v: (len(v), v))
        text += [
            "## Many channels",
            "",
            f"The sensor families on {', '.join(names)} (`robust_sindy.flows.lorenz96`), "
            "the same cells:",
            "",
            table(summary(many)),
            "",
        ]
    (out / "zoo.md").write_text("\n".join(text))
    fig, axes = plt.subplots(1, len(DERIVATIVES), figsize=(13, 4.2), sharey=True)
    methods = [m for m in METHODS if any(s["method"] == m for s in summ)]
    width = 0.8 / len(methods)
    for ax, der in zip(np.atleast_1d(axes), DERIVATIVES, strict=False):
        for i, met in enumerate(methods):
            vals = [
                next((s["exact"] for s in summ
                      if (s["family"], s["derivatives"], s["method"]) == (f, der, met)), np.nan)
                for f in ALL_FAMILIES
            ]  # fmt: skip
            ax.bar(np.arange(len(ALL_FAMILIES)) + i * width, vals, width, label=met)
        ax.set_xticks(
            np.arange(len(ALL_FAMILIES)) + 0.4 - width / 2, ALL_FAMILIES, rotation=40, ha="right"
        )
        ax.set_title(f"derivatives: {der}")
        ax.set_ylim(0, 1)
    np.atleast_1d(axes)[0].set_ylabel("exact support rate")
    np.atleast_1d(axes)[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "zoo.png", dpi=110)
    plt.close(fig)
    return [out / "zoo.csv", out / "zoo.md", out / "zoo.png"]


# ---------------------------------------------------------------------------------------
# many states


@dataclass
class ScalingRow:
    """One method on one record of :func:`run_scaling`."""

    states: int
    terms: int
    samples: int
    family: str
    method: str
    step: float = LORENZ96_STEP  # sampling step of the record
    seconds: float = np.nan
    ratio: float = np.nan  # seconds / PySINDy STLSQ's seconds on the same record
    peak_mb: float = np.nan
    theta_mb: float = np.nan
    exact: bool | None = None
    found: int = 0  # terms found
    true: int = 0
    note: str = ""


#: Methods :func:`run_scaling` compares, and their names in its table.
SCALING_METHODS = ("huber", "stlsq")
NAMES = {"huber": "HuberSINDy()", "stlsq": "PySINDy STLSQ"}


def _timed_fit(method, system, t, x, x_dot, seed, memory):
    """Coefficients, seconds and (``memory``) peak traced MB of one fit on one thread."""
    from threadpoolctl import threadpool_limits

    def once():
        with threadpool_limits(1), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return _fit_method(method, system, t, x, x_dot, seed)[0]

    t0 = time.perf_counter()
    coef = once()
    seconds = time.perf_counter() - t0
    peak = np.nan
    if memory:  # a second run: tracing slows allocations, so it is not timed
        tracemalloc.start()
        once()
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    return coef, seconds, peak


def run_scaling(
    sizes=((10, 4000), (20, 4000)),
    families=("clean", "rows"),
    seed: int = 0,
    methods=SCALING_METHODS,
    memory: bool = False,
    progress: bool = True,
    derivatives: str = "exact",
    noise: float = 0.0,
) -> list[ScalingRow]:
    """Time each method on Lorenz-96 records of each (states, samples) or (states,
    samples, step) size and contamination family
    (:func:`~robust_sindy.flows.lorenz96_records`; the step 0.01 where none is given);
    with ``memory``, the peak memory of ``HuberSINDy()`` from a second, traced run.
    A longer step covers more of the attractor with the same samples: with 100 states
    the degree-2 monomials of 12 000 samples 0.01 apart are numerically collinear
    (thousands of their Gram matrix's eigenvalues below 1e-11 of the largest), 0.1
    apart they are not.

    ``derivatives="states"`` gives both methods the states alone (each differentiates
    them its own way); ``noise`` adds Gaussian noise of that share of each state's
    spread to every reading before the family's contamination."""
    if derivatives not in DERIVATIVES:
        raise ValueError(f"derivatives must be one of {DERIVATIVES}; got {derivatives!r}")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite number >= 0; got {noise!r}")
    from tqdm import tqdm

    from .compile_kernels import warm_up

    warm_up()  # the kernels compiled or loaded before any timing
    if "stlsq" in methods:
        import pysindy  # noqa: F401  (its import is not the fit's time)
    rows = []
    bar = tqdm(total=len(sizes) * len(families) * len(methods), desc="scaling",
               disable=not progress)  # fmt: skip
    for n, m, *rest in sizes:
        step = float(rest[0]) if rest else LORENZ96_STEP
        times = step * np.arange(m) if rest else None
        t, x, x_dot, system = lorenz96_records(n, m, seed, times=times)
        if noise > 0:
            x = x + noise * x.std(axis=0) * np.random.default_rng([seed, n, m, 1]).normal(
                size=x.shape
            )
        if derivatives == "states":
            x_dot = None
        truth = system.coef != 0
        for family in families:
            noisy, _ = contaminate_family(x, family, np.random.default_rng([seed, n, m]))
            block = []
            for method in methods:
                bar.set_postfix_str(f"n={n} {family} {method}")
                row = ScalingRow(n, truth.shape[0], m, family, NAMES[method], step,
                                 theta_mb=m * truth.shape[0] * 8 / 2**20,
                                 true=int(truth.sum()))  # fmt: skip
                try:
                    coef, row.seconds, row.peak_mb = _timed_fit(
                        method, system, t, noisy, x_dot, seed, memory and method == "huber"
                    )
                    found = np.abs(np.asarray(coef)) > 0
                    row.exact = bool(np.array_equal(found, truth))
                    row.found = int(found.sum())
                except Exception as exc:  # a method failing is a result, not a crash
                    row.note = f"failed: {type(exc).__name__}: {exc}"[:120]
                block.append(row)
                bar.update()
            base = next((r.seconds for r in block if r.method == NAMES["stlsq"]), np.nan)
            for r in block:
                r.ratio = r.seconds / base
            rows += block
    bar.close()
    return rows


def scaling_table(rows: list[ScalingRow]) -> str:
    """Markdown: one line per record, the methods side by side."""
    out = [
        "| states (terms) | samples | family | HuberSINDy() | PySINDy STLSQ | time ratio | "
        "peak memory / Θ |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(r):
        if r is None:
            return "not run"
        if r.exact is None:
            return r.note
        verdict = "exact" if r.exact else f"wrong ({r.found} terms, {r.true} true)"
        return f"{r.seconds:.3g} s, {verdict}"

    for n, m, step, family in dict.fromkeys((r.states, r.samples, r.step, r.family) for r in rows):
        sel = {
            r.method: r
            for r in rows
            if (r.states, r.samples, r.step, r.family) == (n, m, step, family)
        }
        h, s = sel.get(NAMES["huber"]), sel.get(NAMES["stlsq"])
        ratio = f"{h.ratio:.1f}" if h is not None and np.isfinite(h.ratio) else "n/a"
        mem = f"{h.peak_mb / h.theta_mb:.1f}" if h is not None and np.isfinite(h.peak_mb) else "n/a"
        terms = (h or s).terms
        samples = f"{m}" if step == LORENZ96_STEP else f"{m} (step {step:g})"
        out.append(
            f"| {n} ({terms}) | {samples} | {family} | {cell(h)} | {cell(s)} | {ratio} | {mem} |"
        )
    return "\n".join(out)
