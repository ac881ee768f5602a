"""One fit's groups of equations on a Dask cluster, against the machine's own threads.

Fits ``HuberSINDy()`` (its defaults, degree-2 monomials, exact derivatives) to Lorenz-96
records (:func:`robust_sindy.flows.lorenz96_records`, clean or with the zoo's ``rows``
contamination) twice in one process: on this machine's cores (threads, BLAS on one
thread), then inside ``robust_sindy.parallel.scheduler`` with a LocalCluster of
``--workers`` single-threaded workers (or ``--scheduler ADDRESS``, a running cluster),
where the row screen's pilot fits go to the workers in groups of equations.  Before the
timed cluster fit, a small fit loads the compiled kernels on every worker.  Reports
both times, their ratio, whether each fit found the true support, and whether the two
models are identical bit for bit.

    python validation/cluster.py [--sizes 20:4000,40:12000] [--families clean,rows]
                                 [--workers 2] [--out validation/results/cluster]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.compile_kernels import warm_up
from robust_sindy.flows import lorenz96_records, write_rows
from robust_sindy.parallel import scheduler
from robust_sindy.zoo import contaminate_family


def _fit(x, t, x_dot):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start = time.perf_counter()
        model = HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, t, x_dot=x_dot)
        return model, time.perf_counter() - start


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="20:4000,40:12000",
                        help="states:samples pairs, comma-separated")  # fmt: skip
    parser.add_argument("--families", default="clean,rows")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", default="local", help="'local' or a scheduler address")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="validation/results/cluster")
    args = parser.parse_args(argv)
    sizes = [tuple(int(v) for v in pair.split(":")) for pair in args.sizes.split(",")]
    warm_up()
    rows = []
    with threadpool_limits(1):
        for n, m in sizes:
            t, x, x_dot, system = lorenz96_records(n, m, args.seed)
            for family in args.families.split(","):
                noisy, _ = contaminate_family(x, family, np.random.default_rng([args.seed, n, m]))
                here, local_s = _fit(noisy, t, x_dot)
                workers = args.workers if args.scheduler == "local" else None
                with scheduler(args.scheduler, n_workers=workers):
                    small = lorenz96_records(6, 150, args.seed)
                    _fit(small[1], small[0], small[2])  # the kernels loaded on the workers
                    there, cluster_s = _fit(noisy, t, x_dot)
                truth = system.coef != 0
                row = {
                    "states": n, "samples": m, "family": family,
                    "threads_s": round(local_s, 2), "cluster_s": round(cluster_s, 2),
                    "ratio": round(cluster_s / local_s, 3),
                    "exact_threads": bool(np.array_equal(here.coef_.T != 0, truth)),
                    "exact_cluster": bool(np.array_equal(there.coef_.T != 0, truth)),
                    "identical": bool(np.array_equal(here.coef_, there.coef_)),
                }  # fmt: skip
                print(row, flush=True)
                rows.append(row)
    out = Path(args.out)
    write_rows(rows, out / "cluster.csv")
    command = "python validation/cluster.py " + " ".join(argv or sys.argv[1:])
    where = (
        f"a LocalCluster of {args.workers} single-threaded workers"
        if args.scheduler == "local"
        else f"the cluster at {args.scheduler}"
    )
    lines = [
        "# One fit's equations on a cluster",
        "",
        f"Command: `{command.strip()}`. `HuberSINDy()` on Lorenz-96 (exact derivatives), "
        f"on this machine's threads and on {where} (the row screen's pilot fits on the "
        "workers), one after the other in one process, BLAS on one thread.",
        "",
        "| states | samples | family | threads | cluster | cluster / threads "
        "| exact (threads, cluster) | identical |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['states']} | {r['samples']} | {r['family']} | {r['threads_s']:.1f} s "
            f"| {r['cluster_s']:.1f} s | {r['ratio']:.2f} | {r['exact_threads']}, "
            f"{r['exact_cluster']} | {r['identical']} |"
        )
    (out / "cluster.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
