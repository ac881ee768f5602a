"""Feature libraries: the candidate functions ``Theta(x, u)`` with readable names.

Libraries follow the scikit-learn transformer conventions (``fit``, ``transform``,
``fit_transform``, ``get_feature_names``).  Their input is one 2-D array whose columns are
the states followed by the controls; ``input_names`` names those columns.  Libraries
compose with ``+``, which concatenates their features in order.

Examples
--------
>>> import numpy as np
>>> from robust_sindy.library import CustomLibrary, PolynomialLibrary
>>> lib = PolynomialLibrary(degree=2).fit(np.zeros((1, 3)), input_names=["x", "y", "z"])
>>> lib.get_feature_names()
['1', 'x', 'y', 'z', 'x^2', 'x*y', 'x*z', 'y^2', 'y*z', 'z^2']
>>> drive = CustomLibrary([np.sin], names=["sin(t)"], inputs=[["t"]])
>>> both = PolynomialLibrary(degree=1, inputs=["x"]) + drive
>>> both.fit_transform(np.array([[2.0, 0.0]]), input_names=["x", "t"])
array([[1., 2., 0.]])
>>> both.get_feature_names()
['1', 'x', 'sin(t)']
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Sequence
from itertools import combinations_with_replacement

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin, clone
from sklearn.utils import check_array

from .core.validation import check_int

__all__ = [
    "FUNCTIONS",
    "BaseLibrary",
    "ConcatLibrary",
    "CustomLibrary",
    "FourierLibrary",
    "PolynomialLibrary",
]

#: Functions a :class:`CustomLibrary` expression may call, with their numpy meaning.
FUNCTIONS = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "arctan": np.arctan,
    "sinh": np.sinh,
    "cosh": np.cosh,
    "tanh": np.tanh,
    "exp": np.exp,
    "log": np.log,
    "sqrt": np.sqrt,
    "abs": np.abs,
    "sign": np.sign,
}
#: Constants an expression may name.
CONSTANTS = {"pi": np.pi}

_OPERATORS = (ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)


def parse_expression(expr: str, input_names: Sequence[str]) -> tuple[ast.Expression, list[str]]:
    """Check a feature expression and list the inputs it uses (in order of appearance).

    An expression is arithmetic (``+ - * / **``) on input names, numbers, the constant
    ``pi`` and calls of the functions in :data:`FUNCTIONS`, e.g. ``"sin(theta) * f1"``.
    Anything else (attributes, keywords, other names) is a ``ValueError`` naming it.
    """
    if not isinstance(expr, str) or not expr.strip():
        raise ValueError(f"a feature expression must be a non-empty string; got {expr!r}")
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(f"feature expression {expr!r} is not valid: {exc.msg}") from None
    used: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
                raise ValueError(
                    f"feature expression {expr!r} calls {ast.unparse(node.func)!r}; the "
                    f"functions available are {sorted(FUNCTIONS)}"
                )
            if node.keywords or len(node.args) != 1:
                raise ValueError(f"feature expression {expr!r}: {node.func.id} takes one argument")
        elif isinstance(node, ast.Name):
            if node.id in input_names:
                if node.id not in used:
                    used.append(node.id)
            elif node.id not in FUNCTIONS and node.id not in CONSTANTS:
                raise ValueError(
                    f"feature expression {expr!r} names {node.id!r}, which is not one of the "
                    f"inputs {list(input_names)} (nor a function or pi)"
                )
        elif isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
                raise ValueError(f"feature expression {expr!r} contains {node.value!r}")
        elif not isinstance(node, (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Load, *_OPERATORS)):
            raise ValueError(
                f"feature expression {expr!r} contains {type(node).__name__}: only arithmetic "
                "on inputs, numbers and function calls is allowed"
            )
    return tree, used


class _Rename(ast.NodeTransformer):
    def __init__(self, mapping):
        self.mapping = mapping

    def visit_Name(self, node):
        if node.id in self.mapping:
            return ast.copy_location(ast.Name(self.mapping[node.id], ast.Load()), node)
        return node


def _substitute(tree: ast.Expression, mapping: dict) -> str:
    """The expression's source with input names replaced by ``mapping``'s codes."""
    import copy

    return ast.unparse(_Rename(mapping).visit(copy.deepcopy(tree)))


def _check_x(x) -> np.ndarray:
    """The input as a finite 2-D float array, with scikit-learn's checks and messages."""
    return check_array(x, dtype=np.float64, input_name="x")


