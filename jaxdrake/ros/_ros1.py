"""ROS 1 through `rospy`: the translator as a node of a ROS 1 (Noetic) network.

`rospy` comes from Debian (`apt-get install ros-core python3-rospy ...`), built for Debian's
Python 3.11, the same minor version as the project's: its folder of packages,
`/usr/lib/python3/dist-packages`, is *appended* to `sys.path` of the translator's process (so a
package the project installed wins over Debian's copy) — the translator is its own process,
the notes' design, and one process keeps the LCM side's coders and the ROS side in one
address space with no extra hop. rospy allows one node per process.

Subscriptions take the raw bytes (`rospy.AnyMsg`) and deserialize them here, so a message of
another type (the publisher's connection header names it) or one that does not deserialize is
counted and dropped instead of being lost inside rospy's threads.

The master is watched every `poll` seconds. When it goes away the node keeps its peer-to-peer
connections; when a master answers again at the same URI (restarted) the node registers its
publishers and subscribers with it anew, as it did at start, and reconnects to the publishers
that master knows. A master absent for longer than `master_timeout` (at start, or later) is a
`MasterError` naming the URI.
"""

from __future__ import annotations

import logging
import os
import struct
import sys
import threading
import time
import xmlrpc.client

log = logging.getLogger("jaxdrake.ros")

DEBIAN_PYTHON_PACKAGES = "/usr/lib/python3/dist-packages"


class RosUnavailableError(ImportError):
    """ROS 1's Python packages (rospy) are not installed."""


class MasterError(RuntimeError):
    """The ROS master cannot be reached (at start, or for longer than the translator waits)."""


def import_rospy():
    """`rospy`, from the environment or else from Debian's packages (appended to `sys.path`)."""
    try:
        import rospy
    except ImportError:
        if os.path.isdir(DEBIAN_PYTHON_PACKAGES) and DEBIAN_PYTHON_PACKAGES not in sys.path:
            sys.path.append(DEBIAN_PYTHON_PACKAGES)
        try:
            import rospy
        except ImportError as error:
            raise RosUnavailableError(
                f"rospy is not installed ({error}); on Debian: apt-get install ros-core python3-rospy "
                "python3-rostopic python3-std-msgs python3-sensor-msgs python3-geometry-msgs (docs/ros.md)") from None
    return rospy


def _message_class(type_name):
    import roslib.message

    cls = roslib.message.get_message_class(type_name)
    if cls is None:
        raise RosUnavailableError(f"the ROS 1 message {type_name} is not installed (apt-get install "
                                  f"python3-{type_name.split('/')[0].replace('_', '-')})")
    return cls


def build(cls, fields: dict):
    """A genpy message of class `cls` from plain fields (`stamp` in nanoseconds)."""
    import genpy

    msg = cls()
    for name, slot_type in zip(cls.__slots__, cls._slot_types):
        if name not in fields:
            continue
        value = fields[name]
        if slot_type == "time":
            value = genpy.Time(*divmod(int(value), 10**9))
        elif isinstance(value, dict):
            value = build(type(getattr(msg, name)), value)
        elif slot_type.endswith("[]") and "/" in slot_type:
            element = _message_class(slot_type[:-2])
            value = [build(element, item) for item in value]
        setattr(msg, name, value)
    return msg


def read(msg) -> dict:
    """The plain fields of a genpy message (`stamp` in nanoseconds)."""
    import genpy

    fields = {}
    for name in msg.__slots__:
        value = getattr(msg, name)
        if isinstance(value, genpy.Time):
            value = value.secs * 10**9 + value.nsecs
        elif isinstance(value, genpy.Message):
            value = read(value)
        elif isinstance(value, (list, tuple)) and value and isinstance(value[0], genpy.Message):
            value = [read(item) for item in value]
        fields[name] = value
    return fields


