"""The plants of the notes, with their parameters named as there."""

from ._hybrid import (BallFlightPhasePlant, BouncingBall, CompassGait, CompassGaitStance, RimlessWheel,
                      RimlessWheelStance)
from ._pendulum import Pendulum
from ._quadrotor import PlanarQuadrotor, Quadrotor
from ._rigid import Acrobot, CartPole, DoublePendulum, Panda
from ._simple import (DoubleIntegrator, LinearGaussianExample, SimpleCTExample, SimpleDTExample,
                      SimpleMixedCTDTExample, VanDerPol)

__all__ = ["Acrobot", "BallFlightPhasePlant", "BouncingBall", "CartPole", "CompassGait", "CompassGaitStance", "DoubleIntegrator", "DoublePendulum", "LinearGaussianExample", "Panda", "Pendulum", "PlanarQuadrotor", "Quadrotor", "RimlessWheel",
           "RimlessWheelStance", "SimpleCTExample", "SimpleDTExample", "SimpleMixedCTDTExample",
           "VanDerPol"]
