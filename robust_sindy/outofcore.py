"""Out of core: data as Dask arrays, never held whole.

* :func:`dask_library` fits a library's names and returns ``Theta`` as a Dask array
  with the row chunks of the states; every pass of :func:`robust_sindy.fit` over it
  evaluates the library on one chunk at a time, so ``Theta`` is never held whole.
* :func:`from_npy` reads a ``.npy`` file as a Dask array, chunk by chunk.
* :func:`sample` and :func:`refit` are the two halves of
  :meth:`HuberSINDy.fit <robust_sindy.HuberSINDy.fit>` on Dask arrays: the whole
  pipeline chooses the model on the first :data:`DASK_SAMPLE` samples in memory, then
  every equation's selected terms are refitted on all samples, chunk by chunk, leaving
  out the samples with gross residuals under the sample's model (the row screen's rule,
  :func:`~robust_sindy.selection.rows.gross_ratio`).

Read more in the user guide: :doc:`/guide/out_of_core`.

    >>> import dask.array as da, numpy as np, robust_sindy as rs
    >>> x = da.from_array(np.random.default_rng(0).normal(size=(1000, 2)), chunks=(250, 2))
    >>> lib, theta = rs.outofcore.dask_library(rs.PolynomialLibrary(2), x)
    >>> theta.shape, theta.chunks[0], lib.get_feature_names()[:3]
    ((1000, 6), (250, 250, 250, 250), ['1', 'x0', 'x1'])
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from sklearn.base import clone

from .core.scaling import robust_scale
from .core.statistics import local_scale
from .diagnostics import MAX_FLAGGED_FRACTION, MAX_LEFT_OUT
from .fitting import FitResult, fit
from .library import BaseLibrary, PolynomialLibrary
from .selection.constrained import restricted, scaled_fit
from .selection.rows import SCALE_WINDOW, gross_ratio
from .timeseries.derivatives import chunk_derivative
from .timeseries.trajectories import Trajectories

__all__ = [
    "DASK_OVERLAP",
    "DASK_SAMPLE",
    "OutOfCore",
    "dask_library",
    "from_npy",
    "refit",
    "sample",
]

#: Samples (the first ones, contiguous) on which the automatic choices are made when the
#: data are Dask arrays.
DASK_SAMPLE = 200_000
#: Samples each chunk borrows from its neighbours to differentiate Dask states.
DASK_OVERLAP = 64


def _read_rows(path: str, start: int, stop: int) -> np.ndarray:
    return np.array(np.load(path, mmap_mode="r")[start:stop])


def from_npy(path, chunk_rows: int = 1_000_000):
    """A ``.npy`` file (2-D) as a Dask array whose tasks each read their own rows.

    Each chunk is read from the file when its task runs and released when the task's
    consumers are done, so a pass holds about as many chunks as there are workers.
    (``dask.array.from_array`` on a ``numpy.memmap`` held copies of many chunks at
    once: 0.6 GB for a sum over 10 chunks of 24 MB, against 0.18 GB this way.)
    """
    import dask
    import dask.array as da

    path = str(path)
    head = np.load(path, mmap_mode="r")
    if head.ndim != 2:
        raise ValueError(f"{path!r} holds a {head.ndim}-D array; expected 2-D")
    m, k = head.shape
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, int) or chunk_rows < 1:
        raise ValueError(f"chunk_rows must be an integer >= 1; got {chunk_rows!r}")
    parts = [
        da.from_delayed(
            dask.delayed(_read_rows)(path, a, min(m, a + chunk_rows)),
            shape=(min(m, a + chunk_rows) - a, k),
            dtype=head.dtype,
        )
        for a in range(0, m, chunk_rows)
    ]
    return da.concatenate(parts, axis=0)


def dask_library(library: BaseLibrary | None, x, u=None, input_names=None):
    """The fitted library and ``Theta(x, u)`` as a lazy Dask array (same row chunks as ``x``).

    ``x`` (m, n) and ``u`` (m, q) are Dask arrays (or arrays, wrapped), chunked by rows
    only; ``u`` is rechunked to ``x``'s rows.
    """
    import dask.array as da

    x = da.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"x must be 2-D; got shape {x.shape}")
    x = x.rechunk({1: -1})
    z = x
    if u is not None:
        u = da.asarray(u)
        u = u[:, None] if u.ndim == 1 else u
        if u.shape[0] != x.shape[0]:
            raise ValueError(f"u has {u.shape[0]} samples but x has {x.shape[0]}")
        z = da.concatenate([x, u.rechunk({0: x.chunks[0], 1: -1})], axis=1).rechunk({1: -1})
    lib = clone(library) if library is not None else PolynomialLibrary()
    lib.fit(np.zeros((1, z.shape[1])), input_names=input_names)
    p = lib.n_output_features_
    theta = z.map_blocks(
        lib.transform,
        chunks=(z.chunks[0], (p,)),
        dtype=float,  # a bound method: picklable
    )
    return lib, theta


def sample(data: Trajectories, size: int | None = None) -> Trajectories:
    """The first ``size`` samples (default :data:`DASK_SAMPLE`) of Dask trajectories, in
    memory: whole trajectories first, the last one cut."""
    import dask.array as da

    if data.x_dot is None and data.step is None:
        raise ValueError(
            "with a Dask x, derivatives are computed out of core for a uniform time "
            "step only: pass t as a number (the step), or pass x_dot"
        )
    left = DASK_SAMPLE if size is None else size
    parts = []
    ds = [None] * len(data.x) if data.x_dot is None else data.x_dot
    us = [None] * len(data.x) if data.u is None else data.u
    ts = [None] * len(data.x) if data.t is None else data.t
    for a, d, b, ti in zip(data.x, ds, us, ts, strict=True):
        if left <= 0:
            break
        k = min(a.shape[0], left)
        left -= k
        if ti is not None:
            ti = np.asarray(ti[:k], dtype=float)
        arrays = [None if v is None else v[:k] for v in (a, d, b)]
        got = iter(da.compute(*(v for v in arrays if v is not None)))
        sa, sd, sb = (None if v is None else np.asarray(next(got), float) for v in arrays)
        parts.append((sa, ti, sd, sb))
    sx, st, sd, su = (list(v) for v in zip(*parts, strict=True))
    one = len(parts) == 1

    def given(values):
        return values[0] if one else values

    if data.step is not None:
        t = data.step
    else:
        t = None if data.t is None else given(st)
    return Trajectories.from_user(
        given(sx),
        t,
        None if data.x_dot is None else given(sd),
        None if data.u is None else given(su),
        data.names,
    )


@dataclass(frozen=True)
class OutOfCore:
    """Outcome of :func:`refit`.

    Attributes
    ----------
    coef : ndarray (p, n)
        Every equation's selected terms refitted on all samples.
    screened : Dask array of bool (m,)
        The samples left out of the refit (lazy).
    unresolved : ndarray of bool (m,)
        Samples whose estimated derivatives the sampling does not resolve.
    outliers : Dask array of bool (m, n)
        Residuals beyond ``delta`` under the refitted model (lazy).
    certified : ndarray of bool (n,)
        Whether each equation's refit was certified.
    info : dict
        ``sample``, ``samples``, ``flagged``, ``unresolved``, ``passes``, ``refit``.
    warnings : list of str
        What the refit found that the sample's diagnostics could not.
    """

    coef: np.ndarray
    screened: object
    unresolved: np.ndarray
    outliers: object
    certified: np.ndarray
    info: dict
    warnings: list


def refit(model, data: Trajectories, chosen: Trajectories) -> OutOfCore:
    """Refit ``model`` (fitted on the in-memory sample ``chosen`` of ``data``) on all of
    ``data``, chunk by chunk.

    Without ``x_dot`` (``t`` must then be the time step) every chunk is differentiated
    as the sample was, with the sample's windows and noise levels and
    :data:`DASK_OVERLAP` samples of its neighbours, its samples whose derivatives the
    sampling does not resolve left out (found in one pass).  A sample is left out when
    its residual under the sample's model is gross in any equation
    (:func:`~robust_sindy.selection.rows.gross_ratio`) against the larger of the sample's
    robust scale and the local robust scale of the residuals within
    :data:`~robust_sindy.selection.rows.SCALE_WINDOW` samples (here counting every
    sample, capped at its largest ratio to the global scale on the sample's kept
    samples).  Every equation's selected terms are then refitted by Huber (``lam = 0``,
    or the model's ``lam`` when it was fixed and not refitted; the chosen ``delta``) on
    the samples kept, in one batched solve (:mod:`robust_sindy.solvers.chunked`; a term
    outside an equation's support held at 0 by an L1 weight above ``delta ||A_j||_1``).
    Derivatives and local scales never reach across two trajectories.
    """
    import dask.array as da

    xs, us = list(data.x), [b for _, b in data.pairs()]
    estimate = data.x_dot is None
    coef_sample = model.coef_.T.copy()
    unresolved = [np.zeros(a.shape[0], dtype=bool) for a in xs]
    sd = chosen.x_dot
    if estimate:
        robust = isinstance(model.differentiation, str) and model.differentiation == "robust"
        # A module-level function: the lazy results (screened, outliers) hold it, and a
        # fitted model is pickled with them.
        derivative = functools.partial(
            chunk_derivative,
            dt=data.step,
            how=model.differentiation,
            window=model.derivative_window,
            screen=model.screen,
            half=model.derivative_windows_ if robust else None,
            noise=None if model.temporal_ is None else model.temporal_.scale,
        )
        xs = [a.rechunk({1: -1}) for a in xs]
        ds = [
            a.map_overlap(derivative, depth={0: DASK_OVERLAP, 1: 0}, boundary="none", dtype=float)
            for a in xs
        ]
        # The unresolved samples, found in one pass and kept (one byte per sample):
        # every pass of the refit recomputes the derivatives, not this check.
        *unresolved, sd = da.compute(
            *(
                a.map_overlap(
                    functools.partial(derivative, check=True),
                    depth={0: DASK_OVERLAP, 1: 0}, boundary="none", dtype=bool,
                )[:, 0]
                for a in xs
            ),
            [d[: a.shape[0]] for d, a in zip(ds, chosen.x, strict=False)],
        )  # fmt: skip
        sd = [np.asarray(v, dtype=float) for v in sd]
    else:
        ds = data.x_dot
    # The sample's model and scales screen every sample, chunk by chunk.
    kept = ~model.screened_
    r_sample = np.vstack(sd) - model.library_.transform(chosen.inputs()) @ coef_sample
    scale = np.maximum(robust_scale(r_sample[kept]), np.finfo(float).tiny)
    # The local scale may exceed the global one only as far as it does on the sample's
    # kept samples: where most residuals in a window are gross (a stretch of corrupted
    # data after the sample), the local scale would excuse them all.
    local_sample = np.vstack([local_scale(r_sample[seg], SCALE_WINDOW) for seg in chosen.segments])
    cap = np.max(local_sample[kept] / scale, axis=0, initial=1.0) * scale
    thetas, rs, bads = [], [], []
    for a, d, b, loose in zip(xs, ds, us, unresolved, strict=True):
        _, theta_i = dask_library(model.library_, a, b, input_names=model.library_.input_names_)
        r_i = d - theta_i @ da.from_array(coef_sample)
        local = da.map_overlap(
            functools.partial(local_scale, half_width=SCALE_WINDOW), r_i,
            depth={0: SCALE_WINDOW, 1: 0}, boundary="none", dtype=float,
        )  # fmt: skip
        thetas.append(theta_i)
        rs.append(r_i)
        gross = gross_ratio(r_i, np.maximum(np.minimum(local, cap), scale)) > 1
        bads.append(gross | da.from_array(loose, chunks=gross.chunks))
    theta, r, bad = (da.concatenate(v, axis=0) for v in (thetas, rs, bads))
    unresolved = np.concatenate(unresolved)
    x_dot = da.concatenate(ds, axis=0)
    m, k = theta.shape[0], chosen.n_samples
    keep = ~bad
    # One pass for the count of samples left out and the columns' L1 norms (kept rows).
    n_flagged, l1 = da.compute(bad.sum(), abs(theta * keep[:, None]).sum(axis=0))
    coef, result, certified = _refit_selected(
        model, theta * keep[:, None], x_dot * keep[:, None], coef_sample, l1
    )
    left_out = int(n_flagged) / max(m, 1)
    unresolved_part = int(unresolved.sum()) / max(m, 1)
    found = []
    # The sample's diagnostics speak for the sample: a model that fits the sample but
    # not the rest of the data (a regime, a sensor or a contamination that changes
    # after it) shows in what the out-of-core screen leaves out.
    if max(left_out - unresolved_part, unresolved_part) > MAX_FLAGGED_FRACTION or (
        left_out > MAX_LEFT_OUT
    ):
        found.append(
            f"out of core, {100 * left_out:.0f} % of all samples were left out of the "
            f"refit ({100 * (left_out - unresolved_part):.0f} % with gross residuals "
            f"under the sample's model, {100 * unresolved_part:.0f} % with unresolved "
            f"derivatives), against {100 * model.diagnostics_.flagged_fraction:.0f} % "
            f"of the first {k} samples, where the model was chosen: it may not describe "
            "the rest of the data (see dask_ and screened_); fit a sample from another "
            "part of the data, or more of it (robust_sindy.outofcore.DASK_SAMPLE)"
        )
    if not certified.all():
        found.append(
            f"the out-of-core refit of equations {np.flatnonzero(~certified).tolist()} "
            "was not certified (see dask_['refit'])"
        )
    info = {
        "sample": k,
        "samples": m,
        "flagged": int(n_flagged),
        "unresolved": int(unresolved.sum()),
        "passes": 0 if result is None else result.info["passes"],
        "refit": result,
    }
    outliers = abs(r) > model.delta_
    return OutOfCore(coef, bad, unresolved, outliers, certified, info, found)


def _refit_selected(model, theta_k, y_k, coef_sample, l1):
    """Every equation's selected terms refitted in one batched solve (its passes over the
    data shared by all equations): a term outside an equation's support gets an L1
    weight above ``delta ||A_j||_1``, the most ``|A_j^T psi|`` can be with ``|psi| <=
    delta``, which holds its coefficient at exactly 0."""
    coef = np.zeros_like(coef_sample)
    certified = np.ones(coef.shape[1], dtype=bool)
    if model.constrained_ is not None:
        return _refit_constrained(model, theta_k, y_k, coef, certified)
    cols = np.flatnonzero((coef_sample != 0).any(axis=0))
    terms = np.flatnonzero((coef_sample != 0).any(axis=1))
    result: FitResult | None = None
    if cols.size == 0:
        return coef, result, certified
    support = coef_sample[np.ix_(terms, cols)] != 0
    lam = np.zeros(support.shape)  # lam="auto" and refit: the selected terms, unpenalised
    if model.selection_ is None and not model.refit:
        lam_ = np.asarray(model.lam_, dtype=float)
        lam = np.broadcast_to(
            lam_[np.ix_(terms, cols)]
            if lam_.ndim == 2
            else np.broadcast_to(lam_, (coef.shape[1],))[cols][None, :],
            support.shape,
        ).copy()  # fmt: skip
    delta = np.asarray(model.delta_, dtype=float)[cols]
    bound = 2.0 * delta[None, :] * np.maximum(l1[terms], np.finfo(float).tiny)[:, None]
    options = {k: v for k, v in (model.solver_options or {}).items() if k in ("tol", "max_iter")}
    result = fit(
        theta_k[:, terms], y_k[:, cols], delta=delta, lam=np.where(support, lam, bound), **options
    )
    coef[np.ix_(terms, cols)] = np.where(support, np.asarray(result.coef), 0.0)
    certified[cols] = result.column_converged
    return coef, result, certified


def _refit_constrained(model, theta_k, y_k, coef, certified):
    """The selected terms under the model's constraints refitted as the sample's were
    (:func:`~robust_sindy.selection.constrained.scaled_fit`: unpenalised, each
    equation's loss on the scale of its constrained ``delta``, every coefficient off
    the support held at zero), in one problem over all equations
    (:func:`~robust_sindy.solvers.chunked.solve_chunked_constrained`), from the sample's
    coefficients."""
    refit = model.constrained_
    support = refit.support
    if not support.any():
        return coef, None, certified
    cols, sub = restricted(refit.constraints, support)
    options = {k: v for k, v in (model.solver_options or {}).items() if k in ("tol", "max_iter")}
    # From the sample's answer, which meets the constraints: near the optimum on all rows.
    fitted, result = scaled_fit(
        theta_k[:, cols], y_k, model.delta_, sub, warm_start=model.coef_.T[cols], **options
    )
    coef[cols] = np.where(support[cols], fitted, 0.0)
    certified[:] = result.converged
    return coef, result, certified
