r"""Rapidly-exploring random trees (Underactuated, ch. 15; LaValle 1998), in JAX with fixed-size
node arrays, so that one jitted program grows a tree and `jax.vmap` over PRNG keys grows many
at once.

Each iteration samples a point (the goal with probability `goal_bias`, else uniformly in the
box), finds the nearest node, and extends towards the sample:

- `rrt`: geometric, a straight step of at most `step_size`, kept when the segment misses every
  circular (spherical) obstacle and stays in the box;
- `kinodynamic_rrt`: by simulating the system for `dt` from the nearest node under
  `num_controls` random inputs and keeping the end state nearest the sample (in the weighted,
  wrapped distance), when valid.

A tree stops when a node is within `goal_tolerance` of the goal, or when `max_nodes` nodes or
`max_iterations` samples are used.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import simulate
from ..simulation import leaves_to_arrays
from ..systems import System


class RRTResult(eqx.Module):
    """A grown tree: `nodes` (max_nodes, d) (the first `num_nodes` used), `parents` (-1 for the
    root), `controls` (the input that reached each node; kinodynamic trees only, else empty),
    `success`, `goal_node` (the node that reached the goal, -1 if none), `iterations` (samples
    drawn). Batched under `vmap`: every field gains a leading axis."""

    nodes: jax.Array
    parents: jax.Array
    controls: jax.Array
    num_nodes: jax.Array
    success: jax.Array
    goal_node: jax.Array
    iterations: jax.Array

    def path(self) -> np.ndarray:
        """The nodes from the root to the goal node, on the host (one tree, successful)."""
        if np.ndim(self.num_nodes) != 0:
            raise ValueError("path() is for one tree; index a batch first: jax.tree.map(lambda a: a[i], result)")
        if not bool(self.success):
            raise ValueError("this tree did not reach the goal: no path")
        parents, k, chain = np.asarray(self.parents), int(self.goal_node), []
        while k >= 0:
            chain.append(k)
            k = parents[k]
        return np.asarray(self.nodes)[chain[::-1]]


def rrt(start, goal, bounds, key, *, obstacles=None, step_size=0.1, goal_bias=0.05,
        goal_tolerance=None, max_nodes: int = 2000, max_iterations: int | None = None) -> RRTResult:
    """Geometric RRT in a box `bounds = (low, high)` with circular / spherical `obstacles =
    (centres (k, d), radii (k,))`. `goal_tolerance` defaults to `step_size`;
    `max_iterations` to 20 x `max_nodes`."""
    start, goal, low, high = _points(start, goal, bounds)
    centres, radii = _obstacles(obstacles, start.shape[0], start.dtype)
    if _concrete(start, goal, centres, radii):
        for name, p in (("start", start), ("goal", goal)):
            if np.any(np.linalg.norm(np.asarray(p) - np.asarray(centres), axis=1) <= np.asarray(radii)):
                raise ValueError(f"rrt: the {name} {np.asarray(p)} is inside an obstacle")
    tolerance = step_size if goal_tolerance is None else goal_tolerance
    extend = _StraightStep(jnp.asarray(step_size, start.dtype), centres, radii, low, high)
    return _grow(start, goal, low, high, key, extend, _WeightedDistance(jnp.ones_like(start)), tolerance,
                 goal_bias, max_nodes, max_iterations or 20 * max_nodes, 0)


def kinodynamic_rrt(system: System, x_start, x_goal, bounds, input_bounds, dt, key, *, num_controls: int = 8,
                    weights=None, periodic=(), goal_bias=0.05, goal_tolerance=0.1, max_nodes: int = 2000,
                    max_iterations: int | None = None, is_valid=None, solver="rk4") -> RRTResult:
    """Kinodynamic RRT for a time-invariant continuous `system`: states sampled in `bounds`,
    inputs uniformly in `input_bounds = (low, high)`, held for `dt` (one `solver` step).
    Distance: sqrt(sum(weights * d**2)) with d wrapped for `periodic` coordinates
    (`(index, low, high)` triples, as in `fitted_value_iteration`). `is_valid(x)`: an extra
    state check (default: inside `bounds`, periodic coordinates wrapped)."""
    if not isinstance(system, System):
        raise TypeError(f"kinodynamic_rrt needs a jaxdrake.System, got {type(system).__name__}")
    x_start, x_goal, low, high = _points(x_start, x_goal, bounds)
    u_low, u_high = (jnp.broadcast_to(jnp.asarray(b, x_start.dtype), (system.num_inputs,)) for b in input_bounds)
    if x_start.shape[0] != system.num_states:
        raise ValueError(f"{system.name} has {system.num_states} states; x_start has {x_start.shape[0]}")
    w = jnp.ones_like(x_start) if weights is None else jnp.asarray(weights, x_start.dtype)
    periodic = tuple((int(k), float(lo), float(hi)) for k, lo, hi in periodic)
    distance = _WeightedDistance(w, periodic)
    extend = _SimulatedStep(leaves_to_arrays(system, x_start.dtype), u_low, u_high, low, high, jnp.asarray(dt, x_start.dtype), distance,
                            num_controls, solver, is_valid)
    return _grow(x_start, x_goal, low, high, key, extend, distance, goal_tolerance, goal_bias, max_nodes,
                 max_iterations or 20 * max_nodes, system.num_inputs)


class _StraightStep(eqx.Module):
    """Geometric extension: at most `step_size` towards the target, if the segment is free."""

    step_size: jax.Array
    centres: jax.Array
    radii: jax.Array
    low: jax.Array
    high: jax.Array

    def __call__(self, nearest, target, key):
        step = target - nearest
        length = jnp.sqrt(jnp.sum(step ** 2))
        new = jnp.where(length > self.step_size,
                        nearest + step * (self.step_size / jnp.maximum(length, 1e-300)), target)
        free = _segment_misses(nearest, new, self.centres, self.radii) & jnp.all((new >= self.low) & (new <= self.high))
        return new, free, jnp.zeros(0, nearest.dtype)


class _WeightedDistance(eqx.Module):
    """sqrt(sum(w d^2)), d wrapped into [-span/2, span/2) for periodic coordinates."""

    weights: jax.Array
    periodic: tuple = eqx.field(static=True, default=())

    def wrap(self, x):
        for k, lo, hi in self.periodic:
            x = x.at[k].set(lo + jnp.mod(x[k] - lo, hi - lo))
        return x

    def squared(self, a, b):
        """sum_k w_k d_k^2 over the last axis, written out (a 2- or 4-entry reduce is a slow
        kernel of its own on the CPU; the sum of products fuses)."""
        d = a - b
        periodic = {k: hi - lo for k, lo, hi in self.periodic}
        total = 0.0
        for k in range(d.shape[-1]):
            dk = d[..., k]
            if k in periodic:
                dk = jnp.mod(dk + periodic[k] / 2, periodic[k]) - periodic[k] / 2
            total = total + self.weights[k] * dk * dk
        return total

    def __call__(self, a, b):
        return jnp.sqrt(self.squared(a, b))


class _SimulatedStep(eqx.Module):
    """Kinodynamic extension: `num_controls` random inputs held for dt; the valid end state
    nearest the target."""

    system: System
    u_low: jax.Array
    u_high: jax.Array
    low: jax.Array
    high: jax.Array
    dt: jax.Array
    distance: _WeightedDistance
    num_controls: int = eqx.field(static=True)
    solver: object = eqx.field(static=True)
    is_valid: object = eqx.field(static=True)

    def __call__(self, nearest, target, key):
        us = jax.random.uniform(key, (self.num_controls, self.u_low.shape[0]), nearest.dtype, self.u_low, self.u_high)
        end = lambda u: self.distance.wrap(simulate(self.system, (0.0, self.dt), nearest, inputs=lambda t: u,
                                                    solver=self.solver, dt=self.dt, dense=False,
                                                    throw=False).final_state)
        ends = jax.vmap(end)(us)
        valid = jax.vmap(lambda x: jnp.all((x >= self.low) & (x <= self.high)) & jnp.all(jnp.isfinite(x))
                         & (True if self.is_valid is None else self.is_valid(x)))(ends)
        gaps = jnp.where(valid, jax.vmap(lambda x: self.distance(x, target))(ends), jnp.inf)
        best = jnp.argmin(gaps)
        return ends[best], valid[best], us[best]


@eqx.filter_jit
def _grow(start, goal, low, high, key, extend, distance, tolerance, goal_bias, max_nodes, max_iterations,
          num_inputs):
    d = start.shape[0]
    nodes = jnp.zeros((max_nodes, d), start.dtype).at[0].set(start)
    parents = jnp.full(max_nodes, -1, jnp.int32)
    controls = jnp.zeros((max_nodes, num_inputs), start.dtype)
    reached = distance(start, goal) <= tolerance

    def iterate(s):
        nodes, parents, controls, count, done, goal_node, k, key = s
        key, k_pick, k_point, k_extend = jax.random.split(key, 4)
        target = jnp.where(jax.random.uniform(k_pick) < goal_bias, goal,
                           jax.random.uniform(k_point, (d,), start.dtype, low, high))
        gaps = distance.squared(nodes, target)
        nearest = jnp.argmin(jnp.where(jnp.arange(max_nodes) < count, gaps, jnp.inf))
        new, free, u = extend(nodes[nearest], target, k_extend)
        add = free & (count < max_nodes)
        slot = jnp.minimum(count, max_nodes - 1)
        nodes = nodes.at[slot].set(jnp.where(add, new, nodes[slot]))  # in place: one row written
        parents = parents.at[slot].set(jnp.where(add, nearest.astype(jnp.int32), parents[slot]))
        controls = controls.at[slot].set(jnp.where(add, u, controls[slot]))
        arrived = add & (distance(new, goal) <= tolerance)
        goal_node = jnp.where(arrived, slot, goal_node)
        return nodes, parents, controls, count + add, done | arrived, goal_node, k + 1, key

    def going(s):
        return ~s[4] & (s[3] < max_nodes) & (s[6] < max_iterations)

    state = (nodes, parents, controls, jnp.asarray(1), reached, jnp.where(reached, 0, -1), jnp.asarray(0), key)
    nodes, parents, controls, count, done, goal_node, k, _ = jax.lax.while_loop(going, iterate, state)
    return RRTResult(nodes=nodes, parents=parents, controls=controls, num_nodes=count, success=done,
                     goal_node=goal_node, iterations=k)


def _points(start, goal, bounds):
    start = jnp.asarray(start, jnp.result_type(float))
    goal = jnp.asarray(goal, start.dtype)
    low, high = (jnp.broadcast_to(jnp.asarray(b, start.dtype), start.shape) for b in bounds)
    if start.ndim != 1 or goal.shape != start.shape:
        raise ValueError(f"start and goal must be vectors of one size, got shapes {start.shape} and {goal.shape}")
    if _concrete(low, high) and not np.all(np.asarray(low) < np.asarray(high)):
        raise ValueError(f"bounds must be (low, high) with low < high, got {np.asarray(low)}, {np.asarray(high)}")
    return start, goal, low, high


def _obstacles(obstacles, d, dtype):
    if obstacles is None:
        return jnp.zeros((0, d), dtype), jnp.zeros(0, dtype)
    centres, radii = obstacles
    centres, radii = jnp.asarray(centres, dtype).reshape(-1, d), jnp.asarray(radii, dtype).reshape(-1)
    if centres.shape[0] != radii.shape[0]:
        raise ValueError(f"obstacles: {centres.shape[0]} centres but {radii.shape[0]} radii")
    return centres, radii


def _segment_misses(a, b, centres, radii):
    """Whether the segment a-b keeps out of every ball: the closest point of the segment to
    each centre is farther than its radius."""
    ab = b - a
    s = jnp.clip(((centres - a) @ ab) / jnp.maximum(ab @ ab, 1e-300), 0.0, 1.0)
    closest = a + s[:, None] * ab
    return jnp.all(jnp.sum((centres - closest) ** 2, axis=1) > radii ** 2)


def _concrete(*arrays):
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)
