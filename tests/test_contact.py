"""Contact in the rigid-body plant: against pydrake's continuous MultibodyPlant (point contact),
closed forms, finite differences, and named errors for bad robot files."""

import functools
import os
import pathlib
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.geometry import Box, Convex, GeometryError, HalfSpace, Sphere, penetration
from jaxdrake.multibody import ContactMaterial, URDFError

DATA = pathlib.Path(__file__).parent / "data"


def _rotation_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _material(k, d, mu_s, mu_d):
    return ContactMaterial(point_contact_stiffness=k, hunt_crossley_dissipation=d, mu_static=mu_s, mu_dynamic=mu_d)


# scenes of our own: (URDF, floating base, shapes on the world (name, shape, R, p, material), stiction tolerance)
SCENES = {
    "ball_between_walls": ("contact_ball.urdf", True, [
        ("floor", Box(3.0, 3.0, 0.2), np.eye(3), (0.0, 0.0, -0.1), _material(1e5, 5.0, 0.6, 0.6)),
        ("left_wall", Box(0.2, 3.0, 2.0), np.eye(3), (-0.6, 0.0, 0.9), _material(2e4, 2.0, 0.3, 0.3)),
        ("right_wall", Box(0.2, 3.0, 2.0), np.eye(3), (0.6, 0.0, 0.9), _material(4e4, 1.0, 0.5, 0.4))], 1e-2),
    "dumbbell_on_a_slope": ("contact_dumbbell.urdf", True, [
        ("slope", Box(4.0, 2.0, 0.4), _rotation_y(0.3), (0.0, 0.0, -0.2), _material(8e4, 4.0, 0.7, 0.5)),
        ("floor", HalfSpace(), np.eye(3), (0.0, 0.0, -0.6), _material(1e5, 1.0, 0.9, 0.9))], 1e-2),
    "hopper_landing": ("contact_hopper.urdf", True, [
        ("floor", Box(4.0, 4.0, 0.5), np.eye(3), (0.0, 0.0, -0.25), _material(1e5, 10.0, 1.0, 0.8))], 1e-2),
    # three free bodies' worth of coordinates: an arm on the world, a ball freed by a floating
    # joint, a puck no joint holds
    "arm_pushing_free_bodies": ("contact_pusher.urdf", False, [
        ("floor", HalfSpace(), np.eye(3), (0.0, 0.0, 0.0), _material(2e4, 3.0, 0.5, 0.4))], 1e-2),
}


def _ours(scene):
    urdf, floating, world, stiction = SCENES[scene]
    plant = jd.RigidBodySystem.from_urdf(DATA / urdf, floating_base=floating, contact=True, stiction_tolerance=stiction)
    for name, shape, R, p, material in world:
        plant = plant.with_collision_geometry("world", shape, rotation=R, translation=p, name=name, material=material)
    return plant


def _drake(scene, plant):
    from _drake_contact import StateMap, drake_scene
    urdf, _, world, stiction = SCENES[scene]
    drake_plant, diagram = drake_scene(DATA / urdf, world, stiction)
    return drake_plant, diagram, StateMap(drake_plant, plant)


def _random_state(scene, plant, rng):
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    if scene == "ball_between_walls":  # near the floor and the right wall, at times inside it
        q = np.concatenate([[0.38 + 0.06 * rng.random(), 0.2, 0.085 + 0.03 * rng.random()], quat])
    elif scene == "dumbbell_on_a_slope":
        q = np.concatenate([[0.1 * rng.normal(), 0.0, 0.02 + 0.04 * rng.random()], quat])
    elif scene == "arm_pushing_free_bodies":   # tip near the ball, ball and puck on the floor
        ball = np.concatenate([[0.12 + 0.03 * rng.normal(), 0.0, 0.075 + 0.01 * rng.random()], quat])
        quat = rng.normal(size=4)
        puck = np.concatenate([[0.25 + 0.02 * rng.normal(), 0.01, 0.055 + 0.01 * rng.random()], quat / np.linalg.norm(quat)])
        q = np.concatenate([[0.2 + 0.05 * rng.normal(), 0.05 * rng.normal()], ball, puck])
    else:  # hopper: torso upright-ish, feet into the floor
        tilt = np.array([0.1 * rng.normal(), 0.1 * rng.normal(), 0.0])
        quat = np.concatenate([np.sin(np.linalg.norm(tilt) / 2) * tilt / max(np.linalg.norm(tilt), 1e-12),
                               [np.cos(np.linalg.norm(tilt) / 2)]])
        q = np.concatenate([[0.0, 0.0, 0.43 + 0.04 * rng.random()], quat, 0.2 * rng.normal(size=4)])
    return np.concatenate([q, rng.normal(size=plant.tree.nv)])


@pytest.mark.parametrize("scene", [pytest.param("ball_between_walls"),
                                   pytest.param("dumbbell_on_a_slope", marks=pytest.mark.slow),
                                   pytest.param("hopper_landing"), pytest.param("arm_pushing_free_bodies")])
def test_time_derivatives_equal_drakes_continuous_plant(scene):
    pytest.importorskip("pydrake")
    from _drake_contact import drake_velocity_derivative
    plant = _ours(scene)
    drake_plant, diagram, state_map = _drake(scene, plant)
    dynamics = jax.jit(plant.dynamics)
    rng = np.random.default_rng(7)
    touching = 0
    for _ in range(12):
        x = _random_state(scene, plant, rng)
        ours = np.asarray(dynamics(0.0, jnp.asarray(x), jnp.zeros(plant.num_inputs)))[plant.tree.nq:]
        theirs = drake_velocity_derivative(drake_plant, diagram, state_map, x)
        np.testing.assert_allclose(ours, theirs, rtol=1e-10, atol=1e-9 * np.max(np.abs(theirs)))
        touching += int(np.sum(np.asarray(plant.contact_results(jnp.asarray(x)).active)))
    assert touching >= 6  # the states probe contact, not free flight


@pytest.mark.parametrize("scene", [pytest.param("ball_between_walls"),
                                   pytest.param("dumbbell_on_a_slope", marks=pytest.mark.slow),
                                   pytest.param("hopper_landing", marks=pytest.mark.slow),
                                   pytest.param("arm_pushing_free_bodies", marks=pytest.mark.slow)])
def test_simulations_equal_drakes_continuous_plant(scene):
    pytest.importorskip("pydrake")
    from _drake_contact import drake_simulate
    plant = _ours(scene)
    drake_plant, diagram, state_map = _drake(scene, plant)
    x0 = {"ball_between_walls": [0.0, 0.0, 0.4, 0, 0, 0, 1, 3.0, 0.5, 0.0, 0.0, 0.0, 8.0],
          "dumbbell_on_a_slope": [0.0, 0.0, 0.3, 0.1, 0.2, 0.0, 0.97467943, 0.5, 0.0, 0.0, 1.0, -2.0, 0.5],
          "hopper_landing": [0.05, 0.0, 0.6, 0.05, 0.0, 0.0, 0.99875, 0.3, -0.6, -0.2, 0.5,
                             0.3, 0.0, -1.0, 0.2, 0.0, 0.5, 0.0, 1.0, 0.0, -1.0],
          # the arm swings into the ball, which the puck, sliding and spinning, meets
          "arm_pushing_free_bodies": [-0.6, 0.1, 0.12, 0.0, 0.1, 0, 0, 0, 1, 0.5, 0.02, 0.07, 0, 0, 0.3, 0.95,
                                      3.0, 0.5, 0, 0, -0.5, 0, 0, 0, -1.64, 1.15, 0, 0, 0, 6.0]}[scene]
    x0 = np.asarray(x0, float)
    for start, kind in zip(plant.tree.q_starts, plant.tree.joint_types):
        if kind == "floating":
            x0[start + 3: start + 7] /= np.linalg.norm(x0[start + 3: start + 7])
    times = np.linspace(0.1, 0.6, 6)
    # the hopper's landing amplifies errors ~5e4-fold by t = 0.6 s (x0 moved by 1e-12: 5e-8 there):
    # Drake's RK5 at accuracy 1e-11 is itself 8.5e-7 off its own 1e-13 solution at 0.6 s, where
    # ours at rtol 1e-11 is 9e-8 off it; so the reference is Drake at 1e-13 there (9 s)
    accuracy = 1e-13 if scene == "hopper_landing" else 1e-11
    expected = drake_simulate(drake_plant, diagram, state_map, x0, times, accuracy=accuracy)
    traj = jd.simulate(plant, (0.0, 0.6), jnp.asarray(x0), rtol=1e-11, atol=1e-12, max_steps=40000)
    states = np.asarray(traj.state(jnp.asarray(times)))
    assert int(np.sum(np.asarray(jax.vmap(plant.contact_results)(jnp.asarray(states)).active))) > 0
    scale = np.maximum(np.abs(expected), 1.0)
    np.testing.assert_array_less(np.abs(states - expected) / scale, 1e-6)


def test_a_sliding_box_stops_after_v0_squared_over_2_mu_g():
    mu, v0, g = 0.4, 2.0, 9.81
    box = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True)  # the ball's link ...
    box = box.with_collision_geometry("ball", Box(0.2, 0.2, 0.2), material=_material(1e6, 50.0, mu, mu))  # ... as a box
    box = box.with_ground(material=_material(1e6, 50.0, mu, mu))
    # a stiction tolerance of 1 cm/s: the law's slope at rest is then mild enough for explicit steps
    # (the slide lengthens by ~v_s^2 / (mu g), 2.5e-5 m)
    import equinox as eqx
    box = eqx.tree_at(lambda p: p.contact.stiction_tolerance, box, jnp.asarray(1e-2))
    x0 = jnp.array([0.0, 0.0, 0.1 - 2 * 9.81 / 4e6, 0, 0, 0, 1, v0, 0, 0, 0, 0, 0])  # resting on its 4 corners
    t_stop = v0 / (mu * g)
    traj = jd.simulate(box, (0.0, t_stop + 0.3), x0, rtol=1e-8, atol=1e-10, max_steps=20000)
    x = np.asarray(traj.final_state)
    np.testing.assert_allclose(x[0], v0 ** 2 / (2 * mu * g), rtol=2e-3)
    assert abs(x[7]) < 1e-3 and abs(x[2] - 0.1) < 1e-4   # stopped, upright on the floor


def test_a_float32_ball_thrown_onto_the_floor_lands_and_rolls_as_float64_does():
    """Thrown sideways at 1 m/s with Drake's default contact properties: the touchdown needs
    steps of ~3 units of float32's spacing of t there; the old floor of 16 units (MATLAB's)
    stopped it with STEP_SIZE_TOO_SMALL. At the default tolerances it ends within float32's
    tolerances of float64's run at rtol 1e-9."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    x0 = np.array([0, 0, 0.3, 0, 0, 0, 1, 1.0, 0, 0, 0, 0, 0])
    single = jd.simulate(ball, (0.0, 1.0), jnp.asarray(x0, jnp.float32), dense=False).final_state
    double = jd.simulate(ball, (0.0, 1.0), jnp.asarray(x0), rtol=1e-9, atol=1e-10, dense=False, max_steps=20000).final_state
    assert single.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(single, float), np.asarray(double), atol=2e-3)


def test_float32_cubes_landing_while_they_slide_or_tumble_come_to_rest(tmp_path):
    """A 1-kg cube dropped flat while it slides, or tilted onto a corner: its corners go from
    sliding to sticking under kilonewtons, where float64 takes steps of ~2e-9 s, below
    float32's spacing of t there (1.5e-8 to 3e-8 s). Each stopped with STEP_SIZE_TOO_SMALL
    (19 of 36 such drops did); float32 now carries time as a pair, and each comes to rest on
    a face, sunk m g / (4 k) (k: the geometries' 1e6 N/m in series)."""
    (tmp_path / "cube.urdf").write_text("""<robot name="cube"><link name="cube">
      <inertial><mass value="1.0"/><inertia ixx="0.001667" iyy="0.001667" izz="0.001667" ixy="0" ixz="0" iyz="0"/></inertial>
      <collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link></robot>""")
    cube = jd.RigidBodySystem.from_urdf(tmp_path / "cube.urdf", floating_base=True, contact=True).with_ground()
    starts = []
    for z, vx, tilt in ((0.3, 0.3, 0.0), (0.5, 0.3, 0.7), (1.0, 1.0, 0.3), (1.0, 0.0, 0.7)):
        c, s = np.cos(tilt / 2), np.sin(tilt / 2)
        starts.append([0, 0, z, c, 0.6 * s, 0.8 * s, 0, vx, 0, 0, 0, 0, 0])
    traj = jax.vmap(lambda x0: jd.simulate(cube, (0.0, 1.5), x0, max_steps=20000, throw=False, dense=False))(
        jnp.asarray(starts, jnp.float32))
    assert traj.final_state.dtype == jnp.float32
    np.testing.assert_array_equal(traj.status, jd.SimulationStatus.SUCCESS)
    np.testing.assert_allclose(traj.final_state[:, 2], 0.05 - 9.81 / (4 * 5e5), atol=2e-6)
    np.testing.assert_allclose(traj.final_state[:, 7:], 0.0, atol=1e-3)


def test_a_float32_box_slides_its_closed_form_distance_at_the_default_tolerances():
    """float32 with float64's atol 1e-9 (below float32's rounding near 1) ran out of steps
    within 0.06 s; float32's default atol is 1e-5, and an explicit 1e-9 is told why it failed.
    Drake's stiction tolerance 1e-4 m/s (the stiff solver's case)."""
    mu, v0, g = 0.3, 1.5, 9.81
    box = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True)
    box = box.with_collision_geometry("ball", Box(0.3, 0.2, 0.2), material=_material(1e6, 50.0, mu, mu))
    box = box.with_ground(material=_material(1e6, 50.0, mu, mu))
    x0 = np.array([0.0, 0.0, 0.1, 0, 0, 0, 1, v0, 0, 0, 0, 0, 0], np.float32)
    solver = jd.simulation.Rosenbrock23(jacobian="stiff")
    x = jd.simulate(box, (0.0, v0 / (mu * g) + 0.2), x0, solver=solver, dense=False).final_state
    assert x.dtype == jnp.float32
    np.testing.assert_allclose(x[0], v0 ** 2 / (2 * mu * g), rtol=2e-3)
    with pytest.raises(jd.SimulationError, match="MAX_STEPS_REACHED.*float32.*atol >= 1e-05"):
        jd.simulate(box, (0.0, 0.5), x0, solver=solver, atol=1e-9, max_steps=2000, dense=False)