class BaseLibrary(TransformerMixin, BaseEstimator):
    """Common machinery: input naming, input selection, composition with ``+``."""

    def _fit_inputs(self, x, input_names) -> np.ndarray:
        x = _check_x(x)
        k = x.shape[1]
        if input_names is None:
            input_names = [f"x{i}" for i in range(k)]
        input_names = [str(s) for s in input_names]
        if len(input_names) != k:
            raise ValueError(
                f"input_names has {len(input_names)} entries but x has {k} columns: "
                "give one name per column"
            )
        if len(set(input_names)) != k:
            raise ValueError(f"input_names must be distinct; got {input_names}")
        self.input_names_ = input_names
        self.n_features_in_ = k
        return x

    def _index(self, ref, what: str) -> int:
        """Position of the input ``ref`` (a name or an integer index)."""
        if isinstance(ref, str):
            if ref not in self.input_names_:
                raise ValueError(
                    f"{what} names input {ref!r}, which is not one of {self.input_names_}"
                )
            return self.input_names_.index(ref)
        if isinstance(ref, (int, np.integer)) and not isinstance(ref, bool):
            if not 0 <= ref < self.n_features_in_:
                raise ValueError(
                    f"{what} refers to input {ref}, but there are {self.n_features_in_} inputs"
                )
            return int(ref)
        raise ValueError(f"{what} entries must be input names or indices; got {ref!r}")

    def _input_columns(self) -> list[int]:
        """Positions of the ``inputs`` parameter's inputs (all inputs when it is None)."""
        if self.inputs is None:
            return list(range(self.n_features_in_))
        return [self._index(ref, "inputs") for ref in self.inputs]

    def _check_fitted(self) -> None:
        if not hasattr(self, "input_names_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet: call fit first")

    def _check_transform_input(self, x) -> np.ndarray:
        self._check_fitted()
        x = _check_x(x)
        if x.shape[1] != self.n_features_in_:
            raise ValueError(
                f"X has {x.shape[1]} features, but {type(self).__name__} is expecting "
                f"{self.n_features_in_} features as input (x: one column per input "
                f"{self.input_names_})"
            )
        return x

    def fit_transform(self, x, y=None, input_names=None) -> np.ndarray:
        return self.fit(x, input_names=input_names).transform(x)

    def input_columns(self, k: int) -> np.ndarray | None:
        """The features that may depend on input ``k`` (indices), or None where the
        library cannot tell (then any of them may)."""
        return None

    def transform_columns(self, x, columns) -> np.ndarray:
        """``transform(x)[:, columns]``; a library that can form only those does so."""
        return self.transform(x)[:, columns]

    def term_codes(self, args: Sequence[str]) -> tuple[list[str], dict]:
        """Each feature as a Python expression of the input codes ``args``.

        Returns the expressions (they use the names of :data:`FUNCTIONS` and ``pi``) and
        the extra names they need (user callables).  They serve the exported right-hand
        side (:meth:`robust_sindy.HuberSINDy.rhs`) and :meth:`~robust_sindy.HuberSINDy.to_sympy`.
        """
        raise NotImplementedError(f"{type(self).__name__} does not export its terms")

    def __add__(self, other: BaseLibrary) -> ConcatLibrary:
        if not isinstance(other, BaseLibrary):
            return NotImplemented
        left = self.libraries if isinstance(self, ConcatLibrary) else [self]
        right = other.libraries if isinstance(other, ConcatLibrary) else [other]
        return ConcatLibrary([*left, *right])


