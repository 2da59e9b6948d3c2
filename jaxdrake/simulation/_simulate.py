"""`simulate`: validate in Python, then run the one jit-compiled loop (`_loop.py`).

The loop is `equinox.internal.while_loop` with the trajectory as in-place buffers. Its
derivatives (`autodiff`): `"forward"` runs it as it is (`jax.jvp` / `jax.jacfwd`);
`"reverse"` (the default) makes it a custom VJP (`_reverse.py`: forward sensitivities for up
to 32 differentiated scalars, else the discrete adjoint), which forward mode cannot enter;
`"adjoint"` always takes the discrete adjoint. Step sizes are not differentiated (the
gradient is that of the discrete scheme on its grid), nor is a Rosenbrock step's matrix;
event times are, by the implicit function theorem, so gradients see the shift of a switching instant and the saltation jump
at an impact.
"""
from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._compiled import compiled
from .._numbers import call_argument
from ..systems import System
from ..systems import check_initialised
from ._controller import ConstantStepSize, IController
from ._inputs import NoisyInput, leaf_to_array, make_source
from ._loop import run_simulation, vector_field_reads_time
from ._result import SimulatedTrajectory, trajectory_bytes
from ._solvers import Ros34PW2, Rosenbrock23, make_solver
from ._status import SimulationError, SimulationStatus



@compiled
def _run_simulation(system, solver, step_control, source, t0, tf, x0, *args):
    # Shapes are checked while tracing, so a wrong shape is a named Python error before any
    # compilation, and a second call (the compiled program kept) checks and traces nothing.
    # The step-size controller is built here, not on every call: `step_control` is
    # (rtol, atol) for an adaptive solver, (dt,) for a fixed step.
    system.check_shapes(t0, x0)
    controller = IController(*step_control, solver.error_order) if solver.adaptive else ConstantStepSize(*step_control)
    return run_simulation(system, solver, controller, source, t0, tf, x0, *args)


DEFAULT_ATOL = {"float64": 1e-9, "float32": 1e-5}


