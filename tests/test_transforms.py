"""simulate under jax.grad, jax.jacfwd, jax.vmap and jax.jit; the static / traced split."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from jaxdrake.models import Pendulum, VanDerPol

TOL = dict(rtol=1e-12, atol=1e-12)


def final_loss(b, x0):
    traj = jd.simulate(Pendulum(b=b), (0.0, 3.0), x0, inputs=lambda t: jnp.array([0.3 * jnp.cos(t)]),
                       max_steps=2048, **TOL)
    x = traj.final_state
    return x[0] ** 2 + jnp.sin(x[1])


def central_difference(f, x, h):
    x = np.asarray(x, float)
    g = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def test_grad_wrt_initial_state_and_damping_matches_finite_differences():
    b, x0 = 0.1, jnp.array([1.2, -0.4])
    db, dx0 = jax.grad(final_loss, argnums=(0, 1))(b, x0)
    fd_b = central_difference(lambda v: float(final_loss(float(v), x0)), b, 1e-4)
    fd_x0 = central_difference(lambda v: float(final_loss(b, jnp.asarray(v))), x0, 1e-4)
    np.testing.assert_allclose(db, fd_b, rtol=1e-6)
    np.testing.assert_allclose(dx0, fd_x0, rtol=1e-6)


def test_forward_mode_matches_reverse_mode():
    x0 = jnp.array([1.2, -0.4])
    f = lambda x0, mode: jd.simulate(Pendulum(), (0.0, 2.0), x0, autodiff=mode, **TOL).final_state
    J_fwd = jax.jacfwd(lambda x: f(x, "forward"))(x0)
    J_rev = jax.jacrev(lambda x: f(x, "reverse"))(x0)
    np.testing.assert_allclose(J_fwd, J_rev, rtol=1e-10, atol=1e-12)
    # the state-transition matrix of a Hamiltonian flow (b = 0) would have det 1; with
    # damping, Liouville's formula gives det = exp(-b / (m l^2) * t)
    np.testing.assert_allclose(np.linalg.det(J_fwd), np.exp(-0.1 / 0.25 * 2.0), rtol=1e-8)


def test_grad_through_fixed_step_solver_is_exact_for_the_scheme():
    # Euler on xdot = -k x: x_N = (1 - k h)^N x0, so d x_N / dk = -N h (1 - k h)^(N-1) x0
    sys = lambda k: jd.System.from_functions(dynamics=lambda t, x, u, k: -k * x, num_states=1, params=k)
    g = jax.grad(lambda k: jd.simulate(sys(k), (0.0, 1.0), 2.0, solver="euler", dt=0.01).final_state[0])(0.7)
    np.testing.assert_allclose(g, -100 * 0.01 * (1 - 0.007) ** 99 * 2.0, rtol=1e-10)


def test_vmap_over_initial_states_equals_single_runs():
    x0s = jax.random.uniform(jax.random.key(0), (1000, 2), minval=-2.0, maxval=2.0)
    sim = lambda x0: jd.simulate(Pendulum(), (0.0, 3.0), x0, rtol=1e-8, atol=1e-10, dense=False).final_state
    batched = jax.vmap(sim)(x0s)
    single = jax.jit(sim)
    looped = np.stack([np.asarray(single(x0)) for x0 in x0s])
    np.testing.assert_array_equal(np.asarray(batched), looped)


def test_vmap_over_parameters_and_dense_output():
    mus = jnp.array([0.5, 1.0, 2.0])
    trajs = jax.vmap(lambda mu: jd.simulate(VanDerPol(mu), (0.0, 5.0), jnp.array([1.0, 0.0]),
                                            rtol=1e-9, atol=1e-11))(mus)
    ts = jnp.linspace(0.0, 5.0, 11)
    batched = jax.vmap(lambda tr: tr.eval(ts))(trajs)
    # a batch's final states, read outside vmap, are each member's
    for i, mu in enumerate(mus):
        np.testing.assert_array_equal(trajs.final_state[i], trajs[i].final_state)
        np.testing.assert_allclose(trajs.final_state[i], trajs[i].state(5.0), rtol=1e-12)
    for mu, y in zip(mus, batched):
        single = jd.simulate(VanDerPol(float(mu)), (0.0, 5.0), jnp.array([1.0, 0.0]), rtol=1e-9, atol=1e-11)
        # XLA's vectorized pow differs from its scalar one in the last bit, which can flip an
        # accept / reject decision of the step-size controller: agreement is to the tolerance
        np.testing.assert_allclose(y, single.eval(ts), rtol=1e-7, atol=1e-9)


def test_jit_equals_no_jit_and_status_is_returned_inside_jit():
    f = lambda x0: jd.simulate(Pendulum(), (0.0, 2.0), x0)
    x0 = jnp.array([0.5, 0.5])
    np.testing.assert_array_equal(jax.jit(f)(x0).final_state, f(x0).final_state)
    # inside jit no exception can be raised: the status comes back on the trajectory
    traj = jax.jit(lambda x0: jd.simulate(Pendulum(), (0.0, 100.0), x0, max_steps=10))(x0)
    assert int(traj.status) == jd.SimulationStatus.MAX_STEPS_REACHED and not bool(traj.success)


class CompileCounter:
    """Counts XLA compilations (JAX's own monitoring events)."""

    def __enter__(self):
        self.count = 0

        def listener(event, duration, **kwargs):
            if event == "/jax/core/compile/backend_compile_duration":
                self.count += 1

        self._listener = listener
        jax.monitoring.register_event_duration_secs_listener(listener)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._listener)


def test_new_parameters_and_initial_states_do_not_recompile_but_new_structure_does():
    jd.simulate(Pendulum(), (0.0, 1.0), jnp.array([0.1, 0.0]))  # warm up
    with CompileCounter() as c:
        jd.simulate(Pendulum(m=2.0, b=0.3), (0.0, 2.0), jnp.array([1.0, 0.5]), rtol=1e-7)
    assert c.count == 0
    with CompileCounter() as c:
        jd.simulate(Pendulum(input_limits=(-1.0, 1.0)), (0.0, 1.0), jnp.array([0.1, 0.0]))
    assert c.count > 0  # input limits add events: a different program
    with CompileCounter() as c:
        jd.simulate(Pendulum(), (0.0, 1.0), jnp.array([0.1, 0.0]), max_steps=100)
    assert c.count > 0  # buffer sizes are structure


def test_the_loop_is_traced_once_for_many_calls():
    sim = lambda x0, b: jd.simulate(Pendulum(b=b), (0.0, 1.0), x0)
    counted = eqx.debug.assert_max_traces(sim, max_traces=1)
    jitted = jax.jit(counted)
    for i in range(4):
        jitted(jnp.array([0.1 * i, 0.0]), 0.1 * i)
    assert eqx.debug.get_num_traces(counted) == 1
