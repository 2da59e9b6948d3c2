r"""Diagrams: systems wired together by their input and output ports (notes, D.3.4).

A `Diagram` is itself a `System`. Its state stacks the subsystems' states in the notes' layout,
all discrete parts first, $x = [x_{d,1}; \dots; x_{d,N}; x_{c,1}; \dots; x_{c,N}]$. Each
subsystem input is the sum of the signals wired into it (outputs of other subsystems, through
a registered frame conversion where frames differ, times a gain; or coordinates of the
diagram's own input). Outputs are evaluated in a topological order of the direct-feedthrough
graph, fixed at construction; a cycle in that graph is an algebraic loop and an error.

What the parts are, the diagram is: with a hybrid subsystem it is hybrid (its mode is the
tuple of the subsystems' modes, one mixed-radix integer; its transitions are theirs); with a
stochastic one it is stochastic (w stacks their noise); discrete subsystems keep their sample
times, and a diagram may mix several (each update fires at its own instants). Subsystems and
their parameters are pytree leaves; names, wiring and layout are static.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import array_module
from ._frame import Frame, frame_conversion
from ._hybrid import HybridSystem
from ._system import System, _static

INPUT = -1  # the source index of the diagram's own input in a wire


@dataclasses.dataclass(frozen=True)
class Wire:
    """A connection: coordinates `source_index` of subsystem `source`'s output (after the
    frame `conversion`, if any), or of the diagram's input when `source` is `INPUT`, added
    with `gain` into coordinates `target_index` of subsystem `target`'s input."""

    source: int
    source_index: tuple[int, ...]
    target: int
    target_index: tuple[int, ...]
    conversion: Callable | None = None
    gain: float = 1.0


