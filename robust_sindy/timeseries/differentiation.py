"""Numerical derivatives for data without measured derivatives.

Examples
--------
>>> import numpy as np
>>> t = np.linspace(0.0, 1.0, 201)
>>> x = np.sin(t)[:, None]
>>> bool(np.abs(finite_difference(x, t) - np.cos(t)[:, None]).max() < 1e-4)
True
>>> bool(np.abs(savgol_derivative(x, t) - np.cos(t)[:, None]).max() < 1e-5)
True
"""

from __future__ import annotations

import numpy as np
import scipy.signal

from ..core.certificates import column_norms
from ..core.scaling import robust_scale
from ..core.statistics import correlation_time
from ..core.validation import as_float_array, check_int, check_positive, check_time
from .temporal import clean_neighbours, loo_predict

__all__ = [
    "HALF_WINDOWS",
    "choose_half_window",
    "finite_difference",
    "higher_order_derivative",
    "local_polynomial_derivative",
    "savgol_derivative",
    "unresolved_derivatives",
]

#: Half widths (samples on each side of a sample) among which
#: :func:`choose_half_window` chooses the window of the local polynomial.
HALF_WINDOWS = (2, 3, 4, 6, 8, 12, 16, 24, 32)
#: A window is chosen when its states' prediction error is within this fraction of the
#: smallest one (the smallest such window: no wider, more biased window for a gain
#: that is within the noise of the estimate).
WINDOW_TOL = 0.02
#: Each window must fit this many times into the usable samples of a component.
_WINDOWS_PER_COMPONENT = 5
#: Samples scored per component (evenly spread over the usable ones).
_SCORED = 2000
#: Wider windows are not scored once one predicts this much worse than the best so far.
_STOP = 1.5
#: Level of the test that a widening of the window changed the derivative along the
#: library (see :func:`choose_half_window`).
BIAS_LEVEL = 1e-3


def _check(x, t, min_length: int) -> tuple[np.ndarray, np.ndarray]:
    x = as_float_array(x, "x", (1, 2))
    t = check_time(t, min_length=min_length)
    if x.shape[0] != t.size:
        raise ValueError(f"x has {x.shape[0]} rows but t has {t.size} time points")
    return x, t


def finite_difference(x, t) -> np.ndarray:
    """Second-order finite differences (central inside, one-sided at the ends).

    ``t`` may be non-uniform (:func:`numpy.gradient` with coordinates).
    """
    x, t = _check(x, t, 3)
    return np.gradient(x, t, axis=0, edge_order=2)


def savgol_derivative(x, t, window_length: int = 11, polyorder: int = 3) -> np.ndarray:
    """Savitzky-Golay smoothed derivative (:func:`scipy.signal.savgol_filter`).

    Needs a uniform ``t``; ``window_length`` (odd) must not exceed the number of samples
    and ``polyorder`` must be smaller than it.
    """
    window_length = check_int(window_length, "window_length", 3)
    polyorder = check_int(polyorder, "polyorder", 1)
    x, t = _check(x, t, window_length)
    if window_length % 2 == 0:
        raise ValueError(f"window_length must be odd; got {window_length}")
    if polyorder >= window_length:
        raise ValueError(f"polyorder ({polyorder}) must be < window_length ({window_length})")
    dt = np.diff(t)
    if np.ptp(dt) > 1e-9 * dt.mean():
        raise ValueError("t must be uniformly spaced for savgol_derivative; use finite_difference")
    return scipy.signal.savgol_filter(
        x, window_length, polyorder, deriv=1, delta=float(dt.mean()), axis=0, mode="interp"
    )


def _nearest_usable(usable: np.ndarray, size: int) -> np.ndarray:
    """For each sample, the indices (ascending) of the ``size`` usable samples nearest
    to it in index (itself included when usable); on an all-usable array these are the
    centred windows, shifted inside at the ends."""
    m = usable.size
    u = np.flatnonzero(usable)
    i = np.arange(m)
    pos = np.searchsorted(u, i)
    cand = pos[:, None] + np.arange(-size, size)[None, :]
    valid = (cand >= 0) & (cand < u.size)
    idx = u[np.clip(cand, 0, u.size - 1)]
    # distance, ties broken towards the earlier sample; invalid candidates last
    dist = np.where(valid, 2.0 * np.abs(idx - i[:, None]) + (idx > i[:, None]), np.inf)
    best = np.argsort(dist, axis=1, kind="stable")[:, :size]
    return np.sort(np.take_along_axis(idx, best, axis=1), axis=1)


