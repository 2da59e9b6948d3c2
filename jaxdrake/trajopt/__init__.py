"""Trajectory optimization: direct transcription, direct collocation and multiple shooting as
sparse nonlinear programs (IPOPT or SciPy), and a batched, `vmap`-able iLQR for many small
problems at once."""

from ._ilqr import ILQRResult, ilqr
from ._nlp import NonlinearProgram, SolverResult, Term
from ._program import (DirectCollocation, DirectTranscription, MultipleShooting,
                       TrajectoryOptimizationResult)
from ._status import ILQRStatus, SolverStatus

__all__ = ["DirectCollocation", "DirectTranscription", "ILQRResult", "ILQRStatus", "MultipleShooting",
           "NonlinearProgram", "SolverResult", "SolverStatus", "Term", "TrajectoryOptimizationResult", "ilqr"]
