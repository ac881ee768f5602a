"""Out-of-core fits: the Huber-Lasso on data that does not fit in memory, through Dask.

The states (``m x 3``) and the measured derivatives are ``.npy`` files, read in row chunks
of 10^6 samples by the tasks that use them (:func:`robust_sindy.outofcore.from_npy`); the
library (monomials up to degree 2: 10 terms) is a lazy Dask expression of the states
(:func:`robust_sindy.outofcore.dask_library`), so ``Theta`` (``80 m`` bytes) exists only
one chunk at a time.  The data: Lorenz states
drawn from its attractor (a 20 000-sample trajectory, resampled with 1 % noise), exact
derivatives of the clean states, 10 % of the rows with gross errors (Gaussian, 50).
``delta = 0.5``, ``lam = 1``.

With ``--constraints`` both fits are constrained to an energy-preserving quadratic part
(:func:`robust_sindy.constraints.energy_preserving`; Lorenz's is), one problem over the
three equations; the KKT column is then the constrained certificate (stationarity with
the multipliers, and the constraints' relative residual).

Each measurement runs in a fresh process, so its peak resident memory is its own.

    python validation/out_of_core.py 1e6 1e7          # Dask against in memory
    python validation/out_of_core.py 1e8 --dask-only  # Theta 8 GB: Dask alone
    python validation/out_of_core.py 1e6 1e7 --constraints

Writes ``validation/results/out_of_core.md`` (``out_of_core_constrained.md`` with
``--constraints``; rows are appended per run).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CHUNK = 1_000_000
HERE = Path(__file__).parent


def make_data(m: int, folder: Path) -> tuple[Path, Path]:
    import robust_sindy as rs

    xs, ys = folder / f"x_{m}.npy", folder / f"y_{m}.npy"
    if xs.exists() and ys.exists():
        return xs, ys
    lorenz = rs.systems.Lorenz()
    pool = lorenz.generate(t_end=200.0, dt=0.01).x
    x = np.lib.format.open_memmap(xs, mode="w+", dtype=float, shape=(m, 3))
    y = np.lib.format.open_memmap(ys, mode="w+", dtype=float, shape=(m, 3))
    rng = np.random.default_rng(m)
    for a in range(0, m, CHUNK):
        b = min(m, a + CHUNK)
        clean = pool[rng.integers(0, len(pool), b - a)]
        x[a:b] = clean + 0.01 * rng.normal(size=clean.shape)
        dy = lorenz.rhs(0.0, clean)
        bad = rng.uniform(size=b - a) < 0.1
        dy[bad] += 50.0 * rng.normal(size=(int(bad.sum()), 3))
        y[a:b] = dy
    x.flush()
    y.flush()
    del x, y
    return xs, ys


def _anon_bytes() -> int:
    """Resident anonymous memory of this process (not file pages such as memory maps)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) * 1024
    return 0


