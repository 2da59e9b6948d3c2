"""The plants of the notes, with their parameters named as there."""

from ._pendulum import Pendulum
from ._simple import (DoubleIntegrator, SimpleCTExample, SimpleDTExample, SimpleMixedCTDTExample,
                      VanDerPol)

__all__ = ["DoubleIntegrator", "Pendulum", "SimpleCTExample", "SimpleDTExample",
           "SimpleMixedCTDTExample", "VanDerPol"]
