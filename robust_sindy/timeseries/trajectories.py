"""Trajectories: the user's records as the pipeline sees them.

:meth:`Trajectories.from_user` is the one parser of what :meth:`HuberSINDy.fit
<robust_sindy.HuberSINDy.fit>` (and the ensembles) accept: one trajectory or a list of
them, arrays or pandas DataFrames, states ``x`` with optional sample times ``t``,
measured derivatives ``x_dot`` and controls ``u``, in memory or as Dask arrays.  It
checks every shape against the states and names the argument at fault; the stacked
samples of all trajectories keep their order, and :attr:`Trajectories.segments` says
where each trajectory lies among them (derivatives, local scales and correlation times
never reach across two trajectories).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..core.validation import as_float_array, check_time

__all__ = [
    "GAP_STEPS",
    "MIN_READINGS",
    "Trajectories",
    "gapless_pieces",
    "input_names",
    "is_dask",
    "is_frame",
    "is_series",
    "reading_steps",
    "runs",
    "segments_of",
    "slices",
]


def is_dask(a) -> bool:
    """Whether ``a`` is a Dask array (without importing Dask)."""
    return type(a).__module__.startswith("dask.") and hasattr(a, "chunks")


def is_series(obj) -> bool:
    return hasattr(obj, "to_numpy") and hasattr(obj, "index") and not hasattr(obj, "columns")


def is_frame(obj) -> bool:
    return hasattr(obj, "columns") and hasattr(obj, "to_numpy") and hasattr(obj, "index")


def input_names(names, n: int, q: int) -> list[str]:
    """Names of ``n`` states then ``q`` controls: ``names`` checked, or ``x0.., u0..``."""
    if names is None:
        return [f"x{i}" for i in range(n)] + [f"u{i}" for i in range(q)]
    names = [str(s) for s in names]
    if len(names) != n + q:
        raise ValueError(
            f"feature_names has {len(names)} names but there are {n} states "
            f"and {q} controls: give one name per state, then per control"
        )
    return names


def slices(lengths) -> list[slice]:
    """Consecutive slices of the given lengths."""
    edges = np.cumsum([0, *lengths])
    return [slice(a, b) for a, b in itertools.pairwise(edges)]


#: An interval between consecutive samples longer than this many median steps is a gap
#: in the record: longer than the temporal screen's window (2 x 4 + 1 samples), so that
#: no local fit has readings inside it.  (Uniformly random times have intervals this
#: long about once in 500.)
GAP_STEPS = 9.0


def runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of True in the 1-D ``mask``: their first indices and the indices just
    past them (``mask[first:stop]`` is each run)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]])))
    return edges[::2], edges[1::2]


def reading_steps(t: np.ndarray, lost: np.ndarray) -> np.ndarray:
    """Per column of ``lost`` (m, k: missing entries of one record sampled at ``t``), the
    step of its readings: the median interval between them (a channel read every few
    samples has its own), at least the record's median step."""
    step = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    own = np.full(lost.shape[1], step)
    for k in np.flatnonzero(lost.any(axis=0)):
        read = t[~lost[:, k]]
        if read.size > 1:
            own[k] = max(step, float(np.median(np.diff(read))))
    return own


def gapless_pieces(t: np.ndarray, cut: np.ndarray | None = None) -> list[slice]:
    """The samples of one record between its gaps (intervals longer than
    :data:`GAP_STEPS` median steps), as slices in time order; without the samples
    ``cut`` (a mask of the record's samples, e.g. those whose missing readings lie too
    far from any reading to be filled, :func:`~robust_sindy.timeseries.missing.far_from_readings`),
    which lie in no piece and split the piece they are in."""
    t = np.asarray(t, dtype=float)
    if t.size < 3:
        pieces = [slice(0, t.size)]
    else:
        steps = np.diff(t)
        breaks = np.flatnonzero(steps > GAP_STEPS * np.median(steps)) + 1
        edges = [0, *breaks.tolist(), t.size]
        pieces = [slice(a, b) for a, b in itertools.pairwise(edges)]
    if cut is None or not np.any(cut):
        return pieces
    out = []
    for piece in pieces:
        first, stop = runs(~np.asarray(cut[piece], dtype=bool))  # the samples not cut
        out.extend(
            slice(piece.start + int(a), piece.start + int(b))
            for a, b in zip(first, stop, strict=True)
        )
    return out


def segments_of(keep: np.ndarray, segments: list[slice]) -> list[slice]:
    """The slices of ``segments`` among the samples ``keep`` (a mask of all samples)."""
    return slices(int(keep[seg].sum()) for seg in segments)


def _as_list(value, name: str, multiple: bool):
    if value is None:
        return None
    if multiple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{name} must be a list with one array per trajectory, like x")
        return list(value)
    return [value]


def _frame_times(frame):
    """Seconds from the first sample of a datetime or timedelta index, else None."""
    index = frame.index
    if getattr(index.dtype, "kind", "") not in ("m", "M"):
        return None
    seconds = (index - index[0]).to_numpy().astype("timedelta64[ns]").astype(np.int64) / 1e9
    return np.asarray(seconds, dtype=float)


