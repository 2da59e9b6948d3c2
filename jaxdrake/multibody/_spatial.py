r"""Spatial algebra (Featherstone, *Rigid Body Dynamics Algorithms*, ch. 2), angular first.

A spatial motion vector is $[\omega; v]$ (angular velocity, then the velocity of the point
at the frame's origin), a force $[n; f]$. A Plücker transform ${}^B X_A$ from frame A to
frame B, where B's origin is at $r$ (A coordinates) and $E$ rotates A coordinates into B
coordinates, is $\begin{bmatrix} E & 0 \\ -E [r]_\times & E \end{bmatrix}$; forces transform
with ${}^B X_A^{*} = {}^B X_A^{-T}$. Transforms are kept as the pair (E, r) and applied by
blocks (cross products, 3x3 products), never as dense 6x6 matrices. Plain `jax.numpy`.
"""

from __future__ import annotations

import jax.numpy as jnp


def skew(w):
    """[w]x, the matrix of w x (.); batched over leading axes of w (..., 3) -> (..., 3, 3)."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                      jnp.stack([-y, x, o], -1)], -2)


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


def spatial_inertia(mass, com, inertia_com):
    """The 6x6 inertia of a body of `mass` with centre of mass `com` and rotational inertia
    `inertia_com` about the centre of mass, all in the body frame."""
    C = skew(com)
    return jnp.block([[inertia_com + mass * C @ C.T, mass * C], [mass * C.T, mass * jnp.eye(3, dtype=C.dtype)]])


def transform_inertia(E, r, inertia):
    r"""${}^B X_A^T\, I\, {}^B X_A$: a 6x6 (articulated) inertia in B coordinates moved to A, by
    blocks: with $I' = \mathrm{diag}(E, E)^T I\, \mathrm{diag}(E, E)$ and $R = [r]_\times$,
    the result is $\begin{bmatrix} A' + R B'^T - (B' + R C') R & B' + R C' \\ \cdot & C' \end{bmatrix}$
    (about half the work of the two 6x6 products)."""
    A, B, C = inertia[:3, :3], inertia[:3, 3:], inertia[3:, 3:]
    A1, B1, C1 = E.T @ A @ E, E.T @ B @ E, E.T @ C @ E
    R = skew(r)
    top = B1 + R @ C1
    return jnp.block([[A1 + R @ B1.T - top @ R, top], [top.T, C1]])


def motion_cross(v, m):
    """v x m for motion vectors, without building [v]x."""
    w, u = v[:3], v[3:]
    return jnp.concatenate([jnp.cross(w, m[:3]), jnp.cross(u, m[:3]) + jnp.cross(w, m[3:])])


def force_cross(v, f):
    """v x* f for a motion vector v and a force f."""
    w, u = v[:3], v[3:]
    return jnp.concatenate([jnp.cross(w, f[:3]) + jnp.cross(u, f[3:]), jnp.cross(w, f[3:])])


def transform_motion(E, r, m):
    """X m for X = (E, r): [E w; E (v - r x w)]."""
    return jnp.concatenate([E @ m[:3], E @ (m[3:] - jnp.cross(r, m[:3]))])


def transform_force_back(E, r, f):
    """X^T f for X = (E, r): a force in B coordinates expressed in A: [E^T n + r x E^T f; E^T f]."""
    f_lin = E.T @ f[3:]
    return jnp.concatenate([E.T @ f[:3] + jnp.cross(r, f_lin), f_lin])
