"""Trajectory optimization against closed forms (the notes' chapter-12 double integrator),
finite differences, and the failure modes a user must see."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake import trajopt


def min_effort(program_type, N, T=2.0, **kwargs):
    prog = program_type(jd.models.DoubleIntegrator(), N, duration=T, **kwargs)
    prog.set_initial_state([1.0, 0.0]).set_final_state([0.0, 0.0])
    return prog.add_running_cost(lambda t, x, u: u @ u)


def min_time(program_type, N, **kwargs):
    plant = jd.models.DoubleIntegrator().with_input_limits(-1.0, 1.0)
    prog = program_type(plant, N, duration=(0.5, 6.0), **kwargs)
    prog.set_initial_state([-2.0, 0.0]).set_final_state([0.0, 0.0])
    return prog.add_duration_cost()


def zoh_min_effort_cost(N, T):
    """min sum h u_k^2 s.t. the exact zero-order-hold double integrator reaches the origin from
    (1, 0) in N steps: the least-norm solution of a linear system (numpy)."""
    h = T / N
    A, B = np.array([[1.0, h], [0.0, 1.0]]), np.array([[h * h / 2], [h]])
    G = np.hstack([np.linalg.matrix_power(A, N - 1 - k) @ B for k in range(N)])
    u = np.linalg.lstsq(G, -np.linalg.matrix_power(A, N) @ np.array([1.0, 0.0]), rcond=None)[0]
    return h * u @ u


def test_collocation_minimum_effort_matches_closed_form():
    T = 2.0
    prog = min_effort(trajopt.DirectCollocation, 11, T)
    result = prog.solve()
    assert result.success and result.status == trajopt.SolverStatus.SOLVED and result.message == "solved"
    assert abs(result.cost - 12 / T**3) < 1e-4
    assert abs(result.cost - 12 / T**3) < 1e-10  # Simpson on a linear input is exact
    t = result.times
    u_exact = -6 / T**2 + 12 * t / T**3  # x(t) = 1 - 3 (t/T)^2 + 2 (t/T)^3
    np.testing.assert_allclose(result.knot_inputs[:, 0], u_exact, atol=1e-8)
    s = np.linspace(0, T, 37)
    np.testing.assert_allclose(np.asarray(result.states.state(jnp.asarray(s)))[:, 0],
                               1 - 3 * (s / T) ** 2 + 2 * (s / T) ** 3, atol=1e-8)
    assert result.max_defect < 1e-8
    # the default guess: the straight line, then one Gauss-Newton step, exact for linear dynamics
    guess = prog.initial_guess()
    assert np.abs(prog.nlp.constraint_values(guess)).max() < 1e-10
    np.testing.assert_array_equal(guess[[0, 1, 20, 21]], [1.0, 0.0, 0.0, 0.0])  # the fixed ends stay


@pytest.mark.parametrize("rule", ["rk4", "euler"])
def test_transcription_minimum_effort_matches_discrete_optimum(rule):
    N, T = 40, 2.0
    result = min_effort(trajopt.DirectTranscription, N + 1, T, rule=rule).solve()
    assert result.success
    assert abs(result.cost - zoh_min_effort_cost(N, T)) < 1e-10
    assert abs(result.cost - 12 / T**3) < 2e-3  # O(h^2) from the continuous optimum


def test_shooting_minimum_effort_through_simulate():
    T = 2.0
    result = min_effort(trajopt.MultipleShooting, 6, T).solve()
    assert result.success
    assert abs(result.cost - 12 / T**3) < 1e-6
    s = np.array([0.3, 1.0, 1.7])
    np.testing.assert_allclose(np.asarray(result.states.state(jnp.asarray(s)))[:, 0],
                               1 - 3 * (s / T) ** 2 + 2 * (s / T) ** 3, atol=1e-6)


def test_minimum_time_bang_bang():
    result = min_time(trajopt.DirectCollocation, 101).solve()
    assert result.success
    assert abs(result.duration - 2 * np.sqrt(2)) < 1e-3
    u, t = result.knot_inputs[:, 0], result.times
    away = np.abs(t - result.duration / 2) > 2 * (t[1] - t[0])
    np.testing.assert_allclose(u[away], np.where(t[away] < result.duration / 2, 1.0, -1.0), atol=1e-6)
    # with the input held over each step (exact for q'' = u under RK4) the switch sits on a knot
    exact = min_time(trajopt.DirectTranscription, 41, rule="rk4").solve()
    assert abs(exact.duration - 2 * np.sqrt(2)) < 1e-6
    np.testing.assert_allclose(np.abs(exact.knot_inputs[:-1, 0]), 1.0, atol=1e-5)


def test_simpson_cost_ignoring_the_state_skips_the_midpoint_dynamics_without_changing_it():
    """A running cost that does not read x needs no midpoint state (a dynamics evaluation):
    its value and gradient equal those of the same cost made to read x (times zero), and the
    Simpson midpoint of a state-reading cost is the Hermite cubic's (x_0+x_1)/2 + h/8 (f_0-f_1)."""
    def objective(cost):
        prog = trajopt.DirectCollocation(jd.models.Pendulum(), 6, duration=1.0).add_running_cost(cost)
        z = np.random.default_rng(3).standard_normal(prog.num_variables)
        return prog.nlp.objective(z), prog.nlp.gradient(z), prog, z

    plain, plain_gradient, _, _ = objective(lambda t, x, u: u @ u)
    reading, reading_gradient, _, _ = objective(lambda t, x, u: u @ u + 0.0 * x[0])
    np.testing.assert_allclose(plain, reading, rtol=1e-14)
    np.testing.assert_allclose(plain_gradient, reading_gradient, rtol=1e-14, atol=1e-14)
    value, _, prog, z = objective(lambda t, x, u: x[1])  # Simpson of the angular velocity
    X, h = z[:12].reshape(6, 2), 1.0 / 5
    U = z[12:18].reshape(6, 1)
    with jax.enable_x64(True):
        F = np.stack([np.asarray(prog.system.dynamics(0.0, X[k], U[k])) for k in range(6)])
    midpoint = (X[:-1, 1] + X[1:, 1]) / 2 + h / 8 * (F[:-1, 1] - F[1:, 1])
    np.testing.assert_allclose(value, np.sum(h / 6 * (X[:-1, 1] + 4 * midpoint + X[1:, 1])), rtol=1e-12)