def _from_frames(x, t, x_dot, u):
    """Values of pandas inputs, the names their columns give, and times from the index."""
    multiple = isinstance(x, (list, tuple))
    xl = list(x) if multiple else [x]
    if not any(is_frame(a) for a in xl):
        return x, t, x_dot, u, None

    def values(obj):
        if obj is None:
            return None
        if isinstance(obj, (list, tuple)):
            return [a.to_numpy(dtype=float) if is_frame(a) else a for a in obj]
        return obj.to_numpy(dtype=float) if is_frame(obj) else obj

    names = [str(c) for c in xl[0].columns] if is_frame(xl[0]) else None
    for a in xl:
        if is_frame(a) and names is not None and [str(c) for c in a.columns] != names:
            raise ValueError("x: every DataFrame must have the same columns")
    ul = None if u is None else (list(u) if isinstance(u, (list, tuple)) else [u])
    if names is not None and ul is not None:
        names = names + [str(c) for c in ul[0].columns] if is_frame(ul[0]) else None
    if t is None:
        times = [_frame_times(a) if is_frame(a) else None for a in xl]
        if all(ti is not None for ti in times):
            t = times if multiple else times[0]
    return values(x), t, values(x_dot), values(u), names


#: The fewest readings of each state (control, derivative) in a trajectory with missing
#: entries: the temporal screen's local fits, which fill the others, need this many.
MIN_READINGS = 10


def _in_memory(values, name: str):
    """2-D float arrays; NaN marks a missing reading (each column of each trajectory
    with missing entries keeps at least :data:`MIN_READINGS` readings)."""
    out = [as_float_array(a, name, (1, 2), allow_nan=True) for a in values]
    out = [a[:, None] if a.ndim == 1 else a for a in out]
    for i, a in enumerate(out):
        lost = np.isnan(a)
        if not lost.any():
            continue
        have = (~lost).sum(axis=0)
        few = np.flatnonzero(have < min(MIN_READINGS, a.shape[0]))
        if few.size:
            where = f" of trajectory {i}" if len(out) > 1 else ""
            raise ValueError(
                f"{name}: column {int(few[0])}{where} has {int(have[few[0]])} readings of "
                f"{a.shape[0]} (the rest NaN, missing); at least {MIN_READINGS} are needed to "
                "fill the missing ones from their neighbours in time"
            )
    return out


def _lazy(values, name: str):
    import dask.array as da

    out = [da.asarray(a) for a in values]
    out = [a[:, None] if a.ndim == 1 else a for a in out]
    if any(a.ndim != 2 for a in out):
        shapes = [a.shape for a in out]
        raise ValueError(f"with Dask, each trajectory of {name} must be 2-D; got shapes {shapes}")
    return out


def _times(t, xs, multiple):
    """Sample times per trajectory from a step or from the times given."""
    if t is None:
        raise ValueError("t is required (a time step or the sample times)")
    if not isinstance(t, (list, tuple)) and np.ndim(t) == 0:
        dt = as_float_array(t, "t", (0,))
        if dt <= 0:
            raise ValueError(f"t as a time step must be > 0; got {float(dt)}")
        return [float(dt) * np.arange(a.shape[0]) for a in xs]
    tl = _as_list(t, "t", multiple)
    if len(tl) != len(xs):
        raise ValueError(f"t has {len(tl)} trajectories but x has {len(xs)}")
    out = []
    for ti, a in zip(tl, xs, strict=True):
        ti = check_time(ti, "t", min_length=1)
        if ti.size != a.shape[0]:
            raise ValueError(f"t has {ti.size} time points but x has {a.shape[0]} samples")
        out.append(ti)
    return out


