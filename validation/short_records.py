"""The weak form on records short for their library: Lorenz-96 from the states.

Runs ``HuberSINDy()`` (``formulation="auto"``, degree-2 monomials, states only) and, on
the same record, the form ``auto`` did not take, and reports for each record the weak
form's independent rows per library term
(:meth:`robust_sindy.timeseries.weak.WeakRows.effective_rows`), the form ``auto`` chose,
and whether each form found exactly the true support.  Each case is
``states:samples:noise:seed:family``; the family is ``clean`` (uniform steps),
``irregular`` (uniformly random times), or one of the zoo's outlier families such as
``glitches`` (uniform steps); noise is relative to each state's root mean square.

    python validation/short_records.py [--jobs 2] [--out DIR] CASE [CASE ...]

The held-out measurement of the design notes ("Short records for the library take the
strong form"), its 40 cases (``HELDOUT``), about 25 minutes on two cores:

    python validation/short_records.py --heldout --out validation/results/short_records
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from robust_sindy import HuberSINDy, flows, zoo
from robust_sindy.library import PolynomialLibrary

#: Lorenz-96 with 8, 12 and 16 states on two record lengths each (about 0.6 and 1.3
#: independent rows per term in the weak form), three noise levels, uniform steps and
#: uniformly random times; glitches; 24 states.
HELDOUT = [
    f"{size}:{level}:41:{family}"
    for size in ("8:300", "8:600", "12:600", "12:1200", "16:1000", "16:2000")
    for level in ("0.005", "0.02", "0.04")
    for family in ("clean", "irregular")
] + [
    "12:600:0.04:43:glitches",
    "12:1200:0.04:43:glitches",
    "24:2000:0.02:42:clean",
    "24:4000:0.02:42:irregular",
]


def _fit(x, t, formulation, system) -> dict:
    model = HuberSINDy(library=PolynomialLibrary(degree=2), formulation=formulation)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t)
    coef = model.coef_.T
    found, truth = coef != 0, system.coef != 0
    per_term = np.nan
    if model.weak_ is not None:
        per_term = model.weak_.effective_rows() / coef.shape[0]
    return dict(
        form=model.diagnostics_.formulation,
        exact=bool(np.array_equal(found, truth)),
        wrong=int((found != truth).sum()),
        error=float(np.linalg.norm(coef - system.coef) / np.linalg.norm(system.coef)),
        warned=bool(caught),
        seconds=time.perf_counter() - start,
        per_term=per_term,
    )


def run_case(spec: str):
    """``spec`` = ``states:samples:noise:seed:family``: ``auto`` and the other form."""
    n, m, level, seed, family = spec.split(":")
    n, m, level, seed = int(n), int(m), float(level), int(seed)
    rng = np.random.default_rng([seed, 911, n])
    times = zoo.sample_times(family, m, 0.01, rng)
    t, x, _, system = flows.lorenz96_records(n, m, seed, times=times)
    outliers = family if family in zoo.ALL_FAMILIES and family not in zoo.TIME_FAMILIES else "clean"
    noisy, _ = zoo.contaminate_family(x, outliers, rng, zoo.Contamination(base_noise=level))
    auto = _fit(noisy, t, "auto", system)
    other = _fit(noisy, t, "weak" if auto["form"] == "strong" else "strong", system)
    return spec, auto, other


def _cell(r: dict) -> str:
    verdict = "exact" if r["exact"] else f"wrong ({r['wrong']} terms)"
    return f"{r['form']}: {verdict}{', warned' if r['warned'] else ''}, {r['seconds']:.0f} s"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="*", help="states:samples:noise:seed:family")
    parser.add_argument("--heldout", action="store_true", help="the cases of HELDOUT")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None, help="folder for short_records.md")
    args = parser.parse_args(argv)
    cases = args.cases + (HELDOUT if args.heldout else [])
    if not cases:
        parser.error("give cases, or --heldout")
    # One thread per case for the library's own threads (core.threads reads this at
    # each call); BLAS, loaded with NumPy above, keeps its own thread count.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    lines = [
        "| case | independent rows per term | `auto` | the other form |",
        "|---|---|---|---|",
    ]
    with ProcessPoolExecutor(args.jobs) as pool:
        for spec, auto, other in pool.map(run_case, cases):
            per_term = auto["per_term"] if auto["form"] == "weak" else other["per_term"]
            line = f"| {spec} | {per_term:.2f} | {_cell(auto)} | {_cell(other)} |"
            lines.append(line)
            print(line, flush=True)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        command = "python validation/short_records.py " + " ".join(argv or sys.argv[1:])
        text = f"# Short records for the library\n\nCommand: `{command}`.\n\n" + "\n".join(lines)
        (out / "short_records.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