def drake_pendulum_collocation(N, min_step, max_step):
    """Drake's DirectCollocation of its PendulumPlant (the parameters of jd.models.Pendulum()),
    equal time steps, as the notes' swing-up example builds it."""
    from pydrake.examples import PendulumPlant
    from pydrake.planning import DirectCollocation

    plant = PendulumPlant()
    dircol = DirectCollocation(plant, plant.CreateDefaultContext(), num_time_samples=N,
                               minimum_time_step=min_step, maximum_time_step=max_step)
    dircol.AddEqualTimeIntervalsConstraints()
    return dircol


def drake_decision_vector(dircol, X, U, h):
    z = np.zeros(dircol.prog().num_vars())
    for k in range(len(X)):
        dircol.prog().SetDecisionVariableValueInVector(dircol.state(k), X[k], z)
        dircol.prog().SetDecisionVariableValueInVector(dircol.input(k), U[k], z)
        if k < len(X) - 1:
            dircol.prog().SetDecisionVariableValueInVector(dircol.time_step(k), [h], z)
    return z


def test_collocation_with_the_trapezoid_is_drakes_program():
    """At the same (random) knots, DirectCollocation(quadrature="trapezoid")'s objective equals
    Drake's DirectCollocation objective for the same running cost (time-dependent, to check the
    knot times), and its defects are Drake's collocation constraints times 2h/3 (Drake writes
    the cubic's slope minus f at the midpoint: (3/2h) (x1 - x0) - (f0 + f1)/4 - f_c); Simpson's
    rule gives another number for the same trajectory."""
    pytest.importorskip("pydrake")
    N, T = 11, 2.0
    h = T / (N - 1)
    dircol = drake_pendulum_collocation(N, 0.01, 1.0)
    x, u, t = dircol.state(), dircol.input(), dircol.time()
    dircol.AddRunningCost(u[0] ** 2 + (x[0] - np.pi) ** 2 * (1 + t[0]))
    rng = np.random.default_rng(0)
    X, U = rng.normal(size=(N, 2)), rng.normal(size=(N, 1))
    z = drake_decision_vector(dircol, X, U, h)
    drake_cost = sum(dircol.prog().EvalBinding(b, z)[0] for b in dircol.prog().GetAllCosts())
    drake_defects = np.stack([dircol.prog().EvalBinding(b, z) for b in dircol.prog().GetAllConstraints()
                              if type(b.evaluator()).__name__ == "DirectCollocationConstraint"])

    def ours(quadrature):
        prog = trajopt.DirectCollocation(jd.models.Pendulum(), N, duration=T, quadrature=quadrature)
        prog.add_running_cost(lambda t, x, u: u[0] ** 2 + (x[0] - jnp.pi) ** 2 * (1 + t))
        return prog.nlp, np.concatenate([X.ravel(), U.ravel()])

    nlp, w = ours("trapezoid")
    assert abs(nlp.objective(w) - drake_cost) < 1e-12 * drake_cost
    np.testing.assert_allclose(nlp.constraint_values(w)[:(N - 1) * 2].reshape(N - 1, 2), 2 * h / 3 * drake_defects,
                               atol=1e-13)
    simpson, w = ours("simpson")
    assert abs(simpson.objective(w) - drake_cost) > 0.01 * drake_cost
    with pytest.raises(ValueError, match="quadrature"):
        trajopt.DirectCollocation(jd.models.Pendulum(), N, duration=T, quadrature="gauss")


