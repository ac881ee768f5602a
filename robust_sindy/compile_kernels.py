"""Compile the kernels of this installation: ``python -m robust_sindy.compile_kernels``.

:mod:`robust_sindy.core.compiled` starts it in the background the first time the
kernels are needed and not compiled yet.  It runs small identifications (measured and
estimated derivatives, so that every kernel is compiled for the argument types it is
called with), which fill Numba's disk cache, and writes the marker (``ok``, or
``failed: reason``).  Running it by hand compiles the kernels before a first fit.
"""

from __future__ import annotations

import os
import sys
import warnings

import numpy as np

__all__ = ["main", "warm_up"]


def warm_up() -> None:
    """Two small identifications of Lorenz's equations, kernels compiled in this process
    (as they are called in real fits)."""
    from .estimator import HuberSINDy
    from .library import PolynomialLibrary
    from .systems import Lorenz

    previous = os.environ.get("ROBUST_SINDY_KERNELS")
    os.environ["ROBUST_SINDY_KERNELS"] = "wait"
    try:
        data = Lorenz().generate(t_end=3.0)
        rng = np.random.default_rng(0)
        x = data.x + 1e-3 * rng.normal(size=data.x.shape)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, data.t, x_dot=data.x_dot)
            HuberSINDy(library=PolynomialLibrary(degree=2)).fit(x, data.t)
    finally:
        if previous is None:
            os.environ.pop("ROBUST_SINDY_KERNELS", None)
        else:
            os.environ["ROBUST_SINDY_KERNELS"] = previous


def main(argv=None) -> int:
    from .core import compiled
    from .solvers import _kernel
    from .timeseries import _temporal_kernels

    argv = sys.argv[1:] if argv is None else argv
    path = compiled.marker() if not argv else compiled.Path(argv[0])
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        warm_up()
    broken = None
    if not (_kernel.usable() and _temporal_kernels.usable()):
        broken = _kernel.failure_reason() or _temporal_kernels.failure_reason()
    tmp = path.with_suffix(".tmp")
    tmp.write_text("ok" if broken is None else f"failed: {broken}")
    tmp.replace(path)
    path.with_suffix(".lock").unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
