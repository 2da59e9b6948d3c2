"""Model-predictive control as discrete systems (`jd.control.linear_mpc`, `nonlinear_mpc`,
`mppi`) and the QP solver under linear MPC: each step's QP against OSQP and Clarabel, the
closed loop against Drake's LinearModelPredictiveController (its formulation, rebuilt with
pydrake), gradients against central differences, constraints, statuses and invariants."""

import clarabel
import jax
import jax.numpy as jnp
import numpy as np
import osqp
import pytest
import scipy.sparse as sp

import jaxdrake as jd
from jaxdrake.control import QPStatus

PERIOD = 0.1
Q_DI, R_DI = np.diag([1.0, 0.5]), np.array([[0.1]])
U_MAX, V_MAX = 1.0, 0.8


def _constrained_mpc(R=R_DI, **kwargs):
    return jd.control.linear_mpc(jd.models.DoubleIntegrator(), Q_DI, R, 1.0, period=PERIOD, input_lower=-U_MAX,
                                 input_upper=U_MAX, state_lower=[-np.inf, -V_MAX], state_upper=[np.inf, V_MAX],
                                 **kwargs)


def _closed_loop(controller, q0, tf):
    plant = jd.models.DoubleIntegrator()
    loop = jd.feedback(plant, controller)
    x0 = loop.initial_state().at[-2:].set(jnp.array([q0, 0.0]))  # [controller (discrete); plant]
    return jd.simulate(loop, (0.0, tf), x0)


def _osqp(P, q, A, l, u):
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.triu(P)), q, sp.csc_matrix(A), l, u, eps_abs=1e-10, eps_rel=1e-10,
                 max_iter=200000, polishing=True, verbose=False)
    result = solver.solve(raise_error=False)
    assert result.info.status == "solved"
    return result.x


def _clarabel(P, q, A, l, u):
    upper, lower = np.isfinite(u), np.isfinite(l)
    G = np.vstack([A[upper], -A[lower]])
    h = np.concatenate([u[upper], -l[lower]])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-12
    solver = clarabel.DefaultSolver(sp.csc_matrix(np.triu(P)), q, sp.csc_matrix(G), h,
                                    [clarabel.NonnegativeConeT(len(h))], settings)
    result = solver.solve()
    assert str(result.status) == "Solved"
    return np.asarray(result.x)


@pytest.fixture(scope="module")
def constrained_loop():
    """The double integrator from q = 3 at rest, both the input and the speed limits active."""
    controller = _constrained_mpc()
    return controller, _closed_loop(controller, 3.0, 4.0)


def test_each_step_qp_equals_osqp_and_clarabel(constrained_loop):
    controller, traj = constrained_loop
    samples = np.arange(0, 40) * PERIOD
    plant_states = np.asarray(traj.state(samples))[:, -2:]
    held = np.asarray(traj.state(samples + PERIOD / 2))[:, :controller.num_states]  # after each update
    active = 0
    for x, state in zip(plant_states, held):
        P, q, A, l, u = (np.asarray(v) for v in controller.qp(x))
        ours = np.asarray(controller.plan(state)).reshape(-1)  # u0 = 0: the plan is the QP's x
        assert int(controller.status(state)) == QPStatus.SOLVED
        np.testing.assert_allclose(ours, _osqp(P, q, A, l, u), atol=1e-6)
        np.testing.assert_allclose(ours, _clarabel(P, q, A, l, u), atol=1e-6)
        assert state[0] == ours[0]  # the output is the plan's first input
        active += np.any(np.isclose(A @ ours, l, atol=1e-8) | np.isclose(A @ ours, u, atol=1e-8))
    assert active >= 10  # the comparison covered steps with active constraints


def test_constraints_hold_along_the_closed_loop(constrained_loop):
    controller, traj = constrained_loop
    t = np.linspace(0, 4.0, 801)
    states = np.asarray(traj.state(t))
    u, v = states[:, 0], states[:, -1]
    assert np.all(np.abs(u) <= U_MAX + 1e-9)
    assert np.all(np.abs(v) <= V_MAX + 1e-7)  # the model is exact (ZOH): realised = predicted
    assert np.isclose(u.min(), -U_MAX) and np.isclose(v.min(), -V_MAX, atol=1e-6)  # both limits were reached
    assert abs(states[-1, -2]) < 0.1 * abs(states[0, -2])  # and it still converges towards the origin


