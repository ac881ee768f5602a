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
import threading
import warnings

__all__ = ["AVAILABLE", "Kernels"]

#: Whether Numba is installed (a dependency; without it the NumPy code does the work).
AVAILABLE = importlib.util.find_spec("numba") is not None


class Kernels:
    """Registry of one module's kernels (use an instance as a decorator)."""

    def __init__(self, namespace: dict):
        self._namespace = namespace
        self._names: list[str] = []
        self._ready = False
        self._lock = threading.Lock()  # kernels may be first called from several threads
        #: Why the kernels cannot be used (set on a failure to compile), else None.
        self.broken: str | None = None if AVAILABLE else "numba is not installed"

    def __call__(self, f):
        self._names.append(f.__name__)
        return f

    @property
    def usable(self) -> bool:
        return self.broken is None

    def compile(self) -> None:
        """Replace the marked functions by their compiled versions (once)."""
        if self._ready:
            return
        with self._lock:
            if self._ready:
                return
            import numba

            for name in self._names:
                self._namespace[name] = numba.njit(cache=True, nogil=True)(self._namespace[name])
            self._ready = True

    def run(self, name: str, *args):
        """Call the kernel ``name``; ``None`` if Numba cannot compile it here (a Numba
        release that does not support this NumPy, say): then a warning says so once,
        and the caller's NumPy code does the work from then on."""
        if self.broken is not None:
            return None
        try:
            self.compile()
            return self._namespace[name](*args)
        except ImportError as exc:
            return self._disable(exc)
        except Exception as exc:  # Numba's own errors only, told apart here
            from numba.core.errors import NumbaError

            if not isinstance(exc, NumbaError):
                raise
            return self._disable(exc)

    def _disable(self, exc: Exception) -> None:
        self.broken = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
        warnings.warn(
            f"the compiled kernels could not be compiled ({self.broken}); the NumPy "
            "code does the work (slower on small problems, same results). Installing "
            "a Numba release that supports this NumPy restores them.",
            RuntimeWarning,
            stacklevel=4,
        )