def test_a_ball_sliding_then_rolling_ends_at_five_sevenths_of_its_speed():
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground(
        material=_material(1e6, 50.0, 0.8, 0.6))
    v0, m, r, inertia = 2.0, 2.0, 0.1, 0.008
    x0 = jnp.array([0.0, 0.0, 0.1, 0, 0, 0, 1, v0, 0, 0, 0, 0, 0])
    traj = jd.simulate(ball, (0.0, 1.0), x0, solver="rosenbrock23", rtol=1e-8, atol=1e-10, max_steps=20000)
    x = np.asarray(traj.final_state)
    R = np.asarray(jd.multibody._spatial.quaternion_matrix(jnp.asarray(x[3:7])))
    v_world, w_world = R @ x[7:10], R @ x[10:13]
    # angular momentum about the contact point C is conserved; C lies x/2 below the undeformed
    # surface (the midpoint of the witness points), x = m g / k the static penetration:
    # v = v0 / (1 + I / (m r'^2)), r' = r - x/2 (5/7 v0 as k -> infinity)
    k = 3e4 * 1e6 / (3e4 + 1e6)
    lever = r - m * 9.81 / k / 2
    np.testing.assert_allclose(v_world[0], v0 / (1 + inertia / (m * lever ** 2)), rtol=2e-4)  # creep: ~1e-4 m/s
    np.testing.assert_allclose(v0 / (1 + inertia / (m * r ** 2)), 5 / 7 * v0)
    np.testing.assert_allclose(w_world[1] * lever, v_world[0], rtol=2e-4)  # rolling without slip


def test_a_rolling_ball_held_outside_the_stiction_band_at_a_loose_tolerance_is_told_the_remedy():
    """Sliding at 1 m/s, the ball starts to roll; at rtol 1e-4 the W-method's steps then hold
    it at a slip of 3.5 v_s, just outside the stiction band where Drake's law is flat (each
    step's midpoint lands at zero slip, where friction is ~0, so the step leaves the slip as
    it was), in steps of 4e-5 s: ~23,000 steps for 1 s, against ~1,700 at rtol 1e-6 and ~700
    under dopri5. The error says so; both remedies end at 5/7 of the speed."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    x0 = jnp.array([0.0, 0.0, 0.1, 0, 0, 0, 1, 1.0, 0, 0, 0, 0, 0])
    run = functools.partial(jd.simulate, ball, (0.0, 1.0), x0, max_steps=4000, dense=False)
    with pytest.raises(jd.SimulationError, match="MAX_STEPS_REACHED.*outside the stiction band.*rtol=1e-6.*dopri5"):
        run(rtol=1e-4)
    speeds = [float((np.asarray(jd.multibody._spatial.quaternion_matrix(x[3:7])) @ np.asarray(x[7:10]))[0])
              for x in (run().final_state, run(rtol=1e-4, solver="dopri5").final_state)]
    # rolling at 5/7 of the speed (the test above checks the closed form tightly at its setting)
    np.testing.assert_allclose(speeds, 5 / 7, rtol=5e-3)
    np.testing.assert_allclose(speeds[0], speeds[1], rtol=1e-3)


THROWN_BALL = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True,
                                          stiction_tolerance=0.05).with_ground(material=_material(5e4, 2.0, 0.9, 0.9))


def _thrown_ball(mu, mass, x0, solver):
    import equinox as eqx
    ball = eqx.tree_at(lambda p: (p.contact.mu_static, p.contact.mu_dynamic, p.tree.mass),
                       THROWN_BALL, (jnp.full(2, mu), jnp.full(2, mu), jnp.full(1, mass)))
    accuracy = dict(dt=2.5e-4) if solver == "rk4" else dict(rtol=1e-10, atol=1e-12)
    return jd.simulate(ball, (0.0, 0.5), x0, solver=solver, max_steps=20000, autodiff="forward",
                       **accuracy).final_state


@pytest.mark.parametrize("solver, h, rtol", [
    ("rk4", 1e-6, 1e-5),   # fixed steps: the derivative of the discrete scheme itself
    # adaptive: differences see step-size noise ~ tol / h, and the computed solution's derivative
    # in the height (which moves the impacts) is 3.7e-5 of the largest entry from differences of
    # a run at rtol 1e-12
    pytest.param("dopri5", 1e-4, 6e-5, marks=pytest.mark.slow)])
def test_gradients_through_bounces_equal_central_differences(solver, h, rtol):
    # dropped with spin and a sideways throw: two impacts (onsets and releases) and sliding friction
    x0 = jnp.array([0.0, 0.0, 0.3, 0, 0, 0, 1, 1.0, 0.3, -1.0, 5.0, -3.0, 2.0])
    f = jax.jit(functools.partial(_thrown_ball, solver=solver))
    J = jax.jit(jax.jacfwd(f, argnums=(0, 1, 2)))(0.5, 2.0, x0)
    for argnum, derivative in enumerate(J[:2]):   # friction coefficient, mass
        plus, minus = [0.5, 2.0], [0.5, 2.0]
        plus[argnum] += h
        minus[argnum] -= h
        fd = (np.asarray(f(*plus, x0)) - np.asarray(f(*minus, x0))) / (2 * h)
        np.testing.assert_allclose(np.asarray(derivative), fd, rtol=rtol, atol=rtol * np.max(np.abs(fd)))
    for i, step in ((2, h / 10), (7, h), (10, h)):  # height (which moves the impacts: more curvature), speed, spin
        e = jnp.zeros(13).at[i].set(step)
        fd = (np.asarray(f(0.5, 2.0, x0 + e)) - np.asarray(f(0.5, 2.0, x0 - e))) / (2 * step)
        np.testing.assert_allclose(np.asarray(J[2][:, i]), fd, rtol=rtol, atol=rtol * np.max(np.abs(fd)))


def test_the_gradient_at_the_instant_of_touch_is_finite():
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    x = jnp.array([0.0, 0.0, 0.1, 0, 0, 0, 1, 0.0, 0.0, 0.0, 0, 0, 0])   # touching, at rest: slip 0
    J = jax.jit(jax.jacfwd(lambda x: ball.dynamics(0.0, x, jnp.zeros(0))))(x)
    assert np.all(np.isfinite(np.asarray(J)))
    g = jax.jit(jax.grad(lambda x: jnp.sum(ball.dynamics(0.0, x, jnp.zeros(0)) ** 2)))(x)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow   # 11 s; batching of the contact law is exercised by the GPU benchmark and the example
def test_vmap_over_friction_equals_a_loop():
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    import equinox as eqx
    x0 = jnp.array([0.0, 0.0, 0.1, 0, 0, 0, 1, 2.0, 0, 0, 0, 0, 0])

    def final(mu):
        p = eqx.tree_at(lambda p: (p.contact.mu_static, p.contact.mu_dynamic), ball, (jnp.full(2, mu), jnp.full(2, mu)))
        return jd.simulate(p, (0.0, 0.1), x0, dense=False, max_steps=4000).final_state

    mus = jnp.array([0.2, 0.5, 1.0])
    batched = jax.vmap(final)(mus)
    looped = jnp.stack([jax.jit(final)(m) for m in mus])
    np.testing.assert_allclose(np.asarray(batched), np.asarray(looped), rtol=1e-9, atol=1e-12)
    assert batched[0, 0] > batched[2, 0]   # less friction, further


def test_the_default_solver_is_the_stiff_w_method_for_contact_at_everyday_tolerances():
    """solver="auto": a contact plant at rtol >= 1e-7 runs Rosenbrock23(jacobian="stiff") (a
    box tumbling to rest: 10x faster than dopri5 at rtol 1e-6, benchmarks/RESULTS.md),
    tighter or without contact dopri5; the same steps and state as asking for them."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    x0 = jnp.array([0.0, 0.0, 0.2, 0, 0, 0, 1, 0.5, 0, 0, 0, 0, 0])
    stiff = jd.simulation.Rosenbrock23(jacobian="stiff")
    # (the ball alone has collision geometry but nothing to touch: dopri5, and no step bound,
    # which was NaN without a pair)
    for system, rtol, expected in ((ball.with_ground(), 1e-6, stiff), (ball.with_ground(), 1e-8, "dopri5"),
                                   (ball, 1e-6, "dopri5")):
        run = lambda solver, rtol=rtol, system=system: jd.simulate(system, (0.0, 0.3), x0, solver=solver,  # noqa: E731
                                                                   rtol=rtol, dense=False, throw=False)
        auto, chosen = run("auto"), run(expected)
        assert bool(auto.success) and int(auto.num_accepted_steps) == int(chosen.num_accepted_steps)
        np.testing.assert_array_equal(np.asarray(auto.final_state), np.asarray(chosen.final_state))
        if expected is stiff:   # dopri5 runs out of its 4096 default steps before the ball has bounced twice
            assert int(run("dopri5").status) == jd.simulation.SimulationStatus.MAX_STEPS_REACHED


# ----- geometry ---------------------------------------------------------------------------------


def test_box_on_a_half_space_touches_at_its_lowest_corners():
    tilt = _rotation_y(0.2)
    params = {"size": jnp.array([0.5, 0.3, 0.2])}
    ground = {"size": jnp.zeros(3)}
    depth, pa, pb, n, _ = penetration("box", params, (jnp.asarray(tilt), jnp.array([0.0, 0.0, 0.5])),
                                   "halfspace", ground, (jnp.eye(3), jnp.zeros(3)))
    corners = np.asarray(Box(1.0, 0.6, 0.4).vertices()) @ tilt.T + [0, 0, 0.5]
    np.testing.assert_allclose(np.asarray(depth), -corners[:, 2], atol=1e-14)
    np.testing.assert_allclose(np.asarray(pa), corners, atol=1e-14)
    np.testing.assert_allclose(np.asarray(n), np.tile([0, 0, 1.0], (8, 1)))


def test_capsules_touch_at_the_closest_points_of_their_segments():
    rng = np.random.default_rng(3)
    for _ in range(20):
        Ra, Rb = (np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(2))
        Ra, Rb = Ra * np.sign(np.linalg.det(Ra)), Rb * np.sign(np.linalg.det(Rb))
        pa, pb = rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.3
        a, b = {"size": jnp.array([0.1, 0.3, 0.0])}, {"size": jnp.array([0.15, 0.2, 0.0])}
        depth = penetration("capsule", a, (jnp.asarray(Ra), jnp.asarray(pa)), "capsule", b,
                            (jnp.asarray(Rb), jnp.asarray(pb)))[0]
        s = np.linspace(-0.3, 0.3, 601)[:, None] * Ra[:, 2] + pa
        t = np.linspace(-0.2, 0.2, 401)[:, None] * Rb[:, 2] + pb
        distance = np.min(np.linalg.norm(s[:, None] - t[None], axis=-1))   # brute force
        np.testing.assert_allclose(float(depth[0]), 0.25 - distance, atol=2e-6)


def _random_rotation(rng):
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    return jnp.asarray(R * np.sign(np.linalg.det(R)))


def _hull_params(hull):
    return jd.geometry.shape_parameters(hull)[1]


def test_a_sphere_and_a_capsule_touch_a_convex_hull_as_they_touch_the_same_box():
    """A hull's signed distance outside it is the distance to its nearest triangle (its planes
    alone underestimate it near edges and corners): a sphere against the hull of a box's
    corners equals Drake's closed form for the box, at points all around it (faces, edges,
    corners, inside), with its gradient; a capsule too (end spheres and the hull's vertices)."""
    rng = np.random.default_rng(7)
    box = Box(0.4, 0.3, 0.2)
    hull = _hull_params(Convex.from_points(box.vertices()))
    X_B = (_random_rotation(rng), jnp.array([0.1, -0.2, 0.3]))
    as_box = {"size": jnp.asarray(box.half_sizes)}

    def sphere_on(kind, params, centre, radius):
        return penetration("sphere", {"size": jnp.stack([radius, 0.0, 0.0])}, (jnp.eye(3), centre), kind, params, X_B)

    centres = X_B[1] + jnp.asarray(rng.uniform(-0.33, 0.33, (500, 3))) @ X_B[0].T
    radii = jnp.asarray(rng.uniform(0.01, 0.1, 500))
    for ours, drakes in zip(*(jax.jit(jax.vmap(functools.partial(sphere_on, kind, params)))(centres, radii)
                              for kind, params in (("convex", hull), ("box", as_box)))):
        np.testing.assert_allclose(np.asarray(ours), np.asarray(drakes), atol=1e-14)
    corner = X_B[1] + X_B[0] @ jnp.array([0.23, 0.17, 0.11])   # beyond a corner, 5 cm sphere touching
    grads = [jax.jit(jax.grad(lambda c: sphere_on(kind, params, c, jnp.asarray(0.05))[0][0]))(corner)
             for kind, params in (("convex", hull), ("box", as_box))]
    np.testing.assert_allclose(np.asarray(grads[0]), np.asarray(grads[1]), atol=1e-14)
    capsule = {"size": jnp.array([0.05, 0.15, 0.0])}
    X_A = (jnp.stack([_random_rotation(rng) for _ in range(50)]), X_B[1] + jnp.asarray(rng.uniform(-0.3, 0.3, (50, 3))))
    ours, drakes = (jax.jit(jax.vmap(lambda R, p: penetration("capsule", capsule, (R, p), kind, params, X_B)[0]))(*X_A)
                    for kind, params in (("convex", hull), ("box", as_box)))
    assert int(jnp.sum(drakes > 0)) > 10   # some touch
    np.testing.assert_allclose(np.sort(np.asarray(ours), 1), np.sort(np.asarray(drakes), 1), atol=1e-14)


