"""The simple pendulum (Underactuated, ch. 2; Drake's PendulumPlant)."""

from __future__ import annotations

import jax.numpy as jnp

from ..systems import Frame, System


class Pendulum(System):
    r"""A damped, torque-driven simple pendulum, $\theta = 0$ hanging straight down:

    $$m l^2 \ddot\theta + b\dot\theta + m g l \sin\theta = \tau.$$

    State $[\theta, \dot\theta]$, input $\tau$, output the state. Parameters (pytree leaves)
    default to Drake's: m = 1 kg, l = 0.5 m, b = 0.1 N m s, g = 9.81 m/s^2.
    """

    m: float = 1.0
    l: float = 0.5
    b: float = 0.1
    g: float = 9.81

    def __init__(self, m=1.0, l=0.5, b=0.1, g=9.81, *, input_limits=None):
        self.m, self.l, self.b, self.g = m, l, b, g
        state = Frame("PendulumState", ("theta", "thetadot"))
        super().__init__(num_continuous_states=2, num_inputs=1, direct_feedthrough=False,
                         time_invariant=True, input_limits=input_limits,
                         input_frame=Frame("PendulumInput", ("tau",)),
                         state_frame=state, output_frame=state)

    def dynamics(self, t, x, u):
        theta, thetadot = x
        inertia = self.m * self.l**2
        thetaddot = (u[0] - self.b * thetadot - self.m * self.g * self.l * jnp.sin(theta)) / inertia
        return jnp.stack([thetadot, thetaddot])

    def energy(self, x):
        r"""Total energy $\tfrac12 m l^2\dot\theta^2 - m g l\cos\theta$ (conserved when b = 0, u = 0)."""
        theta, thetadot = x[..., 0], x[..., 1]
        return 0.5 * self.m * self.l**2 * thetadot**2 - self.m * self.g * self.l * jnp.cos(theta)
