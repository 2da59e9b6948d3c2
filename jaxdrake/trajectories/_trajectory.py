"""Trajectories: piecewise polynomials in fixed-size buffers (pytrees), evaluable at any time.

A `Trajectory` knows nothing of simulation (statuses, events, guards): input tapes, trajectory
optimization results, time-varying LQR gains, and the state of a simulation
(`jaxdrake.simulation.SimulatedTrajectory` holds one) are all `Trajectory`s.
"""

from __future__ import annotations

import functools
from math import comb

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._compiled import compiled_query
from .._numbers import array_module, call_argument, device_array

NUM_COEFFICIENTS = 5  # pieces are polynomials of degree <= 4 in the normalized time theta

# Reversing a piece: sum_j c_j theta^j with theta = 1 - theta' has the coefficients
# c'_k = (-1)^k sum_{j >= k} binom(j, k) c_j.
_REVERSAL = np.array([[(-1) ** k * comb(j, k) for j in range(NUM_COEFFICIENTS)]
                      for k in range(NUM_COEFFICIENTS)], dtype=float)
# Fitting a piece through values at theta = 0, 1/4, ..., 1: the inverse Vandermonde matrix.
_FIT_NODES = np.linspace(0.0, 1.0, NUM_COEFFICIENTS)
_FIT = np.linalg.inv(np.vander(_FIT_NODES, NUM_COEFFICIENTS, increasing=True))


def eval_polynomial(coefficients, theta):
    """Evaluate $\\sum_j c_j \\theta^j$ by Horner's rule (coefficients: (degree + 1, n))."""
    y = coefficients[-1]
    for c in coefficients[-2::-1]:
        y = y * theta + c
    return y


def vectorize_in_time(fn, t, dtype):
    """fn at a scalar time, or mapped over a 1-D array of times."""
    t = jnp.asarray(t, dtype=dtype)
    if t.ndim == 0:
        return fn(t)
    if t.ndim == 1:
        return jax.vmap(fn)(t)
    raise ValueError(f"times must be a scalar or a 1-D array, got shape {t.shape}")


def compiled_when_eager(method):
    """`method(self, t, *options)` as a `compiled_query`, t first made an array of the
    trajectory's dtype: called outside any trace, one compiled program (kept per trajectory
    structure, shape of t and options), not op by op (eager evaluation compiles every
    primitive for every new shape of t, ~20 ms each)."""
    query = compiled_query(method)

    @functools.wraps(method)
    def wrapper(self, t, *options, **named):
        return query(self, call_argument(t, self.t_start.dtype), *options, **named)
    return wrapper


@jax.jit
def _last_piece_end(coefficients, num_segments):
    """Sum of the coefficients of piece num_segments - 1: one compiled call, not op by op."""
    last = jnp.asarray(num_segments - 1)[..., None, None, None]
    return jnp.take_along_axis(coefficients, last, axis=-3)[..., 0, :, :].sum(axis=-2)


def check_side(side):
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    return side


