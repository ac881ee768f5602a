"""PySINDy interop: the Huber-Lasso as a PySINDy optimizer (needs the ``pysindy`` extra).

Examples
--------
>>> import pysindy as ps
>>> from robust_sindy.pysindy import HuberOptimizer
>>> from robust_sindy.systems import Lorenz
>>> data = Lorenz().generate(t_end=5.0)
>>> model = ps.SINDy(
...     optimizer=HuberOptimizer(delta=1.0, lam=1.0),
...     feature_library=ps.PolynomialLibrary(degree=2),
... )
>>> model = model.fit(data.x, t=data.t, x_dot=data.x_dot, feature_names=["x", "y", "z"])
>>> model.print(precision=2)
(x)' = -9.98 x +  9.99 y
(y)' =  27.98 x + -0.99 y + -1.00 x z
(z)' = -2.67 z +  1.00 x y
"""

from __future__ import annotations

import numpy as np

from ._fit import fit

try:
    from pysindy.optimizers import BaseOptimizer
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "robust_sindy.pysindy needs PySINDy: pip install 'robust-sindy[pysindy]'"
    ) from exc

__all__ = ["HuberOptimizer"]


class HuberOptimizer(BaseOptimizer):
    """Huber loss plus L1 penalty, solved by :func:`robust_sindy.fit`, for ``ps.SINDy``.

    Parameters
    ----------
    delta : float, array_like (n,) or "auto"
        Huber threshold per target.
    lam : float or array_like (n,)
        L1 weight per target.
    method : {"admm", "cvxpy"}
    solver : str, optional
        For ``method="cvxpy"``.
    solver_options : dict, optional
        Keyword options of :func:`robust_sindy.fit`.
    normalize_columns : bool
        PySINDy's column normalisation (the ADMM equilibrates columns itself).
    unbias : bool
        Default ``False``.  PySINDy's unbiasing refits the selected terms by ordinary
        least squares, which gives every outlier its full quadratic influence again and
        undoes the robustness this optimizer is for.  For a debiased robust fit use
        :class:`robust_sindy.HuberSINDy` with ``refit=True`` (a Huber refit).

    Attributes
    ----------
    coef_ : ndarray (n_targets, n_features)
    result_ : FitResult
        The certificate and solver report of the last fit.
    """

    def __init__(
        self,
        delta=1.0,
        lam=1.0,
        method: str = "admm",
        solver: str | None = None,
        solver_options: dict | None = None,
        normalize_columns: bool = False,
        unbias: bool = False,
        copy_X: bool = True,
        initial_guess=None,
    ):
        super().__init__(
            max_iter=1,
            normalize_columns=normalize_columns,
            initial_guess=initial_guess,
            copy_X=copy_X,
            unbias=unbias,
        )
        self.delta = delta
        self.lam = lam
        self.method = method
        self.solver = solver
        self.solver_options = solver_options

    def _reduce(self, x, y):
        res = fit(
            np.asarray(x),
            np.asarray(y),
            method=self.method,
            delta=self.delta,
            lam=self.lam,
            solver=self.solver,
            **(self.solver_options or {}),
        )
        self.result_ = res
        self.coef_ = res.coef.T
        self.history_.append(self.coef_)
        self.iters = int(np.max(res.iterations))