class PolynomialLibrary(BaseLibrary):
    """All monomials of total degree ``<= degree`` in the selected inputs.

    Parameters
    ----------
    degree : int
        Highest total degree (>= 0).
    include_bias : bool
        Include the constant feature ``1``.
    inputs : sequence of str or int, optional
        The inputs the monomials are built from (all of them by default).

    Notes
    -----
    Monomials come in order of degree, then in the lexicographic order of
    :func:`itertools.combinations_with_replacement`; for degree 2 in ``(x, y, z)`` that is
    ``1, x, y, z, x^2, x*y, x*z, y^2, y*z, z^2``.
    """

    def __init__(self, degree: int = 2, include_bias: bool = True, inputs=None):
        self.degree = degree
        self.include_bias = include_bias
        self.inputs = inputs

    def fit(self, x, y=None, input_names=None) -> PolynomialLibrary:
        x = self._fit_inputs(x, input_names)
        d = check_int(self.degree, "degree", 0)
        cols = self._input_columns()
        start = 0 if self.include_bias else 1
        self.powers_ = [
            tuple(cols[i] for i in combo)
            for deg in range(start, d + 1)
            for combo in combinations_with_replacement(range(len(cols)), deg)
        ]
        self.n_output_features_ = len(self.powers_)
        return self

    def transform(self, x) -> np.ndarray:
        self._check_fitted()
        return self.transform_columns(x, range(self.n_output_features_))

    def input_columns(self, k: int) -> np.ndarray:
        self._check_fitted()
        return np.array([j for j, combo in enumerate(self.powers_) if k in combo], dtype=int)

    def transform_columns(self, x, columns) -> np.ndarray:
        x = self._check_transform_input(x)
        # Each monomial is formed as a contiguous row of the transpose (a column of a
        # row-major array is strided), the factors multiplied in the order of its powers.
        inputs = np.ascontiguousarray(x.T)
        columns = list(columns)
        out = np.empty((len(columns), x.shape[0]))
        for j, c in enumerate(columns):
            combo = self.powers_[c]
            if not combo:
                out[j] = 1.0
                continue
            out[j] = inputs[combo[0]]
            for i in combo[1:]:
                out[j] *= inputs[i]
        return np.ascontiguousarray(out.T)

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        names = self.input_names_ if input_names is None else list(input_names)
        out = []
        for combo in self.powers_:
            if not combo:
                out.append("1")
                continue
            parts = []
            for i in dict.fromkeys(combo):
                k = combo.count(i)
                parts.append(names[i] if k == 1 else f"{names[i]}^{k}")
            out.append("*".join(parts))
        return out

    def term_codes(self, args: Sequence[str]) -> tuple[list[str], dict]:
        self._check_fitted()
        codes = []
        for combo in self.powers_:
            parts = []
            for i in dict.fromkeys(combo):
                k = combo.count(i)
                parts.append(args[i] if k == 1 else f"{args[i]}**{k}")
            codes.append("*".join(parts) if parts else "1.0")
        return codes, {}


class FourierLibrary(BaseLibrary):
    """``sin(k x)`` and ``cos(k x)`` for ``k = 1..n_frequencies`` of each selected input.

    Parameters
    ----------
    n_frequencies : int
        Highest multiple ``k`` (>= 1).
    include_sin, include_cos : bool
        Which of the two to include (at least one).
    inputs : sequence of str or int, optional
        The inputs the features are built from (all of them by default).

    Notes
    -----
    Features come per frequency, then per input, ``sin`` before ``cos``: for
    ``n_frequencies=2`` in ``(x, y)`` that is ``sin(x), cos(x), sin(y), cos(y),
    sin(2*x), cos(2*x), sin(2*y), cos(2*y)``.
    """

    def __init__(
        self,
        n_frequencies: int = 1,
        include_sin: bool = True,
        include_cos: bool = True,
        inputs=None,
    ):
        self.n_frequencies = n_frequencies
        self.include_sin = include_sin
        self.include_cos = include_cos
        self.inputs = inputs

    def fit(self, x, y=None, input_names=None) -> FourierLibrary:
        x = self._fit_inputs(x, input_names)
        k = check_int(self.n_frequencies, "n_frequencies", 1)
        if not (self.include_sin or self.include_cos):
            raise ValueError("include_sin and include_cos are both False: the library is empty")
        cols = self._input_columns()
        kinds = [f for f, on in (("sin", self.include_sin), ("cos", self.include_cos)) if on]
        self.terms_ = [(f, j, i) for j in range(1, k + 1) for i in cols for f in kinds]
        self.n_output_features_ = len(self.terms_)
        return self

    def transform(self, x) -> np.ndarray:
        self._check_fitted()
        return self.transform_columns(x, range(self.n_output_features_))

    def input_columns(self, k: int) -> np.ndarray:
        self._check_fitted()
        return np.array([c for c, (_, _, i) in enumerate(self.terms_) if i == k], dtype=int)

    def transform_columns(self, x, columns) -> np.ndarray:
        x = self._check_transform_input(x)
        columns = list(columns)
        out = np.empty((x.shape[0], len(columns)))
        for col, c in enumerate(columns):
            f, j, i = self.terms_[c]
            out[:, col] = FUNCTIONS[f](j * x[:, i])
        return out

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        names = self.input_names_ if input_names is None else list(input_names)
        return [f"{f}({names[i]})" if j == 1 else f"{f}({j}*{names[i]})" for f, j, i in self.terms_]

    def term_codes(self, args: Sequence[str]) -> tuple[list[str], dict]:
        self._check_fitted()
        return [
            f"{f}({args[i]})" if j == 1 else f"{f}({j}*{args[i]})" for f, j, i in self.terms_
        ], {}