class Ros1Network:
    """A rospy node named `node_name` (made unique with a suffix), on the master of
    `ROS_MASTER_URI`; see the module doc for `master_timeout` and `poll`."""

    kind = "ROS 1"

    def __init__(self, node_name: str = "jaxdrake_ros", *, master_timeout: float = 30.0, poll: float = 0.5):
        self._rospy = rospy = import_rospy()
        import rosgraph

        self.master_uri = rosgraph.get_master_uri()
        self.master_timeout, self.poll = float(master_timeout), float(poll)
        self._master = rosgraph.Master("/jaxdrake_ros_watch")
        self._pid = self._wait_for_master(time.monotonic() + self.master_timeout)
        rospy.init_node(node_name, anonymous=True, disable_signals=True)
        self.master_losses = self.reregistrations = 0
        self.error: MasterError | None = None
        self._closed = threading.Event()
        self._watcher = threading.Thread(target=self._watch, daemon=True, name="jaxdrake-ros-master-watch")
        self._watcher.start()

    def _master_pid(self):
        try:
            return self._master.getPid()
        except Exception:  # refused, reset, or one of rosgraph's own errors: no master now
            return None

    def _wait_for_master(self, deadline):
        while (pid := self._master_pid()) is None:
            if time.monotonic() > deadline:
                raise MasterError(f"no ROS master answers at {self.master_uri} (waited {self.master_timeout:g} s): "
                                  f"start roscore, or set ROS_MASTER_URI")
            time.sleep(min(self.poll, 0.1))
        return pid

    # ----- topics ---------------------------------------------------------------------------

    def publisher(self, topic, message):
        """A function publishing plain fields of `message` on `topic`."""
        cls = _message_class(message.type_name)
        pub = self._rospy.Publisher(topic, cls, queue_size=100)
        return lambda fields: pub.publish(build(cls, fields))

    def subscribe(self, topic, message, deliver, refuse):
        """Call `deliver(fields)` for each message on `topic`, `refuse(kind, reason)` (kind
        "wrong_type" or "malformed") for one that cannot be read as `message`."""
        import genpy

        cls = _message_class(message.type_name)

        def on_raw(raw):
            sent_type = raw._connection_header.get("type")
            if sent_type != message.type_name:
                return refuse("wrong_type", f"{sent_type} on {topic}, which carries {message.type_name}")
            try:
                fields = read(cls().deserialize(raw._buff))
            except (genpy.DeserializationError, struct.error, ValueError, UnicodeDecodeError) as error:
                return refuse("malformed", f"{message.type_name} of {len(raw._buff)} bytes on {topic}: {error}")
            deliver(fields)

        self._rospy.Subscriber(topic, self._rospy.AnyMsg, on_raw, tcp_nodelay=True)

    # ----- the master -----------------------------------------------------------------------

    def _watch(self):
        lost_since = None
        while not self._closed.wait(self.poll):
            pid = self._master_pid()
            now = time.monotonic()
            if pid is None:
                if lost_since is None:
                    lost_since = now
                    self.master_losses += 1
                    log.warning("the ROS master at %s is gone; waiting up to %g s for it", self.master_uri,
                                self.master_timeout)
                elif now - lost_since > self.master_timeout:
                    self.error = MasterError(f"the ROS master at {self.master_uri} has been gone for "
                                             f"{self.master_timeout:g} s")
                    return
                continue
            if lost_since is not None or pid != self._pid:
                self._register_again()
            lost_since, self._pid = None, pid

    def _register_again(self):
        """Register every publisher and subscriber of this node with a (restarted) master, and
        hand the publishers it knows to the node, as rospy does at start."""
        from rospy.impl.registration import get_topic_manager

        rospy = self._rospy
        uri, manager = rospy.get_node_uri(), get_topic_manager()
        master = xmlrpc.client.ServerProxy(self.master_uri)
        caller = rospy.get_caller_id()
        try:
            for topic, type_name in manager.get_publications():
                master.registerPublisher(caller, topic, type_name, uri)
            for topic, type_name in manager.get_subscriptions():
                code, _, publishers = master.registerSubscriber(caller, topic, type_name, uri)
                if code == 1:
                    xmlrpc.client.ServerProxy(uri).publisherUpdate("/master", topic, publishers)
        except (OSError, xmlrpc.client.Error) as error:
            log.warning("registering again with the ROS master at %s failed (%s); retrying", self.master_uri, error)
            self._pid = None  # try again on the next poll
            return
        self.reregistrations += 1
        log.warning("the ROS master at %s answers again: publishers and subscribers registered anew",
                    self.master_uri)

    def check(self):
        """Raise the `MasterError` the watcher found, if any."""
        if self.error is not None:
            raise self.error

    def close(self):
        self._closed.set()
        self._rospy.signal_shutdown("jaxdrake.ros translator stopped")