def simulate(system: System, tspan, x0=None, *, inputs=None, key=None, solver="auto", rtol=1e-6,
             atol=None, dt=None, max_step_size=None, max_steps: int = 4096,
             max_events: int = 256, event_tol=1e-10, dense: bool = True,
             constraint_projection: bool = False, autodiff: str = "reverse",
             throw: bool = True, device=None) -> SimulatedTrajectory:
    """Simulate a system over `tspan = (t0, tf)` (the notes' `simulate(sys, [t0 tf], x0)`).

    **Arguments:**

    - `system`: a `jaxdrake.System`.
    - `tspan`: `(t0, tf)` with t0 < tf.
    - `x0`: initial state, shape (num_states,), or as `system.full_state` takes it (a scalar
      for one state, a hybrid system's initial-mode state, a diagram's mapping from subsystems
      to their states); None takes `system.initial_state()`. With state constraints it is
      first projected onto phi(x) = 0.
    - `inputs`: a `Trajectory` (input tape), a function of time returning u(t), or a constant
      u (an array: Drake's `FixValue`; a new value, like a tape's, does not recompile, where a
      new function does); None means u = 0, as in the notes. Input limits of the system
      saturate it.
    - `key`: a JAX PRNG key, for a stochastic system (required then, refused otherwise): the
      noise path is a function of the key alone; `jax.vmap` over keys gives a Monte-Carlo batch.
    - `solver`: `"auto"` (default): `Rosenbrock23(jacobian="stiff")` for a system with
      contact (a candidate pair's geometry on a moving body: `System.bounds_steps`) at rtol >= 1e-7
      (a traced rtol counts as one: pass `solver=` for a traced tight one), else `"dopri5"`
      (`benchmarks/RESULTS.md`, "The default solver for contact");
      `"dopri5"` (adaptive), `"rosenbrock23"` (adaptive, for stiff systems), `"ros34pw2"`
      (adaptive, third order, for stiff systems at tight tolerances), `"rk4"`, `"midpoint"`
      or `"euler"` (fixed step `dt`), or a solver instance (`Rosenbrock23(jacobian="stiff")`:
      for rigid bodies in stiff contact, its matrix from the systems' `stiff_linearization`).
    - `rtol`, `atol`: tolerances of the adaptive solvers (atol: 1e-9 for a float64 state,
      1e-5 for a float32 one, whose rounding near 1 is 6e-8: at 1e-9 a box sliding on the
      floor ran out of steps within 0.06 s, and at 1e-6 Rosenbrock23 rejected 62% of its
      steps there); `dt`: the fixed step (or the first step of an adaptive one; shortened
      where the system bounds its steps, as a contact plant does: `System.step_size_bound`);
      `max_step_size`: an upper bound on steps.
    - `max_steps`: the bound on loop iterations (accepted + rejected steps) and the size of
      the trajectory buffers; `max_events`: the bound on events (Zeno protection).
    - `event_tol`: the time tolerance to which event instants are located.
    - `dense`: keep the dense output (else only the final state, for big batches).
    - `constraint_projection`: project the state onto phi(x) = 0 after every step.
    - `autodiff`: `"reverse"` (default; `jax.grad` / `jax.vjp` work: up to 32 differentiated
      scalars by forward sensitivities, which compile fast, more by the discrete adjoint),
      `"adjoint"` (`jax.grad` always by the discrete adjoint: the VJP of one loop iteration,
      looped backwards over the kept iteration states) or `"forward"` (`jax.jvp` /
      `jax.jacfwd` work, `jax.grad` does not). Second derivatives: `jax.hessian` (forward over reverse)
      in the reverse modes, `jax.jacfwd(jax.jacfwd(...))` with `"forward"`; reverse over
      reverse (`jax.grad` of a `jax.grad`) is not supported (JAX cannot transpose the loop).
      Nothing controls the derivative's own error: through a stiff impact it needs a tighter
      rtol than the value (docs/from_drake.md: a bouncing ball's at 1e-6 had the wrong sign).
    - `throw`: outside `jit` / `vmap`, raise `SimulationError` on failure; inside, the
      status is on the result (`traj.status`, `traj.success`) either way.
    - `device`: where a call from Python (outside `jit` / `vmap` / `grad`) runs. None: the
      host CPU when JAX's default device is an accelerator and no argument is committed to
      one, since one simulation is a sequence of small dependent steps that a GPU runs
      kernel by kernel, several times slower than the host; batches belong inside `vmap` /
      `jd.run_batch`, which run where their caller's program runs. A `jax.Device` chooses.

    **Returns:** a `SimulatedTrajectory`.
    """
    if not isinstance(system, System):
        raise TypeError(f"simulate needs a jaxdrake.System, got {type(system).__name__}")
    check_initialised(system)
    solver = make_solver(_default_solver(system, rtol) if isinstance(solver, str) and solver.lower() == "auto"
                         else solver)
    try:
        t0, tf = tspan
    except (TypeError, ValueError):
        raise ValueError(f"tspan must be a pair (t0, tf), got {tspan!r}") from None
    # methods through the class: a method read from a module instance is an equinox
    # BoundMethod, built anew each time (~35 us, a tenth of a pendulum's call)
    if x0 is None:
        x0 = type(system).initial_state(system)
    x0 = type(system).full_state(system, x0)
    # float16 / bfloat16 states are promoted: the step-size control needs float32 at least
    dtype = (jnp.promote_types(x0.dtype, jnp.float32) if jnp.issubdtype(x0.dtype, jnp.floating)
             else jnp.result_type(float))
    if x0.dtype != dtype:
        x0 = x0.astype(dtype)
    system = _parameters_as_arrays(system, dtype)
    if _concrete(t0, tf) and not (np.isfinite(float(t0)) and np.isfinite(float(tf)) and float(tf) > float(t0)):
        raise ValueError(f"tspan must be finite with t0 < tf, got ({float(t0)}, {float(tf)})")
    t0, tf = call_argument(t0, dtype), call_argument(tf, dtype)
    if _concrete(x0):
        host_x0 = np.asarray(x0)  # checked on the host: no op-by-op device work
        if not np.isfinite(host_x0).all():
            raise ValueError(f"x0 is not finite: {x0}")
        type(system).check_initial_state(system, host_x0)
    source = make_source(system, inputs, t0, dtype)
    if system.is_stochastic:
        if key is None:
            raise ValueError(f"{system.name} is stochastic (noise inputs {system.noise_groups}): "
                             "simulate needs a PRNG key, e.g. key=jax.random.key(0)")
        source = NoisyInput(source, key, system.noise_groups)
    elif key is not None:
        raise ValueError(f"a key was given, but {system.name} is deterministic (it has no noise inputs)")
    if not solver.adaptive and dt is None:
        raise ValueError(f"the fixed-step solver {type(solver).__name__} needs a step size dt")
    for name, v in (("rtol", rtol), ("atol", atol), ("dt", dt), ("max_step_size", max_step_size),
                    ("event_tol", event_tol)):
        if v is not None and _concrete(v) and not float(v) > 0:
            raise ValueError(f"{name} must be positive, got {v}")
    if atol is None:
        atol = DEFAULT_ATOL[np.dtype(dtype).name]
    if autodiff not in ("reverse", "forward", "adjoint"):
        raise ValueError(f"autodiff must be 'reverse', 'forward' or 'adjoint', got {autodiff!r}"
                         + (" (the checkpointed loop's VJP was replaced by the discrete adjoint, 'adjoint': the "
                            "same derivative)" if autodiff == "checkpointed" else ""))
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")

    arr = lambda v: None if v is None else call_argument(v, dtype)  # noqa: E731
    if solver.adaptive:
        step_control = (arr(rtol), arr(atol))
        h0 = dt if dt is not None else (tf - t0 if system.num_continuous_states == 0 else np.nan)
    else:
        step_control = (arr(dt),)
        h0 = dt
    try:
        with _placement(device, (system, source, x0)):
            traj = _run_simulation(system, solver, step_control, source, t0, tf, x0, arr(h0),
                                   arr(np.inf if max_step_size is None else max_step_size), arr(event_tol),
                                   max_steps, max_events, dense, constraint_projection, autodiff)
    except jax.errors.JaxRuntimeError as error:
        if "RESOURCE_EXHAUSTED" not in str(error):
            raise
        member = trajectory_bytes(system.num_states, max_steps, max_events, dense, np.dtype(dtype).itemsize)
        raise MemoryError(f"simulate: out of device memory; each simulated trajectory holds about {member:,} "
                          f"bytes (dense={dense}, max_steps={max_steps}). For a large batch: "
                          "simulate(..., dense=False) keeps only the final state, and "
                          "jd.run_batch(fn, inputs, chunk_size=...) runs it in chunks") from error
    except TypeError as error:
        if "forward-mode autodiff" in str(error):
            raise TypeError("simulate: forward-mode differentiation (jax.jvp, jax.jacfwd, jax.hessian) needs "
                            "simulate(..., autodiff='forward'); the default autodiff='reverse' is for "
                            "jax.grad / jax.vjp") from error
        if _mixes_in_float64(error, dtype):
            raise TypeError(f"simulate: the state is float32 (x0's dtype, the simulation's), but {system.name} "
                            "computes part of it in float64 (with jax_enable_x64 on, a constant such as "
                            "jnp.array([0.5, -0.9]) or np.pi * jnp.ones(2) inside one of its functions is float64): "
                            "make such constants follow the state, e.g. jnp.array([0.5, -0.9], x.dtype), or pass "
                            f"x0 as float64. ({str(error).splitlines()[0]})") from error
        raise
    if throw and _concrete(traj.status):
        status = SimulationStatus(int(traj.status))
        if not SimulationStatus.is_success(status):
            raise SimulationError(status, _failure_message(system, status, t0, tf, traj)
                                  + (_held_slip_advice(system, solver, status, rtol) or _solver_advice(solver, status))
                                  + (_clock_advice(system, source, t0, x0, status)
                                     or _precision_advice(x0.dtype, status, rtol, atol)))
    return traj


