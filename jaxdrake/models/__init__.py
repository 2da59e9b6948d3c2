"""The plants of the notes, with their parameters named as there."""

from ._hybrid import BallFlightPhasePlant, BouncingBall, RimlessWheel, RimlessWheelStance
from ._pendulum import Pendulum
from ._simple import (DoubleIntegrator, LinearGaussianExample, SimpleCTExample, SimpleDTExample,
                      SimpleMixedCTDTExample, VanDerPol)

__all__ = ["BallFlightPhasePlant", "BouncingBall", "DoubleIntegrator", "LinearGaussianExample", "Pendulum", "RimlessWheel",
           "RimlessWheelStance", "SimpleCTExample", "SimpleDTExample", "SimpleMixedCTDTExample",
           "VanDerPol"]
