r"""Joint actuators with a fixed gain and an affine bias: MuJoCo's motors, position and
velocity servos (its `general` actuator with `gaintype="fixed"`, `biastype="affine"` or none,
no activation dynamics) on hinges, slides and fixed tendons, as the plant's inputs.

Actuator k acts through its moment arms $m_k$ (a row over the velocity coordinates: its gear
$g_k$ at a joint's coordinate, or $g_k$ times a fixed tendon's coefficients): its length is
$l_k = m_k \cdot q$ (over the hinges' and slides' positions) and its velocity $\dot l_k = m_k
\cdot v$. Its force is $f_k = \mathrm{clip}(a_k u_k + b_{0k} + b_{1k} l_k + b_{2k} \dot l_k,\
f^-_k, f^+_k)$ (the clip where the actuator is force-limited, MuJoCo's `forcerange`) and the
generalized force is $\tau = \sum_k m_k f_k$, each joint's total clipped again to its
`actuatorfrcrange`. A position servo `kp`, `kv` is $a = k_p$, $b = (0, -k_p, -k_v)$: u is the
target length. The input u is MuJoCo's `ctrl`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import device_array


class JointActuators(eqx.Module):
    """The actuators (module docstring): leaves `gain` (a), `bias` (nu, 3: b0, b1, b2),
    `moment` (nu, nv: the moment arms), `force_lower` / `force_upper` (per actuator, +-inf
    where not limited), `joint_force_lower` / `joint_force_upper` (per velocity coordinate);
    static `names` and `ctrl_range` ((lower, upper) per actuator or None: the inputs'
    limits). Built from `force_range` (nu, 2) and `joint_force_range` (nv, 2) pairs; from an
    MJCF file by `RigidBodySystem.from_mjcf`. The lengths are taken over `qj`, the joints'
    positions per velocity coordinate (`KinematicTree.joint_positions`)."""

    gain: jax.Array
    bias: jax.Array
    moment: jax.Array
    force_lower: jax.Array
    force_upper: jax.Array
    joint_force_lower: jax.Array
    joint_force_upper: jax.Array
    names: tuple = eqx.field(static=True)
    ctrl_range: tuple | None = eqx.field(static=True)

    def __init__(self, names, gain, bias, moment, force_range, joint_force_range, ctrl_range=None):
        self.names = tuple(names)
        self.gain, self.bias, self.moment = device_array(gain, float), device_array(bias, float), device_array(moment, float)
        self.force_lower, self.force_upper = _bounds(force_range, len(self.names))
        self.joint_force_lower, self.joint_force_upper = _bounds(joint_force_range, self.moment.shape[1])
        self.ctrl_range = None if ctrl_range is None else tuple(tuple(float(c) for c in side) for side in ctrl_range)

    def input_matrix(self) -> np.ndarray:
        """$\\partial \\tau / \\partial u$ where no force limit binds: $m_k^T a_k$ (nv, nu)."""
        return np.asarray(self.moment).T * np.asarray(self.gain)

    def joint_forces(self, qj, v, u):
        """The generalized force (nv,) of the actuators at input u."""
        length = self.moment @ qj
        force = self.gain * u + self.bias[:, 0] + self.bias[:, 1] * length + self.bias[:, 2] * (self.moment @ v)
        force = jnp.clip(force, self.force_lower, self.force_upper)
        return jnp.clip(force @ self.moment, self.joint_force_lower, self.joint_force_upper)


class FixedTendons(eqx.Module):
    r"""MuJoCo's fixed tendons' springs and dampers: tendon t, of length $l_t = c_t \cdot q$
    (its coefficients $c_t$ over the velocity coordinates, applied to the hinges' and slides'
    positions), pulls with $f_t = k_t (\mathrm{clip}(l_t, l^-_t, l^+_t) - l_t) - b_t\, c_t
    \cdot v$ (a spring with a dead band $[l^-, l^+]$, MuJoCo's `springlength`, and a damper);
    the generalized force is $\sum_t c_t f_t$, and the springs store $\tfrac12 k_t
    (l_t - \mathrm{clip}(l_t, l^-_t, l^+_t))^2$. Leaves `coefficients` (nt, nv), `stiffness`,
    `damping`, `spring_lower`, `spring_upper`; static `names`. Lengths over `qj`, as
    `JointActuators`'."""

    coefficients: jax.Array
    stiffness: jax.Array
    damping: jax.Array
    spring_lower: jax.Array
    spring_upper: jax.Array
    names: tuple = eqx.field(static=True)

    def __init__(self, names, coefficients, stiffness, damping, spring_range):
        self.names = tuple(names)
        self.coefficients = device_array(coefficients, float)
        self.stiffness, self.damping = device_array(stiffness, float), device_array(damping, float)
        self.spring_lower, self.spring_upper = _bounds(spring_range, len(self.names))

    def _stretch(self, qj):
        length = self.coefficients @ qj
        return length - jnp.clip(length, self.spring_lower, self.spring_upper)

    def forces(self, qj, v):
        """The generalized force (nv,) of the tendons' springs and dampers."""
        tension = -self.stiffness * self._stretch(qj) - self.damping * (self.coefficients @ v)
        return tension @ self.coefficients

    def energy(self, qj):
        """What the tendons' springs store."""
        return 0.5 * jnp.sum(self.stiffness * self._stretch(qj) ** 2)


def _bounds(pairs, count):
    """(lower, upper) device arrays of `count` (lower, upper) pairs."""
    pairs = np.asarray(pairs, float).reshape(count, 2)
    return device_array(pairs[:, 0]), device_array(pairs[:, 1])


__all__ = ["FixedTendons", "JointActuators"]
