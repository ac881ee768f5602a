"""Compiled local fits of the temporal screen (Numba).

:func:`loo_predict` computes the leave-one-out predictions of
:func:`robust_sindy.timeseries.temporal.loo_predict` sample by sample: each sample's
weights from the normal equations of its own neighbours (a Cholesky factorisation of a
``(degree + 1)``-square system), where the NumPy code solves each distinct pattern of
relative times once and gathers.  Same systems, same ridge; the predictions agree to
rounding.

:func:`lts_windows` runs, window by window in compiled loops, the concentration steps
that :func:`robust_sindy.timeseries.temporal._concentrate` runs as array expressions:
the elemental starts of a window, one concentration step for all of them, the most
promising kept, the remaining steps for those, and the fitted value at the window's own
sample of the best.  The arithmetic is the NumPy code's (the same elemental inverses,
the same Hankel normal equations with the same ridge, the same trimming rule); only the
order of the sums differs, so the fitted values agree to rounding.  The NumPy code
builds ``(windows, starts, samples)`` arrays and makes a few dozen passes over them;
here each window's work stays in a few hundred bytes.

Numba is imported on first use and the compiled code cached on disk
(:mod:`robust_sindy.core.compiled`); where it cannot compile, :func:`lts_windows` returns
``None`` and the caller's NumPy code does the work.
"""

from __future__ import annotations

import numpy as np

from ..core.compiled import Kernels

__all__ = ["failure_reason", "loo_predict", "lts_windows", "usable"]

_jit = Kernels(globals())


@_jit
def _rank(x, f, V, p, coef, nk, q, r2, top, cut, trimmed, bits, below):
    """For the first ``nk`` fits (columns of ``coef``, (a, K)) of the window
    ``x[f : f + w]`` with rows ``V[p]``: the squared residuals ``r2`` (w, K), the
    ``q``-th smallest of each column (``cut``; the ``w - q + 1`` largest kept in
    ``top`` by a branch-free insertion), the sum of its ``q`` smallest (``trimmed``,
    the ties at the cut counted once each up to ``q``) and the bits of the samples at
    or below the cut (``bits``); ``below`` is work space.  The loops run across the
    fits, so they vectorise."""
    w, a = V.shape[1], V.shape[2]
    L = w - q + 1
    for j in range(w):
        for k in range(nk):
            r2[j, k] = x[f + j]
        for c in range(a):
            vc = V[p, j, c]
            for k in range(nk):
                r2[j, k] -= vc * coef[c, k]
        for k in range(nk):
            r2[j, k] *= r2[j, k]
    for i in range(L):
        for k in range(nk):
            top[i, k] = -np.inf
    for j in range(w):
        for k in range(nk):
            v = r2[j, k]
            for i in range(L):
                hi = max(top[i, k], v)
                v = min(top[i, k], v)
                top[i, k] = hi
    for k in range(nk):
        cut[k] = top[L - 1, k]
        trimmed[k] = 0.0
        bits[k] = 0
        below[k] = 0
    for j in range(w):
        for k in range(nk):
            v = r2[j, k]
            lt = v < cut[k]
            trimmed[k] += v if lt else 0.0
            below[k] += 1 if lt else 0
            bits[k] |= (1 if v <= cut[k] else 0) << j
    for k in range(nk):
        trimmed[k] += (q - below[k]) * cut[k]


@_jit
def _cholesky_solve(gram, rhs, low, out):
    """Solve ``gram out = rhs`` for a small symmetric positive definite ``gram`` (its
    lower triangle is read) by Cholesky, pivots floored at the smallest normal number;
    ``low`` is work space."""
    a = rhs.size
    tiny = np.finfo(np.float64).tiny
    for c in range(a):
        diag = gram[c, c]
        for e in range(c):
            diag -= low[c, e] ** 2
        low[c, c] = np.sqrt(max(diag, tiny))
        for r in range(c + 1, a):
            s = gram[r, c]
            for e in range(c):
                s -= low[r, e] * low[c, e]
            low[r, c] = s / low[c, c]
    for c in range(a):
        s = rhs[c]
        for e in range(c):
            s -= low[c, e] * out[e]
        out[c] = s / low[c, c]
    for c in range(a - 1, -1, -1):
        s = out[c]
        for e in range(c + 1, a):
            s -= low[e, c] * out[e]
        out[c] = s / low[c, c]


