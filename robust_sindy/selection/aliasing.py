"""Library terms that are exact linear combinations of earlier ones on the data.

A state that does not move (a parameter channel, a stuck sensor, an exactly conserved
quantity, a binary input with ``u**2 == u``) makes some library columns exact linear
combinations of others: ``x0``, ``x0**2`` and the constant are then the same column up
to a factor, and no data can tell which of them an equation uses.  The Lasso splits
the weight among such columns, so every candidate support would carry all of them.
Before the selection, each column is tested against the span of the columns before it
(library order: lower degree first) and left out when its distance to that span is
within rounding of zero; the equations found use the first term of each group, and
the diagnostics name the ones left out.
"""

from __future__ import annotations

import numpy as np

from ..core.statistics import ALIAS_RTOL
from ..core.validation import as_float_array

__all__ = ["ALIAS_RTOL", "aliased_columns"]


def aliased_columns(theta, rtol: float = ALIAS_RTOL) -> np.ndarray:
    """Columns of ``theta`` (m, p) within ``rtol`` of the span of the columns before
    them, relative to their norm (bool, p).

    The distance of column ``j`` to the span of columns ``0..j-1`` is ``|R_jj|`` of the
    Householder QR factorisation without pivoting.  Zero columns count as aliased.
    Rescaling a column does not change the answer.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0.0, 1.0, 50)
    >>> theta = np.column_stack([np.ones(50), np.full(50, 3.0), x, 2.0 * x - 1.0, x**2])
    >>> aliased_columns(theta).tolist()
    [False, True, False, True, False]
    """
    theta = as_float_array(theta, "theta", (2,))
    m, p = theta.shape
    norms = np.linalg.norm(theta, axis=0)
    out = norms == 0
    if m < p or not np.all(np.isfinite(theta)):
        # Fewer samples than terms: every column beyond the rank is a combination,
        # which the caller reports as too little data, not as aliasing.
        return out
    scaled = theta / np.where(norms > 0, norms, 1.0)
    r = np.linalg.qr(scaled, mode="r")
    return out | (np.abs(np.diag(r)) <= rtol)