def one(kind: str, m: int, folder: Path, constrained: bool = False) -> dict:
    """One measurement in this process: wall time, passes, certificate, peak memory."""
    import threading

    import robust_sindy as rs

    xs, ys = make_data(m, folder)
    peak_anon = [_anon_bytes()]
    stop = threading.Event()

    def sample():
        while not stop.wait(0.05):
            peak_anon[0] = max(peak_anon[0], _anon_bytes())

    watcher = threading.Thread(target=sample, daemon=True)
    watcher.start()
    library = rs.PolynomialLibrary(2)
    names = library.fit(np.zeros((1, 3))).get_feature_names()
    extra = {"constraints": rs.constraints.energy_preserving(names)} if constrained else {}
    t0 = time.perf_counter()
    if kind == "dask":
        x = rs.outofcore.from_npy(xs, CHUNK)  # each task reads its own rows
        y = rs.outofcore.from_npy(ys, CHUNK)
        _, theta = rs.outofcore.dask_library(library, x)
        res = rs.fit(theta, y, delta=0.5, lam=1.0, **extra)
        passes = res.info["passes"]
    else:
        x, y = np.load(xs), np.load(ys)
        theta = library.fit_transform(x)
        res = rs.fit(theta, y, delta=0.5, lam=1.0, **extra)
        passes = res.info.get("passes", float("nan"))
    seconds = time.perf_counter() - t0
    stop.set()
    watcher.join()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # bytes (Linux: KiB)
    return {
        "kind": kind,
        "m": m,
        "seconds": seconds,
        "passes": passes,
        "converged": bool(res.converged),
        "kkt": float(np.max(res.kkt if res.certificate_kkt is None else res.certificate_kkt)),
        "objective": [float(v) for v in res.objective],
        "coef": np.asarray(res.coef).tolist(),
        "peak_gb": peak / 1e9,
        "anon_gb": max(peak_anon[0], _anon_bytes()) / 1e9,
        "theta_gb": 80 * m / 1e9,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sizes", nargs="+", type=float, help="numbers of samples")
    parser.add_argument("--dask-only", action="store_true", help="skip the in-memory fit")
    parser.add_argument("--dir", default="/tmp/robust_sindy_ooc", help="folder for the data")
    parser.add_argument(
        "--constraints", action="store_true", help="energy-preserving constraints on both fits"
    )
    parser.add_argument("--one", nargs=2, metavar=("KIND", "M"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    folder = Path(args.dir)
    folder.mkdir(parents=True, exist_ok=True)
    if args.one:
        print(json.dumps(one(args.one[0], int(float(args.one[1])), folder, args.constraints)))
        return
    lines = []
    for m in (int(s) for s in args.sizes):
        make_data(m, folder)
        runs = {}
        for kind in ("dask",) if args.dask_only else ("dask", "memory"):
            out = subprocess.run(
                [sys.executable, __file__, "--dir", str(folder), "--one", kind, str(m), "0"]
                + (["--constraints"] if args.constraints else []),
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            runs[kind] = json.loads(out.stdout.strip().splitlines()[-1])
        d = runs["dask"]
        row = (
            f"| {m:.0e} | {d['theta_gb']:.2g} GB | {d['seconds']:.1f} s | {d['passes']} | "
            f"{d['kkt']:.1e} ({'certified' if d['converged'] else 'NOT certified'}) | "
            f"{d['anon_gb']:.2f} GB ({d['peak_gb']:.2f} GB) |"
        )
        if "memory" in runs:
            mem = runs["memory"]
            rel = np.max(
                np.abs(np.subtract(d["objective"], mem["objective"])) / np.abs(mem["objective"])
            )
            row += (
                f" {mem['seconds']:.1f} s ({d['seconds'] / mem['seconds']:.2f}x) | "
                f"{mem['anon_gb']:.2f} GB ({mem['peak_gb']:.2f} GB) | {rel:.1e} |"
            )
        else:
            row += " not run | | |"
        print(row, flush=True)
        lines.append(row)
    flag = " --constraints" if args.constraints else ""
    out = HERE / "results" / f"out_of_core{'_constrained' if args.constraints else ''}.md"
    if not out.exists():
        out.write_text(
            f"# Out-of-core fits (Dask){' under constraints' if args.constraints else ''}\n\n"
            f"From `python validation/out_of_core.py{flag}` "
            "(see its docstring for the data). "
            "Dask: states and derivatives read chunk by chunk from `.npy` files "
            "(`robust_sindy.outofcore.from_npy`), library evaluated chunk by chunk "
            "(10^6 rows), Dask's threaded scheduler on 2 cores. Memory: the largest "
            "anonymous resident memory of the measuring process (sampled every 50 ms), and "
            "in brackets its peak resident set, which also counts the file pages mapped "
            "while a chunk is read (page cache the system can reclaim). Objective "
            "difference: largest relative difference between the two certified optima.\n\n"
            "| m | Theta | Dask time | passes | KKT | Dask memory | in-memory time "
            "(Dask / in memory) | in-memory memory | objective difference |\n"
            "|---|---|---|---|---|---|---|---|---|\n"
        )
    with out.open("a") as f:
        f.write("\n".join(lines) + "\n")
    print(f"appended to {out}")


if __name__ == "__main__":
    main()