class Diagram(System):
    """Systems wired by port; build one with `DiagramBuilder` (or `cascade`, `feedback`,
    `parallel`).

    **Fields:** `subsystems` (a tuple of systems, pytree leaves), `names`, `wires`, `outputs`
    (for each diagram output coordinate, the (subsystem, coordinate) it reads) and the static
    layout derived from them.
    """

    subsystems: tuple
    names: tuple[str, ...] = _static()
    wires: tuple[Wire, ...] = _static()
    outputs: tuple[tuple[int, int], ...] = _static()
    order: tuple[int, ...] = _static()
    diagram_name: str = _static()

    def __init__(self, subsystems: Sequence[System], names: Sequence[str], wires: Sequence[Wire],
                 outputs: Sequence[tuple[int, int]], *, num_inputs: int, input_frame: Frame,
                 output_frame: Frame, input_limits=None, name: str = "Diagram"):
        self.subsystems, self.names = tuple(subsystems), tuple(names)
        self.wires, self.outputs = tuple(wires), tuple(outputs)
        self.order = _output_order(self.subsystems, self.names, self.wires)
        self.diagram_name = name
        subs = self.subsystems
        sample_times = sorted({p for s in subs for p in s.sample_times})
        state = Frame(f"{name}State", tuple(
            [f"{n}.{c}" for s, n in zip(subs, self.names) for c in s.state_frame.coordinates[:s.num_discrete_states]]
            + [f"{n}.{c}" for s, n in zip(subs, self.names) for c in s.state_frame.coordinates[s.num_discrete_states:]]))
        super().__init__(
            num_continuous_states=sum(s.num_continuous_states for s in subs),
            num_discrete_states=sum(s.num_discrete_states for s in subs),
            num_inputs=num_inputs, num_outputs=len(self.outputs),
            sample_time=tuple(sample_times) if sample_times else None,
            direct_feedthrough=_input_reaches_output(subs, self.wires, self.outputs),
            time_invariant=all(s.time_invariant for s in subs),
            num_state_constraints=sum(s.num_state_constraints for s in subs),
            input_limits=input_limits, input_frame=input_frame, state_frame=state,
            output_frame=output_frame, noise_groups=tuple(g for s in subs for g in s.noise_groups))

    # ----- time breakpoints: the subsystems' --------------------------------------------------

    @property
    def has_breakpoints(self) -> bool:
        return any(s.has_breakpoints for s in self.subsystems)

    def next_breakpoint(self, t):
        return functools.reduce(jnp.minimum, [s.next_breakpoint(t) for s in self.subsystems if s.has_breakpoints],
                                jnp.asarray(jnp.inf, jnp.asarray(t).dtype))

    def on_step(self, t):
        if not self.has_breakpoints:
            return self
        return eqx.tree_at(lambda d: d.subsystems, self, tuple(s.on_step(t) for s in self.subsystems))

    # ----- static layout ------------------------------------------------------------------

    def _offsets(self, sizes):
        return np.concatenate([[0], np.cumsum(sizes)]).astype(int).tolist()

    def _state_slices(self, i: int):
        """Where subsystem i's discrete and continuous states sit in the diagram's state."""
        s = self.subsystems[i]
        d = self._offsets([t.num_discrete_states for t in self.subsystems])[i]
        c = self.num_discrete_states + self._offsets([t.num_continuous_states for t in self.subsystems])[i]
        return slice(d, d + s.num_discrete_states), slice(c, c + s.num_continuous_states)

    def _locate(self, which):
        """(i, rest): subsystem i is `which` -- its index, its name, or the system object itself
        (the one added) -- or, for a dotted name `"a.b"` as in the state frame's coordinates,
        holds it: `a` is a sub-diagram and `rest` (`"b"`) names the subsystem inside."""
        if isinstance(which, str):
            if which in self.names:
                return self.names.index(which), None
            for k in (k for k, ch in enumerate(which) if ch == "."):
                head = which[:k]
                if head in self.names and isinstance(self.subsystems[self.names.index(head)], Diagram):
                    return self.names.index(head), which[k + 1:]
            raise KeyError(f"{self.name} has no subsystem named {which!r}; its subsystems are {list(self.names)}")
        if isinstance(which, System):
            found = [i for i, s in enumerate(self.subsystems) if s is which]
            if not found:
                raise KeyError(f"{which.name} is not a subsystem of {self.name} (a system object is found "
                               f"by identity: pass the one that was added, or its name, one of {list(self.names)})")
            if len(found) > 1:
                raise ValueError(f"{which.name} was added to {self.name} {len(found)} times, as "
                                 f"{[self.names[i] for i in found]}: name the one you mean")
            return found[0], None
        if isinstance(which, (int, np.integer)) and not isinstance(which, bool):
            if not 0 <= which < len(self.subsystems):
                raise IndexError(f"{self.name} has {len(self.subsystems)} subsystems, no number {which}")
            return int(which), None
        raise TypeError(f"a subsystem of {self.name} is given by its index, its name or the system "
                        f"object, got {type(which).__name__}")

    def subsystem(self, which) -> System:
        """A subsystem, by its index, its name (dotted, `"a.b"`, for subsystem `b` of the
        sub-diagram `a`) or the system object itself."""
        i, rest = self._locate(which)
        return self.subsystems[i] if rest is None else self.subsystems[i].subsystem(rest)

    def subsystem_state(self, which, x):
        """The own state [x_d; x_c] of subsystem `which` (as for `subsystem`) from the diagram's
        state x, or from states stacked along leading axes (`traj.state(ts)`)."""
        i, rest = self._locate(which)
        d, c = self._state_slices(i)
        x_i = array_module(x).concatenate([x[..., d], x[..., c]], axis=-1)  # numpy stays numpy
        return x_i if rest is None else self.subsystems[i].subsystem_state(rest, x_i)

    def state_with(self, x, which, x_i):
        """The diagram's state x with subsystem `which`'s part (as for `subsystem`) set to
        x_i, as the subsystem's `full_state` takes it (a hybrid subsystem's initial-mode state,
        a sub-diagram's mapping: see `initial_state_with`). Drake's
        `GetMutableSubsystemState`, as a pure function: x itself is not changed."""
        x = self.full_state(x)
        i, rest = self._locate(which)
        sub = self.subsystems[i]
        if rest is not None:
            x_i = sub.state_with(self.subsystem_state(i, x), rest, x_i)
        try:
            x_i = sub.full_state(x_i)
        except ValueError as error:
            raise ValueError(f"{self.name}: subsystem {self.names[i]!r}: {error}") from None
        d, c = self._state_slices(i)
        nd = sub.num_discrete_states
        return x.at[d].set(x_i[:nd]).at[c].set(x_i[nd:])

    def initial_state_with(self, states: Mapping) -> jax.Array:
        """The initial state with some subsystems' parts given: `states` maps a subsystem (its
        index, name or the system object, as for `subsystem`) to its state (as `state_with`
        takes it; a sub-diagram's may itself be such a mapping); the others keep their
        `initial_state()`."""
        x = self.initial_state()
        for which, x_i in states.items():
            x = self.state_with(x, which, x_i)
        return x

    def full_state(self, x0):
        """The state vector from x0: the vector itself, or a mapping from subsystems to their
        states (`initial_state_with`)."""
        return self.initial_state_with(x0) if isinstance(x0, Mapping) else super().full_state(x0)

    def _noise(self, i: int, u):
        start = self.num_inputs + self._offsets([s.num_noise_inputs for s in self.subsystems])[i]
        return u[start: start + self.subsystems[i].num_noise_inputs]

    @property
    def _strides(self):
        return [math.prod(s.num_modes for s in self.subsystems[:i]) for i in range(len(self.subsystems))]

    def subsystem_mode(self, i: int, mode):
        """Subsystem i's mode from the diagram's mode (a mixed-radix digit)."""
        n = self.subsystems[i].num_modes
        return 0 if n == 1 else (mode // self._strides[i]) % n

    @property
    def num_modes(self) -> int:
        return math.prod(s.num_modes for s in self.subsystems)

    @property
    def initial_mode(self) -> int:
        return sum(s.initial_mode * k for s, k in zip(self.subsystems, self._strides))

    @property
    def transitions(self) -> tuple:
        """The hybrid subsystems' transitions, in subsystem order (each in its own modes)."""
        return tuple(tr for s in self.subsystems for tr in s.transitions)

    def _transition_owner(self, k: int):
        for i, s in enumerate(self.subsystems):
            if k < len(s.transitions):
                return i, k
            k -= len(s.transitions)
        raise IndexError(k)

    # ----- signals ------------------------------------------------------------------------

    def _input(self, i, u_ext, ys, dtype):
        """Subsystem i's input: the sum of the wires into it (after its input limits)."""
        u = jnp.zeros(self.subsystems[i].num_inputs, dtype)
        for w in self.wires:
            if w.target != i:
                continue
            if w.source == INPUT:
                y = u_ext
            else:
                y = ys[w.source]
                if w.conversion is not None:
                    y = jnp.asarray(w.conversion(y), dtype)
            if w.source_index != tuple(range(y.shape[0])):
                y = y[np.asarray(w.source_index, int)]
            y = y if w.gain == 1.0 else w.gain * y
            if w.target_index == tuple(range(u.shape[0])):
                u = u + y  # the whole input: no scatter (slow on CPUs)
            else:
                u = u.at[np.asarray(w.target_index, int)].add(y)
        return self.subsystems[i].saturate(u)

    def _outputs(self, mode, t, x, u):
        """Every subsystem's output, in the static topological order, and the inputs of the
        direct-feedthrough ones (computed on the way: their sources come first); None for
        the others, whose outputs do not read their input."""
        u_ext, dtype = u[: self.num_inputs], x.dtype
        subs = self.subsystems
        ys, inputs = [None] * len(subs), [None] * len(subs)
        for i in self.order:
            s = subs[i]
            if s.direct_feedthrough:
                inputs[i] = self._input(i, u_ext, ys, dtype)
            u_i = inputs[i] if inputs[i] is not None else jnp.zeros(s.num_inputs, dtype)
            ys[i] = s.mode_output(self.subsystem_mode(i, mode), t, self.subsystem_state(i, x),
                                  jnp.concatenate([u_i, self._noise(i, u)]))
        return inputs, ys

    def signals(self, mode, t, x, u):
        """Every subsystem's (full) input and output at (t, x, u): two lists, in subsystem
        order. `u` is the diagram's full input (inputs, then noise samples)."""
        inputs, ys = self._outputs(mode, t, x, u)
        u_ext = u[: self.num_inputs]
        us = [jnp.concatenate([u_i if u_i is not None else self._input(i, u_ext, ys, x.dtype),
                               self._noise(i, u)])
              for i, u_i in enumerate(inputs)]
        return us, ys

    # ----- the mode view (what the simulator calls) ---------------------------------------

    def mode_dynamics(self, mode, t, x, u):
        us, _ = self.signals(mode, t, x, u)
        parts = [s.mode_dynamics(self.subsystem_mode(i, mode), t, self.subsystem_state(i, x), us[i])
                 for i, s in enumerate(self.subsystems) if s.num_continuous_states]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, x.dtype)

    def mode_update(self, mode, t, x, u, due):
        us, _ = self.signals(mode, t, x, u)
        parts = []
        for i, s in enumerate(self.subsystems):
            if not s.num_discrete_states:
                continue
            x_i = self.subsystem_state(i, x)
            due_i = jnp.stack([due[self.sample_times.index(p)] for p in s.sample_times])
            new = s.mode_update(self.subsystem_mode(i, mode), t, x_i, us[i], due_i)
            parts.append(jnp.where(jnp.any(due_i), new, x_i[: s.num_discrete_states]))
        return jnp.concatenate(parts)

    def discrete_update(self, t, x, u, due):
        return self.mode_update(self.initial_mode, t, x, self._with_zero_noise(u, x), due)

    def mode_output(self, mode, t, x, u):
        _, ys = self._outputs(mode, t, x, u)
        if not self.outputs:
            return jnp.zeros(0, x.dtype)
        # one slice per run of consecutive coordinates of one subsystem, not one per coordinate
        # (three exported 64-wide sources: `traj.eval` compiled in 48 s with per-coordinate slices)
        runs = []
        for i, j in self.outputs:
            if runs and runs[-1][0] == i and runs[-1][2] == j:
                runs[-1][2] += 1
            else:
                runs.append([i, j, j + 1])
        return jnp.concatenate([ys[i][start:stop] for i, start, stop in runs])

    @property
    def bounds_steps(self) -> bool:
        return any(s.bounds_steps for s in self.subsystems)

    def step_size_bound(self, t, x):
        """The subsystems' smallest bound."""
        return functools.reduce(jnp.minimum, [s.step_size_bound(t, self.subsystem_state(i, x))
                                              for i, s in enumerate(self.subsystems) if s.bounds_steps],
                                jnp.asarray(jnp.inf, x.dtype))

    def transition_guards(self, mode, t, x, u):
        us, _ = self.signals(mode, t, x, u)
        parts = [s.transition_guards(self.subsystem_mode(i, mode), t, self.subsystem_state(i, x), us[i])
                 for i, s in enumerate(self.subsystems) if s.transitions]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, x.dtype)

    def apply_transition(self, mode, k, t, x, u):
        """Take transition k (of the subsystem that owns it): (x+, diagram mode, stop)."""
        def branch(j, mode, t, x, u):
            i, local = self._transition_owner(j)
            us, _ = self.signals(mode, t, x, u)
            sub_mode = self.subsystem_mode(i, mode)
            x_i, target, stop = self.subsystems[i].apply_transition(
                sub_mode, local, t, self.subsystem_state(i, x), us[i])
            new_mode = mode + (target - sub_mode) * self._strides[i]
            return self.state_with(x, i, x_i), jnp.asarray(new_mode, jnp.int32), stop
        return HybridSystem._switch(k, len(self.transitions), branch, mode, t, x, u)

    # ----- the deterministic, one-mode contract -------------------------------------------

    def _with_zero_noise(self, u, x):
        return jnp.concatenate([u, jnp.zeros(self.num_noise_inputs, x.dtype)])

    def _single_mode(self, method):
        if self.is_hybrid:
            raise TypeError(f"{self.name} contains a hybrid system: its {method} depends on the "
                            f"mode; use mode_{method}(mode, t, x, u)")
        return 0

    def dynamics(self, t, x, u):
        return self.mode_dynamics(self._single_mode("dynamics"), t, x, self._with_zero_noise(u, x))

    def update(self, t, x, u):
        due = jnp.ones(len(self.sample_times), bool)
        return self.mode_update(self._single_mode("update"), t, x, self._with_zero_noise(u, x), due)

    def output(self, t, x, u):
        return self.mode_output(self._single_mode("output"), t, x, self._with_zero_noise(u, x))

    def failure_hint(self, x):
        """The subsystems' hints at their parts of x, each named by the subsystem."""
        hints = [(name, system.failure_hint(self.subsystem_state(i, x)))
                 for i, (name, system) in enumerate(zip(self.names, self.subsystems))]
        return "; ".join(f"{name}: {hint}" for name, hint in hints if hint) or None

    def check_initial_state(self, x0):
        for i, system in enumerate(self.subsystems):
            if type(system).check_initial_state is not System.check_initial_state:  # not the no-op
                system.check_initial_state(self.subsystem_state(i, x0))

    def initial_state(self):
        x = jnp.zeros(self.num_states)
        for i, s in enumerate(self.subsystems):
            x = self.state_with(x, i, jnp.asarray(s.initial_state(), x.dtype))
        return x

    def check_shapes(self, t, x) -> None:
        """Each subsystem as a system of its own, then the wiring (frame conversions)."""
        for i, sub in enumerate(self.subsystems):
            sub.check_shapes(t, self.subsystem_state(i, x))
        u = jax.ShapeDtypeStruct((self.num_inputs + self.num_noise_inputs,), x.dtype)
        mode = jnp.asarray(self.initial_mode, jnp.int32)
        try:
            out = jax.eval_shape(lambda x, u: self.mode_output(mode, t, x, u), x, u)
        except Exception as e:
            raise ValueError(f"evaluating the signals of diagram {self.name} failed (a frame "
                             f"conversion returning the wrong shape?): {type(e).__name__}: {e}") from e
        if out.shape != (self.num_outputs,):
            raise ValueError(f"diagram {self.name}'s output has shape {out.shape}, expected "
                             f"({self.num_outputs},)")

    def state_constraints(self, x):
        parts = [s.state_constraints(self.subsystem_state(i, x))
                 for i, s in enumerate(self.subsystems) if s.num_state_constraints]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, x.dtype)

    @property
    def name(self) -> str:
        return self.diagram_name