def test_pendulum_swing_up_from_no_guess_reaches_drakes_optimum():
    """The notes' swing-up (Drake's example: 21 knots, time steps in [0.05, 0.5], |u| <= 3,
    cost 10 u^2 + T) solves with no guess at all (the straight line, one step toward the
    dynamics; from the line alone IPOPT ends 'infeasible problem detected'), at the optimum
    Drake's IPOPT reaches from its own guess (the line over 4 s): the same cost and duration."""
    pytest.importorskip("pydrake")
    from pydrake.solvers import IpoptSolver
    from pydrake.trajectories import PiecewisePolynomial

    N, goal = 21, np.array([np.pi, 0.0])
    prog = trajopt.DirectCollocation(jd.models.Pendulum(), N, duration=(20 * 0.05, 20 * 0.5), quadrature="trapezoid")
    prog.set_initial_state([0.0, 0.0]).set_final_state(goal).add_input_bounds(-3.0, 3.0)
    result = prog.add_running_cost(lambda t, x, u: 10 * u @ u).add_duration_cost().solve()
    assert result.success and result.max_defect < 1e-8

    dircol = drake_pendulum_collocation(N, 0.05, 0.5)
    u = dircol.input()
    dircol.AddConstraintToAllKnotPoints(-3.0 <= u[0])
    dircol.AddConstraintToAllKnotPoints(u[0] <= 3.0)
    dircol.prog().AddBoundingBoxConstraint([0.0, 0.0], [0.0, 0.0], dircol.initial_state())
    dircol.prog().AddBoundingBoxConstraint(goal, goal, dircol.final_state())
    dircol.AddRunningCost(10 * u[0] ** 2)
    dircol.AddFinalCost(dircol.time()[0])
    dircol.SetInitialTrajectory(PiecewisePolynomial(),
                                PiecewisePolynomial.FirstOrderHold([0.0, 4.0], np.column_stack([[0.0, 0.0], goal])))
    drake = IpoptSolver().Solve(dircol.prog())
    assert drake.is_success()
    drake_duration = sum(drake.GetSolution(dircol.time_step(k))[0] for k in range(N - 1))
    assert abs(result.cost - drake.get_optimal_cost()) < 1e-6 * drake.get_optimal_cost()
    assert abs(result.duration - drake_duration) < 1e-6
    np.testing.assert_allclose(result.knot_inputs[:, 0], [drake.GetSolution(dircol.input(k))[0] for k in range(N)],
                               atol=1e-4)


