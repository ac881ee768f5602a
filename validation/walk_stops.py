"""Where the λ path's walk may stop: every point walked, the stop rules simulated.

``record`` fits cases with the selection's walk forced through every point of every
column's path and records, per point, the selection stage's proposal: its number of
terms, its BIC under the first correlation time, the lower bound on the BIC of any fit
on that many terms (``selection.criteria._Walk``), the point's own number of terms, and
whether the proposal is the limit's support past the limit's size.  ``evaluate``
replays the stop rules on those records: the limit rule (``STABLE_POINTS``) alone and
with proposals out of reach for K consecutive points at G times the best candidate's
terms, and counts the walks *harmed* (a point after the stop proposes another support
scoring better than, or within ``MIN_BIC_MARGIN`` of, the best at the stop) and the
share of the walks' cost (the sum of the points' squared numbers of terms) skipped.

    python validation/walk_stops.py record --cases zoo,heldout --out zoo.pkl
    python validation/walk_stops.py record --sensors "DuffingForced glitches 3 0.05;Hopf clean 45 0.1" --out s.pkl
    python validation/walk_stops.py record --frontier 5 10 --out frontier.pkl
    python validation/walk_stops.py evaluate zoo.pkl s.pkl
"""  # noqa: E501

from __future__ import annotations

import argparse
import pickle
import sys
import warnings
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

sys.path.insert(0, str(Path(__file__).parent))


def _full_walks():
    """Make every ``_Walk`` of this process walk every point and record its proposals."""
    from robust_sindy.selection import criteria as cr

    if getattr(cr._Walk, "recorded", None) is not None:
        return cr
    cr._Walk.recorded = []
    init = cr._Walk.__init__

    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.points = {}
        cr._Walk.recorded.append(self.points)

    def until(self, i, coef, cols):
        stage = self.stage
        proposed = stage.side_by_side(lambda k: stage._column(k, coef[:, k]), cols)
        for k, c in zip(cols, proposed, strict=True):
            self.candidates[i, :, k] = c
            self.used[i, k] = True
            on = np.flatnonzero(c)
            loss = cr._candidate_loss(stage.theta, stage.y[:, k], c, stage.delta[k])
            self.losses[i, k] = loss
            args = (self.sigma[k], self.penalty[k], self.tau[k])
            limit = self.limit[:, k] != 0
            nnz = int(np.count_nonzero(coef[:, k]))
            settled = nnz > limit.sum() and np.array_equal(c != 0, limit)
            bound = cr.bic_from_loss(stage.whole_floor(k), on.size, *args)
            score = cr.bic_from_loss(loss, on.size, *args)
            self.points.setdefault(int(k), []).append(
                (i, on.size, score, bound, nnz, bool(settled), bool(self.bounded[k]))
            )
        return np.zeros(cols.size, dtype=bool)

    cr._Walk.__init__, cr._Walk.until = recording_init, until
    return cr


def _one(key, func, args):
    cr = _full_walks()
    cr._Walk.recorded.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            func(*args)
        except RuntimeError:  # a trajectory that could not be integrated: not a case
            return key, None
    return key, [dict(w) for w in cr._Walk.recorded]


def _sensor_fit(name, family, seed, noise):
    import sensors

    from robust_sindy import HuberSINDy, PolynomialLibrary

    s, t, _, u, _, noisy = sensors.make_record(name, family, "states", seed, 2000, noise)
    HuberSINDy(library=PolynomialLibrary(degree=s.degree)).fit(noisy, t, u=u)


def _frontier_fit(system, level):
    from robust_sindy import frontier

    t, x = frontier._noisy(system, level, 4, 2000)
    frontier._ours("auto", x, t)


