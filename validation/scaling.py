"""Whole identifications on many states: Lorenz-96 with 10 to 100 states.

Times ``HuberSINDy()`` (its defaults, degree-2 monomials) and PySINDy's STLSQ (its
default threshold 0.1) on the same Lorenz-96 records with exact derivatives, clean (the
zoo's base noise) and with 20 % of the samples hit by Gaussian noise of 0.2 standard
deviations (the zoo's ``rows`` family), side by side in one process on one BLAS
thread (:func:`robust_sindy.zoo.run_scaling`); reports time, the ratio of the times,
whether each found exactly the true support and, with ``--memory``, the peak memory of
``HuberSINDy()`` over the library's own size (a second, traced run).

    python validation/scaling.py [--sizes 10:4000,20:4000,40:12000,100:12000:0.1]
                                 [--families clean,rows]
                                 [--derivatives exact|states] [--noise 0.03]
                                 [--memory] [--out validation/results/scaling]

A size is states:samples (sampling step 0.01, the zoo's) or states:samples:step.
With ``--derivatives states`` both methods get the states alone (``--noise``: Gaussian
noise of that share of each state's spread on every reading).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

from robust_sindy import zoo
from robust_sindy.flows import write_rows


def _size(text: str, parser) -> tuple:
    """``states:samples`` or ``states:samples:step`` as a tuple."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        size = (int(parts[0]), int(parts[1]), *(float(v) for v in parts[2:]))
    except ValueError:
        parser.error(f"--sizes: expected states:samples[:step]; got {text!r}")
    return size


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="10:4000,20:4000,40:12000",
                        help="states:samples or states:samples:step, comma-separated")  # fmt: skip
    parser.add_argument("--families", default="clean,rows")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--derivatives", default="exact", choices=("exact", "states"))
    parser.add_argument(
        "--noise", type=float, default=0.0,
        help="Gaussian noise on every reading, a share of each state's spread",
    )  # fmt: skip
    parser.add_argument("--memory", action="store_true", help="also the peak memory")
    parser.add_argument("--out", default="validation/results/scaling")
    args = parser.parse_args(argv)
    sizes = [_size(text, parser) for text in args.sizes.split(",")]
    if not (args.noise >= 0 and args.noise < float("inf")):
        parser.error(f"--noise: expected a finite number >= 0; got {args.noise!r}")
    rows = zoo.run_scaling(sizes, families=args.families.split(","), seed=args.seed,
                           memory=args.memory, derivatives=args.derivatives,
                           noise=args.noise)  # fmt: skip
    out = Path(args.out)
    write_rows([asdict(r) for r in rows], out / "scaling.csv")
    command = "python validation/scaling.py " + " ".join(argv or sys.argv[1:])
    given = (
        "Exact derivatives"
        if args.derivatives == "exact"
        else "From the states alone (no derivatives given)"
    )
    if args.noise:
        given += f", Gaussian noise of {100 * args.noise:g} % of each state's spread"
    title = "" if args.derivatives == "exact" else " from the states"
    text = (
        f"# Many states: Lorenz-96, whole identifications{title}\n\n"
        f"Command: `{command.strip()}`. {given}, degree-2 monomials, one BLAS "
        "thread, both methods on the same record in one process; ratio: HuberSINDy() time "
        "over PySINDy STLSQ time.\n\n" + zoo.scaling_table(rows) + "\n"
    )
    (out / "scaling.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
