"""ROS bags: a simulation's or a node's messages in files ROS tools read.

`RosBag(path)` writes a ROS 1 bag (`path` ends in `.bag`; `rosbag info`, `rosbag play`) or a
ROS 2 bag folder stored as MCAP (any other path; `ros2 bag info`, Foxglove), through the
`rosbags` library, its writers and its serializers, with the message definitions of ROS 1
Noetic / ROS 2 Humble. `lcm_log_to_bag` turns an LCM event log (`LcmNode(log_path=...)`,
`lcm-logger`) into a bag along the routes of a mapping, each message logged at the time LCM
logged it.
"""

from __future__ import annotations

import pathlib

import numpy as np

from .._extras import require
from ..lcm import MessageError
from ._messages import RosMessage, stamp_from_seconds


def _build(typestore, msgtype, fields):
    """A `rosbags` message of `msgtype` from plain fields (`stamp` in nanoseconds; a field not
    given, such as ROS 1's `header.seq`, is 0)."""
    from rosbags.typesys.base import Nodetype

    if msgtype == "builtin_interfaces/msg/Time":
        return typestore.types[msgtype](*divmod(int(fields), 10**9))
    values = {}
    for name, (nodetype, detail) in typestore.fielddefs[msgtype][1]:
        value = fields.get(name, 0)
        if nodetype == Nodetype.NAME:
            value = _build(typestore, detail, value)
        elif nodetype == Nodetype.SEQUENCE:
            (element_kind, element), _ = detail
            if element_kind == Nodetype.NAME:
                value = [_build(typestore, element, item) for item in value]
            elif element[0] != "string":
                value = np.asarray(value, dtype=element[0])
            else:
                value = list(value)
        values[name] = value
    return typestore.types[msgtype](**values)


class RosBag:
    """A bag being written at `path` (`.bag`: ROS 1; otherwise a ROS 2 folder with MCAP
    storage). `write(topic, message, fields, log_time_ns)` adds one message of the `RosMessage`
    type `message`; `write_vector(topic, message, t, x)` one vector, logged at its time t.
    Use as a context manager or call `close()`."""

    def __init__(self, path):
        require("rosbags", "RosBag")
        from rosbags.typesys import Stores, get_typestore

        self.path = pathlib.Path(path)
        self.ros1 = self.path.suffix == ".bag"
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self.typestore, self._writer = get_typestore(Stores.ROS1_NOETIC), Writer(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            self._writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections = {}
        self.count = 0

    def _connection(self, topic, msgtype):
        if topic not in self._connections:
            self._connections[topic] = (self._writer.add_connection(topic, msgtype, typestore=self.typestore), msgtype)
        connection, known = self._connections[topic]
        if known != msgtype:
            raise ValueError(f"topic {topic} already carries {known} in {self.path}, not {msgtype}")
        return connection

    def write(self, topic: str, message: RosMessage, fields: dict, log_time_ns: int):
        msgtype = f"{message.package}/msg/{message.name}"
        obj = _build(self.typestore, msgtype, fields)
        serialize = self.typestore.serialize_ros1 if self.ros1 else self.typestore.serialize_cdr
        self._writer.write(self._connection(topic, msgtype), int(log_time_ns), serialize(obj, msgtype))
        self.count += 1

    def write_vector(self, topic: str, message: RosMessage, t: float, x):
        self.write(topic, message, message.encode(t, x), stamp_from_seconds(t))

    def close(self):
        self._writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def lcm_log_to_bag(log_path, bag_path, routes) -> dict:
    """Write the messages of an LCM event log on the routes' channels (either direction) to a
    bag on their topics; returns {topic: messages written}. Messages that do not decode are
    skipped and counted under `"malformed"`."""
    lcm = require("lcm", "lcm_log_to_bag")

    by_channel = {route.channel: route for route in routes}
    counts = dict.fromkeys([route.topic for route in routes], 0)
    counts["malformed"] = 0
    with RosBag(bag_path) as bag:
        for event in lcm.EventLog(str(log_path), "r"):
            route = by_channel.get(event.channel)
            if route is None:
                continue
            try:
                fields = route.message.encode(*route.coder.decode(event.data))
            except MessageError:
                counts["malformed"] += 1
                continue
            bag.write(route.topic, route.message, fields, event.timestamp * 1000)
            counts[route.topic] += 1
    return counts
