"""MuJoCo models as systems (MJX): C MuJoCo's own `mj_step` is the oracle; vmap equals single
runs; gradients against central differences; discrete LQR of the linearized update balances
the cart-pole. (MJX's step compiles for seconds: the batched, differentiated and LQR tests are
`slow`.)"""

import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd

mujoco = pytest.importorskip("mujoco")
pytest.importorskip("mujoco.mjx")
DATA = pathlib.Path(__file__).parent / "data"
PENDULUM = """<mujoco model="pendulum"><option timestep="0.002"/>
  <worldbody><body name="arm"><joint name="theta" type="hinge" axis="0 1 0" damping="0.05"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/></body></worldbody>
  <actuator><motor name="tau" joint="theta" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


def c_mujoco(model, x0, controls, warmstart=True):
    """States after each of len(controls) mj_step calls (C MuJoCo, float64)."""
    if not warmstart:
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_WARMSTART
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = x0[: model.nq], x0[model.nq:]
    states = []
    for u in controls:
        data.ctrl[:] = u
        mujoco.mj_step(model, data)
        states.append(np.concatenate([data.qpos, data.qvel]))
    return np.asarray(states)


@pytest.mark.parametrize("source", [PENDULUM, pytest.param(DATA / "mj_cartpole.xml", marks=pytest.mark.slow)],
                         ids=["pendulum", "cartpole"])  # the cart-pole: 21 s, the same check on a second model
def test_a_thousand_steps_equal_c_mujoco(source):
    system = jd.MujocoSystem.from_xml(source)
    dt, n = system.sample_time, 1000
    x0 = np.array(system.initial_state()) + 0.3
    controls = 0.8 * np.sin(3.0 * dt * np.arange(n))[:, None] * np.ones((1, system.num_inputs))
    expected = c_mujoco(system.mj_model, x0, controls)
    tape = jd.Trajectory.from_samples(dt * np.arange(n), controls, interpolation="zoh")
    traj = jd.simulate(system, (0.0, n * dt), jnp.asarray(x0), inputs=tape)
    np.testing.assert_allclose(np.asarray(traj.final_state), expected[-1], rtol=0, atol=1e-10)
    samples = np.asarray(traj.state(jnp.asarray(dt * np.arange(1, n + 1))))
    np.testing.assert_allclose(samples, expected, rtol=0, atol=1e-10)


@pytest.mark.slow  # MuJoCo Warp's kernels compile for ~50 s on a CPU the first time (cached after)
@pytest.mark.parametrize("source", [PENDULUM, DATA / "mj_cartpole.xml"], ids=["pendulum", "cartpole"])
def test_steps_on_mujoco_warp_equal_c_mujoco_to_float32_rounding(source):
    """impl="warp" (MuJoCo Warp, float32): a thousand steps under a sine input equal C MuJoCo's
    float64 steps to 2e-5 (the pendulum measured 2.8e-7, the cart-pole 5.5e-6 on a CPU: float32
    rounding over 1000 steps); a vmapped batch equals its members run one by one."""
    pytest.importorskip("mujoco_warp")
    system = jd.MujocoSystem.from_xml(source, impl="warp")
    dt, n = system.sample_time, 1000
    x0 = np.array(system.initial_state()) + 0.3
    controls = 0.8 * np.sin(3.0 * dt * np.arange(n))[:, None] * np.ones((1, system.num_inputs))
    expected = c_mujoco(system.mj_model, x0, controls)
    tape = jd.Trajectory.from_samples(dt * np.arange(n), controls, interpolation="zoh")
    on_warp = jd.simulate(system, (0.0, n * dt), jnp.asarray(x0), inputs=tape).final_state
    np.testing.assert_allclose(np.asarray(on_warp), expected[-1], rtol=0, atol=2e-5)
    starts = jnp.asarray(x0) + 0.01 * jnp.arange(4)[:, None]
    final = lambda x: jd.simulate(system, (0.0, 100 * dt), x, dense=False).final_state  # noqa: E731
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(final))(starts)), np.stack([final(x) for x in starts]))


def test_the_implementation_is_checked_and_warp_sizes_need_warp():
    with pytest.raises(ValueError, match="impl must be 'jax'"):
        jd.MujocoSystem.from_xml(PENDULUM, impl="cuda")
    with pytest.raises(ValueError, match="with impl='warp' only"):
        jd.MujocoSystem.from_xml(PENDULUM, warp_sizes={"naconmax": 100})
    import importlib.util
    if importlib.util.find_spec("mujoco_warp") is None:
        with pytest.raises(ImportError, match=r"jaxdrake\[mujoco-warp\]"):
            jd.MujocoSystem.from_xml(PENDULUM, impl="warp")
    else:
        with pytest.raises(ValueError, match="naconmax, naccdmax, njmax, nvmax"):
            jd.MujocoSystem.from_xml(PENDULUM, impl="warp", warp_sizes={"nconmax": 100})


def test_contacts_equal_c_mujoco_to_the_solver_tolerance():
    """A spinning ball dropped onto a plane, converged solver (MuJoCo's defaults: tolerance
    1e-8): MJX and C MuJoCo (warm start off in both) agree to 1e-6 over 400 steps (2 s),
    through the impact and the rolling contact; before the contact, to rounding (1e-14)."""
    system = jd.MujocoSystem.from_xml((DATA / "mj_ball.xml").read_text().replace(
        'iterations="1" ls_iterations="4"', ""))
    x0 = np.array(system.initial_state())
    x0[7], x0[11] = 0.5, 1.0   # moving along x, spinning about y
    expected = c_mujoco(system.mj_model, x0, np.zeros((400, 0)), warmstart=False)
    traj = jd.simulate(system, (0.0, 400 * system.sample_time), jnp.asarray(x0))
    ours = np.asarray(traj.state(jnp.asarray(system.sample_time * np.arange(1, 401))))
    np.testing.assert_allclose(ours[:80], expected[:80], rtol=0, atol=1e-14)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-6)
    assert expected[-1, 2] == pytest.approx(0.1, abs=1e-3)  # resting on the plane


def test_a_hopper_with_contacts_under_a_jaxdrake_controller_equals_c_mujoco():
    """The sprung one-legged hopper of tests/data, its leg force from a jaxdrake static
    controller in feedback (thrust while rising in stance, the leg held in flight): 1000 steps
    (2 s, touch-downs and lift-offs) equal C MuJoCo under the same control law,
    evaluated in NumPy each step, to 1e-9."""
    hopper = jd.MujocoSystem.from_xml(DATA / "mj_hopper.xml")

    def thrust(height, leg, rise, legdot, where, clip):
        return where(height - leg < 1e-3, where(rise > 0, clip(3000.0 * (0.2 - height) + 150.0, 0.0, 400.0), 0.0),
                     -300.0 * leg - 20.0 * legdot)

    controller = jd.System.from_functions(
        output=lambda t, x, u: jnp.atleast_1d(thrust(*u, where=jnp.where, clip=jnp.clip)), num_states=0, num_inputs=4)
    x0 = np.array([0.1, 0.0, 0.0, 0.0])
    dt, n = hopper.sample_time, 1000
    traj = jd.simulate(jd.feedback(hopper, controller), (0.0, n * dt), jnp.asarray(x0))
    ours = np.asarray(traj.state(jnp.asarray(dt * np.arange(1, n + 1))))
    model = hopper.mj_model
    data = mujoco.MjData(model)
    data.qpos[:] = x0[:2]
    expected = []
    for _ in range(n):
        data.ctrl[:] = thrust(*data.qpos, *data.qvel, where=np.where, clip=np.clip)
        mujoco.mj_step(model, data)
        expected.append(np.concatenate([data.qpos, data.qvel]))
    expected = np.asarray(expected)
    foot = expected[:, 0] - expected[:, 1]
    assert np.sum(np.diff((foot < 1e-3).astype(int)) == 1) >= 2 and foot.max() > 0.05  # it hops
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-9)


def heavier_hand(model):
    model.body_mass[4] *= 1.7
    model.body_inertia[4] *= 1.7


def moved_and_resized(model):
    model.body_pos[2] += [0.1, 0.0, 0.05]
    model.geom_size[1] *= 1.3
    model.qpos0[0] = 0.2


@pytest.mark.parametrize("change", [heavier_hand, pytest.param(moved_and_resized, marks=pytest.mark.slow)])  # ~6 s each
def test_derived_constants_equal_c_mujocos_mj_set_const(change):
    """Slide, hinge, ball and free joints, a welded body, fixed and spatial tendons, motor and
    muscle actuators, a connect constraint, tracking camera and light: the model's arrays
    changed, its derived constants (stale in the MJX model made from it) recomputed in JAX equal
    those of C MuJoCo's mj_setConst; under vmap over the changed body's mass and inertia too."""
    from mujoco import mjx

    from jaxdrake.mujoco import DERIVED_CONSTANTS, set_const

    path = str(DATA / "mj_set_const.xml")
    scales = (1.0, 0.5, 2.0)
    changed = [mujoco.MjModel.from_xml_path(path) for _ in scales]
    for k, model in zip(scales, changed):
        change(model)
        model.body_mass[4] *= k
        model.body_inertia[4] *= k
    stale = mjx.put_model(changed[0])
    ours = jax.jit(jax.vmap(lambda k: set_const(stale.replace(body_mass=stale.body_mass.at[4].multiply(k),
                                                              body_inertia=stale.body_inertia.at[4].multiply(k)),
                                                changed[0])))(jnp.asarray(scales))
    for model in changed:
        mujoco.mj_setConst(model, mujoco.MjData(model))
    for field in DERIVED_CONSTANTS:
        for i, model in enumerate(changed):
            computed = getattr(ours, field)[i]
            expected = np.asarray(getattr(model, field)).reshape(computed.shape)
            np.testing.assert_allclose(computed, expected, rtol=1e-12, atol=1e-12, err_msg=f"{field} x{scales[i]}")
    moved = [f for f in DERIVED_CONSTANTS if not np.allclose(getattr(stale, f), np.reshape(getattr(changed[0], f), np.shape(getattr(stale, f))))]
    assert len(moved) >= 4, moved  # the change matters


LIMITED = """<mujoco model="limited"><option timestep="0.002"/>
  <worldbody><body name="upper"><joint name="shoulder" type="hinge" axis="0 1 0" range="-0.5 0.5"
      limited="true" frictionloss="0.05"/><geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="1"/>
    <body name="lower" pos="0 0 -0.5"><joint name="elbow" type="hinge" axis="0 1 0" range="-0.3 0.3" limited="true"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02" mass="0.5"/></body></body></worldbody></mujoco>"""


