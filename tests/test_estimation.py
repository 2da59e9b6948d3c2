"""Kalman filters and observers (jaxdrake.estimation) against Drake, python-control, SciPy and
filterpy: steady-state gains, the time-varying covariance, EKF / UKF step by step, observer
error decay, the separation principle of LQG, and the refusals of bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate as si
import scipy.linalg as sl

import jaxdrake as jd
from jaxdrake.estimation import (ExtendedKalmanFilter, UnscentedKalmanFilter, kalman_filter,
                                 luenberger_observer, time_varying_kalman_filter)

M, LENGTH, DAMPING, G = 1.0, 0.5, 0.1, 9.81  # the pendulum's defaults (jd.models.Pendulum)


def relative(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


def measured_pendulum(output=lambda x: x[:1]):
    """jd.models.Pendulum with a partial measurement y = output(x)."""
    pendulum = jd.models.Pendulum()
    return jd.System.from_functions(dynamics=pendulum.dynamics, output=lambda t, x, u: output(x),
                                    num_states=2, num_inputs=1, time_invariant=True)


def lti_example(discrete):
    """An unstable 3-state plant with 2 inputs, 2 outputs and direct feedthrough."""
    A = np.array([[0.0, 1.0, 0.0], [3.0, -0.2, 1.0], [0.0, -1.0, -0.5]])
    if discrete:
        A = sl.expm(0.1 * A)
    B = np.array([[0.0, 0.0], [1.0, 0.0], [0.3, 1.0]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    D = np.array([[0.0, 0.1], [0.0, 0.0]])
    W = np.array([[0.2, 0.05, 0.0], [0.05, 0.5, 0.1], [0.0, 0.1, 0.3]])
    V = np.array([[0.01, 0.002], [0.002, 0.04]])
    return A, B, C, D, W, V


# ----- steady state ---------------------------------------------------------------------------

@pytest.mark.parametrize("discrete", [False, True])
def test_steady_state_gain_equals_drake_and_python_control(discrete):
    from pydrake.systems.estimators import DiscreteTimeSteadyStateKalmanFilter, SteadyStateKalmanFilter

    A, B, C, D, W, V = lti_example(discrete)
    plant = jd.LinearSystem(A, B, C, D, sample_time=0.1 if discrete else None)
    result = kalman_filter(plant, W, V)
    drake = (DiscreteTimeSteadyStateKalmanFilter if discrete else SteadyStateKalmanFilter)(A, C, W, V)
    import control   # ~5 s to import: only where it is used

    L, P, _ = (control.dlqe if discrete else control.lqe)(A, np.eye(3), C, W, V)
    assert relative(result.L, drake) < 1e-9
    assert relative(result.L, L) < 1e-9 and relative(result.P, P) < 1e-9
    # the observer is LTI at the plant's period: A - L C, [B - L D, L]
    observer = result.observer
    assert isinstance(observer, jd.LinearSystem) and observer.sample_time == plant.sample_time
    np.testing.assert_allclose(observer.A, A - drake @ C, atol=1e-9)
    np.testing.assert_allclose(observer.B, np.hstack([B - drake @ D, drake]), atol=1e-9)
    assert observer.input_frame.dim == 4 and not observer.direct_feedthrough


def test_steady_state_filter_of_a_nonlinear_plant_equals_drakes_at_the_upright():
    from pydrake.systems.estimators import SteadyStateKalmanFilter

    plant, upright = measured_pendulum(), jnp.array([np.pi, 0.0])
    W, V = np.diag([1e-3, 1e-2]), np.array([[1e-4]])
    result = kalman_filter(plant, W, V, x0=upright)
    A = np.array([[0.0, 1.0], [G / LENGTH, -DAMPING / (M * LENGTH**2)]])
    assert relative(result.L, SteadyStateKalmanFilter(A, np.array([[1.0, 0.0]]), W, V)) < 1e-9
    # Drake's observer of a nonlinear plant: its model f(x̂, u) plus L (y - g(x̂, u))
    x_hat, u, y = jnp.array([3.0, 0.2]), jnp.array([0.5]), jnp.array([3.1])
    observed, expected = jax.jit(lambda observer: (
        observer.dynamics(0.0, x_hat, jnp.concatenate([u, y])),
        plant.dynamics(0.0, x_hat, u) + result.L @ (y - x_hat[:1])))(result.observer)
    np.testing.assert_allclose(observed, expected, rtol=1e-12)


@pytest.mark.parametrize("discrete", [False, True])
def test_a_stochastic_plant_brings_its_own_noise_with_the_cross_term(discrete):
    """x' = A x + B u + G w, y = C x + H w (w of unit intensity, StochasticSystem's convention)
    plus v ~ V: the filter of SciPy's Riccati equation with the cross term s = G H^T."""
    A, B, C, _, _, V = lti_example(discrete)
    Gw = np.array([[0.3, 0.0], [1.0, 0.2], [0.0, 0.5]])
    Hw = np.array([[0.0, 0.1], [0.05, 0.0]])
    field = lambda t, x, u, w: jnp.asarray(A) @ x + jnp.asarray(B) @ u + jnp.asarray(Gw) @ w
    kwargs = dict(update=field, sample_time=0.1) if discrete else dict(dynamics=field, noise_time_constant=0.01)
    plant = jd.StochasticSystem.from_functions(
        output=lambda t, x, u, w: jnp.asarray(C) @ x + jnp.asarray(Hw) @ w,
        num_states=3, num_inputs=2, num_noise_inputs=2, **kwargs)
    result = kalman_filter(plant, V=V)
    Wx, Vy, N = Gw @ Gw.T, Hw @ Hw.T + V, Gw @ Hw.T
    if discrete:
        P = sl.solve_discrete_are(A.T, C.T, Wx, Vy, s=N)
        L = (A @ P @ C.T + N) @ np.linalg.inv(C @ P @ C.T + Vy)
    else:
        P = sl.solve_continuous_are(A.T, C.T, Wx, Vy, s=N)
        L = (P @ C.T + N) @ np.linalg.inv(Vy)
    assert relative(result.P, P) < 1e-9 and relative(result.L, L) < 1e-9


