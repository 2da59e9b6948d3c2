"""jaxdrake: Drake's ideas for modelling, simulating and controlling dynamical systems, in JAX."""

from . import models, simulation, systems, trajectories
from .simulation import SimulationError, SimulationStatus, simulate
from .systems import Frame, LinearSystem, System
from .trajectories import Trajectory

__version__ = "0.1.0"

__all__ = ["Frame", "LinearSystem", "SimulationError", "SimulationStatus", "System",
           "Trajectory", "models", "simulate", "simulation", "systems", "trajectories"]
