"""ROS 2 over DDS with Cyclone DDS's Python binding (`cyclonedds`), no ROS 2 installation.

A ROS 2 node's topic `/a/b` of type `pkg/msg/T` is the DDS topic `rt/a/b` of type
`pkg::msg::dds_::T_`, its samples in little-endian plain CDR (XCDR1, encapsulation
`00 01 00 00`), with ROS 2's default QoS: reliable, keep last 10, volatile. The structs below
are those types, field for field in the order of their `.msg` files (Humble to Jazzy agree on
all of them).

`LOOPBACK` is a Cyclone configuration that keeps every participant on the loopback interface:
multicast off on `lo` and in general, discovery by unicast to the participant ports of
127.0.0.1. (Cyclone itself, when it lists the interfaces, sends one 16-byte datagram with TTL 0
to 239.255.0.1 on `lo` to see whether the loopback interface loops multicast back: that probe
happens before any configuration is read and never leaves the host; no DDS traffic goes to a
multicast address.) Other ROS 2 processes reach a translator on `LOOPBACK` only with the same
configuration (`CYCLONEDDS_URI`, see docs/ros.md).
"""


import dataclasses
import logging

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

log = logging.getLogger("jaxdrake.ros")

LOOPBACK = """<CycloneDDS><Domain Id="any">
  <General><Interfaces><NetworkInterface name="lo" multicast="false"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>
    <Peers><Peer Address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


def _dds(package, name):
    return f"{package}::msg::dds_::{name}_"


@dataclasses.dataclass
class Time(IdlStruct, typename=_dds("builtin_interfaces", "Time")):
    sec: t.int32
    nanosec: t.uint32


@dataclasses.dataclass
class Header(IdlStruct, typename=_dds("std_msgs", "Header")):
    stamp: Time
    frame_id: str


@dataclasses.dataclass
class MultiArrayDimension(IdlStruct, typename=_dds("std_msgs", "MultiArrayDimension")):
    label: str
    size: t.uint32
    stride: t.uint32


@dataclasses.dataclass
class MultiArrayLayout(IdlStruct, typename=_dds("std_msgs", "MultiArrayLayout")):
    dim: t.sequence[MultiArrayDimension]
    data_offset: t.uint32


@dataclasses.dataclass
class Float64MultiArray(IdlStruct, typename=_dds("std_msgs", "Float64MultiArray")):
    layout: MultiArrayLayout
    data: t.sequence[t.float64]


@dataclasses.dataclass
class JointState(IdlStruct, typename=_dds("sensor_msgs", "JointState")):
    header: Header
    name: t.sequence[str]
    position: t.sequence[t.float64]
    velocity: t.sequence[t.float64]
    effort: t.sequence[t.float64]


@dataclasses.dataclass
class Vector3(IdlStruct, typename=_dds("geometry_msgs", "Vector3")):
    x: t.float64
    y: t.float64
    z: t.float64


@dataclasses.dataclass
class Twist(IdlStruct, typename=_dds("geometry_msgs", "Twist")):
    linear: Vector3
    angular: Vector3


@dataclasses.dataclass
class Wrench(IdlStruct, typename=_dds("geometry_msgs", "Wrench")):
    force: Vector3
    torque: Vector3


@dataclasses.dataclass
class WrenchStamped(IdlStruct, typename=_dds("geometry_msgs", "WrenchStamped")):
    header: Header
    wrench: Wrench


IDL_TYPES = {"std_msgs/Float64MultiArray": Float64MultiArray, "sensor_msgs/JointState": JointState,
             "geometry_msgs/Twist": Twist, "geometry_msgs/WrenchStamped": WrenchStamped}
# the struct-valued fields (a list: a sequence of that struct)
_NESTED = {(Header, "stamp"): Time, (MultiArrayLayout, "dim"): [MultiArrayDimension],
           (Float64MultiArray, "layout"): MultiArrayLayout, (JointState, "header"): Header,
           (Twist, "linear"): Vector3, (Twist, "angular"): Vector3, (Wrench, "force"): Vector3,
           (Wrench, "torque"): Vector3, (WrenchStamped, "header"): Header, (WrenchStamped, "wrench"): Wrench}


def build(cls, fields):
    """A sample of IDL struct `cls` from plain fields (`stamp` in nanoseconds)."""
    if cls is Time:
        return Time(*divmod(int(fields), 10**9))
    values = {}
    for field in dataclasses.fields(cls):
        value, nested = fields[field.name], _NESTED.get((cls, field.name))
        if isinstance(nested, list):
            value = [build(nested[0], item) for item in value]
        elif nested is not None:
            value = build(nested, value)
        elif isinstance(value, (list, tuple)):
            value = list(value)
        values[field.name] = value
    return cls(**values)


def read(sample) -> dict:
    """The plain fields of an IDL sample (`stamp` in nanoseconds)."""
    if isinstance(sample, Time):
        return sample.sec * 10**9 + sample.nanosec
    fields = {}
    for field in dataclasses.fields(sample):
        value = getattr(sample, field.name)
        if isinstance(value, IdlStruct):
            value = read(value)
        elif isinstance(value, list) and value and isinstance(value[0], IdlStruct):
            value = [read(item) for item in value]
        fields[field.name] = value
    return fields


def default_qos():
    """ROS 2's default QoS profile (`rmw_qos_profile_default`), samples in XCDR1."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10),
               Policy.Durability.Volatile, Policy.DataRepresentation(use_cdrv0_representation=True))