class Trajectory(eqx.Module):
    r"""A piecewise-polynomial signal (the notes' `Trajectory`).

    Piece $i$ covers $(t^{start}_i, t^{end}_i]$ and is $x(t) = \sum_{j=0}^{4} c_{ij}\theta^j$
    with $\theta = (t - t^{start}_i)/(t^{end}_i - t^{start}_i)$. Buffers have a fixed size (so a
    trajectory can be returned from `jit`, vmapped and differentiated); only the first
    `num_segments` pieces are used.

    At a jump the value depends on the side: `"left"` gives the limit from before, `"right"`
    the limit from after (`side` is the default; zero-order-hold tapes use `"right"`). A
    trajectory can be passed as `inputs` to `simulate` (an input tape).
    """

    t_start: jax.Array
    t_end: jax.Array
    coefficients: jax.Array
    num_segments: jax.Array
    side: str = eqx.field(static=True, default="left")

    # ----- construction ---------------------------------------------------------------------

    @classmethod
    def from_samples(cls, ts, values, interpolation: str = "linear") -> "Trajectory":
        """A trajectory through samples `values[k]` at times `ts[k]`.

        `interpolation`: `"linear"` (first-order hold) or `"zoh"` (zero-order hold: `values[k]`
        on $[t_k, t_{k+1})$). `values` has shape (len(ts), n) or (len(ts),).
        """
        xp = array_module(ts, values)  # numbers stay on the host: nothing compiled
        ts = xp.asarray(ts, dtype=float)
        values = xp.asarray(values, dtype=ts.dtype)
        if values.ndim == 1:
            values = values[:, None]
        if ts.ndim != 1 or ts.shape[0] < 2 or values.shape[0] != ts.shape[0]:
            raise ValueError(f"from_samples needs at least two times and one value per time; "
                             f"got ts {ts.shape}, values {values.shape}")
        if not isinstance(ts, jax.core.Tracer) and np.any(np.diff(np.asarray(ts)) <= 0):
            raise ValueError("from_samples needs strictly increasing times")
        zeros = xp.zeros_like(values[:-1])
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
            ts = xp.concatenate([ts, ts[-1:]])
            c = [xp.concatenate([ci, v[None]]) for ci, v in zip(c, [values[-1]] + [values[-1] * 0] * 4)]
        return cls.from_pieces(ts[:-1], ts[1:], xp.stack(c, axis=1), side=side)

    @classmethod
    def from_pieces(cls, t_start, t_end, coefficients, num_segments=None, *,
                    side: str = "left") -> "Trajectory":
        """A trajectory from its pieces: piece i covers $(t^{start}_i, t^{end}_i]$ with
        `coefficients[i]` (shape (5, n)) in the normalized time; only the first `num_segments`
        are used (default all). `side`: the limit taken at a jump."""
        coefficients = device_array(coefficients)
        if coefficients.ndim != 3 or coefficients.shape[1] != NUM_COEFFICIENTS:
            raise ValueError(f"from_pieces needs coefficients of shape (pieces, {NUM_COEFFICIENTS}, n), "
                             f"got {coefficients.shape}")
        size = coefficients.shape[0]
        return cls(t_start=device_array(t_start, coefficients.dtype), t_end=device_array(t_end, coefficients.dtype),
                   coefficients=coefficients, num_segments=device_array(size if num_segments is None else num_segments),
                   side=check_side(side))

    def __getitem__(self, i) -> "Trajectory":
        """Member i of a batch of trajectories (the result of `jax.vmap`)."""
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
    def t_final(self):
        """The end of the last used piece."""
        return jnp.take_along_axis(self.t_end, jnp.asarray(self.num_segments - 1)[..., None], axis=-1)[..., 0]

    def piece_index(self, t, side: str = "right"):
        """The index of the piece holding time t (at a breakpoint: the piece after it for
        `side="right"`, before it for `"left"`)."""
        return jnp.clip(jnp.searchsorted(self.t_end, t, side=side), 0, self.num_segments - 1)

    def next_breakpoint(self, t):
        """The first end of a used piece after time t (inf past the last): where a simulation
        that reads this trajectory as an input must end a step."""
        valid = (jnp.arange(self.t_end.shape[0]) < self.num_segments) & (self.t_end > t)
        return jnp.min(jnp.where(valid, self.t_end, jnp.inf))

    def eval_piece(self, i, t):
        """The value at time t computed from piece i alone (its one-sided limits at its ends)."""
        t0, t1 = self.t_start[i], self.t_end[i]
        width = t1 - t0
        safe = jnp.where(width > 0, width, 1.0)  # zero-length pieces are constants
        theta = jnp.clip(jnp.where(width > 0, (t - t0) / safe, 0.0), 0.0, 1.0)
        return eval_polynomial(self.coefficients[i], theta)

    @compiled_when_eager
    def eval(self, t, side: str | None = None):
        """The value x(t) (shape (n,), or (len(t), n) for an array of times)."""
        side = check_side(self.side if side is None else side)
        return vectorize_in_time(lambda s: self.eval_piece(self.piece_index(s, side), s), t, self.t_start.dtype)

    def state(self, t, side: str | None = None):
        """Same as `eval`: the trajectory's value (a state trajectory's x(t))."""
        return self.eval(t, side)

    def __call__(self, t):
        """Same as `eval(t)`: a trajectory is a function of time (usable as an input)."""
        return self.eval(t)

    @property
    def final_value(self):
        """The value at the end of the last piece (for a batch, of every member): the sum of
        the last piece's coefficients."""
        return _last_piece_end(self.coefficients, self.num_segments)

    # ----- algebra on the pieces ------------------------------------------------------------

    def reversed_in_time(self, t_reflect) -> "Trajectory":
        """The trajectory of s = t_reflect - t, as a function of t: piece order reversed and
        each piece re-expanded in 1 - theta (e.g. a Riccati solution integrated backward in
        tau = t_f - t, made a trajectory of t)."""
        size = self.t_start.shape[0]
        used = self.num_segments
        order = jnp.clip(used - 1 - jnp.arange(size), 0, size - 1)
        pad = jnp.arange(size) >= used
        t_start = jnp.where(pad, t_reflect, t_reflect - self.t_end[order])
        t_end = jnp.where(pad, t_reflect, t_reflect - self.t_start[order])
        reversal = jnp.asarray(_REVERSAL, self.coefficients.dtype)
        coefficients = jnp.einsum("kj,pjn->pkn", reversal, self.coefficients[order])
        return Trajectory.from_pieces(t_start, t_end, coefficients, used, side=self.side)

    def interpolate(self, fn) -> "Trajectory":
        """g(t) = fn(t, x(t)) on the same pieces, each the quartic through g at five equally
        spaced points of the piece (exact when g is a polynomial of degree <= 4 in t on it)."""
        widths = self.t_end - self.t_start
        theta = jnp.asarray(_FIT_NODES, widths.dtype)
        times = self.t_start[:, None] + widths[:, None] * theta
        x_values = jnp.einsum("kj,pjn->pkn", jnp.vander(theta, NUM_COEFFICIENTS, increasing=True), self.coefficients)
        values = jax.vmap(jax.vmap(fn))(times, x_values)  # (pieces, 5, m)
        coefficients = jnp.einsum("kj,pjn->pkn", jnp.asarray(_FIT, values.dtype), values)
        return Trajectory.from_pieces(self.t_start, self.t_end, coefficients, self.num_segments, side=self.side)

    # ----- host-side views ------------------------------------------------------------------

    def breakpoints(self) -> np.ndarray:
        """The times at which pieces start and end, on the host."""
        n = int(self.num_segments)
        return np.unique(np.concatenate([np.asarray(self.t_start[:n]), np.asarray(self.t_end[:n])]))

    def sample(self, num: int = 400):
        """Times and values for plotting (see `sample_signal`). Returns (ts, ys) as numpy arrays."""
        return sample_signal(self.eval, float(self.t_start[0]), float(self.t_final), self.breakpoints(), num)

    def plot(self, ax=None, outputs=None, **kwargs):
        """Plot the values against time with matplotlib (the notes' `fnplt`); returns the figure.
        `outputs`: indices of the coordinates to draw (default all)."""
        ts, ys = self.sample()
        return plot_signal(ts, ys, [f"y{i}" for i in range(ys.shape[1])], None, outputs, ax=ax, **kwargs)


