"""The robust derivatives' half window on one sensor record: how wrong the derivatives
are, how much of that the library can explain, and what the fit makes of it.

For one record of ``validation/sensors.py`` (a system, a family, a seed, a noise level
and a number of samples, states only) and each half window given, the robust
derivatives of the screened states (``local_polynomial_derivative`` with the temporal
screen's flags and noise levels, the same window for every state) are compared with the
true derivatives:

* ``error``: the root mean square error, relative to that of the true derivatives;
* ``in span``: the part of that error in the span of the library of the measured
  states (what a regression on the library can take for signal);
* ``bias in span``: the same windows on the noise-free states, in the span;
* ``tau true`` and ``tau dense``: the correlation time
  (``robust_sindy.selection.correlation_time``, median over the equations) of the
  residuals of the true model, and of the least-squares fit on every column (the
  densest model, from which the information criterion takes its correlation time).

With ``--fit`` it also fits ``HuberSINDy()`` (strong form) with every state's half
window imposed (the automatic choice replaced, nothing else), and with the automatic
windows, and reports the true terms lost and the terms added.  A study of one stage,
not a benchmark:

    python validation/derivative_windows.py --system Lorenz96_30 --family jitter \\
        --seed 5 --noise 0.02 --windows 2,4,8,12 [--fit]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import sensors

from robust_sindy import HuberSINDy, PolynomialLibrary
from robust_sindy.selection import correlation_time
from robust_sindy.timeseries import derivatives as derivative_stage
from robust_sindy.timeseries.differentiation import local_polynomial_derivative
from robust_sindy.timeseries.temporal import temporal_screen


def derivative_table(s, t, x, u, dx, noisy, windows) -> list[dict]:
    """Per half window: the derivatives' error, its part in the library's span, the
    bias in the span, and the correlation times of the true and the densest model."""
    screen = temporal_screen(noisy, t)
    usable = ~screen.flags & np.isfinite(noisy)
    states = screen.repaired
    # The system's own library: its columns in the order of its coefficients.
    lib = s.library(states if u is None else np.hstack([states, np.reshape(u, (len(t), -1))]))
    basis = np.linalg.svd(lib / np.linalg.norm(lib, axis=0), full_matrices=False)[0]
    norm = np.linalg.norm(dx)
    rows = []
    for h in windows:
        half = np.full(x.shape[1], h)
        d = local_polynomial_derivative(states, t, half, mask=usable, scale=screen.scale)
        err = d - dx
        bias = local_polynomial_derivative(x, t, half) - dx
        dense = d - lib @ np.linalg.lstsq(lib, d, rcond=None)[0]
        rows.append(
            dict(
                window=h,
                error=np.linalg.norm(err) / norm,
                in_span=np.linalg.norm(basis.T @ err) / norm,
                bias_in_span=np.linalg.norm(basis.T @ bias) / norm,
                tau_true=float(np.median(correlation_time(d - lib @ s.coef))),
                tau_dense=float(np.median(correlation_time(dense))),
            )
        )
    return rows


def fit_with_window(s, t, noisy, u, half) -> dict:
    """``HuberSINDy()`` (strong form) with every state's half window ``half`` (None:
    the automatic choice): true terms lost, terms added, relative error, seconds."""
    chosen = derivative_stage.choose_half_window
    if half is not None:
        derivative_stage.choose_half_window = lambda x, *a, **k: np.full(x.shape[1], half)
    try:
        model = HuberSINDy(library=PolynomialLibrary(degree=s.degree), formulation="strong")
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(noisy, t, u=u)
        seconds = time.perf_counter() - start
    finally:
        derivative_stage.choose_half_window = chosen
    coef = model.coef_.T
    return dict(
        window="auto " + str(sorted(set(model.derivative_windows_.tolist())))
        if half is None
        else half,
        lost=int(((s.coef != 0) & (coef == 0)).sum()),
        added=int(((s.coef == 0) & (coef != 0)).sum()),
        error_rel=float(np.linalg.norm(coef - s.coef) / np.linalg.norm(s.coef)),
        seconds=seconds,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="Lorenz96_30", help="as in sensors.py --systems")
    ap.add_argument("--family", default="jitter", help="a family of sensors.py")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--noise", type=float, default=0.02, help="relative to each state's spread")
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--windows", default="2,4,8,12", help="comma-separated half windows")
    ap.add_argument("--fit", action="store_true", help="also fit with each window imposed")
    args = ap.parse_args(argv)
    if args.family not in sensors.FAMILIES:
        ap.error(f"--family must be one of {sensors.FAMILIES}; got {args.family!r}")
    try:
        windows = [int(w) for w in args.windows.split(",")]
    except ValueError:
        ap.error(f"--windows must be comma-separated integers; got {args.windows!r}")
    if min(windows) < 1:
        ap.error(f"--windows must be >= 1; got {args.windows!r}")
    s, t, x, u, dx, noisy = sensors.make_record(
        args.system, args.family, "states", args.seed, args.samples, args.noise
    )
    print(
        f"{args.system}, {args.family}, seed {args.seed}, noise {args.noise:g}, "
        f"{args.samples} samples, {s.coef.shape[0]} terms"
    )
    print("| half window | error | in span | bias in span | tau true | tau dense |")
    print("|---|---|---|---|---|---|")
    for r in derivative_table(s, t, x, u, dx, noisy, windows):
        print(
            f"| {r['window']} | {r['error']:.3f} | {r['in_span']:.3f} | "
            f"{r['bias_in_span']:.3f} | {r['tau_true']:.1f} | {r['tau_dense']:.1f} |"
        )
    if args.fit:
        print("\n| half window | true terms lost | terms added | relative error | seconds |")
        print("|---|---|---|---|---|")
        for h in [*windows, None]:
            r = fit_with_window(s, t, noisy, u, h)
            print(
                f"| {r['window']} | {r['lost']} | {r['added']} | {r['error_rel']:.3g} | "
                f"{r['seconds']:.0f} |"
            )


if __name__ == "__main__":
    main()
