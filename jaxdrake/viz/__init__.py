"""Visualizers (the notes, D.3.7): systems whose input is a plant's state, that draw it, play a
simulated trajectory back and write movies (.gif, .mp4, .html)."""

from ._planar import (BouncingBallVisualizer, CartPoleVisualizer, CompassGaitVisualizer, PendulumVisualizer,
                      PlanarQuadrotorVisualizer, PlanarRigidBodyVisualizer, RimlessWheelVisualizer,
                      visualizer_for)
from ._visualizer import DRAW_PERIOD, Visualizer

__all__ = ["DRAW_PERIOD", "BouncingBallVisualizer", "CartPoleVisualizer", "CompassGaitVisualizer",
           "PendulumVisualizer", "PlanarQuadrotorVisualizer", "PlanarRigidBodyVisualizer",
           "RimlessWheelVisualizer", "Visualizer", "visualizer_for"]
