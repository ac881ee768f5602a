"""How the compiled kernels become available: compiled in the background on a fresh
installation (the NumPy code working meanwhile), in process, or never."""

import warnings

import numpy as np
import pytest

import robust_sindy as rs
from robust_sindy.core import compiled

pytestmark = pytest.mark.skipif(not compiled.AVAILABLE, reason="numba is not installed")


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """A process that has not seen the kernels, its marker in ``tmp_path``, and the
    compiling processes it would start recorded instead of started."""
    started = []
    monkeypatch.setattr(compiled, "_READY", False)
    monkeypatch.setattr(compiled, "_SPAWNED", False)
    monkeypatch.setattr(compiled, "_MARKER", tmp_path / "kernels.ready")
    monkeypatch.setattr(compiled, "_CHILD", None)

    class Child:  # records the command instead of starting it
        def __init__(self, args, **kw):
            started.append(args)

    monkeypatch.setattr(compiled.subprocess, "Popen", Child)
    namespace = {}

    def twice(x):
        return 2.0 * x

    namespace["twice"] = twice
    kernels = compiled.Kernels(namespace)
    kernels(twice)
    return kernels, started, tmp_path / "kernels.ready"


def test_background_mode_starts_one_compilation_and_waits_for_its_marker(fresh, monkeypatch):
    kernels, started, marker = fresh
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "background")
    assert kernels.run("twice", 1.5) is None  # not compiled yet: the caller's NumPy code
    assert kernels.run("twice", 1.5) is None
    assert len(started) == 1 and started[0][1:3] == ["-m", "robust_sindy.compile_kernels"]
    # Its handle is held: collected while the compiler runs, it would warn
    # (ResourceWarning) inside the caller's code.
    assert compiled._CHILD is not None
    assert marker.with_suffix(".lock").exists()
    marker.write_text("ok")  # the compiling process is done
    assert kernels.run("twice", 1.5) == 3.0
    assert len(started) == 1


def test_another_process_compiling_is_not_started_again(fresh, monkeypatch):
    kernels, started, marker = fresh
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "background")
    marker.with_suffix(".lock").write_text("12345")  # a fresh lock: compiling elsewhere
    assert kernels.run("twice", 1.0) is None and started == []


def test_a_recorded_failure_warns_once_and_leaves_the_work_to_numpy(fresh, monkeypatch):
    kernels, started, marker = fresh
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "background")
    marker.write_text("failed: TypingError: no implementation for this NumPy")
    with pytest.warns(RuntimeWarning, match="no implementation for this NumPy"):
        assert kernels.run("twice", 1.0) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert kernels.run("twice", 1.0) is None
    assert started == []


def test_off_and_wait_modes(fresh, monkeypatch):
    kernels, started, _ = fresh
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "off")
    assert kernels.run("twice", 2.0) is None and started == []
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "wait")
    assert kernels.run("twice", 2.0) == 4.0 and started == []
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "sometimes")
    with pytest.raises(ValueError, match="ROBUST_SINDY_KERNELS"):
        compiled.mode()


def test_a_fit_while_the_kernels_compile_reaches_the_same_certified_optimum(monkeypatch, tmp_path):
    from .conftest import lorenz_library

    theta, y = lorenz_library(0)
    compiled_fit = rs.fit(theta, y, delta=1.0, lam=1.0)
    monkeypatch.setattr(compiled, "_READY", False)
    monkeypatch.setattr(compiled, "_SPAWNED", True)  # as if started already
    monkeypatch.setattr(compiled, "_MARKER", tmp_path / "kernels.ready")
    monkeypatch.setenv("ROBUST_SINDY_KERNELS", "background")
    from robust_sindy.solvers import _kernel

    monkeypatch.setattr(_kernel._jit, "_ready", False)
    numpy_fit = rs.fit(theta, y, delta=1.0, lam=1.0)
    assert numpy_fit.converged and compiled_fit.converged
    rel = np.abs(numpy_fit.objective - compiled_fit.objective) / np.abs(compiled_fit.objective)
    assert rel.max() <= 1e-10