def test_round_sides_that_cross_touch_at_the_closed_form_depth():
    """Two cylinders, or a capsule and a cylinder, whose axes cross: depth r_a + r_b - |the
    axes' distance|, at the point between the axes, along their common normal."""
    rng = np.random.default_rng(11)
    R_A, R_B = jnp.stack([_random_rotation(rng) for _ in range(10)]), jnp.stack([_random_rotation(rng) for _ in range(10)])
    a_axis, b_axis = R_A[:, :, 2], R_B[:, :, 2]
    normal = jnp.cross(a_axis, b_axis) / jnp.linalg.norm(jnp.cross(a_axis, b_axis), axis=1, keepdims=True)
    gap = 0.23   # axes 0.23 apart, radii 0.1 + 0.15: 2 cm deep
    for kind_a in ("capsule", "cylinder"):
        def deepest(R_A, p_A, R_B, p_B):
            depth, pa, pb, n, _ = penetration(kind_a, {"size": jnp.array([0.1, 0.4, 0.0])}, (R_A, p_A),
                                           "cylinder", {"size": jnp.array([0.15, 0.5, 0.0])}, (R_B, p_B))
            i = jnp.argmax(depth)
            return depth[i], pb[i], n[i]
        depth, pb, n = jax.jit(jax.vmap(deepest))(R_A, 0.05 * a_axis + gap * normal, R_B, -0.03 * b_axis)
        # a capsule's point found by a search to ~sqrt(eps): the depth is stationary there
        close = 1e-12 if kind_a == "cylinder" else 1e-7
        np.testing.assert_allclose(np.asarray(depth), 0.1 + 0.15 - gap, atol=1e-12)
        np.testing.assert_allclose(np.asarray(n), np.asarray(normal), atol=close)
        np.testing.assert_allclose(np.asarray(pb), np.asarray(0.15 * normal), atol=close)


def test_a_capsule_across_a_box_edge_touches_at_the_closed_form_depth():
    """A tilted capsule lying across a box's (or the same hull's) top edge, its segment r - x
    from the edge: one candidate between its end spheres at depth x along the common normal;
    lying flat on the face, only its two end spheres touch (no third point between them)."""
    box = Box(0.4, 0.4, 0.2)
    shapes = (("box", {"size": jnp.asarray(box.half_sizes)}),
              ("convex", _hull_params(Convex.from_points(box.vertices()))))
    capsule, r, x, tilt = {"size": jnp.array([0.05, 0.3, 0.0])}, 0.05, 2e-3, 0.3
    axis = np.array([np.cos(tilt), 0.0, -np.sin(tilt)])   # down toward +x, past the edge
    up = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    R_A = jnp.asarray(np.column_stack([up, np.cross(axis, up), axis]))
    X_A = (R_A, jnp.asarray(np.array([0.2, 0.05, 0.1]) + (r - x) * up))
    for kind, params in shapes:
        across = jax.jit(lambda X: penetration("capsule", capsule, X, kind, params, (jnp.eye(3), jnp.zeros(3))))
        depth, _, pb, n, _ = across(X_A)
        i = int(jnp.argmax(depth))
        assert int(jnp.sum(depth > 0)) == 1
        np.testing.assert_allclose(float(depth[i]), x, atol=1e-12)
        np.testing.assert_allclose(np.asarray(n[i]), up, atol=1e-9)
        np.testing.assert_allclose(np.asarray(pb[i]), [0.2, 0.05, 0.1], atol=1e-9)
        for s in (0.27, 0.29):   # crossing within a radius of the end: once, by the middle sphere
            depth = across((R_A, X_A[1] - s * jnp.asarray(axis)))[0]
            np.testing.assert_allclose(np.asarray(depth[depth > 0]), [x], atol=1e-12)
        flat = (jnp.asarray(np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])), jnp.array([0.0, 0.0, 0.1 + r - x]))
        short = {"size": jnp.array([r, 0.15, 0.0])}
        depth = jax.jit(penetration, static_argnums=(0, 3))("capsule", short, flat, kind, params,
                                                            (jnp.eye(3), jnp.zeros(3)))[0]
        np.testing.assert_allclose(np.sort(np.asarray(depth[depth > 0])), [x, x], atol=1e-12)


def _least_overlap(vertices_a, vertices_b, axes):
    """Brute force: the least overlap of two convex point sets' projections over `axes` (their
    penetration depth where `axes` hold every face normal and edge-pair cross product)."""
    a, b = vertices_a @ axes.T, vertices_b @ axes.T
    return np.min(np.minimum(a.max(0) - b.min(0), b.max(0) - a.min(0)))


def test_two_polytopes_overlap_by_the_brute_force_separating_axes_least_depth():
    """Boxes and hulls at random poses: they touch exactly where the separating-axis test over
    every face normal and every edge-pair cross product (brute force) finds them overlapping;
    an edge crossing an edge is at the overlap along its normal, a face's clipped points no
    deeper than that along theirs; every touching candidate's witnesses lie depth apart along
    its normal."""
    rng = np.random.default_rng(5)
    hull = Convex.from_points(rng.normal(size=(14, 3)) * [0.3, 0.2, 0.25])
    box = Box(0.4, 0.3, 0.2)
    shapes = {"box": ({"size": jnp.asarray(box.half_sizes)}, box.vertices(),
                      np.array([[a, b] for a in box.vertices() for b in box.vertices()
                                if np.sum(a != b) == 1])),
              "convex": (_hull_params(hull), hull.vertices,
                         np.concatenate([hull.triangles[:, [0, 1]], hull.triangles[:, [1, 2]], hull.triangles[:, [2, 0]]]))}
    touching_edges = 0
    for kind_a, kind_b in (("box", "box"), ("box", "convex"), ("convex", "convex")):
        (params_a, local_a, edges_a), (params_b, local_b, edges_b) = shapes[kind_a], shapes[kind_b]
        R_A, R_B = jnp.stack([_random_rotation(rng) for _ in range(60)]), jnp.stack([_random_rotation(rng) for _ in range(60)])
        p_A = jnp.asarray(rng.normal(size=(60, 3)) * 0.2)
        depth, pa, pb, n, _ = jax.jit(jax.vmap(lambda Ra, pa, Rb: penetration(kind_a, params_a, (Ra, pa), kind_b, params_b,
                                                                            (Rb, jnp.zeros(3)))))(R_A, p_A, R_B)
        for k in range(60):
            Ra, Rb = np.asarray(R_A[k]), np.asarray(R_B[k])
            va, vb = local_a @ Ra.T + np.asarray(p_A[k]), local_b @ Rb.T
            ea, eb = (edges_a[:, 1] - edges_a[:, 0]) @ Ra.T, (edges_b[:, 1] - edges_b[:, 0]) @ Rb.T
            crosses = np.cross(ea[:, None], eb[None]).reshape(-1, 3)
            crosses = crosses[np.linalg.norm(crosses, axis=1) > 1e-9]
            faces = [np.asarray(p["planes"])[:, :3] if "planes" in p else np.eye(3) for p in (params_a, params_b)]
            axes = np.concatenate([faces[0] @ Ra.T, faces[1] @ Rb.T, crosses / np.linalg.norm(crosses, axis=1)[:, None]])
            least = _least_overlap(va, vb, axes)
            d = np.asarray(depth[k])
            if abs(least) < 1e-9:
                continue
            assert (d.max() > 0) == (least > 0), (kind_a, kind_b, k, least, d.max())
            touching = d > 0
            np.testing.assert_allclose(np.asarray(pb[k] - pa[k])[touching], d[touching, None] * np.asarray(n[k])[touching],
                                       atol=1e-12)
            # each touching point no deeper than the overlap along its own normal; an edge
            # crossing an edge at exactly that overlap
            for i in np.flatnonzero(touching):
                along = _least_overlap(va, vb, np.asarray(n[k, i])[None])
                assert d[i] <= along + 1e-12, (kind_a, kind_b, k, i, d[i], along)
            if np.isfinite(d[-1]):
                np.testing.assert_allclose(d[-1], _least_overlap(va, vb, np.asarray(n[k, -1])[None]), atol=1e-12)
                touching_edges += d[-1] > 0
    assert touching_edges >= 5


