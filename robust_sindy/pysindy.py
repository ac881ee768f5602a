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

from .core.scaling import Standardizer
from .fitting import fit

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
        Huber threshold per target (default ``"auto"``: the robust-scale rule,
        :func:`robust_sindy.selection.auto_delta`, on standardised columns).
    lam : float, array_like (n,) or "auto"
        L1 weight per target.  ``"auto"`` (the default) chooses it per target as
        :class:`robust_sindy.HuberSINDy` does, by :func:`robust_sindy.selection.select`
        on standardised library columns and targets (unit-free); ``coef_`` is then the
        selection stage's refit on the chosen terms and ``result_`` the penalised fit
        at the chosen ``lam`` with its certificate.
    method : {"admm", "cvxpy"}
    solver : str, optional
        For ``method="cvxpy"``.
    solver_options : dict, optional
        Keyword options of :func:`robust_sindy.fit`.
    normalize_columns : bool
        PySINDy's column normalisation (the ADMM equilibrates columns itself).
    constraints : LinearConstraints, optional
        Linear constraints on the coefficients across equations
        (:mod:`robust_sindy.constraints`), for a coefficient matrix of shape
        ``(n_features, n_targets)``: build them from the PySINDy library's names, e.g.
        ``rc.energy_preserving(library.get_feature_names(["x", "y", "z"]))``.  With a
        fixed ``lam`` the penalised problem is solved under them; with ``lam="auto"``
        the terms are selected as without them and then searched again under them
        (:func:`robust_sindy.selection.constrained.constrained_selection`), as
        :class:`robust_sindy.HuberSINDy` does.
    unbias : bool
        Default ``False``.  PySINDy's unbiasing refits the selected terms by ordinary
        least squares, which gives every outlier its full quadratic influence again and
        undoes the robustness this optimizer is for.  For a debiased robust fit use
        :class:`robust_sindy.HuberSINDy` with ``refit=True`` (a Huber refit).

    Attributes
    ----------
    coef_ : ndarray (n_targets, n_features)
    result_ : FitResult
        The certificate and solver report of the last fit (with ``constraints`` and
        ``lam="auto"``, of the refit of the chosen terms with each equation's loss on
        its own scale, :func:`robust_sindy.selection.constrained.scaled_fit`).
    """

    def __init__(
        self,
        delta="auto",
        lam="auto",
        method: str = "admm",
        solver: str | None = None,
        solver_options: dict | None = None,
        normalize_columns: bool = False,
        unbias: bool = False,
        copy_X: bool = True,
        initial_guess=None,
        constraints=None,
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
        self.constraints = constraints

    def _reduce(self, x, y):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        options = self.solver_options or {}
        delta, lam, coef, con = self.delta, self.lam, None, self.constraints
        res = None
        if isinstance(lam, str) and lam == "auto":
            from .selection import auto_delta, select

            y2 = y.reshape(len(y), -1)
            scaler = Standardizer.from_data(x, y2)
            th, ys = scaler.theta(x), scaler.y(y2)
            if isinstance(delta, str) and delta == "auto":
                delta_s = auto_delta(th, ys, method=self.method)
            else:
                delta_s = np.broadcast_to(np.asarray(delta, float), (y2.shape[1],))
                delta_s = delta_s / scaler.y_scale
            sel = select(th, ys, delta_s, method=self.method, solver=self.solver, **options)
            delta, lam = scaler.delta_to_user(sel.delta), scaler.lam_to_user(sel.lam)
            coef = scaler.coef_to_user(sel.coef)
            if self.constraints is not None:
                from .selection.constrained import (
                    constrained_selection,
                    held_off_support,
                    scaled_fit,
                )
                from .selection.problem import Problem

                found = constrained_selection(
                    Problem(x, y2, scaler, [slice(0, len(y2))]), coef, delta,
                    self.constraints, method=self.method, solver=self.solver,
                )  # fmt: skip
                # The chosen support's constrained refit over the whole library, each
                # equation's loss on its own scale as in the search.
                con = held_off_support(self.constraints, found.support)
                coef, res = scaled_fit(
                    x, y2, found.delta, con, method=self.method, solver=self.solver
                )
        if res is None:
            res = fit(
                x, y, method=self.method, delta=delta, lam=lam, solver=self.solver,
                constraints=con, **options,
            )  # fmt: skip
        self.result_ = res
        self.coef_ = (res.coef if coef is None else coef.reshape(res.coef.shape)).T
        self.history_.append(self.coef_)
        self.iters = int(np.max(res.iterations))
