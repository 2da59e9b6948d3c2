"""jaxdrake: Drake's ideas for modelling, simulating and controlling dynamical systems, in JAX."""

from . import models, simulation, systems, trajectories
from .simulation import SimulationError, SimulationStatus, simulate
from .systems import Frame, HybridSystem, LinearSystem, System, Transition, and_guards, not_guard
from .trajectories import Trajectory

__version__ = "0.1.0"

__all__ = ["Frame", "HybridSystem", "LinearSystem", "SimulationError", "SimulationStatus", "System",
           "Trajectory", "Transition", "and_guards", "models", "not_guard", "simulate", "simulation",
           "systems", "trajectories"]