@dataclass(frozen=True)
class Trajectories:
    """One or several trajectories, checked.

    Attributes
    ----------
    x : list of ndarray (m_i, n)
        The states of each trajectory (Dask arrays when :attr:`lazy`).
    t : list of ndarray (m_i,) or None
        The sample times of each trajectory; None when derivatives were measured and
        no times were needed (for Dask input: when ``t`` was not given or was a step).
    x_dot : list of ndarray (m_i, n) or None
        Measured derivatives.
    u : list of ndarray (m_i, q) or None
        Controls.
    names : list of str or None
        Names of the states then the controls, when the input gave them (DataFrame
        columns) or the user did.
    multiple : bool
        Whether the user passed a list of trajectories.
    lazy : bool
        Whether the arrays are Dask arrays.
    step : float or None
        For Dask input, the time step when ``t`` was one number.
    """

    x: list
    t: list | None
    x_dot: list | None
    u: list | None
    names: list[str] | None
    multiple: bool
    lazy: bool = False
    step: float | None = None

    @classmethod
    def from_user(
        cls, x, t=None, x_dot=None, u=None, feature_names=None, *, need_t: bool = False
    ) -> Trajectories:
        """Check the user's arrays (see the module docstring).

        ``need_t``: the sample times are needed even with measured derivatives.
        """
        lazy = any(
            is_dask(a) or (isinstance(a, (list, tuple)) and any(is_dask(b) for b in a))
            for a in (x, x_dot, u)
        )
        frame_names = None
        if not lazy:
            x, t, x_dot, u, frame_names = _from_frames(x, t, x_dot, u)
        names = feature_names if feature_names is not None else frame_names
        multiple = isinstance(x, (list, tuple))
        convert = _lazy if lazy else _in_memory
        xs = convert(_as_list(x, "x", multiple), "x")
        if multiple and not xs:
            raise ValueError("x is an empty list: give at least one trajectory")
        n = xs[0].shape[1]
        for a in xs:
            if a.shape[1] != n:
                raise ValueError("x: every trajectory must have the same number of states")
        us = cls._matching(u, "u", xs, multiple, convert)
        if us is not None:
            for a, b in zip(us, xs, strict=True):
                if a.shape[0] != b.shape[0]:
                    raise ValueError(f"u has {a.shape[0]} samples but x has {b.shape[0]}")
            q = us[0].shape[1]
            if any(a.shape[1] != q for a in us):
                raise ValueError("u: every trajectory must have the same number of controls")
        ds = cls._matching(x_dot, "x_dot", xs, multiple, convert)
        if ds is not None:
            for a, b in zip(ds, xs, strict=True):
                if a.shape != b.shape:
                    raise ValueError(f"x_dot has shape {a.shape} but x has shape {b.shape}")
        if lazy:
            return cls._lazy_times(xs, t, ds, us, names, multiple)
        ts = _times(t, xs, multiple) if need_t or ds is None else None
        return cls(xs, ts, ds, us, None if names is None else list(names), multiple)

    @staticmethod
    def _matching(values, name: str, xs: list, multiple: bool, convert) -> list | None:
        """``values`` as a list of 2-D arrays, one per trajectory of ``xs``."""
        vs = _as_list(values, name, multiple)
        if vs is None:
            return None
        if len(vs) != len(xs):
            raise ValueError(f"{name} has {len(vs)} trajectories but x has {len(xs)}")
        return convert(vs, name)

    @classmethod
    def _lazy_times(cls, xs, t, ds, us, names, multiple) -> Trajectories:
        step = None
        ts = None
        if t is not None and not isinstance(t, (list, tuple)) and np.ndim(t) == 0:
            if is_dask(t):
                raise ValueError("with a Dask x, t must be a number (the step) or arrays")
            step = float(t)
            if not (np.isfinite(step) and step > 0):
                raise ValueError(f"t as a time step must be a finite number > 0; got {t!r}")
        elif t is not None:
            tl = _as_list(t, "t", multiple)
            if len(tl) != len(xs):
                raise ValueError(f"t has {len(tl)} trajectories but x has {len(xs)}")
            ts = list(tl)
        return cls(xs, ts, ds, us, None if names is None else list(names), multiple, True, step)

    # ------------------------------------------------------------------ derived views
    @property
    def n_states(self) -> int:
        return int(self.x[0].shape[1])

    @property
    def n_controls(self) -> int:
        return 0 if self.u is None else int(self.u[0].shape[1])

    @property
    def lengths(self) -> list[int]:
        return [int(a.shape[0]) for a in self.x]

    @property
    def n_samples(self) -> int:
        return sum(self.lengths)

    @property
    def segments(self) -> list[slice]:
        """Each trajectory's slice of the stacked samples."""
        return slices(self.lengths)

    def pairs(self):
        """``(x_i, u_i)`` per trajectory (``u_i`` None without controls)."""
        return zip(self.x, [None] * len(self.x) if self.u is None else self.u, strict=True)

    def feature_names(self) -> list[str]:
        """Names of the states then the controls (given, or ``x0.., u0..``)."""
        return input_names(self.names, self.n_states, self.n_controls)

    def inputs(self) -> np.ndarray:
        """The library's inputs (states, then controls) of all samples, stacked (NaN
        where a reading is missing)."""
        return np.vstack([a if b is None else np.hstack([a, b]) for a, b in self.pairs()])

    @property
    def missing(self) -> np.ndarray:
        """Entries of the states not measured (NaN), stacked (m, n)."""
        return np.isnan(np.vstack(self.x))

    @property
    def missing_controls(self) -> np.ndarray:
        """Entries of the controls not measured (NaN), stacked (m, q)."""
        if self.u is None:
            return np.zeros((self.n_samples, 0), dtype=bool)
        return np.isnan(np.vstack(self.u))

    @property
    def missing_derivatives(self) -> np.ndarray:
        """Entries of the measured derivatives missing (NaN), stacked (m, n); none when
        the derivatives are estimated."""
        if self.x_dot is None:
            return np.zeros((self.n_samples, self.n_states), dtype=bool)
        return np.isnan(np.vstack(self.x_dot))
