"""Errors in the variables in the weak form: candidates scored under the noise their own
terms carry.

In the weak form every row integrates the measured states against a test function:
``b_r = -sum_i s_ri x(t_i)`` and ``G_rj = sum_i w_ri theta_j(x(t_i))``.  The states'
noise ``e`` enters both, and the residual of coefficients ``xi`` carries, to first
order,

    eta(xi) = -S e_k - sum_l W diag(g_l) e_l,    g_l = sum_j xi_j d theta_j / d x_l,

(``S``, ``W`` the test functions' slopes and weights at the samples, ``g_l`` the
candidate model's derivative with respect to state ``l`` at every sample).  Its
covariance ``C(xi) = D(xi) D(xi)^T`` depends on the candidate: a model with large
coefficients on noisy columns (a small difference of large terms, such as
``x' = 36 (y - x)`` where ``x`` follows ``y`` closely) has residuals far noisier than
the states' own noise, and a criterion that reads every candidate's residuals on one
scale prefers a wrong model with small coefficients, or a dense one whose extra terms
fit part of the columns' noise.

:func:`gls_score` fits a support by generalised least squares under ``C(xi)``,
updating ``C`` from the fit (the approximate maximum-likelihood estimator of
errors-in-variables regression, which is consistent where least squares is not), and
returns its chi-square ``r^T C^{-1} r``: about the number of rows for a support that
holds the true model, more where the support misses part of it, whatever the scale of
its coefficients.  :func:`rescore_supports` scores the selection's candidates so, each
with ``log(rows)`` per term (whitened rows are independent), and reports the
equations where another candidate (or one a stepwise search under the same score
reaches from the best of them, adding a pair of terms together where no single move
lowers the score: ``x' = 36 (y - x)`` again, where either term alone explains little
of it) scores better than the chosen support by more than
:data:`~robust_sindy.selection.criteria.MIN_BIC_MARGIN`, where the states' noise
explains that candidate's residuals (:data:`NOISE_EXPLAINS`).

Units: everything is in the standardised problem's units (columns over
``theta_scale``, targets over ``y_scale``), where the noise of the columns is
:func:`~robust_sindy.selection.bias.noise_columns`'; the chi-square does not depend on
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse

from ..core.threads import map_threads
from .bias import LibraryNoise
from .choice import Fitted, huber_method
from .criteria import MIN_BIC_MARGIN, score_margin
from .problem import Problem
from .refit import refit_column

__all__ = [
    "GLS_ROUNDS",
    "KEEP_EVIDENCE",
    "Rescored",
    "RowNoise",
    "displacement_refused",
    "dropped_evidence",
    "gls_score",
    "rescore_supports",
    "rescore_weak",
    "search_penalty",
]

_PBTRF, _TBTRS = scipy.linalg.get_lapack_funcs(("pbtrf", "tbtrs"), dtype=np.float64)

#: Rounds of the generalised least squares, each with the covariance of the last fit.
GLS_ROUNDS = 4
#: The stepwise search scores this many of its best-ranked moves under their own
#: covariance (the ranking uses the current fit's).
MOVES_SCORED = 3
#: The pair moves of the stepwise search rank pairs among at most this many candidate
#: terms (those whose single addition lowers the chi-square most), a cost bound: every
#: pair's fall needs the candidates' products with each other (rows x terms^2).
PAIR_TERMS = 400
#: A support replaces the chosen one only where the states' noise explains its
#: residuals: its chi-square is at most this many times the number of rows (about 1
#: when it does; far more where the residuals hold what the noise model leaves out,
#: such as the quadrature's error on nearly noise-free states, which would make every
#: term look significant).
NOISE_EXPLAINS = 2.0
#: How much a term the final selection dropped from the support the rescoring chose may
#: lower the score when put back before the drop goes against the data: 10 is "very
#: strong" evidence on the scale of Kass and Raftery (twice the log of the Bayes factor).
KEEP_EVIDENCE = 10.0


@dataclass
class RowNoise:
    """How the samples' noise enters the weak rows (see the module docstring).

    Attributes
    ----------
    weights, slopes : sparse arrays (K, m)
        The test functions and their derivatives times the quadrature weights at the
        samples, for the rows kept (block diagonal over the trajectories).
    columns : LibraryNoise
        The noise of the standardised library columns at every sample per state
        (``sigma_l d theta / d x_l / theta_scale``).
    target : ndarray (n,)
        Each state's noise over its target's scale (``sigma_k / y_scale_k``).
    """

    weights: scipy.sparse.csr_array
    slopes: scipy.sparse.csr_array
    columns: LibraryNoise
    target: np.ndarray
    _products: list | None = field(default=None, repr=False)

    @classmethod
    def of_weak(cls, weak, keep, columns: LibraryNoise, target) -> RowNoise:
        """From the weak rows (a :class:`~robust_sindy.timeseries.weak.WeakRows`), the
        rows ``keep`` (bool, K), the samples' column noise and the targets' noise."""

        def stacked(parts):
            whole = scipy.sparse.block_diag(
                [scipy.sparse.csr_array(a) for a in parts], format="csr"
            )
            return scipy.sparse.csr_array(whole[np.flatnonzero(keep)])

        return cls(stacked(weak.weights), stacked(weak.slopes), columns, np.asarray(target))

    def factor(self, xi: np.ndarray, k: int) -> scipy.sparse.csr_array:
        """``D(xi)`` (K, m n) for equation ``k``: the residual's noise is ``D e`` for
        independent ``e`` of unit variance, one block of samples per state."""
        blocks = []
        # Per state l, g_l (m,): the noise it puts, through xi, in the model's value.
        for state, g in enumerate(self.columns.per_state(xi)):
            block = -(self.weights @ scipy.sparse.diags_array(g))
            if state == k:
                block = block - self.target[k] * self.slopes
            blocks.append(block)
        return scipy.sparse.hstack(blocks, format="csr")

    def covariance(self, xi: np.ndarray, k: int) -> scipy.sparse.csr_array:
        """``C(xi) = D(xi) D(xi)^T`` (K, K), sparse: rows share noise only where their
        test functions share samples."""
        d = self.factor(xi, k)
        return (d @ d.T).tocsr()

    def prepare(self) -> tuple:
        """The products of the test functions :meth:`band` reads, formed on the first
        call (:func:`_band_products`)."""
        if self._products is None:
            self._products = _band_products(self.weights, self.slopes)
        return self._products

    def band(self, xi: np.ndarray, k: int) -> np.ndarray:
        """The lower band of :meth:`covariance` (``out[d, j] = C[j + d, j]``, LAPACK's
        banded storage), from products of the test functions formed once:
        ``C = W diag(sum_l g_l^2) W^T + t_k (W diag(g_k) S^T + S diag(g_k) W^T) +
        t_k^2 S S^T``."""
        ww, ws, ss, at = self.prepare()
        q = np.zeros(self.weights.shape[1])
        own = np.zeros_like(q)
        for state, g in self.columns.reaching(xi):  # the others' g is zero
            q += g * g
            if state == k:
                own = g
        t = float(self.target[k])
        out = np.zeros(at[0])
        out[at[1]] = ww @ q + t * (ws @ own) + t * t * ss
        return out.reshape(at[2])


def _band_products(w, s):
    """The rows' elementwise products ``W_{j+d} W_j``, ``W_{j+d} S_j + S_{j+d} W_j``
    (sparse, stacked over the offsets ``d`` of the band) and ``S_{j+d} . S_j``, with
    where each row goes in the band's storage (its size, the flat positions, its
    shape)."""
    pattern = (abs(w) + abs(s)).astype(bool).astype(float)
    overlap = (pattern @ pattern.T).tocoo()
    width = int(np.max(np.abs(overlap.row - overlap.col))) if overlap.nnz else 0
    rows = w.shape[0]
    ww, ws, ss, flat = [], [], [], []
    for d in range(width + 1):
        hi_w, lo_w = w[d:], w[: rows - d]
        hi_s, lo_s = s[d:], s[: rows - d]
        ww.append(scipy.sparse.csr_array(hi_w.multiply(lo_w)))
        ws.append(scipy.sparse.csr_array(hi_w.multiply(lo_s) + hi_s.multiply(lo_w)))
        ss.append(np.asarray(hi_s.multiply(lo_s).sum(axis=1)).ravel())
        flat.append(d * rows + np.arange(rows - d))
    shape = (width + 1, rows)
    at = ((width + 1) * rows, np.concatenate(flat), shape)
    return (
        scipy.sparse.vstack(ww, format="csr"),
        scipy.sparse.vstack(ws, format="csr"),
        np.concatenate(ss),
        at,
    )


def _whitener(band: np.ndarray):
    """A function applying ``L^{-1}`` (``C = L L^T``, ``band`` the lower band of ``C``:
    neighbouring rows share samples) to a matrix of rows; None where ``C`` is not
    positive definite."""
    band = band.copy()
    if not np.all(np.isfinite(band)) or not band[0].max() > 0:
        return None
    band[0] += np.finfo(float).eps * band[0].max()  # rounding of nearly shared rows
    factor, info = _PBTRF(band, lower=1)  # LAPACK's banded Cholesky (scipy's wrapper)
    if info != 0:
        return None

    def apply(a):
        rows = np.asarray(a, dtype=float).reshape(band.shape[1], -1)
        out, info = _TBTRS(factor, rows, uplo="L")
        return out.reshape(np.shape(a)) if info == 0 else np.full(np.shape(a), np.nan)

    return apply


def gls_score(g, y, support, start, noise: RowNoise, k: int, rounds: int = GLS_ROUNDS):
    """Chi-square of the support ``support`` (bool, p) of equation ``k`` fitted by
    generalised least squares under the noise its own coefficients carry (``g`` (K, p),
    ``y`` (K,), standardised; ``start`` (p,) the first coefficients), and the fitted
    coefficients (p,); ``(inf, start)`` where the covariance is singular."""
    on = np.flatnonzero(support)
    xi = np.zeros(g.shape[1])
    xi[on] = start[on]
    chi2 = np.inf
    for _ in range(rounds):
        white = _whitener(noise.band(xi, k))
        if white is None:
            return np.inf, xi
        both = white(np.column_stack([g[:, on], y]))
        gw, yw = both[:, :-1], both[:, -1]
        sol = np.linalg.lstsq(gw, yw, rcond=None)[0] if on.size else np.zeros(0)
        r = yw - gw @ sol
        chi2 = float(r @ r)
        moved = np.max(np.abs(sol - xi[on]), initial=0.0) > 1e-8 * max(
            np.max(np.abs(sol), initial=0.0), np.finfo(float).tiny
        )
        xi = np.zeros(g.shape[1])
        xi[on] = sol
        if not moved:
            break
    return chi2, xi


def _added_chi2(gw, yw, support) -> list[tuple[float, int]]:
    """``(chi-square, j)`` of the least-squares fit of ``yw`` on the columns of ``gw`` in
    ``support`` and the column ``j``, for every column ``j`` outside it that is not
    zero: from one factorisation of the support's columns, the residual ``r`` and each
    candidate's part ``c`` orthogonal to them, ``|r - c (c^T r) / |c|^2|^2`` (the
    support's directions below the pseudo-inverse's default cut left out, as
    ``numpy.linalg.lstsq`` does; a candidate whose orthogonal part is below that cut
    adds nothing)."""
    rows = gw.shape[0]
    cand = np.flatnonzero(~support & np.any(gw != 0, axis=0))
    if not cand.size:
        return []
    base = gw[:, support]
    cut = np.finfo(float).eps * max(rows, base.shape[1] + 1)
    r, c = yw, gw[:, cand]
    norms = np.linalg.norm(c, axis=0)  # the candidates' own, before the projection
    top = 0.0
    if base.shape[1]:
        u, sv, _ = np.linalg.svd(base, full_matrices=False)
        top = float(sv[0]) if sv.size else 0.0
        u = u[:, sv > cut * top]
        r = yw - u @ (u.T @ yw)
        c = c - u @ (u.T @ c)
    norm2 = np.einsum("ij,ij->j", c, c)
    scale = np.maximum(top, norms)
    step = np.zeros(cand.size)
    ok = np.sqrt(norm2) > cut * scale
    step[ok] = (c[:, ok].T @ r) / norm2[ok]
    left = r[:, None] - c * step  # each candidate's residual, formed (no cancellation)
    chi2 = np.einsum("ij,ij->j", left, left)
    return [(float(v), int(j)) for v, j in zip(chi2, cand, strict=True)]


def _added_pairs(
    gw, yw, support, count: int, among=None
) -> tuple[list[tuple[float, int, int]], int]:
    """The ``count`` pairs of columns outside ``support`` whose joint addition lowers the
    least-squares chi-square of ``yw`` on ``gw[:, support]`` most, as ``(chi-square, j,
    l)``, and the number of pairs ranked.  With ``c`` the candidates' parts orthogonal to
    the support's columns, ``r`` the residual, ``s = c^T r`` and ``h = c^T c``, adding
    ``{j, l}`` removes ``s_J^T h_JJ^{-1} s_J``; pairs whose 2 x 2 block is singular to
    rounding (a column that repeats another) are not ranked.  ``among`` (indices), if
    given, limits the candidates to those columns."""
    cand = np.flatnonzero(~support & np.any(gw != 0, axis=0))
    if among is not None:
        cand = np.intersect1d(cand, among)
    if cand.size < 2:
        return [], 0
    r, c = yw, gw[:, cand]
    base = gw[:, support]
    if base.shape[1]:
        u, sv, _ = np.linalg.svd(base, full_matrices=False)
        cut = np.finfo(float).eps * max(gw.shape[0], base.shape[1] + 1)
        u = u[:, sv > cut * sv[0]]
        r = yw - u @ (u.T @ yw)
        c = c - u @ (u.T @ c)
    s, h = c.T @ r, c.T @ c
    d = np.diag(h)
    a, b = np.triu_indices(cand.size, 1)
    det = d[a] * d[b] - h[a, b] ** 2
    ok = det > np.sqrt(np.finfo(float).eps) * d[a] * d[b]
    fall = np.full(a.size, -np.inf)
    fall[ok] = (
        d[b][ok] * s[a][ok] ** 2 - 2 * h[a, b][ok] * s[a][ok] * s[b][ok] + d[a][ok] * s[b][ok] ** 2
    ) / det[ok]
    rr = float(r @ r)
    best = np.argsort(-fall)[:count]
    return [(rr - fall[i], int(cand[a[i]]), int(cand[b[i]])) for i in best if ok[i]], int(a.size)


def _stepwise(g, y, key, score, noise: RowNoise, k: int, penalty: float, memo, steps: int = 40):
    """From the support ``key`` (bytes of a bool array) with score ``score``: add or drop
    the one term that lowers the score most, or, where no single move does, add the
    pair of terms that does (:func:`_added_pairs`, charged ``2 log`` of the pairs
    ranked), until nothing does (``steps`` moves at most).
    Every drop is scored under its own covariance (:func:`gls_score`, from the current
    fit): dropping a term the others imitated raises the remaining coefficients, and
    with them the noise they carry, which a ranking under the current covariance does
    not see.  Additions are ranked under the current covariance (one whitening for
    all), the :data:`MOVES_SCORED` best then scored under their own.  ``memo`` holds
    the supports already fitted (bytes: chi-square, coefficients)."""

    def fitted(trial, start):
        key = trial.tobytes()
        if key not in memo:
            memo[key] = gls_score(g, y, trial, start, noise, k)
        return memo[key]

    support = np.frombuffer(key, dtype=bool).copy()
    xi = np.zeros(g.shape[1])
    if support.any():
        _, xi = fitted(support, xi)
    for _ in range(steps):
        white = _whitener(noise.band(xi, k))
        if white is None:
            break
        gw, yw = white(g), white(y)
        ranked = _added_chi2(gw, yw, support)
        moves = [j for _, j in sorted(ranked)[:MOVES_SCORED]]
        if support.sum() > 1:
            moves += np.flatnonzero(support).tolist()
        best = None
        for j in moves:
            trial = support.copy()
            trial[j] = not trial[j]
            chi2, new_xi = fitted(trial, xi)
            new_score = chi2 + penalty * int(trial.sum())
            if new_score < score and (best is None or new_score < best[2]):
                best = (trial, new_xi, new_score)
        if best is None:
            # No single move lowers the score: a pair of terms added together, where
            # each alone explains little (a small difference of two large terms, such
            # as x' = 36 (y - x) with x following y).  The best of N pairs lowers the
            # chi-square by about 2 log N by chance, so that is charged on top of the
            # two terms' penalty.
            among = [j for _, j in sorted(ranked)[:PAIR_TERMS]]
            pairs, searched = _added_pairs(gw, yw, support, MOVES_SCORED, among)
            charge = 2.0 * np.log(max(searched, 1))
            for _, a, b in pairs:
                trial = support.copy()
                trial[[a, b]] = True
                chi2, new_xi = fitted(trial, xi)
                new_score = chi2 + penalty * int(trial.sum())
                if new_score + charge < score and (best is None or new_score < best[2]):
                    best = (trial, new_xi, new_score)
        if best is None:
            break
        support, xi, score = best
    return support.tobytes(), score


@dataclass
class Rescored:
    """Outcome of :func:`rescore_supports`.

    Attributes
    ----------
    support : ndarray of bool (p, n)
        Per equation, the candidate support with the lowest score (the chosen one
        unless another beat it by more than the margin).
    switched : ndarray of bool (n,)
        Equations whose support was replaced.
    chosen_score, best_score : ndarray (n,)
        The score of the support the selection chose and of the best candidate
        (``nan`` for equations not rescored).
    candidates : ndarray of int (n,)
        The distinct supports scored per equation.
    trusted : ndarray of bool (n,)
        Equations whose support stayed and whose chi-square the states' noise explains
        (at most :data:`NOISE_EXPLAINS` times the rows, as a replacement needs): there
        the score judges the selection's choice too.
    scored : list
        Per equation, every support fitted (the candidates and the searches' steps):
        ``(supports (S, p) bool, scores (S,), coefficients (S, p))``, standardised.
    """

    support: np.ndarray
    switched: np.ndarray
    chosen_score: np.ndarray
    best_score: np.ndarray
    candidates: np.ndarray
    trusted: np.ndarray
    scored: list = field(default_factory=list, repr=False)

    def rival_margin(self, reference: np.ndarray) -> np.ndarray:
        """Per replaced or :attr:`trusted` equation, the score of the best support
        fitted that is another model than ``reference`` (p, n, standardised: the model
        finally reported; it leaves out one of its terms or changes one of its
        coefficients by more than half, as
        :func:`~robust_sindy.selection.criteria.score_margin` counts rivals) minus the
        score of the support kept, ``inf`` where none is (negative where a rival scored
        better, by no more than the margin a replacement needs); ``nan`` for the other
        equations, where the score is not a yardstick."""
        out = np.full(self.switched.shape, np.nan)
        for k in np.flatnonzero(self.switched | self.trusted):
            supports, scores, coefs = self.scored[k]
            best = np.flatnonzero(np.all(supports == self.support[:, k], axis=1))
            out[k] = score_margin(
                scores[:, None], coefs[:, :, None], best[:1], rivals=True,
                reference=reference[:, [k]],
            )[0]  # fmt: skip
        return out


def _explained(scores: dict, key: bytes, penalty: float, rows: int) -> bool:
    """Whether the support ``key``'s chi-square (its score less ``penalty`` per term)
    is within what the states' noise explains (:data:`NOISE_EXPLAINS` times the
    ``rows``): there the score is a yardstick."""
    size = int(np.frombuffer(key, dtype=bool).sum())
    return scores[key] - penalty * size <= NOISE_EXPLAINS * rows


def rescore_supports(g, y, chosen, pools, noise: RowNoise, margin: float) -> Rescored:
    """Score the chosen support and every candidate of ``pools`` (arrays (L, p, n) of
    coefficients, standardised, whose nonzero patterns are the candidates) per
    equation by :func:`gls_score` plus ``log(rows)`` per term; replace the chosen support
    where another beats it by more than ``margin`` and has a chi-square of at most
    :data:`NOISE_EXPLAINS` times the rows.  ``chosen`` (p, n): the chosen coefficients
    (standardised)."""
    rows = g.shape[0]
    n = y.shape[1]
    penalty = np.log(max(rows, 2))
    support = chosen != 0
    switched = np.zeros(n, dtype=bool)
    trusted = np.zeros(n, dtype=bool)
    chosen_score = np.full(n, np.nan)
    best_score = np.full(n, np.nan)
    counts = np.zeros(n, dtype=int)
    scored = [None] * n
    noise.prepare()  # the products the equations share, formed before they run

    def equation(k):  # writes only equation k's entries: the equations run side by side
        starts = {support[:, k].tobytes(): chosen[:, k]}
        for pool in pools:
            for c in pool[:, :, k]:
                key = (c != 0).tobytes()
                if (c != 0).any() and key not in starts:
                    starts[key] = c
        counts[k] = len(starts)
        scores, memo = {}, {}
        for key, start in starts.items():
            s = np.frombuffer(key, dtype=bool)
            memo[key] = gls_score(g, y[:, k], s, start, noise, k)
            scores[key] = memo[key][0] + penalty * int(s.sum())
        best = min(scores, key=scores.get)
        # Local searches from the best candidate, from the chosen support and from the
        # empty model: the path and the subsets were ranked by a criterion that reads
        # the columns' noise as signal, and may not hold the support this score prefers.
        empty = np.zeros(g.shape[1], dtype=bool).tobytes()
        for start in dict.fromkeys((best, support[:, k].tobytes(), empty)):
            found, score = _stepwise(
                g, y[:, k], start, scores.get(start, np.inf), noise, k, penalty, memo
            )
            if score < scores.get(found, np.inf):
                scores[found] = score
        best = min(scores, key=scores.get)
        kept = support[:, k].tobytes()
        own = scores[kept]
        chosen_score[k], best_score[k] = own, scores[best]
        if _explained(scores, best, penalty, rows) and own - scores[best] > margin:
            support[:, k] = np.frombuffer(best, dtype=bool)
            switched[k] = True
        else:
            trusted[k] = _explained(scores, kept, penalty, rows)
        fitted = np.array([np.frombuffer(key, dtype=bool) for key in memo])
        chi2 = np.array([chi2 for chi2, _ in memo.values()])
        coefs = np.array([xi for _, xi in memo.values()])
        scored[k] = (fitted, chi2 + penalty * fitted.sum(axis=1), coefs)

    map_threads(equation, range(n))
    return Rescored(support, switched, chosen_score, best_score, counts, trusted, scored)


def search_penalty(rows: int, terms: int, kept: int) -> float:
    """The extended BIC's penalty (Chen and Chen 2008, Biometrika 95:759) for adding a
    term to ``kept`` of ``terms`` candidates, beyond the BIC's ``log(rows)``:
    ``2 gamma log((terms - kept) / (kept + 1))`` (the change in ``2 gamma log`` of the
    number of supports of that size, never below zero), ``gamma = 1 - log(rows) /
    (2 log(terms))`` clipped to [0, 1] (their smallest consistent choice where the
    candidates number ``rows**kappa``): zero while the library is smaller than the root
    of the rows.  The best of many candidate terms lowers a chi-square by more than
    the best of a few: without it, a fixed bar on the fall warns more often as the
    library grows with the channels."""
    if terms < 2 or rows < 2:
        return 0.0
    gamma = min(max(1.0 - np.log(rows) / (2.0 * np.log(terms)), 0.0), 1.0)
    return 2.0 * gamma * max(np.log(max(terms - kept, 1) / (kept + 1)), 0.0)


def displacement_refused(g, y, current, outcome, noise: RowNoise, cols) -> np.ndarray:
    """Per equation of ``cols`` (integer array), whether the score under the noise the
    terms carry refuses the support ``outcome`` in place of ``current`` (coefficients,
    standardised, p x n): where the states' noise explains the residuals of
    ``current`` (chi-square at most :data:`NOISE_EXPLAINS` times the rows, where the
    score is a yardstick) and its :func:`gls_score` plus ``log(rows)`` per term is
    lower than the outcome's by more than
    :data:`~robust_sindy.selection.criteria.MIN_BIC_MARGIN`.

    The final selection's put-back terms (:func:`~.final.missed_terms`) may replace
    selected ones: a true term that a few stand-ins had replaced on the path displaces
    them, but a term whose column carries little of the states' noise can as well
    displace true terms whose columns carry much of it (a shift mode's ``x2^2`` for its
    drive ``x0^2 + x1^2`` of noisy oscillating states), which the Huber loss on the rows
    then prefers."""
    rows = g.shape[0]
    bound = NOISE_EXPLAINS * rows
    penalty = np.log(max(rows, 2))
    out = np.zeros(len(cols), dtype=bool)
    for i, k in enumerate(cols):
        now, _ = gls_score(g, y[:, k], current[:, k] != 0, current[:, k], noise, k)
        if not now <= bound:
            continue
        new, _ = gls_score(g, y[:, k], outcome[:, k] != 0, outcome[:, k], noise, k)
        count_now = int(np.count_nonzero(current[:, k]))
        count_new = int(np.count_nonzero(outcome[:, k]))
        out[i] = (new + penalty * count_new) - (now + penalty * count_now) > MIN_BIC_MARGIN
    return out


def dropped_evidence(g, y, before, after, start, noise: RowNoise, tol: float = 0.0) -> np.ndarray:
    """Per equation whose support ``after`` (bool, p x n: the model reported) left out
    terms of ``before`` (the support the rescoring chose), the most that putting one of
    them back lowers the score, where the states' noise explains the residuals of both
    supports compared (chi-square at most :data:`NOISE_EXPLAINS` times the rows, as
    :func:`rescore_supports` requires of a replacement: beyond it the residuals hold
    what the noise model leaves out, such as the quadrature's error on nearly
    noise-free states, which a spurious term absorbs); NaN for the other equations.

    The fall is the :func:`gls_score` chi-square's, read in units of the larger
    support's residuals where their chi-square exceeds the rows (the noise model then
    understates the residuals' spread, and the fall with it: an F statistic's
    denominator), less the score's ``log(rows)`` per term (as in
    :func:`rescore_supports`) and :func:`search_penalty` for the library's candidates
    (the rescoring's search took the term as the best of all of them).  ``start`` (p,
    n, standardised) starts the fits.  Positive: the score, under the noise the terms
    carry, prefers that term in the model.

    A term that, put back, would contribute less than ``tol`` of the equation
    (``|xi_j| |g_j| / |y|``, the final selection's measure and its ``selection_tol``,
    under which it drops any term) is not counted: kept, it would be dropped again.  On
    nearly noise-free weak rows, terms of a millionth of their equation lower the
    chi-square by tens, fitted to the quadrature's error."""
    rows = g.shape[0]
    bound = NOISE_EXPLAINS * rows
    terms = int(np.count_nonzero(np.any(g != 0, axis=0)))
    col = np.linalg.norm(g, axis=0)
    out = np.full(y.shape[1], np.nan)
    for k in np.flatnonzero(np.any(before & ~after, axis=0)):
        least = tol * np.linalg.norm(y[:, k])
        reported = gls_score(g, y[:, k], after[:, k], start[:, k], noise, k)[0]
        if not reported <= bound:
            continue
        penalty = np.log(max(rows, 2)) + search_penalty(rows, terms, int(after[:, k].sum()))
        gains = []
        for j in np.flatnonzero(before[:, k] & ~after[:, k]):
            back = after[:, k].copy()
            back[j] = True
            chi2, xi = gls_score(g, y[:, k], back, start[:, k], noise, k)
            if chi2 <= bound and abs(xi[j]) * col[j] >= least:
                gains.append((reported - chi2) / max(1.0, chi2 / rows) - penalty)
        if gains:
            out[k] = max(gains)
    return out


def rescore_weak(
    kept: Problem, design, selection, fitted: Fitted, noise: RowNoise, *, method, solver, options
) -> tuple[Fitted, Rescored]:
    """:func:`rescore_supports` on the weak form's kept rows (``design``: the standardised
    library the selection saw; ``selection`` its
    :class:`~robust_sindy.selection.criteria.Selection`), the replaced equations refitted
    by Huber without penalty on their new support (user units, as ``fitted``)."""
    chosen = kept.scaler.coef_to_standard(fitted.coef)
    out = rescore_supports(
        design, kept.y_s, chosen, (selection.candidates, selection.subsets), noise,
        MIN_BIC_MARGIN,
    )  # fmt: skip
    if not out.switched.any():
        return fitted, out
    method = huber_method(method)
    solver = solver if method == "cvxpy" else None
    delta = np.broadcast_to(np.asarray(fitted.result.delta, float), (kept.y.shape[1],))
    coef = fitted.coef.copy()
    for k in np.flatnonzero(out.switched):
        coef[:, k] = refit_column(
            kept.theta, kept.y[:, k], out.support[:, k], delta[k], method, solver, options
        )
    return Fitted(fitted.result, coef), out
