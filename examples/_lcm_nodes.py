"""The two nodes of the LCM examples and tests: the pendulum plant and its LQR balancing
controller (Q = diag(10, 1), R = 1 about the upright), named for `python -m jaxdrake.lcm`."""

import jax.numpy as jnp

import jaxdrake as jd

UPRIGHT = jnp.array([jnp.pi, 0.0])


def plant():
    return jd.models.Pendulum()


def controller():
    return jd.control.lqr(plant(), jnp.diag(jnp.array([10.0, 1.0])), jnp.eye(1), x0=UPRIGHT).controller