def test_a_replaced_mass_steps_as_c_mujoco_after_mj_set_const():
    """A double pendulum against its joint limits (constraints scaled by dof_invweight0), the
    lower link 3 times heavier by eqx.tree_at: 1.5 s equal C MuJoCo with mj_setConst applied to
    the same change (the compiled constants kept were 2e-2 off)."""
    import equinox as eqx

    system = jd.MujocoSystem.from_xml(LIMITED)
    lower = system.mj_model.body("lower").id
    heavier = eqx.tree_at(lambda s: (s.model.body_mass, s.model.body_inertia), system,
                          (system.model.body_mass.at[lower].multiply(3.0),
                           system.model.body_inertia.at[lower].multiply(3.0)))
    x0 = np.array([0.0, 0.0, 1.0, 1.0])
    steps = 750

    def c_run(set_const):
        model = mujoco.MjModel.from_xml_string(LIMITED)
        model.body_mass[lower] *= 3.0
        model.body_inertia[lower] *= 3.0
        if set_const:
            mujoco.mj_setConst(model, mujoco.MjData(model))
        return c_mujoco(model, x0, np.zeros((steps, 0)), warmstart=False)[-1]

    ours = jd.simulate(heavier, (0.0, steps * system.sample_time), jnp.asarray(x0), dense=False).final_state
    np.testing.assert_allclose(ours, c_run(True), rtol=0, atol=1e-10)
    assert np.max(np.abs(c_run(False) - c_run(True))) > 1e-2


