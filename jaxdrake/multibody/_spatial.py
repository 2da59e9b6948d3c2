r"""Spatial algebra (Featherstone, *Rigid Body Dynamics Algorithms*, ch. 2), angular first.

A spatial motion vector is $[\omega; v]$ (angular velocity, then the velocity of the point
at the frame's origin), a force $[n; f]$. A Plücker transform ${}^B X_A$ from frame A to
frame B, where B's origin is at $r$ (A coordinates) and $E$ rotates A coordinates into B
coordinates, is $\begin{bmatrix} E & 0 \\ -E [r]_\times & E \end{bmatrix}$; forces transform
with ${}^B X_A^{*} = {}^B X_A^{-T}$. The algorithms work in world coordinates, where they need
no transforms (`_algorithms`); what they share lives here. Plain `jax.numpy`, batched over
leading axes.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._numbers import array_module


def skew(w):
    """[w]x, the matrix of w x (.); batched over leading axes of w (..., 3) -> (..., 3, 3)."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1),
                      jnp.stack([-y, x, o], -1)], -2)


def rpy(r, p, y):
    """URDF's fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll) (numpy for numbers, as
    when a URDF is read: no JAX program to compile; jax.numpy for arrays and tracers)."""
    xp = array_module(r, p, y)
    cr, sr, cp, sp, cy, sy = xp.cos(r), xp.sin(r), xp.cos(p), xp.sin(p), xp.cos(y), xp.sin(y)
    return xp.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                      [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                      [-sp, cp * sr, cp * cr]])


def quaternion_matrix(quat):
    r"""Rotation matrix of the quaternion (x, y, z, w) (Pinocchio's order) scaled to unit norm:
    $R = I + s\,(w [v]_\times + [v]_\times^2)$, $s = 2 / |q|^2$. A proper rotation for any
    non-zero quaternion (a state drifted off the unit sphere, a finite-difference probe), so
    the forward and inverse dynamics stay each other's inverse there and their derivatives
    agree (the radial direction is a symmetry)."""
    x, y, z, w = quat[0], quat[1], quat[2], quat[3]
    s = 2 / (x * x + y * y + z * z + w * w)
    return jnp.stack([
        jnp.stack([1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)]),
        jnp.stack([s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)]),
        jnp.stack([s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)])])
