"""Trajectories: piecewise polynomials in fixed-size buffers, usable as input tapes."""

from ._trajectory import Trajectory

__all__ = ["Trajectory"]
