"""Simulation: the jit-compiled loop, its solvers, step-size controllers and status."""

from ._controller import AbstractStepSizeController, ConstantStepSize, IController
from ._ensemble import EnsembleResult, simulate_ensemble
from ._inputs import leaves_to_arrays
from ._loop import project_to_constraints
from ._result import SimulatedTrajectory
from ._simulate import simulate
from ._solvers import RK4, AbstractExplicitRungeKutta, AbstractSolver, Dopri5, Euler, Midpoint, Ros34PW2, Rosenbrock23
from ._step import FIXED_STEP_RULES, discrete_step
from ._status import SimulationError, SimulationStatus

__all__ = ["FIXED_STEP_RULES", "RK4", "AbstractExplicitRungeKutta", "AbstractSolver", "AbstractStepSizeController",
           "ConstantStepSize", "Dopri5", "EnsembleResult", "Euler", "IController", "Midpoint", "Ros34PW2", "Rosenbrock23",
           "SimulatedTrajectory", "SimulationError", "SimulationStatus", "discrete_step", "leaves_to_arrays", "project_to_constraints", "simulate",
           "simulate_ensemble"]