def _drake_lmpc_input(A, B, Q, R, period, time_horizon, x):
    """Drake's LinearModelPredictiveController::SetupAndSolveQp (removed from Drake in Dec
    2024, drake#22306), line for line with pydrake: DirectTranscription of the discrete model
    over round(time_horizon / period) samples, running cost x'Qx + u'Ru, x_0 = x."""
    from pydrake.planning import DirectTranscription
    from pydrake.solvers import Solve
    from pydrake.systems.primitives import LinearSystem as DrakeLinearSystem

    model = DrakeLinearSystem(A, B, np.eye(A.shape[0]), np.zeros((A.shape[0], B.shape[1])), period)
    context = model.CreateDefaultContext()
    model.get_input_port().FixValue(context, np.zeros(B.shape[1]))
    dirtran = DirectTranscription(model, context, int(time_horizon / period + 0.5))
    state, inputs = dirtran.state(), dirtran.input()
    dirtran.AddRunningCost(state.dot(Q @ state) + inputs.dot(R @ inputs))
    dirtran.prog().AddLinearEqualityConstraint(np.eye(A.shape[0]), x, dirtran.initial_state())
    result = Solve(dirtran.prog())
    assert result.is_success()
    return dirtran.GetInputSamples(result)[:, 0]


def test_closed_loop_equals_drakes_linear_mpc():
    # Drake's controller has no constraints and no terminal cost, and its horizon counts samples:
    # round(H / T) samples are our N = round(H / T) - 1 steps with Qf = 0.
    drake_horizon, steps = 1.0, 9
    controller = jd.control.linear_mpc(jd.models.DoubleIntegrator(), Q_DI, R_DI, steps * PERIOD, period=PERIOD,
                                       terminal_cost=np.zeros((2, 2)))
    traj = _closed_loop(controller, 1.0, 3.0)
    Ad, Bd = np.array([[1.0, PERIOD], [0.0, 1.0]]), np.array([[PERIOD ** 2 / 2], [PERIOD]])  # exact ZOH
    x, drake_states = np.array([1.0, 0.0]), []
    for _ in range(30):
        drake_states.append(x)
        x = Ad @ x + Bd @ _drake_lmpc_input(Ad, Bd, Q_DI, R_DI, PERIOD, drake_horizon, x)
    ours = np.asarray(traj.state(np.arange(30) * PERIOD))[:, -2:]
    np.testing.assert_allclose(ours, np.array(drake_states), atol=1e-8)


def _discrete_closed_loop_cost(r, steps=20):
    """sum_k q_k^2 + 0.1 qdot_k^2 along the closed loop of the exact (ZOH) discrete double
    integrator and the constrained MPC with the input weight r R (terminal cost 10 Q: the
    DARE's derivative would only add compile time here; `test_gradient_through_simulate` has it)."""
    controller = _constrained_mpc(R=r * R_DI, terminal_cost=10 * Q_DI)
    Ad, Bd = jd.control.zero_order_hold(jnp.array([[0.0, 1.0], [0.0, 0.0]]), jnp.array([[0.0], [1.0]]), PERIOD)

    def step(carry, _):
        x, memory = carry
        memory = controller.update(0.0, memory, x)
        return (Ad @ x + Bd @ memory[:1], memory), x[0] ** 2 + 0.1 * x[1] ** 2

    start = (jnp.array([1.5, 0.0]), controller.initial_state())
    return jnp.sum(jax.lax.scan(step, start, None, length=steps)[1])


def test_gradient_of_closed_loop_cost_matches_central_differences():
    value_and_grad = jax.jit(jax.value_and_grad(_discrete_closed_loop_cost))  # one program for all three
    r, h = 2.0, 1e-4
    cost, gradient = value_and_grad(r)
    central = (value_and_grad(r + h)[0] - value_and_grad(r - h)[0]) / (2 * h)
    assert abs(float(gradient)) > 1e-3 * float(cost)  # the weight matters here
    np.testing.assert_allclose(float(gradient), float(central), rtol=1e-6)