class Ros2Network:
    """A DDS participant in `domain_id` (ROS_DOMAIN_ID) speaking ROS 2's topics; `config` is a
    Cyclone XML configuration (default `LOOPBACK`; None: Cyclone's own, from `CYCLONEDDS_URI`)."""

    kind = "ROS 2"

    def __init__(self, domain_id: int = 0, *, config: str | None = LOOPBACK):
        from cyclonedds.domain import Domain, DomainParticipant

        self.domain_id = int(domain_id)
        self._domain = Domain(self.domain_id, config) if config is not None else None
        self.participant = DomainParticipant(self.domain_id)
        self._topics, self._entities = {}, []
        self.error = None

    def _topic(self, topic, message):
        from cyclonedds.topic import Topic

        if topic not in self._topics:
            self._topics[topic] = Topic(self.participant, "rt" + topic, IDL_TYPES[message.type_name], qos=default_qos())
        return self._topics[topic]

    def publisher(self, topic, message):
        from cyclonedds.pub import DataWriter

        cls = IDL_TYPES[message.type_name]
        writer = DataWriter(self.participant, self._topic(topic, message), qos=default_qos())
        self._entities.append(writer)
        return lambda fields: writer.write(build(cls, fields))

    def subscribe(self, topic, message, deliver, refuse):
        """Call `deliver(fields)` for each sample on `topic`, `refuse("malformed", reason)` for a
        sample that does not deserialize. (A writer of another type never matches the reader:
        DDS refuses the pair by type name.)"""
        from cyclonedds.core import Listener
        from cyclonedds.sub import DataReader

        def on_data(reader):
            while True:
                try:
                    samples = reader.take(N=64)
                except Exception as error:  # the binding's deserializer raises on bad bytes
                    refuse("malformed", f"{message.type_name} sample on {topic}: {error}")
                    continue
                if not samples:
                    return
                for sample in samples:
                    if isinstance(sample, IdlStruct):  # not an InvalidSample (a writer gone, ...)
                        deliver(read(sample))

        reader = DataReader(self.participant, self._topic(topic, message), qos=default_qos(),
                            listener=Listener(on_data_available=on_data))
        self._entities.append(reader)

    def check(self):
        pass

    def close(self):
        """Delete the readers, writers and the participant (the binding deletes a DDS entity
        when its last Python reference goes)."""
        self._entities.clear()
        self._topics.clear()
        self.participant = self._domain = None
