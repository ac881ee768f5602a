"""Compiled kernels (Numba), compiled on first use and cached on disk.

A module marks its kernels with a :class:`Kernels` instance made from its globals and
calls :meth:`Kernels.compile` before the first call: every marked function is then
replaced by its compiled version at once (a compiled function resolves the helpers it
calls among the module's globals when it is first compiled, so all are replaced
before any runs).  ``import robust_sindy`` does not import Numba; the first kernel call
in a fresh installation compiles (seconds), later processes load the cache.
"""

from __future__ import annotations

import importlib.util

__all__ = ["AVAILABLE", "Kernels"]

#: Whether Numba is installed (a dependency; without it the NumPy code does the work).
AVAILABLE = importlib.util.find_spec("numba") is not None


class Kernels:
    """Registry of one module's kernels (use an instance as a decorator)."""

    def __init__(self, namespace: dict):
        self._namespace = namespace
        self._names: list[str] = []
        self._ready = False

    def __call__(self, f):
        self._names.append(f.__name__)
        return f

    def compile(self) -> None:
        """Replace the marked functions by their compiled versions (once)."""
        if self._ready:
            return
        import numba

        for name in self._names:
            self._namespace[name] = numba.njit(cache=True, nogil=True)(self._namespace[name])
        self._ready = True
