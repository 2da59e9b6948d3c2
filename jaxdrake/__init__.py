"""jaxdrake: Drake's ideas for modelling, simulating and controlling dynamical systems, in JAX."""

from . import control, models, multibody, simulation, systems, trajectories
from .control import linearize
from .multibody import LoopConstraint, RigidBodySystem
from .simulation import SimulationError, SimulationStatus, simulate
from .systems import (Diagram, DiagramBuilder, Frame, HybridSystem, LinearSystem, StochasticSystem,
                      System, Transition, add_frame_conversion, and_guards, cascade, feedback,
                      not_guard, parallel)
from .trajectories import Trajectory

__version__ = "0.1.0"

__all__ = ["Diagram", "DiagramBuilder", "Frame", "HybridSystem", "LinearSystem", "SimulationError",
           "LoopConstraint", "RigidBodySystem", "SimulationStatus", "StochasticSystem", "System", "Trajectory", "Transition",
           "add_frame_conversion", "and_guards", "cascade", "control", "feedback", "linearize", "models", "multibody", "not_guard",
           "parallel", "simulate", "simulation", "systems", "trajectories"]
