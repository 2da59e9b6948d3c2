"""Systems: the System contract, frames and the special cases (LTI, ...)."""

from ._frame import Frame
from ._linear import LinearSystem
from ._system import FunctionSystem, System

__all__ = ["Frame", "FunctionSystem", "LinearSystem", "System"]