def sample_signal(eval_fn, t0: float, tf: float, breakpoints: np.ndarray, num: int = 400):
    """Times and values of `eval_fn(ts, side=...)` for plotting: a uniform grid plus both sides of
    every breakpoint, so that jumps show as vertical lines."""
    grid = np.linspace(t0, tf, num)
    br = breakpoints[(breakpoints >= t0) & (breakpoints <= tf)]
    if len(br) > 4 * num:  # many small steps: the uniform grid already resolves the curve
        br = br[:0]
    ts = np.sort(np.concatenate([grid, br, br]))
    sides = np.zeros(len(ts), bool)
    sides[1:] = ts[1:] == ts[:-1]  # the second copy of a repeated time takes the right limit
    left = np.asarray(eval_fn(jnp.asarray(ts), side="left"))
    right = np.asarray(eval_fn(jnp.asarray(ts), side="right"))
    return ts, np.where(sides[:, None], right, left)


def plot_signal(ts, ys, names, title, outputs=None, *, ax=None, held_samples=None, **kwargs):
    """Lines of the columns `outputs` (indices or names; default all) of ys against ts.
    `held_samples`: (tk, yk) drawn as dots (the samples of a discrete-time signal)."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3.5), layout="constrained")
    if outputs is None:
        outputs = range(ys.shape[1])
    idx = [list(names).index(o) if isinstance(o, str) else int(o) for o in outputs]
    for i in idx:
        line, = ax.plot(ts, ys[:, i], label=names[i], **kwargs)
        if held_samples is not None:
            ax.plot(held_samples[0], held_samples[1][:, i], "o", ms=4, color=line.get_color())
    ax.set_xlabel("t")
    if title is not None:
        ax.set_title(title)
    if len(idx) > 1 or title is not None:
        ax.legend(loc="best")
    ax.grid(True, alpha=0.3)
    return ax.figure