def _window_rows(t, idx, degree):
    """The polynomial rows (m, size, degree + 1) of the windows ``idx`` (m, size), in
    time relative to each sample and divided by the window's span (unit-free), and
    the spans (m, 1)."""
    tau = t[idx] - t[:, None]
    span = np.abs(tau).max(axis=1, keepdims=True)
    tau = tau / np.where(span > 0, span, 1.0)
    # The powers by repeated multiplication (``tau ** k`` calls pow for every entry,
    # thirty times slower; the two differ by a rounding).
    rows = np.empty((*tau.shape, degree + 1))
    rows[..., 0] = 1.0
    for k in range(1, degree + 1):
        np.multiply(rows[..., k - 1], tau, out=rows[..., k])
    return rows, span


#: Huber threshold (in noise scales) and reweighting steps of the robust local fits.
HUBER_C, _HUBER_STEPS = 2.0, 4


def _local_fit(x2, t, usable, half_window, degree, scale=None):
    """Per sample and component: the derivative of the least-squares polynomial through
    the ``2 half_window[k] + 1`` usable samples nearest to it; with a noise ``scale``
    per component, of the Huber fit (threshold ``HUBER_C`` scales, by reweighting)."""
    m, n = x2.shape
    out = np.empty((m, n))
    eye = np.eye(degree + 1)
    for k in range(n):
        size = 2 * int(half_window[k]) + 1
        ok = usable[:, k] if usable[:, k].sum() >= size else np.ones(m, dtype=bool)
        idx = _nearest_usable(ok, size)
        v, span = _window_rows(t, idx, degree)
        xw = x2[idx, k]

        def solve(w=None, v=v, xw=xw):
            """The (weighted) least-squares coefficients of every window."""
            vw = np.swapaxes(v if w is None else v * w[..., None], 1, 2)
            gram = vw @ v  # a stack of small products: matmul, several times einsum's speed
            ridge = 1e-12 * np.trace(gram, axis1=-2, axis2=-1)[..., None, None]
            return np.linalg.solve(gram + ridge * eye, vw @ xw[..., None])

        coef = solve()
        robust = scale is not None and size > degree + 1 and np.isfinite(scale[k])
        for _ in range(_HUBER_STEPS if robust and scale[k] > 0 else 0):
            # An error the temporal screen left unflagged is not spread over the window.
            r = np.abs(xw - (v @ coef)[..., 0])
            coef = solve(np.minimum(1.0, HUBER_C * scale[k] / np.maximum(r, np.finfo(float).tiny)))
        out[:, k] = coef[:, 1, 0] / span[:, 0]  # d/dt of c1 tau at tau = 0
    return out


