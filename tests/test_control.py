"""Linearization and LQR against SciPy's and python-control's Riccati solvers, closed forms and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate as si
import scipy.linalg as sl

import jaxdrake as jd
from jaxdrake.control import lqr, solve_continuous_are, solve_discrete_are


def relative(a, b):
    return np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b))


@pytest.mark.parametrize("n, m", [(2, 1), pytest.param(4, 1, marks=pytest.mark.slow),  # ~3 s a size
                                  pytest.param(6, 2, marks=pytest.mark.slow), (12, 4)])
def test_riccati_solutions_match_scipy(n, m):
    rng = np.random.default_rng(n)
    A, B = rng.normal(size=(n, n)), rng.normal(size=(n, m))
    M = rng.normal(size=(n, n))
    Q, R, N = M @ M.T + np.eye(n), 0.5 * np.eye(m) + 0.1, 0.1 * rng.normal(size=(n, m))
    assert relative(solve_continuous_are(A, B, Q, R), sl.solve_continuous_are(A, B, Q, R)) < 1e-8
    assert relative(solve_continuous_are(A, B, Q, R, N), sl.solve_continuous_are(A, B, Q, R, s=N)) < 1e-8
    Ad = 0.3 * A
    assert relative(solve_discrete_are(Ad, B, Q, R), sl.solve_discrete_are(Ad, B, Q, R)) < 1e-8
    assert relative(solve_discrete_are(Ad, B, Q, R, N), sl.solve_discrete_are(Ad, B, Q, R, s=N)) < 1e-8


def test_small_riccati_linear_algebra_pivots_and_matches_numpy():
    """The elementwise Gauss-Jordan solve of small matrices (the DARE's doubling steps) pivots:
    a matrix whose leading entries are zero, a permutation, and a vmapped batch of random ones
    agree with LAPACK's through numpy."""
    from jaxdrake.control._riccati import _ELEMENTWISE_UP_TO, _mm, _solve

    rng = np.random.default_rng(3)
    n = _ELEMENTWISE_UP_TO
    rhs = rng.normal(size=(n, 2 * n))
    permutation = np.eye(n)[rng.permutation(n)]
    zero_lead = rng.normal(size=(n, n))
    zero_lead[0, 0] = zero_lead[1, 1] = 0.0
    for A in (permutation, zero_lead):
        np.testing.assert_allclose(_solve(jnp.asarray(A), jnp.asarray(rhs)), np.linalg.solve(A, rhs), rtol=1e-10, atol=1e-12)
    As, Bs = rng.normal(size=(2, 50, 4, 4))
    np.testing.assert_allclose(jax.vmap(_solve)(As, Bs), np.linalg.solve(As, Bs), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(jax.vmap(_mm)(As, Bs), As @ Bs, rtol=1e-14, atol=1e-14)


def test_double_integrator_lqr_closed_form():
    """Q = I, R = 1: K = [1, sqrt(3)], S = [[sqrt(3), 1], [1, sqrt(3)]]."""
    result = lqr(jd.models.DoubleIntegrator(), np.eye(2), np.eye(1))
    np.testing.assert_allclose(result.K, [[1.0, np.sqrt(3)]], rtol=1e-12)
    np.testing.assert_allclose(result.S, [[np.sqrt(3), 1.0], [1.0, np.sqrt(3)]], rtol=1e-12)
    assert result.success and result.status == jd.control.LQRStatus.SUCCESS and "stabilising" in result.message


def finite_difference_jacobians(system, x0, u0, eps=1e-6):
    f = lambda x, u: np.asarray(system.dynamics(0.0, jnp.asarray(x), jnp.asarray(u)))
    A = np.stack([(f(x0 + eps * e, u0) - f(x0 - eps * e, u0)) / (2 * eps) for e in np.eye(len(x0))], axis=1)
    B = np.stack([(f(x0, u0 + eps * e) - f(x0, u0 - eps * e)) / (2 * eps) for e in np.eye(len(u0))], axis=1)
    return A, B


PLANTS = {
    "acrobot": (jd.models.Acrobot, lambda p: (np.array([np.pi, 0, 0, 0.0]), np.zeros(1)),
                np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1)),
    "cart-pole": (jd.models.CartPole, lambda p: (np.array([0, np.pi, 0, 0.0]), np.zeros(1)),
                  np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1)),
    "quadrotor": (jd.models.Quadrotor, lambda p: (np.zeros(12), np.full(4, p.m * p.g / 4)),
                  np.eye(12), np.eye(4)),
}


