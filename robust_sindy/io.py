"""Portable model files: a fitted :class:`HuberSINDy` as human-readable JSON (no pickle).

The file holds what the model needs to predict, print and simulate (the library's
specification and input names, the feature names, the coefficients, the number of
controls), what it was fitted with (δ, λ, the selection threshold, the estimator's
parameters that are plain values) and a summary of its diagnostics, with the package
version and a format version.  A loaded model predicts, prints and simulates exactly as
the saved one.  A file holds no code, so the library must be described by data:
``PolynomialLibrary``, ``FourierLibrary``, a ``CustomLibrary`` whose features are
expression strings, and sums of them.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.exceptions import NotFittedError

from ._version import __version__
from .core.constraints import LinearConstraints
from .library import BaseLibrary, ConcatLibrary, CustomLibrary, FourierLibrary, PolynomialLibrary

__all__ = ["FORMAT", "FORMAT_VERSION", "SavedModel", "read_model", "save_model"]

FORMAT = "robust-sindy model"
FORMAT_VERSION = 1


def library_spec(lib: BaseLibrary) -> dict:
    """A JSON-ready description of a library, or a ``ValueError`` naming what is not."""
    if isinstance(lib, PolynomialLibrary):
        return {
            "type": "polynomial",
            "degree": int(lib.degree),
            "include_bias": bool(lib.include_bias),
            "inputs": _inputs_spec(lib),
        }
    if isinstance(lib, FourierLibrary):
        return {
            "type": "fourier",
            "n_frequencies": int(lib.n_frequencies),
            "include_sin": bool(lib.include_sin),
            "include_cos": bool(lib.include_cos),
            "inputs": _inputs_spec(lib),
        }
    if isinstance(lib, CustomLibrary) and lib.portable:
        return {
            "type": "expressions",
            "functions": [str(f) for f in lib.functions],
            "names": None if lib.names is None else [str(v) for v in lib.names],
        }
    if isinstance(lib, ConcatLibrary):
        return {"type": "concat", "libraries": [library_spec(sub) for sub in lib.libraries]}
    raise ValueError(
        f"a {type(lib).__name__} with Python functions cannot be saved portably (a model "
        "file holds no code): give CustomLibrary its features as expression strings, e.g. "
        "CustomLibrary(['sin(x) * y']), or use PolynomialLibrary and FourierLibrary"
    )


def _inputs_spec(lib) -> list | None:
    """A library's ``inputs`` parameter as JSON values."""
    return None if lib.inputs is None else [_plain(v) for v in lib.inputs]


def library_from_spec(spec: dict) -> BaseLibrary:
    kind = spec.get("type")
    if kind == "polynomial":
        return PolynomialLibrary(spec["degree"], spec["include_bias"], spec["inputs"])
    if kind == "fourier":
        return FourierLibrary(
            spec["n_frequencies"], spec["include_sin"], spec["include_cos"], spec["inputs"]
        )
    if kind == "expressions":
        return CustomLibrary(list(spec["functions"]), spec["names"])
    if kind == "concat":
        return ConcatLibrary([library_from_spec(s) for s in spec["libraries"]])
    raise ValueError(f"unknown library type {kind!r} in the model file")


def _plain(value):
    """numpy scalars and arrays as JSON values (lists, floats; inf and NaN as strings)."""
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()] if value.ndim else _plain(value.item())
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if np.isfinite(v) else str(v)
    return value


def _array(value) -> np.ndarray:
    def num(v):
        return [num(x) for x in v] if isinstance(v, list) else float(v)

    return np.array(num(value), dtype=float)


def _fields(obj) -> dict:
    return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}


