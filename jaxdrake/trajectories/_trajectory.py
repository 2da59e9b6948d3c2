"""Trajectories: piecewise polynomials in fixed-size buffers (pytrees), evaluable at any time."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

NUM_COEFFICIENTS = 5  # pieces are polynomials of degree <= 4 in the normalized time theta


def eval_polynomial(coefficients, theta):
    """Evaluate $\\sum_j c_j \\theta^j$ by Horner's rule (coefficients: (degree + 1, n))."""
    y = coefficients[-1]
    for c in coefficients[-2::-1]:
        y = y * theta + c
    return y


class Trajectory(eqx.Module):
    r"""A piecewise-polynomial signal, as returned by `simulate` (the notes' `Trajectory`).

    Piece $i$ covers $(t^{start}_i, t^{end}_i]$ and is $x(t) = \sum_{j=0}^{4} c_{ij}\theta^j$
    with $\theta = (t - t^{start}_i)/(t^{end}_i - t^{start}_i)$. Buffers have a fixed size (so a
    trajectory can be returned from `jit`, vmapped and differentiated); only the first
    `num_segments` pieces are used.

    At a jump (a discrete update, an event) the value depends on the side: `"left"` gives
    the limit from before, `"right"` the limit from after. Simulated trajectories default to
    `"left"`, the notes' timing for discrete states (an update computed at $t_k$ holds on
    $(t_k, t_{k+1}]$); zero-order-hold input tapes default to `"right"`.

    A simulated trajectory also holds its system and input source, so `eval(t)` gives the
    system's output $y(t) = g(t, x(t), u(t))$ while `state(t)` gives $x(t)$; a trajectory made
    from samples has no system and `eval` gives the interpolated value. A trajectory can be
    passed as `inputs` to `simulate` (an input tape).
    """

    t_start: jax.Array
    t_end: jax.Array
    coefficients: jax.Array
    num_segments: jax.Array
    t_final: jax.Array
    status: jax.Array
    event_times: jax.Array
    event_indices: jax.Array
    num_events: jax.Array
    num_rejected_steps: jax.Array
    modes: jax.Array | None = None
    event_modes: jax.Array | None = None
    event_states: jax.Array | None = None
    system: Any = None
    inputs: Any = None
    side: str = eqx.field(static=True, default="left")
    dense: bool = eqx.field(static=True, default=True)

    # ----- construction ---------------------------------------------------------------------

    @classmethod
    def from_samples(cls, ts, values, interpolation: str = "linear") -> "Trajectory":
        """A trajectory through samples `values[k]` at times `ts[k]`.

        `interpolation`: `"linear"` (first-order hold) or `"zoh"` (zero-order hold: `values[k]`
        on $[t_k, t_{k+1})$). `values` has shape (len(ts), n) or (len(ts),).
        """
        ts = jnp.asarray(ts, dtype=float)
        values = jnp.asarray(values, dtype=ts.dtype)
        if values.ndim == 1:
            values = values[:, None]
        if ts.ndim != 1 or ts.shape[0] < 2 or values.shape[0] != ts.shape[0]:
            raise ValueError(f"from_samples needs at least two times and one value per time; "
                             f"got ts {ts.shape}, values {values.shape}")
        if not isinstance(ts, jax.core.Tracer) and np.any(np.diff(np.asarray(ts)) <= 0):
            raise ValueError("from_samples needs strictly increasing times")
        zeros = jnp.zeros_like(values[:-1])
        if interpolation == "linear":
            c = [values[:-1], values[1:] - values[:-1]]
            side = "left"
        elif interpolation == "zoh":
            c = [values[:-1], zeros]
            side = "right"
        else:
            raise ValueError(f"unknown interpolation {interpolation!r}; use 'linear' or 'zoh'")
        c += [zeros] * (NUM_COEFFICIENTS - len(c))
        if interpolation == "zoh":  # the last sample holds from t_N on: a zero-length piece
            ts = jnp.concatenate([ts, ts[-1:]])
            c = [jnp.concatenate([ci, v[None]]) for ci, v in zip(c, [values[-1]] + [values[-1] * 0] * 4)]
        return cls.from_pieces(ts[:-1], ts[1:], jnp.stack(c, axis=1), side=side)

    @classmethod
    def from_pieces(cls, t_start, t_end, coefficients, num_segments=None, *,
                    side: str = "left") -> "Trajectory":
        """A trajectory from its pieces: piece i covers $(t^{start}_i, t^{end}_i]$ with
        `coefficients[i]` (shape (5, n)) in the normalized time; only the first `num_segments`
        are used (default all). `side`: the limit taken at a jump."""
        coefficients = jnp.asarray(coefficients)
        if coefficients.ndim != 3 or coefficients.shape[1] != NUM_COEFFICIENTS:
            raise ValueError(f"from_pieces needs coefficients of shape (pieces, {NUM_COEFFICIENTS}, n), "
                             f"got {coefficients.shape}")
        size = coefficients.shape[0]
        used = jnp.asarray(size if num_segments is None else num_segments)
        t_end = jnp.asarray(t_end, coefficients.dtype)
        return cls(t_start=jnp.asarray(t_start, coefficients.dtype), t_end=t_end,
                   coefficients=coefficients, num_segments=used, t_final=t_end[used - 1],
                   status=jnp.asarray(0), event_times=jnp.zeros(0, t_end.dtype),
                   event_indices=jnp.zeros(0, int), num_events=jnp.asarray(0),
                   num_rejected_steps=jnp.asarray(0), modes=jnp.zeros(size, jnp.int32), side=side)

    def __getitem__(self, i) -> "Trajectory":
        """Member i of a batch of trajectories (the result of `jax.vmap(simulate...)`)."""
        if self.t_start.ndim < 2:
            raise IndexError("this trajectory is not a batch: only vmapped trajectories can be indexed")
        return jax.tree.map(lambda leaf: leaf[i] if isinstance(leaf, jax.Array) else leaf, self)

    # ----- evaluation -----------------------------------------------------------------------

    @property
    def num_states(self) -> int:
        return self.coefficients.shape[-1]

    @property
    def t0(self):
        return self.t_start[0]

    @property
    def success(self):
        """True when the simulation reached its final time (or was stopped by a reset)."""
        return (self.status == 0) | (self.status == 6)  # SimulationStatus SUCCESS, STOPPED_BY_RESET

    def _check_dense(self):
        if not self.dense:
            raise ValueError("this trajectory was simulated with dense=False and keeps only the "
                             "final state: use traj.final_state, or simulate with dense=True")

    def _vectorize(self, fn, t):
        t = jnp.asarray(t, dtype=self.t_start.dtype)
        if t.ndim == 0:
            return fn(t)
        if t.ndim == 1:
            return jax.vmap(fn)(t)
        raise ValueError(f"times must be a scalar or a 1-D array, got shape {t.shape}")

    def piece_index(self, t, side: str = "right"):
        """The index of the piece holding time t (at a breakpoint: the piece after it for
        `side="right"`, before it for `"left"`)."""
        return jnp.clip(jnp.searchsorted(self.t_end, t, side=side), 0, self.num_segments - 1)

    def _state_in_piece(self, i, t):
        t0, t1 = self.t_start[i], self.t_end[i]
        width = t1 - t0
        safe = jnp.where(width > 0, width, 1.0)  # zero-length pieces are constants
        theta = jnp.clip(jnp.where(width > 0, (t - t0) / safe, 0.0), 0.0, 1.0)
        return eval_polynomial(self.coefficients[i], theta)

    def _state_at(self, t, side):
        return self._state_in_piece(self.piece_index(t, side), t)

    def eval_piece(self, i, t):
        """The output at time t computed from piece i alone (its one-sided limits at its ends)."""
        x = self._state_in_piece(i, t)
        if self.system is None:
            return x
        return self.system.mode_output(self.modes[i], t, x, self.system.saturate(self.inputs(t)))

    def mode(self, t, side: str | None = None):
        """The active mode at time t (for a hybrid system; 0 otherwise)."""
        side = self._side(side)
        return self._vectorize(lambda s: self.modes[self.piece_index(s, side)], t)

    def state(self, t, side: str | None = None):
        """The state x(t) (shape (n,), or (len(t), n) for an array of times)."""
        self._check_dense()
        side = self._side(side)
        return self._vectorize(lambda s: self._state_at(s, side), t)

    def input(self, t):
        """The input u(t) applied to the system (after its input limits)."""
        if self.system is None:
            raise ValueError("this trajectory has no system, so no input")
        nu = self.system.num_inputs  # without the noise samples of a stochastic system
        return self._vectorize(lambda s: self.system.saturate(self.inputs(s))[:nu], t)

    def eval(self, t, side: str | None = None):
        """The output y(t) = g(t, x(t), u(t)) of the simulated system at any time (dense)."""
        self._check_dense()
        side = self._side(side)
        if self.system is None:
            return self._vectorize(lambda s: self._state_at(s, side), t)

        return self._vectorize(lambda s: self.eval_piece(self.piece_index(s, side), s), t)

    def __call__(self, t):
        """Same as `eval(t)`: a trajectory is a function of time (usable as an input)."""
        return self.eval(t)

    def _side(self, side):
        side = self.side if side is None else side
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        return side

    @property
    def final_state(self):
        """The state at the last time reached (for a batch, of every member): the last piece
        at theta = 1, the sum of its coefficients."""
        last = jnp.asarray(self.num_segments - 1)[..., None, None, None]
        return jnp.take_along_axis(self.coefficients, last, axis=-3)[..., 0, :, :].sum(axis=-2)

    # ----- host-side views ------------------------------------------------------------------

    def breakpoints(self) -> np.ndarray:
        """The times at which pieces start and end (steps, sample times, events), on the host."""
        n = int(self.num_segments)
        return np.unique(np.concatenate([np.asarray(self.t_start[:n]), np.asarray(self.t_end[:n])]))

    @property
    def events(self) -> dict:
        """Events that fired, on the host: `times`; `indices`, the guard that fired (input
        limits first: 2 per input, high then low; then the transitions, so that index
        `2 * num_inputs_with_limits + k` is transition k); `transitions`, k or -1 for an
        input-limit event; `modes`, the mode after the event; `states`, the state after it."""
        n = int(self.num_events)
        indices = np.asarray(self.event_indices[:n])
        out = {"times": np.asarray(self.event_times[:n]), "indices": indices}
        if self.system is not None:
            limit_guards = 2 * self.system.num_inputs if self.system.input_limits is not None else 0
            out["transitions"] = np.where(indices >= limit_guards, indices - limit_guards, -1)
        if self.event_modes is not None:
            out["modes"] = np.asarray(self.event_modes[:n])
            out["states"] = np.asarray(self.event_states[:n])
        return out

    @property
    def num_steps(self) -> int:
        """The number of accepted integration steps (pieces after the initial point)."""
        return int(self.num_segments) - 1

    def sample(self, num: int = 400):
        """Times and outputs for plotting: a uniform grid plus both sides of every breakpoint,
        so that jumps show as vertical lines. Returns (ts, ys) as numpy arrays."""
        self._check_dense()
        t0, tf = float(self.t_start[0]), float(self.t_final)
        grid = np.linspace(t0, tf, num)
        br = self.breakpoints()
        br = br[(br >= t0) & (br <= tf)]
        if len(br) > 4 * num:  # many small steps: the uniform grid already resolves the curve
            br = br[:0]
        ts = np.sort(np.concatenate([grid, br, br]))
        sides = np.zeros(len(ts), bool)
        sides[1:] = ts[1:] == ts[:-1]  # the second copy of a repeated time takes the right limit
        left = np.asarray(self.eval(jnp.asarray(ts), side="left"))
        right = np.asarray(self.eval(jnp.asarray(ts), side="right"))
        ys = np.where(sides[:, None], right, left)
        return ts, ys

    def plot(self, ax=None, outputs=None, **kwargs):
        """Plot outputs against time with matplotlib (the notes' `fnplt`); returns the figure.

        `outputs`: indices or coordinate names of the outputs to draw (default all).
        Outputs of discrete-time systems are drawn as held values with a dot at each sample.
        """
        import matplotlib.pyplot as plt

        if ax is None:
            fig, ax = plt.subplots(figsize=(6, 3.5), layout="constrained")
        fig = ax.figure
        ts, ys = self.sample()
        frame = None if self.system is None else self.system.output_frame
        names = (list(frame.coordinates) if frame is not None
                 else [f"y{i}" for i in range(ys.shape[1])])
        if outputs is None:
            outputs = range(ys.shape[1])
        idx = [names.index(o) if isinstance(o, str) else int(o) for o in outputs]
        discrete = (self.system is not None and self.system.has_discrete_state
                    and not self.system.has_continuous_state)
        for i in idx:
            line, = ax.plot(ts, ys[:, i], label=names[i], **kwargs)
            if discrete:
                dt = min(self.system.sample_times)  # the fastest rate of a multi-rate system
                tk = np.arange(np.ceil(ts[0] / dt), np.floor(ts[-1] / dt) + 1) * dt
                ax.plot(tk, np.asarray(self.eval(jnp.asarray(tk)))[:, i], "o", ms=4,
                        color=line.get_color())
        ax.set_xlabel("t")
        if frame is not None:
            ax.set_title(frame.name)
        if len(idx) > 1 or frame is not None:
            ax.legend(loc="best")
        ax.grid(True, alpha=0.3)
        return fig
