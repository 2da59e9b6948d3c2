"""Dynamic programming (ch. 9): fitted value iteration against Drake's FittedValueIteration
and the exact minimum time of the double integrator, the pendulum swung up by its DP policy,
the grid world against breadth-first search, barycentric interpolation's invariants."""

import collections

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.planning import BarycentricMesh, fitted_value_iteration, grid_world

Q_GRID, QDOT_GRID, U_GRID = np.linspace(-3, 3, 31), np.linspace(-3, 3, 51), np.linspace(-1, 1, 9)


def min_time_cost(x, u):
    """The notes' minimum-time cost: 1 per second outside a small ball around the origin."""
    return jnp.where(x @ x < 0.05, 0.0, 1.0)


def exact_minimum_time(q, qdot):
    """Bang-bang time to the origin with |u| <= 1: switching curve q = -qdot |qdot| / 2."""
    right = q + qdot * np.abs(qdot) / 2 > 0
    return np.where(right, qdot + 2 * np.sqrt(np.maximum(q + qdot ** 2 / 2, 0)),
                    -qdot + 2 * np.sqrt(np.maximum(-q + qdot ** 2 / 2, 0)))


def test_double_integrator_min_time_agrees_with_drake_and_the_exact_minimum_time():
    result = fitted_value_iteration(jd.models.DoubleIntegrator(), min_time_cost, [Q_GRID, QDOT_GRID], [U_GRID], 0.01,
                                    progress=True)
    J = np.asarray(result.J)
    assert J.shape == (31, 51) and float(result.max_change) <= 1e-4
    Q, QD = np.meshgrid(Q_GRID, QDOT_GRID, indexing="ij")
    inner = (np.abs(Q) <= 2) & (np.abs(QD) <= 2)  # away from the clamped mesh boundary
    error = (J - exact_minimum_time(Q, QD))[inner]
    # a coarse mesh and dt = 0.01 diffuse the value (the notes' figure shows it): bounded, unbiased shape
    assert np.median(np.abs(error)) < 0.5 and np.max(np.abs(error)) < 1.1
    assert np.corrcoef(J[inner], exact_minimum_time(Q, QD)[inner])[0, 1] > 0.97
    pytest.importorskip("pydrake")
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.controllers import DynamicProgrammingOptions, FittedValueIteration
    from pydrake.systems.primitives import LinearSystem

    plant = LinearSystem(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.zeros((2, 1)))

    def cost(context):
        x = context.get_continuous_state_vector().CopyToVector()
        return 0.0 if x.dot(x) < 0.05 else 1.0

    options = DynamicProgrammingOptions()
    options.convergence_tol = 1e-4
    _, J_drake = FittedValueIteration(Simulator(plant), cost, [set(Q_GRID), set(QDOT_GRID)], [set(U_GRID)], 0.01, options)
    # Drake numbers mesh points with the first coordinate fastest
    np.testing.assert_allclose(J, np.asarray(J_drake).reshape(31, 51, order="F"), rtol=0, atol=1e-9)


def test_the_pendulum_swings_up_under_its_value_iteration_policy():
    """Torque limited to 3 N m < m g l = 4.9 N m (it must pump); the mesh policy closed around
    the plant with `feedback` brings it from hanging to upright and holds it there."""
    plant = jd.models.Pendulum(input_limits=(-3.0, 3.0))
    result = fitted_value_iteration(
        plant, lambda x, u: 2 * (x[0] - np.pi) ** 2 + x[1] ** 2 + u[0] ** 2,
        [np.linspace(0, 2 * np.pi, 51), np.linspace(-10, 10, 51)], [np.linspace(-3, 3, 9)], 0.01,
        periodic=[(0, 0.0, 2 * np.pi)])
    traj = jd.simulate(jd.feedback(plant, result.policy), (0.0, 10.0), jnp.array([0.1, 0.0]))
    theta, thetadot = np.asarray(traj.state(jnp.linspace(8.0, 10.0, 21))).T
    assert np.max(np.abs(np.mod(theta, 2 * np.pi) - np.pi)) < 0.05 and np.max(np.abs(thetadot)) < 0.05


def bfs_distance(blocked, goal):
    rows, cols = blocked.shape
    dist = np.full(blocked.shape, np.inf)
    dist[goal] = 0
    queue = collections.deque([goal])
    while queue:
        r, c = queue.popleft()
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (r + dr, c + dc)
            if 0 <= n[0] < rows and 0 <= n[1] < cols and not blocked[n] and dist[n] == np.inf:
                dist[n] = dist[r, c] + 1
                queue.append(n)
    return dist


def test_grid_world_is_the_shortest_path_around_obstacles():
    free = grid_world(np.zeros((10, 12), bool), (2, 3))
    rows, cols = np.indices((10, 12))
    np.testing.assert_array_equal(np.asarray(free.J), np.abs(rows - 2) + np.abs(cols - 3))
    blocked = np.zeros((10, 12), bool)
    blocked[1:9, 6] = True   # a wall with gaps at both ends
    blocked[4, 2:6] = True
    result = grid_world(blocked, (2, 9), obstacle_cost=1000.0)
    reachable = ~blocked
    np.testing.assert_array_equal(np.asarray(result.J)[reachable], bfs_distance(blocked, (2, 9))[reachable])
    path = result.path((8, 1))
    assert tuple(path[-1]) == (2, 9) and len(path) - 1 == bfs_distance(blocked, (2, 9))[8, 1]
    assert not blocked[tuple(path.T)].any()


