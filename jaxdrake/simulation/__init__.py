"""Simulation: the jit-compiled loop, its solvers, step-size controllers and status."""

from ._controller import AbstractStepSizeController, ConstantStepSize, IController
from ._loop import project_to_constraints
from ._simulate import simulate
from ._solvers import RK4, AbstractExplicitRungeKutta, AbstractSolver, Dopri5, Euler, Midpoint, Rosenbrock23
from ._step import FIXED_STEP_RULES, discrete_step
from ._status import SimulationError, SimulationStatus

__all__ = ["AbstractExplicitRungeKutta", "AbstractSolver", "AbstractStepSizeController", "ConstantStepSize",
           "FIXED_STEP_RULES", "discrete_step",
           "Dopri5", "Euler", "IController", "Midpoint", "RK4", "Rosenbrock23", "SimulationError",
           "SimulationStatus", "project_to_constraints", "simulate"]
