"""`simulate_ensemble`: many simulations of one small continuous system, one member per lane.

`jax.vmap(simulate)` runs a batch in lockstep: every iteration of its `while` loop launches the
step's kernels and (on a GPU) reads the loop's condition back to the host, so 10^5 pendulums
cost about what 10^3 do (20 ms on an H200, latency bound). Here each member is a lane of its
own inside one kernel (Pallas on a GPU; on other devices the same arithmetic as one jitted
program over all lanes): the state is a list of vectors, one per state component, with a
member in each position, and every member steps, accepts and rejects on its own.

The system's vector field runs inside the kernel as straight-line code on those vectors: its
jaxpr is evaluated component by component (`_lanes`), each array of the original program an
array of lane vectors, so only elementwise arithmetic reaches the kernel. Data movement with
indices known at trace time (slices, gathers, reshapes, concatenations, `.at[].set`) is
resolved while tracing; a vector field with loops, linear solves or other reductions over a
traced size is refused with a named error (use `jax.vmap(simulate)` there).
"""

from __future__ import annotations

import collections
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._solvers import Dopri5
from ._status import SimulationStatus

BLOCK = 128  # members per GPU program (lanes of one Pallas block); 64 / 256 measured no faster


class EnsembleResult(eqx.Module):
    """The end of each member's simulation: `final_time` (N,), `final_state` (N, n), `status`
    (N,) `SimulationStatus` codes, `attempts` (N,) step attempts taken (accepted and rejected)."""

    final_time: jax.Array
    final_state: jax.Array
    status: jax.Array
    attempts: jax.Array

    @property
    def success(self) -> jax.Array:
        return self.status == SimulationStatus.SUCCESS


def simulate_ensemble(system, tspan, x0s, *, inputs=None, rtol: float = 1e-6, atol: float = 1e-6,
                      max_steps: int = 4096, kernel: str | None = None,
                      max_operations: int = 2000) -> EnsembleResult:
    r"""N simulations of `system` over `tspan` from the rows of `x0s` (N, n), each with its own
    steps: Dormand-Prince 5(4) with `simulate`'s step control (`IController`: error
    $\mathrm{rms}(e_i / (atol + rtol \max(|y_{0,i}|, |y_{1,i}|))) \le 1$, next step
    $h\,\mathrm{clip}(0.9\|e\|^{-1/5}, 0.2, 10)$, Hairer's first step), so each member equals
    `simulate(system, tspan, x0, rtol=rtol, atol=atol)` to rounding.

    - `system`: continuous states only; no events, modes, noise, sampled parts, state
      constraints or time breakpoints; its vector field free of loops and linear solves.
    - `inputs`: None (zero), a vector (m,) for every member, or one per member (N, m); held
      constant and clipped to the system's input limits.
    - `rtol`, `atol`, `tspan`: Python numbers (compiled into the kernel); `max_steps`: attempts
      per member.
    - `max_operations`: the most per-lane operations one evaluation of the vector field may
      unroll into (the pendulum: 10; the acrobot's rigid-body tree: ~3,900, a 36-s first call
      on a 2-core CPU); beyond, a named error.
    - `kernel`: "pallas" (one GPU lane per member; the default on a GPU; elsewhere Pallas's
      interpreter, slow, for checking) or "xla" (one jitted program over all lanes; the default
      off a GPU).

    Returns an `EnsembleResult`; members that fail carry their status (no exception). Not
    differentiable (use `simulate`). The compiled program is kept per system, sizes and settings. Measured on an H200 (float64, 10
    s, rtol 1e-8): 10^5 pendulums in 2.6 ms against 20.5 ms for `jax.vmap(simulate)`."""
    x0s = jnp.asarray(x0s)
    _check_system(system)
    n, m = system.num_continuous_states, system.num_inputs
    if x0s.ndim != 2 or x0s.shape[1] != n:
        raise ValueError(f"simulate_ensemble: x0s must have shape (N, {n}) for {system.name}'s {n} states, "
                         f"got {x0s.shape}")
    if not jnp.issubdtype(x0s.dtype, jnp.floating):
        x0s = x0s.astype(jnp.result_type(float))
    count, dtype = x0s.shape[0], x0s.dtype
    us = jnp.zeros((count, m), dtype) if inputs is None else jnp.broadcast_to(jnp.asarray(inputs, dtype), (count, m))
    try:
        t0, tf, rtol, atol = (float(v) for v in (*tspan, rtol, atol))
    except (TypeError, jax.errors.ConcretizationTypeError):
        raise TypeError("simulate_ensemble: tspan, rtol and atol must be Python numbers (they are compiled "
                        "into the kernel); for traced ones use jax.vmap(simulate)") from None
    if not (np.isfinite(t0) and np.isfinite(tf) and tf > t0):
        raise ValueError(f"simulate_ensemble: tspan must be finite with t0 < tf, got {tspan}")
    if not (rtol > 0 and atol > 0):
        raise ValueError(f"simulate_ensemble: rtol and atol must be positive, got {rtol}, {atol}")
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"simulate_ensemble: max_steps must be a positive int, got {max_steps!r}")
    kernel = kernel or ("pallas" if jax.default_backend() == "gpu" else "xla")
    if kernel not in ("pallas", "xla"):
        raise ValueError(f"simulate_ensemble: kernel must be 'pallas' or 'xla', got {kernel!r}")
    program = _program(system, n, m, str(dtype), (t0, tf, rtol, atol, max_steps, int(max_operations)), kernel)
    t, x, status, attempts = program(x0s.T, system.saturate(us).T)
    return EnsembleResult(t, x.T, status, attempts)