def _mixes_in_float64(error, dtype) -> bool:
    """Whether a TypeError raised while tracing a float32 simulation under x64 is a float64
    value meeting the float32 state (a scan's carry, a concatenation, a select)."""
    text = str(error)
    return (np.dtype(dtype) == np.float32 and jax.config.jax_enable_x64
            and "float64" in text and "float32" in text)


def _placement(device, arguments):
    """The device context of a call (see `simulate`'s `device`): the given device; else the
    host CPU for a call from Python whose arguments are concrete and not committed to an
    accelerator, when the default device is one; else the caller's placement."""
    if device is not None:
        return jax.default_device(device)
    if jax.default_backend() == "cpu":
        return contextlib.nullcontext()
    leaves = jax.tree.leaves(arguments)
    if not _concrete(leaves):
        return contextlib.nullcontext()
    if any(isinstance(leaf, jax.Array) and leaf.committed and any(d.platform != "cpu" for d in leaf.devices())
           for leaf in leaves):
        return contextlib.nullcontext()
    return jax.default_device(jax.devices("cpu")[0])


def _failure_message(system, status, t0, tf, traj) -> str:
    """What failed, where and the remedy; values that are traced (under `jax.grad` outside
    `jit` the status is concrete, the states are not) are left out."""
    span = f" over [{float(t0)}, {float(tf)}]" if _concrete(t0, tf) else ""
    where = f" stopped at t = {float(traj.t_final)!r}" if _concrete(traj.t_final) else " stopped"
    if _concrete(traj.final_state):
        size = float(jnp.max(jnp.abs(traj.final_state))) if traj.final_state.size else 0.0
        hint = system.failure_hint(traj.final_state)
        where += f" with max |x| = {size:.3g}"
    else:
        hint = None
    return (f"simulating {system.name}{span}{where}: "
            + (f"{hint} (status: {status.name})" if hint else f"{status.message} (status: {status.name})"))