def choose_half_window(
    x, t, mask=None, degree: int = 4, candidates=HALF_WINDOWS, library=None, rows=None,
    scale=None,
) -> np.ndarray:  # fmt: skip
    """Half width of the local polynomial per component, chosen by leave-one-out
    prediction of the states themselves.

    For each candidate ``h`` every usable sample is predicted by the least-squares
    polynomial of ``degree`` through its ``2 h`` nearest usable neighbours (itself left
    out); the error's robust scale (:func:`robust_sindy.selection.robust_scale`) is the
    noise of the sample plus that of the prediction plus the window's bias.  Narrow
    windows predict noisily, wide ones with bias.  Scores start at the narrowest window
    with enough neighbours for the polynomial (``2 h > degree``); the smallest ``h``
    within :data:`WINDOW_TOL` of the best score is chosen when it is wider than that
    one, and otherwise the narrowest candidate (the fourth-order difference, ``h = 2``,
    for the defaults).  On densely sampled noisy states this is a wide window (the
    fourth-order difference multiplies the noise by about ``1 / dt``); where the
    trajectory is coarsely sampled or nearly noise-free the bias dominates at once and
    the window stays narrow.  Only ratios of errors of the same component enter, so the
    choice does not depend on the units of the states or of time.  Candidates wider
    than a fifth of the usable samples are not tried.

    A window that predicts the states well can still bias their derivative, and a
    regression explains a bias that is smooth in time with library terms: on nearly
    noise-free data even a tiny one is significant.  Given the ``library`` matrix
    (m, p; of the repaired states, as a fit builds it; its ``rows``, a boolean mask,
    are those tested, with each component's usable samples: by default all), the window
    is widened from the narrowest candidate one step at a time, up to the choice
    above, only while the change of the derivative has no component along the
    library: the Wald statistic of the least-squares projection of that change on the
    library's columns, with its sandwich covariance (the residuals' correlation time
    counted, as in :func:`robust_sindy.selection.significance.robust_t`) plus the
    change's own noise given ``scale`` (the two estimators' least-squares weights on
    noise of that level: at irregular times the narrower window's is heavy-tailed),
    stays below the ``1 - BIAS_LEVEL`` quantile of its distribution when the change is
    that noise alone (given ``scale``: a quadratic form in Gaussian noise, matched in
    mean and variance by a scaled chi-square; without it, the chi-square of the
    library's rank); the samples tested
    are those of ``rows`` and the component's usable ones (a flagged reading of
    another component costs its entry, not the sample) whose narrowest derivative the
    library fits within 3.5 robust scales of the deleted residuals (a gross error the
    temporal screen missed would bend the projection and inflate the errors the change
    is measured against; where it sits in the library's row as well, that row's own
    columns fit it), and at each step the samples where either window's derivative
    is that far off are left out of the change (an error a window reaches and the
    other does not is a spike, not a bias).  The test is
    invariant to rescaling the columns, so still unit-free.  ``scale`` (the noise of
    each component): the derivatives tested are the Huber fits that
    :func:`local_polynomial_derivative` gives with it.

    Returns an int array (n,) (a 1-element array for 1-D ``x``).
    """

    degree = check_int(degree, "degree", 1)
    x, t = _check(x, t, 2)
    x2 = x[:, None] if x.ndim == 1 else x
    m, n = x2.shape
    usable = _usable(mask, m, n)
    cands = sorted({check_int(h, "candidates", 1) for h in candidates})
    out = np.full(n, cands[0], dtype=int)
    for k in range(n):
        ok = usable[:, k]
        # A left-out sample is predicted from 2 h neighbours, enough for the polynomial
        # only from the second narrowest window on: the narrowest is kept unless a wider
        # one predicts clearly better than the narrowest that can be scored.
        fit_in = [h for h in cands if 2 * h > degree
                  and _WINDOWS_PER_COMPONENT * (2 * h + 1) <= ok.sum()]  # fmt: skip
        if len(fit_in) < 2:
            continue
        # The same usable samples scored for every window (at most _SCORED of them,
        # evenly spread): the scores differ by the predictions only.
        at = np.flatnonzero(ok)
        at = at[np.linspace(0, at.size - 1, min(at.size, _SCORED)).round().astype(int)]
        scores = []
        for h in fit_in:
            nb = clean_neighbours(~ok, h, at)
            pred, _ = loo_predict(x2[:, k], t, nb, degree, at)
            scores.append(float(robust_scale((x2[at, k] - pred)[(nb >= 0).all(axis=1)])))
            if scores[-1] > _STOP * min(scores):
                break  # the bias dominates: wider windows only predict worse
        scores = np.array(scores)
        if not np.all(np.isfinite(scores)) or scores.min() <= 0:
            continue  # noise-free (or degenerate) states: the narrowest window
        best = int(np.flatnonzero(scores <= (1 + WINDOW_TOL) * scores.min())[0])
        if best > 0:
            out[k] = fit_in[best]
    if library is not None:
        scale = _noise_scale(scale, n)
        out = _library_guard(x2, t, usable, out, degree, cands, library, rows, scale)
    return out


