"""Named linear constraints on the coefficient matrix, read from the library's names.

Each helper returns a :class:`~robust_sindy.core.constraints.LinearConstraints` for a
coefficient matrix of shape (terms, equations); combine them with ``+`` and pass the
result to :func:`robust_sindy.fit` (``constraints=``).  Terms are named as the library
names them (``library.get_feature_names()``; PySINDy's names, ``"x0 x1"`` for a
product, are read too), equations by their index or by the name
of their state (``states``; by default the library's linear terms, so give ``states``
or ``n_equations`` when the library has control inputs).

* :func:`energy_preserving`: the quadratic part of the right-hand side conserves
  ``|x|^2 / 2`` (``sum_i x_i f_i(x)`` has no cubic terms): for states ``a <= b <= c``
  the coefficients of ``x_b x_c`` in equation ``a``, of ``x_a x_c`` in ``b`` and of
  ``x_a x_b`` in ``c`` sum to zero (each distinct permutation of the index triple
  counted once).  Quadratic models of fluids (Galerkin models of POD amplitudes) have
  this structure; a model without it may blow up.
* :func:`fixed`: a coefficient known from physics.
* :func:`equal` and :func:`antisymmetric`: two coefficients equal, or opposite.
* :func:`sign`: a coefficient at least (``"+"``) or at most (``"-"``) zero.

Examples
--------
>>> from robust_sindy import PolynomialLibrary
>>> import numpy as np
>>> library = PolynomialLibrary(degree=2).fit(np.zeros((1, 2)))
>>> energy_preserving(library.get_feature_names())
LinearConstraints(4 equalities, 0 inequalities on 6 terms x 2 equations)
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from itertools import combinations_with_replacement

import numpy as np

from .core.constraints import LinearConstraints

__all__ = [
    "antisymmetric",
    "energy_preserving",
    "equal",
    "fixed",
    "sign",
]


def _states(names: Sequence[str], states, n_equations) -> list[str]:
    if states is None and n_equations is None:
        # The library's linear terms: the states, unless it has controls.
        states = [f for f in names if f != "1" and not _PRODUCT.search(f) and "^" not in f]
        if not states:
            raise ValueError("give states (the names of the equations' states) or n_equations")
    if states is None:
        return [f"x{i}" for i in range(int(n_equations))]
    states = [str(s) for s in states]
    if len(set(states)) != len(states):
        raise ValueError(f"states must be distinct; got {states}")
    return states


#: A product in a feature name: ``"x0*x1"`` here, ``"x0 x1"`` in PySINDy's libraries.
_PRODUCT = re.compile(r"[*\s]+")


def _monomial(name: str, states: list[str]) -> tuple[int, ...] | None:
    """The state indices of a monomial name (``"x0*x1"`` or PySINDy's ``"x0 x1"``,
    ``"x2^2"``; sorted), or None when the name is not a product of states (a constant,
    a control, a function)."""
    if name == "1":
        return ()
    out = []
    for part in _PRODUCT.split(name.strip()):
        base, _, power = part.partition("^")
        if base not in states:
            return None
        try:
            k = int(power) if power else 1
        except ValueError:
            return None
        out += [states.index(base)] * k
    return tuple(sorted(out))


def _position(value, names: list[str], out_of_range: str, unknown: str) -> int:
    """The index ``value`` (checked against ``len(names)``) or the position of the name
    ``value`` in ``names``; ``ValueError`` with the message that fits otherwise."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        if not 0 <= value < len(names):
            raise ValueError(out_of_range)
        return int(value)
    if value not in names:
        raise ValueError(unknown)
    return names.index(value)


class _Index:
    """Positions in ``vec(Xi)`` of (term, equation) pairs given by name or index."""

    def __init__(self, feature_names, states, n_equations):
        self.names = [str(f) for f in feature_names]
        self.states = _states(self.names, states, n_equations)
        self.p, self.n = len(self.names), len(self.states)

    def term(self, term) -> int:
        return _position(
            term, self.names, f"term index {term} is out of range for {self.p} terms",
            f"no library term named {term!r}; the terms are {self.names}",
        )  # fmt: skip

    def equation(self, equation) -> int:
        return _position(
            equation, self.states,
            f"equation {equation} is out of range for {self.n} equations",
            f"no equation for a state named {equation!r}: {self.states}",
        )  # fmt: skip

    def at(self, term, equation) -> int:
        return self.equation(equation) * self.p + self.term(term)

    def label(self, term, equation) -> str:
        return f"{self.names[self.term(term)]} in ({self.states[self.equation(equation)]})'"

    def row(self) -> np.ndarray:
        return np.zeros(self.p * self.n)