def _check_system(system):
    """Refuse what one lane cannot simulate, naming what to use instead."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(system)):
        raise TypeError(f"simulate_ensemble: {system.name}'s parameters are traced (under jit, vmap or grad), "
                        "but they are compiled into the kernel as constants: pass a concrete system; for "
                        "parameters per member, or gradients, use jax.vmap(jd.simulate(...))")
    unsupported = [(system.num_discrete_states > 0, "a discrete (sampled) state"),
                   (system.is_hybrid, "modes and transitions (events)"),
                   (system.is_stochastic, "noise inputs"),
                   (system.num_state_constraints > 0, "state constraints"),
                   (system.has_breakpoints, "time breakpoints (a piecewise input tape)"),
                   (system.num_continuous_states == 0, "no continuous state")]
    for present, what in unsupported:
        if present:
            raise ValueError(f"simulate_ensemble: {system.name} has {what}; simulate_ensemble integrates "
                             "continuous dynamics only: use jax.vmap(jd.simulate(...)) for it")


_PROGRAMS: collections.OrderedDict = collections.OrderedDict()


def _program(system, n, m, dtype, settings, kernel):
    """The compiled ensemble program, kept per system values, sizes and settings (32 kept)."""
    leaves, treedef = jax.tree.flatten(system)
    arrays = [np.asarray(v) if eqx.is_array_like(v) else None for v in leaves]
    values = tuple((a.shape, str(a.dtype), a.tobytes()) if a is not None else v for a, v in zip(arrays, leaves))
    key = (treedef, values, n, m, dtype, settings, kernel)
    try:
        program = _PROGRAMS.pop(key)
    except KeyError:
        program = _build(system, n, m, settings, kernel)
    _PROGRAMS[key] = program
    if len(_PROGRAMS) > 32:
        _PROGRAMS.popitem(last=False)
    return program


def _build(system, n, m, settings, kernel):
    t0, tf, rtol, atol, max_steps, max_operations = settings

    def vector_field(t, x, u):
        return system.dynamics(t, x, u)

    def integrate(x_lanes, u_lanes):
        dtype, shape = x_lanes[0].dtype, x_lanes[0].shape
        closed = jax.make_jaxpr(vector_field)(jnp.zeros((), dtype), jnp.zeros(n, dtype), jnp.zeros(m, dtype))

        def f(t, x):
            out = _lanes(closed.jaxpr, closed.consts, [_elements([t], ()), _elements(x, (n,)), _elements(u_lanes, (m,))],
                         shape, dtype, _Budget(system.name, max_operations))[0]
            return [_materialize(v, shape, dtype) for v in _objects(out).reshape(-1)]

        return _dopri5_lanes(f, x_lanes, t0, tf, rtol, atol, max_steps)

    if kernel == "xla":
        @jax.jit
        def program(x0s, us):
            t, x, status, attempts = integrate(list(x0s), list(us))
            return t, jnp.stack(x), status, attempts
        return program
    return _pallas_program(integrate, n, m)


def _pallas_program(integrate, n, m):
    """One Pallas (Triton) program per `BLOCK` members: rows of the (n, N) states padded to a
    power of two (Triton's block shapes), members padded to a multiple of `BLOCK`."""
    from jax.experimental import pallas as pl

    rows_x, rows_u = pl.next_power_of_2(n), pl.next_power_of_2(max(m, 1))

    def kernel(x_ref, u_ref, t_ref, xf_ref, status_ref, attempts_ref):
        t, x, status, attempts = integrate([x_ref[i, :] for i in range(n)], [u_ref[i, :] for i in range(m)])
        t_ref[...] = t
        for i in range(n):
            xf_ref[i, :] = x[i]
        status_ref[...] = status
        attempts_ref[...] = attempts

    @jax.jit
    def program(x0s, us):
        count, dtype = x0s.shape[1], x0s.dtype
        padded = -(-count // BLOCK) * BLOCK
        x0s = jnp.pad(x0s, ((0, rows_x - n), (0, padded - count)), mode="edge")
        us = jnp.pad(us, ((0, rows_u - m), (0, padded - count)), mode="edge") if m else jnp.zeros((1, padded), dtype)
        lanes = pl.BlockSpec((BLOCK,), lambda i: (i,))
        t, x, status, attempts = pl.pallas_call(
            kernel, grid=(padded // BLOCK,),
            in_specs=[pl.BlockSpec((rows_x, BLOCK), lambda i: (0, i)), pl.BlockSpec((rows_u, BLOCK), lambda i: (0, i))],
            out_specs=[lanes, pl.BlockSpec((rows_x, BLOCK), lambda i: (0, i)), lanes, lanes],
            out_shape=[jax.ShapeDtypeStruct((padded,), dtype), jax.ShapeDtypeStruct((rows_x, padded), dtype),
                       jax.ShapeDtypeStruct((padded,), jnp.int32), jax.ShapeDtypeStruct((padded,), jnp.int32)],
            interpret=jax.default_backend() != "gpu",  # elsewhere Pallas's interpreter (slow: for checking)
        )(x0s, us)
        return t[:count], x[:n, :count], status[:count], attempts[:count]

    return program


def _dopri5_lanes(f, x, t0, tf, rtol, atol, max_steps):
    """Dormand-Prince 5(4) on lanes (x: a list of n vectors), each lane with its own t, h,
    acceptance and status; the rules of `simulate`'s loop with an `IController` (first step,
    step ends snapped onto tf, the error norm, the step-size update and its floor, FSAL)."""
    n, dtype, shape = len(x), x[0].dtype, x[0].shape
    eps = float(jnp.finfo(dtype).eps)
    c, a, b, e = Dopri5.c, Dopri5.a, Dopri5.b, Dopri5.e
    rms = lambda vs: jnp.sqrt(sum(v * v for v in vs) / n)  # noqa: E731

    def combine(weights, ks, i):  # sum_j w_j k_j[i] in stage order, as the solvers combine
        terms = [float(w) * k[i] for w, k in zip(weights, ks) if w != 0]
        return functools.reduce(lambda p, q: p + q, terms)

    k0 = f(jnp.full(shape, t0, dtype), x)
    scale = [atol + rtol * jnp.abs(v) for v in x]  # IController.initial_step
    d0, d1 = rms([v / s for v, s in zip(x, scale)]), rms([k / s for k, s in zip(k0, scale)])
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1)).astype(dtype)
    finite0 = functools.reduce(lambda p, q: p & q, [jnp.isfinite(v) for v in x])
    status0 = jnp.where(finite0, SimulationStatus.SUCCESS, SimulationStatus.NONFINITE_INITIAL_STATE).astype(jnp.int32)

    def running(t, status):
        return (t < tf) & (status == SimulationStatus.SUCCESS)

    def cond(carry):
        t, _, _, _, status, attempts = carry
        return jnp.sum(jnp.where(running(t, status) & (attempts < max_steps), 1, 0)) > 0

    def body(carry):
        t, h, x, k0, status, attempts = carry
        active = running(t, status) & (attempts < max_steps)
        t_next = t + h
        t_next = jnp.where(t_next >= tf - (1e-6 * h + 64 * eps * abs(tf)), tf, t_next)
        step = t_next - t
        ks = [k0]
        for s in range(1, 7):
            ks.append(f(t + float(c[s]) * step, [x[i] + step * combine(a[s, :s], ks, i) for i in range(n)]))
        x1 = [x[i] + step * combine(b, ks, i) for i in range(n)]
        error = [step * combine(e, ks, i) for i in range(n)]
        finite = functools.reduce(lambda p, q: p & q, [jnp.isfinite(v) for v in x1])
        norm = rms([err / (atol + rtol * jnp.maximum(jnp.abs(x0), jnp.abs(y1))) for err, x0, y1 in zip(error, x, x1)])
        factor = jnp.where(norm > 0, 0.9 * jnp.where(norm > 0, norm, 1.0) ** -0.2, 10.0)
        factor = jnp.where(finite, jnp.clip(factor, 0.2, 10.0), 0.2)
        accept = active & finite & (norm <= 1)
        h_next = step * factor
        h_next = jnp.where(accept & (step < h), jnp.maximum(h, h_next), h_next)  # a step cut at tf
        tiny = active & ~accept & (h_next <= 16 * eps * jnp.maximum(jnp.abs(t), 1.0))
        status = jnp.where(tiny, jnp.where(finite, SimulationStatus.STEP_SIZE_TOO_SMALL,
                                           SimulationStatus.NONFINITE_STATE), status).astype(jnp.int32)
        return (jnp.where(accept, t_next, t), jnp.where(active, h_next, h),
                [jnp.where(accept, x1[i], x[i]) for i in range(n)],
                [jnp.where(accept, ks[6][i], k0[i]) for i in range(n)],
                status, attempts + jnp.where(active, 1, 0))

    carry = (jnp.full(shape, t0, dtype), h0, x, k0, status0, jnp.ones(shape, jnp.int32))  # the first f: one attempt
    t, _, x, _, status, attempts = jax.lax.while_loop(cond, body, carry)
    status = jnp.where((status == SimulationStatus.SUCCESS) & (t < tf), SimulationStatus.MAX_STEPS_REACHED, status)
    return t, x, status.astype(jnp.int32), attempts


# ----- the vector field on lanes ---------------------------------------------------------------
# A value of the original program is either concrete (a NumPy array, known while tracing) or an
# object array of its shape whose elements are lane vectors (or Python / NumPy scalars).

_ELEMENTWISE = {
    "abs", "acos", "acosh", "add", "and", "asin", "asinh", "atan", "atan2", "atanh", "cbrt", "ceil", "clamp",
    "convert_element_type", "copy", "copy_p", "cos", "cosh", "div", "eq", "erf", "erf_inv", "erfc", "exp", "exp2",
    "expm1", "floor", "ge", "gt", "integer_pow", "is_finite", "le", "log", "log1p", "logistic", "lt", "max", "min",
    "mul", "ne", "neg", "nextafter", "not", "or", "pow", "rem", "round", "rsqrt", "select_n", "sign", "sin", "sinh",
    "sqrt", "square", "sub", "tan", "tanh", "xor"}
# single-operand data movement: where each output element comes from, found by running the
# primitive on the operand's flat positions
_MOVEMENT = {"slice", "reshape", "squeeze", "broadcast_in_dim", "transpose", "rev", "dynamic_slice", "gather",
             "expand_dims"}
# two-operand data movement of the same kind (the update's positions offset past the operand's)
_OVERWRITE = {"dynamic_update_slice", "scatter"}
_CALLS = {"pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr", "custom_jvp_call": "call_jaxpr",
          "custom_vjp_call": "call_jaxpr", "custom_vmap_call": "call", "remat": "jaxpr", "checkpoint": "jaxpr",
          "jit": "jaxpr"}


class _Budget:
    """Counts the lane vectors one evaluation of the vector field makes, and refuses more
    than `limit`: a rigid-body tree unrolls into long straight-line code, slow to trace and
    compile (the acrobot's ABA: ~3,900 operations, a 36-s first call on a 2-core CPU)."""

    def __init__(self, name, limit):
        self.name, self.limit, self.spent = name, limit, 0

    def spend(self, outputs):
        self.spent += sum(np.size(v) for v in outputs if not _concrete(v))
        if self.spent > self.limit:
            raise NotImplementedError(
                f"simulate_ensemble: {self.name}'s vector field unrolls into more than max_operations="
                f"{self.limit:,} per-lane operations (a rigid-body tree?), whose kernel is slow to compile: "
                "use jax.vmap(jd.simulate(...)) or jd.run_batch for it, or raise max_operations to accept "
                "a first call of tens of seconds")


def _lanes(jaxpr, consts, args, shape, dtype, budget):
    """Evaluate `jaxpr` with `args` (object arrays of lanes, or concrete arrays); returns its
    outputs in the same representation."""
    env = {}

    def read(v):
        return np.asarray(v.val) if isinstance(v, jax.extend.core.Literal) else env[v]

    for var, value in zip(jaxpr.constvars, consts):
        env[var] = np.asarray(value)
    for var, value in zip(jaxpr.invars, args):
        env[var] = value
    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        if all(_concrete(v) for v in inputs) and name not in _CALLS:
            with jax.ensure_compile_time_eval():
                out = eqn.primitive.bind(*[jnp.asarray(v) for v in inputs], **eqn.params)
            outs = [np.asarray(o) for o in (out if eqn.primitive.multiple_results else [out])]
        elif name in _CALLS:
            outs = _lanes(*_open(eqn.params[_CALLS[name]]), inputs, shape, dtype, budget)
        elif name == "scan":
            outs = _unrolled_scan(eqn, inputs, shape, dtype, budget)
        elif name in _ELEMENTWISE:
            outs = [_elementwise(eqn, inputs, shape)]
        elif name in _MOVEMENT:
            outs = [_moved(eqn, inputs[0], inputs[1:])]
        elif name in _OVERWRITE:
            outs = [_overwritten(eqn, inputs)]
        elif name == "scatter-add":
            outs = [_scatter_added(eqn, inputs)]
        elif name == "concatenate":
            outs = [np.concatenate([_objects(v) for v in inputs], axis=eqn.params["dimension"])]
        elif name == "stack":
            outs = [np.stack([_objects(v) for v in inputs], axis=eqn.params["axis"])]
        elif name == "unstack":
            outs = list(np.moveaxis(_objects(inputs[0]), eqn.params.get("axis", 0), 0))
        elif name == "split":
            outs = np.split(_objects(inputs[0]), np.cumsum(eqn.params["sizes"])[:-1], axis=eqn.params["axis"])
        elif name in ("reduce_sum", "reduce_max", "reduce_min"):
            outs = [_reduced(name, _objects(inputs[0]), eqn.params["axes"])]
        elif name == "dot_general":
            outs = [_dot(eqn, inputs)]
        else:
            raise NotImplementedError(
                f"simulate_ensemble: the vector field uses `{name}`, which has no per-lane form here (loops, "
                "linear solves and traced indices do not); use jax.vmap(jd.simulate(...)) for this system")
        if name not in _CALLS and name != "scan":  # (counted inside)
            budget.spend(outs)
        for var, value in zip(eqn.outvars, outs):
            env[var] = _wrapped(value)
    return [read(v) for v in jaxpr.outvars]


def _open(closed):
    """(jaxpr, consts) of a closed or open jaxpr."""
    return (closed.jaxpr, closed.consts) if hasattr(closed, "consts") else (closed, ())


def _unrolled_scan(eqn, inputs, shape, dtype, budget):
    """A `lax.scan` (a static length) unrolled: its body evaluated once per iteration, so that
    indices computed from the iteration counter are known while tracing."""
    p = eqn.params
    consts, carry = inputs[:p["num_consts"]], inputs[p["num_consts"]:p["num_consts"] + p["num_carry"]]
    xs, ys = inputs[p["num_consts"] + p["num_carry"]:], []
    order = range(p["length"] - 1, -1, -1) if p["reverse"] else range(p["length"])
    for i in order:
        outs = _lanes(*_open(p["jaxpr"]), [*consts, *carry, *[_element(x, i) for x in xs]], shape, dtype, budget)
        carry, y = outs[:p["num_carry"]], outs[p["num_carry"]:]
        ys.append(y)
    if p["reverse"]:
        ys.reverse()
    stacked = [np.stack([y[k] for y in ys]) if all(_concrete(y[k]) for y in ys)
               else np.stack([_objects(y[k]) for y in ys]) for k in range(len(eqn.outvars) - len(carry))]
    return [*carry, *stacked]


def _element(value, i):
    """value[i] along the first axis, in the same representation as value."""
    return np.asarray(value[i]) if _concrete(value) else _wrapped(value[i])


def _wrapped(value):
    """An object array as it is; a lone element (a lane vector, from indexing or a product)
    as a 0-d object array."""
    return value if isinstance(value, np.ndarray) else _elements([value], ())


def _concrete(value) -> bool:
    return not (isinstance(value, np.ndarray) and value.dtype == object)


def _elements(lanes, shape):
    """An object array of `shape` holding the lane vectors `lanes` (NumPy would otherwise read
    the vectors as one more axis)."""
    out = np.empty(len(lanes), dtype=object)
    for i, lane in enumerate(lanes):
        out[i] = lane
    return out.reshape(shape)


def _objects(value):
    """An object array of the value's elements (concrete numbers stay NumPy scalars)."""
    return value if not _concrete(value) else np.asarray(value).astype(object)


def _materialize(element, shape, dtype):
    """A lane vector of `dtype` from an element (a lane vector or a number)."""
    if isinstance(element, (int, float, bool, np.generic, np.ndarray)) or np.ndim(element) == 0:
        return jnp.full(shape, element, dtype)
    return element.astype(dtype) if element.dtype != dtype else element


def _elementwise(eqn, inputs, shape):
    out_aval = eqn.outvars[0].aval
    arrays = np.broadcast_arrays(*[_objects(v) for v in inputs])
    result = np.empty(out_aval.shape, dtype=object)
    for index in np.ndindex(*out_aval.shape):
        elements = []
        for var, array in zip(eqn.invars, arrays):
            element = array[index]
            elements.append(_materialize(element, shape, var.aval.dtype) if not hasattr(element, "shape")
                            or element.shape != shape else element)
        result[index] = eqn.primitive.bind(*elements, **eqn.params)
    return result


def _moved(eqn, operand, others):
    """A data-movement primitive on an object array, from the positions it moves."""
    _require_concrete(eqn, others)
    operand = _objects(operand)
    positions = np.arange(operand.size, dtype=np.int32).reshape(operand.shape)
    with jax.ensure_compile_time_eval():
        moved = np.asarray(eqn.primitive.bind(jnp.asarray(positions), *[jnp.asarray(v) for v in others], **eqn.params))
    return operand.reshape(-1)[moved]


def _overwritten(eqn, inputs):
    """`dynamic_update_slice(operand, update, *indices)` or `scatter(operand, indices, updates)`
    (replacing): the operand's and the update's elements, placed by their positions."""
    if eqn.primitive.name == "scatter":
        operand, indices, update = inputs[0], inputs[1], inputs[2]
        others = [indices]
    else:
        operand, update, others = inputs[0], inputs[1], inputs[2:]
    _require_concrete(eqn, others)
    operand, update = _objects(operand), _objects(update)
    offset = operand.size
    positions = np.arange(operand.size, dtype=np.int32).reshape(operand.shape)
    update_positions = offset + np.arange(update.size, dtype=np.int32).reshape(update.shape)
    with jax.ensure_compile_time_eval():
        if eqn.primitive.name == "scatter":
            placed = eqn.primitive.bind(jnp.asarray(positions), jnp.asarray(others[0]), jnp.asarray(update_positions),
                                        **eqn.params)
        else:
            placed = eqn.primitive.bind(jnp.asarray(positions), jnp.asarray(update_positions),
                                        *[jnp.asarray(v) for v in others], **eqn.params)
    return np.concatenate([operand.reshape(-1), update.reshape(-1)])[np.asarray(placed)]


def _scatter_added(eqn, inputs):
    """`scatter-add(operand, indices, updates)` with known indices: each update's target found
    by scattering a one-hot update onto zeros, then added there."""
    operand, indices, updates = inputs
    _require_concrete(eqn, [indices])
    out, updates = _objects(operand).reshape(-1).copy(), _objects(updates)
    dtype = eqn.invars[0].aval.dtype  # the primitive's own (its adding region is typed)
    for j in range(updates.size):
        one_hot = np.zeros(updates.size, dtype)
        one_hot[j] = 1
        with jax.ensure_compile_time_eval():
            hit = np.asarray(eqn.primitive.bind(jnp.zeros(np.shape(operand), dtype), jnp.asarray(indices),
                                                jnp.asarray(one_hot.reshape(updates.shape)), **eqn.params))
        for target in np.flatnonzero(hit.reshape(-1)):
            out[target] = out[target] + updates.reshape(-1)[j]
    return out.reshape(np.shape(operand))


def _require_concrete(eqn, indices):
    if not all(_concrete(v) for v in indices):
        raise NotImplementedError(f"simulate_ensemble: the vector field's `{eqn.primitive.name}` takes indices that "
                                  "depend on the state (or time); use jax.vmap(jd.simulate(...)) for this system")


def _reduced(name, operand, axes):
    combine = {"reduce_sum": lambda p, q: p + q, "reduce_max": jnp.maximum, "reduce_min": jnp.minimum}[name]
    moved = np.moveaxis(operand, axes, tuple(range(-len(axes), 0)))
    flat = moved.reshape(moved.shape[:moved.ndim - len(axes)] + (-1,))
    out = np.empty(flat.shape[:-1], dtype=object)
    for index in np.ndindex(*out.shape):
        out[index] = functools.reduce(combine, list(flat[index]))
    return out


def _dot(eqn, inputs):
    """`dot_general` as sums of products, one `tensordot` per batch index: batch dimensions
    first, then the left operand's free dimensions and the right one's (XLA's order)."""
    (lhs_contract, rhs_contract), (lhs_batch, rhs_batch) = eqn.params["dimension_numbers"]
    lhs = np.moveaxis(_objects(inputs[0]), tuple(lhs_batch), tuple(range(len(lhs_batch))))
    rhs = np.moveaxis(_objects(inputs[1]), tuple(rhs_batch), tuple(range(len(rhs_batch))))
    # the contracting axes counted among each operand's axes that are not batch axes
    lhs_axes = [[d for d in range(lhs.ndim) if d not in lhs_batch].index(c) for c in lhs_contract]
    rhs_axes = [[d for d in range(rhs.ndim) if d not in rhs_batch].index(c) for c in rhs_contract]
    batch = lhs.shape[:len(lhs_batch)]
    parts = [_wrapped(np.tensordot(lhs[index], rhs[index], axes=(lhs_axes, rhs_axes))) for index in np.ndindex(*batch)]
    return parts[0] if not batch else np.stack(parts).reshape(batch + parts[0].shape)

