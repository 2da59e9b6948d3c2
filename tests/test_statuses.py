"""Issue 39: every failure reported as what it is — inside and outside jit / vmap — and the
reported bugs and silently accepted inputs, each from its repro line."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake._batch import default_chunk_size, member_bytes
from jaxdrake.models import Pendulum
from jaxdrake.trajectories import NUM_COEFFICIENTS

S = jd.SimulationStatus
X0 = jnp.array([1.0, 0.0])


@jax.jit
def _jitted(t0, tf, x0, b=0.1, u=0.0):  # one program for every case below
    return jd.simulate(Pendulum(b=b), (t0, tf), x0, inputs=lambda t: jnp.full(1, u))


def _jitted_status(t0, tf, x0, b=0.1, u=0.0):
    return _jitted(*(jnp.asarray(v, float) for v in (t0, tf, x0, b, u)))


@pytest.mark.parametrize("t0, tf", [(1.0, 0.0), (0.0, np.nan), (0.0, np.inf), (0.5, 0.5)])
def test_an_invalid_time_span_inside_jit_is_a_status(t0, tf):
    traj = _jitted_status(t0, tf, X0)
    assert S(int(traj.status)) == S.INVALID_TIME_SPAN and not traj.success
    assert int(traj.num_steps) == 0 and "t0 < tf" in S.INVALID_TIME_SPAN.message


@pytest.mark.parametrize("x0, b, u, expected", [
    (jnp.array([np.nan, 0.0]), 0.1, 0.0, S.NONFINITE_INITIAL_STATE),
    (X0, 0.1, np.nan, S.NONFINITE_INPUT),
    (X0, np.nan, 0.0, S.NAN_PARAMETER)])
def test_non_finite_values_stop_at_once_inside_jit_and_vmap(x0, b, u, expected):
    traj = _jitted_status(0.0, 1.0, x0, b, u)
    assert S(int(traj.status)) == expected and int(traj.num_steps) == 0  # no max_steps burnt
    batch = jax.vmap(lambda x, b: jd.simulate(Pendulum(b=b), (0.0, 1.0), x, inputs=lambda t: jnp.full(1, u)))(
        jnp.stack([X0, x0]), jnp.array([0.1, b]))
    assert [S(int(s)) for s in batch.status] == [S.SUCCESS if u == 0.0 else S.NONFINITE_INPUT, expected]


def test_outside_jit_the_same_inputs_are_named_errors():
    with pytest.raises(ValueError, match="t0 < tf"):
        jd.simulate(Pendulum(), (1.0, 0.0), X0)
    with pytest.raises(ValueError, match="x0 is not finite"):
        jd.simulate(Pendulum(), (0.0, 1.0), jnp.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match=r"Pendulum\.b is NaN"):
        jd.simulate(Pendulum(b=np.nan), (0.0, 1.0), X0)
    with pytest.raises(jd.SimulationError, match="NONFINITE_INPUT"):
        jd.simulate(Pendulum(), (0.0, 1.0), X0, inputs=lambda t: jnp.full(1, jnp.nan))


def test_grad_through_a_failing_simulation_raises_its_own_error_outside_jit_and_a_status_inside():
    def loss(x0):
        return jd.simulate(Pendulum(), (0.0, 10.0), x0, max_steps=5).final_state[0]

    with pytest.raises(jd.SimulationError, match="max_steps was reached") as caught:
        jax.grad(loss)(X0)
    assert caught.value.status == S.MAX_STEPS_REACHED
    assert np.all(np.isfinite(jax.jit(jax.grad(loss))(X0)))  # inside jit: no error raised ...
    traj = jax.jit(lambda x0: jd.simulate(Pendulum(), (0.0, 10.0), x0, max_steps=5))(X0)
    assert S(int(traj.status)) == S.MAX_STEPS_REACHED  # ... the status is on the result


def test_num_steps_counts_accepted_steps_also_when_not_dense():
    dense = jd.simulate(Pendulum(), (0.0, 3.0), X0)
    sparse = jd.simulate(Pendulum(), (0.0, 3.0), X0, dense=False)
    assert int(sparse.num_steps) == int(dense.num_steps) == int(dense.num_segments) - 1 > 10


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16, jnp.float32])
def test_low_precision_initial_states_are_promoted_to_float32_at_least(dtype):
    traj = jd.simulate(Pendulum(b=0.0), (0.0, 1.0), X0.astype(dtype))
    assert traj.final_state.dtype == jnp.float32
    # energy m g l (1 - cos 1) conserved to the float32 tolerance of the run
    reference = jd.simulate(Pendulum(b=0.0), (0.0, 1.0), X0)
    np.testing.assert_allclose(traj.final_state, reference.final_state, atol=1e-4)


def test_a_lone_free_floating_body_falls_freely(tmp_path):
    urdf = tmp_path / "one.urdf"
    urdf.write_text('<robot name="one"><link name="body"><inertial><mass value="2"/><inertia ixx="0.1" '
                    'iyy="0.2" izz="0.3" ixy="0" ixz="0" iyz="0"/></inertial></link></robot>')
    # without floating_base the root link is the world's frame: the error names the remedy
    with pytest.raises(jd.multibody.URDFError, match="no movable joint.*'body'.*floating_base=True"):
        jd.RigidBodySystem.from_urdf(urdf)
    body = jd.RigidBodySystem.from_urdf(urdf, floating_base=True)
    traj = jd.simulate(body, (0.0, 1.0))
    np.testing.assert_allclose(traj.final_state[:3], [0.0, 0.0, -0.5 * 9.81], atol=1e-9)  # z = -g t^2 / 2


def test_a_mujoco_model_without_degrees_of_freedom_says_so():
    mujoco = pytest.importorskip("mujoco")
    model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom type="plane" size="1 1 0.1"/>'
                                           '<body><geom type="sphere" size="0.1"/></body></worldbody></mujoco>')
    with pytest.raises(ValueError, match="no degrees of freedom.*<joint>"):
        jd.MujocoSystem(model)


def test_lqr_refuses_cost_weights_that_make_the_cost_unbounded():
    upright = dict(x0=[np.pi, 0.0])
    for Q in (-np.eye(2), np.diag([1.0, -1.0])):
        with pytest.raises(ValueError, match="Q must be positive semidefinite.*-1"):
            jd.control.lqr(Pendulum(), Q, np.eye(1), **upright)
    with pytest.raises(ValueError, match="symmetric"):
        jd.control.lqr(Pendulum(), np.array([[1.0, 1.0], [0.0, 1.0]]), np.eye(1), **upright)
    with pytest.raises(ValueError, match=r"\[\[Q, N\], \[N\^T, R\]\] must be positive semidefinite"):
        jd.control.lqr(Pendulum(), np.eye(2), np.eye(1), N=np.array([[2.0], [0.0]]), **upright)
    with pytest.raises(ValueError, match="Qf must be positive semidefinite"):
        jd.control.finite_horizon_lqr(Pendulum(), np.eye(2), np.eye(1), (0.0, 1.0), Qf=-np.eye(2))


def test_a_start_past_a_joint_limit_is_warned_once_and_the_default_start_is_inside():
    panda = jd.models.Panda()
    lower, upper = np.asarray(panda.tree.position_lower), np.asarray(panda.tree.position_upper)
    q = np.asarray(panda.initial_state())[:7]
    assert np.all((lower <= q) & (q <= upper))  # joint 4's zero is past its upper limit -0.0698
    x0 = panda.initial_state().at[3].set(0.5)
    with pytest.warns(UserWarning, match=r"'panda_joint4' at 0\.5, past its upper limit -0\.0698"):
        jd.simulate(panda, (0.0, 0.01), x0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jd.simulate(panda, (0.0, 0.01), x0)  # once per joint


def test_out_of_memory_names_dense_false_and_chunk_size(monkeypatch):
    from jaxdrake.simulation import _simulate

    def exhausted(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 61.4GiB")

    monkeypatch.setattr(_simulate, "_run_simulation", exhausted)
    pieces, events = 4097 * (NUM_COEFFICIENTS * 2 + 3), 256 * (2 + 3)  # polynomial, times, mode / state, ...
    with pytest.raises(MemoryError, match=rf"about {(pieces + events) * 8:,} bytes.*dense=False.*chunk_size"):
        jd.simulate(Pendulum(), (0.0, 1.0), X0)


def test_run_batch_picks_a_chunk_from_free_memory_and_names_out_of_memory(monkeypatch):
    from jaxdrake import _batch

    def final(x0):
        return jd.simulate(Pendulum(), (0.0, 1.0), x0).final_state

    member = jax.ShapeDtypeStruct((2,), jnp.float64)
    # the dense buffers inside the loop dominate, though only the final state is returned
    assert member_bytes(final, member) >= 3 * 4097 * NUM_COEFFICIENTS * 2 * 8
    monkeypatch.setattr(_batch, "free_memory", lambda device: 40 * member_bytes(final, member))
    assert default_chunk_size(final, member, jax.devices()[:1]) == 10
    x0 = np.random.default_rng(0).uniform(-2, 2, (25, 2))
    np.testing.assert_allclose(jd.run_batch(final, x0), jax.vmap(final)(x0), atol=1e-12)  # 3 chunks

    def exhausted(*args):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory")

    monkeypatch.setattr(_batch, "_device_program", lambda fn, device: exhausted)
    with pytest.raises(MemoryError, match="chunk of 10 members.*bytes per member.*chunk_size.*dense=False"):
        jd.run_batch(final, x0)


def test_a_vector_field_that_is_nan_from_the_start_is_a_non_finite_state_at_once():
    """A NaN first stage made a NaN first step size, and NaN never compared as too small: the
    loop rejected until max_steps and reported MAX_STEPS_REACHED (with stiff-solver advice)."""
    broken = jd.System.from_functions(dynamics=lambda t, x, u: jnp.sqrt(x - 2.0), num_states=1)
    for solver in ("dopri5", "rosenbrock23"):
        traj = jd.simulate(broken, (0.0, 1.0), jnp.ones(1), solver=solver, throw=False)
        assert int(traj.status) == S.NONFINITE_STATE and int(traj.num_rejected_steps) <= 2, solver
    with pytest.raises(jd.SimulationError, match="non-finite"):
        jd.simulate(broken, (0.0, 1.0), jnp.ones(1))
    assert int(jd.simulate_ensemble(broken, (0.0, 1.0), [[1.0]]).status[0]) == S.NONFINITE_STATE


def test_a_float32_simulation_out_of_steps_at_a_tight_rtol_is_told_about_float64():
    """A float32 x0 (measured data) keeps the simulation in float32 even with x64 on; a
    pendulum at rtol 1e-10 ran out of steps with advice for stiff systems only. It is told
    that float32 is the cause, and the float64 x0 runs (655 steps)."""
    x0 = np.array([1.0, 0.0])
    with pytest.raises(jd.SimulationError, match=r"MAX_STEPS_REACHED.*float32.*rtol=1e-10 and atol=1e-12.*"
                                                 r"jnp.asarray\(x0, jnp.float64\)"):
        jd.simulate(jd.models.Pendulum(), (0.0, 5.0), x0.astype(np.float32), rtol=1e-10, atol=1e-12)
    assert jd.simulate(jd.models.Pendulum(), (0.0, 5.0), x0, rtol=1e-10, atol=1e-12, dense=False).success


def test_float32_takes_steps_below_the_spacing_of_t():
    """An oscillation of period 6e-7 s near t = 1 needs steps of ~4e-8 s, below float32's
    spacing of t there (1.2e-7 s): float32 carries time as a pair and resolves them, as
    float64 does (closed form cos(w (t - 1)) over float32's interval: tf = 1 + 1e-5 rounds to
    1.0000100136, 0.14 rad of phase). A float32 run that does stop with its steps too small
    is told about float64."""
    w = 1e7
    fast = jd.System.from_functions(dynamics=lambda t, x, u: w * jnp.stack([x[1], -x[0]]), num_states=2)
    x0 = jnp.array([1.0, 0.0])
    single = jd.simulate(fast, (1.0, 1.0 + 1e-5), x0.astype(jnp.float32), dense=False)
    span = float(np.float32(1.0 + 1e-5)) - 1.0
    assert single.final_state.dtype == jnp.float32
    np.testing.assert_allclose(single.final_state, [np.cos(w * span), -np.sin(w * span)], atol=2e-3)
    traj = jd.simulate(fast, (1.0, 1.0 + 1e-5), x0, rtol=1e-10, atol=1e-12, dense=False)
    np.testing.assert_allclose(traj.final_state, [np.cos(w * 1e-5), -np.sin(w * 1e-5)], atol=1e-7)
    blow_up = jd.System.from_functions(dynamics=lambda t, x, u: x ** 2, num_states=1)   # x = 1 / (1 - t)
    with pytest.raises(jd.SimulationError, match="STEP_SIZE_TOO_SMALL.*float64") as raised:
        jd.simulate(blow_up, (0.0, 2.0), jnp.ones(1, jnp.float32))
    assert raised.value.status == S.STEP_SIZE_TOO_SMALL
    # a vector field that reads t sees it as one float32 number, which steps below its spacing
    # do not move: a pulse 1e-8 s wide at t = 1 (its integral pi) passed unseen between such
    # steps with SUCCESS; there steps keep one number's floor, and the run says so
    pulse = jd.System.from_functions(dynamics=lambda t, x, u: 1e8 / (1 + (1e8 * (t - 1.0)) ** 2) + 0 * x,
                                     num_states=1)
    with pytest.raises(jd.SimulationError, match="STEP_SIZE_TOO_SMALL.*reads t.*float32 holds as one number.*float64"):
        jd.simulate(pulse, (1.0 - 3e-6, 1.0 + 3e-6), jnp.zeros(1, jnp.float32))


def test_a_nan_error_estimate_rejects_the_step_and_shrinks_it():
    """A vector field that is NaN away from the solution (sin's derivative within 1e-2 of sin,
    NaN beyond): Rosenbrock23's long step ends at a finite y1 whose last stage, and so its error
    estimate, is NaN. That grew the rejected step tenfold (clipped at tf) until max_steps; it is
    a non-finite attempt, rejected with the step shrunk, and the run reaches sin(6)."""
    band = jd.System.from_functions(
        dynamics=lambda t, x, u: jnp.where(jnp.abs(x - jnp.sin(t)) < 1e-2, jnp.cos(t), jnp.nan), num_states=1)
    traj = jd.simulate(band, (0.0, 6.0), jnp.zeros(1), solver="rosenbrock23", rtol=0.1, atol=0.1, dense=False)
    np.testing.assert_allclose(traj.final_state, [np.sin(6.0)], atol=1e-2)