def test_crossed_planks_and_crossed_edges_touch_at_their_closed_form_points():
    """Two planks crossed flat touch at the 4 corners of their overlap (no corner of either is
    inside the other); two equal cubes stacked, aligned or turned, on the corners of their
    overlap, weighted by its exterior angles (no jump as the turn grows from 0); two
    cubes standing on edges crossed at right angles touch once, at their edges' crossing,
    along the vertical, at depth 2 h - z (h: half a face's diagonal)."""
    x, I = 1e-3, jnp.eye(3)
    plank_a, plank_b = {"size": jnp.array([0.5, 0.05, 0.05])}, {"size": jnp.array([0.05, 0.5, 0.05])}
    depth, pa, pb, n, _ = penetration("box", plank_a, (I, jnp.array([0.0, 0.0, 0.1 - x])), "box", plank_b, (I, jnp.zeros(3)))
    touching = np.asarray(depth) > 0
    np.testing.assert_allclose(np.asarray(depth)[touching], [x] * 4, atol=1e-15)
    corners = [[sx * 0.05, sy * 0.05, 0.05] for sx in (-1, 1) for sy in (-1, 1)]
    np.testing.assert_allclose(sorted(np.asarray(pb)[touching].tolist()), corners, atol=1e-15)
    np.testing.assert_allclose(np.asarray(n)[touching], [[0, 0, 1.0]] * 4, atol=1e-15)
    cube = {"size": jnp.array([0.1, 0.1, 0.1])}
    for turn in (0.0, 1e-7, 1e-3, 0.3, np.pi / 4):
        # their overlap: a square (4 corners of weight 1), then an octagon of 4 corners turning by
        # pi/2 - turn and 4 where the sides cross, turning by `turn` (weight 4 angle / 2 pi)
        c, s = np.cos(turn), np.sin(turn)
        depth, _, _, _, weight = penetration("box", cube, (jnp.asarray([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
                                                           jnp.array([0.0, 0.0, 0.2 - x])), "box", cube, (I, jnp.zeros(3)))
        touching = np.asarray(depth) > 0
        np.testing.assert_allclose(np.asarray(depth)[touching], [x] * touching.sum(), atol=1e-15)
        crossing = 2 * turn / np.pi
        expected = [1.0] * 4 if turn == 0 else [crossing] * 4 + [1 - crossing] * 4
        np.testing.assert_allclose(np.sort(np.asarray(weight)[touching]), np.sort(expected), atol=1e-9)
    h = 0.1 * np.sqrt(2)
    R_A, R_B = (jnp.asarray(np.asarray(jd.multibody.rpy(*angles))) for angles in ((np.pi / 4, 0, 0), (0, np.pi / 4, 0)))
    depth, pa, pb, n, _ = penetration("box", cube, (R_A, jnp.array([0.01, -0.02, 2 * h - x])), "box", cube, (R_B, jnp.zeros(3)))
    touching = np.asarray(depth) > 0
    np.testing.assert_allclose(np.asarray(depth)[touching], [x], atol=1e-15)
    np.testing.assert_allclose(np.asarray(pb)[touching], [[0.0, -0.02, h]], atol=1e-15)   # on B's edge, under A's
    np.testing.assert_allclose(np.asarray(pa)[touching], [[0.0, -0.02, h - x]], atol=1e-15)
    np.testing.assert_allclose(np.asarray(n)[touching], [[0, 0, 1.0]], atol=1e-15)


CUBE_LINK = """<link name="{}"><inertial><mass value="1"/>
  <inertia ixx="0.00667" iyy="0.00667" izz="0.00667" ixy="0" ixz="0" iyz="0"/></inertial>
  <collision><geometry><box size="0.2 0.2 0.2"/></geometry></collision></link>"""


def _free_cubes(tmp_path, names, **options):
    """A plant of free 1-kg, 0.2-m cubes (links not joined: each floats)."""
    (tmp_path / "cubes.urdf").write_text(f'<robot name="cubes">{"".join(CUBE_LINK.format(n) for n in names)}</robot>')
    return jd.RigidBodySystem.from_urdf(tmp_path / "cubes.urdf", floating_base=True, contact=True, **options)


def _cube_on_an_equal_cube(tmp_path):
    """A free cube, and an equal one fixed to the world with its top face at z = 0."""
    return _free_cubes(tmp_path, ["cube"]).with_collision_geometry("world", Box(0.2, 0.2, 0.2),
                                                                    translation=(0.0, 0.0, -0.1), name="below")


def _turned_then_tilted(yaw, tilt):
    """The quaternion (x, y, z, w) of R_z(yaw) R_x(tilt)."""
    return jnp.stack([jnp.sin(tilt / 2) * jnp.cos(yaw / 2), jnp.sin(tilt / 2) * jnp.sin(yaw / 2),
                      jnp.cos(tilt / 2) * jnp.sin(yaw / 2), jnp.cos(tilt / 2) * jnp.cos(yaw / 2)])


def test_a_cube_twisted_on_an_equal_cube_is_held_by_a_force_continuous_in_its_tilt(tmp_path):
    """A free 0.2-m cube twisted by 0.3 rad on an equal one fixed to the world, sunk 1e-5 m:
    their overlap is an octagon, whose 4 corners near the cubes' corners turn by pi/2 - 0.3 and
    4 where their sides cross by 0.3 (weights 4 angle / 2 pi). Level, the normal force is 4 k
    delta and the torque 0; tilted by +-1e-7 rad, the torque is the closed-form rotational
    stiffness (k/2) sum w r^2 times the tilt. Keeping 4 of the 8 corners, the choice flipped
    with the tilt's sign and the torque jumped by tens of N m (a twisted stack stalled)."""
    plant = _cube_on_an_equal_cube(tmp_path)
    h, delta, twist, k = 0.1, 1e-5, 0.3, 1e6 / 2   # k: two 1e6-N/m geometries in series
    force = jax.jit(lambda tilt: plant.contact_force(jnp.concatenate([
        jnp.array([0.0, 0.0, h - delta]), _turned_then_tilted(twist, tilt)]), jnp.zeros(6)))
    level, up, down = (np.asarray(force(jnp.asarray(a))) for a in (0.0, 1e-7, -1e-7))
    np.testing.assert_allclose(level[:3], [0.0, 0.0, 4 * k * delta], atol=1e-9)
    np.testing.assert_allclose(level[3:], 0.0, atol=1e-10)
    crossing = 2 * twist / np.pi
    spread = crossing / np.cos(twist / 2) ** 2 + (1 - crossing) / np.cos(np.pi / 4 - twist / 2) ** 2
    stiffness = 2 * k * h ** 2 * spread   # (k/2) sum_i w_i |r_i|^2 over the octagon's 8 corners
    np.testing.assert_allclose((up[3:] - down[3:]) / 2e-7, [-stiffness, 0.0, 0.0], rtol=1e-4, atol=1e-4 * stiffness)
    np.testing.assert_allclose(up + down, 2 * level, atol=1e-4 * stiffness * 1e-7)   # odd in the tilt


def test_a_cube_dropped_turned_onto_an_equal_cube_comes_to_rest(tmp_path):
    """A free cube dropped from 1 cm onto an equal cube fixed to the world, turned by 0.3 rad:
    it lands on the octagon of their overlap and rests sunk m g / 4k within 0.5 s. Keeping 4
    of the octagon's 8 corners, which 4 flipped as it bounced, and the run ran out of 100000
    steps at t = 0.064 s."""
    plant = _cube_on_an_equal_cube(tmp_path)
    x0 = jnp.concatenate([jnp.array([0.005, -0.003, 0.11]), _turned_then_tilted(0.3, 0.0), jnp.zeros(6)])
    traj = jd.simulate(plant, (0.0, 0.5), x0, dense=False)   # within the default 4096 steps
    x = np.asarray(traj.final_state)
    np.testing.assert_allclose(x[2], 0.1 - 9.81 / (4 * 1e6 / 2), atol=1e-8)
    assert np.max(np.abs(x[7:])) < 1e-3


def test_the_gradient_of_a_slide_on_a_table_is_the_closed_form_one(tmp_path):
    """A 2-kg plank (0.2 x 0.2 x 0.05 m), turned 20 degrees, sliding at v0 = 1.2 m/s on a box
    fixed to the world (mu 0.45): it stops after d = v0^2 / (2 mu g), and jax.grad through the
    box-box contact (the weighted corners of the clipped polygon) gives dd/dv0 = v0 / (mu g)
    and dd/dmu = -v0^2 / (2 mu^2 g)."""
    (tmp_path / "plank.urdf").write_text("""<robot name="plank"><link name="plank"><inertial><mass value="2"/>
      <inertia ixx="0.00708" iyy="0.00708" izz="0.01333" ixy="0" ixz="0" iyz="0"/></inertial>
      <collision><geometry><box size="0.2 0.2 0.05"/></geometry></collision></link></robot>""")
    plank = jd.RigidBodySystem.from_urdf(tmp_path / "plank.urdf", floating_base=True, contact=True)
    plant = plank.with_collision_geometry("world", Box(3.0, 3.0, 0.1), translation=(0.5, 0.0, -0.05), name="table")
    g, yaw, v0, mu = 9.81, np.radians(20.0), 1.2, 0.45

    def distance(v0, mu):
        p = eqx.tree_at(lambda p: (p.contact.mu_static, p.contact.mu_dynamic), plant, (jnp.full(2, mu), jnp.full(2, mu)))
        resting = 0.025 - 2 * g / (4 * 1e6 / 2)
        x0 = jnp.concatenate([jnp.array([0.0, 0.0, resting]), _turned_then_tilted(yaw, 0.0),
                              v0 * jnp.array([np.cos(yaw), -np.sin(yaw), 0.0]), jnp.zeros(3)])   # (v0, 0, 0) in the world
        return jd.simulate(p, (0.0, 0.5), x0, dense=False, max_steps=20_000).final_state[0]

    d, (d_v0, d_mu) = jax.jit(jax.value_and_grad(distance, argnums=(0, 1)))(v0, mu)
    np.testing.assert_allclose(float(d), v0 ** 2 / (2 * mu * g), rtol=1e-4)
    np.testing.assert_allclose([float(d_v0), float(d_mu)], [v0 / (mu * g), -v0 ** 2 / (2 * mu ** 2 * g)], rtol=1e-3)


@pytest.mark.slow
def test_a_twisted_stack_of_three_cubes_comes_to_rest_at_its_closed_form_heights(tmp_path):
    """Three 1-kg cubes dropped 5 cm apart onto the floor, turned by 0, 0.2 and 0.4 rad and the
    upper two tilted: after 1 s they rest sunk 3 m g / 4k, then 2 m g / 4k and m g / 4k more
    (4 weights in all under each). Keeping 4 of the 8 corners of each twisted overlap, the run
    ran out of 100000 steps at t = 0.48 (steps of 1e-10 s)."""
    plant = _free_cubes(tmp_path, ["cube0", "cube1", "cube2"]).with_ground()
    q = [jnp.concatenate([jnp.array([0.0, 0.0, 0.1 + 0.25 * i]), _turned_then_tilted(yaw, tilt)])
         for i, (yaw, tilt) in enumerate([(0.0, 0.0), (0.2, 0.01), (0.4, 0.02)])]
    traj = jd.simulate(plant, (0.0, 1.0), jnp.concatenate(q + [jnp.zeros(18)]), dense=False, max_steps=60_000)
    x = np.asarray(traj.final_state)
    sink = 9.81 / (4 * 1e6 / 2)   # m g / 4k, k: two 1e6-N/m geometries in series
    np.testing.assert_allclose(x[2:21:7], [0.1 - 3 * sink, 0.3 - 5 * sink, 0.5 - 6 * sink], atol=1e-7)
    assert np.max(np.abs(x[21:])) < 1e-4


def _plank_on_a_ridge(tmp_path):
    """A 1 kg plank (1 x 0.2 x 0.05 m) free above a box (0.2 x 1 x 0.2 m) turned 45 degrees about
    y, whose top edge (the ridge) runs along y at z = 0.1 sqrt(2)."""
    (tmp_path / "plank.urdf").write_text("""<robot name="plank">
      <link name="plank"><inertial><mass value="1"/><inertia ixx="0.0035" iyy="0.0835" izz="0.0867" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><box size="1.0 0.2 0.05"/></geometry></collision></link></robot>""")
    plank = jd.RigidBodySystem.from_urdf(tmp_path / "plank.urdf", floating_base=True, contact=True)
    return plank.with_collision_geometry("world", Box(0.2, 1.0, 0.2), rotation=_rotation_y(np.pi / 4), name="ridge")


def test_a_plank_across_a_ridge_rests_on_both_ends_of_the_ridge_under_it(tmp_path):
    """The plank's face lies on the ridge: two points, where the ridge leaves the face under
    its two long edges, at their closed-form depths below the face, however little the plank
    is turned along the ridge (an edge-edge axis ties with the face there: turned by 1e-9 rad,
    the edge was chosen and gave one point, the support halving in a jump)."""
    plank = _plank_on_a_ridge(tmp_path)
    top, x = 0.1 * np.sqrt(2), 1e-5
    for a in (0.0, 1e-9, -1e-9, 1e-7, 1e-5, -1e-5):
        c, s = np.cos(a), np.sin(a)
        p = np.array([0.0, 0.003, top + 0.025 - x])
        q = np.concatenate([p, [np.sin(a / 2), 0, 0, np.cos(a / 2)], np.zeros(6)])
        res = plank.contact_results(jnp.asarray(q))
        active = np.asarray(res.active)
        b = p + 0.025 * np.array([0.0, s, -c])                  # the plank's bottom face's centre
        expected = []
        for side in (0.1, -0.1):                                 # the ridge crossing its long edges
            y = p[1] + (side - s * (top - p[2])) / c
            expected.append(s * (b[1] - y) - c * (b[2] - top))   # n . (b - r), n = (0, s, -c)
        np.testing.assert_allclose(np.sort(np.asarray(res.depth)[active]), np.sort(expected), rtol=1e-9, atol=1e-15)


def test_a_plank_sliding_along_a_ridge_stops_after_v0_squared_over_2_mu_g(tmp_path):
    """Resting on the ridge (sunk m g / 2k at its two points), sliding along it at 0.5 m/s:
    it stops after v0^2 / (2 mu g), mu = 2/3 (Drake's defaults, 1.0 for the URDF's collision
    and 0.5 for the ridge's, combined as 2 mu_a mu_b / (mu_a + mu_b)). Before a face was
    preferred over an edge that ties with it, its contact points flipped between one and two
    and the run stalled at t = 5e-5 s with steps of 1e-10 s."""
    plank = _plank_on_a_ridge(tmp_path)
    top, v0, mu, g, k = 0.1 * np.sqrt(2), 0.5, 2 * 1.0 * 0.5 / (1.0 + 0.5), 9.81, 1e6 / 2
    x0 = jnp.array([0.0, 0.0, top + 0.025 - g / (2 * k), 0, 0, 0, 1, 0, v0, 0, 0, 0, 0])
    traj = jd.simulate(plank, (0.0, 0.2), x0, dense=False)
    np.testing.assert_allclose(float(traj.final_state[1]), v0 ** 2 / (2 * mu * g), rtol=1e-4)
    assert abs(float(traj.final_state[8])) < 1e-4


def _turned_about_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_a_corner_repeated_in_a_contact_polygon_keeps_its_weight_and_a_finite_gradient():
    """A unit square whose last corner comes 5 times (as clipping can repeat a corner): the
    corners weigh 1, 1, 1 and, split among the repeats, 1 (its turning falls on the last
    repeat); one point alone weighs 4. The gradients are finite (a repeated corner's edge has
    no direction, where arctan2's derivative is NaN)."""
    from jaxdrake.geometry._polytopes import _corner_weights
    up = jnp.array([0.0, 0.0, 1.0])
    square = jnp.array([[0, 0, 0], [1, 0, 0], [1, 1, 0]] + [[0, 1, 0]] * 5, float)
    for points, count, expected in ((square, 8, [1, 1, 1, 0, 0, 0, 0, 1]), (jnp.zeros((8, 3)), 1, [4.0])):
        used = jnp.arange(8) < count
        weights = _corner_weights(points, used, up)
        np.testing.assert_allclose(np.asarray(weights)[:count], expected, atol=1e-12)
        gradient = jax.grad(lambda p: jnp.sum(_corner_weights(p, used, up) * jnp.arange(8.0)))(points)
        assert np.all(np.isfinite(np.asarray(gradient)))


def test_polytope_contact_weighs_a_larger_polygons_corners_by_their_angles_and_takes_the_least_deep_face():
    """(helper-13's review) A cube turned over a slab's corner has a 5-corner overlap, whose
    corners weigh 4 in all, the slab's right-angled corner among them 1 (4 were once kept, and
    the fourth once fell on the first two's line and was dropped). An upright cube on one
    turned 0.01 rad rests along its own face's normal, the least deep axis (the face margin
    once chose the deeper one). Two float32 cubes stacked, turned by rounding (1e-7 rad), all
    touch with weights of 4 in all (a near-parallel edge pair once passed as an axis through
    rounding and reported them apart, in 69 of 2000 poses)."""
    cube, slab = {"size": jnp.array([0.1, 0.1, 0.1])}, {"size": jnp.array([1.0, 1.0, 0.1])}
    over_corner = jax.jit(jax.vmap(lambda R, p: penetration("box", cube, (R, p), "box", slab, (jnp.eye(3), jnp.zeros(3)))))
    angles = np.linspace(0.1, 0.7, 7)
    depth, _, pb, _, weight = (np.asarray(a) for a in over_corner(
        jnp.asarray(np.stack([_turned_about_z(a) for a in angles])), jnp.tile(jnp.array([0.97, 0.97, 0.199]), (7, 1))))
    touching = depth > 0
    assert np.all(touching.sum(1) >= 4)
    np.testing.assert_allclose(np.sum(np.where(touching, weight, 0.0), 1), 4.0, rtol=1e-12)
    at_corner = touching & (np.linalg.norm(pb[..., :2] - 1.0, axis=-1) < 1e-12)
    assert at_corner.sum() >= 3
    np.testing.assert_allclose(weight[at_corner], 1.0, rtol=1e-12)
    # A's bottom face: 1.0010e-3 deep; B's turned top face: 1.0111e-3
    depth, _, _, n, _ = penetration("box", cube, (jnp.eye(3), jnp.array([0.0, 0.0, 0.2])), "box", cube,
                                 (jnp.asarray(_rotation_y(0.01)), jnp.zeros(3)))
    np.testing.assert_allclose(np.asarray(n)[np.asarray(depth) > 0], [[0, 0, 1.0]] * 2, atol=1e-12)
    rng = np.random.default_rng(4)
    turns = rng.normal(size=(500, 3)) * 1e-7
    rotations = np.stack([np.asarray(jax.scipy.linalg.expm(jnp.asarray(np.cross(np.eye(3), w)))) for w in turns[:50]])
    single = {"size": jnp.array([0.1, 0.1, 0.1], jnp.float32)}
    stacked = jax.jit(jax.vmap(lambda R: penetration("box", single, (R, jnp.array([0.0, 0.0, 0.199], jnp.float32)), "box",
                                                     single, (jnp.eye(3, dtype=jnp.float32), jnp.zeros(3, jnp.float32)))[::4]))
    depth, weight = (np.asarray(a) for a in stacked(jnp.asarray(rotations, jnp.float32)))
    assert depth.dtype == np.float32 and np.all(np.sum(depth > 0, 1) >= 4)
    np.testing.assert_allclose(np.sum(np.where(depth > 0, weight, 0.0), 1), 4.0, rtol=1e-5)


def test_a_hull_of_slightly_noisy_points_has_the_faces_of_the_exact_one():
    """(helper-13's review) A 64-sided cylinder's points moved by 1e-12, or written with 10
    digits: its flat caps are one face each, as without the noise (merging some of a cap's
    triangles but not others had given overlapping faces, V - E + F = 14)."""
    ring = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    points = np.vstack([np.column_stack([0.1 * np.cos(ring), 0.1 * np.sin(ring), np.full(64, z)]) for z in (-0.05, 0.05)])
    turned = points @ np.asarray(jd.multibody.rpy(0.3, 0.2, 0.1)).T
    for noisy in (points + 1e-12 * np.random.default_rng(0).normal(size=points.shape),
                  np.array([[float(f"{x:.10g}") for x in p] for p in turned])):
        hull = Convex.from_points(noisy)
        assert hull.is_closed() and sorted(len(f) for f in hull.faces)[-2:] == [64, 64]
        assert len(hull.faces) == 66


def test_polytope_contact_gradients_equal_central_differences():
    """The depths, witnesses and weights of a box against a hull (face and edge contacts) as
    functions of A's pose: their derivatives, forward and reverse, equal central differences."""
    rng = np.random.default_rng(2)
    hull = _hull_params(Convex.from_points(rng.normal(size=(12, 3)) * 0.2))
    box = {"size": jnp.array([0.2, 0.15, 0.1])}

    def contacts(theta, R, w, p):   # A turned about the unit w by theta[3] (Rodrigues), moved by theta[:3]
        K = jnp.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        turn = jnp.eye(3) + jnp.sin(theta[3]) * K + (1 - jnp.cos(theta[3])) * K @ K
        out = penetration("box", box, (turn @ R, p + theta[:3]), "convex", hull, (jnp.eye(3), jnp.zeros(3)))
        touching = out[0] > 0
        return jnp.concatenate([jnp.where(touching, out[0], 0.0)] + [
            jnp.where(touching.reshape(touching.shape + (1,) * (x.ndim - 1)), x, 0.0).ravel() for x in out[1:]])

    f, forward, reverse = jax.jit(contacts), jax.jit(jax.jacfwd(contacts)), jax.jit(jax.jacrev(contacts))
    k = jax.eval_shape(lambda: penetration("box", box, (jnp.eye(3), jnp.zeros(3)), "convex", hull,
                                           (jnp.eye(3), jnp.zeros(3))))[0].shape[0]   # the last: an edge pair
    checked, edges = 0, 0
    for _ in range(16):
        R, w = _random_rotation(rng), rng.normal(size=3)
        args = (R, jnp.asarray(w / np.linalg.norm(w)), jnp.asarray(rng.normal(size=3) * 0.15))
        value = np.asarray(f(jnp.zeros(4), *args))
        if not np.any(value[:k] > 0):
            continue
        step = 1e-6
        fd = np.stack([(np.asarray(f(step * e, *args)) - np.asarray(f(-step * e, *args))) / (2 * step)
                       for e in np.eye(4)], 1)
        for jacobian in (forward, reverse):
            np.testing.assert_allclose(np.asarray(jacobian(jnp.zeros(4), *args)), fd, atol=2e-6)
        checked, edges = checked + 1, edges + (value[k - 1] > 0)
    assert checked >= 4 and edges >= 1


def test_a_plank_dropped_across_a_plank_rests_on_their_overlap_sunk_m_g_over_4k(tmp_path):
    """No corner of either plank is inside the other: before the contact polygon, the upper one
    fell through. It rests on the overlap's 4 corners, sunk m g / (4 k)."""
    (tmp_path / "plank.urdf").write_text("""<robot name="plank">
      <link name="plank"><inertial><mass value="0.5"/><inertia ixx="0.0005" iyy="0.04" izz="0.04" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><box size="1.0 0.1 0.1"/></geometry></collision></link></robot>""")
    plank = jd.RigidBodySystem.from_urdf(tmp_path / "plank.urdf", floating_base=True, contact=True)
    plank = plank.with_collision_geometry("world", Box(0.1, 1.0, 0.1), translation=(0.0, 0.0, 0.05), name="lower")
    k, mg = 1e6 / 2, 0.5 * 9.81
    x0 = jnp.array([0.0, 0.0, 0.16, 0, 0, 0, 1] + [0.0] * 6)
    x = jd.simulate(plank, (0.0, 0.6), x0, solver=jd.simulation.Rosenbrock23(jacobian="stiff"), dense=False).final_state
    np.testing.assert_allclose(float(x[2]), 0.15 - mg / (4 * k), atol=1e-9)
    assert int(jnp.sum(plank.contact_results(x).active)) == 4


def test_a_cylinder_lying_across_a_box_edge_touches_at_the_closed_form_depth():
    """A cylinder's round side across a box's top edge (the box turned 45 degrees): one contact
    between its rims, at depth r - (distance of its axis from the edge), along the vertical."""
    r, x, h = 0.05, 1e-3, 0.1 * np.sqrt(2)
    along_x = jnp.asarray(np.asarray(jd.multibody.rpy(0, np.pi / 2, 0)))
    ridge = jnp.asarray(np.asarray(jd.multibody.rpy(0, np.pi / 4, 0)))
    depth, pa, pb, n, _ = penetration("cylinder", {"size": jnp.array([r, 0.2, 0.0])}, (along_x, jnp.array([0.03, 0.02, h + r - x])),
                                   "box", {"size": jnp.array([0.1, 0.1, 0.1])}, (ridge, jnp.zeros(3)))
    touching = np.asarray(depth) > 0
    np.testing.assert_allclose(np.asarray(depth)[touching], [x], atol=1e-12)
    np.testing.assert_allclose(np.asarray(pb)[touching], [[0.0, 0.02, h]], atol=1e-8)
    np.testing.assert_allclose(np.asarray(n)[touching], [[0, 0, 1.0]], atol=1e-8)


def test_a_cylinder_rests_on_a_box_on_two_rim_points_lying_and_four_standing(tmp_path):
    """A cylinder dropped onto a box fixed to the world comes to rest sunk m g / (n k), n = 2
    rim points lying on its side, 4 standing on a cap."""
    (tmp_path / "can.urdf").write_text("""<robot name="can">
      <link name="can"><inertial><mass value="0.8"/><inertia ixx="0.004" iyy="0.004" izz="0.002" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><cylinder radius="0.05" length="0.2"/></geometry></collision></link></robot>""")
    can = jd.RigidBodySystem.from_urdf(tmp_path / "can.urdf", floating_base=True, contact=True)
    can = can.with_collision_geometry("world", Box(1.0, 1.0, 0.1), translation=(0.0, 0.0, -0.05), name="table")
    k, mg = 1e6 / 2, 0.8 * 9.81   # Drake's default stiffness on both, in series
    stiff = jd.simulation.Rosenbrock23(jacobian="stiff")
    lying = np.array([0, 0, 0.06, 0, np.sin(np.pi / 4), 0, np.cos(np.pi / 4)] + [0.0] * 6)
    standing = np.array([0, 0, 0.11, 0, 0, 0, 1] + [0.0] * 6)
    for x0, half_height, points in ((lying, 0.05, 2), (standing, 0.1, 4)):
        x = jd.simulate(can, (0.0, 1.0), jnp.asarray(x0), solver=stiff, dense=False).final_state
        np.testing.assert_allclose(float(x[2]), half_height - mg / (points * k), atol=1e-9)
        assert int(jnp.sum(can.contact_results(x).active)) == points


@pytest.mark.slow   # ~6 s; the sphere-hull query is checked against the box's closed form by default
def test_a_ball_rests_on_a_hulls_face_sunk_m_g_over_k():
    stiff = jd.simulation.Rosenbrock23(jacobian="stiff")
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    frustum = [[sx * w, sy * w, z] for w, z in ((0.3, 0.0), (0.1, 0.2)) for sx in (-1, 1) for sy in (-1, 1)]
    ball = ball.with_collision_geometry("world", Convex.from_points(np.array(frustum)), name="rock")
    k_a, k_b = np.asarray(ball.contact.stiffness)
    x = jd.simulate(ball, (0.0, 1.5), jnp.array([0.03, 0.02, 0.6, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0]), solver=stiff,
                    dense=False).final_state   # on the hull's top face
    np.testing.assert_allclose(float(x[2]), 0.3 - float(ball.tree.mass[0]) * 9.81 / (k_a * k_b / (k_a + k_b)),
                               atol=1e-9)


def test_convex_hull_of_a_mesh_file(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    trimesh.creation.box(extents=(0.2, 0.4, 0.6)).export(tmp_path / "block.obj")
    hull = Convex.from_mesh_file(tmp_path / "block.obj", scale=(2.0, 1.0, 1.0))
    assert len(hull.vertices) == 8 and len(hull.planes) == 6
    np.testing.assert_allclose(np.sort(np.abs(hull.vertices), axis=0)[0], [0.2, 0.2, 0.3])


# ----- bad input: named errors at construction ------------------------------------------------------


def _urdf(tmp_path, collision, inertial=True, name="bad.urdf"):
    mass = ('<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/>'
            '</inertial>' if inertial else "")
    text = f"""<robot name="bad" xmlns:drake="http://drake.mit.edu">
      <link name="base"/>
      <link name="arm"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/>
        </inertial></link>
      <link name="tip">{mass}{collision}</link>
      <joint name="j" type="continuous"><parent link="base"/><child link="arm"/><axis xyz="0 1 0"/></joint>
      <joint name="k" type="continuous"><parent link="arm"/><child link="tip"/><axis xyz="0 1 0"/></joint>
    </robot>"""
    path = tmp_path / name
    path.write_text(text)
    return path


def test_bad_collision_elements_are_named_errors(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    sphere = '<collision name="c"><geometry><sphere radius="0.1"/></geometry>{}</collision>'
    with pytest.raises(URDFError, match="link 'tip'.*point_contact_stiffness must be a non-negative"):
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, sphere.format(
            '<drake:proximity_properties><drake:point_contact_stiffness value="-5"/></drake:proximity_properties>')),
            contact=True)
    with pytest.raises(URDFError, match="mu_dynamic must be a non-negative"):
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, sphere.format(
            '<drake:proximity_properties><drake:mu_dynamic value="-0.1"/></drake:proximity_properties>')), contact=True)
    with pytest.raises(URDFError, match="<sphere> has no radius attribute"):   # a typo: radis
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, '<collision><geometry><sphere radis="0.1"/></geometry></collision>'),
                                     contact=True)
    with pytest.raises(URDFError, match="unsupported collision shape <cone>"):
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, '<collision><geometry><cone radius="1" length="1"/></geometry></collision>'),
                                     contact=True)
    with pytest.raises(URDFError, match="link 'tip', which has no mass or inertia.*Give the link an <inertial>"):
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, sphere.format(""), inertial=False), contact=True)
    torus = trimesh.creation.torus(major_radius=0.3, minor_radius=0.05)
    torus.export(tmp_path / "ring.stl")
    with pytest.raises(URDFError, match="ring.stl: the collision mesh is not convex.*Split it into convex pieces"):
        jd.RigidBodySystem.from_urdf(_urdf(tmp_path, '<collision><geometry><mesh filename="ring.stl"/></geometry>'
                                     '</collision>'), contact=True)
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    with pytest.raises(GeometryError, match=r"rotation is not a rotation matrix .*det R = 8"):
        ball.with_collision_geometry("ball", Sphere(0.1), rotation=2 * np.eye(3))
    with pytest.raises(TypeError, match="material must be a jd.multibody.ContactMaterial, got dict"):
        ball.with_ground(material={"mu_static": 0.3})
    outside = '<collision><geometry><mesh filename="{}"/></geometry></collision>'
    for filename, message in (("../secret.stl", "outside the model's folder"), ("/etc/passwd", "not a path relative"),
                              ("package://robot/x.stl", "pass package_map")):
        with pytest.raises(URDFError, match=message):
            jd.RigidBodySystem.from_urdf(_urdf(tmp_path, outside.format(filename)), contact=True)


