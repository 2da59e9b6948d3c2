"""The two nodes of the LCM examples and tests: the pendulum plant and its LQR balancing
controller (Q = diag(10, 1), R = 1 about the upright), named for `python -m jaxdrake.lcm`."""

import jax.numpy as jnp
import numpy as np

import jaxdrake as jd

UPRIGHT = np.array([np.pi, 0.0])  # numpy: made in the precision JAX has when it is used


def plant():
    return jd.models.Pendulum()


def controller():
    return jd.control.lqr(plant(), jnp.diag(jnp.array([10.0, 1.0])), jnp.eye(1), x0=jnp.asarray(UPRIGHT)).controller
