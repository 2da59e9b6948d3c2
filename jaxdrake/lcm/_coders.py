r"""Coders: the conversion between an LCM message and a timestamped vector (notes, D.5.1).

Drake "traffics primarily in signals, which are (timestamped) vectors of doubles"; a coder
turns a vector $x$ at time $t$ into the bytes of one message type and back. The bytes are
always made and read by the `lcm-gen` class of the type (`jaxdrake.lcmtypes`), so what a coder
publishes decodes with that class — and with Drake, for `lcmt_drake_signal` — byte for byte.
Any failure to read a message (wrong fingerprint, truncated, wrong sizes or names) is a
`MessageError`, which a bridge counts and drops.
"""

from __future__ import annotations

import importlib

import numpy as np

from ..lcmtypes.drake import lcmt_drake_signal
from ..lcmtypes.jaxdrake_msgs import robot_command, robot_state
from ..systems import Frame

_NUMERIC = {"int8_t", "int16_t", "int32_t", "int64_t", "float", "double", "boolean", "byte"}
_TIME_FIELDS = ("timestamp", "utime")


class MessageError(ValueError):
    """A message that cannot be read as the coder's type: malformed, truncated, or of the
    wrong size or coordinate names."""


class LcmCoder:
    """Converts between (t, x) and the bytes of `message_type`; `dim` = len(x); `frame` names
    the coordinates. Subclasses write `_fill(msg, t, x)` and `_read(msg) -> (t, x)`."""

    message_type: type
    frame: Frame

    @property
    def dim(self) -> int:
        return self.frame.dim

    def encode(self, t: float, x) -> bytes:
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape != (self.dim,):
            raise ValueError(f"{type(self).__name__}: the vector must have {self.dim} entries "
                             f"({self.frame}), got {x.shape[0]}")
        msg = self.message_type()
        self._fill(msg, float(t), x)
        return msg.encode()

    def decode(self, data: bytes):
        """(t, x) from the bytes of one message; `MessageError` if they are not one."""
        try:
            msg = self.message_type.decode(data)
        except Exception as error:  # the generated decoder raises ValueError, struct.error, ...
            raise MessageError(f"not a valid {self.message_type.__name__} message "
                               f"({len(data)} bytes): {error}") from None
        t, x = self._read(msg)
        if not np.all(np.isfinite(x)):
            raise MessageError(f"{self.message_type.__name__} message carries non-finite values")
        return t, x


def _microseconds(t: float) -> int:
    return int(round(t * 1e6))


class SignalCoder(LcmCoder):
    """Drake's `lcmt_drake_signal` for the vectors of `frame`: `val` the vector, `coord` the
    frame's coordinate names, `timestamp` in microseconds. Decoding checks the size and the
    names (a message with no names is accepted by size)."""

    message_type = lcmt_drake_signal

    def __init__(self, frame: Frame):
        self.frame = frame

    def _fill(self, msg, t, x):
        msg.dim, msg.val, msg.coord, msg.timestamp = self.dim, list(x), list(self.frame.coordinates), _microseconds(t)

    def _read(self, msg):
        if msg.dim != self.dim:
            raise MessageError(f"lcmt_drake_signal of dimension {msg.dim}; {self.frame} needs {self.dim}")
        if any(msg.coord) and tuple(msg.coord) != self.frame.coordinates:
            raise MessageError(f"lcmt_drake_signal names {tuple(msg.coord)}; {self.frame} expected")
        return msg.timestamp * 1e-6, np.asarray(msg.val, float)


class _JointCoder(LcmCoder):
    def __init__(self, joint_names, frame_name, suffixes):
        self.joint_names = tuple(str(j) for j in joint_names)
        self.frame = Frame(frame_name, tuple(f"{j}{s}" for s in suffixes for j in self.joint_names))

    def _check_names(self, msg):
        if msg.num_joints != len(self.joint_names) or tuple(msg.joint_name) != self.joint_names:
            raise MessageError(f"{self.message_type.__name__} for joints {tuple(msg.joint_name)}; "
                               f"expected {self.joint_names}")

    def _header(self, msg, t):
        n = len(self.joint_names)
        msg.utime, msg.num_joints, msg.joint_name = _microseconds(t), n, list(self.joint_names)
        msg.joint_position, msg.joint_velocity, msg.joint_effort = [0.0] * n, [0.0] * n, [0.0] * n


class RobotStateCoder(_JointCoder):
    """`jaxdrake_msgs.robot_state` for a state x = [q; v] of the named joints (efforts sent as 0)."""

    message_type = robot_state

    def __init__(self, joint_names, frame_name: str = "RobotState"):
        super().__init__(joint_names, frame_name, ("", "dot"))

    def _fill(self, msg, t, x):
        self._header(msg, t)
        n = len(self.joint_names)
        msg.joint_position, msg.joint_velocity = list(x[:n]), list(x[n:])

    def _read(self, msg):
        self._check_names(msg)
        return msg.utime * 1e-6, np.concatenate([msg.joint_position, msg.joint_velocity]).astype(float)