# the tightest rtol at which `solver="auto"` gives contact the W-method; tighter, dopri5's fifth
# order wins on bouncing and sliding (2.6x at 1e-8), the W-method only on resting contact (3x)
_STIFF_CONTACT_RTOL = 1e-7


def _default_solver(system, rtol):
    """`solver="auto"`: the stiff W-method for contact at everyday tolerances (a box tumbling
    to rest 10x faster than dopri5 at rtol 1e-6, Solo-12's drop 1.3x), else dopri5."""
    try:
        loose = float(rtol) >= _STIFF_CONTACT_RTOL
    except (TypeError, jax.errors.ConcretizationTypeError):   # a traced rtol: the everyday case
        loose = True
    return _STIFF_CONTACT if system.bounds_steps and loose else "dopri5"


_STIFF_CONTACT = Rosenbrock23(jacobian="stiff")


def _solver_advice(solver, status) -> str:
    """For too many or too small steps: which stiff solver to try, or, having run one, what to
    try next (the status's own message says only "a stiff solver")."""
    if status not in (SimulationStatus.MAX_STEPS_REACHED, SimulationStatus.STEP_SIZE_TOO_SMALL):
        return ""
    if isinstance(solver, (Rosenbrock23, Ros34PW2)) and solver.jacobian == "stiff":
        return (f". This ran {type(solver).__name__}(jacobian='stiff'), whose matrix leaves out some of the dynamics' "
                f"derivative (the derivatives of H and the Coriolis terms): solver='{type(solver).__name__.lower()}' "
                "(the exact Jacobian) may take fewer steps")
    if isinstance(solver, (Rosenbrock23, Ros34PW2)):
        return (f". This ran {type(solver).__name__.lower()} already: raise max_steps, loosen rtol / atol, or for "
                "contact raise the stiction tolerance (stiction_tolerance=) or soften the contact")
    return (". Stiff solvers: solver='rosenbrock23' (the exact Jacobian); for rigid bodies in stiff contact "
            "solver=jd.simulation.Rosenbrock23(jacobian='stiff')")


def _held_slip_advice(system, solver, status, rtol) -> str:
    """For contact that ran out of steps under a Rosenbrock method at a tolerance looser than
    1e-6: a rolling or sticking contact can be held by the step at a slip s just outside the
    stiction band. Drake's law is flat there (no slope along the slip in the matrix), so stage
    1 decelerates the slip explicitly, its midpoint lands at zero slip where the law's smooth
    step gives ~no friction, and the step's slope k2 ~ 0 leaves s unchanged (a fixed point of
    the step at h ~ 2 s / A). A ball rolling on the floor at rtol 1e-4 took 29,000 steps of
    3e-5 s for 1 s; at rtol 1e-6 (the default) 1,500, under dopri5 800 (`benchmarks/RESULTS.md`)."""
    if (status != SimulationStatus.MAX_STEPS_REACHED or not system.bounds_steps
            or not isinstance(solver, (Rosenbrock23, Ros34PW2)) or not _concrete(rtol) or float(rtol) <= 1e-6):
        return ""
    return (f". At rtol {float(rtol):g} a rolling or sticking contact can be held at a slip just outside the stiction "
            "band in short steps; rtol=1e-6 (the default) or solver='dopri5' may take far fewer steps")


