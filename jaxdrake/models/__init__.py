"""The plants of the notes, with their parameters named as there."""

from ._hybrid import BallFlightPhasePlant, BouncingBall, RimlessWheel, RimlessWheelStance
from ._pendulum import Pendulum
from ._simple import (DoubleIntegrator, SimpleCTExample, SimpleDTExample, SimpleMixedCTDTExample,
                      VanDerPol)

__all__ = ["BallFlightPhasePlant", "BouncingBall", "DoubleIntegrator", "Pendulum", "RimlessWheel",
           "RimlessWheelStance", "SimpleCTExample", "SimpleDTExample", "SimpleMixedCTDTExample",
           "VanDerPol"]
