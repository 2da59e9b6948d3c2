"""Input sources of the simulation loop: u(t) from nothing, a constant, a function, an input
tape, plus the noise samples of a stochastic system."""

from __future__ import annotations

import functools

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import scalar_argument
from ..trajectories import Trajectory
from ._result import SimulatedTrajectory


class InputSource(eqx.Module):
    """u(t) for the loop. A source with breakpoints (an input tape) makes the loop stop a
    step at each one and, within a step, evaluates only the piece the step started in, so a
    jump or kink of the input never falls inside a step."""

    has_breakpoints = False

    def next_breakpoint(self, t):
        return jnp.asarray(jnp.inf, t.dtype)

    def on_step(self, t):
        """u(s) for s in the step starting at t."""
        return self


class _ZeroInput(InputSource):
    num_inputs: int = eqx.field(static=True)
    dtype: np.dtype = eqx.field(static=True)

    def __call__(self, t):
        return jnp.zeros(self.num_inputs, self.dtype)


@functools.cache
def _zero_input(num_inputs: int, dtype: np.dtype) -> _ZeroInput:
    """One instance per size and dtype (immutable; an equinox module costs microseconds to build)."""
    return _ZeroInput(num_inputs, dtype)


class _FunctionInput(InputSource):
    fn: Callable = eqx.field(static=True)
    num_inputs: int = eqx.field(static=True)

    def __call__(self, t):
        return jnp.reshape(jnp.asarray(self.fn(t), dtype=t.dtype), (self.num_inputs,))


class _ConstantInput(InputSource):
    """A constant u, an argument of the compiled program: a new value does not recompile."""

    value: jax.Array

    def __call__(self, t):
        return jnp.asarray(self.value, t.dtype)


class _TrajectoryInput(InputSource):
    trajectory: Trajectory | SimulatedTrajectory
    num_inputs: int = eqx.field(static=True)
    piece: jax.Array | None = None
    has_breakpoints = True

    def __call__(self, t):
        traj = self.trajectory
        y = traj.eval(t) if self.piece is None else traj.eval_piece(self.piece, t)
        return jnp.reshape(y, (self.num_inputs,)).astype(t.dtype)

    def next_breakpoint(self, t):
        return self.trajectory.next_breakpoint(t).astype(t.dtype)

    def on_step(self, t):
        return _TrajectoryInput(self.trajectory, self.num_inputs, self.trajectory.piece_index(t))


class NoisyInput(InputSource):
    """[u(t); w(t)]: the inputs followed by the noise samples of a stochastic system.

    Noise group g (size n, period tau, scale c) is held constant on [k tau, (k+1) tau) with
    the value c * N(0, I) drawn from fold_in(fold_in(key, g), k): a pure function of the key
    and k, so paths are reproducible and independent across keys. The instants k tau are
    breakpoints: a step never straddles a jump of w, so `on_step` draws the step's samples
    once and every stage of the step reuses them."""

    inputs: InputSource
    key: jax.Array
    groups: tuple = eqx.field(static=True)
    samples: jax.Array | None = None
    has_breakpoints = True

    def _periods(self, t):
        return jnp.asarray([tau for _, tau, _ in self.groups], t.dtype)

    def _piece(self, t):
        """The index k with k tau <= t < (k+1) tau, exact at the breakpoints (which the loop
        reaches as the same products k * tau)."""
        tau = self._periods(t)
        k = jnp.floor(t / tau)
        k = jnp.where((k + 1) * tau <= t, k + 1, k)
        return jnp.where(k * tau > t, k - 1, k)

    def _draw(self, t):
        pieces = self._piece(t).astype(jnp.int32)
        return jnp.concatenate([c * jax.random.normal(jax.random.fold_in(jax.random.fold_in(self.key, g), pieces[g]),
                                                      (n,), t.dtype)
                                for g, (n, _, c) in enumerate(self.groups)])

    def __call__(self, t):
        w = self._draw(t) if self.samples is None else self.samples.astype(t.dtype)
        return jnp.concatenate([self.inputs(t), w])

    def next_breakpoint(self, t):
        tau = self._periods(t)
        return jnp.minimum(self.inputs.next_breakpoint(t), jnp.min((self._piece(t) + 1) * tau))

    def on_step(self, t):
        return NoisyInput(self.inputs.on_step(t), self.key, self.groups, self._draw(t))


def leaves_to_arrays(tree, dtype):
    """Python floats and numpy arrays in a system become JAX arrays: traced, not static, so
    changing a parameter's value does not recompile."""
    return jax.tree.map(lambda leaf: leaf_to_array(leaf, dtype), tree)


def leaf_to_array(v, dtype):
    """One leaf as `leaves_to_arrays` converts it, to `dtype` (an argument of the compiled
    call): a float through `scalar_argument`, a floating numpy array to a numpy array, a
    floating JAX array by `astype`."""
    if isinstance(v, float):
        return scalar_argument(v, dtype)
    if isinstance(v, np.ndarray) and np.issubdtype(v.dtype, np.floating):
        return np.asarray(v, dtype)
    if isinstance(v, jax.Array) and jnp.issubdtype(v.dtype, jnp.floating) and v.dtype != dtype:
        return v.astype(dtype)
    return v


def make_source(system, inputs, t0, dtype):
    nu = system.num_inputs
    if inputs is None:
        return _zero_input(nu, np.dtype(dtype))
    if nu == 0:
        raise ValueError(f"{system.name} has no inputs, but inputs were given")
    tape = isinstance(inputs, (Trajectory, SimulatedTrajectory))  # a simulation's output is a tape too
    if tape:
        source = _TrajectoryInput(leaves_to_arrays(inputs, dtype), nu)
    elif callable(inputs):
        source = _FunctionInput(inputs, nu)
    elif isinstance(inputs, (jax.Array, np.ndarray, list, tuple, float, int)):
        value = np.asarray(inputs, dtype) if not isinstance(inputs, jax.Array) else leaf_to_array(inputs, dtype)
        if jnp.shape(value) not in ((nu,), ()) or (jnp.shape(value) == () and nu != 1):
            raise ValueError(f"inputs has shape {jnp.shape(value)}, but {system.name}'s input frame "
                             f"{system.input_frame} needs shape ({nu},)")
        return _ConstantInput(jnp.reshape(value, (nu,)) if isinstance(value, jax.Array) else np.reshape(value, (nu,)))
    else:
        raise TypeError(f"inputs must be a Trajectory, a function of time or a constant u (an array of the "
                        f"input frame's size), got {type(inputs).__name__}")
    raw = inputs.eval if tape else inputs
    try:
        shape = jax.eval_shape(raw, t0).shape
    except Exception as e:
        raise ValueError(f"evaluating the inputs at t0 failed: {e}") from e
    if shape not in ((nu,), ()) or (shape == () and nu != 1):
        raise ValueError(f"inputs(t) returns shape {shape}, but {system.name}'s input frame "
                         f"{system.input_frame} needs shape ({nu},)")
    return source