@pytest.mark.slow  # 35-75 s compiling reverse mode through simulate; the scan version above runs by default
def test_gradient_through_simulate_matches_central_differences():
    def closed_loop_cost(r):
        traj = _closed_loop(_constrained_mpc(R=r * R_DI), 1.5, 2.0)
        states = traj.state(jnp.arange(20) * PERIOD)
        return jnp.sum(states[:, -2] ** 2 + 0.1 * states[:, -1] ** 2)

    r, h = 2.0, 1e-4
    gradient = jax.grad(closed_loop_cost)(r)
    central = (closed_loop_cost(r + h) - closed_loop_cost(r - h)) / (2 * h)
    np.testing.assert_allclose(float(gradient), float(central), rtol=1e-5)


def test_vmapped_steps_infeasible_status_and_lqr_inside_the_constraints():
    controller = _constrained_mpc()
    # active constraints; 5 m/s (more than the braking within one step allows: infeasible);
    # near the origin, where no constraint is active
    states = jnp.array([[2.0, 0.0], [0.0, 5.0], [0.05, -0.02]])
    x = jnp.broadcast_to(controller.initial_state(), (3, controller.num_states))
    new = jax.jit(jax.vmap(controller.update, in_axes=(None, 0, 0)))(0.0, x, states)
    assert controller.status(new).tolist() == [QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE, QPStatus.SOLVED]
    assert np.all(np.isfinite(np.asarray(new))) and np.all(np.abs(np.asarray(new[:, 0])) <= U_MAX)
    P, q, A, l, u = (np.asarray(v) for v in controller.qp(states[0]))
    np.testing.assert_allclose(np.asarray(controller.plan(new[0])).reshape(-1), _osqp(P, q, A, l, u), atol=1e-6)
    solver = osqp.OSQP()  # OSQP agrees that the second is infeasible
    P, q, A, l, u = (np.asarray(v) for v in controller.qp(states[1]))
    solver.setup(sp.csc_matrix(np.triu(P)), q, sp.csc_matrix(A), l, u, verbose=False)
    assert solver.solve(raise_error=False).info.status == "primal infeasible"
    # with the DARE's cost-to-go as terminal cost (the default) and nothing active, MPC is the LQR
    discrete = jd.LinearSystem(np.array([[1.0, PERIOD], [0.0, 1.0]]), np.array([[PERIOD ** 2 / 2], [PERIOD]]),
                               sample_time=PERIOD)
    K = np.asarray(jd.control.lqr(discrete, Q_DI, R_DI).K)
    np.testing.assert_allclose(np.asarray(new[2, :1]), -K @ np.asarray(states[2]), rtol=1e-9)


def test_float32_qp_solve_equals_osqp():
    # the degenerate vertex of the constrained loop's first step (an input bound and a speed
    # bound meet), solved in float32 inside jit; OSQP solves it in float64
    controller = _constrained_mpc()
    P, q, A, l, u = (np.asarray(v) for v in controller.qp(np.array([2.0, 0.0])))
    @jax.jit
    def solve(P, q, A, l, u):
        return jd.control.solve_qp(jd.control.qp_workspace(P, A), q, l, u)

    solution = solve(*(v.astype(np.float32) for v in (P, q, A, l, u)))
    assert solution.x.dtype == jnp.float32 and int(solution.status) == QPStatus.SOLVED
    np.testing.assert_allclose(np.asarray(solution.x), _osqp(P, q, A, l, u), atol=1e-4)