def test_jacobian_sparse_and_matches_finite_differences():
    """A pendulum with free duration and a free mass: every block, including the global
    columns, against central differences; the pattern covers every non-zero."""
    make = lambda p: jd.models.Pendulum(m=p[0])  # noqa: E731
    prog = trajopt.DirectCollocation(make, 15, duration=(1.0, 4.0), parameters=[1.0],
                                     parameter_bounds=([0.5], [2.0]))
    prog.set_initial_state([0.0, 0.0]).add_state_bounds([-10, -10], [10, 10])
    prog.add_running_cost(lambda t, x, u: u @ u + jnp.sin(x[0]) ** 2)
    prog.add_final_cost(lambda T, x: (x[0] - np.pi) ** 2 + T)
    prog.add_path_constraint(lambda t, x, u: x[1] ** 2 + u[0] ** 2, 0.0, 50.0)
    prog.add_periodicity([1])
    z = prog.initial_guess(np.zeros((15, 2)), duration=2.5) + 0.1 * np.random.default_rng(1).standard_normal(prog.num_variables)
    check = prog.nlp.check_derivatives(z)
    assert check["jacobian_error"] < 1e-7 * max(1.0, check["jacobian_scale"])
    assert check["hessian_error"] < 1e-6 * max(1.0, check["hessian_scale"])
    assert check["outside_pattern"] == 0.0
    sparsity = prog.nlp.sparsity()
    assert sparsity["jacobian_nonzeros"] < 0.2 * sparsity["jacobian_dense"]


def test_bad_problems_report_status():
    # the origin cannot be reached from (-2, 0) in 1 s with |u| <= 1
    plant = jd.models.DoubleIntegrator().with_input_limits(-1.0, 1.0)
    prog = trajopt.DirectCollocation(plant, 21, duration=1.0)
    prog.set_initial_state([-2.0, 0.0]).set_final_state([0.0, 0.0]).add_running_cost(lambda t, x, u: u @ u)
    result = prog.solve()
    assert not result.success and result.status == trajopt.SolverStatus.INFEASIBLE
    assert result.message.startswith("infeasible problem detected") and "duration" in result.message
    assert result.constraint_violation > 1e-3
    scipy_result = prog.solve(solver="scipy", max_iterations=300)
    assert not scipy_result.success
    assert scipy_result.status in (trajopt.SolverStatus.MAXIMUM_ITERATIONS, trajopt.SolverStatus.CONSTRAINTS_VIOLATED)

    nan_cost = min_effort(trajopt.DirectCollocation, 11).add_running_cost(lambda t, x, u: jnp.log(-1.0 - x[0] ** 2))
    result = nan_cost.solve()
    assert not result.success and result.status == trajopt.SolverStatus.NONFINITE
    assert "invalid number" in result.message

    with pytest.raises(ValueError, match="lower bound 1.0 > upper bound -1.0"):
        min_effort(trajopt.DirectCollocation, 11).add_input_bounds(1.0, -1.0)
    with pytest.raises(ValueError, match="contradict earlier bounds"):
        min_effort(trajopt.DirectCollocation, 11).add_state_bounds([-5, -5], [0.5, 5], knots=[0])
    with pytest.raises(ValueError, match="duration"):
        trajopt.DirectCollocation(plant, 11)
    with pytest.raises(ValueError, match="discrete"):
        trajopt.DirectCollocation(jd.models.SimpleDTExample(), 11, duration=1.0)
    with pytest.raises(ValueError, match="hybrid"):
        trajopt.DirectTranscription(jd.models.BouncingBall(), 11, duration=1.0)
    with pytest.raises(ValueError, match="no cost"):
        trajopt.DirectCollocation(plant, 11, duration=1.0).solve()
    with pytest.raises(ValueError, match="initial guess for the states"):
        min_effort(trajopt.DirectCollocation, 11).solve(states=np.zeros((5, 2)))


