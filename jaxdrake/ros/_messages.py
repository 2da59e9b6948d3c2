r"""The ROS message types the translator speaks, as conversions between a timestamped vector
$(t, x)$ and the message's fields.

A message is handled here as plain data: nested dicts with ROS's field names, numbers and lists,
and one convention for time: a header's `stamp` is an integer count of nanoseconds. Each wire
(`rospy` for ROS 1, Cyclone DDS for ROS 2, `rosbags` for bag files) turns that into its own
message objects, so the meaning of every field is decided once, here:

| type | vector $x$ | time |
|---|---|---|
| `std_msgs/Float64MultiArray` | `data` (one `layout.dim` labelled with the frame's name) | none: the receiver's clock |
| `sensor_msgs/JointState` | the chosen `fields` (position, velocity, effort) of `joints`, read by name | `header.stamp` |
| `geometry_msgs/Twist` | `[linear.x, linear.y, linear.z, angular.x, angular.y, angular.z]` | none: the receiver's clock |
| `geometry_msgs/WrenchStamped` | `[force.x, force.y, force.z, torque.x, torque.y, torque.z]` | `header.stamp` |

LCM stamps are microseconds, so a ROS stamp reaches LCM rounded to the microsecond; an LCM stamp
reaches ROS exactly. A message that cannot be read as its type (wrong sizes, a joint missing or
named twice, non-finite values) is a `jaxdrake.lcm.MessageError`, which the translator counts and
drops.
"""

from __future__ import annotations

import numpy as np

from ..lcm import MessageError

_AXES = ("x", "y", "z")
JOINT_FIELDS = ("position", "velocity", "effort")


def stamp_from_seconds(t: float) -> int:
    """Nanoseconds of a time in seconds, on LCM's microsecond grid (`t` = utime · 1e-6 exactly)."""
    return int(round(t * 1e6)) * 1000


def _finite(x, type_name):
    x = np.asarray(x, dtype=float).reshape(-1)
    if not np.all(np.isfinite(x)):
        raise MessageError(f"{type_name} message carries non-finite values")
    return x


def _vector3(values):
    return dict(zip(_AXES, (float(v) for v in values)))


def _read_vector3(value):
    return [value[axis] for axis in _AXES]


def _header(t):
    return {"stamp": stamp_from_seconds(t), "frame_id": ""}


class RosMessage:
    """A ROS message type carrying vectors of `dim` entries: `encode(t, x)` gives the message's
    fields, `decode(fields)` gives `(t, x)` (`t` None for a type without a header)."""

    type_name: str  # ROS 1 spelling, e.g. "sensor_msgs/JointState"
    dim: int

    @property
    def package(self) -> str:
        return self.type_name.split("/")[0]

    @property
    def name(self) -> str:
        return self.type_name.split("/")[1]

    def check_dim(self, dim: int, where: str):
        if dim != self.dim:
            raise ValueError(f"{where}: {self.type_name} carries {self.dim} values here, the LCM side {dim}")

    def encode(self, t: float, x) -> dict:
        raise NotImplementedError

    def decode(self, fields: dict):
        raise NotImplementedError


class Float64MultiArray(RosMessage):
    """`std_msgs/Float64MultiArray`: `data` is x; its layout names the frame (`label`)."""

    type_name = "std_msgs/Float64MultiArray"

    def __init__(self, dim: int, label: str = ""):
        self.dim, self.label = int(dim), str(label)

    def encode(self, t, x):
        x = np.asarray(x, float).reshape(-1)
        return {"layout": {"dim": [{"label": self.label, "size": self.dim, "stride": self.dim}], "data_offset": 0},
                "data": [float(v) for v in x]}

    def decode(self, fields):
        data = fields["data"]
        if len(data) != self.dim:
            raise MessageError(f"Float64MultiArray of {len(data)} values; {self.dim} expected")
        return None, _finite(data, self.type_name)


