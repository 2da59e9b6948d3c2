"""Systems: the System contract, frames and the special cases (LTI, hybrid, ...)."""

from ._frame import Frame
from ._hybrid import HybridSystem, Transition, and_guards, not_guard
from ._linear import LinearSystem
from ._system import FunctionSystem, System

__all__ = ["Frame", "FunctionSystem", "HybridSystem", "LinearSystem", "System", "Transition",
           "and_guards", "not_guard"]