def test_steady_state_gain_is_differentiable():
    A, B, C, D, W, V = lti_example(False)
    trace_L = lambda scale: jnp.sum(kalman_filter(jd.LinearSystem(A, B, C, D), W, scale * V).L)
    value_and_derivative = jax.jit(lambda s: jax.jvp(trace_L, (s,), (1.0,)))
    fd = (value_and_derivative(1.0 + 1e-5)[0] - value_and_derivative(1.0 - 1e-5)[0]) / 2e-5
    np.testing.assert_allclose(value_and_derivative(1.0)[1], fd, rtol=1e-6)


# ----- observers ------------------------------------------------------------------------------

def estimation_loop(plant, observer):
    """Plant and observer side by side, the observer fed [u; y]; input [u (plant); u (observer)]."""
    builder = jd.DiagramBuilder()
    builder.add(plant, "plant")
    builder.add(observer, "observer")
    m = plant.num_inputs
    builder.connect("plant", ("observer", list(range(m, m + plant.num_outputs))))
    builder.export_input("plant")
    builder.export_input(("observer", list(range(m))))
    builder.export_output("observer")
    return builder.build("Estimation")


def test_observer_error_decays_at_the_rate_of_its_poles():
    A = np.array([[0.0, 1.0], [2.0, -0.5]])  # unstable: e^{t sqrt 2}-ish
    B, C = np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])
    poles = np.array([-2.0, -6.0])
    import scipy.signal

    L = scipy.signal.place_poles(A.T, C.T, poles).gain_matrix.T
    plant = jd.LinearSystem(A, B, C)
    loop = estimation_loop(plant, luenberger_observer(plant, L))
    x0, x_hat0 = np.array([1.0, -0.5]), np.zeros(2)
    u = lambda t: jnp.array([jnp.sin(3 * t), jnp.sin(3 * t)])
    traj = jd.simulate(loop, (0.0, 3.0), jnp.concatenate([x0, x_hat0]), inputs=u, rtol=1e-11, atol=1e-13)
    ts = np.linspace(0.0, 3.0, 7)
    states = np.asarray(traj.state(jnp.asarray(ts)))
    error = states[:, :2] - states[:, 2:]
    expected = np.stack([sl.expm((A - L @ C) * t) @ (x0 - x_hat0) for t in ts])  # independent of u
    np.testing.assert_allclose(error, expected, atol=1e-9)
    decay = np.log(np.linalg.norm(error[-1]) / np.linalg.norm(error[-2])) / (ts[-1] - ts[-2])
    assert abs(decay - poles.max()) < 0.02  # the slowest pole sets the rate