def energy_preserving(
    feature_names: Sequence[str], states: Sequence[str] | None = None, n_equations=None
) -> LinearConstraints:
    """The quadratic terms conserve energy (see the module docstring).

    Parameters
    ----------
    feature_names : sequence of str
        The library's terms; the quadratic monomials of the states must all be there.
    states : sequence of str, optional
        The states, one equation each, as the names spell them (default: the library's
        linear terms, or ``x0, x1, ...`` for ``n_equations`` equations).
    n_equations : int, optional
        The number of equations when ``states`` is not given.
    """
    index = _Index(feature_names, states, n_equations)
    quad = {}
    for j, name in enumerate(index.names):
        mono = _monomial(name, index.states)
        if mono is not None and len(mono) == 2:
            quad[mono] = j
    rows, labels = [], []
    for triple in combinations_with_replacement(range(index.n), 3):
        row = index.row()
        for i in sorted(set(triple)):  # each distinct permutation once
            rest = list(triple)
            rest.remove(i)
            pair = tuple(sorted(rest))
            if pair not in quad:
                names = "*".join(index.states[s] for s in pair)
                raise ValueError(
                    f"energy_preserving needs every quadratic term of the states; "
                    f"{names} is not among the library's terms"
                )
            row[i * index.p + quad[pair]] += 1.0
        rows.append(row)
        labels.append("energy: " + "*".join(index.states[s] for s in triple))
    return LinearConstraints(
        index.p, index.n, np.array(rows), np.zeros(len(rows)), labels_eq=tuple(labels)
    )


def fixed(feature_names, term, equation, value: float, states=None, n_equations=None):
    """The coefficient of ``term`` in ``equation`` is ``value``."""
    index = _Index(feature_names, states, n_equations)
    if not np.isfinite(value):
        raise ValueError(f"value must be finite; got {value!r}")
    row = index.row()
    row[index.at(term, equation)] = 1.0
    return LinearConstraints(
        index.p, index.n, row[None], [float(value)],
        labels_eq=(f"fixed: {index.label(term, equation)} = {value:g}",),
    )  # fmt: skip


def _pair(feature_names, first, second, states, n_equations, factor: float, what: str):
    index = _Index(feature_names, states, n_equations)
    a, b = index.at(*first), index.at(*second)
    if a == b:
        raise ValueError(f"{what} needs two different coefficients; got {first} twice")
    row = index.row()
    row[a], row[b] = 1.0, -factor
    label = f"{what}: {index.label(*first)}, {index.label(*second)}"
    return LinearConstraints(index.p, index.n, row[None], [0.0], labels_eq=(label,))


def equal(feature_names, first, second, states=None, n_equations=None):
    """Two coefficients are equal; ``first`` and ``second`` are ``(term, equation)``."""
    return _pair(feature_names, first, second, states, n_equations, 1.0, "equal")


def antisymmetric(feature_names, first, second, states=None, n_equations=None):
    """Two coefficients are opposite (``first = -second``), ``(term, equation)`` each."""
    return _pair(feature_names, first, second, states, n_equations, -1.0, "antisymmetric")


def sign(feature_names, term, equation, which: str, states=None, n_equations=None):
    """The coefficient of ``term`` in ``equation`` is ``>= 0`` (``which="+"``) or
    ``<= 0`` (``"-"``)."""
    if which not in ("+", "-"):
        raise ValueError(f"which must be '+' or '-'; got {which!r}")
    index = _Index(feature_names, states, n_equations)
    row = index.row()
    row[index.at(term, equation)] = -1.0 if which == "+" else 1.0
    label = f"sign: {index.label(term, equation)} {'>=' if which == '+' else '<='} 0"
    return LinearConstraints(index.p, index.n, A_ub=row[None], b_ub=[0.0], labels_ub=(label,))