def _precision_advice(dtype, status, rtol, atol) -> str:
    """For a float32 simulation whose steps became too small: float32 does not resolve error
    estimates near its rounding (steps below t's spacing it does: time is carried as a pair,
    `_controller.advance`); or that ran out of steps with atol below float32's
    default 1e-5 (at 1e-9 a box sliding on the floor took 20,000 steps for 0.06 s) or rtol
    below `simulate`'s default 1e-6, within 8 eps of float32's resolution (a float32 x0 keeps
    a simulation in float32 under x64: a pendulum at rtol 1e-10 ran out of steps, where
    float64 takes 655)."""
    if np.dtype(dtype) != np.float32:
        return ""
    tight = [f"{name}={float(value):g}" for name, value, floor in (
        ("rtol", rtol, _FLOAT32_RTOL), ("atol", atol, DEFAULT_ATOL["float32"])) if _concrete(value) and float(value) < floor]
    if status == SimulationStatus.MAX_STEPS_REACHED and tight:
        return (f". The state is float32, whose rounding near 1 is 6e-8: with {' and '.join(tight)} the error test "
                f"may never pass; use rtol >= {_FLOAT32_RTOL:g} and atol >= {DEFAULT_ATOL['float32']:g} (float32's "
                f"defaults), or {_IN_FLOAT64}")
    if status != SimulationStatus.STEP_SIZE_TOO_SMALL:
        return ""
    return (". The state is float32: unless the solution blows up here, its 7 digits may be what stops the steps "
            f"(error estimates at its rounding): {_IN_FLOAT64}, or loosen rtol / atol")


def _clock_advice(system, source, t0, x0, status) -> str:
    """For a float32 simulation whose steps became too small while its vector field reads t
    (an input tape, a reference r(t)): t is one float32 number there, so steps below its
    spacing, which a contact's stick needs, are refused (`Loop.steps_below_spacing`). A leg
    pushed by a constant tape stopped at its touchdown; the same torque as a constant, the
    reference as an oscillator's state, or the tape held by a sampled system ran."""
    if np.dtype(x0.dtype) != np.float32 or status != SimulationStatus.STEP_SIZE_TOO_SMALL:
        return ""
    if not system.num_continuous_states or not vector_field_reads_time(system, source, jnp.asarray(t0, x0.dtype), x0):
        return ""
    return (". Unless the solution blows up here: its vector field reads t (an input tape or function of t, a "
            "reference r(t)), which float32 holds as one number, so steps shorter than its spacing (a contact "
            "going from sliding to sticking needs them) are refused. Make the reference a state of the diagram "
            "(e.g. an oscillator), hold the input with a sampled system (sample_time=) or give a constant, or "
            "simulate in float64")


_FLOAT32_RTOL = 1e-6   # float32 is told an rtol below this is too tight for it (simulate's default is this)

_IN_FLOAT64 = ("simulate in float64 (jax.config.update('jax_enable_x64', True) and x0 as float64, e.g. "
               "jnp.asarray(x0, jnp.float64): x0's dtype is the simulation's)")


def _parameters_as_arrays(system, dtype):
    """`leaves_to_arrays(system, dtype)` in one pass over the leaves, which also checks them:
    a NaN among the (concrete) parameters is named by its path, before it becomes a
    'non-finite state' at t0 (the paths, slow to list, only once one is found)."""
    leaves, treedef = jax.tree.flatten(system)
    if any(_is_nan_parameter(leaf) for leaf in leaves):
        for path, leaf in jax.tree_util.tree_leaves_with_path(system):
            if _is_nan_parameter(leaf):
                raise ValueError(f"{system.name}: the parameter {system.name}{jax.tree_util.keystr(path)} is NaN "
                                 f"({np.asarray(leaf)})")
    return jax.tree.unflatten(treedef, [leaf_to_array(leaf, dtype) for leaf in leaves])


def _is_nan_parameter(leaf) -> bool:
    if isinstance(leaf, float):
        return math.isnan(leaf)
    if not isinstance(leaf, (np.ndarray, jax.Array)) or isinstance(leaf, jax.core.Tracer):
        return False
    if not jax.dtypes.issubdtype(leaf.dtype, np.inexact):
        return False  # integers, booleans, typed PRNG keys (a noise parameter)
    return bool(np.isnan(np.asarray(leaf)).any())  # host values as they are; no device array is made


def _concrete(*values) -> bool:
    """No tracer among `values` (pytrees): a call from Python, not inside jit / vmap / grad."""
    if all(isinstance(v, _HOST_NUMBERS) or (isinstance(v, jax.Array) and not isinstance(v, jax.core.Tracer))
           for v in values):
        return True  # the common case, without flattening
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(values))


_HOST_NUMBERS = (int, float, np.ndarray, np.number)
