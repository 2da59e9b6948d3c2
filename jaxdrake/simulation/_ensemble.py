"""`simulate_ensemble`: many simulations of one small continuous system, one member per lane.

`jax.vmap(simulate)` runs a batch in lockstep: every iteration of its `while` loop launches the
step's kernels and (on a GPU) reads the loop's condition back to the host, so 10^5 pendulums
cost about what 10^3 do (20 ms on an H200, latency bound). Here each member is a lane of its
own inside one kernel (Pallas on a GPU; on other devices the same arithmetic as one jitted
program over all lanes): the state is a list of vectors, one per state component, with a
member in each position, and every member steps, accepts and rejects on its own.

The system's vector field runs inside the kernel as straight-line code on those vectors: its
jaxpr is evaluated component by component (`jaxdrake._lanes`), each array of the original program an
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

from .. import _lanes
from ._controller import least_step, smallest_step
from ._solvers import Dopri5
from ._status import SimulationStatus

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
    key = (_lanes.value_key(system), n, m, dtype, settings, kernel)
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
    budget = _lanes.Budget("simulate_ensemble", f"{system.name}'s vector field", max_operations,
                           "use jax.vmap(jd.simulate(...)) or jd.run_batch for it (or raise max_operations to "
                           "accept a first call of tens of seconds)")

    def vector_field(t, x, u):
        return system.dynamics(t, x, u)

    def integrate(x_lanes, u_lanes):
        dtype, shape = x_lanes[0].dtype, x_lanes[0].shape
        closed = jax.make_jaxpr(vector_field)(jnp.zeros((), dtype), jnp.zeros(n, dtype), jnp.zeros(m, dtype))
        u = _lanes.elements(u_lanes, (m,))

        def f(t, x):
            args = [_lanes.elements([t], ()), _lanes.elements(x, (n,)), u]
            out = _lanes.evaluate(closed.jaxpr, closed.consts, args, shape, dtype, budget.fresh())[0]
            return [_lanes.materialize(v, shape, dtype) for v in _lanes.objects(out).reshape(-1)]

        return _dopri5_lanes(f, x_lanes, t0, tf, rtol, atol, max_steps)

    @jax.jit
    def program(x0s, us):
        if kernel == "xla":
            t, x, status, attempts = integrate(list(x0s), list(us))
            return t, jnp.stack(x), status, attempts

        def body(rows):  # one Pallas program: `BLOCK` members
            t, x, status, attempts = integrate(*rows)
            return [[t], x, [status], [attempts]]

        t, x, status, attempts = _lanes.pallas_over_lanes(
            body, [x0s, us], [(1, x0s.dtype), (n, x0s.dtype), (1, jnp.int32), (1, jnp.int32)])
        return t[0], x, status[0], attempts[0]

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
    h0 = jnp.maximum(h0, least_step(jnp.full(shape, t0, dtype)))  # as simulate's loop: a first step that moves t
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
        norm = rms([err / (atol + rtol * jnp.maximum(jnp.abs(x0), jnp.abs(y1))) for err, x0, y1 in zip(error, x, x1)])
        finite = functools.reduce(lambda p, q: p & q, [jnp.isfinite(v) for v in x1]) & jnp.isfinite(norm)
        factor = jnp.where(norm > 0, 0.9 * jnp.where(norm > 0, norm, 1.0) ** -0.2, 10.0)
        factor = jnp.where(finite, jnp.clip(factor, 0.2, 10.0), 0.2)
        accept = active & finite & (norm <= 1)
        h_next = step * factor
        h_next = jnp.where(accept & (step < h), jnp.maximum(h, h_next), h_next)  # a step cut at tf
        tiny = active & ~accept & ~(h_next > smallest_step(t, finite))  # a NaN step size too
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


