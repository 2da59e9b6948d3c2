r"""Dynamic programming on a mesh (Underactuated, ch. 9): fitted value iteration with
barycentric interpolation (Munos & Moore), with the semantics of Drake's
`FittedValueIteration`, and value iteration on a finite grid world.

For every mesh state $x_i$ and mesh input $u_j$ the transition $x_{ij}' = \phi_{dt}(x_i, u_j)$
(a simulation over dt with u held, or one update of a discrete system of period dt) and the
stage cost $dt\,\ell(x_i, u_j)$ are computed once; then, from $J = 0$,

$$J^{k+1}(x_i) = \min_j \Big[dt\,\ell(x_i, u_j) + \gamma \sum_v w_v(x'_{ij}) J^k(x_v)\Big]$$

until $\max_i |J^{k+1} - J^k| \le$ `tol`, the weights $w_v$ those of the simplex of the
mesh's Kuhn triangulation that holds $x'$ (n + 1 vertices; a state outside the mesh is
clamped onto it, periodic coordinates are wrapped first). Every sweep is one vectorised
gather over all (state, input) pairs, jitted, on any device.
"""

from __future__ import annotations

import functools
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from .._batch import batch_sharding
from .._progress import finish, progress_bar
from ..simulation import simulate
from ..simulation import leaves_to_arrays
from ..systems import Frame, System


class BarycentricMesh(eqx.Module):
    """A rectangular mesh (one increasing 1-D array of values per coordinate) with barycentric
    interpolation on the simplices of its Kuhn triangulation (Drake's `BarycentricMesh`).
    Mesh points are numbered in C order of the coordinates (`values.reshape(shape)` puts
    coordinate 0 on the first axis)."""

    grids: tuple

    def __init__(self, grids):
        checked = []
        for k, g in enumerate(grids):
            g = np.asarray(g, float).ravel()
            if g.size < 2 or not np.all(np.diff(g) > 0) or not np.all(np.isfinite(g)):
                raise ValueError(f"mesh coordinate {k}: needs at least 2 finite, strictly increasing "
                                 f"values, got {g}")
            checked.append(jnp.asarray(g))
        self.grids = tuple(checked)

    @property
    def shape(self) -> tuple:
        return tuple(g.shape[0] for g in self.grids)

    @property
    def num_points(self) -> int:
        return int(np.prod(self.shape))

    def points(self):
        """Every mesh point, (num_points, n), in C order."""
        xp = jnp if any(isinstance(g, jax.core.Tracer) for g in self.grids) else np   # on the host: no program
        return jnp.asarray(xp.stack([a.ravel() for a in xp.meshgrid(*self.grids, indexing="ij")], axis=1))

    def weights(self, x):
        r"""(indices, weights) of the n + 1 mesh points whose combination interpolates at x:
        with $f_k$ the fractional position of $x_k$ in its cell, sorted decreasingly, the
        vertices walk from the cell's lower corner one coordinate at a time, weights
        $1 - f_{(1)}, f_{(1)} - f_{(2)}, \dots, f_{(n)}$."""
        strides = np.cumprod((1,) + self.shape[::-1])[:-1][::-1]
        base, fractions = 0, []
        for g, stride, xk in zip(self.grids, strides, x):
            xk = jnp.clip(xk, g[0], g[-1])
            i = jnp.clip(jnp.searchsorted(g, xk, side="right") - 1, 0, g.shape[0] - 2)
            fractions.append((xk - g[i]) / (g[i + 1] - g[i]))
            base = base + i * stride
        fractions = jnp.stack(fractions)
        order = jnp.argsort(-fractions, stable=True)
        sorted_f = fractions[order]
        indices = base + jnp.concatenate([jnp.zeros(1, order.dtype), jnp.cumsum(jnp.asarray(strides)[order])])
        weights = jnp.concatenate([1 - sorted_f[:1], sorted_f[:-1] - sorted_f[1:], sorted_f[-1:]])
        return indices, weights

    def interpolate(self, values, x):
        """The barycentric interpolant of `values` (one per mesh point, any trailing shape) at x."""
        indices, weights = self.weights(x)
        flat = values.reshape((self.num_points,) + values.shape[len(self.shape):])
        return jnp.tensordot(weights, flat[indices], axes=1)


