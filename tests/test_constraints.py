"""State constraints phi(x) = 0: projection of x0 and of long simulations onto the manifold."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd


class Rotation(jd.System):
    """xdot = omega [-x2, x1] on the unit circle phi(x) = x1^2 + x2^2 - 1 = 0."""

    omega: float

    def __init__(self, omega=1.0):
        self.omega = omega
        super().__init__(num_continuous_states=2, num_state_constraints=1, time_invariant=True,
                         direct_feedthrough=False)

    def dynamics(self, t, x, u):
        return self.omega * jnp.array([-x[1], x[0]])

    def state_constraints(self, x):
        return jnp.array([x[0] ** 2 + x[1] ** 2 - 1.0])


def test_initial_state_is_projected_onto_the_manifold():
    x0 = np.array([1.5, 2.0])  # radius 2.5: the nearest point on the circle is x0 / 2.5
    np.testing.assert_allclose(jd.simulation.project_to_constraints(Rotation(), jnp.asarray(x0)),
                               x0 / 2.5, rtol=1e-12)
    traj = jd.simulate(Rotation(), (0.0, 1.0), x0, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(traj.state(0.0), x0 / 2.5, rtol=1e-12)
    c, s = np.cos(1.0), np.sin(1.0)
    np.testing.assert_allclose(traj.final_state, np.array([[c, -s], [s, c]]) @ (x0 / 2.5), rtol=1e-9)


def test_projection_keeps_a_long_simulation_on_the_manifold():
    # forward Euler spirals outwards: |x| grows by sqrt(1 + h^2) a step
    free = jd.simulate(Rotation(), (0.0, 50.0), jnp.array([1.0, 0.0]), solver="euler", dt=0.01,
                       max_steps=6000)
    assert float(jnp.linalg.norm(free.final_state)) == pytest.approx((1 + 1e-4) ** 2500, rel=1e-9)
    kept = jd.simulate(Rotation(), (0.0, 50.0), jnp.array([1.0, 0.0]), solver="euler", dt=0.01,
                       max_steps=6000, constraint_projection=True)
    steps = kept.breakpoints()
    assert len(steps) == 5001
    np.testing.assert_allclose(np.linalg.norm(np.asarray(kept.state(steps)), axis=1), 1.0, atol=1e-12)
    # between steps the dense output is a chord: inside by at most h^2 / 8
    between = np.linalg.norm(np.asarray(kept.state(steps[:-1] + 0.005)), axis=1)
    assert np.all(np.abs(between - 1.0) < 0.01**2)
    # the phase still advances at omega (Euler's phase error is O(h^2) a unit of time)
    angle = np.arctan2(kept.final_state[1], kept.final_state[0])
    assert np.angle(np.exp(1j * (angle - 50.0))) == pytest.approx(0.0, abs=2e-3)


def test_unreachable_manifold_is_a_status():
    class Impossible(Rotation):
        def state_constraints(self, x):
            return jnp.array([x[0] ** 2 + x[1] ** 2 + 1.0])  # no real solution

    with pytest.raises(jd.SimulationError, match="state constraints"):
        jd.simulate(Impossible(), (0.0, 1.0), jnp.array([1.0, 0.0]))


def test_gradient_through_the_projection():
    # the projected x0 is x0 / |x0|; d(x_final[0]) / d x0 follows by the chain rule
    f = lambda x0: jd.simulate(Rotation(), (0.0, 0.5), x0, rtol=1e-12, atol=1e-12).final_state[0]
    x0 = jnp.array([1.5, 2.0])
    c, s = np.cos(0.5), np.sin(0.5)
    r = 2.5
    dproj = (np.eye(2) - np.outer(x0, x0) / r**2) / r
    np.testing.assert_allclose(jax.grad(f)(x0), np.array([c, -s]) @ dproj, rtol=1e-8)
