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

import functools

import jax.numpy as jnp
import numpy as np

from ..multibody import RigidBodySystem
from ..systems import HybridSystem, System, Transition, and_guards
from ._lqr import LQRResult


def _wrap(angle):
    """The angle in [-pi, pi)."""
    return jnp.mod(angle + jnp.pi, 2 * jnp.pi) - jnp.pi


def _actuated_joint(plant: RigidBodySystem) -> int:
    """The index of the one joint that the one input drives directly (B a unit column)."""
    B = np.asarray(plant.B)
    if B.shape[1] != 1 or plant.tree.nq != plant.tree.nv or np.sum(B != 0) != 1 or B.max() != 1.0:
        raise ValueError(f"collocated partial feedback linearization needs one input driving one "
                         f"joint directly (B a unit column) and no floating base; {plant.name} has "
                         f"B of shape {B.shape}")
    return int(np.argmax(B[:, 0]))


def collocated_pfl(plant: RigidBodySystem, x, qdd_actuated, actuated: int | None = None):
    r"""The input that gives the actuated joint a (B the unit column $e_a$) the acceleration
    `qdd_actuated`: the passive rows give $\ddot q_p = -H_{pp}^{-1}(H_{pa}\ddot q_a^d + \phi_p)$
    ($H_{pp}$ symmetric positive definite, solved by an unrolled Cholesky factorization), then
    $u = H_{ap}\ddot q_p + H_{aa}\ddot q_a^d + \phi_a$. `actuated`: a's index, found from B
    when not given (B must then be concrete: pass it inside a traced function)."""
    a = _actuated_joint(plant) if actuated is None else actuated
    nq = plant.tree.nq
    q, v = x[:nq], x[nq:]
    H, Cv, G, _ = plant.manipulator_dynamics(q, v)
    phi = Cv + G + plant.tree.damping * v
    passive = np.array([i for i in range(nq) if i != a])
    qdd = jnp.zeros(nq, H.dtype).at[a].set(qdd_actuated)
    if len(passive):
        rhs = -(H[passive, a] * qdd_actuated + phi[passive])
        qdd = qdd.at[passive].set(_spd_solve(H[np.ix_(passive, passive)], rhs))
    return (H[a] @ qdd + phi[a]).reshape(1)


def _spd_solve(M, b):
    """$M^{-1} b$ for a small symmetric positive-definite M by a Cholesky factorization written
    out entry by entry: elementwise operations, which under `vmap` on a CPU cost a fraction of
    LAPACK's per-matrix calls (a batch of 50 2x2 solves: 9 us against 67 us)."""
    n = M.shape[0]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        L[j][j] = jnp.sqrt(M[j, j] - sum(L[j][k] ** 2 for k in range(j)))
        for i in range(j + 1, n):
            L[i][j] = (M[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    y = []
    for i in range(n):
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return jnp.stack(x)


@functools.lru_cache(maxsize=None)
def _with_actuated(law, actuated: int):
    """`law` with its actuated joint bound, one object per (law, joint): a static field whose
    identity is stable, so a second controller reuses the first one's compiled programs."""
    return functools.partial(law, actuated=actuated)


def _acrobot_spong(t, _, x, params, actuated):
    plant, k_e, k_p, k_d, energy_up, torque_limit = params
    energy_error = plant.energy(x) - energy_up
    u = collocated_pfl(plant, x, -k_p * x[1] - k_d * x[3], actuated) - k_e * energy_error * x[3]
    return jnp.clip(u, -torque_limit, torque_limit)


def acrobot_spong_controller(acrobot: RigidBodySystem, k_e=5.0, k_p=50.0, k_d=5.0,
                             torque_limit=20.0) -> System:
    r"""Spong's swing-up for `models.Acrobot` as in Drake's `AcrobotSpongController` (its gains
    and its saturation at +-20 N m): a static system from the acrobot's state to the elbow
    torque $u = \mathrm{sat}(u_p - k_e\tilde E\dot q_2)$, $u_p$ the collocated PFL of
    $\ddot q_2 = -k_p q_2 - k_d\dot q_2$; then $\dot E = -k_e\tilde E\dot q_2^2 + \dots$."""
    actuated = _actuated_joint(acrobot)
    energy_up = acrobot.energy(jnp.array([jnp.pi, 0.0, 0.0, 0.0]))
    return System.from_functions(output=_with_actuated(_acrobot_spong, actuated), num_states=0, num_inputs=4,
                                 num_outputs=1, params=(acrobot, k_e, k_p, k_d, energy_up, torque_limit),
                                 time_invariant=True, input_frame=acrobot.state_frame, output_frame=acrobot.input_frame)


def _cart_pole_energy_shaping(t, _, x, params, actuated):
    plant, k_e, k_p, k_d, m_p, length, g = params
    theta, xdot, thetadot = x[1], x[2], x[3]
    energy_error = 0.5 * m_p * length**2 * thetadot**2 - m_p * g * length * (jnp.cos(theta) + 1.0)
    xdd = k_e * thetadot * jnp.cos(theta) * energy_error - k_p * x[0] - k_d * xdot
    return collocated_pfl(plant, x, xdd, actuated)


def cart_pole_swing_up_controller(cart_pole: RigidBodySystem, k_e=0.5, k_p=1.0, k_d=1.0) -> System:
    """Energy shaping of the pole with PD on the cart, through collocated PFL, for
    `models.CartPole` (the pole a point mass at its tip)."""
    actuated = _actuated_joint(cart_pole)
    tree = cart_pole.tree
    m_p, length = tree.mass[1], -tree.com[1, 2]
    g = -tree.gravity[2]
    return System.from_functions(output=_with_actuated(_cart_pole_energy_shaping, actuated), num_states=0,
                                 num_inputs=4, num_outputs=1, params=(cart_pole, k_e, k_p, k_d, m_p, length, g),
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
        K, goal, u_goal = lqr.K, lqr.x0, lqr.u0
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