@pytest.mark.parametrize("name", list(PLANTS))
def test_lqr_of_the_notes_plants_matches_scipy_and_stabilises(name):
    model, point, Q, R = PLANTS[name]
    plant = model()
    x0, u0 = point(plant)
    result = lqr(plant, Q, R, x0=x0, u0=u0)
    A_fd, B_fd = finite_difference_jacobians(plant, x0, u0)
    np.testing.assert_allclose(result.linearization.A, A_fd, atol=1e-6)
    np.testing.assert_allclose(result.linearization.B, B_fd, atol=1e-6)
    A, B = np.asarray(result.linearization.A), np.asarray(result.linearization.B)
    S = sl.solve_continuous_are(A, B, Q, R)
    assert relative(result.S, S) < 1e-8
    assert relative(result.K, np.linalg.solve(R, B.T @ S)) < 1e-8
    import control as ct   # ~5 s to import: only where it is used

    K_ct, S_ct, _ = ct.lqr(A, B, Q, R)
    assert relative(result.S, S_ct) < 1e-8 and relative(result.K, K_ct) < 1e-8
    assert np.max(np.linalg.eigvals(A - B @ np.asarray(result.K)).real) < 0
    closed = jd.feedback(plant, result.controller)
    perturbation = 0.05 * np.random.default_rng(0).standard_normal(len(x0))
    # converges at the rate of the slowest closed-loop pole (the cart-pole's cart is slow)
    slowest = np.max(np.linalg.eigvals(A - B @ np.asarray(result.K)).real)
    T = min(60.0, 20.0 / -slowest)
    traj = jd.simulate(closed, (0.0, T), jnp.asarray(x0 + perturbation), max_steps=20000)
    assert np.max(np.abs(np.asarray(traj.final_state) - x0)) < 1e-3 * np.max(np.abs(perturbation))


def test_discrete_lqr_matches_scipy_and_stabilises():
    h = 0.1
    plant = jd.LinearSystem([[1.0, h], [0.0, 1.0]], [[h * h / 2], [h]], sample_time=h)
    Q, R, N = np.diag([1.0, 0.5]), np.array([[0.2]]), np.array([[0.05], [0.0]])
    result = lqr(plant, Q, R, N=N)
    A, B = np.asarray(plant.A), np.asarray(plant.B)
    S = sl.solve_discrete_are(A, B, Q, R, s=N)
    assert relative(result.S, S) < 1e-8
    assert relative(result.K, np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A + N.T)) < 1e-8
    import control as ct   # ~5 s to import: only where it is used

    K_ct, S_ct, _ = ct.dlqr(A, B, Q, R, N)
    assert relative(result.S, S_ct) < 1e-8 and relative(result.K, K_ct) < 1e-8
    assert result.linearization.is_discrete
    traj = jd.simulate(jd.feedback(plant, result.controller), (0.0, 20.0), jnp.array([1.0, 0.0]))
    assert np.max(np.abs(traj.final_state)) < 1e-4


def test_continuous_lqr_with_a_cross_term_matches_scipy():
    plant = jd.models.DoubleIntegrator()
    Q, R, N = np.diag([2.0, 1.0]), np.array([[0.5]]), np.array([[0.3], [0.1]])
    result = lqr(plant, Q, R, N=N)
    S = sl.solve_continuous_are(np.asarray(plant.A), np.asarray(plant.B), Q, R, s=N)
    assert relative(result.S, S) < 1e-8
    assert relative(result.K, np.linalg.solve(R, np.asarray(plant.B).T @ S + N.T)) < 1e-8
    import control as ct   # ~5 s to import: only where it is used

    K_ct, S_ct, _ = ct.lqr(np.asarray(plant.A), np.asarray(plant.B), Q, R, N)
    assert relative(result.S, S_ct) < 1e-8 and relative(result.K, K_ct) < 1e-8


def test_gradient_of_trace_S_wrt_a_link_mass_matches_finite_differences():
    Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1)
    x0 = jnp.array([jnp.pi, 0.0, 0.0, 0.0])
    cost = lambda m2: jnp.trace(lqr(jd.models.Acrobot(m2=m2), Q, R, x0=x0).S)
    g = jax.grad(cost)(1.0)
    fd = (cost(1.0 + 1e-5) - cost(1.0 - 1e-5)) / 2e-5
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    # the plant can be built inside jit (its URDF is parsed on the host even while tracing)
    np.testing.assert_allclose(jax.jit(cost)(1.2), cost(1.2), rtol=1e-12)


