"""``robust-sindy fit DATA``: a table of measurements in, equations, a report and a model out.

The pieces are usable from Python too: :func:`read_table` (CSV, TSV, Parquet, NPZ),
:func:`parse_library` (``"poly:3"``, ``"poly:2+trig"``, expressions), and :func:`run`,
which fits, prints and writes ``model.json``, ``report.md`` and the figures.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .library import BaseLibrary, CustomLibrary, FourierLibrary, PolynomialLibrary
from .timeseries.temporal import fill_missing

__all__ = ["FitJob", "parse_library", "read_table", "run"]

#: Ways ``--derivatives`` may name a differentiation method.
DIFFERENTIATION = ("robust", "finite_difference", "savgol")
#: Column names taken as time when neither ``--time`` nor ``--dt`` is given.
TIME_NAMES = ("t", "time")


class InputError(ValueError):
    """Bad data or arguments; the command prints the message as one line."""


def read_table(path):
    """A pandas DataFrame from a CSV/TSV/text, Parquet or NPZ file.

    NPZ: every array of one dimension is a column; a 2-D array ``a`` of ``k`` columns
    gives ``a0, ..., a{k-1}``; all must have the same length.
    """
    import pandas as pd

    path = Path(path)
    if not path.exists():
        raise InputError(f"DATA: no such file: {str(path)!r}")
    if path.is_dir():
        raise InputError(f"DATA: {str(path)!r} is a folder, not a data file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".parquet":
            try:
                return pd.read_parquet(path)
            except ImportError:
                raise InputError(
                    'DATA: reading Parquet needs pyarrow: pip install "robust_sindy[parquet]"'
                ) from None
        if suffix == ".npz":
            return _npz_frame(path)
        sep = "\t" if suffix == ".tsv" else None
        frame = pd.read_csv(path, sep=sep, engine="python", comment="#")
    except InputError:
        raise
    except Exception as exc:  # a parser's message, on one line
        text = " ".join(str(exc).split())
        raise InputError(f"DATA: cannot read {str(path)!r}: {text}") from None
    if frame.shape[1] < 1 or frame.shape[0] < 1:
        raise InputError(f"DATA: {str(path)!r} has no data rows")
    frame.columns = [str(c).strip() for c in frame.columns]
    return frame


def _npz_frame(path):
    import pandas as pd

    with np.load(path, allow_pickle=False) as npz:
        cols = {}
        for key in npz.files:
            a = npz[key]
            if a.ndim == 1:
                cols[key] = a
            elif a.ndim == 2:
                cols.update({f"{key}{j}": a[:, j] for j in range(a.shape[1])})
            else:
                raise InputError(f"DATA: array {key!r} in {str(path)!r} has {a.ndim} dimensions")
    lengths = {k: len(v) for k, v in cols.items()}
    if len(set(lengths.values())) > 1:
        raise InputError(f"DATA: the arrays of {str(path)!r} differ in length: {lengths}")
    return pd.DataFrame(cols)


def parse_library(spec: str, terms=()) -> BaseLibrary:
    """A library from a ``+``-separated spec and extra expression terms.

    Parts: ``poly`` or ``poly:D`` (monomials up to degree ``D``, default 2; constant
    included), ``trig`` or ``trig:N`` (``sin(k x)``, ``cos(k x)``, ``k = 1..N``, of every
    input).  ``terms`` are expressions of the inputs by name (``"sin(x) * y"``; see
    :class:`~robust_sindy.library.CustomLibrary`).  Examples: ``"poly:3"``,
    ``"poly:2+trig"``, ``"poly:1"`` with ``terms=["x*y"]``.
    """
    parts: list[BaseLibrary] = []
    for raw in str(spec).split("+") if str(spec).strip() else []:
        name, _, arg = raw.strip().partition(":")
        name = name.strip().lower()
        if name in ("poly", "polynomial"):
            parts.append(PolynomialLibrary(degree=_int_arg(arg, 2, raw, 0)))
        elif name in ("trig", "fourier"):
            parts.append(FourierLibrary(n_frequencies=_int_arg(arg, 1, raw, 1)))
        else:
            raise InputError(
                f"--library: unknown part {raw.strip()!r}; use poly[:DEGREE] and "
                "trig[:FREQUENCIES] joined by '+', e.g. poly:2+trig (and --terms for "
                "expressions)"
            )
    if terms:
        parts.append(CustomLibrary([str(e) for e in terms]))
    if not parts:
        raise InputError("--library: empty; e.g. poly:2")
    out = parts[0]
    for lib in parts[1:]:
        out = out + lib
    return out


def _int_arg(arg: str, default: int, raw: str, low: int) -> int:
    if not arg.strip():
        return default
    try:
        value = int(arg)
    except ValueError:
        value = None
    if value is None or value < low:
        raise InputError(f"--library: {raw.strip()!r} needs an integer >= {low} after ':'")
    return value


def _names(text: str | None, what: str) -> list[str] | None:
    if text is None:
        return None
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise InputError(f"{what}: give column names separated by commas")
    return names


def _number(text, what: str):
    if text is None or str(text).strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise InputError(f"{what}: expected 'auto' or a finite number >= 0; got {text!r}")
    return value


@dataclass
class FitJob:
    """The columns and choices of one ``fit`` run, checked against the table."""

    t: np.ndarray
    time_label: str
    states: list[str]
    controls: list[str]
    derivatives: list[str] | None
    differentiation: str
    x: np.ndarray
    u: np.ndarray | None
    x_dot: np.ndarray | None

    @classmethod
    def from_table(
        cls,
        frame,
        *,
        time=None,
        dt=None,
        states=None,
        controls=None,
        derivatives=None,
    ):
        columns = list(frame.columns)

        def need(names, what):
            missing = [c for c in names if c not in columns]
            if missing:
                raise InputError(
                    f"{what}: no column {', '.join(map(repr, missing))} in the data; its "
                    f"columns are {columns}"
                )
            return names

        def numeric(name, what, missing_ok=True):
            values = frame[name]
            try:
                arr = np.asarray(values, dtype=float)
            except (TypeError, ValueError):
                raise InputError(
                    f"{what}: column {name!r} is not numeric (first values {list(values.iloc[:3])})"
                ) from None
            # An empty cell (NaN) is a missing reading, which the fit handles and reports
            # (robust_sindy.timeseries.missing); inf is not a reading, nor is a missing time.
            bad = np.flatnonzero(np.isinf(arr) if missing_ok else ~np.isfinite(arr))
            if bad.size:
                rows = ", ".join(str(i + 2) for i in bad[:5])  # file lines: header is 1
                kind = "infinite" if missing_ok else "missing or non-finite"
                raise InputError(
                    f"{what}: column {name!r} has {bad.size} {kind} values "
                    f"(file lines {rows}{', ...' if bad.size > 5 else ''})"
                    + ("" if missing_ok else "; every sample needs its time")
                )
            return arr

        if time is not None and dt is not None:
            raise InputError("--time and --dt: give one of them")
        if time is not None:
            need([time], "--time")
        elif dt is None:
            found = [c for c in columns if c.lower() in TIME_NAMES]
            if not found:
                raise InputError(f"no time: give --time COLUMN or --dt STEP (columns: {columns})")
            time = found[0]
        derivative_cols = None
        method = "robust"
        if derivatives is not None:
            if derivatives in DIFFERENTIATION:
                method = derivatives
            else:
                derivative_cols = need(_names(derivatives, "--derivatives"), "--derivatives")
        controls = need(_names(controls, "--controls") or [], "--controls")
        if states is not None:
            states = need(_names(states, "--states"), "--states")
        else:
            taken = {time, *controls, *(derivative_cols or [])}
            states = []
            for c in columns:
                if c in taken:
                    continue
                try:
                    np.asarray(frame[c], dtype=float)
                except (TypeError, ValueError):
                    continue  # non-numeric columns are not states unless named
                states.append(c)
            if not states:
                raise InputError(f"no state columns left (columns: {columns}); give --states")
        dup = sorted({c for c in states + controls if (states + controls).count(c) > 1})
        if time in states + controls or dup:
            raise InputError(
                f"a column is used twice: {dup or [time]} (time, states and controls differ)"
            )
        if derivative_cols is not None and len(derivative_cols) != len(states):
            raise InputError(
                f"--derivatives: {len(derivative_cols)} columns for {len(states)} states "
                f"{states}: give one derivative column per state, in order"
            )
        if dt is not None:
            if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
                raise InputError(f"--dt: expected a finite number > 0; got {dt!r}")
            t, label = dt * np.arange(len(frame)), f"sample x {dt:g}"
        else:
            t, label = numeric(time, "--time", missing_ok=False), time
            if np.any(np.diff(t) <= 0):
                i = int(np.flatnonzero(np.diff(t) <= 0)[0])
                raise InputError(
                    f"--time: column {time!r} must increase strictly; it does not at file "
                    f"line {i + 3} ({t[i]:g} then {t[i + 1]:g})"
                )
        x = np.column_stack([numeric(c, "states") for c in states])
        u = np.column_stack([numeric(c, "--controls") for c in controls]) if controls else None
        x_dot = (
            None
            if derivative_cols is None
            else np.column_stack([numeric(c, "--derivatives") for c in derivative_cols])
        )
        return cls(t, label, states, controls, derivative_cols, method, x, u, x_dot)


def run(
    data,
    *,
    out="fit_results",
    time=None,
    dt=None,
    states=None,
    controls=None,
    library="poly:2",
    terms=(),
    derivatives=None,
    delta="auto",
    lam="auto",
    formulation="auto",
    constraints=None,
    progress=True,
    echo=print,
) -> list[Path]:
    """Fit ``HuberSINDy`` to the table ``data``; print and write the results to ``out``.

    Writes ``model.json`` (:meth:`~robust_sindy.HuberSINDy.save`), ``report.md``,
    ``data.png`` (each state against the model's simulation from the first sample,
    samples the screen left out marked) and ``coefficients.png``.  Raises
    :class:`InputError` for bad data or arguments.  Returns the written paths.
    """
    from .estimator import HuberSINDy

    frame = read_table(data)
    job = FitJob.from_table(
        frame, time=time, dt=dt, states=states, controls=controls, derivatives=derivatives
    )
    lib = parse_library(library, terms)
    delta, lam = _number(delta, "--delta"), _number(lam, "--lam")
    out = Path(out)
    model = HuberSINDy(
        library=lib,
        delta=delta,
        lam=lam,
        differentiation=job.differentiation,
        progress=progress,
        formulation=formulation,
        constraints=constraints,
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model.fit(
                job.x, job.t, x_dot=job.x_dot, u=job.u, feature_names=job.states + job.controls
            )
        except ValueError as exc:
            raise InputError(" ".join(str(exc).split())) from None
    messages = list(dict.fromkeys(str(w.message) for w in caught))
    out.mkdir(parents=True, exist_ok=True)
    lines = _summary(model, job, Path(data).name, messages)
    echo("\n".join(lines))
    paths = [model.save(out / "model.json")]
    with warnings.catch_warnings(record=True) as sim_caught:
        warnings.simplefilter("always")
        sim = _simulate(model, job)
    sim_note = [str(w.message) for w in sim_caught]
    paths += _figures(model, job, sim, out)
    report = out / "report.md"
    report.write_text(_report(lines, job, sim_note, paths, data))
    paths.insert(1, report)
    echo("wrote " + ", ".join(str(p) for p in paths))
    return paths


def _summary(model, job, source: str, messages) -> list[str]:
    d = model.diagnostics_
    lines = [
        f"{source}: {len(job.t)} samples; states {job.states}"
        + (f"; controls {job.controls}" if job.controls else "")
        + f"; time {job.time_label!r}"
        + (
            f"; derivatives from columns {job.derivatives}"
            if job.derivatives
            else "; no derivatives (the weak form)"
            if d.formulation == "weak"
            else f"; derivatives by differentiation={job.differentiation!r}"
        ),
        f"library: {len(model.get_feature_names())} terms",
        "",
        "Identified equations:",
    ]
    lines += [f"  ({name})' = {eq}" for name, eq in zip(job.states, model.equations(), strict=True)]
    lines += [
        "",
        "delta: " + ", ".join(f"{v:.3g}" for v in np.ravel(model.delta_)),
        (
            "lam (on standardised columns, chosen): "
            + ", ".join(f"{v:.3g}" for v in model.selection_.lam)
            if model.selection_ is not None
            else "lam: " + ", ".join(f"{v:.3g}" for v in np.ravel(model.lam_))
        ),
        "",
        repr(d),
    ]
    names = model.get_feature_names()
    for label, mask in (
        ("dropped as errors-in-variables bias", model.bias_dropped_),
        ("dropped as derivative truncation bias", np.isfinite(model.truncation_ratio_)),
        ("left out below the noise floor", np.isfinite(model.below_floor_)),
        (f"dropped, robust t below {d.significance_level:g}", np.isfinite(model.pruned_)),
        (f"selected, robust t below {d.significance_level:g}", d.weak),
    ):
        for state, row in zip(job.states, mask, strict=True):
            if row.any():
                terms = ", ".join(repr(names[j]) for j in np.flatnonzero(row))
                lines.append(f"  ({state})': {label}: {terms}")
    others = [m for m in messages if m not in d.problems()]
    if others:
        lines += ["", "Other warnings:"] + [f"  - {m}" for m in others]
    return lines


def _simulate(model, job):
    """The model integrated from the first sample over the data's times (may stop early)."""
    start = job.x[0]
    if np.isnan(start).any():  # a missing first reading: the fit's fill of it
        start = model.temporal_.repaired[0]
    u = job.u
    if u is not None and np.isnan(u).any():  # filled as the fit filled them
        u = fill_missing(u, job.t).repaired
    try:
        sim = model.simulate(start, job.t, u=u)
    except Exception as exc:  # an unstable model is a finding, not a crash
        warnings.warn(f"the simulation failed: {exc}", UserWarning, stacklevel=2)
        return np.full((0, job.x.shape[1]), np.nan)
    return sim