def test_two_detailed_hulls_that_may_touch_are_warned_of_with_the_remedy():
    """Two hulls test every pair of their edges: a pair of 642-vertex hulls (3.7 million edge
    pairs per evaluation) is named at construction, with the remedy; small hulls are not."""
    trimesh = pytest.importorskip("trimesh")
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True)
    detailed = Convex.from_points(trimesh.creation.icosphere(3, radius=0.1).vertices)
    with pytest.warns(UserWarning, match=r"1 pair\(s\) of hulls may touch, each testing 3,686,400 pairs of edges.*'mesh', "
                                         r"of 642 vertices.*max_hull_vertices=64"):
        ball.with_collision_geometry("ball", detailed, name="mesh").with_collision_geometry("world", detailed, name="rock")
    coarse = Convex.from_points(trimesh.creation.icosphere(1, radius=0.1).vertices)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ball.with_collision_geometry("ball", coarse, name="mesh").with_collision_geometry("world", coarse, name="rock")


def test_a_hull_simplified_to_fewer_vertices_keeps_the_extreme_ones_first():
    """Cube corners (+-1) inside an octahedron of tips at +-2 on the axes: simplified to 6
    vertices, the hull is the octahedron (the extreme points along the axes come first) and
    the corners lie 1/sqrt(3) outside its faces |x| + |y| + |z| = 2; with room for all 14 the
    hull is exact; fewer than 4 is refused."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    tips = 2.0 * np.concatenate([np.eye(3), -np.eye(3)])
    points = np.concatenate([corners, tips])
    six = Convex.from_points(points, max_vertices=6)
    np.testing.assert_allclose(np.sort(six.vertices, axis=0), np.sort(tips, axis=0))
    outside = np.max(corners @ six.planes[:, :3].T - six.planes[:, 3], axis=1)
    np.testing.assert_allclose(outside, 1 / np.sqrt(3), rtol=1e-12)
    assert len(Convex.from_points(points, max_vertices=14).vertices) == 14
    assert len(Convex.from_points(points, max_vertices=10).vertices) == 10
    with pytest.raises(GeometryError, match="max_vertices must be an integer of at least 4"):
        Convex.from_points(points, max_vertices=3)
    # every extreme along an axis on one plane z = (x + y) / 2, the fifth vertex below it: the
    # 4 kept span a volume (the plane's farthest pair, the one farthest from their line, then
    # the one off the plane)
    wedge = np.array([[2, 0, 1], [-2, 0, -1], [0, 2, 1], [0, -2, -1], [0.5, 0.5, -0.5]], float)
    four = Convex.from_points(wedge, max_vertices=4)
    assert len(four.vertices) == 4 and any(np.allclose(v, [0.5, 0.5, -0.5]) for v in four.vertices)


def test_solo12_with_its_own_meshes_is_warned_of_or_refused_and_loads_with_simplified_hulls(monkeypatch):
    """Solo-12's URDF with its own collision meshes (hulls of 273-672 vertices, 120 pairs that
    may touch, each padded to 1398 edges): the model names its cost (up to 235 million edge
    pairs per evaluation, those of the near pairs, tested one pair at a time: 0.3 GB at once
    in float64) and the remedy, refused on a machine with less memory than that; with
    max_hull_vertices=32 every hull has 32 vertices, all of them the mesh's own, and nothing is
    warned of."""
    import importlib.metadata
    root = pathlib.Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")))
    urdf, packages = root / "solo_description/robots/solo12.urdf", {"example-robot-data": str(root.parent)}
    load = functools.partial(jd.RigidBodySystem.from_urdf, urdf, floating_base=True, contact=True, mesh_hulls=True,
                             package_map=packages)
    message = (r"120 pair\(s\) of hulls may touch, each testing 1,954,404 pairs of edges.*up to 234,528,480 per "
               r"evaluation.*0.3 GB at once in float64.*max_hull_vertices=64")
    with monkeypatch.context() as patch:   # a machine of 0.2 GB
        patch.setattr(os, "sysconf", lambda name: {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": 50_000}[name])
        with pytest.raises(GeometryError, match=message + ".*this machine has 0.2 GB"):
            load()
    with pytest.warns(UserWarning, match=message):
        load()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plant = load(max_hull_vertices=32).with_ground()
    hulls = np.asarray(plant.contact.kinds) == "convex"
    assert plant.contact.vertices.shape[1] == 32 and bool(np.all(np.asarray(plant.contact.vertex_valid)[hulls]))
    foot = Convex.from_mesh_file(root / "solo_description/meshes/stl/solo12/solo12_lower_leg_left_side.stl",
                                 require_convex=False)
    simplified = Convex.from_mesh_file(root / "solo_description/meshes/stl/solo12/solo12_lower_leg_left_side.stl",
                                       require_convex=False, max_vertices=32)
    assert {tuple(v) for v in simplified.vertices} <= {tuple(v) for v in foot.vertices}


def test_detailed_hulls_are_tested_only_where_their_bounding_spheres_meet():
    """Two 30-vertex hulls, their vertices on a sphere of radius 0.1 (84 edges, 7056 edge pairs:
    past CULLED_EDGE_PAIRS, so tested one pair at a time where near): touching, the model's
    candidates are `penetration`'s own; apart, they sit at minus the gap of the bounding
    spheres (about the vertices' mean m, radius max |v - m|) with no force, and the force's
    gradient is finite on both sides."""
    from jaxdrake.geometry import shape_parameters
    from jaxdrake.multibody._contact import CULLED_EDGE_PAIRS
    points = np.random.default_rng(3).normal(size=(30, 3))
    rock = Convex.from_points(0.1 * points / np.linalg.norm(points, axis=1, keepdims=True))
    assert len(rock.edges[0]) ** 2 > CULLED_EDGE_PAIRS
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True)
    plant = ball.with_collision_geometry("ball", rock, name="mesh").with_collision_geometry("world", rock, name="rock")
    q_near = jnp.array([0.03, 0.01, 0.15, 0.0, 0.0, np.sin(0.1), np.cos(0.1)])
    x_near = jnp.concatenate([q_near, jnp.zeros(6)])
    # one program: the candidates and the force's gradient at both states
    force = lambda x: jnp.sum(plant.contact_force(x[:7], x[7:]) ** 2)  # noqa: E731
    results_and_gradient = jax.jit(lambda x: (plant.contact_results(x), jax.grad(force)(x)))
    near, near_gradient = results_and_gradient(x_near)
    assert plant.contact.groups[0][2:] == ((0,), (1,))   # A: the mesh on the ball, B: the rock
    kind, params = shape_parameters(rock)
    yaw = np.array([[np.cos(0.2), -np.sin(0.2), 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.0, 0.0, 1.0]])  # q_near's
    depth = jax.jit(lambda R, p: penetration(kind, params, (R, p), kind, params, (jnp.eye(3), jnp.zeros(3)))[0])(
        jnp.asarray(yaw), q_near[:3])
    np.testing.assert_allclose(np.asarray(near.depth), np.asarray(depth), rtol=1e-12, atol=1e-15)
    assert np.any(np.asarray(near.depth) > 0)
    far, far_gradient = results_and_gradient(x_near.at[:3].set(jnp.array([0.0, 0.3, 0.4])))
    m = rock.vertices.mean(0)
    r = np.max(np.linalg.norm(rock.vertices - m, axis=1))
    gap = np.linalg.norm(yaw @ m + np.array([0.0, 0.3, 0.4]) - m) - 2 * r
    np.testing.assert_allclose(np.asarray(far.depth), -gap, rtol=1e-12)
    assert not np.any(np.asarray(far.active))
    assert np.all(np.isfinite(np.asarray(near_gradient))) and np.any(np.asarray(near_gradient) != 0)
    np.testing.assert_array_equal(np.asarray(far_gradient), 0.0)


def test_bad_shapes_and_materials_are_named_at_construction():
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    with pytest.raises(GeometryError, match="Sphere: radius must be a positive"):
        Sphere(-1.0)
    with pytest.raises(GeometryError, match="flat"):
        Convex.from_points(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))
    with pytest.raises(GeometryError, match="half-space must be fixed to the world"):
        ball.with_collision_geometry("ball", HalfSpace())
    with pytest.raises(GeometryError, match="mu_dynamic .* exceeds mu_static"):
        ball.with_ground(material=ContactMaterial(mu_static=0.2, mu_dynamic=0.5))


def test_without_contact_nothing_changes():
    plain = jd.RigidBodySystem.from_urdf(DATA / "contact_hopper.urdf", floating_base=True)
    assert plain.contact is None
    x = jnp.asarray(_random_state("hopper_landing", plain, np.random.default_rng(0)))
    touching = _ours("hopper_landing")
    far = x.at[2].add(5.0)   # well above the floor: the contact plant's dynamics are the plain one's
    np.testing.assert_allclose(np.asarray(touching.dynamics(0.0, far, jnp.zeros(4))),
                               np.asarray(plain.dynamics(0.0, far, jnp.zeros(4))), rtol=1e-14, atol=1e-12)


def test_a_floating_joint_from_a_declared_world_frees_its_child(tmp_path):
    """A `<joint type="floating">` from the world: its child is a free body with the joint's
    name, the floating base's layout; beside a body hanging from the world too."""
    text = (DATA / "contact_ball.urdf").read_text()
    with_world = text.replace("</robot>", '<link name="world"/><joint name="free" type="floating">'
                              '<parent link="world"/><child link="ball"/></joint></robot>')
    (tmp_path / "free.urdf").write_text(with_world)
    free = jd.RigidBodySystem.from_urdf(tmp_path / "free.urdf", contact=True).with_ground()
    base = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    assert free.tree.joint_types == ("floating",)
    assert free.state_frame.coordinates == tuple(c.replace("floating_base", "free") for c in base.state_frame.coordinates)
    x = jnp.array([0.1, 0.0, 0.095, 0, 0, 0, 1, 1.0, 0, 0, 0, 2.0, 0])
    np.testing.assert_array_equal(np.asarray(free.dynamics(0.0, x, jnp.zeros(0))),
                                  np.asarray(base.dynamics(0.0, x, jnp.zeros(0))))
    two = with_world.replace("</robot>", '<link name="other"><inertial><mass value="1"/><inertia ixx="1" iyy="1" '
                             'izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link><joint name="pin" type="revolute">'
                             '<parent link="world"/><child link="other"/><axis xyz="0 0 1"/></joint></robot>')
    (tmp_path / "two.urdf").write_text(two)
    both = jd.RigidBodySystem.from_urdf(tmp_path / "two.urdf", contact=True).with_ground()
    assert both.tree.joint_names == ("pin", "free") and both.tree.joint_types == ("revolute", "floating")
    x_both = jnp.concatenate([jnp.array([0.3]), x[:7], jnp.array([0.5]), x[7:]])   # the pin turning freely
    xdot = np.asarray(both.dynamics(0.0, x_both, jnp.zeros(1)))
    np.testing.assert_allclose(xdot[[1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14]],
                               np.asarray(base.dynamics(0.0, x, jnp.zeros(0))), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(xdot[[0, 8]], [0.5, 0.0], atol=1e-12)


def test_filtering_pairs_and_the_stiction_tolerance_of_a_plant_built_in_steps():
    hopper = jd.RigidBodySystem.from_urdf(DATA / "contact_hopper.urdf", floating_base=True, stiction_tolerance=0.02)
    hopper = hopper.with_collision_geometry("left_shin", Sphere(0.03), translation=(0, 0, -0.2), name="l")
    hopper = hopper.with_collision_geometry("right_shin", Sphere(0.03), translation=(0, 0, -0.2), name="r")
    hopper = hopper.with_ground()
    assert float(hopper.contact.stiction_tolerance) == 0.02   # not Drake's default: the plant's own
    pairs = lambda p: {(p.contact.names[a], p.contact.names[b]) for _, _, ia, ib in p.contact.groups  # noqa: E731
                       for a, b in zip(ia, ib)}
    assert pairs(hopper) == {("l", "r"), ("l", "ground"), ("r", "ground")}
    assert pairs(hopper.without_collisions_between("left_shin", "right_shin")) == {("l", "ground"), ("r", "ground")}
    assert pairs(hopper.without_collisions_between(["left_shin", "right_shin", "world"])) == set()
    with pytest.raises(ValueError, match="no link 'left_foot_typo'"):
        hopper.without_collisions_between("left_foot_typo")


def test_a_non_convex_mesh_collides_through_its_hull_when_asked(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    trimesh.creation.torus(major_radius=0.3, minor_radius=0.05).export(tmp_path / "ring.stl")
    (tmp_path / "ring.urdf").write_text(
        '<robot name="ring"><link name="ring"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.02" '
        'ixy="0" ixz="0" iyz="0"/></inertial><collision><geometry><mesh filename="ring.stl"/></geometry></collision>'
        '</link></robot>')
    ring = jd.RigidBodySystem.from_urdf(tmp_path / "ring.urdf", floating_base=True, contact=True, mesh_hulls=True)
    ring = ring.with_ground()
    x = jnp.array([0.0, 0.0, 0.049, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0])   # lying flat, 1 mm into the floor
    res = ring.contact_results(x)
    depths = np.asarray(res.depth)[np.asarray(res.active)]
    assert len(depths) >= 3   # its hull's bottom rim rests on several vertices
    np.testing.assert_allclose(depths.max(), 0.001, rtol=1e-6)   # the lowest vertices: -0.05 (mesh file precision)


def test_contact_results_of_a_resting_ball_are_k_times_depth():
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground(
        material=_material(1e6, 50.0, 0.8, 0.6))
    x = jnp.array([0.0, 0.0, 0.0995, 0, 0, 0, 1, 0.0, 0.0, 0.0, 0, 0, 0])   # 0.5 mm deep, at rest
    res = ball.contact_results(x)
    k = 3e4 * 1e6 / (3e4 + 1e6)   # the URDF's 3e4 in series with the floor's 1e6
    np.testing.assert_allclose(np.asarray(res.normal_force), [k * 5e-4], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(res.force), [[0.0, 0.0, -k * 5e-4]], atol=1e-9)  # on the floor (B)
    np.testing.assert_allclose(np.asarray(res.point), [[0.0, 0.0, -2.5e-4]], atol=1e-15)   # the witnesses' midpoint
    assert ball.contact.names[res.geometry_a[0]] == "ball_surface" and ball.contact.names[res.geometry_b[0]] == "ground"


def test_the_stiff_linearization_is_the_contact_springs_dampers_and_friction_slopes():
    hopper = _ours("hopper_landing")
    x = jnp.asarray(_random_state("hopper_landing", hopper, np.random.default_rng(3)))
    # D is the contact force's derivative in v, exactly: points, normals and Jacobians depend on q
    # alone; on the hopper landing with spheres on every leg link too (36 candidates, of which
    # the deepest 16 are summed)
    spheres = hopper
    for i, link in enumerate(("left_thigh", "left_shin", "right_thigh", "right_shin") * 2):
        spheres = spheres.with_collision_geometry(link, jd.geometry.Sphere(0.01 + 0.005 * i), translation=(0, 0.02 * i, 0),
                                                  name=f"extra{i}")
    touching = spheres.contact_results(x)
    assert 1 <= int(jnp.sum(touching.active)) and len(touching.depth) > 16 + int(jnp.sum(touching.active))
    _the_damping_matrix_is_exact(spheres, x)
    # a frictionless ball at rest on a half-space, moved: the force's line passes through the centre
    # and nothing moves, so what K leaves out (the motion of the points and Jacobians) is zero; turned:
    # the base's force in its own axes turns, a term of the force's size (here ~40 N) left out
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground(
        material=_material(1e6, 50.0, 0.0, 0.0))
    quat = np.random.default_rng(4).normal(size=4)
    q = jnp.concatenate([jnp.array([0.1, -0.2, 0.098]), jnp.asarray(quat / np.linalg.norm(quat))])
    v = jnp.zeros(6)
    K, D = _force_derivatives(ball, q, v)
    along = lambda e: jax.jvp(lambda q: ball.contact_force(q, v), (q,),  # noqa: E731
                              (jd.multibody.configuration_derivative(ball.tree, q, e),))[1]
    K_exact = jax.vmap(along, out_axes=1)(jnp.eye(6))
    np.testing.assert_allclose(np.asarray(K[:, :3]), np.asarray(K_exact[:, :3]), rtol=1e-10, atol=1e-6)
    assert float(jnp.max(jnp.abs(K))) > 1e4 and float(jnp.max(jnp.abs(K[:, 3:] - K_exact[:, 3:]))) < 1e2


_force_derivatives = jax.jit(lambda plant, q, v: plant.contact.force_derivatives(plant.tree, q, v))


def _exact_and_stiff(plant, x, columns):
    """The derivatives of the velocity rates in the state's `columns`, exact and of the stiff
    linearization, from one compiled program (op by op, the two `jacfwd`s took seconds)."""
    u, rates = jnp.zeros(0, x.dtype), slice(plant.tree.nq, None)
    return (np.asarray(j, float) for j in jax.jit(lambda x: [
        jax.jacfwd(lambda y, p=p: p.dynamics(0.0, y, u))(x)[rates, columns] for p in (plant, plant.stiff_linearization())])(x))


def _the_damping_matrix_is_exact(plant, x):
    """D, the contact force's derivative in v, equals `jacfwd` of the force."""
    q, v = x[:plant.tree.nq], x[plant.tree.nq:]
    K, D = _force_derivatives(plant, q, v)
    D_exact = jax.jit(jax.jacfwd(lambda v: plant.contact_force(q, v)))(v)
    np.testing.assert_allclose(np.asarray(D), np.asarray(D_exact), rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(D))))


def test_the_stiff_linearization_of_a_ball_rolling_over_a_box_edge_is_the_exact_jacobian():
    """A ball rolling over a box's edge, slipping at half the stiction tolerance (where the
    friction law is steepest): the contact point stays on the edge, the normal turns with the
    ball and C moves along it by half the approach. Before, the matrix's position columns were
    off by their own size (C moved with the ball's centre), and Rosenbrock took 10x the exact
    Jacobian's steps over the edge."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    plant = ball.with_collision_geometry("world", Box(0.4, 0.4, 0.2), translation=(0.0, 0.0, 0.1), name="block")
    n, r, w = np.array([0.6, 0.0, 0.8]), 0.1, 3.0
    centre = np.array([0.2, 0.0, 0.2]) + (r - 5e-4) * n
    omega = np.array([0.0, w, 0.0])
    velocity = np.cross(omega, (r - 2.5e-4) * n) + 5e-5 * np.array([0.8, 0.0, -0.6])   # C rolls, slips v_s / 2
    x = jnp.asarray(np.concatenate([centre, [0, 0, 0, 1], velocity, omega]))
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 3))
    assert np.max(np.abs(exact)) > 1e6   # the friction law's slope: stiff
    np.testing.assert_allclose(stiff, exact, atol=1e-3 * np.max(np.abs(exact)))


def test_the_stiff_linearization_of_a_ball_rolling_along_a_box_edge_is_the_exact_jacobian():
    """Rolling along the edge, C moves with the ball and the normal does not turn (it turns
    only across the edge): the column along the edge was off by 3e-4 of the largest entry, now 1e-6."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    plant = ball.with_collision_geometry("world", Box(0.4, 0.4, 0.2), translation=(0.0, 0.0, 0.1), name="block")
    n, r, depth, speed = np.array([0.6, 0.0, 0.8]), 0.1, 5e-4, 0.5
    omega = -(speed / (r - depth / 2)) * np.cross([0.0, 1.0, 0.0], n)   # C rolls along the edge (y) ...
    velocity = np.array([0.0, speed + 5e-5, 0.0])                        # ... slipping v_s / 2
    x = jnp.asarray(np.concatenate([np.array([0.2, 0.0, 0.2]) + (r - depth) * n, [0, 0, 0, 1], velocity, omega]))
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 3))
    assert np.max(np.abs(exact)) > 1e6
    np.testing.assert_allclose(stiff, exact, atol=1e-5 * np.max(np.abs(exact)))   # 3e-4 before


