"""Systems: the System contract, frames, the special cases (LTI, hybrid, stochastic), their
combinations (cascade, feedback, parallel, diagrams), polynomial systems and Drake's primitive blocks."""

from ._combinators import cascade, feedback, parallel
from ._diagram import Diagram, DiagramBuilder
from ._frame import Frame, add_frame_conversion
from ._hybrid import HybridSystem, Transition, and_guards, not_guard
from ._linear import LinearSystem
from ._polynomial_system import PolynomialSystem
from ._primitives import (Adder, Demultiplexer, DiscreteTimeDelay, FirstOrderLowPassFilter, Gain, Multiplexer,
                          PidController, Saturation, ZeroOrderHold)
from ._signal_blocks import ConstantVectorSource, RandomDistribution, RandomSource, Sine, WrapToSystem
from ._source import TrajectorySource
from ._stochastic import StochasticSystem
from ._system import FunctionSystem, System, check_initialised, require_plain_system

__all__ = ["Adder", "ConstantVectorSource", "Demultiplexer", "DiscreteTimeDelay", "FirstOrderLowPassFilter", "Gain",
           "Multiplexer", "PidController", "RandomDistribution", "RandomSource", "Saturation", "Sine", "WrapToSystem",
           "ZeroOrderHold",
           "Diagram", "DiagramBuilder", "Frame", "FunctionSystem", "HybridSystem", "LinearSystem",
           "PolynomialSystem",
           "StochasticSystem", "System", "TrajectorySource", "Transition", "add_frame_conversion", "and_guards",
           "cascade", "feedback", "not_guard", "parallel",
           "check_initialised", "require_plain_system"]
