"""Best-subset candidates: exhaustive weighted least squares over small supports.

A lasso-type path proposes supports in the order its penalty admits terms.  When the
library columns are strongly collinear (monomials of states that vary over a narrow
range), the true support may never be on it: every point of the path trades one
correlated term for a combination of others.  An exhaustive search over all supports
up to some size does not depend on that order.  It ranks the supports by the weighted
residual sum of squares of the Huber weights of a reference fit (the iteratively
reweighted least-squares view of the Huber loss), solved from the weighted Gram matrix,
so that a subset costs a ``k x k`` solve; the best few of every size are then refitted
with the Huber loss and scored like the path's candidates.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..solvers.newton import inlier_gram

__all__ = ["SUBSET_BUDGET", "best_subsets", "subset_sizes"]

#: Supports the exhaustive search may rank per equation (all sizes together).
SUBSET_BUDGET = 200_000

#: Relative ridge on the diagonal of every subset's Gram matrix: it keeps exactly
#: collinear subsets solvable; their residual sums are then no better than their
#: independent part's.
_RIDGE = 1e-12

#: Supports ranked per batched solve.
_CHUNK = 20_000


def subset_sizes(n_terms: int, budget: int = SUBSET_BUDGET) -> int:
    """The largest ``s`` such that all supports of 1 to ``s`` of ``n_terms`` terms
    number at most ``budget``."""
    total, s = 0, 0
    while s < n_terms:
        total += math.comb(n_terms, s + 1)
        if total > budget:
            break
        s += 1
    return s


def best_subsets(
    theta,
    y,
    weights,
    *,
    per_size: int = 3,
    budget: int = SUBSET_BUDGET,
    max_size=None,
    gram=None,
):
    """The ``per_size`` supports of each size with the smallest weighted residual sum
    of squares ``sum_i w_i (y_i - theta_i b_S)^2``, least squares on the columns ``S``.

    Sizes run from 1 to :func:`subset_sizes` of the nonzero columns of ``theta`` (zero
    columns take part in no support), and at most to ``max_size``.  Returns a list of
    boolean masks over the columns of ``theta``, the best first within each size, and
    the largest size searched.

    ``gram``, the unweighted Gram matrix of the nonzero columns (shared by searches
    with other weights, ``weights`` in ``[0, 1]``), lets the weighted one be formed
    from the rows with ``w < 1`` (:func:`~robust_sindy.solvers.newton.inlier_gram`).
    Single terms need only its diagonal, which is all that is formed when no larger
    size is searched.
    """
    theta = np.asarray(theta, dtype=float)
    w = np.asarray(weights, dtype=float)
    pool = np.flatnonzero(np.any(theta != 0, axis=0))
    a = theta[:, pool]
    rhs = a.T @ (w * y)
    largest = subset_sizes(pool.size, budget)
    if max_size is not None:
        largest = max(0, min(largest, int(max_size)))
    if largest <= 1:
        gram = None
        diag = np.einsum("ij,ij,i->j", a, a, w)
    elif gram is not None and w.min(initial=1.0) >= 0.0 and w.max(initial=0.0) <= 1.0:
        gram = inlier_gram(a, np.asarray(gram, dtype=float), w[:, None])[0]
        diag = np.diag(gram)
    else:
        gram = a.T @ (w[:, None] * a)
        diag = np.diag(gram)
    masks = []
    for s in range(1, largest + 1):
        best_rss = np.empty(0)
        best_sets = np.empty((0, s), dtype=int)
        combos = itertools.combinations(range(pool.size), s)
        while True:
            chunk = np.fromiter(
                itertools.islice(combos, _CHUNK), dtype=np.dtype((np.intp, s))
            ).reshape(-1, s)
            if chunk.size == 0:
                break
            if gram is None:  # single terms
                g = diag[chunk][:, :, None]  # a new array: the ridge leaves diag alone
            else:
                g = gram[chunk[:, :, None], chunk[:, None, :]]
            g[:, np.arange(s), np.arange(s)] += _RIDGE * diag[chunk]
            b = rhs[chunk]
            sol = np.linalg.solve(g, b[..., None])[..., 0]
            # y'Wy is common to every support: rank by what the fit explains.
            rss = -np.einsum("ij,ij->i", b, sol)
            best_rss = np.concatenate([best_rss, rss])
            best_sets = np.concatenate([best_sets, chunk])
            if best_rss.size > per_size:
                top = np.argpartition(best_rss, per_size)[:per_size]
                best_rss, best_sets = best_rss[top], best_sets[top]
        for j in np.argsort(best_rss, kind="stable"):
            mask = np.zeros(theta.shape[1], dtype=bool)
            mask[pool[best_sets[j]]] = True
            masks.append(mask)
    return masks, largest