class CustomLibrary(BaseLibrary):
    """Features given by user functions of named inputs.

    Parameters
    ----------
    functions : sequence of callables or expression strings
        A callable returns one feature, an array of shape (m,), from 1-D input arrays.
        A string is an expression of the inputs by name (:func:`parse_expression`:
        arithmetic, numbers, ``pi`` and the functions of :data:`FUNCTIONS`), e.g.
        ``"(f1 + f2) * sin(theta)"``; it gives one feature.  A library whose functions
        are all strings can be saved to a model file (:meth:`HuberSINDy.save`).
    names : sequence of str, optional
        One name per feature.  Derived when omitted: the expression itself, or
        ``f(a, b)`` with a callable's ``__name__`` (``f0, f1, ...`` for lambdas).
    inputs : sequence of sequences of str or int, optional
        For each callable, the inputs it receives as positional arguments, in order
        (``None`` for an expression, which names its inputs itself).  When omitted every
        callable takes one argument and is applied to each input in turn (one feature
        per function and input).

    Examples
    --------
    >>> import numpy as np
    >>> lib = CustomLibrary(
    ...     [lambda th, f1, f2: (f1 + f2) * np.sin(th), lambda f1, f2: f1 - f2],
    ...     names=["(f1+f2)*sin(theta)", "f1-f2"],
    ...     inputs=[["theta", "f1", "f2"], ["f1", "f2"]],
    ... )
    >>> lib.fit_transform(np.array([[np.pi / 2, 3.0, 1.0]]), input_names=["theta", "f1", "f2"])
    array([[4., 2.]])
    >>> same = CustomLibrary(["(f1 + f2) * sin(theta)", "f1 - f2"])
    >>> same.fit_transform(np.array([[np.pi / 2, 3.0, 1.0]]), input_names=["theta", "f1", "f2"])
    array([[4., 2.]])
    >>> same.get_feature_names()
    ['(f1 + f2) * sin(theta)', 'f1 - f2']
    >>> same.get_feature_names(["a", "b", "c"])
    ['(b + c) * sin(a)', 'b - c']
    """

    def __init__(
        self,
        functions: Sequence[Callable],
        names: Sequence[str] | None = None,
        inputs: Sequence[Sequence] | None = None,
    ):
        self.functions = functions
        self.names = names
        self.inputs = inputs

    def fit(self, x, y=None, input_names=None) -> CustomLibrary:
        x = self._fit_inputs(x, input_names)
        funcs = list(self.functions) if not isinstance(self.functions, str) else None
        if not funcs or not all(callable(f) or isinstance(f, str) for f in funcs):
            raise ValueError(
                "functions must be a non-empty sequence of callables or expression strings"
            )
        if self.inputs is not None and len(self.inputs) != len(funcs):
            raise ValueError(
                f"inputs has {len(self.inputs)} entries but there are {len(funcs)} "
                "functions: give the arguments of each function"
            )
        self.terms_ = []
        for k, f in enumerate(funcs):
            given = None if self.inputs is None else self.inputs[k]
            if isinstance(f, str):
                tree, used = parse_expression(f, self.input_names_)
                tree.source = f.strip()
                if given is not None:
                    raise ValueError(
                        f"inputs[{k}] is given for the expression {f!r}: an expression names "
                        "its inputs itself (give None)"
                    )
                self.terms_.append((tree, tuple(self.input_names_.index(u) for u in used)))
            elif given is None:
                if self.inputs is not None:
                    raise ValueError(f"inputs[{k}] is None but functions[{k}] is a callable")
                self.terms_.extend((f, (i,)) for i in range(x.shape[1]))
            else:
                self.terms_.append((f, tuple(self._index(ref, "inputs") for ref in given)))
        if self.names is not None and len(self.names) != len(self.terms_):
            raise ValueError(
                f"names has {len(self.names)} entries but the library has "
                f"{len(self.terms_)} features"
            )
        self.n_output_features_ = len(self.terms_)
        return self

    def transform(self, x) -> np.ndarray:
        x = self._check_transform_input(x)
        out = np.empty((x.shape[0], self.n_output_features_))
        names = None
        for j, (f, args) in enumerate(self.terms_):
            with np.errstate(all="ignore"):  # non-finite values are reported below
                if isinstance(f, ast.Expression):
                    scope = {**FUNCTIONS, **CONSTANTS}
                    scope.update({self.input_names_[i]: x[:, i] for i in args})
                    value = eval(compile(f, "<feature>", "eval"), {"__builtins__": {}}, scope)
                else:
                    value = f(*(x[:, i] for i in args))
                col = np.asarray(value, dtype=float)
            col = np.broadcast_to(col, (x.shape[0],)) if col.ndim == 0 else col
            if col.shape != (x.shape[0],):
                raise ValueError(
                    f"function {j} of functions returned shape {col.shape}; expected "
                    f"({x.shape[0]},): functions must act elementwise on 1-D arrays"
                )
            bad = ~np.isfinite(col) & np.all(np.isfinite(x[:, list(args)]), axis=1)
            if bad.any():
                names = self.get_feature_names() if names is None else names
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"CustomLibrary feature {names[j]!r} (function {j} of functions) is "
                    f"{col[i]} at sample {i} (inputs {x[i, list(args)].tolist()}) and at "
                    f"{int(bad.sum())} samples in all: library functions must be finite on "
                    "the data"
                )
            out[:, j] = col
        return out

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        if self.names is not None:
            return [str(s) for s in self.names]
        names = self.input_names_ if input_names is None else list(input_names)
        out = []
        for f, args in self.terms_:
            if isinstance(f, ast.Expression):
                mapping = {self.input_names_[i]: names[i] for i in args}
                same = all(k == v for k, v in mapping.items())
                out.append(f.source if same else _substitute(f, mapping))
                continue
            base = getattr(f, "__name__", "f")
            if base == "<lambda>":
                base = f"f{list(self.functions).index(f)}"
            out.append(f"{base}({', '.join(names[i] for i in args)})")
        return out

    def term_codes(self, args: Sequence[str]) -> tuple[list[str], dict]:
        self._check_fitted()
        names = self.get_feature_names()
        codes, extra = [], {}
        for j, (f, idx) in enumerate(self.terms_):
            if isinstance(f, ast.Expression):
                codes.append(_substitute(f, {self.input_names_[i]: args[i] for i in idx}))
            else:
                key = f"_custom{id(self)}_{j}"
                extra[key] = (f, names[j])
                codes.append(f"{key}({', '.join(args[i] for i in idx)})")
        return codes, extra

    @property
    def portable(self) -> bool:
        """Whether every function is an expression (the library can be saved)."""
        return not isinstance(self.functions, str) and all(
            isinstance(f, str) for f in self.functions
        )