def test_lqg_closed_loop_has_the_controller_and_estimator_poles():
    """Separation principle in one line: feedback(plant, cascade(Kalman filter, LQR)) has the
    closed-loop poles eig(A - B K) and eig(A - L C); the same loop as a diagram (the plant given
    input limits it never reaches) has the same linearization and the same motion."""
    A, B, C, D, W, V = lti_example(False)
    plant = jd.LinearSystem(A, B, C, D)
    estimator = kalman_filter(plant, W, V)
    regulator = jd.control.lqr(plant, np.eye(3), np.eye(2))
    closed = jd.feedback(plant, jd.cascade(estimator.observer, regulator.controller))
    assert isinstance(closed, jd.LinearSystem) and closed.num_states == 6
    poles = np.sort_complex(np.linalg.eigvals(np.asarray(closed.A)))
    expected = np.sort_complex(np.concatenate([np.linalg.eigvals(A - B @ np.asarray(regulator.K)),
                                               np.linalg.eigvals(A - np.asarray(estimator.L) @ C)]))
    np.testing.assert_allclose(poles, expected, atol=1e-8)
    limited = plant.with_input_limits(-1e6 * jnp.ones(2), 1e6 * jnp.ones(2))
    diagram = jd.feedback(limited, jd.cascade(estimator.observer, regulator.controller))
    assert isinstance(diagram, jd.Diagram)
    np.testing.assert_allclose(jd.linearize(diagram, jnp.zeros(6)).A, closed.A, atol=1e-12)
    x0, ts = jnp.array([1.0, -0.5, 0.3, 0.0, 0.0, 0.0]), np.linspace(0.0, 2.0, 9)
    run = lambda system: jd.simulate(system, (0.0, 2.0), x0, rtol=1e-10, atol=1e-12).state(ts)
    np.testing.assert_allclose(run(diagram), run(closed), atol=1e-8)


# ----- time-varying -------------------------------------------------------------------------

def test_time_varying_filter_covariance_equals_scipys_riccati_integration():
    """Along a nominal sweep theta(t) = 2 - 0.75 t (a trajectory, not a solution: the filter
    only linearizes along it), P(t) and L(t) against SciPy's integration of the Riccati ODE."""
    plant, T, u_nominal = measured_pendulum(), 2.0, 0.3
    W, V, P0 = np.diag([1e-3, 2e-2]), np.array([[5e-3]]), np.array([[0.2, 0.01], [0.01, 0.3]])
    sweep = jd.Trajectory.from_samples([0.0, T], [[2.0, 0.0], [2.0 - 0.75 * T, 0.0]])
    result = time_varying_kalman_filter(plant, W, V, (0.0, T), P0=P0, x_nominal=sweep,
                                        u_nominal=jnp.array([u_nominal]), rtol=1e-10, atol=1e-12)
    C = np.array([[1.0, 0.0]])

    def riccati(t, p):  # hand-written Jacobian along the sweep
        P = p.reshape(2, 2)
        A = np.array([[0.0, 1.0], [-G / LENGTH * np.cos(2.0 - 0.75 * t), -DAMPING / (M * LENGTH**2)]])
        return (A @ P + P @ A.T - P @ C.T @ np.linalg.solve(V, C @ P) + W).reshape(-1)

    oracle = si.solve_ivp(riccati, (0.0, T), P0.reshape(-1), method="DOP853", rtol=1e-12, atol=1e-13,
                          dense_output=True)
    ts = np.linspace(0.0, T, 11)
    x_hat, uy = jnp.array([2.1, 0.1]), jnp.array([u_nominal, 2.05])

    @jax.jit  # one program for every evaluation
    def evaluate(result):
        expected = plant.dynamics(1.0, x_hat, uy[:1]) + result.L(1.0) @ (uy[1:] - x_hat[:1])
        return result.P(jnp.asarray(ts)), result.L(jnp.asarray(ts)), result.observer.dynamics(1.0, x_hat, uy), expected

    P, L, observed, expected = evaluate(result)
    P_ref = oracle.sol(ts).T.reshape(-1, 2, 2)
    assert relative(P, P_ref) < 1e-7
    assert relative(L, P_ref @ C.T / V[0, 0]) < 1e-7
    np.testing.assert_allclose(observed, expected, rtol=1e-12)