def test_linearize_checks_the_operating_point():
    with pytest.raises(ValueError, match="not an equilibrium"):
        jd.linearize(jd.models.Pendulum(), jnp.array([1.0, 0.0]), jnp.zeros(1))
    lin = jd.linearize(jd.models.Pendulum(), jnp.array([1.0, 0.0]), jnp.zeros(1), check_equilibrium=False)
    np.testing.assert_allclose(lin.A, [[0.0, 1.0], [-9.81 / 0.5 * np.cos(1.0), -0.1 / 0.25]], rtol=1e-12)
    with pytest.raises(ValueError, match="hybrid"):
        jd.linearize(jd.models.BouncingBall(), jnp.array([2.0, 0.0]))
    with pytest.raises(ValueError, match=r"Q must be \(2, 2\)"):
        lqr(jd.models.DoubleIntegrator(), np.eye(3), np.eye(1))


# ----- finite-horizon / time-varying LQR ------------------------------------------------------

def test_time_varying_lqr_at_an_equilibrium_tends_to_the_infinite_horizon_solution():
    plant, upright = jd.models.Pendulum(), jnp.array([np.pi, 0.0])
    Q, R = np.diag([10.0, 1.0]), np.eye(1)
    result = jd.control.finite_horizon_lqr(plant, Q, R, (0.0, 20.0), x_nominal=upright)
    A, B = np.array([[0.0, 1.0], [9.81 / 0.5, -0.1 / 0.25]]), np.array([[0.0], [1 / 0.25]])
    S = sl.solve_continuous_are(A, B, Q, R)
    assert relative(result.S(0.0), S) < 1e-6
    assert relative(result.K(0.0), np.linalg.solve(R, B.T @ S)) < 1e-6
    np.testing.assert_allclose(result.S(20.0), np.zeros((2, 2)), atol=1e-12)  # S(tf) = Qf = 0


def pendulum_riccati_by_scipy(x_start, u_nominal, Q, R, Qf, T, m=1.0, l=0.5, b=0.1, g=9.81):
    """The nominal (forward) and the Riccati ODE (backward) with SciPy and the pendulum's
    Jacobians written by hand."""
    inertia = m * l * l
    f = lambda t, x: [x[1], (u_nominal - b * x[1] - m * g * l * np.sin(x[0])) / inertia]
    nominal = si.solve_ivp(f, (0.0, T), x_start, method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True)
    B = np.array([[0.0], [1 / inertia]])

    def riccati(t, s):
        theta = nominal.sol(t)[0]
        A = np.array([[0.0, 1.0], [-g / l * np.cos(theta), -b / inertia]])
        S = s.reshape(2, 2)
        return -(Q + S @ A + A.T @ S - S @ B @ np.linalg.solve(R, B.T @ S)).reshape(-1)

    backward = si.solve_ivp(riccati, (T, 0.0), Qf.reshape(-1), method="DOP853", rtol=1e-12,
                            atol=1e-12, dense_output=True)
    return nominal, backward, B


def test_time_varying_lqr_along_a_swing_matches_scipy():
    plant, T, u_nominal = jd.models.Pendulum(), 3.0, 0.4
    x_start = np.array([2.0, 0.0])
    Q, R, Qf = np.diag([5.0, 0.5]), np.array([[0.3]]), np.diag([20.0, 2.0])
    nominal = jd.simulate(plant, (0.0, T), jnp.asarray(x_start), inputs=lambda t: jnp.array([u_nominal]),
                          rtol=1e-11, atol=1e-12)
    result = jd.control.finite_horizon_lqr(plant, Q, R, (0.0, T), Qf=Qf, x_nominal=nominal,
                                           u_nominal=jnp.array([u_nominal]), rtol=1e-10, atol=1e-12)
    _, oracle, B = pendulum_riccati_by_scipy(x_start, u_nominal, Q, R, Qf, T)
    ts = np.linspace(0.0, T, 13)
    S_ref = oracle.sol(ts).T.reshape(-1, 2, 2)
    assert relative(result.S(jnp.asarray(ts)), S_ref) < 1e-7
    K_ref = np.stack([np.linalg.solve(R, B.T @ S) for S in S_ref])
    assert relative(result.K(jnp.asarray(ts)), K_ref) < 1e-7
    # between the knots K is a quartic fit: still exact to the integration tolerance
    t_mid = 0.5 * (np.asarray(result.K_trajectory.t_start[5:9]) + np.asarray(result.K_trajectory.t_end[5:9]))
    K_mid = np.stack([np.linalg.solve(R, B.T @ S) for S in oracle.sol(t_mid).T.reshape(-1, 2, 2)])
    assert relative(result.K(jnp.asarray(t_mid)), K_mid) < 1e-7


