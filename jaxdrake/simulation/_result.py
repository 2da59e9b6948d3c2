"""`SimulatedTrajectory`: what `simulate` returns — the state as a piecewise polynomial, plus the
simulation's status, events, system and input source, so `eval(t)` is the output y(t)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import Reported
from ..trajectories import NUM_COEFFICIENTS, Trajectory, check_side, compiled_when_eager, plot_signal, sample_signal, vectorize_in_time
from ._events import event_transitions
from ._status import SimulationStatus


class SimulatedTrajectory(eqx.Module, Reported):
    r"""The result of `simulate` (the notes' `Trajectory` of a simulation): a pytree, so it can
    be returned from `jit`, batched by `vmap` (index a batch with `traj[i]`) and differentiated.

    - `state_trajectory`: x(t) as a `Trajectory` (one piece per accepted step, in the
      solver's dense output; left-continuous at jumps, the notes' timing for discrete states).
    - `modes`: the hybrid mode of each piece.
    - `t_final`, `status` (a `SimulationStatus` code: 0 SUCCESS, 1 MAX_STEPS_REACHED, 2
      NONFINITE_STATE, 3 STEP_SIZE_TOO_SMALL, ...; `jd.SimulationStatus(int(s)).name` names
      one of a vmapped batch; `success`, True when the final time was reached or a reset
      stopped it, and `message` from it), `num_accepted_steps`, `num_rejected_steps`.
    - `event_times`, `event_indices`, `event_modes`, `event_states`, `num_events`: the
      events, in fixed-size buffers (`events` gives them on the host).
    - `system`, `inputs`: the simulated system and its input source, so `eval(t)` gives the
      output $y(t) = g(t, x(t), u(t))$ and `input(t)` the input u(t).
    - `dense`: False when only the initial and final states were kept.
    """

    state_trajectory: Trajectory
    modes: jax.Array
    t_final: jax.Array
    status: jax.Array
    event_times: jax.Array
    event_indices: jax.Array
    event_modes: jax.Array
    event_states: jax.Array
    num_events: jax.Array
    num_rejected_steps: jax.Array
    num_accepted_steps: jax.Array
    system: Any
    inputs: Any
    dense: bool = eqx.field(static=True, default=True)
    status_type = SimulationStatus

    # ----- the pieces -----------------------------------------------------------------------

    @property
    def t_start(self):
        return self.state_trajectory.t_start

    @property
    def t_end(self):
        return self.state_trajectory.t_end

    @property
    def coefficients(self):
        return self.state_trajectory.coefficients

    @property
    def num_segments(self):
        return self.state_trajectory.num_segments

    @property
    def side(self) -> str:
        return self.state_trajectory.side

    @property
    def num_states(self) -> int:
        return self.state_trajectory.num_states

    @property
    def t0(self):
        return self.state_trajectory.t0

    @property
    def num_steps(self) -> int:
        """The number of accepted integration steps (also when `dense=False`), a Python int
        read on the host; inside `jit`, use the array `num_accepted_steps`."""
        return int(self.num_accepted_steps)

    def __getitem__(self, i) -> "SimulatedTrajectory":
        """Member i of a batch (the result of `jax.vmap(simulate...)`)."""
        if self.t_start.ndim < 2:
            raise IndexError("this trajectory is not a batch: only vmapped trajectories can be indexed")
        return jax.tree.map(lambda leaf: leaf[i] if isinstance(leaf, jax.Array) else leaf, self)

    # ----- the outcome ----------------------------------------------------------------------

    @property
    def events(self) -> dict:
        """Events that fired, on the host: `times`; `indices`, the guard that fired (input
        limits first: 2 per input, high then low; then the transitions, so that index
        `2 * num_inputs_with_limits + k` is transition k); `transitions`, k or -1 for an
        input-limit event; `modes`, the mode after the event; `states`, the state after it."""
        n = int(self.num_events)
        indices = np.asarray(self.event_indices[:n])
        return {"times": np.asarray(self.event_times[:n]), "indices": indices,
                "transitions": event_transitions(self.system, indices),
                "modes": np.asarray(self.event_modes[:n]), "states": np.asarray(self.event_states[:n])}

    # ----- evaluation -----------------------------------------------------------------------

    def _check_dense(self):
        if not self.dense:
            raise ValueError("this trajectory was simulated with dense=False and keeps only the "
                             "final state: use traj.final_state, or simulate with dense=True")

    def _vectorize(self, fn, t):
        return vectorize_in_time(fn, t, self.t_start.dtype)

    @compiled_when_eager
    def mode(self, t, side: str | None = None):
        """The active mode at time t (for a hybrid system; 0 otherwise)."""
        side = check_side(self.side if side is None else side)
        return self._vectorize(lambda s: self.modes[self.state_trajectory.piece_index(s, side)], t)

    def state(self, t, side: str | None = None):
        """The state x(t) (shape (n,), or (len(t), n) for an array of times). Outside
        [t0, t_final] it holds the value at the nearer end (no extrapolation, as Drake's
        trajectories); a simulation that failed inside `jit` ends at its `t_final`. Float32
        steps shorter than t's spacing (a contact's stick) share their ends' float time: there
        x(t) is the state when time first reached it (`final_state` is the last state)."""
        self._check_dense()
        return self.state_trajectory.eval(t, side)

    @compiled_when_eager
    def input(self, t):
        """The input u(t) applied to the system (after its input limits)."""
        nu = self.system.num_inputs  # without the noise samples of a stochastic system
        return self._vectorize(lambda s: self.system.saturate(self.inputs(s))[:nu], t)

    def eval_piece(self, i, t):
        """The output at time t computed from piece i alone (its one-sided limits at its ends)."""
        x = self.state_trajectory.eval_piece(i, t)
        return self.system.mode_output(self.modes[i], t, x, self.system.saturate(self.inputs(t)))

    def piece_index(self, t, side: str = "right"):
        return self.state_trajectory.piece_index(t, side)

    def next_breakpoint(self, t):
        return self.state_trajectory.next_breakpoint(t)

    @compiled_when_eager
    def eval(self, t, side: str | None = None):
        """The output y(t) = g(t, x(t), u(t)) of the simulated system at any time (dense), with
        x held at the nearer end outside [t0, t_final] (as `state`)."""
        self._check_dense()
        side = check_side(self.side if side is None else side)
        return self._vectorize(lambda s: self.eval_piece(self.piece_index(s, side), s), t)

    def __call__(self, t):
        """Same as `eval(t)`: a simulated trajectory is a function of time (usable as an input)."""
        return self.eval(t)

    @property
    def final_state(self):
        """The state at the last time reached (for a batch, of every member)."""
        return self.state_trajectory.final_value

    # ----- host-side views ------------------------------------------------------------------

    def breakpoints(self) -> np.ndarray:
        """The times at which pieces start and end (steps, sample times, events), on the host."""
        return self.state_trajectory.breakpoints()

    def sample(self, num: int = 400):
        """Times and outputs for plotting: a uniform grid plus both sides of every breakpoint,
        so that jumps show as vertical lines. Returns (ts, ys) as numpy arrays."""
        self._check_dense()
        return sample_signal(self.eval, float(self.t_start[0]), float(self.t_final), self.breakpoints(), num)

    def plot(self, ax=None, outputs=None, **kwargs):
        """Plot outputs against time with matplotlib (the notes' `fnplt`); returns the figure.

        `outputs`: indices or coordinate names of the outputs to draw (default all).
        Outputs of discrete-time systems are drawn as held values with a dot at each sample.
        """
        ts, ys = self.sample()
        frame = self.system.output_frame
        held = None
        if self.system.has_discrete_state and not self.system.has_continuous_state:
            dt = min(self.system.sample_times)  # the fastest rate of a multi-rate system
            tk = np.arange(np.ceil(ts[0] / dt), np.floor(ts[-1] / dt) + 1) * dt
            held = (tk, np.asarray(self.eval(jnp.asarray(tk))))
        return plot_signal(ts, ys, list(frame.coordinates), frame.name, outputs, ax=ax, held_samples=held, **kwargs)


def trajectory_bytes(num_states: int, max_steps: int, max_events: int, dense: bool, itemsize: int) -> int:
    """Bytes of one trajectory's buffers: per piece its polynomial (NUM_COEFFICIENTS x n),
    start, end and mode; per event its state, time, index and mode."""
    pieces = (max_steps + 1 if dense else 2) * (NUM_COEFFICIENTS * num_states + 3)
    return (pieces + max_events * (num_states + 3)) * itemsize
