"""Trajectories: piecewise polynomials in fixed-size buffers, usable as input tapes. The helpers
below are what the simulation's result shares with `Trajectory` (its pieces, its evaluation)."""

from ._trajectory import (NUM_COEFFICIENTS, Trajectory, check_side, compiled_when_eager, eval_polynomial,
                          plot_signal, sample_signal, vectorize_in_time)

__all__ = ["NUM_COEFFICIENTS", "Trajectory", "check_side", "compiled_when_eager", "eval_polynomial",
           "plot_signal", "sample_signal", "vectorize_in_time"]