class ConcatLibrary(BaseLibrary):
    """The features of several libraries side by side (what ``lib_a + lib_b`` builds)."""

    def __init__(self, libraries: Sequence[BaseLibrary]):
        self.libraries = libraries

    def fit(self, x, y=None, input_names=None) -> ConcatLibrary:
        x = self._fit_inputs(x, input_names)
        if not self.libraries or not all(isinstance(lib, BaseLibrary) for lib in self.libraries):
            raise ValueError("libraries must be a non-empty sequence of libraries")
        # Fitted copies: the parameters stay as given (scikit-learn's convention).
        self.libraries_ = [
            clone(lib).fit(x, input_names=self.input_names_) for lib in self.libraries
        ]
        self.n_output_features_ = sum(lib.n_output_features_ for lib in self.libraries_)
        return self

    def transform(self, x) -> np.ndarray:
        x = self._check_transform_input(x)
        return np.hstack([lib.transform(x) for lib in self.libraries_])

    def input_columns(self, k: int) -> np.ndarray | None:
        self._check_fitted()
        parts, start = [], 0
        for lib in self.libraries_:
            cols = lib.input_columns(k)
            if cols is None:
                return None
            parts.append(start + np.asarray(cols, dtype=int))
            start += lib.n_output_features_
        return np.concatenate(parts)

    def transform_columns(self, x, columns) -> np.ndarray:
        x = self._check_transform_input(x)
        columns = np.asarray(columns, dtype=int).reshape(-1)
        order = np.argsort(columns, kind="stable")  # each library's columns in turn
        ordered = columns[order]
        out = np.empty((x.shape[0], columns.size))
        done, start = 0, 0
        for lib in self.libraries_:
            end = start + lib.n_output_features_
            mine = ordered[(ordered >= start) & (ordered < end)] - start
            if mine.size:
                out[:, order[done : done + mine.size]] = lib.transform_columns(x, mine)
                done += mine.size
            start = end
        return out

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        return [name for lib in self.libraries_ for name in lib.get_feature_names(input_names)]

    def term_codes(self, args: Sequence[str]) -> tuple[list[str], dict]:
        self._check_fitted()
        codes, extra = [], {}
        for lib in self.libraries_:
            c, e = lib.term_codes(args)
            codes += c
            extra.update(e)
        return codes, extra