@pytest.mark.slow
def test_vmap_over_states_and_masses_equals_single_runs():
    system = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml")
    run = lambda s, x0: jd.simulate(s, (0.0, 1.0), x0, dense=False).final_state
    x0s = jnp.asarray(np.random.default_rng(0).uniform(-0.5, 0.5, (1000, 4)))
    batch = jax.jit(jax.vmap(lambda x0: run(system, x0)))(x0s)
    for i in (0, 517, 999):
        np.testing.assert_allclose(batch[i], run(system, x0s[i]), rtol=0, atol=1e-14)
    pole = system.mj_model.body("pole").id

    def run_mass(m):
        heavier = eqx_set_mass(system, pole, m)
        return run(heavier, x0s[0])
    masses = jnp.linspace(0.05, 0.5, 8)
    per_mass = jax.jit(jax.vmap(run_mass))(masses)
    np.testing.assert_allclose(per_mass[5], run_mass(masses[5]), rtol=0, atol=1e-14)
    assert not np.allclose(per_mass[0], per_mass[-1])


def eqx_set_mass(system, body, mass):
    import equinox as eqx
    return eqx.tree_at(lambda s: s.model.body_mass, system, system.model.body_mass.at[body].set(mass))


@pytest.mark.slow
def test_gradients_of_rollouts_match_central_differences():
    """Contact-free (the cart-pole, w.r.t. x0 and the pole's mass) and with contacts (the
    ball with one solver iteration, w.r.t. its initial height and speed)."""
    cartpole = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml")
    pole = cartpole.mj_model.body("pole").id

    def loss(x0, mass):
        s = eqx_set_mass(cartpole, pole, mass)
        return jnp.sum(jd.simulate(s, (0.0, 0.5), x0, dense=False).final_state ** 2)

    x0, mass = jnp.array([0.1, 0.2, 0.0, -0.3]), 0.1
    gx, gm = jax.grad(loss, argnums=(0, 1))(x0, mass)
    eps = 1e-6
    fd_x = np.array([(loss(x0 + eps * e, mass) - loss(x0 - eps * e, mass)) / (2 * eps) for e in np.eye(4)])
    np.testing.assert_allclose(gx, fd_x, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(gm, (loss(x0, mass + eps) - loss(x0, mass - eps)) / (2 * eps), rtol=1e-5)

    ball = jd.MujocoSystem.from_xml(DATA / "mj_ball.xml")   # iterations="1": differentiable contacts

    def height_after_bounce(z0, vx):
        x = jnp.asarray(ball.initial_state()).at[2].set(z0).at[7].set(vx)
        final = jd.simulate(ball, (0.0, 0.6), x, dense=False).final_state
        return final[0] + final[2]

    g = jax.grad(height_after_bounce, argnums=(0, 1))(0.6, 0.4)
    fd = [(height_after_bounce(0.6 + eps, 0.4) - height_after_bounce(0.6 - eps, 0.4)) / (2 * eps),
          (height_after_bounce(0.6, 0.4 + eps) - height_after_bounce(0.6, 0.4 - eps)) / (2 * eps)]
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_grad_goes_through_the_full_contact_solver(tmp_path):
    """MJX's solver with its default iterations is a while_loop: the default reverse mode
    differentiates it by forward sensitivities (central differences agree)."""
    xml = (DATA / "mj_ball.xml").read_text().replace(' iterations="1" ls_iterations="4"', "")
    (tmp_path / "ball.xml").write_text(xml)
    ball = jd.MujocoSystem.from_xml(tmp_path / "ball.xml")

    def height_after_bounce(z0, vx):
        x = jnp.asarray(ball.initial_state()).at[2].set(z0).at[7].set(vx)
        final = jd.simulate(ball, (0.0, 0.6), x, dense=False).final_state
        return final[0] + final[2]

    g = jax.grad(height_after_bounce, argnums=(0, 1))(0.6, 0.4)
    eps = 1e-6
    fd = [(height_after_bounce(0.6 + eps, 0.4) - height_after_bounce(0.6 - eps, 0.4)) / (2 * eps),
          (height_after_bounce(0.6, 0.4 + eps) - height_after_bounce(0.6, 0.4 - eps)) / (2 * eps)]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)


