"""Compiled kernels (Numba), compiled once per installation and cached on disk.

A module marks its kernels with a :class:`Kernels` instance made from its globals and
calls :meth:`Kernels.run` for each call: the first call replaces every marked function
by its compiled version at once (a compiled function resolves the helpers it calls among
the module's globals when it is first compiled, so all are replaced before any runs).
``import robust_sindy`` does not import Numba.

Compiling the kernels takes tens of seconds, once per installation; loading them from
Numba's disk cache afterwards takes well under a second.  So that the first fit of a
fresh installation does not wait for the compiler, how the kernels become available is
set by the environment variable ``ROBUST_SINDY_KERNELS``:

* ``background`` (the default): when the kernels have not been compiled yet (no
  :func:`marker`), a separate process compiles them (``python -m
  robust_sindy.compile_kernels``), and until it is done every caller's NumPy code does
  the work (the same iteration, the same certificates; results agree to rounding);
* ``wait``: the first call compiles in this process;
* ``off``: the NumPy code always.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

__all__ = ["AVAILABLE", "KERNEL_MODULES", "MODES", "Kernels", "marker", "mode", "ready"]

#: Whether Numba is installed (a dependency; without it the NumPy code does the work).
AVAILABLE = importlib.util.find_spec("numba") is not None
#: The modules holding kernels (their sources key the marker).
KERNEL_MODULES = ("robust_sindy.solvers._kernel", "robust_sindy.timeseries._temporal_kernels")
#: The values of ``ROBUST_SINDY_KERNELS``.
MODES = ("background", "wait", "off")
#: A compilation that started this long ago and has not finished is taken as dead.
STALE_SECONDS = 600.0

_READY = False
_SPAWNED = False
#: The compiling process, held for the life of this one: a handle collected while the
#: compiler still runs raises ``ResourceWarning: subprocess ... is still running`` in
#: whatever code the collection happens to interrupt (a user's fit).
_CHILD = None
_MARKER: Path | None = None
_STATE_LOCK = threading.Lock()


def mode() -> str:
    """How the kernels become available (``ROBUST_SINDY_KERNELS``, see the module)."""
    value = os.environ.get("ROBUST_SINDY_KERNELS", "background")
    if value not in MODES:
        raise ValueError(f"ROBUST_SINDY_KERNELS must be one of {MODES}; got {value!r}")
    return value


def _key() -> str:
    """What the compiled code depends on: Numba, Python and the kernels' sources."""
    import numba

    digest = hashlib.sha1(f"{numba.__version__} {sys.version}".encode())
    for name in KERNEL_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.origin is not None:
            digest.update(Path(spec.origin).read_bytes())
    return digest.hexdigest()[:16]


def _directory() -> Path:
    """Beside this package's byte code when that is writable (where Numba caches the
    kernels too), else the user's cache folder."""
    own = Path(__file__).resolve().parent / "__pycache__"
    try:
        own.mkdir(exist_ok=True)
        if os.access(own, os.W_OK):
            return own
    except OSError:
        pass
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    path = Path(base) / "robust_sindy"
    path.mkdir(parents=True, exist_ok=True)
    return path


def marker() -> Path:
    """The file that says the kernels of this installation have been compiled: it holds
    ``ok``, or ``failed: reason`` where Numba could not compile them."""
    global _MARKER
    if _MARKER is None:
        _MARKER = _directory() / f"kernels-{_key()}.ready"
    return _MARKER


def _recorded() -> str | None:
    """The marker's content, or None while there is none."""
    try:
        return marker().read_text().strip()
    except OSError:
        return None


def ready() -> bool:
    """Whether the kernels may be compiled in this process now (loaded from the cache
    when they were compiled before); in the background mode, starts their compilation
    in another process the first time they are not ready."""
    global _READY
    if _READY:
        return True
    how = mode()
    if how == "off":
        return False
    if how == "wait":
        _READY = True
        return True
    recorded = _recorded()
    if recorded == "ok":
        _READY = True
        return True
    if recorded is None:
        _spawn(marker())
    return False


def _spawn(path: Path) -> None:
    """Start ``python -m robust_sindy.compile_kernels`` once per process, unless another
    process is compiling already (a fresh lock file beside the marker)."""
    global _SPAWNED, _CHILD
    with _STATE_LOCK:
        if _SPAWNED:
            return
        _SPAWNED = True
        lock = path.with_suffix(".lock")
        try:
            if lock.exists() and time.time() - lock.stat().st_mtime < STALE_SECONDS:
                return
            lock.write_text(str(os.getpid()))
        except OSError:
            return
        env = {**os.environ, "ROBUST_SINDY_KERNELS": "wait"}
        _CHILD = subprocess.Popen(
            [sys.executable, "-m", "robust_sindy.compile_kernels", str(path)],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )


def failure() -> str | None:
    """Why the kernels cannot be compiled here (recorded by the compiling process), or
    None."""
    text = _recorded()
    return text.removeprefix("failed: ") if text and text.startswith("failed") else None


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
        """Whether the kernels can be compiled here (Numba present, no failure seen)."""
        return self.broken is None

    def available(self) -> bool:
        """Whether a call runs compiled now (usable, and compiled or ready to load)."""
        if self.broken is not None:
            return False
        if self._ready or ready():
            return True
        reason = None if mode() == "off" else failure()
        if reason is not None:
            self._disable(reason)
        return False

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
        """Call the kernel ``name``; ``None`` while the kernels are not compiled yet (the
        background mode) or if Numba cannot compile it here (a Numba release that does
        not support this NumPy, say): then a warning says so once, and the caller's
        NumPy code does the work from then on."""
        if not self.available():
            return None
        try:
            self.compile()
            return self._namespace[name](*args)
        except ImportError as exc:
            return self._disable(_reason(exc))
        except Exception as exc:  # Numba's own errors only, told apart here
            from numba.core.errors import NumbaError

            if not isinstance(exc, NumbaError):
                raise
            return self._disable(_reason(exc))

    def _disable(self, reason: str) -> None:
        self.broken = reason
        warnings.warn(
            f"the compiled kernels could not be compiled ({reason}); the NumPy code does "
            "the work (slower on small problems, same results). Installing a Numba "
            "release that supports this NumPy restores them.",
            RuntimeWarning,
            stacklevel=4,
        )


def _reason(exc: Exception) -> str:
    return f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
