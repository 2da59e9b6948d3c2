"""Linearization and LQR against SciPy's Riccati solvers, closed forms and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

import jaxdrake as jd
from jaxdrake.control import lqr, solve_continuous_are, solve_discrete_are


def relative(a, b):
    return np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b))


@pytest.mark.parametrize("n, m", [(2, 1), (4, 1), (6, 2), (12, 4)])
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


def test_double_integrator_lqr_closed_form():
    """Q = I, R = 1: K = [1, sqrt(3)], S = [[sqrt(3), 1], [1, sqrt(3)]]."""
    result = lqr(jd.models.DoubleIntegrator(), np.eye(2), np.eye(1))
    np.testing.assert_allclose(result.K, [[1.0, np.sqrt(3)]], rtol=1e-12)
    np.testing.assert_allclose(result.S, [[np.sqrt(3), 1.0], [1.0, np.sqrt(3)]], rtol=1e-12)


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


def test_gradient_of_trace_S_wrt_a_link_mass_matches_finite_differences():
    Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.eye(1)
    x0 = jnp.array([jnp.pi, 0.0, 0.0, 0.0])
    cost = lambda m2: jnp.trace(lqr(jd.models.Acrobot(m2=m2), Q, R, x0=x0).S)
    g = jax.grad(cost)(1.0)
    fd = (cost(1.0 + 1e-5) - cost(1.0 - 1e-5)) / 2e-5
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_linearize_checks_the_operating_point():
    with pytest.raises(ValueError, match="not an equilibrium"):
        jd.linearize(jd.models.Pendulum(), jnp.array([1.0, 0.0]), jnp.zeros(1))
    lin = jd.linearize(jd.models.Pendulum(), jnp.array([1.0, 0.0]), jnp.zeros(1), check_equilibrium=False)
    np.testing.assert_allclose(lin.A, [[0.0, 1.0], [-9.81 / 0.5 * np.cos(1.0), -0.1 / 0.25]], rtol=1e-12)
    with pytest.raises(ValueError, match="hybrid"):
        jd.linearize(jd.models.BouncingBall(), jnp.array([2.0, 0.0]))
    with pytest.raises(ValueError, match=r"Q must be \(2, 2\)"):
        lqr(jd.models.DoubleIntegrator(), np.eye(3), np.eye(1))
