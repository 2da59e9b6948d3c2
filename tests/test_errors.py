"""Bad input gets a clear Python error that names the problem."""

import jax
import jax.numpy as jnp
import pytest

import jaxdrake as jd
from jaxdrake.models import Pendulum


def test_wrong_initial_state_shape():
    with pytest.raises(ValueError, match=r"x0 has shape \(3,\).*PendulumState\(theta, thetadot\).*\(2,\)"):
        jd.simulate(Pendulum(), (0.0, 1.0), jnp.zeros(3))


def test_wrong_input_shape():
    with pytest.raises(ValueError, match=r"inputs\(t\) returns shape \(2,\).*PendulumInput\(tau\)"):
        jd.simulate(Pendulum(), (0.0, 1.0), jnp.zeros(2), inputs=lambda t: jnp.zeros(2))
    with pytest.raises(ValueError, match="has no inputs"):
        jd.simulate(jd.models.VanDerPol(), (0.0, 1.0), inputs=lambda t: jnp.zeros(1))
    with pytest.raises(TypeError, match="a Trajectory, a function of time or a constant u"):
        jd.simulate(Pendulum(), (0.0, 1.0), inputs="1.0")
    with pytest.raises(ValueError, match=r"inputs has shape \(2,\), but .*PendulumInput\(tau\)"):   # a constant u
        jd.simulate(Pendulum(), (0.0, 1.0), inputs=[1.0, 2.0])


def test_reversed_or_bad_tspan():
    with pytest.raises(ValueError, match="t0 < tf"):
        jd.simulate(Pendulum(), (1.0, 0.0))
    with pytest.raises(ValueError, match="t0 < tf"):
        jd.simulate(Pendulum(), (0.0, float("inf")))
    with pytest.raises(ValueError, match="pair"):
        jd.simulate(Pendulum(), 10.0)


def test_non_finite_initial_state():
    with pytest.raises(ValueError, match="x0 is not finite"):
        jd.simulate(Pendulum(), (0.0, 1.0), jnp.array([jnp.nan, 0.0]))


def test_state_becoming_non_finite():
    # xdot = log(x) - 1 from x0 = 1 drives x through 0, where the log is -inf then NaN
    sys = jd.System.from_functions(dynamics=lambda t, x, u: jnp.log(x) - 1.0, num_states=1)
    with pytest.raises(jd.SimulationError, match="non-finite") as info:
        jd.simulate(sys, (0.0, 10.0), 1.0)
    assert info.value.status == jd.SimulationStatus.NONFINITE_STATE
    traj = jd.simulate(sys, (0.0, 10.0), 1.0, throw=False)
    assert int(traj.status) == jd.SimulationStatus.NONFINITE_STATE
    assert 0.0 < float(traj.t_final) < 1.0 and bool(jnp.isfinite(traj.final_state).all())


def test_discrete_update_becoming_non_finite():
    # x+ = 1 / (x - 1) from x0 = 2: 2 -> 1 -> inf at the second sample time
    sys = jd.System.from_functions(update=lambda t, x, u: 1.0 / (x - 1.0), num_states=1, sample_time=0.5)
    with pytest.raises(jd.SimulationError, match="non-finite"):
        jd.simulate(sys, (0.0, 5.0), 2.0)


def test_max_steps_reached():
    with pytest.raises(jd.SimulationError, match="max_steps was reached") as info:
        jd.simulate(Pendulum(), (0.0, 100.0), jnp.array([1.0, 0.0]), max_steps=20)
    assert info.value.status == jd.SimulationStatus.MAX_STEPS_REACHED
    assert "t = " in str(info.value)


def test_bad_options():
    with pytest.raises(ValueError, match="unknown solver"):
        jd.simulate(Pendulum(), (0.0, 1.0), solver="rk45")
    with pytest.raises(ValueError, match="needs a step size dt"):
        jd.simulate(Pendulum(), (0.0, 1.0), solver="rk4")
    with pytest.raises(ValueError, match="rtol must be positive"):
        jd.simulate(Pendulum(), (0.0, 1.0), rtol=-1.0)
    with pytest.raises(TypeError, match="needs a jaxdrake.System"):
        jd.simulate(lambda t, x: x, (0.0, 1.0))
    with pytest.raises(TypeError, match=r"is a class: pass an instance, Rosenbrock23\(\)"):
        jd.simulate(Pendulum(), (0.0, 1.0), solver=jd.simulation.Rosenbrock23)
    with pytest.raises(ValueError, match="use 'exact' .* or 'stiff'"):
        jd.simulation.Rosenbrock23(jacobian="approximate")