# ----- EKF and UKF against filterpy --------------------------------------------------------------

PERIOD = 0.05


def rk4(x, u):
    """One classical Runge-Kutta step of the pendulum over PERIOD (the test's own, in jnp)."""
    def f(x):
        return jnp.stack([x[1], (u[0] - DAMPING * x[1] - M * G * LENGTH * jnp.sin(x[0])) / (M * LENGTH**2)])
    k1 = f(x)
    k2 = f(x + PERIOD / 2 * k1)
    k3 = f(x + PERIOD / 2 * k2)
    k4 = f(x + PERIOD * k3)
    return x + PERIOD / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def horizontal_position(x):
    return jnp.array([LENGTH * jnp.sin(x[0])])


def noisy_run(W, V, steps=40, seed=3):
    """Inputs and measurements of the pendulum with process and measurement noise drawn by NumPy."""
    rng = np.random.default_rng(seed)
    x, us, ys = np.array([0.8, -0.5]), [], []
    for k in range(steps):
        u = np.array([0.5 * np.sin(0.3 * k)])
        ys.append(np.asarray(horizontal_position(x)) + rng.multivariate_normal(np.zeros(1), V))
        us.append(u)
        x = np.asarray(rk4(x, u)) + rng.multivariate_normal(np.zeros(2), W)
    return np.array(us), np.array(ys)


def our_priors(kalman, us, ys):
    """The filter's state after each sample, from a scan over its update."""
    def step(z, sample):
        t, input_output = sample
        z = kalman.update(t, z, input_output)
        return z, z
    samples = (PERIOD * jnp.arange(len(us)), jnp.concatenate([us, ys], axis=1))
    return jax.lax.scan(step, kalman.initial_state(), samples)[1]


FILTER_NOISE = dict(W=np.diag([1e-4, 4e-3]), V=np.array([[2e-3]]))
START = dict(x0=np.array([0.3, 0.0]), P0=np.diag([0.3, 0.5]))


def test_ekf_equals_filterpy_step_by_step():
    from filterpy.kalman import ExtendedKalmanFilter as Reference

    W, V = FILTER_NOISE["W"], FILTER_NOISE["V"]
    us, ys = noisy_run(W, V)
    plant = measured_pendulum(horizontal_position)
    ours = our_priors(ExtendedKalmanFilter(plant, W, V, period=PERIOD, **START), us, ys)

    class Pendulum(Reference):
        def predict_x(self, u=0):
            self.x = np.asarray(rk4(self.x, u))

    reference = Pendulum(dim_x=2, dim_z=1)
    reference.x, reference.P, reference.Q, reference.R = START["x0"].copy(), START["P0"].copy(), W, V
    jacobian = jax.jit(jax.jacfwd(rk4))
    measure_jacobian = jax.jit(jax.jacfwd(horizontal_position))
    for k, (u, y) in enumerate(zip(us, ys)):
        reference.update(y, lambda x: np.asarray(measure_jacobian(x)), lambda x: np.asarray(horizontal_position(x)))
        reference.F = np.asarray(jacobian(reference.x, u))
        reference.predict(u)
        assert relative(ours[k, :2], reference.x) < 1e-10, k
        assert relative(ours[k, 2:].reshape(2, 2), reference.P) < 1e-10, k


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.3, 2.0, 1.0)])
def test_ukf_equals_filterpy_step_by_step(alpha, beta, kappa):
    from filterpy.kalman import MerweScaledSigmaPoints
    from filterpy.kalman import UnscentedKalmanFilter as Reference

    W, V = FILTER_NOISE["W"], FILTER_NOISE["V"]
    us, ys = noisy_run(W, V)
    plant = measured_pendulum(horizontal_position)
    ukf = UnscentedKalmanFilter(plant, W, V, period=PERIOD, alpha=alpha, beta=beta, kappa=kappa, **START)
    ours = our_priors(ukf, us, ys)

    points = MerweScaledSigmaPoints(2, alpha=alpha, beta=beta, kappa=kappa)
    step = jax.jit(rk4)
    reference = Reference(dim_x=2, dim_z=1, dt=PERIOD, points=points,
                          fx=lambda x, dt, u: np.asarray(step(x, u)),
                          hx=lambda x: np.asarray(horizontal_position(x)))
    reference.x, reference.P, reference.Q, reference.R = START["x0"].copy(), START["P0"].copy(), W, V
    reference.sigmas_f = points.sigma_points(reference.x, reference.P)  # filterpy predicts first
    for k, (u, y) in enumerate(zip(us, ys)):
        reference.update(y)
        reference.predict(u=u)
        assert relative(ours[k, :2], reference.x) < 1e-10, k
        assert relative(ours[k, 2:].reshape(2, 2), reference.P) < 1e-10, k
    if alpha == 1.0:  # the library works in float32 too
        with jax.enable_x64(False):
            ukf = UnscentedKalmanFilter(plant, W, V, period=PERIOD, **START)
            single = our_priors(ukf, us.astype(np.float32), ys.astype(np.float32))
        assert single.dtype == jnp.float32
        np.testing.assert_allclose(single, ours, rtol=1e-3, atol=1e-4)


