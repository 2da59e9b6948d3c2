"""Polynomials and polynomial systems: arithmetic against direct evaluation, calculus against
autodiff, Taylor coefficients against closed forms, conversions against the original dynamics,
and structure-preserving composition against the equivalent diagram."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.analysis import taylor_polynomial_system, to_trig_coordinates, trig_polynomial_system
from jaxdrake.polynomials import Polynomial, taylor_polynomial
from jaxdrake.systems import PolynomialSystem

RNG = np.random.default_rng(7)


def test_arithmetic_matches_direct_evaluation():
    x, y, z = Polynomial.variables_of(3)
    p = (x + 2 * y - z) ** 3 - 4 * x * y + 0.5
    q = p * (y - 1) - p.substitute([y, z, x]) / 3
    for point in RNG.normal(size=(20, 3)):
        a, b, c = point
        pv = (a + 2 * b - c) ** 3 - 4 * a * b + 0.5
        pv_sub = (b + 2 * c - a) ** 3 - 4 * b * c + 0.5
        assert np.isclose(float(q(point)), pv * (b - 1) - pv_sub / 3, rtol=1e-12)
    # batched evaluation and evaluation under jit / vmap agree
    points = RNG.normal(size=(50, 3))
    np.testing.assert_allclose(np.asarray(q(points)), np.asarray(jax.jit(jax.vmap(lambda z: q(z)))(jnp.asarray(points))),
                               rtol=1e-12)


def test_derivatives_match_autodiff():
    x, y = Polynomial.variables_of(2)
    p = x**4 * y - 3 * x * y**3 + y**2 + 2
    point = jnp.array([0.4, -1.3])
    np.testing.assert_allclose(p.jacobian()(point), jax.grad(p)(point), rtol=1e-12)
    field = Polynomial(np.array([[1, 0], [0, 2]]), np.array([[0.0, 1.0], [-1.0, 0.0]]))  # (-y^2, x)
    np.testing.assert_allclose(field(point), [-point[1] ** 2, point[0]], rtol=1e-12)
    np.testing.assert_allclose(p.lie_derivative(field)(point), jax.grad(p)(point) @ field(point), rtol=1e-12)


def test_taylor_coefficients_match_closed_forms():
    sin5 = taylor_polynomial(lambda v: jnp.sin(v[0]), jnp.zeros(1), 5)
    expected = {1: 1.0, 3: -1 / 6, 5: 1 / 120}
    for row, c in zip(sin5.exponent_array, np.asarray(sin5.coefficients)):
        assert np.isclose(c, expected.get(int(row[0]), 0.0), atol=1e-14)
    # about a point other than 0, in the original variables: exp(a + b) to degree 3
    exp3 = taylor_polynomial(lambda v: jnp.exp(v[0] + v[1]), jnp.array([0.3, -0.1]), 3)
    for point in RNG.normal(scale=0.3, size=(10, 2)):
        h = point.sum() - 0.2
        assert np.isclose(float(exp3(point)), math.exp(0.2) * (1 + h + h**2 / 2 + h**3 / 6), rtol=1e-12)


def test_decision_coefficients_are_linear_and_bilinear_products_refused():
    from jaxdrake.polynomials import DecisionSpace

    space = DecisionSpace()
    x, y = Polynomial.variables_of(2)
    c = space.new(2)
    p = Polynomial(np.array([[1, 0], [0, 1]]), c)
    q = p * (x + y) + 1.0
    space.solution = np.array([2.0, -1.0])
    point = np.array([0.7, 0.2])
    assert np.isclose(q(point).value, (2 * 0.7 - 0.2) * 0.9 + 1.0)
    with pytest.raises(ValueError, match="bilinear"):
        p * p


def test_coefficients_are_differentiable_pytree_leaves():
    E = np.array([[0], [1], [2]])
    value = lambda c: Polynomial(E, c)(jnp.array([1.5]))
    np.testing.assert_allclose(jax.grad(value)(jnp.array([1.0, 2.0, 3.0])), [1.0, 1.5, 2.25])


def test_polynomial_system_simulates_like_the_same_system_written_by_hand():
    x, = Polynomial.variables_of(1)
    f = Polynomial(np.array([[1], [3]]), np.array([[-1.0], [1.0]]))  # xdot = -x + x^3
    system = PolynomialSystem(f)
    a = jd.simulate(system, (0.0, 5.0), jnp.array([0.9]))
    b = jd.simulate(jd.models.SimpleCTExample(), (0.0, 5.0), jnp.array([0.9]))
    np.testing.assert_allclose(a.final_state, b.final_state, rtol=1e-6)


def test_feedback_of_polynomial_systems_is_polynomial_and_equals_the_diagram():
    pendulum = taylor_polynomial_system(jd.models.Pendulum(), jnp.zeros(2), degree=3)
    controller = jd.LinearSystem(np.zeros((0, 0)), np.zeros((0, 2)), np.zeros((1, 0)), [[-2.0, -0.5]])
    closed = jd.feedback(pendulum, controller)
    assert isinstance(closed, PolynomialSystem)
    builder = jd.DiagramBuilder()
    p, k = builder.add(pendulum), builder.add(controller)
    builder.connect(p, k)
    builder.connect(k, p)
    builder.export_input(p)
    builder.export_output(p)
    diagram = builder.build()
    for state in RNG.normal(size=(5, 2)):
        np.testing.assert_allclose(closed.dynamics(0.0, state, jnp.array([0.3])),
                                   diagram.dynamics(0.0, state, jnp.array([0.3])), rtol=1e-12)
    filtered = PolynomialSystem(Polynomial(np.eye(3, dtype=int), np.array([[-1.0], [0.0], [1.0]])))
    cascade = jd.cascade(pendulum, filtered)  # w' = -w + thetadot
    assert isinstance(cascade, PolynomialSystem) and cascade.num_states == 3
    state, u = jnp.array([0.2, -0.4, 0.7]), jnp.array([0.1])
    np.testing.assert_allclose(cascade.dynamics(0.0, state, u),
                               jnp.concatenate([pendulum.dynamics(0.0, state[:2], u), jnp.array([-0.7 - 0.4])]),
                               rtol=1e-12)


def test_taylor_system_of_the_pendulum_has_the_sine_series():
    pendulum = jd.models.Pendulum()
    poly = taylor_polynomial_system(pendulum, jnp.zeros(2), degree=3)
    gml = pendulum.g / pendulum.l
    for row, c in zip(poly.f.exponent_array, np.asarray(poly.f.coefficients)):
        if tuple(row) == (3, 0, 0):
            assert np.isclose(c[1], gml / 6)
        if tuple(row) == (1, 0, 0):
            assert np.isclose(c[1], -gml)


@pytest.mark.parametrize("name", ["Pendulum", pytest.param("Acrobot", marks=pytest.mark.slow)])  # Acrobot: 24 s
def test_trig_substitution_reproduces_the_dynamics(name):
    system = getattr(jd.models, name)()
    n = system.num_states
    angles = list(range(n // 2))
    poly = trig_polynomial_system(system, angles)
    assert poly.num_states == n + len(angles) and poly.num_state_constraints == len(angles)
    assert poly.is_rational == (name == "Acrobot")
    for _ in range(5):
        x, u = jnp.asarray(RNG.normal(size=n) * 2), jnp.asarray(RNG.normal(size=system.num_inputs))
        z = to_trig_coordinates(x, angles)
        xdot = system.dynamics(0.0, x, u)
        expected = []
        for i in range(n):
            expected += [jnp.cos(x[i]) * xdot[i], -jnp.sin(x[i]) * xdot[i]] if i in angles else [xdot[i]]
        np.testing.assert_allclose(poly.dynamics(0.0, z, u), jnp.stack(expected), rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(poly.state_constraints(z), 0.0, atol=1e-12)


def test_non_trigonometric_dynamics_are_refused():
    with pytest.raises(ValueError, match="not a polynomial of degree"):
        trig_polynomial_system(jd.models.VanDerPol(), [0])


def test_float32_polynomial_system_and_conversion_run():
    with jax.enable_x64(False):
        f = Polynomial(np.array([[1], [3]]), np.array([[-1.0], [1.0]]))
        traj = jd.simulate(PolynomialSystem(f), (0.0, 5.0), jnp.array([0.9], jnp.float32), dense=False)
        assert traj.final_state.dtype == jnp.float32 and bool(traj.success)
        poly = trig_polynomial_system(jd.models.Pendulum(), [0])  # fitted in float64 internally
        xdot = poly.dynamics(0.0, jnp.array([0.1, 0.995, 0.3], jnp.float32), jnp.zeros(1, jnp.float32))
        assert xdot.dtype == jnp.float32
        np.testing.assert_allclose(xdot[2], -19.62 * 0.1 - 0.4 * 0.3, rtol=1e-5)


@pytest.mark.parametrize("dense_columns", [1024, 0, 2])
def test_affine_expressions_evaluate_like_the_numbers_they_stand_for(dense_columns, monkeypatch):
    """Arithmetic on decision expressions (scalars broadcast against vectors, numbers on either
    side, indexing, matrix maps) gives, at any value of the decision vector, what the same
    arithmetic gives on the numbers: with dense maps (a small program), sparse ones, and a
    dense expression meeting a sparse one (the program grew past the dense limit)."""
    from jaxdrake.polynomials import _affine
    from jaxdrake.polynomials import DecisionSpace

    monkeypatch.setattr(_affine, "DENSE_COLUMNS", dense_columns)

    space = DecisionSpace()
    t, x = space.new(), space.new(3)
    y = RNG.normal(size=4)
    space.solution = y
    tv, xv = y[0], y[1:]
    M = RNG.normal(size=(2, 3))
    merged = x.combined(np.array([0, 0, 1]), np.array([2, 0, 1]), np.array([2.0, -1.0, 3.0]), 2)
    cases = [(merged, [2 * xv[2] - xv[0], 3 * xv[1]]), (t + x, tv + xv), (x + t, xv + tv), (t + np.array([1.0, 2.0]), tv + np.array([1.0, 2.0])),
             (np.array([1.0, 2.0]) - t, np.array([1.0, 2.0]) - tv), (t * np.array([1.0, 2.0]), tv * np.array([1.0, 2.0])),
             (x[1] - 2.0 * t, xv[1] - 2 * tv), ((x - 1.0).sum(), (xv - 1).sum()), (M @ x, M @ xv), (x / 4.0, xv / 4)]
    for expression, number in cases:
        assert expression.shape == np.shape(number)
        np.testing.assert_allclose(expression.value, number, rtol=1e-14)