def test_scipy_fallback_solves():
    result = min_effort(trajopt.DirectCollocation, 11).solve(solver="scipy")
    assert result.success and result.solver == "scipy"
    assert abs(result.cost - 12 / 8) < 1e-6


def test_discrete_system_transcription():
    """x+ = x^3 (SimpleDTExample, period 1) driven by u: with x_{k+1} = x_k^3 + u_k ... the
    notes' discrete example has no input, so use a discrete double integrator instead."""
    h = 0.1
    plant = jd.System.from_functions(update=lambda t, x, u: jnp.array([x[0] + h * x[1], x[1] + h * u[0]]),
                                     num_states=2, num_inputs=1, sample_time=h)
    prog = trajopt.DirectTranscription(plant, 21)
    prog.set_initial_state([1.0, 0.0]).set_final_state([0.0, 0.0]).add_running_cost(lambda t, x, u: u @ u)
    result = prog.solve()
    assert result.success and result.duration == pytest.approx(2.0)
    # the same least-norm problem with Euler's matrices
    A, B = np.array([[1.0, h], [0.0, 1.0]]), np.array([[0.0], [h]])
    G = np.hstack([np.linalg.matrix_power(A, 19 - k) @ B for k in range(20)])
    u = np.linalg.lstsq(G, -np.linalg.matrix_power(A, 20) @ np.array([1.0, 0.0]), rcond=None)[0]
    assert abs(result.cost - h * u @ u) < 1e-10


def test_ilqr_matches_discrete_optimum_and_batches():
    N, T = 40, 2.0
    plant = jd.models.DoubleIntegrator()
    traces = []

    def effort(t, x, u):
        traces.append(1)  # counts the traces of the cost
        return u @ u

    def solve(x0):
        return trajopt.ilqr(plant, jnp.array(x0), jnp.zeros((N, 1)), T / N, effort,
                            final_state=jnp.zeros(2), constraint_tol=1e-11)

    result = solve([1.0, 0.0])
    traced = len(traces)
    assert bool(solve([1.0, 0.5]).success) and len(traces) == traced  # the compiled program, reused
    assert bool(result.success)
    assert abs(float(result.cost) - zoh_min_effort_cost(N, T)) < 1e-8

    pendulum = jd.models.Pendulum(input_limits=(-2.0, 2.0))

    def swing_up(x0):
        return trajopt.ilqr(pendulum, x0, jnp.zeros((100, 1)), 0.05, lambda t, x, u: u @ u,
                            final_state=jnp.array([np.pi, 0.0]), max_iterations=1000,
                            constraint_tol=1e-5)

    x0s = jnp.stack([jnp.linspace(-0.3, 0.3, 4), jnp.zeros(4)], axis=1)
    batch = jax.jit(jax.vmap(swing_up))(x0s)
    assert bool(jnp.all(batch.success))
    assert float(jnp.max(jnp.abs(batch.knot_inputs))) <= 2.0 + 1e-5  # bounds active and respected
    assert float(jnp.max(jnp.abs(batch.knot_inputs))) > 1.9
    single = swing_up(x0s[1])
    np.testing.assert_allclose(batch.knot_inputs[1], single.knot_inputs, atol=1e-6)
    # the same discretization by transcription (RK4, inputs held) and IPOPT: the same optimum
    prog = trajopt.DirectTranscription(pendulum, 101, duration=5.0, rule="rk4")
    prog.set_initial_state(x0s[1]).set_final_state([np.pi, 0.0]).add_running_cost(lambda t, x, u: u @ u)
    reference = prog.solve(states=np.asarray(single.knot_states),
                           inputs=np.asarray(jnp.concatenate([single.knot_inputs, single.knot_inputs[-1:]])))
    assert reference.success
    assert abs(float(single.cost) - reference.cost) < 1e-4 * reference.cost