def ukf_loop_error(theta0):
    """The squared estimation error after 2 s of a UKF watching the pendulum (its horizontal
    position) swing from theta0, the filter starting from x̂ = 0."""
    plant = measured_pendulum(horizontal_position)
    ukf = UnscentedKalmanFilter(plant, **FILTER_NOISE, period=PERIOD, P0=np.diag([0.3, 0.5]))
    loop = estimation_loop(plant, ukf)
    x0 = jnp.concatenate([ukf.initial_state(), jnp.stack([theta0, 0.0])])  # discrete part first
    traj = jd.simulate(loop, (0.0, 2.0), x0, solver="rk4", dt=PERIOD / 5, inputs=lambda t: jnp.zeros(2))
    plant_state, filter_state = (loop.subsystem_state(i, traj.final_state) for i in (0, 1))
    return jnp.sum((plant_state - ukf.estimate(filter_state)) ** 2)


def test_ukf_runs_in_simulate_under_vmap():
    errors = jax.jit(jax.vmap(ukf_loop_error))(jnp.array([0.3, 0.5, 0.7]))
    assert np.all(np.asarray(errors) < 1e-3 * np.array([0.3, 0.5, 0.7]) ** 2)  # found the swing


@pytest.mark.slow  # reverse mode through simulate's loop; test_ukf_is_differentiable covers the filter's step
def test_ukf_is_differentiable_through_simulate():
    gradient = jax.jit(jax.grad(ukf_loop_error))(0.5)
    fd = (ukf_loop_error(0.5 + 1e-5) - ukf_loop_error(0.5 - 1e-5)) / 2e-5
    np.testing.assert_allclose(gradient, fd, rtol=1e-5)


@pytest.mark.parametrize("kind", [pytest.param(ExtendedKalmanFilter, marks=pytest.mark.slow),  # the UKF's covers the step
                                  UnscentedKalmanFilter])
def test_filters_are_differentiable(kind):
    """d/ds of the final covariance's trace, W scaled by s, against central differences."""
    W, V = FILTER_NOISE["W"], FILTER_NOISE["V"]
    us, ys = noisy_run(W, V, steps=20)
    plant = measured_pendulum(horizontal_position)

    def spread(s):
        kalman = kind(plant, s * W, V, period=PERIOD, **START)
        final = our_priors(kalman, us, ys)[-1]
        return jnp.trace(kalman.covariance(final)) + jnp.sum(kalman.estimate(final))

    value_and_grad = jax.jit(jax.value_and_grad(spread))
    fd = (value_and_grad(1.0 + 1e-6)[0] - value_and_grad(1.0 - 1e-6)[0]) / 2e-6
    np.testing.assert_allclose(value_and_grad(1.0)[1], fd, rtol=1e-6)


