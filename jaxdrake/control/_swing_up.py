r"""Swing-up by energy shaping and the hybrid switch to LQR (Underactuated ch. 3; Drake's
`AcrobotSpongController`).

Collocated partial feedback linearization: split the manipulator equations
$H\ddot q + \phi = B u$ ($\phi = C\dot q + G + b\circ\dot q$) into passive (p) and actuated (a)
rows. For a desired actuated acceleration $\ddot q_a^d$, the passive rows give
$\ddot q_p = -H_{pp}^{-1}(H_{pa}\ddot q_a^d + \phi_p)$ and the actuated rows the input
$u = H_{ap}\ddot q_p + H_{aa}\ddot q_a^d + \phi_a$.

- Acrobot (Spong 1994, as Drake's `AcrobotSpongController`): $u = u_p - k_e\tilde E\dot q_2$,
  $u_p$ the PFL of $\ddot q_2^d = -k_p q_2 - k_d\dot q_2$, $\tilde E = E - E_{up}$, saturated.
- Cart-pole: $\ddot x^d = k_e \dot\theta\cos\theta\,\tilde E - k_p x - k_d \dot x$, with
  $\tilde E = \tfrac12 m_p l^2\dot\theta^2 - m_p g l\cos\theta - m_p g l$ the pole's energy error.

`SwitchToLQR` is the hybrid controller: mode 0 runs the swing-up controller, mode 1 the LQR;
it enters the LQR when the cost-to-go $V = \tilde x^T S\tilde x$ (angles wrapped about the
goal) falls to `enter` with every angle within `angle_tolerance` of the goal, and falls back
to the swing-up if V grows past `leave` (hysteresis: no chattering at one threshold).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..multibody import RigidBodySystem
from ..systems import HybridSystem, System, Transition, and_guards
from ._lqr import LQRResult


def _wrap(angle):
    """The angle in [-pi, pi)."""
    return jnp.mod(angle + jnp.pi, 2 * jnp.pi) - jnp.pi


def _check_single_actuated_joint(plant: RigidBodySystem):
    B = np.asarray(plant.B)
    if B.shape[1] != 1 or plant.tree.nq != plant.tree.nv or np.sum(B != 0) != 1 or B.max() != 1.0:
        raise ValueError(f"collocated partial feedback linearization needs one input driving one "
                         f"joint directly (B a unit column) and no floating base; {plant.name} has "
                         f"B of shape {B.shape}")


def collocated_pfl(plant: RigidBodySystem, x, qdd_actuated):
    r"""The input that gives the actuated joint (B a unit column b) the acceleration
    `qdd_actuated`: solve $(P H + b b^T)\ddot q = b\,\ddot q_a^d - P\phi$ with
    $P = I - b b^T$ (passive rows of the dynamics, actuated acceleration fixed), then
    $u = b^T(H\ddot q + \phi)$."""
    nq = plant.tree.nq
    q, v = x[:nq], x[nq:]
    H, Cv, G, B = plant.manipulator_dynamics(q, v)
    phi = Cv + G + plant.tree.damping * v
    b = B[:, 0]
    outer = jnp.outer(b, b)
    passive = jnp.eye(nq, dtype=H.dtype) - outer
    qdd = jnp.linalg.solve(passive @ H + outer, b * qdd_actuated - passive @ phi)
    return (b @ (H @ qdd + phi)).reshape(1)


def _acrobot_spong(t, _, x, params):
    plant, k_e, k_p, k_d, energy_up, torque_limit = params
    energy_error = plant.energy(x) - energy_up
    u = collocated_pfl(plant, x, -k_p * x[1] - k_d * x[3]) - k_e * energy_error * x[3]
    return jnp.clip(u, -torque_limit, torque_limit)


def acrobot_spong_controller(acrobot: RigidBodySystem, k_e=5.0, k_p=50.0, k_d=5.0,
                             torque_limit=20.0) -> System:
    r"""Spong's swing-up for `models.Acrobot` as in Drake's `AcrobotSpongController` (its gains
    and its saturation at +-20 N m): a static system from the acrobot's state to the elbow
    torque $u = \mathrm{sat}(u_p - k_e\tilde E\dot q_2)$, $u_p$ the collocated PFL of
    $\ddot q_2 = -k_p q_2 - k_d\dot q_2$; then $\dot E = -k_e\tilde E\dot q_2^2 + \dots$."""
    _check_single_actuated_joint(acrobot)
    energy_up = acrobot.energy(jnp.array([jnp.pi, 0.0, 0.0, 0.0]))
    return System.from_functions(output=_acrobot_spong, num_states=0, num_inputs=4, num_outputs=1,
                                 params=(acrobot, k_e, k_p, k_d, energy_up, torque_limit), time_invariant=True,
                                 input_frame=acrobot.state_frame, output_frame=acrobot.input_frame)


def _cart_pole_energy_shaping(t, _, x, params):
    plant, k_e, k_p, k_d, m_p, length, g = params
    theta, xdot, thetadot = x[1], x[2], x[3]
    energy_error = 0.5 * m_p * length**2 * thetadot**2 - m_p * g * length * (jnp.cos(theta) + 1.0)
    xdd = k_e * thetadot * jnp.cos(theta) * energy_error - k_p * x[0] - k_d * xdot
    return collocated_pfl(plant, x, xdd)


def cart_pole_swing_up_controller(cart_pole: RigidBodySystem, k_e=0.5, k_p=1.0, k_d=1.0) -> System:
    """Energy shaping of the pole with PD on the cart, through collocated PFL, for
    `models.CartPole` (the pole a point mass at its tip)."""
    _check_single_actuated_joint(cart_pole)
    tree = cart_pole.tree
    m_p, length = tree.mass[1], -tree.com[1, 2]
    g = -tree.gravity[2]
    return System.from_functions(output=_cart_pole_energy_shaping, num_states=0, num_inputs=4,
                                 num_outputs=1, params=(cart_pole, k_e, k_p, k_d, m_p, length, g),
                                 time_invariant=True, input_frame=cart_pole.state_frame,
                                 output_frame=cart_pole.input_frame)


def _goal_error(x, goal, wrapped):
    """$x - x_0$ with the wrapped coordinates (angles) in [-pi, pi)."""
    error = x - goal
    return jnp.where(wrapped, _wrap(error), error)


def _angles_near_goal(switch, t, _, x):
    """max |wrapped angle error| - angle_tolerance: keeps the switch away from the wrap at
    +-pi, where V jumps (and where a small V would be an artefact of the linearization)."""
    error = _goal_error(x, switch.goal, switch.wrapped)
    return jnp.max(jnp.where(switch.wrapped, jnp.abs(error), -jnp.inf)) - switch.angle_tolerance


def _enters_basin(switch, t, _, x):
    return switch.cost_to_go(x) - switch.enter


def _leaves_basin(switch, t, _, x):
    return switch.leave - switch.cost_to_go(x)


def _keep(switch, t, state, x):
    return state


class SwitchToLQR(HybridSystem):
    """The hybrid controller "swing up, then balance": mode 0 `swing_up`, mode 1 the LQR
    controller; into LQR when $V \\le$ `enter` (and the angles are within `angle_tolerance`),
    back when $V \\ge$ `leave` (default 2 `enter`). Input: the plant's state; output: its
    input, the LQR's clipped to `output_limits`. `angles`: the state indices wrapped to
    [-pi, pi) about the goal, in V and in the LQR's error."""

    S: jnp.ndarray
    goal: jnp.ndarray
    enter: float
    leave: float
    wrapped: jnp.ndarray
    angle_tolerance: float

    def __init__(self, swing_up: System, lqr: LQRResult, *, angles=(), enter=1e3, leave=None,
                 angle_tolerance=jnp.pi / 2, output_limits=(-jnp.inf, jnp.inf)):
        K, goal, u_goal = lqr.controller.functions.params
        if swing_up.num_inputs != lqr.controller.num_inputs or swing_up.num_outputs != lqr.controller.num_outputs:
            raise ValueError(f"SwitchToLQR: the swing-up controller maps {swing_up.num_inputs} -> "
                             f"{swing_up.num_outputs}, the LQR {lqr.controller.num_inputs} -> "
                             f"{lqr.controller.num_outputs}")
        self.S, self.goal = lqr.S, goal
        self.enter = enter
        self.leave = 2 * enter if leave is None else leave
        self.wrapped = jnp.zeros(len(goal), bool).at[jnp.asarray(angles, int)].set(True)
        self.angle_tolerance = angle_tolerance
        low, high = output_limits
        balance = System.from_functions(output=_wrapped_gain, num_states=0, num_inputs=len(goal),
                                        num_outputs=len(u_goal), params=(K, goal, u_goal, self.wrapped, low, high),
                                        time_invariant=True, input_frame=lqr.controller.input_frame,
                                        output_frame=lqr.controller.output_frame)
        super().__init__([swing_up, balance],
                         [Transition(0, and_guards(_enters_basin, _angles_near_goal), _keep, 1, "balance"),
                          Transition(1, _leaves_basin, _keep, 0, "swing up")])

    def cost_to_go(self, x):
        """$V(x) = \\tilde x^T S \\tilde x$, the angles of $\\tilde x = x - x_0$ wrapped to [-pi, pi)."""
        error = _goal_error(x, self.goal, self.wrapped)
        return error @ self.S @ error


def _wrapped_gain(t, _, x, params):
    K, goal, u_goal, wrapped, low, high = params
    return jnp.clip(u_goal - K @ _goal_error(x, goal, wrapped), low, high)
