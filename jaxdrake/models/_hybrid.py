"""Hybrid plants of the notes: the bouncing ball (D.3.1) and the rimless wheel (ch. 4)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..systems import Frame, HybridSystem, System, Transition, and_guards


class BallFlightPhasePlant(System):
    r"""The ball in the air (the notes' `BallFlightPhasePlant`): $\ddot q = -g$, state
    $[q, \dot q]$, output the height $q$."""

    g: float

    def __init__(self, g=9.81):
        self.g = g
        super().__init__(num_continuous_states=2, num_outputs=1, direct_feedthrough=False,
                         time_invariant=True, state_frame=Frame("BallState", ("q", "qdot")),
                         output_frame=Frame("BallHeight", ("q",)))

    def dynamics(self, t, x, u):
        return jnp.stack([x[1], -self.g * jnp.ones_like(x[1])])

    def output(self, t, x, u):
        return x[:1]


def _ball_touches_ground(ball, t, x, u):
    return x[0] - ball.r  # q - r <= 0


def _ball_falls(ball, t, x, u):
    return x[1]  # qdot <= 0


def _ball_collision(ball, t, x, u):
    """qdot+ = -cor qdot-; the ball has stopped when the rebound speed is below 0.01."""
    x_plus = jnp.stack([x[0], -ball.cor * x[1]])
    return x_plus, x_plus[1] < ball.stop_speed


class BouncingBall(HybridSystem):
    r"""The notes' `BallPlant`: a ball of radius r in flight, with an impact when
    $q - r \le 0$ and $\dot q \le 0$ (`and_guards`) that reverses and scales its speed,
    $\dot q^+ = -e\,\dot q^-$ (coefficient of restitution e = `cor`), and stops the simulation
    when the rebound speed falls below `stop_speed` (0.01 in the notes).

    State $[q, \dot q]$ (height of the centre, vertical speed), output the height.
    """

    r: float
    cor: float
    stop_speed: float

    def __init__(self, g=9.81, r=1.0, cor=0.8, stop_speed=0.01):
        self.r, self.cor, self.stop_speed = r, cor, stop_speed
        impact = Transition(source=0, guard=and_guards(_ball_touches_ground, _ball_falls),
                            reset=_ball_collision, target=0, name="impact")
        super().__init__([BallFlightPhasePlant(g)], [impact])

    @property
    def g(self):
        return self.modes[0].g


class RimlessWheelStance(System):
    r"""The rimless wheel pivoting on one spoke (Underactuated, ch. 4): an inverted pendulum,
    $\ddot\theta = (g / l)\sin\theta$, with $\theta$ the stance spoke's angle from vertical."""

    l: float
    g: float

    def __init__(self, l=1.0, g=9.81):
        self.l, self.g = l, g
        state = Frame("RimlessWheelState", ("theta", "thetadot"))
        super().__init__(num_continuous_states=2, direct_feedthrough=False, time_invariant=True,
                         state_frame=state, output_frame=state)

    def dynamics(self, t, x, u):
        return jnp.stack([x[1], self.g / self.l * jnp.sin(x[0])])


def _spoke_lands_ahead(wheel, t, x, u):
    return wheel.slope + wheel.alpha - x[0]  # theta >= gamma + alpha


def _rolls_forward(wheel, t, x, u):
    return -x[1]


def _spoke_lands_behind(wheel, t, x, u):
    return x[0] - (wheel.slope - wheel.alpha)  # theta <= gamma - alpha


def _rolls_backward(wheel, t, x, u):
    return x[1]


def _step_forward(wheel, t, x, u):
    """The next spoke becomes the stance spoke; the impact keeps cos(2 alpha) of the speed."""
    return jnp.stack([x[0] - 2 * wheel.alpha, jnp.cos(2 * wheel.alpha) * x[1]])


def _step_backward(wheel, t, x, u):
    return jnp.stack([x[0] + 2 * wheel.alpha, jnp.cos(2 * wheel.alpha) * x[1]])


class RimlessWheel(HybridSystem):
    r"""The rimless wheel rolling on a slope (Underactuated, ch. 4; Drake's `RimlessWheel`).

    Spokes of length l, `num_spokes` of them at half-angle $\alpha = \pi / n$ apart, a ramp of
    slope $\gamma$. Between impacts the stance dynamics of `RimlessWheelStance`; when the next
    spoke touches down ($\theta = \gamma + \alpha$ rolling forward, $\gamma - \alpha$ backward)
    an inelastic impact resets $\theta^+ = \theta^- \mp 2\alpha$,
    $\dot\theta^+ = \cos(2\alpha)\dot\theta^-$. Rolling converges to the fixed point of the
    return map $\dot\theta^+ = \cot(2\alpha)\sqrt{4 (g/l) \sin\alpha \sin\gamma}$ (just after
    each impact). Parameters default to Drake's: l = 1, g = 9.81, 8 spokes, slope 0.08.
    """

    slope: float
    num_spokes: int = eqx.field(static=True)

    def __init__(self, l=1.0, g=9.81, num_spokes=8, slope=0.08):
        if not (isinstance(num_spokes, int) and num_spokes >= 3):
            raise ValueError(f"RimlessWheel: num_spokes must be an int >= 3, got {num_spokes!r}")
        self.slope = slope
        self.num_spokes = num_spokes
        forward = Transition(0, and_guards(_spoke_lands_ahead, _rolls_forward), _step_forward, 0,
                             name="step forward")
        backward = Transition(0, and_guards(_spoke_lands_behind, _rolls_backward), _step_backward, 0,
                              name="step backward")
        super().__init__([RimlessWheelStance(l, g)], [forward, backward])

    @property
    def alpha(self):
        return jnp.pi / self.num_spokes

    def rolling_fixed_point(self):
        r"""$\dot\theta^+ = \cot(2\alpha)\sqrt{4 (g/l)\sin\alpha\sin\gamma}$, the speed just after
        each impact of steady rolling."""
        stance = self.modes[0]
        a = self.alpha
        return jnp.sqrt(4 * stance.g / stance.l * jnp.sin(a) * jnp.sin(self.slope)) / jnp.tan(2 * a)