def test_ekf_on_a_linear_plant_tends_to_the_steady_state_filter():
    A, B, C, D, W, V = lti_example(True)
    plant = jd.LinearSystem(A, B, C, D, sample_time=0.1)
    ekf = ExtendedKalmanFilter(plant, W, V, P0=np.eye(3))
    z = jax.lax.fori_loop(0, 300, lambda k, z: ekf.update(0.0, z, jnp.zeros(4)), ekf.initial_state())
    assert relative(ekf.covariance(z), kalman_filter(plant, W, V).P) < 1e-9


# ----- bad input ----------------------------------------------------------------------------

def test_bad_noise_covariances_and_shapes_are_refused_with_the_remedy():
    A, B, C, D, W, V = lti_example(False)
    plant = jd.LinearSystem(A, B, C, D)
    with pytest.raises(ValueError, match=r"W \(the process noise intensity\) must be symmetric"):
        kalman_filter(plant, W + np.triu(np.ones((3, 3)), 1), V)
    with pytest.raises(ValueError, match="W .* must be positive semidefinite .* G @ G.T"):
        kalman_filter(plant, -W, V)
    with pytest.raises(ValueError, match="V .* must be positive definite .* add a small variance"):
        kalman_filter(plant, W, np.diag([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"V \(the measurement noise intensity\) must have shape \(2, 2\)"):
        kalman_filter(plant, W, np.eye(3))
    with pytest.raises(ValueError, match="non-finite"):
        kalman_filter(plant, W * np.nan, V)
    with pytest.raises(ValueError, match="deterministic: give W"):
        kalman_filter(plant)
    with pytest.raises(ValueError, match=r"L \(the observer gain of LinearSystem\) must have shape \(3, 2\)"):
        luenberger_observer(plant, np.ones((2, 3)))
    with pytest.raises(ValueError, match="hybrid"):
        kalman_filter(jd.models.BouncingBall(), np.eye(2), np.eye(2))


def test_an_undetectable_pair_is_refused():
    A = np.diag([1.0, -1.0])  # the unstable mode is not measured
    plant = jd.LinearSystem(A, np.ones((2, 1)), np.array([[0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"not detectable.*\[1\.\].*Measure more of the state"):
        kalman_filter(plant, np.eye(2), np.eye(1))
    # unobservable but stable is fine: detectable
    stable = jd.LinearSystem(np.diag([-1.0, 0.5]), np.ones((2, 1)), np.array([[0.0, 1.0]]))
    assert np.all(np.linalg.eigvals(np.diag([-1.0, 0.5]) - kalman_filter(stable, np.eye(2), np.eye(1)).L
                                    @ np.array([[0.0, 1.0]])).real < 0)
    discrete = jd.LinearSystem(np.diag([1.2, 0.5]), np.ones((2, 1)), np.array([[0.0, 1.0]]), sample_time=0.1)
    with pytest.raises(ValueError, match="not detectable.*unit circle"):
        kalman_filter(discrete, np.eye(2), np.eye(1))


def test_nonlinear_filters_refuse_bad_settings():
    plant = measured_pendulum()
    with pytest.raises(ValueError, match="continuous: give the filter's sample period"):
        ExtendedKalmanFilter(plant, np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match="W .* must have shape \\(2, 2\\)"):
        UnscentedKalmanFilter(plant, np.eye(3), np.eye(1), period=0.1)
    with pytest.raises(ValueError, match="n \\+ lambda .* raise kappa"):
        UnscentedKalmanFilter(plant, np.eye(2), np.eye(1), period=0.1, kappa=-3.0)
    discrete = jd.LinearSystem(np.eye(2), sample_time=0.1)
    with pytest.raises(ValueError, match="runs at that period"):
        ExtendedKalmanFilter(discrete, np.eye(2), np.eye(2), period=0.2)
    noisy = jd.StochasticSystem.from_functions(update=lambda t, x, u, w: x + w, num_states=1,
                                               num_noise_inputs=1, sample_time=0.1)
    with pytest.raises(ValueError, match="stochastic.*additive noise"):
        ExtendedKalmanFilter(noisy, np.eye(1), np.eye(1))