@pytest.mark.slow
def test_lqr_of_the_linearized_update_balances_the_cart_pole():
    cartpole = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml")
    upright, u0 = jnp.zeros(4), jnp.zeros(1)
    result = jd.control.lqr(cartpole, jnp.diag(jnp.array([1.0, 10.0, 1.0, 1.0])), jnp.eye(1), x0=upright, u0=u0)
    closed = jd.feedback(cartpole, result.controller)
    traj = jd.simulate(closed, (0.0, 8.0), jnp.array([0.0, 0.15, 0.0, 0.0]))
    angles = np.asarray(traj.state(jnp.linspace(0.0, 8.0, 801)))[:, 1]
    assert np.max(np.abs(angles)) < 0.2 and abs(angles[-1]) < 1e-3  # caught and settled upright
    np.testing.assert_allclose(traj.final_state, 0.0, atol=1e-2)
    assert cartpole.output_frame.coordinates == ("slider", "hinge", "sliderdot", "hingedot")
    sensed = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml", output="sensors")
    np.testing.assert_allclose(sensed.output(0.0, jnp.array([0.2, -0.4, 1.0, 2.0]), u0), [0.2, -0.4], atol=1e-15)
    assert sensed.output_frame.coordinates == ("cart_position", "pole_angle")


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_with_the_warm_start_in_the_state_steps_equal_mjxs_own_loop():
    """One solver iteration (MuJoCo Playground's setting): MJX's own loop warm-starts each
    solve from the previous accelerations; `warm_start=True` carries them in the state, and the
    bouncing, rolling ball then equals `lax.scan` over `mjx.step` to 5e-6 after 300 steps (the
    two programs round differently; the unconverged solver amplifies it in the out-of-plane
    components, which stay at 1e-5 of noise), where a cold start each step
    differs by 1e-3 and more. (C MuJoCo's single iteration takes another line search: not
    comparable unconverged.)"""
    from mujoco import mjx

    ball = jd.MujocoSystem.from_xml(DATA / "mj_ball.xml", warm_start=True)
    assert ball.num_states == 7 + 6 + 6 and ball.state_frame.coordinates[-1] == "ball_wz_warmstart"
    x0 = np.array(ball.initial_state())
    x0[7], x0[11] = 0.5, 1.0
    data = mjx.make_data(ball.model).replace(qpos=jnp.asarray(x0[:7]), qvel=jnp.asarray(x0[7:13]))
    data = jax.jit(lambda d: jax.lax.scan(lambda d, _: (mjx.step(ball.model, d), None), d, None, length=300)[0])(data)
    traj = jd.simulate(ball, (0.0, 300 * ball.sample_time), jnp.asarray(x0))
    expected = np.concatenate([data.qpos, data.qvel, data.qacc_warmstart])
    np.testing.assert_allclose(np.asarray(traj.final_state), expected, rtol=0, atol=5e-6)
    assert expected[2] < 0.15  # it has landed
    cold = jd.MujocoSystem.from_xml(DATA / "mj_ball.xml")
    final_cold = jd.simulate(cold, (0.0, 300 * cold.sample_time), jnp.asarray(x0[:13])).final_state
    assert np.max(np.abs(np.asarray(final_cold) - expected[:13])) > 1e-3


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_mujoco_renderer_frames_put_the_cart_where_the_camera_sees_it(tmp_path):
    """MuJoCo's own renderer draws the frames (offscreen, EGL): the blue cart's pixel centroid
    lies within 2 px of the pinhole projection of its front face's centre through the model's
    side camera (fovy 45 degrees, 3 m away); a saved .gif decodes to round(T fps) frames equal to
    direct renders of x(t_k)."""
    import imageio.v3 as iio

    cartpole = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml")
    vis = jd.viz.visualizer_for(cartpole)
    assert isinstance(vis, jd.viz.MujocoVisualizer)
    vis = jd.viz.MujocoVisualizer(cartpole, camera="side")
    focal = (vis.height / 2) / np.tan(np.radians(45.0) / 2)
    states = np.array([[x, a, 0.0, 0.0] for x, a in [(-0.5, 0.3), (0.0, -0.6), (0.7, 1.2)]])
    for x, image in zip(states, vis.images(states)):
        blue = (image[..., 2] > 150) & (image[..., 0] < 100)
        rows, cols = np.nonzero(blue)
        expected = vis.width / 2 + focal * x[0] / (3.0 - 0.15)  # the front face at y = -0.15
        assert abs(cols.mean() - (expected - 0.5)) < 2 and abs(rows.mean() - (vis.height / 2 - 0.5)) < 2
    traj = jd.simulate(cartpole, (0.0, 0.5), jnp.array([0.0, 0.4, 0.0, 0.0]))
    frames = iio.imread(vis.save(traj, tmp_path / "cartpole.gif", fps=10), index=None)
    assert frames.shape[:3] == (5, vis.height, vis.width)
    direct = vis.images(np.asarray(traj.state(jnp.arange(5) / 10)))
    assert np.mean(np.abs(frames[3][..., :3].astype(float) - direct[3])) < 8  # the GIF's palette
    assert np.mean(np.abs(direct[4].astype(float) - direct[0])) > 0.5  # the pole moved