def test_barycentric_interpolation_is_exact_for_affine_functions():
    mesh = BarycentricMesh([np.linspace(-1, 2, 7), np.array([0.0, 0.5, 3.0]), np.linspace(0, 1, 4)])
    points = mesh.points()
    values = points @ jnp.array([1.5, -2.0, 0.25]) + 0.7
    rng = np.random.default_rng(0)
    for x in rng.uniform([-1, 0, 0], [2, 3, 1], (20, 3)):
        indices, weights = mesh.weights(jnp.asarray(x))
        assert np.all(np.asarray(weights) >= -1e-15) and abs(float(jnp.sum(weights)) - 1) < 1e-14
        np.testing.assert_allclose(mesh.interpolate(values, jnp.asarray(x)), x @ np.array([1.5, -2.0, 0.25]) + 0.7,
                                   atol=1e-12)
    with pytest.raises(ValueError, match="strictly increasing"):
        BarycentricMesh([np.array([0.0, 0.0, 1.0])])


def test_value_iteration_errors_name_the_problem():
    plant = jd.models.DoubleIntegrator()
    with pytest.raises(ValueError, match="2 states and 1 inputs; the grids have 1 and 1"):
        fitted_value_iteration(plant, min_time_cost, [Q_GRID], [U_GRID], 0.01)
    with pytest.raises(ValueError, match="periodic coordinate"):
        fitted_value_iteration(plant, min_time_cost, [Q_GRID, QDOT_GRID], [U_GRID], 0.01, periodic=[(0, 0.0, 7.0)])


SCENE = dict(obstacles=(np.array([[0.5, 0.5], [0.25, 0.75], [0.75, 0.25]]), np.array([0.2, 0.1, 0.1])),
             step_size=0.05, max_nodes=1000)


def segment_is_free(a, b, centres, radii, samples=200):
    points = a + np.linspace(0, 1, samples)[:, None] * (b - a)
    return np.all(np.linalg.norm(points[:, None] - centres[None], axis=2) > radii)


def test_rrt_paths_are_collision_free_and_a_batch_equals_single_trees():
    from jaxdrake.planning import rrt

    start, goal, bounds = np.array([0.1, 0.1]), np.array([0.9, 0.9]), ([0.0, 0.0], [1.0, 1.0])
    keys = jax.random.split(jax.random.key(0), 64)
    batch = jax.jit(jax.vmap(lambda k: rrt(start, goal, bounds, k, **SCENE)))(keys)
    assert bool(jnp.all(batch.success))
    centres, radii = SCENE["obstacles"]
    for i in (0, 17, 63):
        single = rrt(start, goal, bounds, keys[i], **SCENE)
        member = jax.tree.map(lambda a: a[i], batch)
        np.testing.assert_array_equal(np.asarray(single.nodes), np.asarray(member.nodes))
        path = single.path()
        np.testing.assert_array_equal(path[0], start)
        assert np.linalg.norm(path[-1] - goal) <= SCENE["step_size"]
        steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
        assert np.all(steps <= SCENE["step_size"] + 1e-12)
        assert all(segment_is_free(a, b, centres, radii) for a, b in zip(path[:-1], path[1:]))
    # every edge of every tree, not only the paths, is free and in the box
    nodes, parents, count = np.asarray(batch.nodes[5]), np.asarray(batch.parents[5]), int(batch.num_nodes[5])
    assert all(segment_is_free(nodes[parents[k]], nodes[k], centres, radii) for k in range(1, count))
    with pytest.raises(ValueError, match="the goal .* is inside an obstacle"):
        rrt(start, [0.5, 0.5], bounds, keys[0], **SCENE)


def test_kinodynamic_rrt_swings_the_pendulum_up_along_simulated_edges():
    """Each edge is a simulation of the plant for dt under the recorded input (checked by
    re-simulating it); the tree reaches the upright state with the torque limited to 2 N m."""
    from jaxdrake.planning import kinodynamic_rrt

    plant = jd.models.Pendulum()
    result = kinodynamic_rrt(plant, [0.0, 0.0], [np.pi, 0.0], ([-np.pi, -8.0], [np.pi, 8.0]), (-2.0, 2.0), 0.1,
                             jax.random.key(0), periodic=[(0, -np.pi, np.pi)], weights=[1.0, 0.1],
                             goal_tolerance=0.3, max_nodes=5000)
    assert bool(result.success)
    path = result.path()
    gap = np.mod(path[-1][0] - np.pi + np.pi, 2 * np.pi) - np.pi
    assert np.sqrt(gap ** 2 + 0.1 * path[-1][1] ** 2) <= 0.3
    parents, controls = np.asarray(result.parents), np.asarray(result.controls)
    assert np.all(np.abs(controls[1:int(result.num_nodes)]) <= 2.0)
    for k in (1, int(result.num_nodes) // 2, int(result.goal_node)):
        x_parent = jnp.asarray(result.nodes[parents[k]])
        wrap = lambda x: np.array([np.mod(x[0] + np.pi, 2 * np.pi) - np.pi, x[1]])
        u = lambda t: jnp.asarray(controls[k])
        rk4 = jd.simulate(plant, (0.0, 0.1), x_parent, inputs=u, solver="rk4", dt=0.1).final_state
        np.testing.assert_allclose(np.asarray(result.nodes[k]), wrap(rk4), atol=1e-12)  # the edge: one RK4 step
        exact = jd.simulate(plant, (0.0, 0.1), x_parent, inputs=u, rtol=1e-12, atol=1e-12).final_state
        np.testing.assert_allclose(np.asarray(result.nodes[k]), wrap(exact), atol=1e-3)
