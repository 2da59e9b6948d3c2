"""Visualizers (the notes, D.3.7): systems whose input is a plant's state, that draw it, play a
simulated trajectory back and write movies (.gif, .mp4, .html); URDF robots in 3-D in MeshCat
(`MeshcatVisualizer`, needs the `viz` extra: meshcat, yourdfpy)."""

from ._planar import (BouncingBallVisualizer, CartPoleVisualizer, CompassGaitVisualizer, PendulumVisualizer,
                      PlanarQuadrotorVisualizer, PlanarRigidBodyVisualizer, RimlessWheelVisualizer,
                      visualizer_for)
from ._meshcat import MeshcatVisualizer, SceneRecorder
from ._mujoco import MujocoVisualizer
from ._visualizer import DRAW_PERIOD, Visualizer

__all__ = ["DRAW_PERIOD", "BouncingBallVisualizer", "CartPoleVisualizer", "CompassGaitVisualizer", "MeshcatVisualizer",
           "MujocoVisualizer", "PendulumVisualizer", "PlanarQuadrotorVisualizer", "PlanarRigidBodyVisualizer",
           "RimlessWheelVisualizer", "SceneRecorder", "Visualizer", "visualizer_for"]
