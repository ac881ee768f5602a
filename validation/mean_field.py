"""Energy-preserving fits of mean-field models beside the cylinder wake's record.

The mean-field model of a wake's oscillating modes and shift mode (Noack et al. 2003),

    x0' = mu x0 - w x1 - a x0 x2,  x1' = w x0 + mu x1 - a x1 x2,
    x2' = -g x2 + a (x0^2 + x1^2),

has a limit cycle of radius sqrt(mu g) / a at the shift level mu / a, and its quadratic
part conserves energy.  For three parameter sets other than the tests' one (``--models``
picks some by index), a record of ``--samples`` (3000) samples over ``--span`` growth
times (``span / mu``) from (0.01, 0, 0) is fitted from the states alone by
``HuberSINDy()`` and ``HuberSINDy(constraints="energy_preserving")``, in the wake's
cases (:mod:`cylinder_wake`): exact states; 3 % of the entries moved by 5 of their
channel's standard deviations; Gaussian noise of 2 % of each channel's standard
deviation (seeds 0 and 1 for the last two).  Each model is
simulated from the exact first state; the radius and level are averaged over the last
fifth of the record.  The longer the span, the larger the share of the record on the
limit cycle, where ``x2`` is constant and growth and saturation are one direction, and
(at a fixed number of samples) the fewer samples per period of the oscillation.

    python validation/mean_field.py [--span 20] [--seeds 2] [--samples 3000] [--models 0,1,2]
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
from cylinder_wake import contaminate
from scipy.integrate import solve_ivp

import robust_sindy as rs

HERE = Path(__file__).parent
#: (mu, w, a, g) of the models fitted.
MODELS = ((0.05, 1.0, 1.0, 0.5), (0.2, 2.0, 0.5, 1.0), (0.1, 0.7, 2.0, 0.3))
VARIANTS = {"unconstrained": None, "energy preserving": "energy_preserving"}
#: Samples per record unless ``--samples`` says otherwise.
SAMPLES = 3000


def record(params, span: float, samples: int = SAMPLES):
    mu, w, a, g = params

    def rhs(_, v):
        return [
            mu * v[0] - w * v[1] - a * v[0] * v[2],
            w * v[0] + mu * v[1] - a * v[1] * v[2],
            -g * v[2] + a * (v[0] ** 2 + v[1] ** 2),
        ]

    t = np.linspace(0.0, span / mu, samples)
    sol = solve_ivp(rhs, (0.0, t[-1]), [0.01, 0.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-12)
    return t, sol.y.T


def one(params, span, case, seed, variant, samples: int = SAMPLES) -> dict:
    mu, _w, a, g = params
    t, exact = record(params, span, samples)
    x = contaminate(exact, case, seed)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = rs.HuberSINDy(constraints=VARIANTS[variant]).fit(x, t)
    seconds = time.perf_counter() - t0
    bound = 10.0 * np.abs(exact).max()

    def blowup(_t, v):
        return bound - np.abs(v).max()

    blowup.terminal = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = model.simulate(exact[0], t, events=blowup)
    bounded = len(sim) == len(t) and bool(np.isfinite(sim).all())
    radius = level = np.nan
    if bounded:
        tail = t >= 0.8 * t[-1]
        radius = float(np.hypot(sim[tail, 0], sim[tail, 1]).mean() / (np.sqrt(mu * g) / a))
        level = float(sim[tail, 2].mean() / (mu / a))
    within = bounded and abs(radius - 1) < 0.05 and abs(level - 1) < 0.05
    return {
        "params": params, "case": case, "seed": seed, "variant": variant,
        "bounded": bounded, "radius": radius, "level": level, "within": within,
        "terms": int(np.count_nonzero(model.coef_)), "warnings": len(caught),
        "seconds": seconds,
    }  # fmt: skip


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--span", type=float, default=20.0, help="growth times (1 / mu)")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--samples", type=int, default=SAMPLES, help="samples per record")
    parser.add_argument(
        "--models", default=None, help="comma-separated indices into MODELS (default: all)"
    )
    parser.add_argument("--out", default=str(HERE / "results" / "mean_field"))
    args = parser.parse_args(argv)
    if args.samples < 100:
        parser.error(f"--samples must be at least 100; got {args.samples}")
    models = MODELS
    if args.models is not None:
        try:
            picked = [int(i) for i in args.models.split(",")]
        except ValueError:
            picked = []
        if not picked or not all(0 <= i < len(MODELS) for i in picked):
            parser.error(
                f"--models takes indices from 0 to {len(MODELS) - 1} separated by commas; "
                f"got {args.models!r}"
            )
        models = tuple(MODELS[i] for i in picked)
    cases = [("clean", 0)] + [(c, s) for c in ("glitches", "noise") for s in range(args.seeds)]
    rows = []
    for params in models:
        for case, seed in cases:
            for variant in VARIANTS:
                rows.append(one(params, args.span, case, seed, variant, args.samples))
                r = rows[-1]
                print(
                    f"{params} {case} {seed} {variant}: within {r['within']} "
                    f"radius {r['radius']:.3f} level {r['level']:.3f} terms {r['terms']} "
                    f"warnings {r['warnings']} {r['seconds']:.1f} s",
                    flush=True,
                )
    options = "".join(
        f" {flag} {value}"
        for flag, value, default in (
            ("--samples", args.samples, SAMPLES), ("--models", args.models, None)
        )
        if value != default
    )  # fmt: skip
    lines = [
        f"<!-- written by `python validation/mean_field.py --span {args.span:g} "
        f"--seeds {args.seeds}{options}` -->",
        "",
        f"Records of {args.span:g} growth times, {args.samples} samples; radius and level "
        "over the truth's (last fifth of the record); samples per period of the "
        "oscillation (`2 pi / w` over the step).",
        "",
        "| mu, w, a, g | samples per period | model | within 5 % | bounded | radius | level "
        "| terms | warnings | time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for params in models:
        mu, w = params[0], params[1]
        per_period = 2 * np.pi / w / (args.span / mu / (args.samples - 1))
        for variant in VARIANTS:
            sel = [r for r in rows if r["params"] == params and r["variant"] == variant]
            radius = [r["radius"] for r in sel if r["bounded"]]
            level = [r["level"] for r in sel if r["bounded"]]
            lines.append(
                f"| {', '.join(f'{v:g}' for v in params)} | {per_period:.0f} | {variant} | "
                f"{sum(r['within'] for r in sel)}/{len(sel)} | "
                f"{sum(r['bounded'] for r in sel)}/{len(sel)} | "
                f"{min(radius, default=np.nan):.3f} to {max(radius, default=np.nan):.3f} | "
                f"{min(level, default=np.nan):.3f} to {max(level, default=np.nan):.3f} | "
                f"{min(r['terms'] for r in sel)} to {max(r['terms'] for r in sel)} | "
                f"{min(r['warnings'] for r in sel)} to {max(r['warnings'] for r in sel)} | "
                f"{min(r['seconds'] for r in sel):.1f} to {max(r['seconds'] for r in sel):.1f} s |"
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = "\n".join(lines) + "\n"
    name = f"span_{args.span:g}" + ("" if args.samples == SAMPLES else f"_{args.samples}")
    (out / f"{name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
