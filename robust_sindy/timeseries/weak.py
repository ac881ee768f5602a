"""The weak (integral) form: the regression's rows as integrals against test functions.

For a test function :math:`\\phi` with compact support inside a trajectory,
integration by parts turns :math:`\\dot x_k = \\Theta(x) \\xi_k` into

.. math::

    -\\int \\phi'(t)\\, x_k(t)\\, dt = \\Big(\\int \\phi(t)\\, \\Theta(x(t))\\, dt\\Big) \\xi_k ,

exactly, whatever the support: no derivative is estimated, and the noise of the states
is averaged over the support.  With quadrature weights on the sample times (product
integration: the samples replaced by local least-squares polynomials, their product
with the test function integrated exactly, which is accurate on irregular times) row
``r`` is ``b_r = -sum_i W'_ri x(t_i)`` and ``G_r = sum_i W_ri Theta(x(t_i))``, and each
equation solves the same Huber + L1 problem on ``(G, b)`` (SPEC §9).

* Test functions: :math:`\\phi(t) = (1 - s^2)^4`, :math:`s = (t - c)/h`, centres every
  ``h / 4`` (each sample lies under about eight of them), supports inside each
  trajectory.
* The half width ``h`` (:func:`support_half_width`), in units of time: the test
  function's spectrum falls to half its peak at the frequency where each state's
  spectrum meets ten times the white-noise floor that the temporal screen measured
  (the narrowest over the states with a signal above their noise): the test functions
  pass every state's band where its signal dominates and average the noise beyond it;
  at least ``MIN_SUPPORT_SAMPLES`` steps, where the quadrature is accurate.  Rescaling
  time rescales ``h``: unit-free.  Every library column carries the faster states'
  signal: a support as wide as the slowest state's band allows would damp that signal
  in the columns below the noise left there, and the errors in the variables would
  bias the coefficients.
* The quadrature's local fits take ``LOCAL_SAMPLES`` samples, or ``WIDE_SAMPLES`` where
  the states' noise outweighs the larger quadrature error of the wider fits, both
  measured on the record (:func:`choose_stencil`).
* Entries the temporal screen flagged enter the integrals by their repaired values; the
  rows whose support holds a flagged entry are the row screen's suspects.

Read more in the user guide: :doc:`/guide/derivatives`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal
import scipy.sparse

from .temporal import TemporalScreening
from .trajectories import Trajectories, gapless_pieces, reading_steps, slices

__all__ = [
    "HALF_AMPLITUDE",
    "LOCAL_DEGREE",
    "LOCAL_SAMPLES",
    "MAX_LEBESGUE",
    "MIN_SUPPORT_SAMPLES",
    "POWER",
    "STENCIL_EVIDENCE",
    "WIDE_SAMPLES",
    "Stencil",
    "Support",
    "WeakRows",
    "choose_stencil",
    "support_half_width",
    "weak_rows",
    "weight_functions",
]

#: The exponent ``p`` of the test functions ``(1 - s^2)^p``.
POWER = 4
#: Where the spectrum of ``(1 - s^2)^4`` on ``[-1, 1]`` falls to half its peak (in
#: ``omega h``).
HALF_AMPLITUDE = 3.798
#: A state's spectrum meets its noise at this many times the white-noise floor.
NOISE_FLOOR_FACTOR = 10.0
#: The support holds at least this many samples on each side of its centre: the product
#: integration's local fits are then accurate to well below the noise of nearly
#: noise-free states (tested on Lorenz, uniform and irregular times).
MIN_SUPPORT_SAMPLES = 15
#: The product integration replaces the samples around each interval by a polynomial
#: of degree ``LOCAL_DEGREE`` fitted by least squares to the ``LOCAL_SAMPLES`` samples
#: around it (half on each side, inside the record's gapless piece).  A least-squares fit
#: over more samples than it has coefficients does not swing where sample times cluster,
#: as an interpolating cubic through four of them does (on uniformly random times it
#: amplified the noise hundreds of times, and a straight line in its place cost up to 10 %
#: of an integral on a chaotic record).
LOCAL_SAMPLES, LOCAL_DEGREE = 8, 4
#: The wider stencil of the product integration: its local fits average more samples, so
#: that at irregular times a long interval no longer rests on the few samples around it
#: (a row's noise variance about 0.70 of the narrow stencil's at uniformly random times,
#: about 0.99 at uniform steps), at the cost of a larger quadrature error.  Taken where
#: the states' noise outweighs that error (:func:`choose_stencil`).
WIDE_SAMPLES = 16
#: The wider stencil is taken where the noise variance it removes exceeds the estimate of
#: the squared quadrature error it adds by this many standard errors of that estimate.
STENCIL_EVIDENCE = 2.0
#: The local fit may amplify the samples' noise at most this many times on its interval
#: (its Lebesgue constant there: about 1.3 for uniform samples); where clustered sample
#: times give it more, the degree is lowered until it does not (a straight line last).
MAX_LEBESGUE = 4.0
#: Centres of consecutive test functions are this fraction of ``h`` apart (or closer,
#: down to ``MIN_SPACING``, where the records are short for the library).
SPACING, MIN_SPACING = 0.25, 0.0625


#: Gauss-Legendre nodes and weights on [0, 1] for the product integration (exact for
#: the test function, a polynomial of degree 2 POWER on its support, times the local
#: polynomial).
_NODES, _NODE_WEIGHTS = np.polynomial.legendre.leggauss(POWER + LOCAL_DEGREE // 2 + 1)
_NODES, _NODE_WEIGHTS = (_NODES + 1.0) / 2.0, _NODE_WEIGHTS / 2.0


def _bump(s: np.ndarray, h: float):
    """The test function ``(1 - s^2)^p`` and its derivative in time at ``s`` (|s| <= 1)."""
    base = 1.0 - s**2
    return base**POWER, -2.0 * POWER * s * base ** (POWER - 1) / h


def _local_fits(t: np.ndarray, piece: slice, samples: int = LOCAL_SAMPLES):
    """For each interval ``[t_j, t_j+1]`` of the gapless ``piece`` of the record: the
    stencil (J x w, sample indices: the ``samples`` around the interval, shifted
    inside the piece at its ends), the map (J x (d + 1) x w) from the stencil's values to
    the coefficients of the local least-squares polynomial in ``(tau - t_j) / span_j``,
    and ``span`` (J,), the stencil's time span.  The degree is ``LOCAL_DEGREE``, lowered
    per interval where the fit's Lebesgue constant on the interval exceeds
    ``MAX_LEBESGUE`` (its missing coefficients are zero)."""
    lo, hi = piece.start, piece.stop
    width = min(samples, hi - lo)
    j = np.arange(lo, hi - 1)
    start = np.clip(j - (width // 2 - 1), lo, hi - width)
    stencil = start[:, None] + np.arange(width)[None, :]
    ts = t[stencil]
    span = ts[:, -1] - ts[:, 0]
    s = (ts - t[j][:, None]) / span[:, None]
    inside = (t[j + 1] - t[j])[:, None] / span[:, None] * _NODES[None, :]  # (J, g)
    top = min(LOCAL_DEGREE, width - 1)
    fits = np.zeros((j.size, top + 1, width))
    settled = np.zeros(j.size, dtype=bool)
    for degree in range(top, 0, -1):
        fit = np.linalg.pinv(s[..., None] ** np.arange(degree + 1))  # (J, d + 1, w)
        lebesgue = np.abs((inside[..., None] ** np.arange(degree + 1)) @ fit).sum(axis=-1)
        take = ~settled & ((lebesgue.max(axis=-1) <= MAX_LEBESGUE) | (degree == 1))
        fits[take, : degree + 1] = fit[take]
        settled |= take
    return stencil, fits, span


def weight_functions(
    t: np.ndarray,
    h: float,
    spacing: float = SPACING,
    samples: int = LOCAL_SAMPLES,
    cut: np.ndarray | None = None,
):
    """``(phi, dphi, centres)``: the quadrature weights (arrays K x m) of the integrals
    of the test functions and of their time derivatives against values sampled at ``t``,
    and the centres (K,), every ``spacing * h`` from ``t[0] + h`` to ``t[-1] - h``
    (K = 0 when the record is shorter than ``2 h``); in a record with gaps
    (:func:`~robust_sindy.timeseries.trajectories.gapless_pieces`), in each piece
    between them.  Samples ``cut`` (a mask) lie under no test function: they split the
    record as a gap does.

    Product integration: the sampled values are taken as the local least-squares
    polynomial around each interval (``samples`` samples, by default
    ``LOCAL_SAMPLES``; degree ``LOCAL_DEGREE``), and its product with the (polynomial)
    test function is integrated exactly (Gauss-Legendre), so that irregular sample times
    cost accuracy only through the values' own smoothness.  ``phi @ v`` approximates
    ``int phi(t) v(t) dt``.
    """
    m = t.size
    rows = []  # (centre, the piece's local fits)
    for piece in gapless_pieces(t, cut):  # no support reaches across a gap in the record
        lo, hi = t[piece][0] + h, t[piece][-1] - h
        if hi >= lo and piece.stop - piece.start >= 2:
            count = int(np.floor((hi - lo) / (spacing * h) + 1e-9)) + 1
            fits = _local_fits(t, piece, samples)
            rows.extend((c, piece.start, fits) for c in np.linspace(lo, hi, count))
    centres = np.array([c for c, _, _ in rows])
    phi, dphi = np.zeros((len(rows), m)), np.zeros((len(rows), m))
    for r, (c, offset, (stencils, fits, spans)) in enumerate(rows):
        # The support's intervals, inside the piece (its ends may round past them).
        first = max(int(np.searchsorted(t, c - h, side="right")) - 1, offset)
        last = min(int(np.searchsorted(t, c + h, side="left")), offset + spans.size)
        a = np.maximum(t[first:last], c - h)
        b = np.minimum(t[first + 1 : last + 1], c + h)
        nodes = a[:, None] + (b - a)[:, None] * _NODES[None, :]
        weights = (b - a)[:, None] * _NODE_WEIGHTS[None, :]
        at = slice(first - offset, last - offset)  # the intervals' rows in the piece's fits
        local = (nodes - t[first:last, None]) / spans[at, None]
        powers = local[..., None] ** np.arange(fits.shape[1])  # (J, g, d + 1)
        basis = powers @ fits[at]  # (J, g, w): the samples' shares at the nodes
        value, slope = _bump((nodes - c) / h, h)
        stencil = stencils[at]
        for out, f in ((phi, value), (dphi, slope)):
            shares = np.einsum("jg,jgq->jq", f * weights, basis)
            np.add.at(out[r], stencil.ravel(), shares.ravel())
    return phi, dphi, centres


def _corner(x: np.ndarray, t: np.ndarray, sigma: float, skip=None) -> float | None:
    """The highest frequency at which the spectrum of ``x`` (Welch's estimate on a
    uniform grid of the median step) exceeds ``NOISE_FLOOR_FACTOR`` times the floor of
    white noise of scale ``sigma``; None where it never does (no signal above the
    noise: nothing for the test functions to resolve).  ``skip`` (a mask of the
    samples): values that are no readings (fills far from any); Welch's segments over
    them are left out of the average (all are kept where every segment holds one)."""
    dt = float(np.median(np.diff(t)))
    grid = t[0] + dt * np.arange(round((t[-1] - t[0]) / dt) + 1)
    values = np.interp(grid, t, x)
    nperseg = min(256, grid.size)
    if skip is None or not np.any(skip):
        f, pxx = scipy.signal.welch(values - values.mean(), fs=1.0 / dt, nperseg=nperseg)
    else:
        f, _, sxx = scipy.signal.spectrogram(
            values - values.mean(), fs=1.0 / dt, window="hann", nperseg=nperseg,
            noverlap=nperseg // 2, detrend="constant", scaling="density", mode="psd",
        )  # fmt: skip
        bad = np.interp(grid, t, np.asarray(skip, dtype=float)) > 0
        hop = nperseg - nperseg // 2
        starts = hop * np.arange(sxx.shape[1])
        clean = np.array([not bad[a : a + nperseg].any() for a in starts])
        pxx = sxx[:, clean].mean(axis=1) if clean.any() else sxx.mean(axis=1)
    floor = 2.0 * sigma**2 * dt
    above = np.flatnonzero(pxx[1:] > NOISE_FLOOR_FACTOR * floor) + 1
    return float(f[above.max()]) if above.size else None


@dataclass(frozen=True)
class Support:
    """Outcome of :func:`support_half_width`.

    Attributes
    ----------
    half_width : float
        The test functions' half width (time units).
    noise_limited : bool
        Whether the states' noise asked for wider supports than the quadrature needs
        (``MIN_SUPPORT_SAMPLES`` steps).
    samples : float
        The half width in median steps.
    """

    half_width: float
    noise_limited: bool
    samples: float


def support_half_width(
    data: Trajectories, temporal: TemporalScreening, skip: np.ndarray | None = None
) -> Support:
    """The test functions' half width (time units; see the module docstring), at least
    ``MIN_SUPPORT_SAMPLES`` median steps of every trajectory, and of the readings of
    every state (a state read every few samples: its median interval between readings).
    Each state's spectrum leaves out the stretches ``skip`` (m, n) of that state: its
    fills in runs of missing readings too long to be signal."""
    states = [temporal.repaired[seg] for seg in data.segments]
    skips = None if skip is None else [skip[seg] for seg in data.segments]
    widths = []  # per state with a signal above its noise, the half width it asks for
    steps, slowest = [], []
    for i, (x, t, raw) in enumerate(zip(states, data.t, data.x, strict=True)):
        if x.shape[0] < 8:
            continue
        steps.append(float(np.median(np.diff(t))))
        # A state read every few samples (a slower sensor) is integrated from its own
        # readings: the quadrature needs as many of them under a test function.
        slowest.append(float(reading_steps(t, np.isnan(raw)).max(initial=steps[-1])))
        for k in range(x.shape[1]):
            sigma = float(temporal.scale[k])
            if not np.isfinite(sigma) or sigma <= 0 or np.ptp(x[:, k]) == 0:
                continue
            corner = _corner(x[:, k], t, sigma, None if skips is None else skips[i][:, k])
            if corner is not None:
                widths.append(HALF_AMPLITUDE / (2.0 * np.pi * corner))
    if not steps:
        raise ValueError("the weak form needs trajectories of at least 8 samples")
    least = MIN_SUPPORT_SAMPLES * max(slowest)
    h = min(widths, default=0.0)
    width = max(h, least)
    return Support(width, h > least, width / max(steps))


@dataclass(frozen=True)
class Stencil:
    """Outcome of :func:`choose_stencil`.

    Attributes
    ----------
    samples : int
        The local fits' samples: ``LOCAL_SAMPLES`` or ``WIDE_SAMPLES``.
    ratio : float
        Over the states, the largest of the squared quadrature error the wider stencil
        adds to the targets (estimated, plus ``STENCIL_EVIDENCE`` standard errors of the
        estimate) over the noise variance it removes from them: the wider stencil is
        taken where it is below 1 (``inf`` where a state's noise is not measured, ``nan``
        where no choice was made).
    """

    samples: int
    ratio: float


@dataclass(frozen=True)
class WeakRows:
    """Outcome of :func:`weak_rows`.

    Attributes
    ----------
    G : ndarray (K, p)
        The library integrated against the test functions.
    b : ndarray (K, n)
        Minus the states integrated against the test functions' derivatives.
    half_width : float
        The test functions' half width ``h`` (time units).
    segments : list of slice
        Each trajectory's rows.
    support : list of ndarray of bool (K_i, m_i)
        Per trajectory, the samples under each test function.
    weights : list of ndarray (K_i, m_i)
        Per trajectory, the test functions times the quadrature weights (``phi``).
    slopes : list of ndarray (K_i, m_i)
        Per trajectory, the test functions' derivatives times the quadrature weights
        (``b = -slopes @ states``).
    stencil : Stencil
        The quadrature's local fits (:func:`choose_stencil`).
    """

    G: np.ndarray
    b: np.ndarray
    half_width: float
    segments: list
    support: list
    weights: list
    slopes: list
    stencil: Stencil = Stencil(LOCAL_SAMPLES, float("nan"))

    @property
    def n_rows(self) -> int:
        return int(self.G.shape[0])

    def touched(self, entry_flags: np.ndarray, data: Trajectories) -> np.ndarray:
        """Rows whose support holds a sample with a flagged entry (``entry_flags`` m x n)."""
        out = []
        for seg, sup in zip(data.segments, self.support, strict=True):
            out.append(sup.astype(float) @ entry_flags[seg].any(axis=1).astype(float) > 0)
        return np.concatenate(out) if out else np.zeros(0, dtype=bool)

    def target_noise(self) -> scipy.sparse.csr_array:
        """How the samples' noise enters the targets: ``b``'s noise is this sparse
        matrix (rows x samples, block diagonal over the trajectories) times the
        samples' noise, so neighbouring rows, which integrate the same samples, share
        it (the row screen studentises by it)."""
        return scipy.sparse.block_diag(
            [scipy.sparse.csr_array(d) for d in self.slopes], format="csr"
        )

    def effective_rows(self) -> float:
        """How many independent rows the test functions' overlap leaves: the
        participation ratio ``tr(C)^2 / tr(C^2)`` of ``C = D D^T``, the covariance of the
        targets' noise for white noise of the samples (``D``, :meth:`target_noise`).
        ``K`` for disjoint supports of equal weight; for the test functions of
        :func:`weight_functions`, about three per support width (``2 h``) of record,
        however closely their centres are placed.  Unchanged by the units of time."""
        d = self.target_noise()
        c = d @ d.T
        total = float(c.diagonal().sum())
        return total**2 / float(c.multiply(c).sum()) if total > 0 else 0.0

    def covered(self, keep: np.ndarray) -> np.ndarray:
        """Samples under at least one of the rows ``keep`` (bool, K)."""
        out = []
        for rows, sup in zip(self.segments, self.support, strict=True):
            out.append(keep[rows].astype(float) @ sup.astype(float) > 0)
        return np.concatenate(out) if out else np.zeros(0, dtype=bool)

    def noise(self, noise_columns, data: Trajectories):
        """The noise of the weak rows' library columns, per state, from that of the
        samples (``noise_columns``, a
        :class:`~robust_sindy.selection.bias.LibraryNoise`): noise at different samples
        is independent, so a row's has variance ``sum_i (w_i phi_r(t_i))^2 N_i^2``; it
        is taken as ``sqrt(sum_i (w_i phi_r)^2)`` times the ``(w_i phi_r)^2``-weighted
        mean of the samples' noise columns (exact where those are constant over the
        support, and linear in them, as the strong form's are)."""
        if noise_columns is None:
            return None

        def rows_of(a):
            rows = []
            for seg, w in zip(data.segments, self.weights, strict=True):
                w2 = w**2
                total = np.maximum(w2.sum(axis=1, keepdims=True), np.finfo(float).tiny)
                rows.append(np.sqrt(total) * (w2 @ a[seg]) / total)
            return np.vstack(rows)

        return noise_columns.map_rows(rows_of)