def test_time_varying_lqr_controller_tracks_and_its_cost_is_the_cost_to_go():
    """Closed around the plant from a small offset, the controller's realised cost
    x(T)' Qf x(T) + integral(x' Q x + u' R u) equals x(0)' S(0) x(0) (to O(offset^3))."""
    plant, T = jd.models.Pendulum(), 3.0
    Q, R, Qf = np.diag([5.0, 0.5]), np.array([[0.3]]), np.diag([20.0, 2.0])
    nominal = jd.simulate(plant, (0.0, T), jnp.array([2.0, 0.0]), rtol=1e-11, atol=1e-12)
    result = jd.control.finite_horizon_lqr(plant, Q, R, (0.0, T), Qf=Qf, x_nominal=nominal, rtol=1e-10)
    offset = jnp.array([1e-3, -2e-3])
    closed = jd.feedback(plant, result.controller)
    traj = jd.simulate(closed, (0.0, T), nominal.state(0.0) + offset, rtol=1e-11, atol=1e-14)
    ts = np.linspace(0.0, T, 6001)
    dx = np.asarray(traj.state(jnp.asarray(ts)) - nominal.state(jnp.asarray(ts)))
    du = np.asarray(jax.vmap(lambda t, x: result.controller.output(t, jnp.zeros(0), x))(
        jnp.asarray(ts), traj.state(jnp.asarray(ts))))
    running = np.einsum("ti,ij,tj->t", dx, Q, dx) + np.einsum("ti,ij,tj->t", du, R, du)
    realised = si.simpson(running, x=ts) + dx[-1] @ Qf @ dx[-1]
    predicted = float(offset @ result.S(0.0) @ offset)
    assert abs(realised - predicted) < 1e-3 * predicted
    assert np.linalg.norm(dx[-1]) < 0.2 * np.linalg.norm(offset)


def test_gradient_of_the_time_varying_cost_to_go_matches_finite_differences():
    Q, R = np.diag([10.0, 1.0]), np.eye(1)
    upright = jnp.array([np.pi, 0.0])
    cost = lambda m: jnp.trace(jd.control.finite_horizon_lqr(jd.models.Pendulum(m=m), Q, R, (0.0, 2.0),
                                                              x_nominal=upright, Qf=np.eye(2),
                                                              rtol=1e-10).S(0.0))
    g = jax.grad(cost)(1.0)
    fd = (cost(1.0 + 1e-4) - cost(1.0 - 1e-4)) / 2e-4
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_finite_horizon_lqr_rejects_bad_input():
    plant = jd.models.Pendulum()
    with pytest.raises(ValueError, match=r"Qf must be \(2, 2\)"):
        jd.control.finite_horizon_lqr(plant, np.eye(2), np.eye(1), (0.0, 1.0), Qf=np.eye(3))
    with pytest.raises(ValueError, match="nominal state trajectory has 1"):
        jd.control.finite_horizon_lqr(plant, np.eye(2), np.eye(1), (0.0, 1.0),
                                      x_nominal=jd.Trajectory.from_samples([0.0, 1.0], [0.0, 1.0]))
    with pytest.raises(ValueError, match="continuous"):
        jd.control.finite_horizon_lqr(jd.models.BouncingBall(), np.eye(2), np.eye(0), (0.0, 1.0))


# ----- swing-up and the switch to LQR -------------------------------------------------------

@pytest.mark.parametrize("model, x", [(jd.models.Acrobot, [0.3, -0.7, 1.2, -2.0]),
                                      (jd.models.CartPole, [0.4, 2.0, -0.5, 1.5])])
def test_collocated_pfl_gives_the_actuated_joint_the_desired_acceleration(model, x):
    plant, x = model(), jnp.asarray(x)
    u = jd.control.collocated_pfl(plant, x, 3.7)
    qdd = plant.forward_dynamics(x[:2], x[2:], u)  # articulated-body algorithm, not the PFL's H
    actuated = int(np.flatnonzero(np.asarray(plant.B)[:, 0])[0])
    np.testing.assert_allclose(qdd[actuated], 3.7, rtol=1e-10)


