"""Trajectory optimization: direct transcription, direct collocation and multiple shooting as
sparse nonlinear programs (IPOPT or SciPy), and a batched, `vmap`-able iLQR for many small
problems at once."""

from ._ilqr import ILQRResult, ilqr
from ._nlp import NonlinearProgram, SolverResult, Term
from ._program import (DirectCollocation, DirectTranscription, MultipleShooting,
                       TrajectoryOptimizationResult)

__all__ = ["DirectCollocation", "DirectTranscription", "ILQRResult", "MultipleShooting", "NonlinearProgram",
           "SolverResult", "Term", "TrajectoryOptimizationResult", "ilqr"]