def test_a_rosenbrock_step_out_of_steps_says_what_to_try_next():
    stiff = jd.simulation.Rosenbrock23(jacobian="stiff")
    with pytest.raises(jd.SimulationError, match="solver='rosenbrock23' .the exact Jacobian. may take fewer steps") as info:
        jd.simulate(Pendulum(), (0.0, 100.0), jnp.array([1.0, 0.0]), solver=stiff, max_steps=20)
    assert "with solver=jd.simulation.Rosenbrock23(jacobian='stiff')" not in str(info.value)   # not the one it ran
    with pytest.raises(jd.SimulationError, match="ran rosenbrock23 already: raise max_steps"):
        jd.simulate(Pendulum(), (0.0, 100.0), jnp.array([1.0, 0.0]), solver="rosenbrock23", max_steps=20)
    with pytest.raises(jd.SimulationError, match=r"Stiff solvers: solver='rosenbrock23' .*Rosenbrock23\(jacobian='stiff'\)"):
        jd.simulate(Pendulum(), (0.0, 100.0), jnp.array([1.0, 0.0]), max_steps=20)


def test_methods_returning_wrong_shapes_are_named():
    sys = jd.System.from_functions(dynamics=lambda t, x, u: jnp.zeros(3), num_states=2)
    with pytest.raises(ValueError, match=r"dynamics returned shape \(3,\), expected \(2,\)"):
        jd.simulate(sys, (0.0, 1.0))
    broken = jd.System.from_functions(dynamics=lambda t, x, u: x @ jnp.ones((5, 5)), num_states=2)
    with pytest.raises(ValueError, match="dynamics failed on a state of shape"):
        jd.simulate(broken, (0.0, 1.0))


def test_missing_methods_are_named():
    class NoDynamics(jd.System):
        def __init__(self):
            super().__init__(num_continuous_states=1)

    with pytest.raises(NotImplementedError, match="NoDynamics has continuous states but does not define dynamics"):
        jd.simulate(NoDynamics(), (0.0, 1.0))


def test_an_undeclared_parameter_and_a_missing_super_init_are_named():
    class Undeclared(jd.System):
        def __init__(self, k=1.0):
            self.k = k  # the notes' style, without the class annotation `k: float`
            super().__init__(num_continuous_states=1)

    with pytest.raises(AttributeError, match=r"cannot set 'k'.*declare each parameter.*`k: float`"):
        Undeclared()

    class NoSuperInit(jd.System):
        def __init__(self):
            pass

        def dynamics(self, t, x, u):
            return -x

    with pytest.raises(TypeError, match=r"NoSuperInit was not initialised.*super\(\).__init__"):
        jd.simulate(NoSuperInit(), (0.0, 1.0), jnp.ones(1))
    with pytest.raises(TypeError, match="not initialised"):
        jd.cascade(NoSuperInit(), Pendulum())


def test_forward_mode_through_the_default_simulate_names_the_option():
    import jax

    final = lambda x0, **kw: jd.simulate(Pendulum(), (0.0, 1.0), x0, **kw).final_state  # noqa: E731
    with pytest.raises(TypeError, match="autodiff='forward'"):
        jax.jacfwd(final)(jnp.array([1.0, 0.0]))
    forward = jax.jacfwd(lambda x0: final(x0, autodiff="forward"))(jnp.array([1.0, 0.0]))
    reverse = jax.jacrev(final)(jnp.array([1.0, 0.0]))
    assert jnp.allclose(forward, reverse, rtol=1e-6)


def test_a_nan_parameter_is_named():
    with pytest.raises(ValueError, match=r"parameter Pendulum.b is NaN"):
        jd.simulate(Pendulum(b=float("nan")), (0.0, 1.0), jnp.array([1.0, 0.0]))


def test_a_finite_time_blow_up_says_so():
    # xdot = x^2 from x(0) = 1: x = 1 / (1 - t) escapes at t = 1
    blow_up = jd.System.from_functions(dynamics=lambda t, x, u: x ** 2, num_states=1)
    with pytest.raises(jd.SimulationError, match="blow-up") as info:
        jd.simulate(blow_up, (0.0, 2.0), 1.0)
    assert abs(float(str(info.value).split("t = ")[1].split(" ")[0]) - 1.0) < 1e-3


def test_a_float64_constant_in_a_float32_simulation_is_named_with_the_remedy():
    """With x64 on, a float32 x0 makes a float32 simulation; a controller holding
    jnp.array([...]) of Python floats computes in float64, which met the state deep inside
    the loop as a concatenation's or a scan carry's dtype error."""
    assert jax.config.jax_enable_x64   # tests/conftest.py
    pendulum = Pendulum()
    pd = jd.System.from_functions(output=lambda t, x, y: -10.0 * (y[:1] - jnp.array([jnp.pi])) - y[1:],
                                  num_states=0, num_inputs=2, num_outputs=1)
    with pytest.raises(TypeError, match=r"state is float32.*computes part of it in float64.*x\.dtype"):
        jd.simulate(jd.feedback(pendulum, pd), (0.0, 0.5), jnp.array([0.5, 0.0], jnp.float32))
    follows = jd.System.from_functions(output=lambda t, x, y: -10.0 * (y[:1] - jnp.array([jnp.pi], y.dtype)) - y[1:],
                                       num_states=0, num_inputs=2, num_outputs=1)
    assert jd.simulate(jd.feedback(pendulum, follows), (0.0, 0.5), jnp.array([0.5, 0.0], jnp.float32)).success
