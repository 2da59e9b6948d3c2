"""Events: input limits as saturation modes with guards, and locating the earliest crossing.

Every event is a guard g that fires when it crosses from g < 0 to g >= 0 inside a step. The
guard vector is, in this order (the one owner of the order; `traj.events` reports indices in
it): for each input with limits its high guard, then for each its low guard (2 per input),
then one per transition out of the active mode, -phi_k (phi_k <= 0 triggers transition k).
"""

from __future__ import annotations

import functools

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np


def num_limit_guards(system) -> int:
    """The number of input-limit guards: two per input when the system has input limits."""
    return 2 * system.num_inputs if (system.input_limits is not None and system.num_inputs > 0) else 0


def event_transitions(system, indices):
    """Transition k of each guard index, or -1 for an input-limit event (numpy in, numpy out)."""
    limit = num_limit_guards(system)
    return np.where(indices >= limit, indices - limit, -1)


def saturated_input(system, u_raw, saturation):
    """u with each input held at its limit where its saturation mode says so (+1 high, -1 low);
    noise samples after the inputs pass through."""
    if system.input_limits is None:
        return u_raw
    lo, hi = system.input_limits
    nu = system.num_inputs
    u = jnp.where(saturation > 0, hi, jnp.where(saturation < 0, lo, u_raw[:nu]))
    return jnp.concatenate([u, u_raw[nu:]])


def initial_saturation(system, u_raw):
    if system.input_limits is None:
        return jnp.zeros(system.num_inputs, jnp.int32)
    lo, hi = system.input_limits
    u_raw = u_raw[: system.num_inputs]
    return jnp.where(u_raw >= hi, 1, jnp.where(u_raw <= lo, -1, 0)).astype(jnp.int32)


def limit_guards(system, u_raw, saturation):
    """Input-limit guards [g_high; g_low] (an event fires when one crosses from < 0 to >= 0).

    Free input: g_high = u - u_max, g_low = u_min - u. Saturated high: g_high = u_max - u
    (leave the limit), g_low inactive; saturated low symmetrically.
    """
    lo, hi = system.input_limits
    u_raw = u_raw[: system.num_inputs]
    inactive = -jnp.ones_like(u_raw)
    g_high = jnp.where(saturation == 0, u_raw - hi, jnp.where(saturation > 0, hi - u_raw, inactive))
    g_low = jnp.where(saturation == 0, lo - u_raw, jnp.where(saturation < 0, u_raw - lo, inactive))
    return jnp.concatenate([g_high, g_low])


def saturation_after_event(saturation, index, num_inputs):
    i = index % num_inputs
    entering = jnp.where(index < num_inputs, 1, -1)
    return saturation.at[i].set(jnp.where(saturation[i] == 0, entering, 0))


_ROOT_ITERATIONS = 6  # safeguarded Newton from a secant start: ~4 suffice for smooth guards


def locate_first_crossing(guard_fn, crossed, g_start, g_end, h, tol):
    """The earliest crossing in theta in [0, 1] among the crossed guards, and which guard it is.

    It is the root of G(theta) = max over crossed guards of g_i(theta) (G < 0 at 0, G >= 0 at
    1; `g_start`, `g_end` are the guards there), found by Newton's method safeguarded with
    bisection: the bracket [lo, hi] keeps G(lo) < 0 <= G(hi), and a Newton iterate outside it
    is replaced by the midpoint. It stops when the last update or the bracket is below `tol`
    in time, or G is exactly 0: a few iterations for smooth guards, where bisection alone
    needs ~30. Ties go to the lowest index. `guard_fn(theta)` gives all guards (of frozen
    coefficients); nothing here is differentiated (see the differentiable Newton step in the loop).

    Under `vmap` on the CPU only the members with a crossing are searched: they are gathered
    into chunks of an eighth of the batch (`_search_compacted`), so a batch in which a few
    members have an event in a step pays for those few, not for all.
    """
    # every value guard_fn closes over made an explicit argument (custom_vmap needs its
    # batched inputs as arguments); none is differentiated here
    traced = jax.make_jaxpr(guard_fn)(jnp.zeros((), g_start.dtype))
    consts = jax.lax.stop_gradient(traced.consts)

    def converted(theta, *consts):
        return jax.extend.core.jaxpr_as_fun(jax.extend.core.ClosedJaxpr(traced.jaxpr, consts))(theta)[0]

    one_member = functools.partial(_search, converted)
    search = jax.custom_batching.custom_vmap(one_member)
    search.def_vmap(functools.partial(_search_compacted, one_member))
    return search(crossed, g_start, g_end, jax.lax.stop_gradient(h), tol, *consts)