@_jit
def _refit(x, f, V, Pw, p, mask, ridge, coef, k, mom, b, gram, low, z):
    """Least squares of the window ``x[f : f + w]`` on the rows ``V[p]`` in the bits
    of ``mask`` (the Hankel normal equations of
    :func:`robust_sindy.timeseries.temporal._hankel_solve`), into ``coef[:, k]``;
    ``mom``, ``b``, ``gram``, ``low`` and ``z`` are work space."""
    w, a = V.shape[1], V.shape[2]
    ne = Pw.shape[2]
    mom[:] = 0.0
    b[:] = 0.0
    for j in range(w):
        if (mask >> j) & 1:
            for e in range(ne):
                mom[e] += Pw[p, j, e]
            for c in range(a):
                b[c] += x[f + j] * V[p, j, c]
    for r in range(a):
        for c in range(r + 1):
            gram[r, c] = mom[r + c]
        gram[r, r] += ridge
    _cholesky_solve(gram, b, low, z)
    for c in range(a):
        coef[c, k] = z[c]


@_jit
def _windows(x, first, place, pattern, V, Pw, inverse, subsets, q, steps, keep, ridge, out):
    """Fitted value of every window (one per entry of ``first``): the window of
    ``x[first : first + w]``, its polynomial rows ``V[pattern]`` (w, a), their powers
    ``Pw[pattern]`` (w, 2a - 1), the elemental inverses ``inverse[pattern]`` (K, a, a)
    of the ``subsets`` (K, a) of positions, the fit evaluated at row ``place``."""
    nwin = first.size
    K, a = subsets.shape
    w = V.shape[1]
    coef = np.empty((a, K))
    spare = np.empty((a, K))
    r2 = np.empty((w, K))
    top = np.empty((w, K))
    cut = np.empty(K)
    trimmed = np.empty(K)
    bits = np.empty(K, dtype=np.int64)
    mom = np.empty(2 * a - 1)
    rhs = np.empty(a)
    gram = np.empty((a, a))
    low = np.empty((a, a))
    z = np.empty(a)
    below = np.empty(K, dtype=np.int64)
    # The fits of the masks met in the window (a refit depends on its mask only, and
    # most starts of a window end on the same few masks).
    seen = np.empty(K * max(steps, 1), dtype=np.int64)
    seen_coef = np.empty((K * max(steps, 1), a))
    for b in range(nwin):
        nseen = 0
        p = pattern[b]
        f = first[b]
        for k in range(K):
            for c in range(a):
                s = 0.0
                for j in range(a):
                    s += x[f + subsets[k, j]] * inverse[p, k, c, j]
                coef[c, k] = s
        nk = K
        for step in range(steps):
            _rank(x, f, V, p, coef, nk, q, r2, top, cut, trimmed, bits, below)
            if step == 1 and nk > keep:
                order = np.argsort(trimmed[:nk])[:keep]
                kept = bits[order]
                for kk in range(keep):
                    for c in range(a):
                        spare[c, kk] = coef[c, order[kk]]
                    bits[kk] = kept[kk]
                nk = keep
                coef, spare = spare, coef
            for k in range(nk):
                hit = -1
                for u in range(nseen):
                    if seen[u] == bits[k]:
                        hit = u
                        break
                if hit >= 0:
                    for c in range(a):
                        coef[c, k] = seen_coef[hit, c]
                    continue
                _refit(x, f, V, Pw, p, bits[k], ridge, coef, k, mom, rhs, gram, low, z)
                seen[nseen] = bits[k]
                for c in range(a):
                    seen_coef[nseen, c] = coef[c, k]
                nseen += 1
        _rank(x, f, V, p, coef, nk, q, r2, top, cut, trimmed, bits, below)
        best = 0
        for k in range(1, nk):
            if trimmed[k] < trimmed[best]:
                best = k
        s = 0.0
        for c in range(a):
            s += coef[c, best] * V[p, place[b], c]
        out[b] = s


def usable() -> bool:
    """Whether the kernels can be compiled here."""
    return _jit.usable


def failure_reason() -> str | None:
    """Why they cannot, or None."""
    return _jit.broken


