"""Bad input gets a clear Python error that names the problem."""

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
    with pytest.raises(TypeError, match="Trajectory or a function of time"):
        jd.simulate(Pendulum(), (0.0, 1.0), inputs=[1.0])


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
