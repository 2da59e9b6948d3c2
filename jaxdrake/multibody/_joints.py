r"""`JointType`: the kinds of joint, and the facts each kind implies (its widths in q and v,
its coordinates' names, its neutral position). Every reader (URDF, MJCF, Pinocchio) names its
joints by these kinds, and every rule that depends on a joint's kind asks the kind.
"""

from __future__ import annotations

import enum


class JointType(enum.StrEnum):
    r"""The kind of the joint from a body's parent; a string enum (`JointType.REVOLUTE ==
    "revolute"`), with its widths: `num_positions` (in q) and `num_velocities` (in v, the
    degrees of freedom).

    - `REVOLUTE`: one angle about the joint axis (rad), 1 / 1; URDF's `revolute` and
      `continuous`, MuJoCo's `hinge`.
    - `PRISMATIC`: one length along the axis (m), 1 / 1; MuJoCo's `slide`.
    - `FLOATING`: a free body, 7 / 6: $q = [x, y, z, q_x, q_y, q_z, q_w]$ (the position of the
      body in its parent, a unit quaternion of its orientation), $v = [v_B; \omega_B]$ (linear
      and angular velocity in the body's frame), Pinocchio's free flyer; MuJoCo's `free`.
    - `FIXED`: no motion, 0 / 0. The readers merge a fixed joint's child into its parent body,
      so a `KinematicTree` never holds one.
    """

    REVOLUTE = "revolute", 1, 1
    PRISMATIC = "prismatic", 1, 1
    FLOATING = "floating", 7, 6
    FIXED = "fixed", 0, 0

    def __new__(cls, value: str, num_positions: int, num_velocities: int):
        kind = str.__new__(cls, value)
        kind._value_ = value
        kind.num_positions, kind.num_velocities = num_positions, num_velocities
        return kind

    @classmethod
    def _missing_(cls, value):
        raise ValueError(f"unknown joint type {value!r}: the joint types are {', '.join(k.value for k in cls)} "
                         "(a URDF's 'continuous' joint is a revolute one); other kinds, such as URDF's 'planar', "
                         "are not supported: model them as a chain of revolute and prismatic joints")

    def position_names(self, joint: str) -> tuple[str, ...]:
        """The names of the joint's position coordinates: the joint's own name for one
        coordinate; `<joint>_x`, ..., `<joint>_qw` for a floating joint."""
        if self is JointType.FLOATING:
            return tuple(f"{joint}_{c}" for c in ("x", "y", "z", "qx", "qy", "qz", "qw"))
        return (joint,) * self.num_positions

    def velocity_names(self, joint: str) -> tuple[str, ...]:
        """The names of the joint's velocity coordinates: `<joint>dot` for one coordinate;
        `<joint>_vx`, ..., `<joint>_wz` for a floating joint."""
        if self is JointType.FLOATING:
            return tuple(f"{joint}_{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz"))
        return (f"{joint}dot",) * self.num_velocities

    @property
    def neutral_position(self) -> tuple[float, ...]:
        """q of the joint at rest in its reference pose: zeros; the identity quaternion for a
        floating joint."""
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) if self is JointType.FLOATING else (0.0,) * self.num_positions


__all__ = ["JointType"]