class MeshPolicy(System):
    """A static system u = pi(x): the barycentric interpolant of a policy's values on a mesh
    (Drake's `BarycentricMeshSystem`), for `feedback(plant, policy)`; periodic coordinates
    are wrapped as in the value iteration that made it."""

    mesh: BarycentricMesh
    table: jax.Array
    periodic: tuple = eqx.field(static=True)

    def __init__(self, mesh: BarycentricMesh, table, periodic=(), state_frame: Frame | None = None,
                 input_frame: Frame | None = None):
        self.mesh, self.table, self.periodic = mesh, jnp.asarray(table), tuple(periodic)
        super().__init__(num_inputs=len(mesh.grids), num_outputs=self.table.shape[-1],
                         direct_feedthrough=True, time_invariant=True,
                         input_frame=state_frame, output_frame=input_frame)

    def output(self, t, x, u):
        return self.mesh.interpolate(self.table, _wrap(u, self.periodic))


class ValueIterationResult(eqx.Module):
    """`J`: the cost-to-go on the mesh, axes in state order (`J[i_0, i_1, ...]`); `policy_table`:
    the minimizing input at each mesh point (`policy_table[i_0, ..., :]`); `policy`: a
    `MeshPolicy` system interpolating it; `mesh`; `iterations`; `max_change`, the last sweep's
    largest change of J."""

    J: jax.Array
    policy_table: jax.Array
    policy: MeshPolicy
    mesh: BarycentricMesh
    iterations: jax.Array
    max_change: jax.Array