def _constraints(spec) -> dict | None:
    """A :class:`~robust_sindy.LinearConstraints` (or what a callable built) as plain
    values; None for none or a name (saved with the parameters)."""
    if spec is None or isinstance(spec, str):
        return None
    if not isinstance(spec, LinearConstraints):
        raise ValueError(
            "a model whose constraints are a callable cannot be saved: pass the "
            "LinearConstraints it returns as constraints"
        )
    return {
        "n_terms": spec.n_terms, "n_equations": spec.n_equations,
        "A_eq": _plain(spec.A_eq), "b_eq": _plain(spec.b_eq),
        "A_ub": _plain(spec.A_ub), "b_ub": _plain(spec.b_ub),
        "labels_eq": list(spec.labels_eq), "labels_ub": list(spec.labels_ub),
    }  # fmt: skip


def save_model(model, path) -> Path:
    """Write a fitted :class:`~robust_sindy.HuberSINDy` to ``path`` as JSON; returns the path."""
    if not hasattr(model, "coef_"):
        raise NotFittedError("this model is not fitted yet: call fit before save")
    params = {
        k: _plain(v)
        for k, v in model.get_params(deep=False).items()
        if k != "library" and (v is None or isinstance(v, (str, int, float, bool, np.ndarray)))
    }
    diagnostics = getattr(model, "diagnostics_", None)
    data = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "robust_sindy_version": __version__,
        "library": library_spec(model.library_),
        "input_names": list(model.library_.input_names_),
        "feature_names": list(model.feature_names_),
        "n_control_features": int(model.n_control_features_),
        "terms": model.library_.get_feature_names(),
        "coef": _plain(model.coef_),
        "delta": _plain(model.delta_),
        "lam": _plain(model.lam_),
        "selection_tol": _plain(getattr(model, "selection_tol_", None)),
        "params": params,
        "constraints": _constraints(model.get_params(deep=False).get("constraints")),
        "diagnostics": None
        if diagnostics is None
        else {
            f.name: _plain(getattr(diagnostics, f.name)) for f in dataclasses.fields(diagnostics)
        },
        "equations": model.equations(),
    }
    path = Path(path)
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


@dataclass(frozen=True)
class SavedModel:
    """What a model file holds: the estimator's parameters, its (unfitted) library, and
    the fitted attributes to set (``library_``, ``coef_``, ``delta_``, ...)."""

    params: dict
    library: BaseLibrary
    fitted: dict


def read_model(path) -> SavedModel:
    """Read and check a model file written by :func:`save_model`
    (:func:`robust_sindy.load_model` builds the estimator from it)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read a model file from {str(path)!r}: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{str(path)!r} is not a robust-sindy model file")
    version = data.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise ValueError(
            f"{str(path)!r} has model format version {version!r}; this robust_sindy reads "
            f"up to {FORMAT_VERSION}: upgrade robust_sindy to load it"
        )
    spec = data["library"]
    inputs = data["input_names"]
    library = library_from_spec(spec).fit(np.zeros((1, len(inputs))), input_names=inputs)
    if library.get_feature_names() != data["terms"]:
        raise ValueError(f"{str(path)!r}: the library does not rebuild the saved terms")
    coef = _array(data["coef"])
    fitted = {
        "library_": library,
        "feature_names_": list(data["feature_names"]),
        "n_control_features_": int(data["n_control_features"]),
        "coef_": coef,
        "support_": coef != 0,
        "delta_": _array(data["delta"]),
        "lam_": _array(data["lam"]),
        "diagnostics_summary_": data.get("diagnostics"),
    }
    if data.get("selection_tol") is not None:
        fitted["selection_tol_"] = float(data["selection_tol"])
    params = dict(data["params"])
    saved = data.get("constraints")
    if saved is not None:
        params["constraints"] = LinearConstraints(
            int(saved["n_terms"]), int(saved["n_equations"]),
            _array(saved["A_eq"]).reshape(-1, int(saved["n_terms"]) * int(saved["n_equations"])),
            _array(saved["b_eq"]),
            _array(saved["A_ub"]).reshape(-1, int(saved["n_terms"]) * int(saved["n_equations"])),
            _array(saved["b_ub"]), tuple(saved["labels_eq"]), tuple(saved["labels_ub"]),
        )  # fmt: skip
    return SavedModel(params, library_from_spec(spec), fitted)