#: Robust scales beyond which the guard takes a derivative's residual on the library
#: for a gross error (:func:`_fitted_rows`, :func:`_gross`).
_GROSS_CUTOFF = 3.5


#: Of a direction of the library's span, the least share of its energy on the rows kept
#: for it to stay in the basis of those rows (:func:`_subset_basis`).
_DIRECTION_KEPT = 1e-10


def _orthonormal_basis(a) -> np.ndarray:
    """An orthonormal basis (rows, rank) of the span of the columns of ``a``: its left
    singular vectors above ``1e-10`` of the largest singular value."""
    u, sing, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, sing > 1e-10 * sing[0]]


def _subset_basis(u, base, keep):
    """The orthonormal basis (rows ``keep``, rank) of the library's span on the rows
    ``keep``, a subset of ``base``, from ``u``, an orthonormal basis of it on the rows
    ``base``: one SVD serves every subset (every state's own rows, every round of the
    rows test).  The Gram matrix of ``u`` on the rows kept is ``I - u_R^T u_R`` (``u_R``
    the rows left out); its eigenvectors over the square roots of their eigenvalues
    whiten it (the directions that keep at most :data:`_DIRECTION_KEPT` of their energy
    are dropped).  Returns the basis ``u[keep] w`` and ``w``: the least-squares
    coefficients of ``y[keep]`` in the basis ``u`` are ``w (basis^T y[keep])``.  A
    subset costs a product with the rows kept and an eigendecomposition of the rank's
    size, where an SVD of the rows kept costs several such products.
    """
    inside = keep[base]
    left = u[~inside]
    mu, w = np.linalg.eigh(np.eye(u.shape[1]) - left.T @ left)
    ok = mu > _DIRECTION_KEPT
    w = w[:, ok] / np.sqrt(mu[ok])
    return u[inside] @ w, w


def _fitted_rows(a, y, rows, cutoff: float = _GROSS_CUTOFF, rounds: int = 5, base=None):
    """``rows`` without the samples whose residual of ``y`` on the columns of ``a`` (by
    least squares on the rows kept so far; deleted residuals ``r / (1 - leverage)`` for
    those rows) exceeds ``cutoff`` robust scales, and the orthonormal basis (kept rows,
    rank) of ``a`` on the rows returned.  ``base``: ``(u, base_rows)``, an orthonormal
    basis of ``a`` on rows that hold ``rows`` (:func:`_subset_basis`; by default that
    of ``rows``).

    The deleted residual is the sample's error when the others fit: a row of high
    leverage (a reading the temporal screen missed, far out in the library as well as
    in ``y``) is fitted by its own columns and its plain residual is small.
    """
    if base is None:
        base = (_orthonormal_basis(a[rows]), rows)
    u, where = base
    if np.any(rows & ~where):
        raise ValueError("rows must be among the rows of the base's basis")
    keep = rows.copy()
    for done in range(rounds + 1):
        q, w = _subset_basis(u, where, keep)
        if done == rounds:
            break  # the basis of the rows the last round kept
        # The residuals on every row of the base: the kept rows' least-squares fit,
        # carried to the others through the base's basis.
        r = np.zeros_like(y)
        r[where] = y[where] - u @ (w @ (q.T @ y[keep]))
        r[keep] /= np.maximum(1.0 - np.einsum("ij,ij->i", q, q), np.finfo(float).eps)
        # The scale of the signed residuals: that of their absolute values (about 0.6
        # of it for Gaussian ones) would cut into the bulk a little more every round.
        new = rows & (np.abs(r) <= cutoff * float(robust_scale(r[keep])))
        if np.array_equal(new, keep) or new.sum() <= a.shape[1]:
            break
        keep = new
    return keep, q


def _noise_scale(scale, n: int):
    if scale is None:
        return None
    scale = np.broadcast_to(as_float_array(scale, "scale", (0, 1)), (n,))
    if np.any(scale < 0):
        raise ValueError(f"scale must be >= 0 (the noise of each state); got {scale}")
    return scale