def choose_stencil(ts, states, scale, h: float, spacing: float = SPACING, cuts=None):
    """The product integration's stencil for the records ``ts`` (sample times per
    trajectory) and ``states`` (their values, one (m_i, n) array per trajectory), whose
    noise levels are ``scale`` (n,), and the weights of the chosen one (a list of
    ``(phi, dphi)`` per trajectory, as :func:`weight_functions` gives them).

    Per state ``k``, the targets of both stencils (``-dphi @ x_k``) differ by the extra
    quadrature error of the wider one plus noise of known variance: the sum of their
    squared differences, less that variance (``sigma_k^2 ||D_n - D_w||_F^2``), estimates
    the squared error the wider stencil adds; the noise variance it removes is
    ``sigma_k^2 (||D_n||_F^2 - ||D_w||_F^2)``.  The wider stencil is taken where, for
    every state, the noise it removes exceeds the error it adds by ``STENCIL_EVIDENCE``
    standard errors of the estimate (for Gaussian noise, ``sigma_k^2 sqrt(2) ||C||_F``
    with ``C = (D_n - D_w)(D_n - D_w)^T``).  The library's rows need no check of their
    own: along the trajectory the true terms sum to the derivatives, whose integrals
    against ``phi`` carry the same band as the targets'.  Both sides scale as the
    squares of the states and do not depend on the units of time: unit-free.
    ``cuts``: per trajectory, the samples under no test function (or None).
    """
    scale = np.asarray(scale, dtype=float)
    n = scale.size
    cuts = [None] * len(ts) if cuts is None else cuts
    narrow = [weight_functions(t, h, spacing, cut=c) for t, c in zip(ts, cuts, strict=True)]
    wide = [
        weight_functions(t, h, spacing, WIDE_SAMPLES, cut=c) for t, c in zip(ts, cuts, strict=True)
    ]
    added, noise, variance, removed = np.zeros(n), 0.0, 0.0, 0.0
    for x, (_, dn, _), (_, dw, _) in zip(states, narrow, wide, strict=True):
        diff = scipy.sparse.csr_array(dn - dw)
        added += np.sum((diff @ x) ** 2, axis=0)
        noise += float(diff.multiply(diff).sum())
        cross = diff @ diff.T
        variance += 2.0 * float(cross.multiply(cross).sum())
        removed += float(np.sum(dn**2) - np.sum(dw**2))
    s2 = scale**2
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (added - s2 * noise + STENCIL_EVIDENCE * s2 * np.sqrt(variance)) / (s2 * removed)
    judged = np.isfinite(ratio) & (removed > 0)  # a state without a measured noise: inf
    worst = float(np.max(np.where(judged, ratio, np.inf))) if n else np.inf
    if worst < 1.0:
        return Stencil(WIDE_SAMPLES, worst), [(phi, dphi) for phi, dphi, _ in wide]
    return Stencil(LOCAL_SAMPLES, worst), [(phi, dphi) for phi, dphi, _ in narrow]


