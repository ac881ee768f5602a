"""Solvers: each module solves the same objective (or a baseline) and returns a SolverOutput."""

from .admm import PAPER_OPTIONS, solve_admm
from .newton import solve_newton
from .reference import solve_cvxpy
from .stls import solve_ols, solve_stls

__all__ = ["PAPER_OPTIONS", "solve_admm", "solve_cvxpy", "solve_newton", "solve_ols", "solve_stls"]