def _cases(args) -> list:
    if args.cases:
        import snapshot

        names = args.cases.split(",")
        return [(key, f, a) for key, f, a in snapshot._cases(names, None) if key[0] != "paper"]
    if args.sensors:
        out = []
        for spec in args.sensors.split(";"):
            name, family, seed, noise = spec.split()
            out.append(((name, family, int(seed), float(noise)), _sensor_fit,
                        (name, family, int(seed), float(noise))))  # fmt: skip
        return out
    from robust_sindy.flows import polynomial_systems

    draw, count = args.frontier
    systems = polynomial_systems()
    pick = np.random.default_rng(draw).choice(len(systems), count, replace=False)
    levels = (0.01, 0.05, 0.1, 0.2)
    return [((systems[i].name, v), _frontier_fit, (systems[i], v)) for i in pick for v in levels]


def _simulate(points, reach_points, growth, use_reach=True):
    """The index of the point the walk stops at (None: it walks them all) and the best
    score walked by then."""
    from robust_sindy.selection.criteria import MIN_BIC_MARGIN, STABLE_POINTS

    best, best_size, run, reach = np.inf, 0, 0, 0
    for at, (_, size, score, bound, _, settled, bounded) in enumerate(points):
        if score < best:
            best, best_size = score, size
        out = (
            use_reach and bounded and size > best_size and size >= growth * best_size
            and bound > best + MIN_BIC_MARGIN
        )  # fmt: skip
        run = run + 1 if settled else 0
        reach = reach + 1 if out else 0
        if run >= STABLE_POINTS or reach >= reach_points:
            return at, best
    return None, best


def _evaluate(records, reach_points, growth, use_reach=True):
    from robust_sindy.selection.criteria import MIN_BIC_MARGIN

    walks, harmed, skipped, total = 0, set(), 0.0, 0.0
    for key, found in records:
        for w, walk in enumerate(found or []):
            for k, points in walk.items():
                walks += 1
                cost = np.array([p[4] ** 2 + 1.0 for p in points])
                total += cost.sum()
                stop, best = _simulate(points, reach_points, growth, use_reach)
                if stop is None:
                    continue
                skipped += cost[stop + 1 :].sum()
                tie = 1e-9 * max(1.0, abs(best))
                if any(abs(p[2] - best) > tie and p[2] <= best + MIN_BIC_MARGIN
                       for p in points[stop + 1 :]):  # fmt: skip
                    harmed.add((key, w, k))
    return walks, harmed, skipped / max(total, 1.0)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record")
    which = rec.add_mutually_exclusive_group(required=True)
    which.add_argument("--cases", help="snapshot cases: zoo,heldout")
    which.add_argument("--sensors", help='"SYSTEM FAMILY SEED NOISE;..." (validation/sensors.py)')
    which.add_argument("--frontier", type=int, nargs=2, metavar=("DRAW", "SYSTEMS"))
    rec.add_argument("--jobs", type=int, default=2)
    rec.add_argument("--out", required=True)
    ev = sub.add_parser("evaluate")
    ev.add_argument("files", nargs="+")
    args = parser.parse_args(argv)
    if args.command == "record":
        cases = _cases(args)
        out = Parallel(n_jobs=args.jobs)(delayed(_one)(key, f, a) for key, f, a in cases)
        with open(args.out, "wb") as fh:
            pickle.dump(out, fh)
        print(f"{len(out)} cases -> {args.out}")
        return
    records = []
    for name in args.files:
        with open(name, "rb") as fh:
            records += pickle.load(fh)
    walks, base, cost = _evaluate(records, sys.maxsize, 0.0, use_reach=False)
    print(f"{walks} walks; the limit rule alone: {len(base)} harmed, {100 * cost:.1f} % "
          "of the cost skipped")  # fmt: skip
    print("| points out of reach | growth | harmed beyond the limit rule's | cost skipped |")
    print("|---|---|---|---|")
    for points in (2, 3, 4):
        for growth in (1.0, 2.0):
            _, harmed, cost = _evaluate(records, points, growth)
            print(f"| {points} | {growth:g} | {len(harmed - base)} | {100 * cost:.1f} % |")


if __name__ == "__main__":
    main()