class JointState(RosMessage):
    r"""`sensor_msgs/JointState` for the `fields` (a tuple from position, velocity, effort) of
    `joints`: $x = [\,f_1(j_1..j_n);\ f_2(j_1..j_n); \dots]$. Decoding finds each joint by its
    name, wherever it stands in the message; joints the message has beyond these are ignored,
    a missing one makes the message unreadable."""

    type_name = "sensor_msgs/JointState"

    def __init__(self, joints, fields=("position", "velocity")):
        self.joints, self.fields = tuple(str(j) for j in joints), tuple(fields)
        if not self.joints or len(set(self.joints)) != len(self.joints):
            raise ValueError(f"JointState needs distinct joint names, got {self.joints}")
        unknown = set(self.fields) - set(JOINT_FIELDS)
        if unknown or not self.fields or len(set(self.fields)) != len(self.fields):
            raise ValueError(f"JointState fields are distinct names from {JOINT_FIELDS}, got {self.fields}")
        self.dim = len(self.joints) * len(self.fields)

    @classmethod
    def for_coordinates(cls, coordinates, actuated: bool = False) -> "JointState":
        """The usual reading of a frame's coordinate names: `[q...; q...dot]` (a plant's state,
        `RobotStateCoder`) is position and velocity of the joints q; names ending in `_effort`
        (`RobotCommandCoder`), or an `actuated` frame (a plant's input), are efforts; anything
        else is positions."""
        names = tuple(coordinates)
        n = len(names) // 2
        if len(names) % 2 == 0 and names[n:] == tuple(f"{q}dot" for q in names[:n]):
            return cls(names[:n], ("position", "velocity"))
        if all(name.endswith("_effort") for name in names):
            return cls(tuple(name[: -len("_effort")] for name in names), ("effort",))
        return cls(names, ("effort",) if actuated else ("position",))

    def encode(self, t, x):
        x = np.asarray(x, float).reshape(len(self.fields), len(self.joints))
        fields = {"header": _header(t), "name": list(self.joints)}
        for field in JOINT_FIELDS:
            row = self.fields.index(field) if field in self.fields else None
            fields[field] = [] if row is None else [float(v) for v in x[row]]
        return fields

    def decode(self, fields):
        names = list(fields["name"])
        if len(set(names)) != len(names):
            raise MessageError(f"JointState names a joint twice: {names}")
        missing = [j for j in self.joints if j not in names]
        if missing:
            raise MessageError(f"JointState lacks joints {missing} (it has {names})")
        index = [names.index(j) for j in self.joints]
        rows = []
        for field in self.fields:
            values = fields[field]
            if len(values) != len(names):
                raise MessageError(f"JointState has {len(values)} {field} values for {len(names)} names")
            rows.append([values[i] for i in index])
        return fields["header"]["stamp"] / 1e9, _finite(rows, self.type_name)


class Twist(RosMessage):
    """`geometry_msgs/Twist`: x = [linear; angular]."""

    type_name = "geometry_msgs/Twist"
    dim = 6

    def encode(self, t, x):
        x = np.asarray(x, float).reshape(6)
        return {"linear": _vector3(x[:3]), "angular": _vector3(x[3:])}

    def decode(self, fields):
        return None, _finite(_read_vector3(fields["linear"]) + _read_vector3(fields["angular"]), self.type_name)


class WrenchStamped(RosMessage):
    """`geometry_msgs/WrenchStamped`: x = [force; torque], stamped; `frame_id` names the frame
    the wrench is expressed in."""

    type_name = "geometry_msgs/WrenchStamped"
    dim = 6

    def __init__(self, frame_id: str = ""):
        self.frame_id = str(frame_id)

    def encode(self, t, x):
        x = np.asarray(x, float).reshape(6)
        return {"header": dict(_header(t), frame_id=self.frame_id),
                "wrench": {"force": _vector3(x[:3]), "torque": _vector3(x[3:])}}

    def decode(self, fields):
        wrench = fields["wrench"]
        x = _read_vector3(wrench["force"]) + _read_vector3(wrench["torque"])
        return fields["header"]["stamp"] / 1e9, _finite(x, self.type_name)


MESSAGE_TYPES = {cls.type_name: cls for cls in (Float64MultiArray, JointState, Twist, WrenchStamped)}


def ros_type_name(name: str) -> str:
    """The ROS 1 spelling `pkg/Type` of `pkg/Type`, `pkg/msg/Type` (ROS 2) or `Type`."""
    parts = str(name).split("/")
    if len(parts) == 3 and parts[1] == "msg":
        parts = [parts[0], parts[2]]
    matches = [t for t in MESSAGE_TYPES if t == "/".join(parts) or (len(parts) == 1 and t.endswith("/" + parts[0]))]
    if len(matches) != 1:
        raise ValueError(f"unsupported ROS message type {name!r}: the translator speaks {', '.join(MESSAGE_TYPES)}")
    return matches[0]
