"""`TrajectorySource`: a trajectory as a system, the notes' input tape (D.3.6)."""

from __future__ import annotations

from ..trajectories import Trajectory
from ._frame import Frame
from ._system import System


class TrajectorySource(System):
    r"""A source without state or input whose output is a trajectory's value, $y(t) =
    \mathrm{traj}(t)$ — the notes' idiom "to simulate with an input tape, cascade a Trajectory
    object describing u(t) with the system" (`cascade(trajectory, system)` builds one).

    The simulator does not see the tape's breakpoints through a diagram; its step-size control
    resolves the kinks. For steps that end exactly on them, pass the tape as
    `simulate(system, ..., inputs=trajectory)` instead.
    """

    trajectory: Trajectory

    def __init__(self, trajectory: Trajectory, output_frame: Frame | None = None):
        if not isinstance(trajectory, Trajectory):
            raise TypeError(f"TrajectorySource needs a jaxdrake.Trajectory, got {type(trajectory).__name__}")
        self.trajectory = trajectory
        super().__init__(num_outputs=trajectory.num_states, direct_feedthrough=False, time_invariant=False,
                         output_frame=output_frame)

    def output(self, t, x, u):
        return self.trajectory.eval(t)