class RobotCommandCoder(_JointCoder):
    """`jaxdrake_msgs.robot_command` for an input u = efforts of the named joints (desired
    positions and velocities sent as 0)."""

    message_type = robot_command

    def __init__(self, joint_names, frame_name: str = "RobotCommand"):
        super().__init__(joint_names, frame_name, ("_effort",))

    def _fill(self, msg, t, x):
        self._header(msg, t)
        msg.joint_effort = list(x)

    def _read(self, msg):
        self._check_names(msg)
        return msg.utime * 1e-6, np.asarray(msg.joint_effort, float)


class TypeCoder(LcmCoder):
    """A coder derived from a message type's fields in declaration order (the notes'
    `LCMCoderFromType`): every numeric field — scalars, fixed arrays of any rank, arrays sized
    by an integer field (give their lengths as `sizes={"n": 3}`), and nested structs — is one
    stretch of the vector; strings are left empty; an int64 field named `timestamp` or `utime`
    carries the time in microseconds. Coordinates are named after the fields (`xyz[1]`,
    `inner.id`)."""

    def __init__(self, message_type, *, sizes: dict | None = None, frame_name: str | None = None):
        self.message_type = message_type
        self.sizes = dict(sizes or {})
        self.time_field = next((f for f in _TIME_FIELDS if f in message_type.__slots__
                                and _typename(message_type, f) == "int64_t"), None)
        names = self._names(message_type, "", top=True)
        self.frame = Frame(frame_name or message_type.__name__, tuple(names))

    def _shape(self, cls, field):
        shape = []
        for d in cls.__dimensions__[cls.__slots__.index(field)] or []:
            if isinstance(d, str):
                if d not in self.sizes:
                    raise ValueError(f"{cls.__name__}.{field} is sized by {d!r}: give sizes={{{d!r}: ...}}")
                d = self.sizes[d]
            shape.append(int(d))
        return tuple(shape)

    def _fields(self, cls, top):
        for field in cls.__slots__:
            if top and field == self.time_field:
                continue
            if field in self.sizes and top:  # a length field: set from `sizes`
                continue
            yield field, _typename(cls, field), self._shape(cls, field)

    def _names(self, cls, prefix, top=False):
        names = []
        for field, typename, shape in self._fields(cls, top):
            if typename == "string":
                continue
            for index in np.ndindex(*shape):
                label = prefix + field + "".join(f"[{i}]" for i in index)
                if typename in _NUMERIC:
                    names.append(label)
                else:
                    names.extend(self._names(_resolve(typename), label + "."))
        return names

    def _fill(self, msg, t, x):
        values = iter(x)
        self._fill_struct(msg, values, top=True)
        if self.time_field:
            setattr(msg, self.time_field, _microseconds(t))

    def _fill_struct(self, msg, values, top=False):
        cls = type(msg)
        if top:
            for length_field, size in self.sizes.items():
                setattr(msg, length_field, int(size))
        for field, typename, shape in self._fields(cls, top):
            if typename == "string":
                continue
            def one(_, typename=typename):
                if typename in _NUMERIC:
                    return _cast(typename, next(values))
                inner = _resolve(typename)()
                self._fill_struct(inner, values)
                return inner
            setattr(msg, field, _nested(shape, one))

    def _read(self, msg):
        for length_field, size in self.sizes.items():
            if getattr(msg, length_field) != size:
                raise MessageError(f"{type(msg).__name__}.{length_field} = {getattr(msg, length_field)}; "
                                   f"this coder expects {size}")
        out = []
        self._read_struct(msg, out, top=True)
        t = getattr(msg, self.time_field) * 1e-6 if self.time_field else 0.0
        return t, np.asarray(out, float)

    def _read_struct(self, msg, out, top=False):
        for field, typename, shape in self._fields(type(msg), top):
            if typename == "string":
                continue
            value = getattr(msg, field)
            for index in np.ndindex(*shape):
                item = value
                for i in index:
                    item = item[i]
                if typename in _NUMERIC:
                    out.append(float(item))
                else:
                    self._read_struct(item, out)


def _typename(cls, field):
    return cls.__typenames__[cls.__slots__.index(field)]


def _resolve(typename):
    module, _, name = typename.rpartition(".")
    return getattr(importlib.import_module(module), name)


def _cast(typename, value):
    if typename in ("float", "double"):
        return float(value)
    if typename == "boolean":
        return bool(value)
    return int(round(float(value)))


def _nested(shape, one):
    if not shape:
        return one(None)
    return [_nested(shape[1:], one) for _ in range(shape[0])]