def weak_rows(
    data: Trajectories,
    states: np.ndarray,
    theta: np.ndarray,
    h: float,
    min_rows: int = 0,
    noise=None,
    cut: np.ndarray | None = None,
) -> WeakRows:
    """The weak form of every trajectory: ``states`` (m, n) and the library matrix
    ``theta`` (m, p) of all samples (stacked as in ``data``) integrated against test
    functions of half width ``h``, their centres ``SPACING * h`` apart, or closer (down to
    ``MIN_SPACING * h``) where that gives fewer than ``min_rows`` rows in all.  With the
    states' noise levels ``noise`` (n,), the quadrature's stencil is chosen from them
    (:func:`choose_stencil`); without, it is ``LOCAL_SAMPLES``.  ``cut`` (m,): samples
    under no test function (readings too far to fill,
    :func:`~robust_sindy.timeseries.missing.far_from_readings`)."""
    cuts = [None if cut is None else cut[seg] for seg in data.segments]
    room = sum(max(t[-1] - t[0] - 2 * h, 0.0) for t in data.t)
    spacing = SPACING
    if min_rows > 0 and room > 0:
        spacing = float(np.clip(room / (h * min_rows), MIN_SPACING, SPACING))
    if noise is None:
        stencil = Stencil(LOCAL_SAMPLES, float("nan"))
        weights_of = [
            weight_functions(t, h, spacing, cut=c)[:2] for t, c in zip(data.t, cuts, strict=True)
        ]
    else:
        stencil, weights_of = choose_stencil(
            data.t, [states[seg] for seg in data.segments], noise, h, spacing, cuts
        )
    Gs, bs, supports, weights, slopes, counts = [], [], [], [], [], []
    for seg, (phi, dphi) in zip(data.segments, weights_of, strict=True):
        Gs.append(phi @ theta[seg])
        bs.append(-dphi @ states[seg])
        supports.append(phi != 0)
        weights.append(phi)
        slopes.append(dphi)
        counts.append(phi.shape[0])
    G, b = np.vstack(Gs), np.vstack(bs)
    return WeakRows(G, b, float(h), slices(counts), supports, weights, slopes, stencil)