def test_the_stiff_linearization_of_a_box_sliding_on_a_box_is_the_exact_jacobian(tmp_path):
    """A box sliding on a box welded to the world (A, listed first): the contact points are the
    sliding box's corners, which move with it. Held in the table instead, they coupled the
    box's position to its turning (columns off by up to 2.5e-2 of the largest entry), and the
    W-method took 6152 + 109 steps where the exact Jacobian took 595 + 169
    (a box sliding down a welded slope, rtol 1e-4; now 592 + 162)."""
    (tmp_path / "table.urdf").write_text("""<robot name="table"><link name="world"/>
      <link name="table"><collision><geometry><box size="3 1 0.1"/></geometry></collision></link>
      <joint name="weld" type="fixed"><parent link="world"/><child link="table"/><origin xyz="0 0 -0.05" rpy="0 -0.3 0"/></joint>
      <link name="box"><inertial><mass value="2"/><inertia ixx="0.013" iyy="0.013" izz="0.013" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><box size="0.2 0.2 0.2"/></geometry></collision></link>
      <joint name="free" type="floating"><parent link="world"/><child link="box"/></joint></robot>""")
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "table.urdf", contact=True)
    assert plant.contact.names[0] == "table_collision_0"   # the table is A
    tilt = 0.3
    normal, down = np.array([-np.sin(tilt), 0, np.cos(tilt)]), np.array([-np.cos(tilt), 0, -np.sin(tilt)])
    quaternion = np.array([0.0, -np.sin(tilt / 2), 0.0, np.cos(tilt / 2)])   # turned as the table
    R = np.asarray(jd.multibody._spatial.quaternion_matrix(jnp.asarray(quaternion)))
    centre = (0.1 - 1e-5) * normal + 0.3 * down    # 10 um deep, sliding down at 1 m/s (body frame)
    x = jnp.asarray(np.concatenate([centre, quaternion, R.T @ down, np.zeros(3)]))
    assert int(np.sum(plant.contact_results(x).active)) == 4
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 7))
    assert np.max(np.abs(exact)) > 1e6
    # to 1.4e-6 of the largest entry (the terms the stiff matrix leaves out); 2.5e-2 before
    np.testing.assert_allclose(stiff, exact, atol=1e-5 * np.max(np.abs(exact)))