def upright_error(x, goal, angles):
    err = np.asarray(x) - goal
    err[..., angles] = (err[..., angles] + np.pi) % (2 * np.pi) - np.pi
    return np.max(np.abs(err), axis=-1)


def test_acrobot_swing_up_and_balance_torques_match_drakes_spong_controller():
    """Drake's AcrobotSpongController: LQR (Q = diag(10, 10, 1, 1), R = 1) where
    (x - x0)' S (x - x0) < 1e3, the swing-up elsewhere, saturated at +-20 N m."""
    examples = pytest.importorskip("pydrake.examples")
    drake = examples.AcrobotSpongController()
    context = drake.CreateDefaultContext()
    acrobot, goal = jd.models.Acrobot(), np.array([np.pi, 0.0, 0.0, 0.0])
    balance = lqr(acrobot, np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1), x0=goal)
    switch = jd.control.SwitchToLQR(jd.control.acrobot_spong_controller(acrobot), balance, angles=(0, 1),
                                    output_limits=(-20.0, 20.0))
    rng = np.random.default_rng(3)
    far = rng.uniform([-np.pi, -2, -3, -3], [np.pi, 2, 3, 3], (40, 4))
    near = goal + rng.uniform(-1, 1, (40, 4)) * [0.05, 0.1, 0.1, 0.1] + [2 * np.pi, 0, 0, 0] * rng.integers(-1, 2, (40, 1))
    checked = {0: 0, 1: 0}
    torque = jax.jit(lambda mode, x: switch.mode_output(mode, 0.0, jnp.zeros(0), x))
    for x in np.concatenate([far, near]):
        drake.get_input_port(0).FixValue(context, x)
        expected = drake.get_output_port(0).Eval(context)
        err = x - goal
        err[:2] = (err[:2] + np.pi) % (2 * np.pi) - np.pi
        mode = int(err @ np.asarray(balance.S) @ err < 1e3)
        ours = torque(mode, jnp.asarray(x))
        np.testing.assert_allclose(ours, expected, rtol=1e-9, atol=1e-9)
        checked[mode] += 1
    assert checked[0] > 30 and checked[1] > 30


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_acrobot_swing_up_switches_to_lqr_where_V_crosses_the_threshold_and_balances():
    acrobot, goal = jd.models.Acrobot(), np.array([np.pi, 0.0, 0.0, 0.0])
    balance = lqr(acrobot, np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1), x0=goal)
    switch = jd.control.SwitchToLQR(jd.control.acrobot_spong_controller(acrobot), balance, angles=(0, 1),
                                    enter=300.0, leave=3000.0, output_limits=(-20.0, 20.0))
    # q2 = 0 exactly would leave the direction of the first swing to rounding noise (the
    # outcome then flips with the tolerance); a small elbow angle decides it
    traj = jd.simulate(jd.feedback(acrobot, switch), (0.0, 20.0), jnp.array([0.1, -0.02, 0.0, 0.0]),
                       max_steps=8000)
    events = traj.events
    assert events["modes"][-1] == 1 and upright_error(traj.final_state, goal, [0, 1]) < 1e-3
    for t, mode, x in zip(events["times"], events["modes"], events["states"]):
        err = np.asarray(x) - goal
        err[:2] = (err[:2] + np.pi) % (2 * np.pi) - np.pi
        V = err @ np.asarray(balance.S) @ err
        assert V == pytest.approx(300.0 if mode == 1 else 3000.0, rel=1e-6)
    # the torque never exceeds the limit, in either mode
    ts = jnp.linspace(0.0, 20.0, 2001)
    torque = jax.vmap(lambda t: traj.system.mode_output(traj.mode(t), t, traj.state(t), jnp.zeros(1)))(ts)
    assert np.max(np.abs(np.asarray(torque))) <= 20.0 + 1e-9


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_cart_pole_swing_up_balances_a_batch():
    cart_pole, goal = jd.models.CartPole(), np.array([0.0, np.pi, 0.0, 0.0])
    balance = lqr(cart_pole, np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1), x0=goal)
    switch = jd.control.SwitchToLQR(jd.control.cart_pole_swing_up_controller(cart_pole), balance,
                                    angles=(1,), enter=100.0, leave=1000.0)
    closed = jd.feedback(cart_pole, switch)
    starts = 0.1 * jax.random.normal(jax.random.key(0), (64, 4))
    runs = jax.jit(jax.vmap(lambda x: jd.simulate(closed, (0.0, 10.0), x, max_steps=8000, dense=False)))(starts)
    assert np.all(np.asarray(runs.num_events) == 1)  # one switch into LQR, none back
    final = np.asarray(runs.final_state)
    pole = np.mod(final[:, 1], 2 * np.pi) - np.pi  # theta - pi, wrapped to [-pi, pi)
    assert np.all(np.abs(pole) < 1e-2) and np.all(np.abs(final[:, 3]) < 1e-2)  # the pole is balanced
    assert np.all(np.abs(final[:, 0]) < 0.1)  # and the cart (the slowest closed-loop pole) comes back


