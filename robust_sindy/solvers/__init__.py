"""Solvers: each module solves the same objective (or a baseline) and returns a SolverOutput.

* :mod:`~robust_sindy.solvers.problem` -- what they share: the prepared (equilibrated)
  library, the options, the output;
* :mod:`~robust_sindy.solvers.newton` -- the batched active-set Newton method (NumPy),
  :mod:`~robust_sindy.solvers._kernel` its compiled twin for small problems;
* :mod:`~robust_sindy.solvers.admm` -- the corrected ADMM;
* :mod:`~robust_sindy.solvers.driver` -- the fast path: Newton first, ADMM for the rest;
* :mod:`~robust_sindy.solvers.reference` -- the CVXPY reference (Clarabel, OSQP);
* :mod:`~robust_sindy.solvers.stls` -- least-squares baselines (STLS, OLS);
* :mod:`~robust_sindy.solvers.chunked` -- the fast path on Dask arrays.
"""

from .admm import solve_admm
from .driver import solve, solve_path
from .problem import DEFAULT_OPTIONS, PAPER_OPTIONS
from .reference import solve_cvxpy
from .stls import solve_ols, solve_stls

__all__ = [
    "DEFAULT_OPTIONS",
    "PAPER_OPTIONS",
    "solve",
    "solve_admm",
    "solve_cvxpy",
    "solve_ols",
    "solve_path",
    "solve_stls",
]