def fitted_value_iteration(system: System, cost, state_grid, input_grid, dt, *, discount=1.0,
                           periodic=(), tol=1e-4, max_iterations: int = 100_000, solver="rk4",
                           progress: bool = True, devices=None) -> ValueIterationResult:
    r"""Fitted value iteration on a barycentric mesh (Drake's `FittedValueIteration`).

    - `system`: time-invariant, continuous (a transition is `simulate` over `dt` with u held,
      by `solver`: one RK4 step by default, or e.g. `"dopri5"`) or discrete with period `dt`
      (one update).
    - `cost(x, u)`: the running cost $\ell$; a stage costs `dt * cost(x, u)`.
    - `state_grid`, `input_grid`: one increasing 1-D array per state / input coordinate.
    - `discount` in (0, 1]; `periodic`: `(index, low, high)` triples, the coordinates wrapped
      into [low, high) before interpolation (a pendulum's angle: `(0, 0, 2 pi)`).
    - `tol`: stop when no value changes by more than this in a sweep; `progress`: a progress
      bar (tqdm) with the largest change, drawn once the sweeps have run 2 s; it ends full at
      the sweep that converged.
    - `devices`: the mesh points are split across these (default: every local device): each
      computes its points' transitions and their updates; J is gathered every sweep.
      The result is bit-identical to one device's.
    """
    if not isinstance(system, System):
        raise TypeError(f"fitted_value_iteration needs a jaxdrake.System, got {type(system).__name__}")
    if not system.time_invariant:
        raise ValueError(f"{system.name} is time-varying; value iteration needs a time-invariant system")
    state_mesh, input_mesh = BarycentricMesh(state_grid), BarycentricMesh(input_grid)
    n, m = len(state_mesh.grids), len(input_mesh.grids)
    if n != system.num_states or m != system.num_inputs:
        raise ValueError(f"{system.name} has {system.num_states} states and {system.num_inputs} inputs; "
                         f"the grids have {n} and {m} coordinates")
    if not 0 < discount <= 1:
        raise ValueError(f"discount must be in (0, 1], got {discount}")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    periodic = tuple((int(k), float(low), float(high)) for k, low, high in periodic)
    for k, low, high in periodic:
        grid = np.asarray(state_mesh.grids[k]) if 0 <= k < n else None
        if grid is None or not (grid[0] <= low < high <= grid[-1]):
            raise ValueError(f"periodic coordinate {(k, low, high)}: the index must be a state and "
                             "[low, high] within that coordinate's grid")
    discrete = system.num_discrete_states > 0
    if discrete and (system.num_continuous_states or not np.isclose(system.sample_times[0], dt)):
        raise ValueError(f"{system.name}: a discrete system needs dt equal to its period "
                         f"{system.sample_times}, and no continuous state")

    system = leaves_to_arrays(system, jnp.result_type(float))  # new parameter values: no new compilation
    devices = tuple(jax.local_devices() if devices is None else devices)
    points = _points_on(devices, state_mesh)
    sweeps_on = _sweep_program(devices)
    indices, weights, stage = _transitions(system, cost, points, state_mesh, input_mesh, dt, periodic, solver,
                                           discrete)
    J = jnp.zeros(len(points), weights.dtype)  # the padding's values are never read (no index points there)
    change, done = jnp.inf, 0
    bar = progress_bar(progress, max_iterations, "value iteration", "sweep")
    chunk = max_iterations if bar is None else 50
    while done < max_iterations and not float(change) <= tol:
        start = time.perf_counter()
        J, change, sweeps = sweeps_on(J, indices, weights, stage, discount, tol,
                                      jnp.asarray(min(chunk, max_iterations - done)))
        done += int(sweeps)
        if bar is not None:
            bar.update(int(sweeps))
            bar.set_postfix(max_change=f"{float(change):.3g}")
            chunk = _next_chunk(chunk, time.perf_counter() - start)
    finish(bar, done)
    J, table = _values_and_policy(J, indices, weights, stage, discount, input_mesh.points(), state_mesh.shape)
    policy = MeshPolicy(state_mesh, table, periodic, system.state_frame, system.input_frame)
    return ValueIterationResult(J=J, policy_table=table, policy=policy, mesh=state_mesh,
                                iterations=jnp.asarray(done), max_change=change)


PROGRESS_INTERVAL = 0.25  # s: with a progress bar, sweeps run in chunks of about this long


def _next_chunk(chunk: int, seconds: float) -> int:
    """Sweeps in the next chunk: about `PROGRESS_INTERVAL` s of them, at most 16 times the last
    chunk (fast sweeps are not cut into host round trips: 10^6 points sweep in ~0.2 ms on a GPU)."""
    return int(np.clip(chunk * PROGRESS_INTERVAL / max(seconds, 1e-9), 1, 16 * chunk))


def _wrap(x, periodic):
    for k, low, high in periodic:
        x = x.at[k].set(low + jnp.mod(x[k] - low, high - low))
    return x


def _points_on(devices, mesh: BarycentricMesh):
    """The mesh points made where they are used: on one device, or padded (copies of the last)
    to a multiple of the device count and sharded along their first axis, each device making
    its own slice (nothing is built on the host and copied: 11 ms for 10^6 points on two H200s),
    so that what is computed from them is split too."""
    return _points_program(devices, mesh.shape)(mesh.grids)