def _figures(model, job, sim, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(job.states)
    flagged = model.screened_
    temporal = model.temporal_.flags if model.temporal_ is not None else np.zeros_like(job.x, bool)
    fig, axes = plt.subplots(n, 1, figsize=(7, 1.8 + 1.6 * n), sharex=True, squeeze=False)
    for i, ax in enumerate(axes[:, 0]):
        ax.plot(job.t, job.x[:, i], "o-", ms=3, lw=0.8, color="0.35", label="data")
        if len(sim):
            ax.plot(job.t[: len(sim)], sim[:, i], "-", color="C0", lw=1.6, label="model")
        lost = np.isnan(job.x[:, i])
        if lost.any():
            ax.plot(
                job.t[lost], model.temporal_.repaired[lost, i], "o", mfc="none", color="C2",
                ms=5, label="missing, filled",
            )  # fmt: skip
        mark = (flagged | temporal[:, i]) & ~lost
        if mark.any():
            ax.plot(
                job.t[mark], job.x[mark, i], "x", color="C3", ms=7, mew=2,
                label="left out by the screen",
            )  # fmt: skip
        ax.set_ylabel(job.states[i])
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel(job.time_label)
    fig.suptitle("data and the identified model, simulated from the first sample")
    fig.tight_layout()
    p1 = out / "data.png"
    fig.savefig(p1, dpi=120)
    plt.close(fig)

    names = model.get_feature_names()
    coef = model.coef_
    used = np.flatnonzero(np.any(coef != 0, axis=0))
    used = used if used.size else np.arange(len(names))
    # Colour: each term's share of its equation (coefficient times the term's RMS on the
    # data, over the largest in the row), so the picture does not depend on units.
    z = job.x if job.u is None else np.hstack([job.x, job.u])
    z = z[~np.isnan(z).any(axis=1)]  # the samples with every reading
    rms = np.sqrt(np.mean(model.library_.transform(z)[:, used] ** 2, axis=0))
    contrib = coef[:, used] * rms
    top = np.abs(contrib).max(axis=1, keepdims=True)
    share = contrib / np.where(top > 0, top, 1.0)
    fig, ax = plt.subplots(figsize=(2.0 + 1.0 * len(used), 1.4 + 0.6 * n))
    img = ax.imshow(share, cmap="RdBu_r", vmin=-1, vmax=1, aspect="auto")
    for (i, j), v in np.ndenumerate(coef[:, used]):
        if v != 0:
            colour = "white" if abs(share[i, j]) > 0.6 else "black"
            ax.text(j, i, f"{v:.3g}", ha="center", va="center", fontsize=9, color=colour)
    ax.set_xticks(range(len(used)), [names[j] for j in used], rotation=45, ha="right")
    ax.set_yticks(range(n), [f"({s})'" for s in job.states])
    ax.set_title("coefficients; colour: the term's size on the data relative to the largest")
    fig.colorbar(img, ax=ax, fraction=0.04)
    fig.tight_layout()
    p2 = out / "coefficients.png"
    fig.savefig(p2, dpi=120)
    plt.close(fig)
    return [p1, p2]


def _report(lines, job, sim_note, paths, data) -> str:
    text = [
        "# robust-sindy fit",
        "",
        f"Data: `{data}`.",
        "",
        "```",
        *lines,
        "```",
        "",
    ]
    if sim_note:
        text += ["Simulation: " + " ".join(sim_note), ""]
    text += [f"![{p.stem}]({p.name})" for p in paths if p.suffix == ".png"]
    text += ["", "The model file `model.json` loads with `robust_sindy.load_model`.", ""]
    return "\n".join(text)