def test_ilqr_failures_are_statuses_with_messages():
    """Each way an iLQR solve can fail is its own status (never an exception inside jit): the
    budget spent; a goal out of reach of the input bounds (|u| <= 0.01 cannot bring the double
    integrator from (1, 0) to the origin in T = 2 s: it moves at most 0.01 T^2 / 2 = 0.02); a
    non-finite start. A batch reports one status and message per member."""
    plant, S = jd.models.DoubleIntegrator(), trajopt.ILQRStatus

    def solve(x0, **options):
        return trajopt.ilqr(plant, x0, jnp.zeros((20, 1)), 0.1, lambda t, x, u: u @ u, final_state=jnp.zeros(2),
                            **options)

    spent = solve(jnp.array([1.0, 0.0]), max_iterations=1)
    assert int(spent.status) == S.MAXIMUM_ITERATIONS and not bool(spent.success)
    assert "max_iterations" in spent.message
    starts = jnp.array([[1.0, 0.0], [0.0, 0.0], [np.nan, 0.0]])
    batch = jax.vmap(lambda x0: solve(x0, input_bounds=(-0.01, 0.01), max_outer=3))(starts)
    assert [S(int(code)) for code in batch.status] == [S.GOAL_NOT_REACHED, S.SUCCESS, S.NONFINITE]
    assert float(batch.constraint_violation[0]) >= 0.98 - 1e-9
    assert list(batch.message) == [S.GOAL_NOT_REACHED.message, S.SUCCESS.message, S.NONFINITE.message]
    assert list(np.asarray(batch.success)) == [False, True, False]


def test_float32_collocation():
    with jax.enable_x64(False):
        result = min_effort(trajopt.DirectCollocation, 11).solve()
    assert result.success and abs(result.cost - 1.5) < 1e-8  # the program itself runs in float64
    with jax.enable_x64(False):
        fast = trajopt.ilqr(jd.models.DoubleIntegrator(), jnp.array([1.0, 0.0]), jnp.zeros((20, 1)), 0.1,
                            lambda t, x, u: u @ u, final_state=jnp.zeros(2), constraint_tol=1e-4)
        assert fast.knot_states.dtype == jnp.float32 and bool(fast.success)


def swing_up_program(name, N):
    """The swing-ups of the examples: from hanging at rest to upright at rest, integral of u^2."""
    if name == "acrobot":
        plant, goal, limit, T = jd.models.Acrobot(), [np.pi, 0, 0, 0], 10.0, 5.0
    else:
        plant, goal, limit, T = jd.models.CartPole(), [0, np.pi, 0, 0], 50.0, 3.0
    prog = trajopt.DirectCollocation(plant, N, duration=T).add_input_bounds(-limit, limit)
    prog.set_initial_state(np.zeros(4)).set_final_state(goal)
    return plant, prog.add_running_cost(lambda t, x, u: u @ u)


def segment_errors(plant, result):
    """Each segment simulated from its knot with the optimized first-order-hold input, at a
    tolerance far below the collocation's error: the collocation's local error."""
    ends = jax.jit(jax.vmap(lambda x, t0, t1: jd.simulate(plant, (t0, t1), x, inputs=result.inputs,
                                                          rtol=1e-11, atol=1e-12).final_state))
    simulated = ends(jnp.asarray(result.knot_states[:-1]), jnp.asarray(result.times[:-1]),
                     jnp.asarray(result.times[1:]))
    return np.max(np.abs(np.asarray(simulated) - result.knot_states[1:]))


