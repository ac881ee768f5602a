"""Record what the automatic identification gives, case by case, and compare two records.

A change that should not alter behaviour (a restructuring, a faster stage) is checked by
recording every case before and after it and comparing: the same support, the same
warnings and the same coefficients within a relative tolerance.

Cases (``--cases``, comma-separated):

* ``zoo``: every case of the zoo (``robust-sindy zoo``: each polynomial flow, family and
  derivatives, seed 0), ``HuberSINDy()`` only;
* ``heldout``: the committed held-out check (``validation/heldout_zoo.py``: 16 systems of
  draw 2026, seed 3, its contamination parameters), ``HuberSINDy()`` only;
* ``paper``: the paper's reproduction (``robust-sindy reproduce``: Lorenz and drone, 20
  seeds), every method.

    python validation/snapshot.py record --cases zoo,heldout,paper --out before.pkl
    python validation/snapshot.py compare before.pkl after.pkl

``--derivatives states`` records only the zoo and held-out cases fitted from the states
(the ones a change to the weak form or to estimated derivatives can alter).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
import warnings

import numpy as np
from joblib import Parallel, delayed


def _huber_record(system, t, x, x_dot):
    import robust_sindy as rs

    model = rs.HuberSINDy(library=rs.PolynomialLibrary(degree=system.degree))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.fit(x, t, x_dot=x_dot)
    return {
        "coef": np.asarray(model.coef_),
        "warnings": sorted(f"{w.category.__name__}: {w.message}" for w in caught),
        "screened": np.asarray(model.screened_),
        "delta": np.asarray(model.delta_),
        "lam": np.asarray(model.lam_),
    }


def _zoo_case(system, family, derivatives, seed, contamination, pts_per_period=100):
    from robust_sindy import zoo

    rng = np.random.default_rng(
        [seed, zoo.FAMILIES.index(family), zoo.DERIVATIVES.index(derivatives)]
    )
    try:
        t, x, dx = zoo.simulate_system(system, 2000, seed, pts_per_period)
    except RuntimeError:
        return None
    noisy, _ = zoo.contaminate_family(x, family, rng, contamination)
    return _huber_record(system, t, noisy, dx if derivatives == "exact" else None)


def _paper_case(system, seed):
    from robust_sindy import reproduce

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = reproduce.run_seed(system, seed)
    # run_seed records the warnings of HuberSINDy() itself (where it does).
    inner = [f"{category}: {message}" for category, _, message in out.get("warnings", [])]
    return {
        "coef": {k: np.asarray(v["coef"]) for k, v in out["methods"].items()},
        "warnings": sorted([f"{w.category.__name__}: {w.message}" for w in caught] + inner),
    }


def _cases(names, derivatives=None):
    from robust_sindy import zoo

    kinds = zoo.DERIVATIVES if derivatives is None else derivatives

    out = []
    if "zoo" in names:
        for s in zoo.polynomial_systems():
            for f in zoo.FAMILIES:
                for d in kinds:
                    out.append(
                        (("zoo", s.name, f, d, 0), _zoo_case, (s, f, d, 0, zoo.ZOO_CONTAMINATION))
                    )
    if "heldout" in names:
        sys.path.insert(0, "validation")
        from heldout_zoo import HELDOUT

        systems = zoo.polynomial_systems()
        pick = np.random.default_rng(2026).choice(len(systems), 16, replace=False)
        for i in pick:
            for f in zoo.FAMILIES:
                for d in kinds:
                    key = ("heldout", systems[i].name, f, d, 3)
                    out.append((key, _zoo_case, (systems[i], f, d, 3, HELDOUT)))
    if "paper" in names:
        for system in ("lorenz", "drone"):
            for seed in range(20):
                out.append((("paper", system, seed), _paper_case, (system, seed)))
    return out


def record(names, path, jobs, derivatives=None):
    cases = _cases(names, derivatives)
    t0 = time.perf_counter()
    from tqdm import tqdm

    out = Parallel(n_jobs=jobs, return_as="generator")(delayed(f)(*a) for _, f, a in cases)
    results = list(tqdm(out, total=len(cases), desc="cases"))
    rec = {key: r for (key, _, _), r in zip(cases, results, strict=True) if r is not None}
    with open(path, "wb") as fh:
        pickle.dump(rec, fh)
    print(f"{len(rec)} cases recorded in {time.perf_counter() - t0:.0f} s -> {path}")


def _coef_diff(a, b):
    if isinstance(a, dict):
        return max(_coef_diff(a[k], b[k]) for k in a)
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return np.inf
    scale = max(np.abs(a).max(initial=0.0), np.abs(b).max(initial=0.0), np.finfo(float).tiny)
    return float(np.abs(a - b).max(initial=0.0) / scale)


def _support(a):
    if isinstance(a, dict):
        return {k: _support(v) for k, v in a.items()}
    return (np.asarray(a) != 0).tobytes()


def compare(before, after, rtol):
    with open(before, "rb") as fh:
        a = pickle.load(fh)
    with open(after, "rb") as fh:
        b = pickle.load(fh)
    keys = sorted(set(a) | set(b), key=str)
    bad = 0
    worst = 0.0
    for key in keys:
        if key not in a or key not in b:
            print("only in one record:", key)
            bad += 1
            continue
        ra, rb = a[key], b[key]
        diff = _coef_diff(ra["coef"], rb["coef"])
        worst = max(worst, diff)
        problems = []
        if _support(ra["coef"]) != _support(rb["coef"]):
            problems.append("support")
        if diff > rtol:
            problems.append(f"coef {diff:.1e}")
        if ra["warnings"] != rb["warnings"]:
            problems.append("warnings")
        for name in ("screened", "delta", "lam"):
            if name in ra and _coef_diff(ra[name], rb[name]) > rtol:
                problems.append(name)
        if problems:
            bad += 1
            print(key, ", ".join(problems))
    print(f"{len(keys)} cases, {bad} differ; largest relative coefficient difference {worst:.1e}")
    return bad


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("--cases", default="zoo,heldout,paper")
    rec.add_argument("--out", required=True)
    rec.add_argument("--jobs", type=int, default=2)
    rec.add_argument(
        "--derivatives", default=None,
        help="zoo and held-out cases with these derivatives only (comma-separated: "
        "exact, states); the paper's cases are always recorded when asked for",
    )  # fmt: skip
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("before")
    cmp_.add_argument("after")
    cmp_.add_argument("--rtol", type=float, default=1e-12)
    args = parser.parse_args(argv)
    if args.command == "record":
        kinds = None if args.derivatives is None else args.derivatives.split(",")
        record(args.cases.split(","), args.out, args.jobs, kinds)
    else:
        sys.exit(1 if compare(args.before, args.after, args.rtol) else 0)


if __name__ == "__main__":
    main()