def lts_windows(x, first, place, pattern, v, inverse, subsets, q, steps, keep, ridge):
    """Fitted values of the trimmed fits of the windows ``x[first[b] : first[b] + w]``
    at their rows ``place[b]``; ``v`` (P, w, a) the polynomial rows of the P patterns
    of relative times, ``pattern`` (b,) the pattern of each window, ``inverse`` (P, K,
    a, a) the inverses of the elemental systems.  ``None`` where the kernel cannot be
    compiled."""
    if not _jit.available():
        return None
    v = np.ascontiguousarray(v, dtype=float)
    if v.shape[1] > 62:
        raise ValueError("a window of the trimmed fits has at most 62 samples")
    a = v.shape[-1]
    tau = v[..., 1] if a > 1 else np.zeros(v.shape[:-1])
    powers = np.ascontiguousarray(tau[..., None] ** np.arange(2 * a - 1))
    out = np.empty(len(first))
    _jit.run(
        "_windows",
        np.ascontiguousarray(x, dtype=float),
        np.ascontiguousarray(first, dtype=np.int64),
        np.ascontiguousarray(place, dtype=np.int64),
        np.ascontiguousarray(pattern, dtype=np.int64),
        v,
        powers,
        np.ascontiguousarray(inverse, dtype=float),
        np.ascontiguousarray(subsets, dtype=np.int64),
        int(q),
        int(steps),
        int(keep),
        float(ridge),
        out,
    )
    return out if _jit.usable else None  # None: it could not be compiled after all


@_jit
def _loo(x, t, nb, at, degree, pred, factor):
    m, width = nb.shape
    a = degree + 1
    V = np.empty((width, a))
    gram = np.empty((a, a))
    low = np.empty((a, a))
    z = np.empty(a)
    unit = np.zeros(a)
    unit[0] = 1.0
    key = np.empty(width, dtype=np.int64)
    last = np.empty(width, dtype=np.int64)
    weights = np.empty(width)
    have = False
    unused = np.iinfo(np.int64).min
    for i in range(m):
        here = t[at[i]]
        span = 0.0
        for j in range(width):
            if nb[i, j] >= 0:
                span = max(span, abs(t[nb[i, j]] - here))
        if span <= 0.0:
            span = 1.0
        same = have
        for j in range(width):
            if nb[i, j] >= 0:
                key[j] = np.int64(np.round((t[nb[i, j]] - here) / span * 1e9))
            else:
                key[j] = unused
            same = same and key[j] == last[j]
        if not same:
            _loo_weights(t, nb, i, here, span, a, V, gram, unit, low, z, weights)
            for j in range(width):
                last[j] = key[j]
            have = True
        value = 0.0
        squares = 0.0
        for j in range(width):
            if nb[i, j] >= 0:
                value += weights[j] * x[nb[i, j]]
                squares += weights[j] ** 2
        pred[i] = value
        factor[i] = np.sqrt(1.0 + squares)


@_jit
def _loo_weights(t, nb, i, here, span, a, V, gram, unit, low, z, weights):
    """The weights of sample ``i``'s leave-one-out prediction from its neighbours."""
    width = nb.shape[1]
    for j in range(width):
        if nb[i, j] >= 0:
            tau = (t[nb[i, j]] - here) / span
            V[j, 0] = 1.0
            for c in range(1, a):
                V[j, c] = tau**c
        else:
            for c in range(a):
                V[j, c] = 0.0
    trace = 0.0
    for c in range(a):
        for e in range(c + 1):
            s = 0.0
            for j in range(width):
                s += V[j, c] * V[j, e]
            gram[c, e] = s
        trace += gram[c, c]
    for c in range(a):
        gram[c, c] += 1e-12 * trace
    # gram z = e_0: the weights of the value at tau = 0 are V z (row 0 of gram^-1 V^T).
    _cholesky_solve(gram, unit, low, z)
    for j in range(width):
        wj = 0.0
        for c in range(a):
            wj += V[j, c] * z[c]
        weights[j] = wj


def loo_predict(x, t, nb, degree, at):
    """Leave-one-out predictions of ``x`` at the samples ``at`` from their neighbours
    ``nb`` (rows; -1 unused) and the factors ``sqrt(1 + sum_j w_j^2)``; ``None``
    where the kernel cannot be compiled."""
    if not _jit.available():
        return None
    pred = np.empty(nb.shape[0])
    factor = np.empty(nb.shape[0])
    _jit.run(
        "_loo",
        np.ascontiguousarray(x, dtype=float),
        np.ascontiguousarray(t, dtype=float),
        np.ascontiguousarray(nb, dtype=np.int64),
        np.ascontiguousarray(at, dtype=np.int64),
        int(degree),
        pred,
        factor,
    )
    return (pred, factor) if _jit.usable else None  # None: it could not be compiled after all
