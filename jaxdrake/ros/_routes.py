"""Routes: which LCM channel goes to which ROS topic (or back), with which coder and message type.

A route is given in Python (`Route`), on the command line (`--to-ros CHANNEL TOPIC TYPE LCM`,
`--to-lcm TOPIC CHANNEL TYPE LCM`) or in a TOML mapping file:

    lcm_url = "tcpq://127.0.0.1:7700"        # optional; --url overrides it

    [[route]]
    direction = "to_ros"                     # LCM -> ROS
    channel = "PendulumState"
    topic = "/pendulum/state"
    type = "sensor_msgs/JointState"
    lcm = "state_of=jaxdrake.models:Pendulum"

    [[route]]
    direction = "to_lcm"                     # ROS -> LCM
    topic = "/pendulum/setpoint"
    channel = "PendulumSetpoint"
    type = "std_msgs/Float64MultiArray"
    lcm = "signal=theta_ref"

The `lcm` text names the LCM side's message and coordinates:

- `signal=A,B,...`: Drake's `lcmt_drake_signal` with those coordinate names;
- `robot_state=J1,J2,...` / `robot_command=J1,J2,...`: `jaxdrake_msgs` robot state (positions
  and velocities) or command (efforts) of those joints;
- `state_of=SYSTEM`, `input_of=SYSTEM`, `output_of=SYSTEM`: that port's frame of a system
  (`module:name` or `file.py:name`, as `python -m jaxdrake.lcm` takes it), with its frame's coder.

A `JointState` route reads its joints from those names (`JointState.for_coordinates`): a
state `[q; qdot]` is positions and velocities, a command or a system's input is efforts.
"""

from __future__ import annotations

import dataclasses
import tomllib

from ..lcm import LcmCoder, RobotCommandCoder, RobotStateCoder, SignalCoder
from ..systems import Frame
from ._messages import JointState, MESSAGE_TYPES, RosMessage, ros_type_name

TO_ROS, TO_LCM = "to_ros", "to_lcm"
_PORTS = {"state_of": "state_frame", "input_of": "input_frame", "output_of": "output_frame"}


@dataclasses.dataclass(frozen=True)
class Route:
    """One direction of one LCM channel <-> ROS topic pair: `coder` reads / writes the LCM
    messages, `message` the ROS ones (their dimensions agree)."""

    direction: str
    channel: str
    topic: str
    coder: LcmCoder
    message: RosMessage

    def __post_init__(self):
        if self.direction not in (TO_ROS, TO_LCM):
            raise ValueError(f"a route's direction is {TO_ROS!r} or {TO_LCM!r}, got {self.direction!r}")
        if not self.channel or not self.topic.startswith("/"):
            raise ValueError(f"a route needs an LCM channel and an absolute ROS topic ('/name'), got "
                             f"{self.channel!r} and {self.topic!r}")
        self.message.check_dim(self.coder.dim, str(self))

    def __str__(self):
        arrow = f"{self.channel} -> {self.topic}" if self.direction == TO_ROS else f"{self.topic} -> {self.channel}"
        return f"{arrow} ({self.message.type_name})"

    @classmethod
    def parse(cls, direction: str, channel: str, topic: str, type_name: str, lcm: str) -> "Route":
        """A route from the texts of the command line or the mapping file."""
        coder, actuated = lcm_coder(lcm, channel)
        return cls(direction, channel, topic, coder, ros_message(ros_type_name(type_name), coder, actuated, channel))


def lcm_coder(text: str, channel: str):
    """(coder, whether the vector is a system's input) of an `lcm` text (see the module doc)."""
    kind, _, value = str(text).partition("=")
    if not value:
        raise ValueError(f"the LCM side is 'signal=A,B', 'robot_state=J1,J2', 'robot_command=J1,J2' or "
                         f"'state_of=module:system' (also input_of, output_of), got {text!r}")
    if kind in _PORTS:
        from ..lcm import load_system

        frame = getattr(load_system(value), _PORTS[kind])
        return (frame.coder if frame.coder is not None else SignalCoder(frame)), kind == "input_of"
    names = tuple(n.strip() for n in value.split(",") if n.strip())
    if kind == "signal":
        return SignalCoder(Frame(channel, names)), False
    if kind == "robot_state":
        return RobotStateCoder(names), False
    if kind == "robot_command":
        return RobotCommandCoder(names), True
    raise ValueError(f"unknown LCM message kind {kind!r} in {text!r}: signal, robot_state, robot_command, "
                     f"state_of, input_of or output_of")


def ros_message(type_name: str, coder: LcmCoder, actuated: bool = False, label: str = "") -> RosMessage:
    """The ROS message of `type_name` that carries `coder`'s vectors."""
    cls = MESSAGE_TYPES[type_name]
    if cls is JointState:
        return JointState.for_coordinates(coder.frame.coordinates, actuated or isinstance(coder, RobotCommandCoder))
    if type_name == "std_msgs/Float64MultiArray":
        return cls(coder.dim, label or coder.frame.name)
    return cls()


def check_routes(routes):
    """Refuse routes that would echo a message back where it came from, or publish twice."""
    routes = list(routes)
    if not routes:
        raise ValueError("no routes: give --to-ros / --to-lcm or a mapping file with [[route]] tables")
    # a name may be read by several routes (fan-out), but one that a route writes has no other route
    for what, key, writer in (("LCM channel", "channel", TO_LCM), ("ROS topic", "topic", TO_ROS)):
        users = {}
        for route in routes:
            users.setdefault(getattr(route, key), []).append(route)
        for name, group in users.items():
            if len(group) > 1 and any(route.direction == writer for route in group):
                raise ValueError(f"{what} {name!r} is written by one route and used by another "
                                 f"({'; '.join(map(str, group))}): the translator would echo or interleave "
                                 f"messages; give each its own {what}")
    return routes


def read_mapping(path):
    """(routes, lcm_url or None) of a TOML mapping file (see the module doc)."""
    with open(path, "rb") as file:
        try:
            table = tomllib.load(file)
        except tomllib.TOMLDecodeError as error:
            raise ValueError(f"{path}: not a TOML file: {error}") from None
    unknown = set(table) - {"lcm_url", "route"}
    if unknown:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)} (lcm_url and [[route]] tables)")
    routes = []
    for k, entry in enumerate(table.get("route", [])):
        keys = {"direction", "channel", "topic", "type", "lcm"}
        if set(entry) != keys:
            raise ValueError(f"{path}: route {k + 1} needs exactly the keys {sorted(keys)}, has {sorted(entry)}")
        try:
            routes.append(Route.parse(entry["direction"], entry["channel"], entry["topic"], entry["type"], entry["lcm"]))
        except ValueError as error:
            raise ValueError(f"{path}: route {k + 1}: {error}") from None
    return routes, table.get("lcm_url")