# ----- construction-time checks ---------------------------------------------------------------


def _lookup(names, name):
    try:
        return names.index(name)
    except ValueError:
        raise KeyError(f"no subsystem named {name!r}; the diagram has {list(names)}") from None


def _feedthrough_edges(subsystems, wires):
    """i -> j when i's output enters j's input and j's output depends on its input."""
    return {(w.source, w.target) for w in wires
            if w.source != INPUT and subsystems[w.target].direct_feedthrough}


def _output_order(subsystems, names, wires):
    """A topological order of the direct-feedthrough graph; a cycle is an algebraic loop."""
    edges = _feedthrough_edges(subsystems, wires)
    order, state = [], {}

    def visit(i, path):
        if state.get(i) == "done":
            return
        if state.get(i) == "active":
            loop = path[path.index(i):] + [i]
            raise ValueError("algebraic loop: " + " -> ".join(names[k] for k in loop)
                             + ": every system on it is direct feedthrough (its output depends on "
                               "its input at the same instant), so the signals around the loop are "
                               "defined only implicitly. Break it with a system without direct "
                               "feedthrough (e.g. one with state).")
        state[i] = "active"
        for a, b in sorted(edges):
            if b == i:
                visit(a, path + [i])
        state[i] = "done"
        order.append(i)

    for i in range(len(subsystems)):
        visit(i, [])
    return tuple(order)