def _search(guard_fn, crossed, g_start, g_end, h, tol, *consts):
    """The safeguarded Newton search of `locate_first_crossing` for one member."""
    def G(g):
        return jnp.max(jnp.where(crossed, g, -jnp.inf))

    g0, g1 = G(g_start), G(g_end)
    secant = jnp.clip(-g0 / jnp.where(g1 > g0, g1 - g0, 1.0), 0.0, 1.0)

    def iterate(state):
        lo, hi, theta, which, done = state
        gs, dgs = jax.jvp(lambda th: guard_fn(th, *consts), (theta,), (jnp.ones_like(theta),))
        masked = jnp.where(crossed, gs, -jnp.inf)
        k = jnp.argmax(masked).astype(jnp.int32)
        g, dg = masked[k], dgs[k]
        lo, hi = jnp.where(g >= 0, lo, theta), jnp.where(g >= 0, theta, hi)
        newton = theta - g / jnp.where(dg != 0, dg, 1.0)
        # g == 0: theta is the root (it has just become hi, so the Newton iterate, theta
        # itself, is not inside the bracket: taking the midpoint instead had cost ~20
        # bisections at most events)
        exact = g == 0
        new = jnp.where(exact, theta, jnp.where((dg != 0) & (newton > lo) & (newton < hi), newton, (lo + hi) / 2))
        converged = done | exact | (jnp.abs(new - theta) * h <= tol) | ((hi - lo) * h <= tol)
        return lo, hi, jnp.where(done, theta, new), jnp.where(done, which, k), converged

    which0 = jnp.argmax(jnp.where(crossed, g_end, -jnp.inf)).astype(jnp.int32)
    state = (jnp.zeros_like(secant), jnp.ones_like(secant), secant, which0, ~jnp.any(crossed))
    # The first iterations unrolled in the program (a nested while loop costs a device-host
    # round trip per iteration on a GPU) but traced once, then a loop for the rare hard case
    # (a kink of an and-guard near the root sends Newton to bisection), bounded.
    state = jax.lax.fori_loop(0, _ROOT_ITERATIONS, lambda i, s: iterate(s), state, unroll=True)
    state = jax.lax.while_loop(lambda s: ~s[4] & (s[1] - s[0] > 0), iterate, state)
    return state[2], state[3]


def _search_compacted(search, axis_size, in_batched, crossed, *args):
    """The batched search. On the CPU over the members with a crossing only: their indices
    gathered in chunks of ceil(batch / 8) (one chunk in the usual case), searched, scattered
    back; the other members get theta = 1 and guard 0 (unused: they have no event). On an
    accelerator every member is searched, as the gathering loop's device-host round trips cost
    more there than the search (H100, bouncing-ball batch of 10^4: 32 ms compacted, 12 ms not,
    measured before the exact-root fix; CPU, rimless wheel: ~20% faster compacted)."""
    args = (crossed, *args)
    searched = jax.vmap(search, in_axes=[0 if b else None for b in in_batched])
    need = jnp.any(crossed, axis=-1) if in_batched[0] else jnp.broadcast_to(jnp.any(crossed), (axis_size,))
    chunk = -(-axis_size // 8)

    def compacted(args, need):
        def one_chunk(state):
            remaining, theta, which = state
            index = jnp.nonzero(remaining, size=chunk, fill_value=axis_size)[0]  # past the end: dropped
            members = [jnp.take(a, index, axis=0, mode="clip") if b else a for a, b in zip(args, in_batched)]
            theta_k, which_k = searched(*members)
            return (remaining.at[index].set(False, mode="drop"), theta.at[index].set(theta_k, mode="drop"),
                    which.at[index].set(which_k, mode="drop"))

        state = (need, jnp.ones(axis_size, args[1].dtype), jnp.zeros(axis_size, jnp.int32))
        return jax.lax.while_loop(lambda s: jnp.any(s[0]), one_chunk, state)[1:]

    def everyone(args, need):
        return searched(*args)

    return jax.lax.platform_dependent(args, need, cpu=compacted, default=everyone), (True, True)
