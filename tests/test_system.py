"""The System contract: construction, pytree structure, frames, validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.models import Pendulum, SimpleCTExample, SimpleMixedCTDTExample


def test_sizes_flags_and_layout_of_a_mixed_system():
    sys = SimpleMixedCTDTExample()
    assert (sys.num_discrete_states, sys.num_continuous_states, sys.num_states) == (1, 1, 2)
    assert sys.sample_time == 1.0 and not sys.direct_feedthrough and sys.time_invariant
    xd, xc = sys.split_state(jnp.array([3.0, 4.0]))  # the notes' layout: x = [x_d; x_c]
    assert xd.tolist() == [3.0] and xc.tolist() == [4.0]


def test_numeric_parameters_are_leaves_and_structure_is_static():
    p = Pendulum(m=2.0, b=0.3)
    leaves = jax.tree.leaves(p)
    assert sorted(float(v) for v in leaves) == sorted([2.0, 0.5, 0.3, 9.81])
    grad = jax.grad(lambda p: p.dynamics(0.0, jnp.array([0.3, 0.2]), jnp.array([0.0]))[1])(p)
    # d(thetaddot)/db = -thetadot / (m l^2)
    assert np.isclose(grad.b, -0.2 / (2.0 * 0.25))
    assert p.state_frame.coordinates == ("theta", "thetadot")


def test_subclass_in_the_notes_style_with_parameters():
    class Ball(jd.System):
        g: float = 9.81

        def __init__(self, g=9.81):
            self.g = g
            super().__init__(num_continuous_states=2, num_outputs=1, direct_feedthrough=False)

        def dynamics(self, t, x, u):
            return jnp.array([x[1], -self.g])

        def output(self, t, x, u):
            return x[:1]

    traj = jd.simulate(Ball(), (0.0, 1.0), jnp.array([10.0, 0.0]), rtol=1e-10)
    np.testing.assert_allclose(traj.eval(1.0), [10.0 - 9.81 / 2], rtol=1e-10)
    dh_dg = jax.grad(lambda g: jd.simulate(Ball(g), (0.0, 1.0), jnp.array([10.0, 0.0])).eval(1.0)[0])(9.81)
    np.testing.assert_allclose(dh_dg, -0.5, rtol=1e-8)


def test_from_functions_continuous_discrete_mixed_and_params():
    ct = jd.System.from_functions(dynamics=lambda t, x, u, k: -k * x, num_states=1, params=2.0)
    assert ct.num_continuous_states == 1 and jax.tree.leaves(ct) == [2.0]
    np.testing.assert_allclose(jd.simulate(ct, (0, 1), 1.0, rtol=1e-10, atol=1e-12).eval(1.0), [np.exp(-2)], rtol=1e-9)
    dt = jd.System.from_functions(update=lambda t, x, u: 0.5 * x, num_states=2, sample_time=0.1)
    assert dt.num_discrete_states == 2 and dt.sample_time == 0.1
    with pytest.raises(ValueError, match="num_discrete_states"):
        jd.System.from_functions(lambda t, x, u: x, lambda t, x, u: x, num_states=2)
    with pytest.raises(ValueError, match="dynamics"):
        jd.System.from_functions(num_states=1)


def test_construction_errors_name_the_problem():
    with pytest.raises(ValueError, match="sample_time must be positive"):
        jd.System(num_discrete_states=1, sample_time=-1.0)
    with pytest.raises(ValueError, match="no discrete state"):
        jd.System(num_continuous_states=1, sample_time=0.1)
    with pytest.raises(TypeError, match="sample_time is traced .* but it is static"):   # not a raw conversion error
        jax.grad(lambda h: jd.LinearSystem([[0.9]], [[1.0]], sample_time=h).A[0, 0])(0.1)
    with pytest.raises(ValueError, match="non-negative int"):
        jd.System(num_continuous_states=-1)
    with pytest.raises(ValueError, match="state frame .* has 3 coordinates"):
        jd.System(num_continuous_states=2, state_frame=jd.Frame("S", ("a", "b", "c")))
    with pytest.raises(ValueError, match="u_min <= u_max"):
        Pendulum().with_input_limits(1.0, -1.0)
    with pytest.raises(ValueError, match=r"shape \(1,\)"):
        Pendulum().with_input_limits(jnp.zeros(3), jnp.ones(3))
    with pytest.raises(ValueError, match="repeats a coordinate"):
        jd.Frame("F", ("a", "a"))


def test_frames_default_and_lookup():
    sys = SimpleCTExample()
    assert sys.state_frame.name == "SimpleCTExampleState" and sys.state_frame.coordinates == ("x0",)
    assert sys.input_frame.dim == 0 and sys.output_frame.coordinates == ("x",)
    assert Pendulum().state_frame.index("thetadot") == 1
    with pytest.raises(KeyError, match="no coordinate 'phi'"):
        Pendulum().state_frame.index("phi")


def test_linear_system_matches_matrix_exponential():
    from scipy.linalg import expm

    A = np.array([[0.0, 1.0], [-2.0, -0.3]])
    B = np.array([[0.0], [1.0]])
    sys = jd.LinearSystem(A, B, C=[[1.0, 0.0]], D=[[0.0]])
    assert sys.num_inputs == 1 and sys.num_outputs == 1 and not sys.direct_feedthrough
    x0 = np.array([1.0, -0.5])
    traj = jd.simulate(sys, (0.0, 3.0), x0, rtol=1e-11, atol=1e-12)
    for t in [0.37, 1.0, 2.71, 3.0]:
        np.testing.assert_allclose(traj.state(t), expm(A * t) @ x0, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(traj.eval(t), [(expm(A * t) @ x0)[0]], rtol=1e-9, atol=1e-12)
    assert jd.LinearSystem(A, B, D=np.ones((2, 1))).direct_feedthrough


def test_discrete_linear_system_matches_matrix_powers():
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    B = np.array([[0.0], [0.1]])
    sys = jd.LinearSystem(A, B, sample_time=0.1)
    x0 = np.array([1.0, 2.0])
    traj = jd.simulate(sys, (0.0, 2.0), x0, inputs=lambda t: jnp.ones(1))
    x = x0.copy()
    for n in range(21):
        np.testing.assert_allclose(traj.state(0.1 * n), x, rtol=1e-12)
        x = A @ x + B[:, 0]


def test_linear_system_shape_errors():
    with pytest.raises(ValueError, match="A must be square"):
        jd.LinearSystem(np.ones((2, 3)))
    with pytest.raises(ValueError, match=r"B must have shape \(2, m\)"):
        jd.LinearSystem(np.eye(2), np.ones((3, 1)))
    with pytest.raises(ValueError, match=r"C must have shape \(p, 2\)"):
        jd.LinearSystem(np.eye(2), np.ones((2, 1)), C=np.ones((1, 3)))


def test_jax_transformations_of_a_systems_methods_work_for_array_holding_systems():
    """`jax.jit(plant.dynamics)` as a user writes it: systems holding arrays (a URDF plant, a
    LinearSystem) hash by identity, so the bound method is a cacheable function."""
    acrobot = jd.models.Acrobot()
    x, u = jnp.linspace(0.1, 0.4, 4), jnp.ones(1)
    np.testing.assert_allclose(jax.jit(acrobot.dynamics)(0.0, x, u), acrobot.dynamics(0.0, x, u), rtol=1e-12)
    for plant in (jd.LinearSystem([[0.0, 1.0], [-2.0, -0.5]], [[0.0], [1.0]]),):
        x, u = jnp.linspace(0.1, 0.4, plant.num_states), jnp.ones(plant.num_inputs)
        fast = jax.jit(plant.dynamics)
        np.testing.assert_allclose(fast(0.0, x, u), plant.dynamics(0.0, x, u), rtol=1e-12)
        batch = jax.vmap(fast, in_axes=(None, 0, None))(0.0, jnp.stack([x, 2 * x]), u)
        np.testing.assert_allclose(batch[1], plant.dynamics(0.0, 2 * x, u), rtol=1e-12)
        J = jax.jacrev(lambda x: fast(0.0, x, u))(x)
        e = 1e-6 * np.eye(plant.num_states)[0]
        np.testing.assert_allclose(J[:, 0], (plant.dynamics(0.0, x + e, u) - plant.dynamics(0.0, x - e, u)) / 2e-6,
                                   rtol=1e-6, atol=1e-8)
    linear = jd.LinearSystem([[0.0, 1.0], [-2.0, -0.5]], [[0.0], [1.0]])
    np.testing.assert_allclose(jax.jit(linear.dynamics)(0.0, jnp.array([1.0, 2.0]), jnp.array([3.0])),
                               [2.0, -2.0 - 1.0 + 3.0])


def test_full_state_and_check_shapes_are_the_contract_simulate_asks():
    """`full_state` takes a scalar for one state and names the frame for a wrong shape;
    `check_shapes` names a method that returns the wrong size, from shapes alone (a hybrid
    system's modes and a diagram's subsystems are checked as systems of their own)."""
    np.testing.assert_array_equal(SimpleCTExample().full_state(0.5), [0.5])
    with pytest.raises(ValueError, match=r"x0 has shape \(3,\), but Pendulum's state frame "
                                         r"PendulumState\(theta, thetadot\) needs shape \(2,\)"):
        Pendulum().full_state(jnp.zeros(3))
    t = jnp.zeros(())
    Pendulum().check_shapes(t, jnp.zeros(2))
    wrong = jd.System.from_functions(lambda t, x, u: jnp.zeros(3), num_states=2, num_inputs=2)
    for system in (wrong, jd.HybridSystem([wrong], []), jd.cascade(Pendulum(), wrong)):
        with pytest.raises(ValueError, match=r"FunctionSystem.dynamics returned shape \(3,\), expected \(2,\)"):
            system.check_shapes(t, jnp.zeros(system.num_states))


def test_output_sizes_inferred_once_still_follow_the_parameters():
    """The inferred number of outputs is remembered per output function and parameter shapes
    (lqr rebuilds its controller every call), yet a parameter that sets the size (a Python
    number, an array's shape) gives each system its own."""
    def zeros(t, x, u, n):
        return jnp.zeros(n)

    def project(t, x, u, P):
        return P @ u

    sizes = [jd.System.from_functions(output=zeros, params=n, num_states=0, num_inputs=1).num_outputs
             for n in (3, 4, 3)]
    shapes = [jd.System.from_functions(output=project, params=jnp.ones((k, 1)), num_states=0,
                                       num_inputs=1).num_outputs for k in (2, 5, 2)]
    assert sizes == [3, 4, 3] and shapes == [2, 5, 2]
    with pytest.raises(ValueError, match="output returns 4 values but num_outputs=3"):
        jd.System.from_functions(output=zeros, params=4, num_states=0, num_inputs=1, num_outputs=3)
