"""Hybrid plants of the notes: the bouncing ball (D.3.1), the rimless wheel and the compass
gait (ch. 4)."""

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


class CompassGaitStance(System):
    r"""The compass gait between impacts (Underactuated, ch. 4): two legs of length l joined
    at a hip of mass $m_h$, each leg a point mass m at distance b from the hip
    (a = l - b from the foot), the stance foot pinned; hip torque u between the legs.

    State $[\theta_{st}, \theta_{sw}, \dot\theta_{st}, \dot\theta_{sw}]$, both angles from the
    vertical, one sign convention. $H(q)\ddot q + C(q, \dot q)\dot q + G(q) = B u$ with
    $H = \begin{bmatrix} m_h l^2 + m(l^2 + a^2) & -m l b \cos(\theta_{sw} - \theta_{st}) \\
    \cdot & m b^2 \end{bmatrix}$,
    $C\dot q = m l b \sin(\theta_{st} - \theta_{sw})\,[-\dot\theta_{sw}^2,\ \dot\theta_{st}^2]$,
    $G = g\,[-(m_h l + m(a + l))\sin\theta_{st},\ m b \sin\theta_{sw}]$, $B = [-1, 1]^T$."""

    mass_hip: float
    mass_leg: float
    length_leg: float
    center_of_mass_leg: float
    gravity: float

    def __init__(self, mass_hip=10.0, mass_leg=5.0, length_leg=1.0, center_of_mass_leg=0.5, gravity=9.81):
        self.mass_hip, self.mass_leg, self.length_leg = mass_hip, mass_leg, length_leg
        self.center_of_mass_leg, self.gravity = center_of_mass_leg, gravity
        state = Frame("CompassGaitState", ("stance", "swing", "stancedot", "swingdot"))
        super().__init__(num_continuous_states=4, num_inputs=1, direct_feedthrough=False,
                         time_invariant=True, state_frame=state, output_frame=state,
                         input_frame=Frame("CompassGaitInput", ("hip_torque",)))

    def manipulator_dynamics(self, x):
        """(H, C qdot + G, B) at state x."""
        m, mh, l, b, g = self.mass_leg, self.mass_hip, self.length_leg, self.center_of_mass_leg, self.gravity
        a = l - b
        st, sw, vst, vsw = x[0], x[1], x[2], x[3]
        c, s = jnp.cos(sw - st), jnp.sin(st - sw)
        H = jnp.stack([jnp.stack([mh * l ** 2 + m * (l ** 2 + a ** 2), -m * l * b * c]),
                       jnp.stack([-m * l * b * c, m * b ** 2 * jnp.ones_like(c)])])
        bias = jnp.stack([-m * l * b * vsw ** 2 * s - (mh * l + m * (a + l)) * g * jnp.sin(st),
                          m * l * b * vst ** 2 * s + m * b * g * jnp.sin(sw)])
        return H, bias, jnp.array([-1.0, 1.0], x.dtype)

    def dynamics(self, t, x, u):
        H, bias, B = self.manipulator_dynamics(x)
        rhs = B * u[0] - bias
        det = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
        qdd = jnp.stack([H[1, 1] * rhs[0] - H[0, 1] * rhs[1], H[0, 0] * rhs[1] - H[1, 0] * rhs[0]]) / det
        return jnp.concatenate([x[2:], qdd])


def _swing_foot_reaches_the_ramp(gait, t, x, u):
    """The swing foot's height above the ramp is l (cos(st - gamma) - cos(sw - gamma)): zero
    when the legs make an isosceles triangle with the ramp, st + sw = 2 gamma."""
    return 2 * gait.slope - x[0] - x[1]


def _swing_leg_ahead(gait, t, x, u):
    """Only a foot in front of the stance foot lands (sw < st): the legs pass each other at
    mid-stride without a 'scuffing' impact."""
    return x[1] - x[0]


def _heel_strike(gait, t, x, u):
    r"""The inelastic impact of the swing foot, then the legs swap roles. With the biped as a
    planar floating base $[x_{toe}, y_{toe}, \theta_{st}, \theta_{sw}]$ at the old stance toe,
    its 4x4 mass matrix M and the new stance toe's Jacobian J, the impulse that stops that toe
    gives $v^+ = (I - M^{-1}J^T (J M^{-1} J^T)^{-1} J) v^-$, $v^- = [0, 0, \dot\theta_{st}, \dot\theta_{sw}]$."""
    leg = gait.modes[0]
    m, mh, l, b = leg.mass_leg, leg.mass_hip, leg.length_leg, leg.center_of_mass_leg
    a = l - b
    st, sw = x[0], x[1]
    cst, sst, csw, ssw = jnp.cos(st), jnp.sin(st), jnp.cos(sw), jnp.sin(sw)
    c = jnp.cos(sw - st)
    k = m * a + m * l + mh * l
    one = jnp.ones_like(st)
    M = jnp.stack([jnp.stack([(2 * m + mh) * one, 0 * one, k * cst, -m * b * csw]),
                   jnp.stack([0 * one, (2 * m + mh) * one, -k * sst, m * b * ssw]),
                   jnp.stack([k * cst, -k * sst, (m * a ** 2 + (m + mh) * l ** 2) * one, -m * l * b * c]),
                   jnp.stack([-m * b * csw, m * b * ssw, -m * l * b * c, m * b ** 2 * one])])
    J = jnp.stack([jnp.stack([one, 0 * one, l * cst, -l * csw]),
                   jnp.stack([0 * one, one, -l * sst, l * ssw])])
    v = jnp.stack([0 * one, 0 * one, x[2], x[3]])
    Minv_JT = jnp.linalg.solve(M, J.T)
    v_plus = v - Minv_JT @ jnp.linalg.solve(J @ Minv_JT, J @ v)
    return jnp.stack([sw, st, v_plus[3], v_plus[2]])


class CompassGait(HybridSystem):
    r"""The compass gait walking down a ramp (Underactuated, ch. 4; Drake's `CompassGait`, with
    its parameter names, defaults and state convention $[\theta_{st}, \theta_{sw},
    \dot\theta_{st}, \dot\theta_{sw}]$). Between impacts `CompassGaitStance`; heel strike when
    the swing foot reaches the ramp ahead of the stance foot ($\theta_{st} + \theta_{sw} =
    2\gamma$ with $\theta_{sw} < \theta_{st}$), an inelastic impact, and the legs swap. On the
    default slope (0.0525 rad) the passive walker has a stable limit cycle
    (`jd.analysis.limit_cycle`); input: the hip torque."""

    slope: float

    def __init__(self, mass_hip=10.0, mass_leg=5.0, length_leg=1.0, center_of_mass_leg=0.5,
                 gravity=9.81, slope=0.0525):
        self.slope = slope
        strike = Transition(0, and_guards(_swing_foot_reaches_the_ramp, _swing_leg_ahead), _heel_strike, 0,
                            name="heel strike")
        super().__init__([CompassGaitStance(mass_hip, mass_leg, length_leg, center_of_mass_leg, gravity)],
                         [strike])