def _library_guard(x2, t, usable, upper, degree, cands, library, rows, scale) -> np.ndarray:
    """The widest window up to ``upper`` (per component) reached from the narrowest
    candidate by steps whose change of the derivative the library does not explain
    (see :func:`choose_half_window`)."""
    m, n = x2.shape
    a = as_float_array(library, "library", (2,))
    if a.shape[0] != m:
        raise ValueError(f"library has {a.shape[0]} rows but x has {m} samples")
    rows = np.ones(m, dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
    if rows.shape != (m,):
        raise ValueError(f"rows must be a boolean mask of shape ({m},); got {rows.shape}")
    out = np.full(n, cands[0], dtype=int)
    if rows.sum() <= a.shape[1] or not np.all(np.isfinite(a[rows])):
        return out  # nothing to test with: the narrowest window
    # Columns of unit norm: the rank cuts below then do not depend on the units of the
    # states (the columns' span, and so the test, is the same).
    norms = column_norms(a[rows])
    a = a / np.where(norms > 0, norms, 1.0)
    # One basis of the library on the rows tested, shared by every state's own rows.
    base = (_orthonormal_basis(a[rows]), rows)
    for k in range(n):
        steps = [h for h in cands if h <= upper[k]]
        if len(steps) < 2:
            continue
        sk = None if scale is None else scale[[k]]
        prev = _local_fit(x2[:, [k]], t, usable[:, [k]], [steps[0]], degree, sk)[:, 0]
        w_prev = None if sk is None else _derivative_operator(t, usable[:, k], steps[0], degree)
        # The samples of the component's own usable readings (another component's
        # flagged reading costs its entry, not the sample: the library is of the
        # repaired states) that the narrowest derivative's fit on the library does not
        # reject (gross errors the temporal screen missed would otherwise bend the
        # projection).
        own = rows & usable[:, k]
        if own.sum() <= a.shape[1]:
            continue
        test, u = _fitted_rows(a, prev, own, base=base)
        if test.sum() <= a.shape[1]:
            continue
        leverage = np.einsum("ij,ij->i", u, u)
        gross_prev = _gross(prev[test] - u @ (u.T @ prev[test]), leverage)
        for h in steps[1:]:
            cur = _local_fit(x2[:, [k]], t, usable[:, [k]], [h], degree, sk)[:, 0]
            # The change, against the errors the wider derivative would leave in the
            # regression (its residuals on the whole library, clipped at 3 robust
            # scales as Huber's score clips them): the change counts at the precision
            # the regression will see, not at that of the noisier narrow window.
            r = cur[test] - u @ (u.T @ cur[test])
            # A gross error the temporal screen missed reaches the wider window's
            # derivative at samples the narrower one did not see (and the other way
            # round): a spike, not a bias, left out of the change's projection.
            gross = _gross(r, leverage)
            uk = u * ~(gross | gross_prev)[:, None]
            c = uk.T @ (cur - prev)[test]
            bound = 3.0 * float(robust_scale(r))
            r = np.clip(r, -bound, bound)
            weighted = uk * np.abs(r)[:, None]
            cov = correlation_time(r)[0] * (weighted.T @ weighted)  # one symmetric product
            noise = None
            if sk is not None:
                # The change's own noise, which no test can tell from a bias: the two
                # estimators' weights on the states' noise (large where the narrower
                # window's samples crowd together, as at irregular times).
                w_cur = _derivative_operator(t, usable[:, k], h, degree)
                spread = (w_cur - w_prev)[test].T @ uk
                noise = float(sk[0]) ** 2 * (spread.T @ spread)
                cov += noise
            wald, bar = _wald_against_noise(c, cov, noise)
            if not wald <= bar:
                break
            out[k], prev, gross_prev = h, cur, gross
            if sk is not None:
                w_prev = w_cur
    return out


def _gross(r, leverage, cutoff: float = _GROSS_CUTOFF) -> np.ndarray:
    """The residuals ``r`` whose deleted residuals ``r / (1 - leverage)`` lie beyond
    ``cutoff`` robust scales (as :func:`_fitted_rows` leaves samples out)."""
    r = r / np.maximum(1.0 - leverage, np.finfo(float).eps)
    return np.abs(r) > cutoff * float(robust_scale(r))


def _wald_against_noise(c, cov, noise) -> tuple[float, float]:
    """The Wald statistic ``c' cov^-1 c`` and the ``1 - BIAS_LEVEL`` quantile of its
    distribution when ``c`` is noise of covariance ``noise`` only (no bias).

    ``cov`` holds more than the change's own noise (the errors the regression sees), so
    without a bias the statistic is the quadratic form ``n' cov^-1 n`` of that noise,
    whose eigenvalues ``lambda`` (those of ``cov^-1 noise``) lie between 0 and 1: its
    mean is ``sum lambda``, well below the number of columns when the regression's
    errors are larger than the change's noise, and the chi-square quantile of the
    number of columns would let through a bias as large as the gap between them.  The
    quantile is that of ``g chi2(nu)`` with the same mean and variance (Satterthwaite:
    ``g = sum lambda^2 / sum lambda``, ``nu = (sum lambda)^2 / sum lambda^2``).  With
    ``noise`` None (no noise level known), or ``cov`` not positive definite, the
    chi-square quantile of the number of columns.
    """
    import scipy.linalg
    import scipy.stats

    factor = None
    if noise is not None:
        try:
            factor = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            pass
    if factor is None:
        wald = float(c @ np.linalg.lstsq(cov, c, rcond=None)[0])
        return wald, float(scipy.stats.chi2.ppf(1.0 - BIAS_LEVEL, c.size))
    z = scipy.linalg.solve_triangular(factor, c, lower=True)
    half = scipy.linalg.solve_triangular(factor, noise, lower=True)
    whitened = scipy.linalg.solve_triangular(factor, half.T, lower=True)  # L^-1 N L^-T
    mean, square = float(np.trace(whitened)), float(np.sum(whitened * whitened))
    wald = float(z @ z)
    if not mean > 0 or not square > 0:
        return wald, 0.0
    g, nu = square / mean, mean * mean / square
    return wald, float(g * scipy.stats.chi2.ppf(1.0 - BIAS_LEVEL, nu))


def _derivative_operator(t, usable, half_window: int, degree: int):
    """The sparse matrix (m, m) that maps the states of one component to the
    least-squares derivative :func:`_local_fit` gives without a noise scale (the
    ``2 half_window + 1`` usable samples nearest each sample; all samples where fewer
    are usable)."""
    import scipy.sparse

    m, size = usable.size, 2 * int(half_window) + 1
    ok = usable if usable.sum() >= size else np.ones(m, dtype=bool)
    idx = _nearest_usable(ok, size)
    w = _window_weights(t, idx, degree)
    rows = np.repeat(np.arange(m), size)
    return scipy.sparse.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(m, m))