@functools.cache
def _points_program(devices: tuple, shape: tuple):
    count = int(np.prod(shape))
    length = -(-count // len(devices)) * len(devices)
    sharding = jax.sharding.SingleDeviceSharding(devices[0]) if len(devices) == 1 else batch_sharding(devices)

    def points(grids):
        coordinates = jnp.unravel_index(jnp.minimum(jnp.arange(length), count - 1), shape)
        return jnp.stack([g[c] for g, c in zip(grids, coordinates)], axis=1)

    return jax.jit(points, out_shardings=sharding)


@eqx.filter_jit
def _transitions(system, cost, xs, state_mesh, input_mesh, dt, periodic, solver, discrete):
    """Barycentric (indices, weights) of the next state from each of the points xs (S, n) under
    every mesh input, and the stage costs: (S, M, n + 1) and (S, M)."""
    us = input_mesh.points()

    def next_state(x, u):
        if discrete:
            return system.update(0.0, x, u)
        traj = simulate(system, (0.0, dt), x, inputs=lambda t: u, solver=solver, dt=dt, dense=False,
                        throw=False)
        return traj.final_state

    def one(x, u):
        indices, weights = state_mesh.weights(_wrap(next_state(x, u), periodic))
        return indices, weights, dt * cost(x, u)

    return jax.vmap(lambda x: jax.vmap(lambda u: one(x, u))(us))(xs)


def _costs_to_go(J, indices, weights, stage, discount):
    """The cost of each (state, input) pair: its stage cost plus the discounted interpolant of J
    at its next state, (S, M); a sweep takes the least over the inputs, the policy its input."""
    return stage + discount * jnp.einsum("smv,smv->sm", weights, J[indices])


@functools.partial(jax.jit, static_argnums=6)
def _values_and_policy(J, indices, weights, stage, discount, input_points, shape):
    """J on the mesh (its axes in state order) and the minimizing input at each mesh point,
    the padding of a split mesh dropped: one program (on one device, as the results are)."""
    best = jnp.argmin(_costs_to_go(J, indices, weights, stage, discount), axis=1)
    S = int(np.prod(shape))
    return J[:S].reshape(shape), input_points[best[:S]].reshape(shape + (input_points.shape[1],))


_SWEEPS_PER_EXCHANGE = 25  # on several devices: sweeps per trip of the loop (see _sweep_program)


@functools.cache
def _sweep_program(devices: tuple):
    """`sweeps(J, indices, weights, stage, discount, tol, count)`: up to `count` Jacobi sweeps,
    stopping once the largest change is <= tol, compiled for `devices`.

    On several devices each runs the loop on its own slice of the mesh points (`shard_map`):
    per sweep it gathers J from all (one all-gather) and agrees on the largest change (one
    all-reduce). Each trip of the loop runs `_SWEEPS_PER_EXCHANGE` sweeps, a sweep after the
    stopping one leaving J, the change and the count as they are, so the result is the one
    device's, bit for bit: the trip's end, where every device reads the loop's condition back
    and waits for the others, cost more than the sweep itself (two H100s, 10^6 points: 73 ms
    for 200 sweeps at one sweep per trip, 32 ms at 25; one device 36 ms, where several sweeps
    per trip gain nothing and at 4 * 10^6 points lose a third)."""
    several = len(devices) > 1

    def sweep(J, indices, weights, stage, discount):
        J_all = jax.lax.all_gather(J, "batch", tiled=True) if several else J
        J_next = jnp.min(_costs_to_go(J_all, indices, weights, stage, discount), axis=1)
        change = jnp.max(jnp.abs(J_next - J))
        return J_next, jax.lax.pmax(change, "batch") if several else change

    def sweeps(J, indices, weights, stage, discount, tol, count):
        def running(carry):
            _, change, k = carry
            return (change > tol) & (k < count)

        def trip(carry):
            if not several:
                return *sweep(carry[0], indices, weights, stage, discount), carry[2] + 1

            def sweep_unless_stopped(_, carry):
                J_next, change, k = *sweep(carry[0], indices, weights, stage, discount), carry[2] + 1
                return jax.tree.map(functools.partial(jnp.where, running(carry)), (J_next, change, k), carry)

            return jax.lax.fori_loop(0, _SWEEPS_PER_EXCHANGE, sweep_unless_stopped, carry, unroll=True)

        return jax.lax.while_loop(running, trip, (J, jnp.asarray(jnp.inf, J.dtype), jnp.asarray(0, count.dtype)))

    if not several:
        return jax.jit(sweeps)
    sharding = batch_sharding(devices)
    split, whole = sharding.spec, PartitionSpec()
    return jax.jit(jax.shard_map(sweeps, mesh=sharding.mesh, in_specs=(split,) * 4 + (whole,) * 3,
                                 out_specs=(split, whole, whole), check_vma=False))


# ----- the grid world of chapter 9 -------------------------------------------------------------

GRID_ACTIONS = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))  # stay, up, down, left, right (row, col)


