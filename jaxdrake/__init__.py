"""jaxdrake: Drake's ideas for modelling, simulating and controlling dynamical systems, in JAX."""

from ._xla import prefer_fast_cpu_compilation, use_compilation_cache

prefer_fast_cpu_compilation()

from . import (analysis, control, estimation, geometry, models, mujoco, multibody, planning, polynomials, simulation,
               systems, trajectories, viz)  # noqa: E402
from .control import linearize
from .multibody import CouplerConstraint, LoopConstraint, RigidBodySystem
from .mujoco import MujocoSystem
from .polynomials import Polynomial
from .simulation import EnsembleResult, SimulatedTrajectory, SimulationError, SimulationStatus, simulate, simulate_ensemble
from .systems import (Diagram, DiagramBuilder, Frame, HybridSystem, LinearSystem, PolynomialSystem, StochasticSystem,
                      System, TrajectorySource, Transition, add_frame_conversion, and_guards, cascade, feedback,
                      not_guard, parallel)
from .systems import (Adder, ConstantVectorSource, Demultiplexer, DiscreteTimeDelay, FirstOrderLowPassFilter, Gain,
                      Multiplexer, PidController, RandomDistribution, RandomSource, Saturation, Sine, WrapToSystem,
                      ZeroOrderHold)
from .trajectories import Trajectory
from ._batch import run_batch

from ._version import __version__

_LAZY_PACKAGES = ("lcm", "ros", "trajopt")  # heavier imports (LCM bindings, DDS, IPOPT), loaded on first use


def __getattr__(name):
    """`jd.trajopt`, `jd.lcm` and `jd.ros` without `import jaxdrake.trajopt` first (and without slowing
    `import jaxdrake`): imported on first access."""
    if name in _LAZY_PACKAGES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'jaxdrake' has no attribute {name!r}")

__all__ = ["Adder", "ConstantVectorSource", "Demultiplexer", "DiscreteTimeDelay", "FirstOrderLowPassFilter", "Gain",
           "Multiplexer", "PidController", "RandomDistribution", "RandomSource", "Saturation", "Sine", "WrapToSystem",
           "ZeroOrderHold",
           "Diagram", "DiagramBuilder", "EnsembleResult", "Frame", "HybridSystem", "LinearSystem", "SimulationError",
           "CouplerConstraint", "LoopConstraint", "MujocoSystem", "Polynomial", "PolynomialSystem", "RigidBodySystem", "SimulatedTrajectory", "SimulationStatus", "StochasticSystem", "System", "Trajectory", "TrajectorySource", "Transition",
           "add_frame_conversion", "analysis", "and_guards", "cascade", "control", "estimation", "feedback", "geometry", "lcm", "linearize", "models", "mujoco", "multibody", "not_guard",
           "parallel", "planning", "polynomials", "ros", "run_batch", "simulate", "simulate_ensemble", "simulation", "systems", "trajectories", "trajopt",
           "use_compilation_cache", "viz"]