def _window_weights(t, idx, degree):
    """The weights (m, size) that give the derivative at every sample of the
    least-squares polynomial of ``degree`` through the samples ``idx`` (m, size)."""
    v, span = _window_rows(t, idx, degree)
    gram = np.swapaxes(v, 1, 2) @ v
    gram += 1e-12 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(degree + 1)
    return np.linalg.solve(gram, np.swapaxes(v, 1, 2))[:, 1, :] / np.where(span > 0, span, 1.0)


def higher_order_derivative(x, t, half_window, degree: int = 4, mask=None, scale=None):
    """The reference of :func:`unresolved_derivatives`: per component, the derivative of
    the polynomial two degrees higher than ``degree`` over one more sample on each side
    than ``half_window`` (Huber fits with the noise ``scale``, as in
    :func:`local_polynomial_derivative`).  Its truncation error is of two orders
    higher in the sampling interval, so where the sampling resolves the trajectory
    the difference from the lower-order derivative is that derivative's truncation
    error plus noise.  NaN for a component too short for that window.  Returns an
    array like ``x``."""
    x, t = _check(x, t, 2)
    one_d = x.ndim == 1
    x2 = x[:, None] if one_d else x
    m, n = x2.shape
    degree = check_int(degree, "degree", 1)
    half = _half_windows(half_window, n)
    usable = _usable(mask, m, n)
    noise = _noise_scale(scale, n)
    out = np.full((m, n), np.nan)
    for k in range(n):
        size_b = 2 * half[k] + 3
        if m < size_b or degree + 2 >= size_b:
            continue
        ok = usable[:, k] if usable[:, k].sum() >= size_b else np.ones(m, dtype=bool)
        sk = None if noise is None else noise[[k]]
        out[:, k] = _local_fit(x2[:, [k]], t, ok[:, None], [half[k] + 1], degree + 2, sk)[:, 0]
    return out[:, 0] if one_d else out


