r"""Joint actuators with a fixed gain and an affine bias: MuJoCo's motors, position and
velocity servos (its `general` actuator with `gaintype="fixed"`, `biastype="affine"` or none,
no activation dynamics) on hinges and slides, as the plant's inputs.

Actuator k drives the velocity coordinate $i_k$ (position coordinate $j_k$) through gear
$g_k$: its force is $f_k = \mathrm{clip}(a_k u_k + b_{0k} + b_{1k} g_k q_{j_k} + b_{2k} g_k
v_{i_k},\ f^-_k, f^+_k)$ (the clip where the actuator is force-limited, MuJoCo's
`forcerange`) and the joint receives $g_k f_k$; the joint's total is clipped again to its
`actuatorfrcrange`. A position servo `kp`, `kv` is $a = k_p$, $b = (0, -k_p, -k_v)$: u is
the target position. The input u is MuJoCo's `ctrl`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import device_array


class JointActuators(eqx.Module):
    """The actuators (module docstring): leaves `gain` (a), `bias` (nu, 3: b0, b1, b2),
    `gear`, `force_lower` / `force_upper` (per actuator, +-inf where not limited),
    `joint_force_lower` / `joint_force_upper` (per velocity coordinate); static `names`, the
    velocity coordinate `dofs` and position coordinate `positions` each drives, and `ctrl_range`
    ((lower, upper) per actuator or None: the inputs' limits)."""

    gain: jax.Array
    bias: jax.Array
    gear: jax.Array
    force_lower: jax.Array
    force_upper: jax.Array
    joint_force_lower: jax.Array
    joint_force_upper: jax.Array
    names: tuple = eqx.field(static=True)
    dofs: tuple = eqx.field(static=True)
    positions: tuple = eqx.field(static=True)
    ctrl_range: tuple | None = eqx.field(static=True)

    def __init__(self, names, dofs, positions, gain, bias, gear, force_range, joint_force_range, ctrl_range=None):
        self.names, self.dofs, self.positions = tuple(names), tuple(int(i) for i in dofs), tuple(int(j) for j in positions)
        self.gain, self.bias, self.gear = device_array(gain, float), device_array(bias, float), device_array(gear, float)
        force_range = np.asarray(force_range, float).reshape(len(self.names), 2)
        self.force_lower, self.force_upper = device_array(force_range[:, 0]), device_array(force_range[:, 1])
        joint_force_range = np.asarray(joint_force_range, float)
        self.joint_force_lower, self.joint_force_upper = (device_array(joint_force_range[:, 0]),
                                                          device_array(joint_force_range[:, 1]))
        self.ctrl_range = None if ctrl_range is None else tuple(tuple(float(c) for c in side) for side in ctrl_range)

    def input_matrix(self, nv: int) -> np.ndarray:
        """$\\partial \\tau / \\partial u$ where no force limit binds: $g_k a_k$ at $(i_k, k)$."""
        B = np.zeros((nv, len(self.names)))
        B[list(self.dofs), np.arange(len(self.names))] = np.asarray(self.gear) * np.asarray(self.gain)
        return B

    def joint_forces(self, q, v, u):
        """The generalized force (nv,) of the actuators at input u."""
        dofs, positions = np.asarray(self.dofs, int), np.asarray(self.positions, int)
        force = (self.gain * u + self.bias[:, 0] + self.bias[:, 1] * self.gear * q[positions]
                 + self.bias[:, 2] * self.gear * v[dofs])
        force = jnp.clip(force, self.force_lower, self.force_upper)
        tau = jnp.zeros(v.shape[0], force.dtype).at[dofs].add(self.gear * force)
        return jnp.clip(tau, self.joint_force_lower, self.joint_force_upper)


__all__ = ["JointActuators"]
