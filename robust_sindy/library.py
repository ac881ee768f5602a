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

from collections.abc import Callable, Sequence
from itertools import combinations_with_replacement

import numpy as np
from sklearn.base import BaseEstimator, TransformerMixin

from ._validation import as_float_array

__all__ = ["BaseLibrary", "ConcatLibrary", "CustomLibrary", "PolynomialLibrary"]


class BaseLibrary(TransformerMixin, BaseEstimator):
    """Common machinery: input naming, input selection, composition with ``+``."""

    def _fit_inputs(self, x, input_names) -> np.ndarray:
        x = as_float_array(x, "x", (2,))
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

    def _check_fitted(self) -> None:
        if not hasattr(self, "input_names_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet: call fit first")

    def _check_transform_input(self, x) -> np.ndarray:
        self._check_fitted()
        x = as_float_array(x, "x", (2,))
        if x.shape[1] != self.n_features_in_:
            raise ValueError(
                f"x has {x.shape[1]} columns but the library was fitted on "
                f"{self.n_features_in_} inputs {self.input_names_}"
            )
        return x

    def fit_transform(self, x, y=None, input_names=None) -> np.ndarray:
        return self.fit(x, input_names=input_names).transform(x)

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
        d = self.degree
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or d < 0:
            raise ValueError(f"degree must be an integer >= 0; got {d!r}")
        cols = (
            list(range(x.shape[1]))
            if self.inputs is None
            else [self._index(ref, "inputs") for ref in self.inputs]
        )
        start = 0 if self.include_bias else 1
        self.powers_ = [
            tuple(cols[i] for i in combo)
            for deg in range(start, d + 1)
            for combo in combinations_with_replacement(range(len(cols)), deg)
        ]
        self.n_output_features_ = len(self.powers_)
        return self

    def transform(self, x) -> np.ndarray:
        x = self._check_transform_input(x)
        out = np.ones((x.shape[0], self.n_output_features_))
        for j, combo in enumerate(self.powers_):
            for i in combo:
                out[:, j] *= x[:, i]
        return out

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


class CustomLibrary(BaseLibrary):
    """Features given by user functions of named inputs.

    Parameters
    ----------
    functions : sequence of callables
        Each returns one feature, an array of shape (m,), from 1-D input arrays.
    names : sequence of str, optional
        One name per function.  Derived when omitted: ``f(a, b)`` with the function's
        ``__name__`` (``f0, f1, ...`` for lambdas).
    inputs : sequence of sequences of str or int, optional
        For each function, the inputs it receives as positional arguments, in order.
        When omitted every function takes one argument and is applied to each input
        in turn (one feature per function and input).

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
        funcs = list(self.functions)
        if not funcs or not all(callable(f) for f in funcs):
            raise ValueError("functions must be a non-empty sequence of callables")
        if self.inputs is None:
            self.terms_ = [(f, (i,)) for f in funcs for i in range(x.shape[1])]
        else:
            if len(self.inputs) != len(funcs):
                raise ValueError(
                    f"inputs has {len(self.inputs)} entries but there are {len(funcs)} "
                    "functions: give the arguments of each function"
                )
            self.terms_ = [
                (f, tuple(self._index(ref, "inputs") for ref in args))
                for f, args in zip(funcs, self.inputs, strict=True)
            ]
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
                col = np.asarray(f(*(x[:, i] for i in args)), dtype=float)
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
            base = getattr(f, "__name__", "f")
            if base == "<lambda>":
                base = f"f{list(self.functions).index(f)}"
            out.append(f"{base}({', '.join(names[i] for i in args)})")
        return out


class ConcatLibrary(BaseLibrary):
    """The features of several libraries side by side (what ``lib_a + lib_b`` builds)."""

    def __init__(self, libraries: Sequence[BaseLibrary]):
        self.libraries = libraries

    def fit(self, x, y=None, input_names=None) -> ConcatLibrary:
        x = self._fit_inputs(x, input_names)
        if not self.libraries or not all(isinstance(lib, BaseLibrary) for lib in self.libraries):
            raise ValueError("libraries must be a non-empty sequence of libraries")
        for lib in self.libraries:
            lib.fit(x, input_names=self.input_names_)
        self.n_output_features_ = sum(lib.n_output_features_ for lib in self.libraries)
        return self

    def transform(self, x) -> np.ndarray:
        x = self._check_transform_input(x)
        return np.hstack([lib.transform(x) for lib in self.libraries])

    def get_feature_names(self, input_names=None) -> list[str]:
        self._check_fitted()
        return [name for lib in self.libraries for name in lib.get_feature_names(input_names)]