def unresolved_derivatives(
    x, t, derivative, half_window, degree: int = 4, mask=None, scale=None, cutoff: float = 3.5,
    high=None,
) -> np.ndarray:  # fmt: skip
    """Entries of ``derivative`` (the local polynomial derivative of ``x`` of ``degree``
    over ``half_window`` samples on each side, :func:`local_polynomial_derivative`) that
    the sampling does not resolve: where it differs from the derivative of a polynomial
    two degrees higher over one more sample on each side by more than ``cutoff`` times
    the noise of that difference.

    Where the trajectory is resolved the two derivatives differ by their noise; along
    an excursion only a few samples long (a relaxation jump, a sharp peak) both carry
    a truncation error, and a regression explains such a systematic error with
    spurious terms.  The difference at each sample is divided by the factor by which
    it amplifies the noise of the states (the norm of the difference of the two
    estimators' weights, so that a window widened by a gap of flagged samples is not
    mistaken for an unresolved one), and compared with ``cutoff`` times the larger of
    the state's noise ``scale`` (when given) and the robust scale of these normalised
    differences over the usable entries (on nearly noise-free states the truncation
    error itself sets the scale, and only the excursions where it is gross count).
    Only ratios within a component enter, so the decision does not depend on the
    units of the states or of time.  ``high``: that higher-order derivative
    (:func:`higher_order_derivative`), when already computed.

    Returns a boolean array like ``x`` (m, n).
    """
    x, t = _check(x, t, 2)
    one_d = x.ndim == 1
    x2 = x[:, None] if one_d else x
    m, n = x2.shape
    d = as_float_array(derivative, "derivative", (1, 2))
    if d.size != m * n:
        raise ValueError(f"derivative must have the shape of x {x.shape}; got {d.shape}")
    d = d.reshape(m, n)
    degree = check_int(degree, "degree", 1)
    cutoff = check_positive(cutoff, "cutoff")
    half = _half_windows(half_window, n)
    usable = _usable(mask, m, n)
    noise = _noise_scale(scale, n)
    if high is None:
        high = higher_order_derivative(x2, t, half, degree, usable, noise)
    high = np.asarray(high, dtype=float).reshape(m, n)  # NaN where a component is too short
    out = np.zeros((m, n), dtype=bool)
    for k in range(n):
        size_a, size_b = 2 * half[k] + 1, 2 * half[k] + 3
        if m < size_b or degree + 2 >= size_b:
            continue
        ok = usable[:, k] if usable[:, k].sum() >= size_b else np.ones(m, dtype=bool)
        ok_a = usable[:, k] if usable[:, k].sum() >= size_a else np.ones(m, dtype=bool)
        idx_a, idx_b = _nearest_usable(ok_a, size_a), _nearest_usable(ok, size_b)
        w_a, w_b = _window_weights(t, idx_a, degree), _window_weights(t, idx_b, degree + 2)
        cross = np.sum(w_a * _aligned(idx_a, idx_b, w_b), axis=1)
        factor = np.sqrt(np.maximum((w_a**2).sum(1) + (w_b**2).sum(1) - 2 * cross, 0.0))
        z = (d[:, k] - high[:, k]) / np.where(factor > 0, factor, np.inf)
        level = float(robust_scale(z[usable[:, k]])) if usable[:, k].any() else 0.0
        if noise is not None and np.isfinite(noise[k]):
            level = max(level, float(noise[k]))
        if level > 0:
            out[:, k] = np.abs(z) > cutoff * level
    return out[:, 0] if one_d else out


