"""Input limits: a saturation whose switching instants are located as events."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd

# xdot = -x + sat(u), u(t) = 2 sin t, |sat(u)| <= 1: the input saturates where 2 sin t = +-1
SWITCHES = np.array([np.pi / 6, 5 * np.pi / 6, 7 * np.pi / 6, 11 * np.pi / 6])


def saturated_closed_form(x0, ts):
    """Piecewise: x = x_p + (x(t_k) - x_p(t_k)) e^{-(t - t_k)} with x_p = sin t - cos t while
    free (u = 2 sin t) and x_p = +-1 while saturated."""
    pieces = np.concatenate([[0.0], SWITCHES, [np.inf]])
    particular = [lambda t: np.sin(t) - np.cos(t), lambda t: 1.0 + 0 * t,
                  lambda t: np.sin(t) - np.cos(t), lambda t: -1.0 + 0 * t,
                  lambda t: np.sin(t) - np.cos(t)]
    xk, out = x0, np.empty_like(ts)
    for k, xp in enumerate(particular):
        a, b = pieces[k], pieces[k + 1]
        inside = (ts >= a) & (ts <= b)
        out[inside] = xp(ts[inside]) + (xk - xp(a)) * np.exp(-(ts[inside] - a))
        if np.isfinite(b):
            xk = xp(b) + (xk - xp(a)) * np.exp(-(b - a))
    return out


def saturated_system():
    return jd.LinearSystem([[-1.0]], [[1.0]]).with_input_limits(-1.0, 1.0)


def test_saturated_linear_system_matches_piecewise_closed_form():
    traj = jd.simulate(saturated_system(), (0.0, 6.5), 0.2, inputs=lambda t: 2 * jnp.sin(t),
                       rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(traj.events["times"], SWITCHES, atol=1e-9)
    ts = np.linspace(0.0, 6.5, 651)
    np.testing.assert_allclose(np.asarray(traj.state(ts))[:, 0], saturated_closed_form(0.2, ts),
                               rtol=1e-9, atol=1e-11)
    # the input the system saw is the saturated one
    np.testing.assert_allclose(traj.input(np.array([0.1, 1.5, 4.0])),
                               [[2 * np.sin(0.1)], [1.0], [-1.0]], atol=1e-15)


def test_switching_instants_are_not_smeared_by_step_control():
    # with a loose tolerance the steps are long, but each saturation still starts on time
    traj = jd.simulate(saturated_system(), (0.0, 6.5), 0.2, inputs=lambda t: 2 * jnp.sin(t),
                       rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(traj.events["times"], SWITCHES, atol=1e-9)
    assert traj.num_steps < 40
    bps = traj.breakpoints()
    assert all(np.min(np.abs(bps - s)) < 1e-9 for s in SWITCHES)


def test_gradient_sees_the_shift_of_a_switching_instant():
    # u(t) = a sin t: the first switch is at asin(1/a); x(T) depends on a through it
    @jax.jit   # a traced: one program for the three values below
    def final(a):
        return jd.simulate(saturated_system(), (0.0, 2.0), 0.0, inputs=lambda t: a * jnp.sin(t),
                           rtol=1e-12, atol=1e-13).final_state[0]

    g = jax.grad(final)(2.0)
    h = 1e-5
    fd = (final(2.0 + h) - final(2.0 - h)) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_pendulum_with_torque_limits_never_exceeds_them():
    p = jd.models.Pendulum(input_limits=(-0.5, 0.5))
    traj = jd.simulate(p, (0.0, 4.0), jnp.array([0.0, 0.0]), inputs=lambda t: jnp.array([3 * jnp.cos(3 * t)]))
    u = np.asarray(traj.input(np.linspace(0, 4, 400)))
    assert u.max() == pytest.approx(0.5) and u.min() == pytest.approx(-0.5)
    assert len(traj.events["times"]) >= 6


def test_zero_order_hold_tape_jumping_past_a_limit_saturates():
    tape = jd.Trajectory.from_samples([0.0, 1.0, 2.0, 3.0], [0.5, 3.0, -0.25, 0.0], interpolation="zoh")
    traj = jd.simulate(saturated_system(), (0.0, 3.0), 0.0, inputs=tape, rtol=1e-11, atol=1e-13)
    # xdot = -x + v with v = 0.5, 1 (saturated), -0.25 on the three unit intervals
    x1 = 0.5 * (1 - np.exp(-1))
    x2 = 1 + (x1 - 1) * np.exp(-1)
    x3 = -0.25 + (x2 + 0.25) * np.exp(-1)
    np.testing.assert_allclose(traj.state(np.array([1.0, 2.0, 3.0]))[:, 0], [x1, x2, x3], rtol=1e-10)
