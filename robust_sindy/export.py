"""The identified equations outside the estimator: plain numpy code and sympy expressions.

:class:`ExportedRHS` is the right-hand side ``f(t, x, u)`` of a fitted model as generated
Python source: only the selected terms, no input checks or library objects per call, so
it is what an integrator or a controller should call.  :func:`to_sympy` gives the same
equations as sympy expressions (``pip install "robust_sindy[sympy]"``).
"""

from __future__ import annotations

import numpy as np

from .library import CONSTANTS, FUNCTIONS

__all__ = ["ExportedRHS", "to_sympy"]


def _terms(library, coef):
    """Codes of the library's features in inputs ``z0, z1, ...`` and the used columns."""
    k = library.n_features_in_
    codes, extra = library.term_codes([f"z{i}" for i in range(k)])
    used = np.flatnonzero(np.any(coef != 0, axis=0))
    return codes, extra, used


class ExportedRHS:
    """The right-hand side of a fitted model as generated numpy code.

    ``f(t, x, u=None)`` returns the derivatives at states ``x`` (shape (n,) or (m, n))
    and controls ``u`` (shape (q,) or (m, q), required when the model has controls);
    ``t`` is ignored (the signature is :func:`scipy.integrate.solve_ivp`'s).  Only the
    selected terms are evaluated.

    Attributes
    ----------
    source : str
        The generated module: ``import numpy`` and one function ``rhs(t, x, u=None)``
        with the coefficients written out (``repr`` of each float, so exact).  It runs
        on its own when the library is made of polynomial, Fourier and expression
        features; features that are Python callables are called by name
        (``_custom...``): put :attr:`callables` in the module's namespace.
    callables : dict
        Those names and their functions (empty for a portable library).
    n_states, n_controls : int
    state_names : list of str
    """

    def __init__(self, library, coef, state_names, n_controls: int):
        coef = np.asarray(coef, dtype=float)
        n = coef.shape[0]
        codes, extra, used = _terms(library, coef)
        self.n_states, self.n_controls = n, int(n_controls)
        self.state_names = list(state_names)
        funcs = sorted(FUNCTIONS)
        lines = [
            '"""Right-hand side identified by robust_sindy (generated code)."""',
            "import numpy as np",
            f"from numpy import {', '.join(funcs)}",
            f"pi = {CONSTANTS['pi']!r}",
            "",
            "",
            "def rhs(t, x, u=None):",
            f'    """d/dt of the states {self.state_names} (x: (..., {n}))."""',
            "    x = np.asarray(x, dtype=float)",
            f"    if x.shape[-1] != {n}:",
            f"        raise ValueError(f'x has {{x.shape[-1]}} entries per sample; expected {n}')",
        ]
        lines += [f"    z{i} = x[..., {i}]" for i in range(n)]
        if n_controls:
            lines += [
                "    if u is None:",
                f"        raise ValueError('u is required: the model has {n_controls} controls')",
                "    u = np.asarray(u, dtype=float)",
            ]
            lines += [f"    z{n + i} = u[..., {i}]" for i in range(n_controls)]
        lines += [f"    f{j} = {codes[j]}" for j in used]
        lines.append(f"    out = np.zeros(x.shape[:-1] + ({n},))")
        for i in range(n):
            terms = [f"{coef[i, j]!r} * f{j}" for j in used if coef[i, j] != 0]
            if terms:
                lines.append(f"    out[..., {i}] = " + " + ".join(terms))
        lines.append("    return out")
        self.source = "\n".join(lines) + "\n"
        self.callables = {name: f for name, (f, _) in extra.items()}
        scope = dict(self.callables)
        exec(compile(self.source, "<robust_sindy rhs>", "exec"), scope)
        self._rhs = scope["rhs"]

    def __call__(self, t, x, u=None) -> np.ndarray:
        return self._rhs(t, x, u)

    def write(self, path) -> None:
        """Write :attr:`source` to ``path`` (a ``.py`` file)."""
        from pathlib import Path

        Path(path).write_text(self.source)

    def __repr__(self) -> str:
        return f"ExportedRHS({self.n_states} states, {self.n_controls} controls)"


def _sympy_namespace(sympy):
    table = {
        "arctan": sympy.atan,
        "abs": sympy.Abs,
        "sign": sympy.sign,
    }
    out = {name: table.get(name) or getattr(sympy, name) for name in FUNCTIONS}
    out["pi"] = sympy.pi
    return out


def to_sympy(library, coef, input_names) -> list:
    """The equations as sympy expressions in symbols named by ``input_names``."""
    try:
        import sympy
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError('to_sympy needs sympy: pip install "robust_sindy[sympy]"') from None
    coef = np.asarray(coef, dtype=float)
    codes, extra, used = _terms(library, coef)
    scope = _sympy_namespace(sympy)
    scope.update({f"z{i}": sympy.Symbol(name) for i, name in enumerate(input_names)})
    for key, (_, name) in extra.items():
        scope[key] = sympy.Function(name.split("(")[0] or "f")
    features = {j: eval(codes[j], {"__builtins__": {}}, scope) for j in used}
    return [
        sympy.Add(*[sympy.Float(c) * features[j] for j, c in enumerate(row) if c != 0])
        for row in coef
    ]
