"""The System contract (notes, D.3.1): state-space systems as JAX pytrees.

A system is an `equinox.Module`: its numeric parameters are pytree leaves (so `jax.grad`
with respect to a mass or a gain works, and changing one does not recompile), while its
structure -- sizes, sample time, flags, frames -- is static metadata fixed at construction.

The state vector is laid out as in the notes, discrete part first: x = [x_d; x_c].
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from .._numbers import call_argument
from ._frame import Frame


def _static(**kwargs):
    return eqx.field(static=True, **kwargs)


def _explain_undeclared_fields(init):
    """A subclass's __init__ whose assignment to an undeclared field names the remedy (a
    system is a frozen dataclass: its fields are its class annotations)."""
    @functools.wraps(init)
    def checked_init(self, *args, **kwargs):
        try:
            init(self, *args, **kwargs)
        except dataclasses.FrozenInstanceError as error:
            name = str(error).rpartition(" ")[2].strip("'")
            raise AttributeError(
                f"{type(self).__name__}: cannot set {name!r}, which is not a declared field. A jaxdrake "
                f"System is a frozen dataclass (an equinox Module): declare each parameter in the class "
                f"body, e.g. `{name}: float` (or `{name}: jax.Array`), then assign it in __init__") from None
    return checked_init


class System(eqx.Module):
    r"""A dynamical system in state-space form (the notes' `DrakeSystem`).

    Continuous part, discrete part (sample time $\Delta t$) and output:

    $$\dot x_c = f_c(t, x, u), \qquad
      x_d(t + t') = f_d(t, x, u)\ \ t \in \{0, \Delta t, 2\Delta t, \dots\},\ t' \in (0, \Delta t],
      \qquad y = g(t, x, u),$$

    with $x = [x_d; x_c]$, optional input limits $u_{min} \le u \le u_{max}$ (a saturation
    applied to the input, whose switching instants the simulator locates as events) and
    optional state constraints $\phi(x) = 0$ that the system announces.

    Write a system by subclassing and overriding `dynamics` (continuous), `update` (discrete),
    `output` and `initial_state`, calling `super().__init__(...)` with the sizes; or build one
    from plain functions with `System.from_functions`.

    **Arguments** (all keyword):

    - `num_continuous_states`, `num_discrete_states`, `num_inputs`: sizes.
    - `num_outputs`: defaults to the number of states (and `output` defaults to y = x).
    - `sample_time`: $\Delta t$ of the discrete state; defaults to 1 when there is one. A
      diagram mixing several rates has a tuple of them (`sample_times`); its
      `discrete_update` is told which are due.
    - `direct_feedthrough`: whether the output depends on u at the same instant; by default
      inferred from `output` (see the `direct_feedthrough` property).
    - `time_invariant`: whether dynamics, update and output ignore t (default False).
    - `num_state_constraints`: the size of $\phi(x)$ returned by `state_constraints`.
    - `input_limits`: `(u_min, u_max)`, each a vector of size `num_inputs` (±inf allowed).
    - `input_frame`, `state_frame`, `output_frame`: `Frame`s naming the coordinates.
    """

    num_continuous_states: int = _static(default=0)
    num_discrete_states: int = _static(default=0)
    num_inputs: int = _static(default=0)
    num_outputs: int = _static(default=None)
    sample_times: tuple[float, ...] = _static(default=())
    declared_feedthrough: bool | None = _static(default=None)
    time_invariant: bool = _static(default=False)
    num_state_constraints: int = _static(default=0)
    input_frame: Frame = _static(default=None)
    state_frame: Frame = _static(default=None)
    output_frame: Frame = _static(default=None)
    noise_groups: tuple[tuple[int, float, float], ...] = _static(default=())
    input_limits: tuple[Any, Any] | None = None

    def __hash__(self):
        """Equinox hashes a module by its fields, which fails for array fields; such a system
        hashes by identity instead, so `jax.jit(system.dynamics)` works as for any closure
        (one compiled program per system object, its arrays constants of the program; pass
        the system as an argument, or use `equinox.filter_jit`, to vary them without
        recompiling)."""
        try:
            return super().__hash__()
        except TypeError:
            if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(self)):
                raise  # inside a trace JAX takes the unhashable (uncached) path, as before
            return id(self)

    def __init__(self, *, num_continuous_states: int = 0, num_discrete_states: int = 0,
                 num_inputs: int = 0, num_outputs: int | None = None,
                 sample_time: float | tuple[float, ...] | None = None, direct_feedthrough: bool | None = None,
                 time_invariant: bool = False, num_state_constraints: int = 0,
                 input_limits: tuple[Any, Any] | None = None, input_frame: Frame | None = None,
                 state_frame: Frame | None = None, output_frame: Frame | None = None,
                 noise_groups: tuple = ()):
        name = type(self).__name__
        for label, n in (("num_continuous_states", num_continuous_states),
                         ("num_discrete_states", num_discrete_states),
                         ("num_inputs", num_inputs), ("num_state_constraints", num_state_constraints)):
            if not isinstance(n, (int, np.integer)) or n < 0:
                raise ValueError(f"{name}: {label} must be a non-negative int, got {n!r}")
        num_states = num_continuous_states + num_discrete_states
        num_outputs = num_states if num_outputs is None else num_outputs
        if num_discrete_states > 0 and sample_time is None:
            sample_time = 1.0
        if any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(sample_time)):
            raise TypeError(f"{name}: sample_time is traced (inside jax.grad / jit / vmap), but it is static: it "
                            "fixes the simulator's update instants and the program's structure. Pass a Python "
                            "number; where the period also enters the update (a discretization), make that a parameter "
                            "(a field) of the system")
        periods = () if sample_time is None else np.atleast_1d(np.asarray(sample_time, float))
        for period in periods:
            if not (period > 0 and np.isfinite(period)):
                raise ValueError(f"{name}: sample_time must be positive and finite, got {period}")
        if len(periods) and num_discrete_states == 0:
            raise ValueError(f"{name}: a sample_time was given but the system has no discrete state")
        self.sample_times = tuple(sorted({float(p) for p in periods}))
        self.noise_groups = tuple((int(n), float(p), float(s)) for n, p, s in noise_groups)
        self.num_continuous_states = int(num_continuous_states)
        self.num_discrete_states = int(num_discrete_states)
        self.num_inputs = int(num_inputs)
        self.num_outputs = int(num_outputs)
        self.declared_feedthrough = None if direct_feedthrough is None else bool(direct_feedthrough)
        self.time_invariant = bool(time_invariant)
        self.num_state_constraints = int(num_state_constraints)
        self.input_frame = _check_frame(input_frame, name, "input", self.num_inputs, "u")
        self.state_frame = _check_frame(state_frame, name, "state", num_states, "x")
        self.output_frame = _check_frame(output_frame, name, "output", self.num_outputs, "y")
        self.input_limits = _check_limits(input_limits, name, self.num_inputs)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "__init__" in cls.__dict__:
            cls.__init__ = _explain_undeclared_fields(cls.__dict__["__init__"])

    # ----- the methods a system writer overrides -------------------------------------------

    def dynamics(self, t, x, u):
        """Time derivative of the continuous state, $\\dot x_c = f_c(t, x, u)$."""
        raise NotImplementedError(f"{self.name} has continuous states but does not define dynamics()")

    def update(self, t, x, u):
        """Next discrete state $x_d^+ = f_d(t, x, u)$, evaluated at the sample times."""
        raise NotImplementedError(f"{self.name} has discrete states but does not define update()")

    def output(self, t, x, u):
        """Output $y = g(t, x, u)$; the default is the full state."""
        if self.num_outputs != self.num_states:
            raise NotImplementedError(
                f"{self.name} has {self.num_outputs} outputs but {self.num_states} states "
                "and does not define output()")
        return x

    def initial_state(self):
        """The state used when `simulate` is given no x0 (the notes' default: zeros)."""
        return jnp.zeros(self.num_states)

    def failure_hint(self, x) -> str | None:
        """Why a simulation may have failed at the (last finite) state x, where the system can
        tell (a rigid-body plant: a singular mass matrix); None by default. `simulate` adds it
        to its error message."""
        return None

    def stiff_linearization(self) -> "System":
        """This system with every part that offers one switched to a cheaper derivative that
        keeps its stiff terms, with the same dynamics values: what a linearly implicit step
        (`Rosenbrock23(jacobian="stiff")`) builds its matrix from. A `RigidBodySystem` offers
        one; by default a system passes the request on to the subsystems it holds."""
        is_part = lambda s: isinstance(s, System) and s is not self  # noqa: E731
        return jax.tree.map(lambda s: s.stiff_linearization() if is_part(s) else s, self, is_leaf=is_part)

    def check_initial_state(self, x0) -> None:
        """Warn about a (concrete) start state that the system can tell is questionable (a
        rigid-body plant: a joint past its position limit); nothing by default. `simulate`
        calls it before compiling."""

    def full_state(self, x0):
        """The state vector, shape (num_states,), from an initial state as a user gives it (a
        scalar for one state); another shape is an error naming the state frame. `simulate`
        calls it on its x0. A hybrid system also takes its initial mode's own state, a diagram
        a mapping from subsystems to their states (`Diagram.initial_state_with`). Host numbers
        stay on the host (a numpy array), JAX arrays and tracers stay JAX arrays."""
        x = call_argument(x0)
        if x.shape == () and self.num_states == 1:
            x = x.reshape(1)
        if x.shape != (self.num_states,):
            raise ValueError(f"x0 has shape {x.shape}, but {self.name}'s state frame "
                             f"{self.state_frame} needs shape ({self.num_states},)")
        return x

    def check_shapes(self, t, x) -> None:
        """Trace each declared method once at (t, x) -- shapes only, nothing evaluated -- so that
        a wrong shape is a named Python error: `output`, and `dynamics`, `update` and
        `state_constraints` where the system has them, must return their declared sizes.
        `simulate` calls it while tracing, before compiling. A hybrid system checks its modes,
        guards and resets; a diagram its subsystems and wiring."""
        u = jax.ShapeDtypeStruct((self.num_inputs,), x.dtype)
        expected = [("output", self.output, self.num_outputs, (t, x, u))]
        if self.num_continuous_states:
            expected.append(("dynamics", self.dynamics, self.num_continuous_states, (t, x, u)))
        if self.num_discrete_states:
            expected.append(("update", self.update, self.num_discrete_states, (t, x, u)))
        if self.num_state_constraints:
            expected.append(("state_constraints", self.state_constraints, self.num_state_constraints, (x,)))
        for name, method, size, args in expected:
            try:
                out = jax.eval_shape(method, *args)
            except NotImplementedError:
                raise
            except Exception as e:
                raise ValueError(f"{self.name}.{name} failed on a state of shape {x.shape} and an "
                                 f"input of shape ({self.num_inputs},): {type(e).__name__}: {e}") from e
            if getattr(out, "shape", None) != (size,):
                raise ValueError(f"{self.name}.{name} returned shape {getattr(out, 'shape', type(out))}, "
                                 f"expected ({size},)")

    def state_constraints(self, x):
        """Announced constraints $\\phi(x) = 0$ (size `num_state_constraints`)."""
        if self.num_state_constraints:
            raise NotImplementedError(
                f"{self.name} declares {self.num_state_constraints} state constraints "
                "but does not define state_constraints()")
        return jnp.zeros(0, dtype=jnp.asarray(x).dtype)

    def discrete_update(self, t, x, u, due):
        """The discrete state after the updates that are `due` (one flag per sample time):
        $f_d$ for a single-rate system; a multi-rate diagram updates only its due parts."""
        return self.update(t, x, u)

    # ----- the mode view: every system is a hybrid system with one mode and no transitions ----
    # The simulator calls these. Their `u` is the full input: the inputs followed by the noise
    # samples w of a stochastic system (nothing else for a deterministic one).
    # `HybridSystem` and diagrams override them.

    num_modes = 1
    initial_mode = 0
    transitions = ()

    def mode_dynamics(self, mode, t, x, u):
        return self.dynamics(t, x, u)

    def mode_update(self, mode, t, x, u, due):
        return self.discrete_update(t, x, u, due)

    def mode_output(self, mode, t, x, u):
        return self.output(t, x, u)

    def transition_guards(self, mode, t, x, u):
        return jnp.zeros(0, jnp.asarray(x).dtype)

    # ----- time breakpoints: instants where the system's functions jump or kink in t ----------
    # (a `TrajectorySource`'s piece ends). The simulator ends a step on each, and within a step
    # calls the functions of `on_step(t)`: the system with every time-piecewise part fixed to
    # the piece the step starts in, so a kink never falls inside a step.

    has_breakpoints = False

    def next_breakpoint(self, t):
        """The first breakpoint after t (inf: none)."""
        return jnp.asarray(jnp.inf, jnp.asarray(t).dtype)

    def on_step(self, t) -> "System":
        """This system as seen by a step starting at t."""
        return self

    def apply_transition(self, mode, k, t, x, u):
        raise NotImplementedError(f"{self.name} has no transitions")

    # ----- a state-dependent bound on steps (a contact plant's: no tunnelling) -----------------

    bounds_steps = False

    def step_size_bound(self, t, x):
        """The longest step the system allows from (t, x) (`bounds_steps`; inf here): adaptive
        steps never exceed it, fixed ones are shortened to it."""
        return jnp.asarray(jnp.inf, jnp.asarray(x).dtype)

    # ----- derived facts --------------------------------------------------------------------

    @property
    def name(self) -> str:
        return type(self).__name__

    @property
    def direct_feedthrough(self) -> bool:
        """Whether y = g(t, x, u) reads u at the same instant (Drake's direct feedthrough): as
        declared to `__init__`, else inferred from `output`'s jaxpr — does any output variable
        depend on the input variable? — once per system structure. An output that cannot be
        traced alone counts as reading u (the safe answer)."""
        if self.declared_feedthrough is not None:
            return self.declared_feedthrough
        key = jax.tree_util.tree_structure(self)  # class and static fields: the structure
        try:
            return _INFERRED_FEEDTHROUGH[key]
        except TypeError:  # an unhashable static field: infer without remembering
            return _output_reads_input(self)
        except KeyError:
            return _INFERRED_FEEDTHROUGH.setdefault(key, _output_reads_input(self))

    @property
    def num_states(self) -> int:
        return self.num_continuous_states + self.num_discrete_states

    @property
    def sample_time(self) -> float | None:
        """The period of the discrete state (None without one, or with several rates)."""
        return self.sample_times[0] if len(self.sample_times) == 1 else None

    @property
    def num_noise_inputs(self) -> int:
        """The size of the noise vector w of a stochastic system (0 when deterministic)."""
        return sum(n for n, _, _ in self.noise_groups)

    @property
    def is_stochastic(self) -> bool:
        return bool(self.noise_groups)

    @property
    def is_hybrid(self) -> bool:
        """Whether the system switches between modes (a `HybridSystem` or a diagram with one)."""
        return self.num_modes > 1 or len(self.transitions) > 0

    @property
    def has_continuous_state(self) -> bool:
        return self.num_continuous_states > 0

    @property
    def has_discrete_state(self) -> bool:
        return self.num_discrete_states > 0

    def split_state(self, x):
        """Split x = [x_d; x_c] into (x_d, x_c)."""
        return x[..., : self.num_discrete_states], x[..., self.num_discrete_states:]

    def saturate(self, u):
        """Apply the input limits: clip u to [u_min, u_max] (identity without limits)."""
        if self.input_limits is None:
            return u
        nu = self.num_inputs
        clipped = jnp.clip(u[..., :nu], self.input_limits[0], self.input_limits[1])
        return jnp.concatenate([clipped, u[..., nu:]], axis=-1)  # noise samples pass through

    def with_input_limits(self, u_min, u_max) -> "System":
        """A copy of this system with input limits u_min <= u <= u_max (the notes' setInputLimits)."""
        limits = _check_limits((u_min, u_max), self.name, self.num_inputs)
        return eqx.tree_at(lambda s: s.input_limits, self, limits, is_leaf=lambda v: v is None)

    @classmethod
    def from_functions(cls, dynamics: Callable | None = None, update: Callable | None = None,
                       output: Callable | None = None, *, num_states: int,
                       num_inputs: int = 0, num_discrete_states: int | None = None,
                       params: Any = None, initial_state: Any = None, **kwargs) -> "FunctionSystem":
        """Build a system from plain functions.

        `dynamics(t, x, u)` makes a continuous system, `update(t, x, u)` (with `sample_time`)
        a discrete one, both a mixed one (then give `num_discrete_states`); `output` alone with
        `num_states=0` a static one (a controller u = k(t, y), say). If `params` (any
        pytree; its arrays are leaves of the system) is given, each function is called as
        `f(t, x, u, params)`. The number of outputs is that of `output`'s result (a given
        `num_outputs` or `output_frame` must agree with it; see `infer_num_outputs`). Other
        keyword arguments are those of `System`.
        """
        if dynamics is None and update is None and not (num_states == 0 and output is not None):
            raise ValueError("from_functions needs dynamics (continuous) and/or update (discrete), "
                             "or only an output with num_states=0 (a static, memoryless system)")
        if num_discrete_states is None:
            if dynamics is not None and update is not None:
                raise ValueError("a mixed system (dynamics and update) needs num_discrete_states")
            num_discrete_states = num_states if dynamics is None and update is not None else 0
        return FunctionSystem(dynamics, update, output, params=params, initial_state=initial_state,
                              num_continuous_states=num_states - num_discrete_states,
                              num_discrete_states=num_discrete_states, num_inputs=num_inputs, **kwargs)


def _argument_shapes(num_states: int, num_inputs: int):
    """Abstract (t, x, u) of the default float width: what a system's functions are traced with."""
    dtype = jnp.result_type(float)
    return (jax.ShapeDtypeStruct((), dtype), jax.ShapeDtypeStruct((num_states,), dtype),
            jax.ShapeDtypeStruct((num_inputs,), dtype))


def infer_num_outputs(functions: "Functions", kwargs: dict, *noise: jax.ShapeDtypeStruct) -> dict:
    """The rule every `from_functions` system follows for its number of outputs: the length of
    `functions.output(t, x, u, *noise[, params])`, from its shapes alone (nothing evaluated),
    unless `num_outputs` or `output_frame` is given; a given size that disagrees with the
    function's is an error naming both. Returns `kwargs` (the System's keyword arguments,
    sizes included) with `num_outputs` set."""
    kwargs = dict(kwargs)
    if functions.output is None:
        return kwargs
    declared = kwargs.get("num_outputs")
    frame = kwargs.get("output_frame")
    if declared is None and isinstance(frame, Frame):
        declared = frame.dim
    num_states = kwargs.get("num_continuous_states", 0) + kwargs.get("num_discrete_states", 0)
    args = _argument_shapes(num_states, kwargs.get("num_inputs", 0)) + noise
    try:
        shape = _output_shape(functions, args)
    except Exception:  # noqa: BLE001 -- not traceable on its own: a declared size stands
        if declared is None:
            raise
        return kwargs
    if len(shape) != 1:
        raise ValueError(f"from_functions: output must return a vector, got shape {shape} "
                         "(wrap a scalar as jnp.atleast_1d(y))")
    if declared is not None and declared != shape[0]:
        given = f"num_outputs={declared}" if kwargs.get("num_outputs") is not None else f"output_frame {frame}"
        raise ValueError(f"from_functions: output returns {shape[0]} values but {given} was given; "
                         "leave it out to have it inferred, or make them agree")
    kwargs["num_outputs"] = shape[0]
    return kwargs


_OUTPUT_SHAPES: dict = {}
_MAX_OUTPUT_SHAPES = 256  # remembered at most (the oldest forgotten first): functions made in a loop


def _output_shape(functions: "Functions", args) -> tuple:
    """The shape of `functions.output(*args[, params])`, traced once per output function,
    abstract arguments and parameters' structure and shapes (a controller rebuilt with new
    gains, as `lqr` does every call, traces nothing again)."""
    # arrays by shape and dtype; any other leaf (a Python number may set a size) by its value
    params = jax.tree.map(lambda v: jax.ShapeDtypeStruct(np.shape(v), jnp.result_type(v))
                          if eqx.is_array(v) else v, functions.params)
    key = (functions.output, tuple(args), jax.tree.structure(params), tuple(jax.tree.leaves(params)))

    def traced():
        return jax.eval_shape(lambda *a: functions.call(functions.output, *a), *args).shape

    try:
        return _OUTPUT_SHAPES[key]
    except TypeError:  # an unhashable parameter: trace without remembering
        return traced()
    except KeyError:
        shape = traced()
        if len(_OUTPUT_SHAPES) >= _MAX_OUTPUT_SHAPES:
            del _OUTPUT_SHAPES[next(iter(_OUTPUT_SHAPES))]
        return _OUTPUT_SHAPES.setdefault(key, shape)


class Functions(eqx.Module):
    """The plain functions, parameters and initial state behind a `from_functions` system:
    each function is called as `f(*args)` or, with `params`, `f(*args, params)`."""

    dynamics: Callable | None = _static(default=None)
    update: Callable | None = _static(default=None)
    output: Callable | None = _static(default=None)
    params: Any = None
    x0: Any = None

    def __init__(self, dynamics=None, update=None, output=None, params=None, initial_state=None):
        self.dynamics, self.update, self.output, self.params = dynamics, update, output, params
        self.x0 = None if initial_state is None else jnp.asarray(initial_state)

    def call(self, fn, *args):
        return fn(*args) if self.params is None else fn(*args, self.params)


class FunctionSystem(System):
    """A system whose dynamics, update and output are plain functions (see `System.from_functions`)."""

    functions: Functions

    def __init__(self, dynamics_fn=None, update_fn=None, output_fn=None, *, params=None,
                 initial_state=None, **kwargs):
        self.functions = Functions(dynamics_fn, update_fn, output_fn, params, initial_state)
        super().__init__(**infer_num_outputs(self.functions, kwargs))

    def dynamics(self, t, x, u):
        if self.functions.dynamics is None:
            return super().dynamics(t, x, u)
        return self.functions.call(self.functions.dynamics, t, x, u)

    def update(self, t, x, u):
        if self.functions.update is None:
            return super().update(t, x, u)
        return self.functions.call(self.functions.update, t, x, u)

    def output(self, t, x, u):
        if self.functions.output is None:
            return super().output(t, x, u)
        return self.functions.call(self.functions.output, t, x, u)

    def initial_state(self):
        return super().initial_state() if self.functions.x0 is None else self.functions.x0


_INFERRED_FEEDTHROUGH: dict = {}


def _output_reads_input(system: System) -> bool:
    """Whether an output variable of `system.output`'s jaxpr depends on its input variable u
    (dependencies followed equation by equation; a sub-program counts as one equation)."""
    if system.num_inputs == 0:
        return False
    shapes = _argument_shapes(system.num_states, system.num_inputs + system.num_noise_inputs)
    try:
        # a fresh function, not the bound method: JAX caches traced functions by equality, and a
        # bound method's equality compares the systems' arrays (equinox), which fails inside a trace
        jaxpr = jax.make_jaxpr(lambda t, x, u: system.output(t, x, u))(*shapes).jaxpr
    except Exception:  # noqa: BLE001 -- not traceable on its own: assume it reads u
        return True
    reads_u = {jaxpr.invars[2]}
    for eqn in jaxpr.eqns:
        if any(not isinstance(v, jax.extend.core.Literal) and v in reads_u for v in eqn.invars):
            reads_u.update(eqn.outvars)
    return any(not isinstance(v, jax.extend.core.Literal) and v in reads_u for v in jaxpr.outvars)


def check_initialised(system: System):
    """A named error for a subclass whose __init__ did not call `super().__init__(...)` (its
    sizes and frames were never declared)."""
    if system.state_frame is None:
        raise TypeError(f"{system.name} was not initialised as a System: its __init__ must call "
                        "super().__init__(num_continuous_states=..., num_inputs=..., ...) to declare its sizes")


def require_plain_system(system, caller: str, advice: str):
    """Raise a named error unless `system` is a deterministic, non-hybrid `System` whose states
    are all continuous or all discrete (what linearization and trajectory optimization take)."""
    if not isinstance(system, System):
        raise TypeError(f"{caller} needs a jaxdrake.System, got {type(system).__name__}")
    check_initialised(system)
    if system.is_hybrid or system.is_stochastic:
        raise ValueError(f"{caller}: {system.name} is hybrid or stochastic; {advice}")
    if system.has_continuous_state and system.has_discrete_state:
        raise ValueError(f"{caller}: {system.name} mixes continuous and discrete states")


def _check_frame(frame, system_name, role, size, prefix):
    if frame is None:
        return Frame.default(f"{system_name}{role.capitalize()}", size, prefix)
    if not isinstance(frame, Frame):
        raise TypeError(f"{system_name}: {role}_frame must be a jaxdrake.Frame, got {type(frame).__name__}")
    if frame.dim != size:
        raise ValueError(f"{system_name}: {role} frame {frame} has {frame.dim} coordinates "
                         f"but the system has {size} {role}s")
    return frame


def _check_limits(limits, system_name, num_inputs):
    if limits is None:
        return None
    try:
        lo, hi = limits
    except (TypeError, ValueError):
        raise ValueError(f"{system_name}: input_limits must be a pair (u_min, u_max)") from None
    bounds = []
    for label, v in (("u_min", lo), ("u_max", hi)):
        v = jnp.asarray(v, dtype=float)
        if v.shape not in ((), (num_inputs,)):
            raise ValueError(f"{system_name}: input limit {label} must be a scalar or have shape "
                             f"({num_inputs},), got shape {v.shape}")
        bounds.append(jnp.broadcast_to(v, (num_inputs,)))
    lo, hi = bounds
    if not any(isinstance(v, jax.core.Tracer) for v in bounds) and np.any(np.asarray(lo) > np.asarray(hi)):
        raise ValueError(f"{system_name}: input limits need u_min <= u_max, got {lo} and {hi}")
    return (lo, hi)
