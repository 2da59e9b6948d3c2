"""`TrajectorySource`: a trajectory as a system, the notes' input tape (D.3.6)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..trajectories import Trajectory
from ._frame import Frame
from ._system import System


class TrajectorySource(System):
    r"""A source without state or input whose output is a trajectory's value, $y(t) =
    \mathrm{traj}(t)$ — the notes' idiom "to simulate with an input tape, cascade a Trajectory
    object describing u(t) with the system" (`cascade(trajectory, system)` builds one).

    The tape's breakpoints are the source's (`next_breakpoint`): the simulator ends a step on
    each and evaluates, within a step, the piece the step started in — the same steps as
    `simulate(system, ..., inputs=trajectory)`, in a diagram too.
    """

    trajectory: Trajectory
    piece: jax.Array | None = None  # set by `on_step`: the piece the current step reads

    def __init__(self, trajectory: Trajectory, output_frame: Frame | None = None, piece=None):
        if not isinstance(trajectory, Trajectory):
            raise TypeError(f"TrajectorySource needs a jaxdrake.Trajectory, got {type(trajectory).__name__}")
        self.trajectory, self.piece = trajectory, piece
        super().__init__(num_outputs=trajectory.num_states, direct_feedthrough=False, time_invariant=False,
                         output_frame=output_frame)

    has_breakpoints = True

    def next_breakpoint(self, t):
        return self.trajectory.next_breakpoint(t).astype(jnp.asarray(t).dtype)

    def on_step(self, t):
        return TrajectorySource(self.trajectory, self.output_frame, self.trajectory.piece_index(t))

    def output(self, t, x, u):
        if self.piece is None:
            return self.trajectory.eval(t)
        return self.trajectory.eval_piece(self.piece, t)