def test_the_stiff_linearization_of_a_ball_on_a_turning_free_box_is_the_exact_jacobian(tmp_path):
    """A ball pressed against the face of a free box, both spinning, in the air: the face's
    normal turns with the box, and C = O - r n with it. Without that, the box's rotation
    columns were off by 1.6e3 here (1.1e-4 of the largest entry; 1.6% of it where a sphere
    struck a box in the air), and that strike
    took 25554 + 222 W-method steps against the exact Jacobian's 1747 + 233 (now 1863 + 225)."""
    (tmp_path / "pair.urdf").write_text("""<robot name="pair">
      <link name="box"><inertial><mass value="1"/><inertia ixx="0.0017" iyy="0.0017" izz="0.0017" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link>
      <joint name="jbox" type="floating"><parent link="world"/><child link="box"/></joint>
      <link name="ball"><inertial><mass value="0.5"/><inertia ixx="5e-4" iyy="5e-4" izz="5e-4" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><sphere radius="0.05"/></geometry></collision></link>
      <joint name="jball" type="floating"><parent link="world"/><child link="ball"/></joint></robot>""")
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "pair.urdf", contact=True, gravity=False)
    turn = np.array([0.2, -0.3, 0.1, 0.93])
    turn /= np.linalg.norm(turn)
    R = np.asarray(jd.multibody._spatial.quaternion_matrix(jnp.asarray(turn)))
    ball_centre = R @ np.array([0.1 - 2e-6, 0.02, -0.01])   # against the box's +x face, 2 um deep
    state = np.concatenate([[0, 0, 0], turn, ball_centre, [0, 0, 0, 1],
                            [0.1, -0.2, 0.05], [1.0, -2.0, 3.0], [-0.3, 0.1, 0.2], [0.5, 0.0, -1.5]])
    x = jnp.asarray(state)
    assert int(np.sum(plant.contact_results(x).active)) == 1
    exact, stiff = _exact_and_stiff(plant, x, slice(3, 7))   # the box's rotation columns
    assert np.max(np.abs(exact)) > 1e4
    np.testing.assert_allclose(stiff, exact, atol=1e-6 * np.max(np.abs(exact)))


def test_the_stiff_linearization_of_a_cube_twisted_on_a_free_cube_is_the_exact_jacobian(tmp_path):
    """A free cube twisted by 0.3 rad and tilted by 0.02 rad on an equal free cube, both moving:
    most corners of their overlap are where an edge of one crosses an edge of the other. Such a
    point slides along the incident edge as the bodies move, and the normal turns with the
    reference face (the upper cube's). Held in A instead, the position columns were off by up
    to 0.46 of the largest entry where a twisted stack landed, and the W-method took 10x the
    exact Jacobian's steps there (`benchmarks/RESULTS.md`, "A twisted stack of boxes")."""
    plant = _free_cubes(tmp_path, ["lower", "upper"], gravity=False)
    twist, tilt = 0.3, 0.02
    turn = np.asarray(_turned_then_tilted(twist, tilt))
    lowest = 0.1 * (np.cos(tilt) + np.sin(tilt))   # the upper cube's lowest bottom edge, below its centre
    state = np.concatenate([[0.0, 0.0, 0.0, 0, 0, 0, 1], [0.01, -0.02, 0.1 + lowest - 3e-4], turn,
                            [0.1, -0.2, 0.05, 0.3, -0.2, 0.5], [-0.1, 0.3, -0.2, 0.4, 0.1, -0.6]])
    x = jnp.asarray(state)
    assert int(np.sum(plant.contact_results(x).active)) == 2   # where the lowest edge crosses the lower cube's
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 14))
    assert np.max(np.abs(exact)) > 1e8
    # to 4.3e-5 of the largest entry (the weights' own derivatives are left out); 2.9e-3 before
    np.testing.assert_allclose(stiff, exact, atol=2e-4 * np.max(np.abs(exact)))


def test_the_stiff_linearization_of_a_box_landing_nearly_flat_on_a_table_is_the_exact_jacobian(tmp_path):
    """(helper-18's trial) A 0.7-kg box (0.15 x 0.1 x 0.05 m) landing spinning on a larger box
    fixed to the world, tilted by 1.5e-4 rad: the table's face is the contact polygon's
    reference (the box's face, turned, reaches the table's far corners), so n stays put,
    though the box's face normal is within 1e-6 of it too. Turning n with the box made the
    tilt columns wrong by their own size (0.98 of the largest entry), and such landings took
    4.6x the exact Jacobian's steps."""
    (tmp_path / "box.urdf").write_text("""<robot name="box"><link name="box"><inertial><mass value="0.7"/>
      <inertia ixx="0.000729" iyy="0.001458" izz="0.001896" ixy="0" ixz="0" iyz="0"/></inertial>
      <collision><geometry><box size="0.15 0.1 0.05"/></geometry></collision></link></robot>""")
    box = jd.RigidBodySystem.from_urdf(tmp_path / "box.urdf", floating_base=True, contact=True)
    plant = box.with_collision_geometry("world", Box(0.3, 0.3, 0.1), translation=(0.0, 0.0, -0.05), name="table")
    turn = np.array([8.45e-5, -6.0e-5, 0.7712, 0.6366])
    turn /= np.linalg.norm(turn)
    x = jnp.asarray(np.concatenate([[0.0099, -0.0099, 0.025 - 7e-5], turn, [0.18, 0.06, -0.67, -2.5, 7.2, 0.0]]))
    res = plant.contact_results(x)
    assert int(np.sum(res.active)) == 4
    np.testing.assert_allclose(np.asarray(res.normal)[np.asarray(res.active)], [[0.0, 0.0, 1.0]] * 4, atol=1e-15)
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 7))
    assert np.max(np.abs(exact)) > 1e8
    np.testing.assert_allclose(stiff, exact, atol=1e-6 * np.max(np.abs(exact)))   # 2e-8 measured


def test_the_stiff_linearization_of_a_cylinder_rolling_on_its_side_is_the_exact_jacobian(tmp_path):
    """A cylinder lying on the ground, rolling and slipping at half the stiction tolerance:
    its side is curved across the axis, so C stays under the axis (as under a ball); as a
    flat rim point, C moved with the cylinder, and Rosenbrock took 3x the exact Jacobian's
    steps."""
    (tmp_path / "can.urdf").write_text("""<robot name="can">
      <link name="can"><inertial><mass value="2.0"/><inertia ixx="0.01" iyy="0.01" izz="0.005" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><cylinder radius="0.05" length="0.2"/></geometry></collision></link></robot>""")
    can = jd.RigidBodySystem.from_urdf(tmp_path / "can.urdf", floating_base=True, contact=True).with_ground()
    depth, w = 2e-5, 4.0   # lying along the world's y axis (body z), rolling about it
    q = np.array([0.0, 0.0, 0.05 - depth, -np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])
    omega_body = np.array([0.0, 0.0, w])    # about its axis, the world's y; rolling along x (the body's x)
    velocity_body = np.array([(0.05 - depth / 2) * w + 5e-5, 0.0, 0.0])   # C rolls, slipping v_s / 2
    x = jnp.asarray(np.concatenate([q, velocity_body, omega_body]))
    exact, stiff = _exact_and_stiff(can, x, slice(0, 7))   # position and rotation
    assert int(jnp.sum(can.contact_results(x).active)) == 2 and np.max(np.abs(exact)) > 1e6
    # each coordinate's column to 5% of its own size (the turn about the axis: 1.5%; 70% before)
    error = np.abs(stiff - exact) / np.maximum(np.max(np.abs(exact), 0), 1.0)
    assert np.max(error) < 0.05, np.max(error, 0)


def _can_on_its_rim(tilt, azimuth=0.0, where=(0.0, 0.0), depth=2e-5):
    """A can (r 5 cm, 15 cm long) tilted by `tilt` about the horizontal axis at `azimuth`,
    balanced on its lower rim's lowest point sunk `depth`, spinning about its axis and the
    vertical, that point slipping at a twentieth of the stiction tolerance."""
    r, half = 0.05, 0.075
    turn_axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    quaternion = np.concatenate([np.sin(tilt / 2) * turn_axis, [np.cos(tilt / 2)]])   # (x, y, z, w)
    R = np.asarray(jd.multibody._spatial.quaternion_matrix(jnp.asarray(quaternion)))
    axis = R[:, 2]
    down = -(np.array([0.0, 0.0, 1.0]) - axis[2] * axis)
    down /= np.linalg.norm(down)
    lowest = -half * axis + r * down
    omega = 3.0 * axis + np.array([0.0, 0.0, 2.0])
    velocity = -np.cross(omega, lowest) + np.array([5e-6, 0.0, 0.0])
    return np.concatenate([[*where, -lowest[2] - depth], quaternion, R.T @ velocity, R.T @ omega])


def _can_plant(tmp_path):
    (tmp_path / "can.urdf").write_text("""<robot name="can">
      <link name="can"><inertial><mass value="0.8"/><inertia ixx="0.002" iyy="0.002" izz="0.001" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><cylinder radius="0.05" length="0.15"/></geometry></collision></link></robot>""")
    return jd.RigidBodySystem.from_urdf(tmp_path / "can.urdf", floating_base=True, contact=True).with_ground()


def _rotation_column_errors(plant, x):
    exact, stiff = _exact_and_stiff(plant, x, slice(0, 7))
    return np.abs(stiff - exact) / np.maximum(np.max(np.abs(exact), 0), 1.0), exact


def test_the_stiff_linearization_of_a_can_rolling_on_its_rim_is_the_exact_jacobian(tmp_path):
    """A can tilted by 60 degrees, balanced on one rim point and spinning, sticking: C is the
    rim's lowest point, which stays put as the can turns about its axis and swings around the
    rim as it tips sideways. As a flat rim point moving with the can, the matrix's rotation
    columns were 85-100% off, and a can rolling on its rim took 161150 steps for 1.5 s against
    the exact Jacobian's 7191 (now ~8100)."""
    can = _can_plant(tmp_path)
    x = jnp.asarray(_can_on_its_rim(np.pi / 3))
    error, exact = _rotation_column_errors(can, x)
    assert int(np.sum(can.contact_results(x).active)) == 1 and np.max(np.abs(exact[:, 3:])) > 1e5
    assert np.max(error) < 0.05, np.max(error, 0)