def _input_reaches_output(subsystems, wires, outputs):
    """Whether the diagram's input reaches an output through direct-feedthrough systems only."""
    reached = {w.target for w in wires if w.source == INPUT and subsystems[w.target].direct_feedthrough}
    edges = _feedthrough_edges(subsystems, wires)
    while True:
        more = {b for a, b in edges if a in reached} - reached
        if not more:
            return any(i in reached for i, _ in outputs)
        reached |= more


# ----- the builder ----------------------------------------------------------------------------


class DiagramBuilder:
    """Wire several systems by port into a `Diagram` (Drake's `DiagramBuilder`).

    A port is a subsystem's name (its whole input or output vector) or a pair
    `(name, coordinates)` selecting coordinates by name (or index) in its frame::

        builder = DiagramBuilder()
        builder.add(plant, "plant"); builder.add(controller, "controller")
        builder.connect("plant", "controller")            # y_plant -> u_controller
        builder.connect("controller", "plant")            # y_controller -> u_plant
        builder.export_input("plant")                     # the diagram's input adds to u_plant
        builder.export_output(("plant", ["theta"]))
        diagram = builder.build("ClosedLoop")

    Whole-vector connections check frames (a registered frame conversion is applied; see
    `add_frame_conversion`); selected coordinates must agree in number. Several wires into
    one input coordinate are summed; every input coordinate of every subsystem must be fed.
    """

    def __init__(self):
        self._systems: list[System] = []
        self._names: list[str] = []
        self._wires: list[Wire] = []
        self._inputs: list[tuple[int, tuple[int, ...]]] = []
        self._fanout: list[tuple[int, int, tuple[int, ...]]] = []  # (export, subsystem, coordinates)
        self._outputs: list[tuple[int, tuple[int, ...]]] = []

    def add(self, system: System, name: str | None = None) -> str:
        """Add a subsystem; returns its name (`system.name`, made unique, by default)."""
        if not isinstance(system, System):
            raise TypeError(f"DiagramBuilder.add needs a jaxdrake.System, got {type(system).__name__}")
        if name is None:
            name, k = system.name, 2
            while name in self._names:
                name, k = f"{system.name}{k}", k + 1
        if name in self._names:
            raise ValueError(f"a subsystem named {name!r} was already added")
        self._systems.append(system)
        self._names.append(name)
        return name

    def _port(self, port, role):
        name, coords = (port, None) if isinstance(port, str) else port
        i = _lookup(self._names, name)
        frame = getattr(self._systems[i], f"{role}_frame")
        if coords is None:
            return i, tuple(range(frame.dim)), frame, True
        index = tuple(c if isinstance(c, int) else frame.index(c) for c in coords)
        for c in index:
            if not 0 <= c < frame.dim:
                raise IndexError(f"{role} coordinate {c} of {name!r} is out of range for frame {frame}")
        return i, index, Frame(frame.name, tuple(frame.coordinates[c] for c in index), frame.generic), False

    def connect(self, source, target, *, gain: float = 1.0) -> None:
        """Add `gain` times the output port `source` into the input port `target`."""
        i, src, src_frame, whole_src = self._port(source, "output")
        j, dst, dst_frame, whole_dst = self._port(target, "input")
        conversion = None
        if whole_src and whole_dst:
            conversion = frame_conversion(src_frame, dst_frame)
        elif len(src) != len(dst):
            raise ValueError(f"cannot connect {len(src)} output coordinates {src_frame} of "
                             f"{self._names[i]!r} to {len(dst)} input coordinates {dst_frame} of "
                             f"{self._names[j]!r}: the sizes differ")
        self._wires.append(Wire(i, src, j, dst, conversion, float(gain)))

    def export_input(self, target) -> int:
        """Make an input port of a subsystem part of the diagram's input (appended); returns
        the export's index, for `connect_input`."""
        j, dst, _, _ = self._port(target, "input")
        self._inputs.append((j, dst))
        return len(self._inputs) - 1

    def connect_input(self, export: int, target) -> None:
        """Feed the diagram input made by export number `export` into another input port too
        (Drake's `ConnectInput`: one diagram input, several subsystem inputs)."""
        if not 0 <= export < len(self._inputs):
            raise IndexError(f"no exported input number {export}: export_input has made {len(self._inputs)}")
        j, dst, _, _ = self._port(target, "input")
        if len(dst) != len(self._inputs[export][1]):
            raise ValueError(f"exported input {export} has {len(self._inputs[export][1])} coordinates, "
                             f"{target!r} has {len(dst)}")
        self._fanout.append((export, j, dst))

    def export_output(self, source) -> None:
        """Make an output port of a subsystem part of the diagram's output (appended)."""
        i, src, _, _ = self._port(source, "output")
        self._outputs.append((i, src))

    def build(self, name: str = "Diagram", *, input_frame: Frame | None = None,
              output_frame: Frame | None = None) -> Diagram:
        """The diagram. Its input and output frames default to the exported ports' frames
        (their concatenation, with generic names, when there are several)."""
        if not self._systems:
            raise ValueError("the diagram has no subsystems")
        wires, offset, exported = list(self._wires), 0, []
        for j, dst in self._inputs:
            exported.append(tuple(range(offset, offset + len(dst))))
            wires.append(Wire(INPUT, exported[-1], j, dst))
            offset += len(dst)
        wires += [Wire(INPUT, exported[k], j, dst) for k, j, dst in self._fanout]
        fed = {(w.target, c) for w in wires for c in w.target_index}
        for j, s in enumerate(self._systems):
            missing = [s.input_frame.coordinates[c] for c in range(s.num_inputs) if (j, c) not in fed]
            if missing:
                raise ValueError(f"input coordinates {missing} of {self._names[j]!r} (frame "
                                 f"{s.input_frame}) are not connected: connect an output to them "
                                 "or export them as the diagram's input")
        input_frame = input_frame or self._joint_frame(
            f"{name}Input", [(j, dst, "input") for j, dst in self._inputs])
        output_frame = output_frame or self._joint_frame(
            f"{name}Output", [(i, src, "output") for i, src in self._outputs])
        outputs = [(i, c) for i, src in self._outputs for c in src]
        return Diagram(self._systems, self._names, wires, outputs, num_inputs=offset,
                       input_frame=input_frame, output_frame=output_frame,
                       input_limits=self._input_limits(wires, offset), name=name)

    def _joint_frame(self, name, ports):
        frames = [getattr(self._systems[i], f"{role}_frame") for i, _, role in ports]
        whole = [idx == tuple(range(f.dim)) for f, (_, idx, _) in zip(frames, ports)]
        if len(ports) == 1 and whole[0]:
            return frames[0]
        coords = [f"{self._names[i]}.{f.coordinates[c]}" for f, (i, idx, _) in zip(frames, ports) for c in idx]
        return Frame(name, tuple(coords), generic=True)

    def _input_limits(self, wires, num_inputs):
        """A diagram input coordinate that alone feeds one limited input coordinate inherits
        its limits (so the simulator locates the switching instants); limits on internal
        signals are applied by clipping inside the diagram."""
        if not any(s.input_limits is not None for s in self._systems):
            return None
        lo, hi = jnp.full(num_inputs, -jnp.inf), jnp.full(num_inputs, jnp.inf)
        limited = False
        feeds = {}
        for w in wires:
            for src, dst in zip(w.source_index, w.target_index):
                feeds.setdefault((w.target, dst), []).append((w.source, src))
        for (j, dst), sources in feeds.items():
            limits = self._systems[j].input_limits
            if limits is None or len(sources) != 1 or sources[0][0] != INPUT:
                continue
            e = sources[0][1]
            if sum(1 for s in feeds.values() if (INPUT, e) in s) == 1:
                lo, hi = lo.at[e].set(limits[0][dst]), hi.at[e].set(limits[1][dst])
                limited = True
        return (lo, hi) if limited else None
