"""Simulation: the jit-compiled loop, its solvers and its status."""

from ._simulate import SimulationError, SimulationStatus, project_to_constraints, simulate
from ._solvers import RK4, AbstractSolver, Dopri5, Euler, Midpoint, Rosenbrock23

__all__ = ["AbstractSolver", "Dopri5", "Euler", "Midpoint", "RK4", "Rosenbrock23", "SimulationError",
           "SimulationStatus", "project_to_constraints", "simulate"]