def _aligned(idx_a, idx_b, w_b):
    """``w_b`` (m, size_b) at the samples ``idx_a`` (m, size_a) of each row (0 where a
    sample of ``idx_a`` is not in that row of ``idx_b``); the rows of both are sorted."""
    offset = (np.arange(idx_a.shape[0]) * (max(idx_a.max(), idx_b.max()) + 1))[:, None]
    flat_b = (idx_b + offset).ravel()
    pos = np.minimum(np.searchsorted(flat_b, (idx_a + offset).ravel()), flat_b.size - 1)
    hit = flat_b[pos] == (idx_a + offset).ravel()
    return np.where(hit, w_b.ravel()[pos], 0.0).reshape(idx_a.shape)


def _half_windows(half_window, n: int) -> np.ndarray:
    """``half_window`` (one int, or one per component) as an int array (n,), checked."""
    half = np.broadcast_to(np.atleast_1d(np.asarray(half_window, dtype=object)), (n,))
    return np.array([check_int(h, "half_window", 1) for h in half])


def _usable(mask, m: int, n: int) -> np.ndarray:
    usable = np.ones((m, n), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if usable.shape != (m, n) and usable.size == m * n:
        usable = usable.reshape(m, n)
    if usable.shape != (m, n):
        raise ValueError(f"mask must have the shape of x {(m, n)}; got {usable.shape}")
    return usable


def local_polynomial_derivative(x, t, half_window=2, degree: int = 4, mask=None, scale=None):
    """Derivative of a least-squares polynomial fitted around every sample.

    For sample ``i`` a polynomial of ``degree`` in relative time is fitted to the
    ``2 half_window + 1`` samples centred on it (the window shifted inside the data at
    the ends) and differentiated at ``t_i``.  With the defaults
    (``half_window = 2, degree = 4``) on uniform samples this is the fourth-order
    central difference: its error is a systematic ``O(dt^4)`` bias that a regression on
    a library would otherwise explain with spurious terms, but it multiplies the noise
    of the states by about ``1 / dt``.  Wider windows average the noise away at the
    price of that bias (on a trajectory sampled at 100 samples per period, a 7-sample
    quartic already puts percent-level errors on its fast excursions);
    ``half_window="auto"`` chooses it per component from the data
    (:func:`choose_half_window`), and a sequence gives one per component.  Entries where
    ``mask`` is False (e.g. the outliers flagged by
    :func:`robust_sindy.selection.temporal_screen`) are left out: the window of a
    sample is then its ``2 half_window + 1`` nearest samples that are not, so an
    outlier is not smeared over its window as it is by :func:`savgol_derivative`, and
    the derivatives next to it keep their order.  ``t`` may be non-uniform.  With
    ``scale`` (the noise level of each component, e.g. the temporal screen's), windows
    wider than the polynomial are fitted by Huber's loss (threshold ``HUBER_C``
    scales), so that an error the screen left unflagged is not spread over them.
    """
    degree = check_int(degree, "degree", 1)
    x = as_float_array(x, "x", (1, 2))
    n = 1 if x.ndim == 1 else x.shape[1]
    if isinstance(half_window, str):
        if half_window != "auto":
            raise ValueError(
                f"half_window must be an int, a sequence or 'auto'; got {half_window!r}"
            )
        half = choose_half_window(x, t, mask, degree, scale=scale)
    else:
        half = _half_windows(half_window, n)
    w = 2 * int(half.max()) + 1
    if degree >= 2 * int(half.min()) + 1:
        raise ValueError(f"degree ({degree}) must be < 2 * half_window + 1 ({2 * half.min() + 1})")
    x, t = _check(x, t, w)
    one_d = x.ndim == 1
    x2 = x[:, None] if one_d else x
    m, n = x2.shape
    usable = _usable(mask, m, n)
    out = _local_fit(x2, t, usable, half, degree, _noise_scale(scale, n))
    return out[:, 0] if one_d else out
