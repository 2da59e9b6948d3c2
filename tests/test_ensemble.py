"""`jd.simulate_ensemble`: one lane per member, against closed forms, `simulate` and its statuses.
On this CPU the lanes run as one jitted program ("xla"); the Pallas kernel through Pallas's
interpreter on a few members; on a GPU (`-m gpu`) the kernel itself."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jaxdrake as jd
from jaxdrake.simulation import SimulationStatus

A = np.array([[0.0, 1.0], [-4.0, -0.4]])   # a damped oscillator, driven: xdot = A x + B u
B = np.array([[0.0], [1.0]])


def closed_form(x0, u, T):
    """x(T) = e^{AT} x0 + A^{-1} (e^{AT} - I) B u for a constant u."""
    eAT = scipy.linalg.expm(A * T)
    return eAT @ x0 + np.linalg.solve(A, (eAT - np.eye(2)) @ B @ u)


def test_a_driven_linear_system_ends_at_its_closed_form_with_each_members_input_clipped():
    plant = jd.LinearSystem(A, B, np.eye(2), np.zeros((2, 1)), input_limits=([-1.0], [1.0]))
    rng = np.random.default_rng(0)
    x0s, us = rng.uniform(-2, 2, (37, 2)), rng.uniform(-3, 3, (37, 1))
    result = jd.simulate_ensemble(plant, (0.0, 3.0), x0s, inputs=us, rtol=1e-10, atol=1e-12)
    expected = np.stack([closed_form(x0, np.clip(u, -1, 1), 3.0) for x0, u in zip(x0s, us)])
    np.testing.assert_allclose(np.asarray(result.final_state), expected, rtol=1e-8, atol=1e-10)
    assert result.final_state.shape == (37, 2) and bool(jnp.all(result.success))
    np.testing.assert_array_equal(np.asarray(result.final_time), 3.0)
    one_input = jd.simulate_ensemble(plant, (0.0, 3.0), x0s[:3], inputs=[0.5], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(one_input.final_state),
                               np.stack([closed_form(x0, [0.5], 3.0) for x0 in x0s[:3]]), rtol=1e-8, atol=1e-10)


def test_each_member_takes_simulates_steps():
    # the same Dormand-Prince steps and step control as simulate, to rounding: two programs
    # round differently (their step times part at ~1e-12 after a few steps), so a step whose
    # error norm is near 1 may then go either way; final states equal to the tolerance, and
    # attempts (simulate counts its first evaluation as one, as the ensemble does) within 3%
    # a member and 0.5% in all
    pendulum = jd.models.Pendulum()
    x0s = np.random.default_rng(1).uniform([-2.5, -3.0], [2.5, 3.0], (64, 2))
    result = jd.simulate_ensemble(pendulum, (0.0, 5.0), x0s, rtol=1e-8, atol=1e-8)

    def one(x0):
        traj = jd.simulate(pendulum, (0.0, 5.0), x0, rtol=1e-8, atol=1e-8, dense=False)
        return traj.final_state, traj.num_accepted_steps + traj.num_rejected_steps + 1

    finals, attempts = jax.jit(jax.vmap(one))(jnp.asarray(x0s))
    np.testing.assert_allclose(np.asarray(result.final_state), np.asarray(finals), rtol=1e-6, atol=1e-7)
    ours, theirs = np.asarray(result.attempts), np.asarray(attempts)
    assert np.all(np.abs(ours - theirs) <= 0.03 * theirs) and abs(ours.sum() - theirs.sum()) <= 0.005 * theirs.sum()


def test_failures_are_statuses_per_member():
    vdp = jd.models.VanDerPol(1.0)
    x0s = np.array([[1.0, 0.0], [np.nan, 0.0], [2.0, 0.0]])
    result = jd.simulate_ensemble(vdp, (0.0, 20.0), x0s, max_steps=50)
    assert [int(s) for s in result.status] == [SimulationStatus.MAX_STEPS_REACHED,
                                               SimulationStatus.NONFINITE_INITIAL_STATE,
                                               SimulationStatus.MAX_STEPS_REACHED]
    assert int(result.attempts[0]) == 50 and float(result.final_time[0]) < 20.0
    blow_up = jd.System.from_functions(lambda t, x, u: x ** 2, num_states=1)   # x(t) = 1 / (1 - t)
    assert int(jd.simulate_ensemble(blow_up, (0.0, 2.0), [[1.0]]).status[0]) == SimulationStatus.STEP_SIZE_TOO_SMALL


def test_the_pallas_kernel_equals_the_xla_lanes():
    # Pallas's interpreter on this CPU: the kernel's blocks, padded members and rows
    pendulum = jd.models.Pendulum()
    x0s = np.random.default_rng(2).uniform(-2, 2, (5, 2))
    xla = jd.simulate_ensemble(pendulum, (0.0, 2.0), x0s, kernel="xla")
    pallas = jd.simulate_ensemble(pendulum, (0.0, 2.0), x0s, kernel="pallas")
    np.testing.assert_array_equal(np.asarray(pallas.final_state), np.asarray(xla.final_state))
    np.testing.assert_array_equal(np.asarray(pallas.attempts), np.asarray(xla.attempts))


def test_a_vector_field_written_with_indexing_updates_sums_and_products():
    # x[i], .at[].set, jnp.sum, a matrix product with a constant: all resolved while tracing
    M = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [0.0, -0.5, -0.1]])

    def dynamics(t, x, u):
        xdot = jnp.zeros(3).at[0].set(x[1])
        xdot = xdot.at[1:].set((M @ x)[1:] + 0.0 * jnp.sum(x ** 2))
        return xdot

    system = jd.System.from_functions(dynamics, num_states=3)
    x0s = np.random.default_rng(3).uniform(-1, 1, (4, 3))
    result = jd.simulate_ensemble(system, (0.0, 2.0), x0s, rtol=1e-11, atol=1e-12)
    expected = np.stack([scipy.linalg.expm(M * 2.0) @ x0 for x0 in x0s])
    np.testing.assert_allclose(np.asarray(result.final_state), expected, rtol=1e-9, atol=1e-11)


def test_float32_members_stay_float32():
    x0s = np.random.default_rng(4).uniform(-2, 2, (8, 2))
    single = jd.simulate_ensemble(jd.models.VanDerPol(1.0), (0.0, 3.0), x0s.astype(np.float32), rtol=1e-5, atol=1e-5)
    double = jd.simulate_ensemble(jd.models.VanDerPol(1.0), (0.0, 3.0), x0s, rtol=1e-10, atol=1e-10)
    assert single.final_state.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(single.final_state), np.asarray(double.final_state), rtol=1e-3, atol=1e-3)


def test_what_one_lane_cannot_simulate_is_named():
    with pytest.raises(ValueError, match="BouncingBall has modes and transitions.*jax.vmap"):
        jd.simulate_ensemble(jd.models.BouncingBall(), (0.0, 1.0), np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"x0s must have shape \(N, 2\)"):
        jd.simulate_ensemble(jd.models.Pendulum(), (0.0, 1.0), np.zeros(2))
    solve = jd.System.from_functions(lambda t, x, u: jnp.linalg.solve(jnp.array([[2.0, x[0]], [0.0, 1.0]]), x),
                                     num_states=2)
    with pytest.raises(NotImplementedError, match="uses `.*`, which has no per-lane form.*jax.vmap"):
        jd.simulate_ensemble(solve, (0.0, 1.0), np.ones((2, 2)))
    with pytest.raises(NotImplementedError, match="acrobot.s vector field unrolls into more than 2,000 per-lane operations.*max_operations"):
        jd.simulate_ensemble(jd.models.Acrobot(), (0.0, 1.0), np.zeros((2, 4)))
    with pytest.raises(TypeError, match="VanDerPol's parameters are traced.*jax.vmap"):
        jax.vmap(lambda mu: jd.simulate_ensemble(jd.models.VanDerPol(mu), (0.0, 1.0), np.ones((2, 2))).final_state)(
            jnp.array([1.0, 2.0]))
    with pytest.raises(TypeError, match="tspan, rtol and atol must be Python numbers"):
        jax.jit(lambda tf: jd.simulate_ensemble(jd.models.Pendulum(), (0.0, tf), np.ones((2, 2))).final_state)(1.0)


@pytest.mark.gpu
def test_the_pallas_kernel_on_a_gpu_equals_the_xla_lanes_on_the_host():
    pendulum = jd.models.Pendulum()
    x0s = np.random.default_rng(5).uniform([-2.5, -3.0], [2.5, 3.0], (1000, 2))
    gpu = jd.simulate_ensemble(pendulum, (0.0, 10.0), jax.device_put(x0s, jax.devices("gpu")[0]), rtol=1e-8, atol=1e-8)
    with jax.default_device(jax.devices("cpu")[0]):
        host = jd.simulate_ensemble(pendulum, (0.0, 10.0), x0s, rtol=1e-8, atol=1e-8, kernel="xla")
    np.testing.assert_allclose(np.asarray(gpu.final_state), np.asarray(host.final_state), rtol=1e-6, atol=1e-7)
    assert bool(jnp.all(gpu.success))


@pytest.mark.slow   # 10 s of compiling; by default the acrobot's refusal walks the same unrolled recursions
def test_a_one_link_rigid_body_tree_unrolls_its_recursions(tmp_path):
    # the tree's recursions (scans over depth), gathers, scatter-adds and custom batching rules
    # become straight-line code on lanes; a one-link pendulum from a URDF equals simulate
    (tmp_path / "link.urdf").write_text(
        '<robot name="link"><link name="base"/><link name="arm"><inertial><origin xyz="0 0 -0.5"/>'
        '<mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<joint name="hinge" type="continuous"><parent link="base"/><child link="arm"/><axis xyz="0 1 0"/></joint>'
        '</robot>')
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "link.urdf")
    x0s = np.array([[0.5, 0.0], [1.0, -0.5], [2.0, 1.0]])
    result = jd.simulate_ensemble(plant, (0.0, 2.0), x0s, rtol=1e-10, atol=1e-10)
    single = jax.vmap(lambda x0: jd.simulate(plant, (0.0, 2.0), x0, rtol=1e-10, atol=1e-10, dense=False).final_state)
    np.testing.assert_allclose(np.asarray(result.final_state), np.asarray(single(jnp.asarray(x0s))), rtol=1e-7, atol=1e-8)