def test_a_can_rolling_on_its_rim_on_a_cylinder_listed_before_it_has_the_exact_jacobian(tmp_path):
    """Two cylinders pair in the order of their geometries: a can on the cap of a post listed
    first in the file is B of the pair, and its rolling rim was modelled as a corner moving
    with it (rotation columns 80-290% off)."""
    (tmp_path / "post.urdf").write_text("""<robot name="post"><link name="world"/>
      <link name="post"><collision><origin xyz="0 0 -0.1"/><geometry><cylinder radius="0.5" length="0.2"/></geometry></collision></link>
      <joint name="fix" type="fixed"><parent link="world"/><child link="post"/></joint>
      <link name="can"><inertial><mass value="0.8"/><inertia ixx="0.002" iyy="0.002" izz="0.001" ixy="0" ixz="0" iyz="0"/>
        </inertial><collision><geometry><cylinder radius="0.05" length="0.15"/></geometry></collision></link>
      <joint name="free" type="floating"><parent link="world"/><child link="can"/></joint></robot>""")
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "post.urdf", contact=True)
    assert plant.contact.names[0] == "post_collision_0"   # the post is A
    x = jnp.asarray(_can_on_its_rim(np.pi / 3, azimuth=0.4, where=(0.1, -0.05)))
    error, exact = _rotation_column_errors(plant, x)
    assert int(np.sum(plant.contact_results(x).active)) == 1 and np.max(np.abs(exact[:, 3:])) > 1e5
    assert np.max(error) < 0.05, np.max(error, 0)


def test_a_float32_can_on_its_rim_is_found_to_float32_rounding(tmp_path):
    """The rolling rim point is recognised to the rounding of its witness and of u (float32's
    too): with a float64 margin, 4 of 12 float32 cans tilted by 11-80 degrees within 10 m of
    the origin were taken for flat corners (rotation columns ~100% off)."""
    can = _can_plant(tmp_path)
    can32 = jax.tree.map(lambda leaf: leaf.astype(jnp.float32) if eqx.is_array(leaf) and jnp.issubdtype(
        leaf.dtype, jnp.floating) else leaf, can)
    stiff32 = can32.stiff_linearization()
    jacobians = jax.jit(lambda x: [jax.jacfwd(lambda y, p=p: p.dynamics(0.0, y, jnp.zeros(0, jnp.float32)))(x)[7:, :7]
                                   for p in (can32, stiff32)])
    rng = np.random.default_rng(0)
    for _ in range(12):
        where, azimuth, tilt = rng.uniform(-10, 10, 2), rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.4)
        exact, stiff = (np.asarray(j, float) for j in jacobians(jnp.asarray(_can_on_its_rim(tilt, azimuth, where), jnp.float32)))
        error = np.abs(stiff - exact) / np.maximum(np.max(np.abs(exact), 0), 1.0)
        assert error[:, 4:6].max() < 0.5, (where, azimuth, tilt)


@pytest.mark.slow  # ~8 s; the hopper's case above runs by default
def test_the_stiff_linearization_of_free_bodies_beside_an_arm():
    pusher = _ours("arm_pushing_free_bodies")
    x = jnp.asarray(_random_state("arm_pushing_free_bodies", pusher, np.random.default_rng(5)))
    x = x.at[4].set(0.075).at[11].set(0.055).at[16:].multiply(0.1)   # ball and puck touch, slowly
    assert int(jnp.sum(pusher.contact_results(x).active)) >= 2
    _the_damping_matrix_is_exact(pusher, x)


DUMBBELL_START = np.asarray([0.0, 0.0, 0.3, 0.1, 0.2, 0.0, 0.97467943, 0.5, 0.0, 0.0, 1.0, -2.0, 0.5]) / np.r_[
    1, 1, 1, [np.linalg.norm([0.1, 0.2, 0.0, 0.97467943])] * 4, np.ones(6)]


def _dumbbell_final(x0, solver, rtol):
    """The dumbbell rolling down its slope onto the floor (onsets and releases), at 0.6 s."""
    return jd.simulate(_ours("dumbbell_on_a_slope"), (0.0, 0.6), x0, solver=solver, rtol=rtol, atol=rtol / 10,
                       max_steps=40000, dense=False, autodiff="forward").final_state


def test_a_rosenbrock_step_on_the_stiff_linearization_converges():
    dumbbell, x0 = _ours("dumbbell_on_a_slope"), jnp.asarray(DUMBBELL_START)
    np.testing.assert_array_equal(np.asarray(dumbbell.stiff_linearization().dynamics(0.0, x0, jnp.zeros(0))),
                                  np.asarray(dumbbell.dynamics(0.0, x0, jnp.zeros(0))))   # the same values
    reference = _dumbbell_final(x0, "dopri5", 1e-11)
    w_method = jd.simulation.Rosenbrock23(jacobian="stiff")
    errors = [float(jnp.max(jnp.abs(_dumbbell_final(x0, w_method, rtol) - reference))) for rtol in (1e-6, 1e-8)]
    assert errors[0] < 2e-4 and errors[1] < 2e-5 and errors[1] < errors[0] / 5, errors   # second order, any matrix


@pytest.mark.slow   # 37 s
def test_forward_mode_through_the_stiff_linearization_equals_dopri5s_sensitivities():
    x0 = jnp.asarray(DUMBBELL_START)   # the custom derivative, differentiated once more
    J = jax.jit(jax.jacfwd(functools.partial(_dumbbell_final, solver=jd.simulation.Rosenbrock23(jacobian="stiff"),
                                             rtol=1e-8)))(x0)
    # the reference at rtol 1e-11: at 1e-10 dopri5's own sensitivity of one angular velocity to
    # the start's height is off by 0.017 (7.313 against 7.330 by central differences at 1e-12)
    J_reference = jax.jit(jax.jacfwd(functools.partial(_dumbbell_final, solver="dopri5", rtol=1e-11)))(x0)
    np.testing.assert_allclose(np.asarray(J), np.asarray(J_reference), atol=1e-3 * float(jnp.max(jnp.abs(J_reference))))


@pytest.mark.gpu
def test_float32_contact_dynamics_on_a_gpu_equal_float64_to_float32_rounding():
    """A GPU's default float32 products are TF32 (10 bits): the hopper's contact dynamics were
    off by 1e-3 to 1 in 3 of 4 states (H200). At full float32 precision, as on the host, all
    but a few states with near-cancelling contact terms agree to 1e-3 of max(|xdot|, 1)."""
    plant = _ours("hopper_landing")
    rng = np.random.default_rng(0)
    xs = np.stack([_random_state("hopper_landing", plant, rng) for _ in range(4096)])
    single = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, plant)

    def dynamics(plant, xs):
        return jax.jit(jax.vmap(lambda x: plant.dynamics(0.0, x, jnp.zeros(plant.num_inputs, x.dtype))))(xs)

    gpu = np.asarray(dynamics(single, jax.device_put(jnp.asarray(xs, jnp.float32), jax.devices("gpu")[0])))
    with jax.default_device(jax.devices("cpu")[0]):
        cpu = np.asarray(dynamics(plant, jnp.asarray(xs, jnp.float64)))
    error = np.abs(gpu - cpu) / np.maximum(np.abs(cpu), 1.0)
    assert np.median(error) < 1e-6 and np.sum(error.max(1) > 1e-3) <= 0.005 * len(xs)


def test_two_free_bodies_land_and_rest_under_rosenbrock_at_their_closed_form_depths(tmp_path):
    """A crate falls 3 m beside a ball: Rosenbrock's over-long step through the crate's
    landing shot the ball to 8e7 m, a finite y1 whose vector field is NaN, so a NaN error
    estimate, which grew the rejected step (10x, clipped at tf) until max_steps. A NaN error
    estimate is a rejection that shrinks the step. At rest each body sinks m g / k: the ball
    on one contact, the crate on its four lower corners (k: the geometries' 1e6 N/m in series)."""
    (tmp_path / "two.urdf").write_text("""<robot name="two">
      <link name="crate"><inertial><mass value="1.5"/><inertia ixx="0.01" iyy="0.0125" izz="0.0125" ixy="0" ixz="0" iyz="0"/></inertial>
        <collision><geometry><box size="0.3 0.2 0.2"/></geometry></collision></link>
      <link name="ball"><inertial><mass value="0.5"/><inertia ixx="5e-4" iyy="5e-4" izz="5e-4" ixy="0" ixz="0" iyz="0"/></inertial>
        <collision><geometry><sphere radius="0.05"/></geometry></collision></link></robot>""")
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "two.urdf", floating_base=True, contact=True).with_ground()
    x0 = jnp.zeros(26).at[6].set(1.0).at[13].set(1.0).at[2].set(3.0).at[7].set(1.0).at[9].set(0.5)
    k, g = 1e6 / 2, 9.81
    x = jd.simulate(plant, (0.0, 1.5), x0, solver=jd.simulation.Rosenbrock23(jacobian="stiff"), dense=False).final_state
    np.testing.assert_allclose([x[2], x[9]], [0.1 - 1.5 * g / (4 * k), 0.05 - 0.5 * g / k], atol=1e-10)
    np.testing.assert_allclose(x[14:], 0.0, atol=1e-10)


def test_a_ground_under_unread_collisions_warns_and_traced_materials_name_the_remedy():
    """A file's <collision> elements are read only with contact=True: a ground added without
    them touches nothing (a dropped ball fell through it), so it warns; a material built from
    traced values (inside jax.grad) is named, with the leaf to replace instead; a state of the
    wrong size is named before an XLA gather error."""
    with pytest.warns(UserWarning, match=r"1 <collision> element\(s\), not read.*contact=True"):
        jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True).with_ground()
    plant = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)

    def slide(mu):
        return plant.with_ground(material=ContactMaterial(mu_static=mu, mu_dynamic=mu)).contact.mu_static[0]

    with pytest.raises(GeometryError, match=r"mu_static is traced.*eqx.tree_at\(lambda p: p.contact.mu_static"):
        jax.grad(slide)(0.3)
    with pytest.raises(ValueError, match=r"x must be one state \[q; v\] of 13 coordinates \(7 q, 6 v\), got shape \(5,\)"):
        plant.with_ground().contact_results(jnp.zeros(5))


def test_a_ball_dropped_on_a_small_sphere_rests_on_it_instead_of_passing_through():
    """A free fall is a quadratic, which Rosenbrock23 and Dormand-Prince integrate exactly:
    their error estimates vanish and the steps grew tenfold until one carried the ball through
    a 10-cm sphere between two evaluations of the force (it fell to z = -10.4 m with every
    solver). Steps are bounded so that no geometry moves half the thinnest one's thickness;
    the ball comes to rest on the sphere's top, sunk m g / k (the two stiffnesses in series)."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True)
    ball = ball.with_collision_geometry("world", Sphere(0.05))
    k_a, k_b = np.asarray(ball.contact.stiffness)
    rest = 0.05 + 0.1 - float(ball.tree.mass[0]) * 9.81 / (k_a * k_b / (k_a + k_b))
    x0 = jnp.array([0.0, 0.0, 0.6, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0])
    for solver in (jd.simulation.Rosenbrock23(jacobian="stiff"), "dopri5"):
        x = jd.simulate(ball, (0.0, 1.5), x0, solver=solver, dense=False).final_state
        np.testing.assert_allclose(x[2], rest, atol=1e-9)
        np.testing.assert_allclose(x[7:], 0.0, atol=1e-7)
    # the bound: no point of the moving ball (radius 0.1 at its origin) travels delta / 2 =
    # 0.05 m (the small sphere's thickness 0.1) under speed s + gravity
    s, g = 2.0 + 0.1 * 3.0, 9.81
    x = jnp.zeros(13).at[6].set(1.0).at[7].set(2.0).at[10:].set(1.0)
    h = float(ball.step_size_bound(0.0, x))
    np.testing.assert_allclose(s * h + 0.5 * g * h ** 2, 0.05, rtol=1e-12)


def test_a_fixed_step_longer_than_the_step_bound_is_shortened_to_it():
    """RK4 at dt = 25 ms carried a ball thrown at 10 m/s through a 1-cm wall in one step (and
    reported success, 3 m beyond it); its steps are now cut to the contact's bound, and the
    ball stays in front of the wall."""
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True,
                                       stiction_tolerance=1e-2)
    ball = ball.with_collision_geometry("world", Box(0.01, 2.0, 4.0), translation=(0.5, 0.0, 0.0), name="wall")
    traj = jd.simulate(ball, (0.0, 0.3), jnp.array([0.0, 0.0, 0.0, 0, 0, 0, 1, 10.0, 0, 0, 0, 0, 0]), solver="rk4",
                       dt=0.025)
    assert float(jnp.max(traj.eval(jnp.linspace(0.0, 0.3, 61))[:, 0])) < 0.5 - 0.005 - 0.1 + 0.02   # < 2 cm deep
    assert int(traj.num_steps) > 0.3 / 0.025 * 10


def test_the_step_bound_counts_a_prismatic_extension_and_holds_in_diagrams_and_hybrid_modes(tmp_path):
    """A ball on a slider extended 2 m from a yaw joint turning at 5 rad/s, a 1-cm wall across
    its path: the bound counts the extension (at q = 0 it saw 5 cm of lever, and the ball passed
    through the wall). The ball stops at the wall; a feedback diagram and a hybrid mode keep the
    plant's bound."""
    inertial = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'
    (tmp_path / "slider.urdf").write_text(f"""<robot name="slider">
      <link name="base">{inertial}</link>
      <joint name="yaw" type="continuous"><parent link="world"/><child link="base"/><axis xyz="0 0 1"/></joint>
      <link name="tip">{inertial}<collision><geometry><sphere radius="0.05"/></geometry></collision></link>
      <joint name="ext" type="prismatic"><parent link="base"/><child link="tip"/><axis xyz="1 0 0"/>
        <limit lower="1.999" upper="2.0" effort="100" velocity="10"/></joint></robot>""")
    arm = jd.RigidBodySystem.from_urdf(tmp_path / "slider.urdf", contact=True).with_collision_geometry(
        "world", Box(0.01, 0.4, 0.4), translation=(0.0, 2.0, 0.0))
    x0 = jnp.array([0.0, 2.0, 5.0, 0.0])
    g, delta, s = 9.81, 0.01, 5.0 * (2.0 + 0.05)   # yaw rate x (the extension + the ball's radius)
    np.testing.assert_allclose(float(arm.step_size_bound(0.0, x0)), delta / (s + np.sqrt(s * s + g * delta)), rtol=1e-12)
    x = jd.simulate(arm, (0.0, 0.5), x0, solver=jd.simulation.Rosenbrock23(jacobian="stiff"), rtol=1e-3).final_state
    assert x[0] < np.pi / 2 - 0.02 and abs(x[2]) < 0.1   # stopped at the wall, not through it
    damper = jd.System.from_functions(output=lambda t, x, u: -u[2:], num_states=0, num_inputs=4, num_outputs=2)
    for composed in (jd.feedback(arm, damper), jd.HybridSystem([arm], [])):
        assert composed.bounds_steps
        np.testing.assert_allclose(composed.step_size_bound(0.0, x0), arm.step_size_bound(0.0, x0), rtol=1e-15)