class GridWorldResult(eqx.Module):
    """`J[row, col]`: the optimal cost-to-go; `policy[row, col]`: the index of the best action in
    `GRID_ACTIONS` (stay, up, down, left, right); `iterations`."""

    J: jax.Array
    policy: jax.Array
    iterations: jax.Array

    def path(self, start, max_length: int = 10_000) -> np.ndarray:
        """The cells visited from `start` (row, col) following the policy to the goal, on the host."""
        cell, cells = tuple(int(c) for c in start), [tuple(int(c) for c in start)]
        policy = np.asarray(self.policy)
        for _ in range(max_length):
            move = GRID_ACTIONS[policy[cell]]
            if move == (0, 0):
                break
            cell = (cell[0] + move[0], cell[1] + move[1])
            cells.append(cell)
        return np.asarray(cells)


def grid_world(obstacles, goal, *, obstacle_cost: float = 10.0, tol: float = 1e-9,
               max_iterations: int = 100_000) -> GridWorldResult:
    r"""Value iteration on the notes' grid world (ch. 9): a robot on a grid of cells moves one
    cell up, down, left or right, or stays (a move off the grid stays); each step costs 1, 0
    at the `goal` (row, col), `obstacle_cost` in an obstacle cell (`obstacles`: a boolean
    array, True where blocked). $J(s) = \min_a [\ell(s) + J(s'(s, a))]$ from J = 0 until no
    value changes by more than `tol`: on a free grid J is the Manhattan distance to the goal."""
    blocked = np.asarray(obstacles, bool)
    if blocked.ndim != 2:
        raise ValueError(f"obstacles must be a 2-D boolean array (rows, columns), got shape {blocked.shape}")
    rows, cols = blocked.shape
    goal = tuple(int(g) for g in goal)
    if not (0 <= goal[0] < rows and 0 <= goal[1] < cols):
        raise ValueError(f"goal {goal} is outside the {rows} x {cols} grid")
    cost = np.where(blocked, obstacle_cost, 1.0)
    cost[goal] = 0.0
    r, c = np.indices(blocked.shape)
    successors = np.stack([np.clip(r + dr, 0, rows - 1) * cols + np.clip(c + dc, 0, cols - 1)
                           for dr, dc in GRID_ACTIONS], -1).reshape(-1, len(GRID_ACTIONS))
    J, policy, iterations = _grid_value_iteration(jnp.asarray(cost.ravel()), jnp.asarray(successors), tol,
                                                  max_iterations)
    if goal is not None:
        policy = policy.at[goal[0] * cols + goal[1]].set(0)  # at the goal: stay
    return GridWorldResult(J=J.reshape(rows, cols), policy=policy.reshape(rows, cols), iterations=iterations)


@eqx.filter_jit
def _grid_value_iteration(cost, successors, tol, max_iterations):
    def sweep(carry):
        J, _, k = carry
        J_next = jnp.min(cost[:, None] + J[successors], axis=1)
        return J_next, jnp.max(jnp.abs(J_next - J)), k + 1

    J, _, k = jax.lax.while_loop(lambda c: (c[1] > tol) & (c[2] < max_iterations), sweep,
                                 (jnp.zeros_like(cost), jnp.asarray(jnp.inf, cost.dtype), 0))
    return J, jnp.argmin(cost[:, None] + J[successors], axis=1), k