def test_rendering_works_when_mujoco_was_imported_before_jaxdrake():
    """Without a display and with mujoco imported first (so it chose GLFW), a render still
    works (switched to EGL) and equals the render of a process that imported jaxdrake first."""
    import subprocess
    import sys

    script = ("import {first}, {second}, numpy; import jaxdrake as jd\n"
              "h = jd.MujocoSystem.from_xml({path!r})\n"
              "print(numpy.asarray(h.render(h.initial_state(), width=64, height=48), float).sum())")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY")}
    sums = [subprocess.run([sys.executable, "-c", script.format(first=a, second=b, path=str(DATA / "mj_hopper.xml"))],
                           env=env, capture_output=True, text=True, timeout=120) for a, b in
            [("mujoco", "jaxdrake"), ("jaxdrake", "mujoco")]]
    assert [run.returncode for run in sums] == [0, 0], [run.stderr[-500:] for run in sums]
    values = [float(run.stdout.split()[-1]) for run in sums]
    assert values[0] == values[1] and values[0] > 0


def test_mujoco_warnings_become_python_warnings_and_no_log_file_is_written(tmp_path, monkeypatch, capfd):
    """MuJoCo's own handler writes MUJOCO_LOG.TXT into the working folder; MJX's import
    prints "Failed to import warp" (an optional backend)."""
    monkeypatch.chdir(tmp_path)
    system = jd.MujocoSystem.from_xml('<mujoco><worldbody><body><joint type="hinge"/>'
                                      '<geom type="sphere" size="0.1"/></body></worldbody></mujoco>')
    data = mujoco.MjData(system.mj_model)
    data.qvel[:] = 1e30  # MuJoCo warns of a huge velocity and resets
    with pytest.warns(RuntimeWarning, match="MuJoCo: Nan, Inf or huge value in QVEL"):
        mujoco.mj_step(system.mj_model, data)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert "Failed to import warp" not in capfd.readouterr().out
