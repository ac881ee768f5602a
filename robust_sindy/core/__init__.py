"""Numerics with no knowledge of the pipeline: pure functions every layer above uses.

* :mod:`~robust_sindy.core.losses` -- the Huber loss, its derivative and proximal map;
* :mod:`~robust_sindy.core.certificates` -- objective, KKT violation, duality gap;
* :mod:`~robust_sindy.core.scaling` -- robust scales and the standardisation of columns;
* :mod:`~robust_sindy.core.statistics` -- moving-window scales, correlation times;
* :mod:`~robust_sindy.core.validation` -- input checks that name the argument;
* :mod:`~robust_sindy.core.threads`, :mod:`~robust_sindy.core.blas` -- work on the
  machine's cores, BLAS on one thread;
* :mod:`~robust_sindy.core.compiled` -- compiled kernels (Numba), loaded on first use.
"""