def test_switch_to_lqr_rejects_mismatched_controllers():
    acrobot = jd.models.Acrobot()
    balance = lqr(acrobot, np.eye(4), np.eye(1), x0=np.array([np.pi, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="swing-up controller maps 2 -> 1"):
        jd.control.SwitchToLQR(jd.control.lqr(jd.models.Pendulum(), np.eye(2), np.eye(1),
                                              x0=np.array([np.pi, 0.0])).controller, balance)
    with pytest.raises(ValueError, match="one input driving one joint"):
        jd.control.acrobot_spong_controller(jd.models.DoublePendulum())


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_riccati_derivatives_in_both_modes_match_finite_differences():
    """dS/dA by reverse mode (the transposed Lyapunov / Stein solves) equals forward mode and
    central differences, continuous and discrete."""
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    Q, R, W = np.eye(4), np.eye(2), rng.normal(size=(4, 4))
    for solve, A0 in ((solve_continuous_are, A), (solve_discrete_are, 0.3 * A)):
        loss = lambda A: jnp.sum(W * solve(A, B, Q, R))
        reverse, forward = jax.grad(loss)(A0), jax.jacfwd(loss)(A0)
        E = np.zeros((4, 4))
        E[1, 2] = 1e-6
        central = (loss(A0 + E) - loss(A0 - E)) / 2e-6
        np.testing.assert_allclose(reverse, forward, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(reverse[1, 2], central, rtol=1e-6)


def test_lqr_without_a_stabilising_solution_is_a_named_error():
    uncontrollable = jd.LinearSystem([[1.0, 0.0], [0.0, -1.0]], [[0.0], [1.0]])  # the unstable mode has no input
    with pytest.raises(ValueError, match="no stabilising solution"):
        lqr(uncontrollable, np.eye(2), np.eye(1))
    traced = jax.jit(lambda Q: lqr(uncontrollable, Q, np.eye(1)))(jnp.eye(2))  # inside jit: a status
    assert int(traced.status) == jd.control.LQRStatus.NO_STABILISING_SOLUTION and not bool(traced.success)
    assert "no stabilising solution" in traced.message
    with pytest.raises(ValueError, match="imaginary axis"):  # Q = 0 leaves the double integrator's modes unseen
        lqr(jd.models.DoubleIntegrator(), np.zeros((2, 2)), np.eye(1))
    discrete = jd.LinearSystem([[2.0, 0.0], [0.0, 0.5]], [[0.0], [1.0]], sample_time=0.1)
    with pytest.raises(ValueError, match="unit circle"):
        lqr(discrete, np.eye(2), np.eye(1))


def test_float32_lqr_of_the_upright_cart_pole_and_named_operating_point_errors():
    cartpole, upright = jd.models.CartPole(), np.array([0.0, np.pi, 0.0, 0.0])
    K64 = np.asarray(jd.control.lqr(cartpole, np.eye(4), np.eye(1), x0=upright).K)
    with jax.enable_x64(False):   # pi rounded to float32 leaves a derivative of ~2e-6: still an equilibrium
        K32 = jd.control.lqr(cartpole, np.eye(4), np.eye(1), x0=upright).K
        assert K32.dtype == jnp.float32
        with pytest.raises(ValueError, match="not an equilibrium"):
            jd.control.linearize(cartpole, np.array([0.0, 3.0, 0.0, 0.0]))
    np.testing.assert_allclose(np.asarray(K32), K64, rtol=1e-3)
    with pytest.raises(ValueError, match=r"x0 must hold cartpole's 4 states, got shape \(4, 4\).*weights come first"):
        jd.control.lqr(cartpole, upright, np.zeros(1), np.eye(4), np.eye(1))
    with pytest.raises(ValueError, match=r"u0 must hold cartpole's 1 input, got shape \(2,\)"):
        jd.control.linearize(cartpole, upright, np.zeros(2))