def test_bad_input_is_named_with_the_remedy():
    plant = jd.models.DoubleIntegrator()
    with pytest.raises(ValueError, match="not a whole number of periods.*horizon = N \\* period"):
        jd.control.linear_mpc(plant, Q_DI, R_DI, 1.05, period=0.1)
    with pytest.raises(ValueError, match="continuous: give the controller's period="):
        jd.control.linear_mpc(plant, Q_DI, R_DI, 1.0)
    with pytest.raises(ValueError, match="Q must be positive semidefinite"):
        jd.control.linear_mpc(plant, -Q_DI, R_DI, 1.0, period=0.1)
    with pytest.raises(ValueError, match="R must be positive definite"):
        jd.control.linear_mpc(plant, Q_DI, [[0.0]], 1.0, period=0.1)
    with pytest.raises(ValueError, match="Q must be \\(2, 2\\)"):
        jd.control.linear_mpc(plant, np.eye(3), R_DI, 1.0, period=0.1)
    with pytest.raises(ValueError, match="terminal_cost must be \\(2, 2\\)"):
        jd.control.linear_mpc(plant, Q_DI, R_DI, 1.0, period=0.1, terminal_cost=np.eye(3))
    with pytest.raises(ValueError, match="input_lower must not exceed input_upper"):
        jd.control.linear_mpc(plant, Q_DI, R_DI, 1.0, period=0.1, input_lower=1, input_upper=-1)
    with pytest.raises(ValueError, match="state_lower must be a scalar or have 2 entries"):
        jd.control.linear_mpc(plant, Q_DI, R_DI, 1.0, period=0.1, state_lower=[0, 0, 0])
    discrete = jd.LinearSystem(np.eye(2), np.ones((2, 1)), sample_time=0.05)
    with pytest.raises(ValueError, match="discrete with period 0.05; period=0.1 disagrees"):
        jd.control.linear_mpc(discrete, Q_DI, R_DI, 1.0, period=0.1)
    pendulum = jd.models.Pendulum()
    with pytest.raises(ValueError, match="running_cost\\(t, x, u\\) must return a scalar"):
        jd.control.nonlinear_mpc(pendulum, lambda t, x, u: x, 1.0, period=0.1)
    with pytest.raises(ValueError, match="temperature must be positive"):
        jd.control.mppi(pendulum, lambda t, x, u: x @ x, 1.0, period=0.1, key=jax.random.key(0), temperature=0.0)


def _pendulum_cost(t, x, u):
    return 10 * (x[0] - jnp.pi) ** 2 + x[1] ** 2 + 0.1 * u[0] ** 2


def _pendulum_final_cost(x):
    return 100 * (x[0] - jnp.pi) ** 2 + 10 * x[1] ** 2


def _pendulum_loop(controller, tf=3.0):
    plant = jd.models.Pendulum()
    loop = jd.feedback(plant, controller)
    x0 = loop.initial_state().at[-2:].set(jnp.array([np.pi - 0.3, 0.0]))  # 0.3 rad from upright
    traj = jd.simulate(loop, (0.0, tf), x0)
    return np.asarray(traj.state(np.linspace(0.0, tf, 301)))


def test_mppi_stabilises_the_pendulum():
    controller = jd.control.mppi(jd.models.Pendulum(), _pendulum_cost, 1.0, final_cost=_pendulum_final_cost,
                                 period=0.05, key=jax.random.key(0), num_samples=256, input_lower=-3,
                                 input_upper=3)
    states = _pendulum_loop(controller)
    assert np.all(np.abs(states[:, 0]) <= 3.0)  # the input bounds hold
    assert np.all(np.asarray(controller.status(states)) == 0)
    late = states[200:]  # the last second: held near the top (MPPI's sampling noise keeps it moving)
    assert np.max(np.abs(late[:, -2] - np.pi)) < 0.1 and np.max(np.abs(late[:, -1])) < 1.0
    assert np.max(np.abs(states[:, -2] - np.pi)) <= 0.3 + 1e-9  # it never fell further than it started


@pytest.mark.slow  # ~15 s compiling iLQR inside the loop; by default test_trajopt.py checks iLQR and
# test_mppi_stabilises_the_pendulum the receding-horizon machinery (plan shift, discrete update) it shares
def test_nonlinear_mpc_stabilises_the_pendulum():
    controller = jd.control.nonlinear_mpc(jd.models.Pendulum(), _pendulum_cost, 1.0,
                                          final_cost=_pendulum_final_cost, period=0.05, input_lower=-3,
                                          input_upper=3)
    states = _pendulum_loop(controller)
    assert np.all(np.abs(states[:, 0]) <= 3.0)
    error = np.abs(states[:, -2] - np.pi) + np.abs(states[:, -1])
    assert error[-1] < 1e-3 and np.all(np.diff(error[100:]) <= 1e-9)  # converging monotonically once near
    assert np.all(np.asarray(controller.status(states)) <= 1)
