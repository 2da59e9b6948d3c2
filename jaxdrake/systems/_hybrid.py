r"""Hybrid (event-driven) systems (notes, D.3.1): modes, guards, resets.

A hybrid system is a graph: its nodes are modes (each a `System`: continuous, discrete or
mixed), its edges are transitions. A transition out of mode $m$ fires when its guard
$\phi(t, x, u) \le 0$; then the reset $x^+ = \Delta(t, x^-, u)$ maps the state into the
target mode, and may stop the simulation (the notes' `status`, "the ball has stopped").

Jit-able layout: the state of every mode is padded to one vector $[x_d; x_c]$ with the largest
discrete and continuous sizes among the modes (mode $i$ reads the first $n_{d,i}$ and $n_{c,i}$
entries of each part), and the active mode, an integer carried by the simulator, selects the
mode's methods with `lax.switch`. Modes, transitions and sizes are static structure; the modes'
parameters and the hybrid system's own fields are pytree leaves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp

from .._numbers import call_argument
from ._frame import Frame
from ._system import System


@dataclasses.dataclass(frozen=True)
class Transition:
    """An edge of the mode graph.

    **Arguments:**

    - `source`, `target`: mode indices.
    - `guard(system, t, x, u) -> scalar`: fires when $\\le 0$ (x is the source mode's state).
      `system` is the hybrid system itself, so guards can read its parameters.
    - `reset(system, t, x, u)`: the target mode's state $x^+$, or a pair `(x_plus, stop)`
      where `stop` (a boolean) ends the simulation after this event.
    - `name`: shown in `traj.events`.

    Use module-level functions (or `and_guards` / `not_guard` of them): transitions are
    static structure, compared by value, so equal transitions share a compiled program.
    """

    source: int
    guard: Callable
    reset: Callable
    target: int
    name: str = ""


@dataclasses.dataclass(frozen=True)
class _AndGuard:
    guards: tuple

    def __call__(self, system, t, x, u):
        # the max as selects, whose derivative is the chosen guard's: the derivative rule of
        # jnp.max divides by the number of entries equal to the max, which XLA can make 0
        # (NaN) when it recomputes an entry with other rounding in a fused kernel
        values = [jnp.asarray(g(system, t, x, u)).reshape(()) for g in self.guards]
        largest = values[0]
        for v in values[1:]:
            largest = jnp.where(v > largest, v, largest)
        return largest


@dataclasses.dataclass(frozen=True)
class _NotGuard:
    guard: Callable

    def __call__(self, system, t, x, u):
        return -self.guard(system, t, x, u)


def and_guards(*guards: Callable) -> Callable:
    """The guard that fires when all of `guards` are $\\le 0$: $\\max_i \\phi_i \\le 0$ (the
    notes' `andGuards`). Event location stays exact: the max is continuous and, at a
    crossing, smooth in the guard that crosses."""
    if len(guards) < 2:
        raise ValueError("and_guards needs at least two guards")
    return _AndGuard(tuple(guards))


def not_guard(guard: Callable) -> Callable:
    """The guard that fires when `guard` is $\\ge 0$: $-\\phi \\le 0$ (the notes' `notGuard`)."""
    return _NotGuard(guard)


class HybridSystem(System):
    """A system that switches between modes at events (the notes' `HybridDrakeSystem`).

    **Arguments:**

    - `modes`: a sequence of `System`s. All take the same inputs and give the same number of
      outputs (the output of a hybrid system is the output of its active mode); modes with
      discrete states share one sample time.
    - `transitions`: a sequence of `Transition`s.
    - `initial_mode`: the mode at the start of a simulation (default 0).
    - `input_frame`, `output_frame`: default to the first mode's; modes inherit them (a mode
      that names a different frame is an error).
    - `state_frame`: defaults to the modes' state frame where they all name the same one
      (the rimless wheel's `theta, thetadot`); else a generic `x0, x1, ...`.

    Subclass it to give the system parameters of its own (the notes' `BallPlant` has `r` and
    `cor`), calling `super().__init__(modes, transitions)` at the end of `__init__`.
    """

    modes: tuple
    transitions: tuple = eqx.field(static=True)
    initial_mode: int = eqx.field(static=True)

    def __init__(self, modes: Sequence[System], transitions: Sequence[Transition], *,
                 initial_mode: int = 0, input_frame: Frame | None = None,
                 output_frame: Frame | None = None, state_frame: Frame | None = None):
        name = type(self).__name__
        modes, transitions = tuple(modes), tuple(transitions)
        if not modes:
            raise ValueError(f"{name}: a hybrid system needs at least one mode")
        for i, m in enumerate(modes):
            if not isinstance(m, System) or isinstance(m, HybridSystem):
                raise TypeError(f"{name}: mode {i} must be a (non-hybrid) jaxdrake.System, "
                                f"got {type(m).__name__}")
        first = modes[0]
        for label in ("num_inputs", "num_outputs"):
            sizes = [getattr(m, label) for m in modes]
            if len(set(sizes)) > 1:
                raise ValueError(f"{name}: all modes must have the same {label}, got "
                                 + ", ".join(f"{m.name}: {s}" for m, s in zip(modes, sizes)))
        periods = {m.sample_times for m in modes if m.sample_times}
        if len(periods) > 1:
            raise ValueError(f"{name}: modes with discrete states must share their sample times, "
                             f"got {sorted(periods)}")
        noise = {m.noise_groups for m in modes}
        if len(noise) > 1:
            raise ValueError(f"{name}: all modes must have the same noise inputs, got "
                             + ", ".join(f"{m.name}: {m.noise_groups}" for m in modes))
        for k, tr in enumerate(transitions):
            if not isinstance(tr, Transition):
                raise TypeError(f"{name}: transition {k} must be a jaxdrake.Transition")
            for role, i in (("source", tr.source), ("target", tr.target)):
                if not (isinstance(i, int) and 0 <= i < len(modes)):
                    raise ValueError(f"{name}: transition {k} ({tr.name or 'unnamed'}) has "
                                     f"{role} mode {i!r}, but there are {len(modes)} modes")
        if not (isinstance(initial_mode, int) and 0 <= initial_mode < len(modes)):
            raise ValueError(f"{name}: initial_mode {initial_mode!r} is not one of the "
                             f"{len(modes)} modes")
        input_frame = input_frame or first.input_frame
        output_frame = output_frame or first.output_frame
        for i, m in enumerate(modes):  # modes inherit the hybrid system's frames (notes, D.3.5)
            for role, frame in (("input", input_frame), ("output", output_frame)):
                own = getattr(m, f"{role}_frame")
                if not own.generic and not frame.generic and own != frame:
                    raise ValueError(f"{name}: mode {i} ({m.name}) has {role} frame {own}, but the "
                                     f"hybrid system's {role} frame is {frame}")
        if state_frame is None and len({m.state_frame for m in modes}) == 1 and not first.state_frame.generic \
                and all(m.num_states == first.num_states for m in modes):
            state_frame = first.state_frame  # the modes share one state layout: the padded state is it
        self.modes = modes
        self.transitions = transitions
        self.initial_mode = initial_mode
        limits = first.input_limits
        super().__init__(num_continuous_states=max(m.num_continuous_states for m in modes),
                         num_discrete_states=max(m.num_discrete_states for m in modes),
                         num_inputs=first.num_inputs, num_outputs=first.num_outputs,
                         sample_time=periods.pop() if periods else None,
                         noise_groups=noise.pop(),
                         direct_feedthrough=any(m.direct_feedthrough for m in modes),
                         time_invariant=all(m.time_invariant for m in modes),
                         input_limits=limits,
                         input_frame=input_frame, output_frame=output_frame,
                         state_frame=state_frame)

    # ----- layout -----------------------------------------------------------------------------

    @property
    def num_modes(self) -> int:
        return len(self.modes)

    def mode_state(self, i: int, x):
        """Mode i's own state from the padded state."""
        m = self.modes[i]
        return jnp.concatenate([x[: m.num_discrete_states],
                                x[self.num_discrete_states: self.num_discrete_states + m.num_continuous_states]])

    def pad_state(self, i: int, x_mode):
        """The padded state holding mode i's state (zeros elsewhere)."""
        m = self.modes[i]
        xd = jnp.zeros(self.num_discrete_states, x_mode.dtype).at[: m.num_discrete_states].set(
            x_mode[: m.num_discrete_states])
        xc = jnp.zeros(self.num_continuous_states, x_mode.dtype).at[: m.num_continuous_states].set(
            x_mode[m.num_discrete_states:])
        return jnp.concatenate([xd, xc])

    def full_state(self, x0):
        """The padded state from x0: the padded state itself, or the initial mode's own state."""
        x = call_argument(x0)
        n = self.modes[self.initial_mode].num_states
        if n != self.num_states and x.ndim <= 1 and x.size == n:
            return self.pad_state(self.initial_mode, x.reshape(n))
        return super().full_state(x)

    def check_shapes(self, t, x) -> None:
        """Each mode as a system of its own, then every guard (a scalar) and reset (the target
        mode's state, or a pair (state, stop))."""
        u = jax.ShapeDtypeStruct((self.num_inputs,), x.dtype)
        for i, mode in enumerate(self.modes):
            mode.check_shapes(t, self.mode_state(i, x))
        for k, tr in enumerate(self.transitions):
            label = f"{self.name} transition {k}" + (f" ({tr.name})" if tr.name else "")
            x_source = jax.ShapeDtypeStruct((self.modes[tr.source].num_states,), x.dtype)
            try:
                guard = jax.eval_shape(lambda x, u: tr.guard(self, t, x, u), x_source, u)
                out = jax.eval_shape(lambda x, u: tr.reset(self, t, x, u), x_source, u)
            except Exception as e:
                raise ValueError(f"{label}: the guard or reset failed on a state of shape "
                                 f"{x_source.shape}: {type(e).__name__}: {e}") from e
            if getattr(guard, "shape", None) not in ((), (1,)):
                raise ValueError(f"{label}: the guard must return a scalar, got shape "
                                 f"{getattr(guard, 'shape', type(guard))}")
            x_plus = out[0] if isinstance(out, tuple) else out
            n_target = self.modes[tr.target].num_states
            if getattr(x_plus, "shape", None) != (n_target,):
                raise ValueError(f"{label}: the reset must return the target mode's state, shape "
                                 f"({n_target},), got {getattr(x_plus, 'shape', type(x_plus))}")

    @staticmethod
    def _switch(index, count, branch, *operands):
        """`branch(i, *operands)` for i = index among `count` static branches (`lax.switch`)."""
        if count == 1:
            return branch(0, *operands)
        return jax.lax.switch(index, [lambda *a, i=i: branch(i, *a) for i in range(count)], *operands)

    # ----- the contract, per mode -------------------------------------------------------------

    @property
    def bounds_steps(self) -> bool:
        return any(m.bounds_steps for m in self.modes)

    def step_size_bound(self, t, x):
        """The smallest of the modes' bounds (each read from its share of the state), whichever
        mode is active: the simulator asks it without the mode."""
        bounds = [m.step_size_bound(t, self.mode_state(i, x)) for i, m in enumerate(self.modes) if m.bounds_steps]
        return jnp.min(jnp.stack(bounds)) if bounds else jnp.asarray(jnp.inf, x.dtype)

    def mode_dynamics(self, mode, t, x, u):
        def branch(i, t, x, u):
            m = self.modes[i]
            xc_dot = (m.mode_dynamics(0, t, self.mode_state(i, x), u) if m.num_continuous_states
                      else jnp.zeros(0, x.dtype))
            return jnp.zeros(self.num_continuous_states, x.dtype).at[: m.num_continuous_states].set(xc_dot)
        return self._switch(mode, self.num_modes, branch, t, x, u)

    def mode_update(self, mode, t, x, u, due):
        def branch(i, t, x, u):
            m = self.modes[i]
            xd_next = (m.mode_update(0, t, self.mode_state(i, x), u, due) if m.num_discrete_states
                       else jnp.zeros(0, x.dtype))
            return x[: self.num_discrete_states].at[: m.num_discrete_states].set(xd_next)
        return self._switch(mode, self.num_modes, branch, t, x, u)

    def mode_output(self, mode, t, x, u):
        return self._switch(mode, self.num_modes,
                            lambda i, t, x, u: self.modes[i].mode_output(0, t, self.mode_state(i, x), u),
                            t, x, u)

    def transition_guards(self, mode, t, x, u):
        """$\\phi_k(t, x, u)$ for every transition k out of `mode`; +inf for the others."""
        u = u[: self.num_inputs]  # guards and resets see the inputs, not the noise samples
        values = [jnp.where(mode == tr.source,
                            jnp.asarray(tr.guard(self, t, self.mode_state(tr.source, x), u), x.dtype).reshape(()),
                            jnp.inf)
                  for tr in self.transitions]
        return jnp.stack(values) if values else jnp.zeros(0, x.dtype)

    def apply_transition(self, mode, k, t, x, u):
        """Take transition k: returns (padded x+, target mode, stop)."""
        u = u[: self.num_inputs]
        def branch(j, t, x, u):
            tr = self.transitions[j]
            out = tr.reset(self, t, self.mode_state(tr.source, x), u)
            x_plus, stop = out if isinstance(out, tuple) else (out, False)
            x_plus = jnp.asarray(x_plus, x.dtype).reshape(self.modes[tr.target].num_states)
            return self.pad_state(tr.target, x_plus), jnp.asarray(tr.target, jnp.int32), jnp.asarray(stop, bool)
        return self._switch(k, len(self.transitions), branch, t, x, u)

    def initial_state(self):
        return self.pad_state(self.initial_mode, self.modes[self.initial_mode].initial_state())

    def dynamics(self, t, x, u):
        raise TypeError(f"{self.name} is hybrid: its dynamics depend on the mode; use "
                        "mode_dynamics(mode, t, x, u)")

    def update(self, t, x, u):
        raise TypeError(f"{self.name} is hybrid: use mode_update(mode, t, x, u)")

    def output(self, t, x, u):
        raise TypeError(f"{self.name} is hybrid: use mode_output(mode, t, x, u)")
