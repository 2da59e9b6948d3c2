r"""Spatial algebra (Featherstone, *Rigid Body Dynamics Algorithms*, ch. 2), angular first.

A spatial motion vector is $[\omega; v]$ (angular velocity, then the velocity of the point
at the frame's origin), a force $[n; f]$. A Plücker transform ${}^B X_A$ from frame A to
frame B, where B's origin is at $r$ (A coordinates) and $E$ rotates A coordinates into B
coordinates, is $\begin{bmatrix} E & 0 \\ -E [r]_\times & E \end{bmatrix}$; forces transform
with ${}^B X_A^{*} = {}^B X_A^{-T}$. All functions are plain `jax.numpy` on small arrays.
"""

from __future__ import annotations

import jax.numpy as jnp


def skew(w):
    """[w]x, the matrix of w x (.)."""
    z = jnp.zeros_like(w[0])
    return jnp.stack([jnp.stack([z, -w[2], w[1]]), jnp.stack([w[2], z, -w[0]]),
                      jnp.stack([-w[1], w[0], z])])


def axis_angle(axis, angle):
    """The rotation by `angle` about the unit vector `axis` (Rodrigues)."""
    K = skew(axis)
    return jnp.eye(3, dtype=K.dtype) + jnp.sin(angle) * K + (1 - jnp.cos(angle)) * (K @ K)


def rpy(r, p, y):
    """URDF's fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = jnp.cos(r), jnp.sin(r), jnp.cos(p), jnp.sin(p), jnp.cos(y), jnp.sin(y)
    return jnp.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                      [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                      [-sp, cp * sr, cp * cr]])


def quaternion_matrix(quat):
    """Rotation matrix of a unit quaternion given as (x, y, z, w) (Pinocchio's order)."""
    x, y, z, w = quat[0], quat[1], quat[2], quat[3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)]),
        jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)]),
        jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)])])


def plucker(E, r):
    """The 6x6 motion transform with rotation E and origin offset r (see the module doc)."""
    zero = jnp.zeros((3, 3), E.dtype)
    return jnp.block([[E, zero], [-E @ skew(r), E]])


def pose_transform(R, p):
    """${}^{child}X_{parent}$ for a child frame at position p with orientation R (columns: the
    child's axes) in parent coordinates: E = R^T, r = p."""
    return plucker(R.T, p)


def cross_motion(v):
    """v x (motion): [[w]x, 0; [v]x, [w]x]."""
    w, u = skew(v[:3]), skew(v[3:])
    return jnp.block([[w, jnp.zeros_like(w)], [u, w]])


def cross_force(v):
    """v x* (force) = -(v x)^T."""
    return -cross_motion(v).T


def spatial_inertia(mass, com, inertia_com):
    """The 6x6 inertia of a body of `mass` with centre of mass `com` and rotational inertia
    `inertia_com` about the centre of mass, all in the body frame."""
    C = skew(com)
    return jnp.block([[inertia_com + mass * C @ C.T, mass * C], [mass * C.T, mass * jnp.eye(3, dtype=C.dtype)]])