@pytest.mark.slow  # ~30 s of IPOPT on 101 knots; the collocation's optimum is checked by default against closed forms (minimum effort, bang-bang)
def test_acrobot_swing_up():
    """From the straight line in state space and zero input: defects below 1e-8; each segment
    simulated from its knot with the optimized input lands on the next knot within 1% of the
    state's range (the collocation's local error with inputs on their bounds; the acrobot is
    too unstable to replay 5 s open loop, and refining the knots finds other local optima)."""
    plant, prog = swing_up_program("acrobot", 101)
    result = prog.solve(hessian="limited-memory")
    assert result.success and result.max_defect < 1e-8
    assert np.max(np.abs(result.knot_inputs)) <= 10.0 * (1 + 1e-6)
    np.testing.assert_allclose(result.knot_states[-1], [np.pi, 0, 0, 0], atol=1e-9)
    assert segment_errors(plant, result) < 0.01 * np.max(np.abs(result.knot_states))


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_cart_pole_swing_up_and_simulation_reproduces_it():
    """Defects below 1e-8; simulating the optimized input reproduces the collocated states to
    the collocation's accuracy: the segment-wise error falls at Hermite-Simpson's order (local
    error O(h^5)) when the knots are doubled, and the whole 3 s replays open loop."""
    plant, coarse = swing_up_program("cartpole", 51)
    result = coarse.solve(hessian="limited-memory")
    assert result.success and result.max_defect < 1e-8
    assert np.max(np.abs(result.knot_inputs)) <= 50.0 * (1 + 1e-6)
    np.testing.assert_allclose(result.knot_states[-1], [0, np.pi, 0, 0], atol=1e-9)
    _, fine = swing_up_program("cartpole", 101)
    refined = fine.solve(states=result.states, inputs=result.inputs, hessian="limited-memory")
    assert refined.success and refined.max_defect < 1e-8
    assert abs(refined.cost - result.cost) < 0.01 * result.cost  # the same local optimum, refined
    coarse_error, fine_error = segment_errors(plant, result), segment_errors(plant, refined)
    assert fine_error < coarse_error / 8
    whole = jd.simulate(plant, (0.0, refined.duration), refined.knot_states[0], inputs=refined.inputs,
                        rtol=1e-11, atol=1e-12)
    assert np.max(np.abs(np.asarray(whole.state(jnp.asarray(refined.times))) - refined.knot_states)) < 1e-3


def test_box_qp_matches_scipys_bounded_minimizer():
    """The projected-Newton box QP of the control-limited backward pass, against SciPy's
    L-BFGS-B on random convex QPs with some bounds active."""
    import scipy.optimize as so

    from jaxdrake.trajopt._ilqr import box_qp

    rng, active = np.random.default_rng(4), 0
    for m in (1, 2, 4):
        M = rng.normal(size=(m, m))
        H, g = M @ M.T + 0.5 * np.eye(m), 3 * rng.normal(size=m)
        lower, upper = -np.ones(m), np.ones(m)
        x, free, _ = box_qp(jnp.asarray(H), jnp.asarray(g), jnp.asarray(lower), jnp.asarray(upper), jnp.zeros(m))
        reference = so.minimize(lambda x: 0.5 * x @ H @ x + g @ x, np.zeros(m), jac=lambda x: H @ x + g,
                                bounds=list(zip(lower, upper)), method="L-BFGS-B", options={"gtol": 1e-12, "ftol": 1e-15})
        np.testing.assert_allclose(x, reference.x, atol=1e-7)
        on_bound = np.isclose(np.abs(np.asarray(x)), 1.0)
        np.testing.assert_array_equal(np.asarray(free), ~on_bound)
        active += on_bound.sum()
    assert active >= 2


def test_an_indefinite_quu_is_made_positive_definite_and_a_definite_one_is_kept():
    """The backward pass's fallback where the DDP curvature makes Q_uu indefinite: a definite
    matrix is returned as it is; an indefinite one gains the Gershgorin shift (the largest
    off-diagonal row sum less the diagonal, plus the largest |diagonal|), after which every
    Gershgorin disc, and so every eigenvalue, lies at or above that largest |diagonal|; for one
    input the result is |Q_uu|."""
    from jaxdrake.trajopt._ilqr import convexified

    rng = np.random.default_rng(7)
    M = rng.normal(size=(3, 3))
    definite = M @ M.T + 0.1 * np.eye(3)
    np.testing.assert_array_equal(convexified(jnp.asarray(definite)), definite)
    np.testing.assert_allclose(convexified(jnp.array([[-2.5]])), [[2.5]], rtol=1e-15)
    indefinite = np.array([[1.0, 2.0, 0.5], [2.0, -3.0, 1.0], [0.5, 1.0, 0.2]])
    shift = max(np.abs(indefinite).sum(1) - np.abs(np.diag(indefinite)) - np.diag(indefinite)) + 3.0   # = 9.0
    fixed = np.asarray(convexified(jnp.asarray(indefinite)))
    np.testing.assert_allclose(fixed, indefinite + shift * np.eye(3), rtol=1e-15)
    assert np.linalg.eigvalsh(fixed).min() >= 3.0 - 1e-12


@pytest.mark.parametrize("model", ["pendulum", pytest.param("acrobot", marks=pytest.mark.slow)])
def test_hermite_simpson_structured_derivatives_equal_autodiff_of_the_defect(model):
    """DirectCollocation's defect term is batched over the segments (each knot's f once) and
    brings its own Jacobian and Hessian (chain rule around one traced copy of f's
    derivatives, the Hessian's point-only part kept from the Jacobian's evaluation); values and
    derivatives equal those of the per-segment defect under JAX's autodiff, and central
    differences (check_derivatives). (The acrobot's generic Hessian
    compiles for ~20 s: -m slow.)"""
    from jaxdrake.trajopt._nlp import NonlinearProgram

    for plant in [jd.models.Pendulum() if model == "pendulum" else jd.models.Acrobot()]:
        prog = trajopt.DirectCollocation(plant, 6, duration=2.0).add_input_bounds(-10, 10)
        prog.set_initial_state(np.zeros(plant.num_states)).add_running_cost(lambda t, x, u: u @ u + x @ x)
        nlp = prog.nlp
        defect = nlp.constraints[0]
        assert defect.batched and defect.jacobian is not None and defect.curvature is not None
        plain = prog._segment_term(defect.name, prog._defect, defect.lower, defect.upper)
        generic = NonlinearProgram(nlp.num_variables, nlp.costs, [plain] + nlp.constraints[1:], nlp.lower, nlp.upper)
        rng = np.random.default_rng(1)
        z, lam = rng.normal(size=nlp.num_variables), rng.normal(size=nlp.num_constraints)
        np.testing.assert_allclose(nlp.constraint_values(z), generic.constraint_values(z), atol=1e-12)
        np.testing.assert_allclose(nlp.jacobian_values(z), generic.jacobian_values(z), atol=1e-12)
        # the Hessian from the curvatures kept by the Jacobian at z (IPOPT's order) and, at
        # another point, from curvatures it evaluates itself
        np.testing.assert_allclose(nlp.jacobian_values(z, for_hessian=True), generic.jacobian_values(z), atol=1e-12)
        np.testing.assert_allclose(nlp.hessian_values(z, lam, 0.7), generic.hessian_values(z, lam, 0.7), atol=1e-12)
        z2 = z + 0.1
        np.testing.assert_allclose(nlp.hessian_values(z2, lam, 0.7), generic.hessian_values(z2, lam, 0.7), atol=1e-12)
        check = nlp.check_derivatives(z)
        assert check["jacobian_error"] < 1e-6 * check["jacobian_scale"] and check["outside_pattern"] == 0
        assert check["hessian_error"] < 1e-5 * check["hessian_scale"]


@pytest.mark.slow  # 22 s; float32 runs are checked by default in test_statuses, test_polynomial, test_stochastic
def test_a_float32_session_simulates_the_optimized_inputs():
    """The programs run in float64 inside a float32 session; the result comes back in the
    session's precision and the plant keeps working outside them (regression: the rigid-body
    index arrays, converted as int64 inside the float64 programs, broke the float32 dynamics,
    and the result's trajectories were float64 arrays that a float32 simulation refused)."""
    with jax.enable_x64(False):
        plant = jd.models.CartPole()
        prog = trajopt.DirectCollocation(plant, 21, duration=3.0).add_input_bounds(-50, 50)
        prog.set_initial_state([0, 0, 0, 0]).set_final_state([0, np.pi, 0, 0])
        result = prog.add_running_cost(lambda t, x, u: u @ u).solve(hessian="limited-memory")
        assert result.success and result.inputs.coefficients.dtype == jnp.float32
        simulated = jd.simulate(plant, (0.0, 0.3), np.zeros(4), inputs=result.inputs)
        assert simulated.success and simulated.final_state.dtype == jnp.float32
        np.testing.assert_allclose(simulated.final_state, result.states(0.3), atol=0.05)
