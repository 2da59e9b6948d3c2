"""The ROS–LCM translator against a real ROS 1 master (Debian's roscore, rostopic, rosbag) on
127.0.0.1 at a free port, ROS 2's wire format against `rosbags`' CDR serializer and between two
processes over Cyclone DDS on the loopback interface (strace shows no DDS traffic to a multicast
address), and bags read back by `rosbags` and Debian's `rosbag`. LCM runs on a LoopbackRelay.

ROS 1 tests skip only where Debian's ROS packages are not installed (`.ci/run` installs them);
under CI they fail instead."""

import copy
import json
import logging
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import xmlrpc.client

import lcm
import numpy as np
import pytest
import yaml

import jaxdrake as jd
from jaxdrake.lcm import LcmNode, LoopbackRelay, RobotStateCoder, SignalCoder
from jaxdrake.ros import (TO_LCM, TO_ROS, Float64MultiArray, JointState, Route, RosBag, Twist, WrenchStamped,
                          lcm_log_to_bag, read_mapping)
from jaxdrake.systems import Frame

from _ros1 import DEBIAN_PYTHON, HAVE_ROS1, require_ros1  # tests/_ros1.py

ROOT = pathlib.Path(__file__).resolve().parents[1]


def free_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ros_env(port, home):
    return dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_IP="127.0.0.1",
                ROS_HOSTNAME="127.0.0.1", ROS_HOME=str(home), ROS_LOG_DIR=str(home / "log"))


def start_roscore(env, port):
    """roscore in its own process group (roslaunch starts the master and rosout as children)."""
    process = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    master = xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"])
    deadline = time.time() + 60
    while time.time() < deadline:
        try:
            master.getPid("/test")
            return process
        except OSError:
            time.sleep(0.1)
    stop_process_group(process)
    raise RuntimeError("roscore did not start")


def descendants(pid):
    try:
        children = pathlib.Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return []
    return [int(c) for c in children] + [d for c in children for d in descendants(int(c))]


def stop_process_group(process, sig=signal.SIGINT):
    """Stop roscore: SIGINT lets roslaunch stop its master and rosout; SIGKILL (a crash) kills
    them one by one, as roslaunch starts each in a session of its own."""
    pids = [process.pid] + (descendants(process.pid) if sig == signal.SIGKILL else [])
    try:
        for pid in pids:
            os.kill(pid, sig)
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    except ProcessLookupError:
        pass


def translator(env, *args):
    """`python -m jaxdrake.ros ARGS` once it has printed its start line (its routes are set up)."""
    process = subprocess.Popen([sys.executable, "-m", "jaxdrake.ros", *args], cwd=ROOT, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    while not any(line.startswith("translator between") for line in lines):
        line = process.stdout.readline()
        if not line and process.poll() is not None:
            raise RuntimeError("the translator did not start:\n" + "".join(lines))
        lines.append(line)
    return process


def route_counts(output):
    """{route text: {counter: value}} from the translator's 'stopped:' lines."""
    counts = {}
    for route, numbers in re.findall(r"^stopped: (.*?): (\d+ received.*)$", output, re.M):
        counts[route] = {key.replace(" ", "_"): int(value)
                         for value, key in re.findall(r"(\d+) (received|forwarded|malformed|wrong type)", numbers)}
    return counts


def wait_for(condition, timeout, handle=None):
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            return False
        handle() if handle else time.sleep(0.05)
    return True


# ----- message types and routes (no network) -------------------------------------------------

def test_joint_state_reads_joints_by_name_not_position():
    message = JointState(("shoulder", "elbow"), ("position", "velocity"))
    fields = {"header": {"stamp": 7_250_000_000, "frame_id": ""}, "name": ["elbow", "wrist", "shoulder"],
              "position": [0.2, 9.0, 0.1], "velocity": [2.0, 9.0, 1.0], "effort": []}
    t, x = message.decode(fields)
    assert t == 7.25
    np.testing.assert_array_equal(x, [0.1, 0.2, 1.0, 2.0])
    encoded = message.encode(1.5, [0.1, 0.2, 1.0, 2.0])
    assert encoded["name"] == ["shoulder", "elbow"] and encoded["effort"] == []
    assert encoded["header"]["stamp"] == 1_500_000_000
    for bad, reason in (({"name": ["elbow"], "position": [0.2], "velocity": [2.0]}, "lacks joints"),
                        ({"name": ["elbow", "shoulder"], "position": [0.2], "velocity": [2.0, 1.0]}, "1 position values"),
                        ({"name": ["elbow", "shoulder", "elbow"], "position": [0, 0, 0], "velocity": [0, 0, 0]}, "twice"),
                        ({"name": ["elbow", "shoulder"], "position": [0.2, np.nan], "velocity": [2.0, 1.0]}, "non-finite")):
        with pytest.raises(jd.lcm.MessageError, match=reason):
            message.decode(dict(header={"stamp": 0, "frame_id": ""}, effort=[], **bad))


def test_joint_state_of_a_plant_state_and_of_its_input():
    acrobot = jd.models.Acrobot()
    state = JointState.for_coordinates(acrobot.state_frame.coordinates)
    assert state.joints == ("shoulder", "elbow") and state.fields == ("position", "velocity")
    command = JointState.for_coordinates(acrobot.input_frame.coordinates, actuated=True)
    assert command.joints == ("elbow",) and command.fields == ("effort",)
    robot = JointState.for_coordinates(RobotStateCoder(["a", "b"]).frame.coordinates)
    assert robot.joints == ("a", "b") and robot.fields == ("position", "velocity")


def test_stamps_cross_exactly_on_lcms_microsecond_grid():
    """An LCM stamp (integer microseconds, epoch-sized) reaches a ROS stamp and comes back equal."""
    coder = SignalCoder(Frame("W", tuple("abcdef")))
    message = WrenchStamped("base")
    for utime in (0, 1, 999_999, 1_795_000_000_123_456):
        data = coder.encode(utime * 1e-6, np.arange(6.0))
        fields = message.encode(*coder.decode(data))
        assert fields["header"]["stamp"] == utime * 1000 and fields["header"]["frame_id"] == "base"
        assert coder.encode(*message.decode(fields)) == data


def test_routes_from_a_mapping_file_and_refusals(tmp_path):
    mapping = tmp_path / "map.toml"
    mapping.write_text(textwrap.dedent("""
        lcm_url = "tcpq://127.0.0.1:7700"
        [[route]]
        direction = "to_ros"
        channel = "PendulumState"
        topic = "/pendulum/state"
        type = "sensor_msgs/msg/JointState"
        lcm = "state_of=jaxdrake.models:Pendulum"
        [[route]]
        direction = "to_lcm"
        topic = "/cmd_vel"
        channel = "CmdVel"
        type = "Twist"
        lcm = "signal=vx,vy,vz,wx,wy,wz"
        """))
    routes, url = read_mapping(mapping)
    assert url == "tcpq://127.0.0.1:7700"
    assert [str(r) for r in routes] == ["PendulumState -> /pendulum/state (sensor_msgs/JointState)",
                                       "/cmd_vel -> CmdVel (geometry_msgs/Twist)"]
    assert routes[0].message.joints == ("theta",) and isinstance(routes[1].message, Twist)
    with pytest.raises(ValueError, match="carries 6 values here, the LCM side 2"):
        Route.parse(TO_ROS, "PendulumState", "/x", "Twist", "signal=a,b")
    with pytest.raises(ValueError, match="unsupported ROS message type"):
        Route.parse(TO_ROS, "A", "/x", "std_msgs/String", "signal=a")
    with pytest.raises(ValueError, match="echo or interleave"):
        jd.ros._routes.check_routes([Route.parse(TO_ROS, "A", "/x", "Float64MultiArray", "signal=a"),
                                     Route.parse(TO_LCM, "B", "/x", "Float64MultiArray", "signal=a")])
    mapping.write_text('[[route]]\ndirection = "to_ros"\nchannel = "A"\n')
    with pytest.raises(ValueError, match="route 1 needs exactly the keys"):
        read_mapping(mapping)


def test_command_line_help_and_bad_arguments(capsys):
    from jaxdrake.ros.__main__ import main

    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0 and "--to-ros CHANNEL TOPIC TYPE LCM" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        main(["--to-ros", "A", "/a", "Twist", "nonsense"])
    assert done.value.code == 2 and "the LCM side is" in capsys.readouterr().err


# ----- ROS 2: CDR bytes and DDS between processes ---------------------------------------------

SAMPLES = [(Float64MultiArray(3, "PendulumSetpoint"), 0.0, [1.0, -2.5, 1e-300]),
           (JointState(("shoulder", "elbow"), ("position", "velocity", "effort")), 12.345678, np.arange(6.0) - 2.5),
           (JointState(("j",), ("effort",)), 1795000000.25, [3.0]),
           (Twist(), 0.0, [0.5, 0, 0, 0, 0, -1.25]),
           (WrenchStamped("tool0"), 3.000001, [1, 2, 3, 4, 5, 6])]


@pytest.mark.parametrize("message, t, x", SAMPLES, ids=lambda v: getattr(v, "type_name", None))
def test_cdr_bytes_equal_rosbags_serialisation(message, t, x):
    """What the DDS writer sends (Cyclone's serializer of our IDL structs) is byte for byte what
    rosbags serializes for ROS 2 Humble's definition of the same message."""
    from rosbags.typesys import Stores, get_typestore

    from jaxdrake.ros import _bags, _ros2

    fields = message.encode(t, x)
    ours = _ros2.build(_ros2.IDL_TYPES[message.type_name], fields).serialize()
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    msgtype = f"{message.package}/msg/{message.name}"
    theirs = bytes(typestore.serialize_cdr(_bags._build(typestore, msgtype, fields), msgtype))
    assert ours[:4] == b"\x00\x01\x00\x00" and ours == theirs
    back = _ros2.read(_ros2.IDL_TYPES[message.type_name].deserialize(theirs))
    np.testing.assert_array_equal(message.decode(back)[1], np.asarray(x, float))
    assert "header" not in back or back["header"]["stamp"] == round(t * 1e6) * 1000


ROS2_PEER = r'''
"""A ROS 2 node stand-in: its own IDL structs, Cyclone configured by CYCLONEDDS_URI."""
import dataclasses, json, sys, time
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct, types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

@dataclasses.dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32
    nanosec: t.uint32
@dataclasses.dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str
@dataclasses.dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64
    y: t.float64
    z: t.float64
@dataclasses.dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3
    angular: Vector3
@dataclasses.dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3
    torque: Vector3
@dataclasses.dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header
    wrench: Wrench
@dataclasses.dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header
    name: t.sequence[str]
    position: t.sequence[t.float64]
    velocity: t.sequence[t.float64]
    effort: t.sequence[t.float64]

qos = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10),
          Policy.Durability.Volatile, Policy.DataRepresentation(use_cdrv0_representation=True))
participant = DomainParticipant(int(sys.argv[1]))
twist = DataWriter(participant, Topic(participant, "rt/cmd_vel", Twist, qos=qos), qos=qos)
joints = DataWriter(participant, Topic(participant, "rt/joint_states", JointState, qos=qos), qos=qos)
wrench = DataReader(participant, Topic(participant, "rt/wrench", WrenchStamped, qos=qos), qos=qos)
print("ready", flush=True)
end = time.time() + float(sys.argv[2])
k = 0
bad = [JointState(Header(Time(0, 0), ""), ["a", "b"], [1.0], [1.0, 1.0], []),                # lengths differ
       JointState(Header(Time(0, 0), ""), ["a", "b"], [1.0, float("nan")], [1.0, 1.0], []),  # non-finite
       JointState(Header(Time(0, 0), ""), ["b"], [1.0], [1.0], [])]                           # a joint missing
while time.time() < end:
    twist.write(Twist(Vector3(0.5, 0.0, k), Vector3(0.0, 0.0, -1.25)))
    if k == 40:  # by then the translator's reader has matched
        for sample in bad:
            joints.write(sample)
        joints.write(JointState(Header(Time(5, 250000), ""), ["b", "a"], [2.0, 1.0], [20.0, 10.0], []))
    for sample in wrench.take(N=10):
        if isinstance(sample, WrenchStamped):
            print(json.dumps({"stamp": [sample.header.stamp.sec, sample.header.stamp.nanosec],
                              "frame_id": sample.header.frame_id,
                              "force": [sample.wrench.force.x, sample.wrench.force.y, sample.wrench.force.z],
                              "torque": [sample.wrench.torque.x, sample.wrench.torque.y, sample.wrench.torque.z]}),
                  flush=True)
    k += 1
    time.sleep(0.02)
'''


def test_two_processes_exchange_ros2_messages_over_loopback_dds_without_multicast(tmp_path):
    """The translator (ROS 2, `--dds loopback`) under strace, and a DDS peer configured with the
    same loopback XML through CYCLONEDDS_URI: Twist samples reach LCM, LCM wrenches reach the peer
    with their stamps, malformed JointStates are counted and dropped, and every RTPS datagram the
    translator sends goes to 127.0.0.1 (the only multicast-addressed one is Cyclone's 16-byte
    loopback probe, TTL 0, sent before any configuration is read)."""
    from jaxdrake.ros import LOOPBACK

    require_ros1(shutil.which("strace"), "strace is")
    domain = 1 + os.getpid() % 200  # away from domain 0 and from other test runs on this machine
    config = tmp_path / "cyclonedds.xml"
    config.write_text(LOOPBACK)
    peer_script = tmp_path / "peer.py"
    peer_script.write_text(ROS2_PEER)
    env = dict(os.environ, CYCLONEDDS_URI=config.as_uri())
    trace = tmp_path / "strace.txt"
    with LoopbackRelay() as relay:
        process = subprocess.Popen(
            ["strace", "-f", "-qq", "-e", "trace=sendto,sendmsg,sendmmsg,setsockopt", "-o", str(trace),
             sys.executable, "-m", "jaxdrake.ros", "--ros", "2", "--domain-id", str(domain), "--url", relay.url,
             "--to-ros", "Wrench", "/wrench", "geometry_msgs/WrenchStamped", "signal=fx,fy,fz,tx,ty,tz",
             "--to-lcm", "/cmd_vel", "CmdVel", "geometry_msgs/Twist", "signal=vx,vy,vz,wx,wy,wz",
             "--to-lcm", "/joint_states", "Joints", "sensor_msgs/JointState", "robot_state=a,b"],
            cwd=ROOT, env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        line = ""
        while not line.startswith("translator between"):
            line = process.stdout.readline()
            assert line or process.poll() is None, "the translator did not start"
        peer = subprocess.Popen([sys.executable, str(peer_script), str(domain), "4"], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert peer.stdout.readline().startswith("ready")
        bus = lcm.LCM(relay.url)
        twists, joints = [], []
        twist_coder, joint_coder = SignalCoder(Frame("CmdVel", ("vx", "vy", "vz", "wx", "wy", "wz"))), RobotStateCoder(["a", "b"])
        bus.subscribe("CmdVel", lambda c, d: twists.append(twist_coder.decode(d)))
        bus.subscribe("Joints", lambda c, d: joints.append(joint_coder.decode(d)))
        wrench_coder = SignalCoder(Frame("Wrench", ("fx", "fy", "fz", "tx", "ty", "tz")))
        k = 0
        while peer.poll() is None:
            bus.publish("Wrench", wrench_coder.encode(2.0 + k * 1e-6, [1, 2, 3, 4, 5, k]))
            k += 1
            bus.handle_timeout(20)
        peer_out = peer.stdout.read()
        traced = int(pathlib.Path(f"/proc/{process.pid}/task/{process.pid}/children").read_text().split()[0])
        os.kill(traced, signal.SIGTERM)  # the translator itself: strace would detach on a signal of its own
        out, _ = process.communicate(timeout=60)
    assert process.returncode == 0, out
    received = [json.loads(line) for line in peer_out.splitlines() if line.startswith("{")]
    assert len(received) > 10, peer_out
    last = received[-1]
    j = int(last["torque"][2])
    assert last["stamp"] == [2, j * 1000] and last["force"] == [1, 2, 3] and last["torque"] == [4, 5, j]
    assert len(twists) > 10
    np.testing.assert_array_equal(twists[-1][1][[0, 1, 3, 4, 5]], [0.5, 0, 0, 0, -1.25])
    assert len(joints) == 1 and round(joints[0][0] * 1e6) == 5_000_250  # the stamp, to the microsecond
    # by name: a first, b second
    np.testing.assert_array_equal(joints[0][1], [1.0, 2.0, 10.0, 20.0])
    counts = route_counts(out)
    assert counts["/joint_states -> Joints (sensor_msgs/JointState)"]["malformed"] == 3, out
    sends = [line for line in trace.read_text().splitlines() if "sendmsg(" in line or "sendto(" in line]
    rtps = [line for line in sends if '"RTPS' in line]
    assert len(rtps) > 20 and all('inet_addr("127.0.0.1")' in line for line in rtps)
    multicast = [line for line in sends if re.search(r'inet_addr\("2(2[4-9]|3\d)\.', line)]
    assert all('iov_len=16}' in line and '"RTPS' not in line for line in multicast), multicast
    assert len(multicast) <= 1


# ----- bags -----------------------------------------------------------------------------------

DEBIAN_ROSBAG_READER = r'''
import json, sys, rosbag
with rosbag.Bag(sys.argv[1]) as bag:
    print(json.dumps([[topic, msg._type, msg.header.stamp.to_nsec(), list(msg.name), list(msg.position),
                       list(msg.velocity), t.to_nsec()] for topic, msg, t in bag.read_messages()]))
'''


def test_a_nodes_lcm_log_as_a_ros1_bag_and_its_simulation_as_an_mcap_bag(tmp_path):
    """A simulated plant node's LCM log becomes a ROS 1 bag that rosbags and Debian's rosbag read
    back to the logged states and times; its states written one by one become a ROS 2 MCAP bag
    whose CDR payloads are the bytes the DDS writer sends, and which rosbags reads back."""
    from rosbags.highlevel import AnyReader

    from jaxdrake.ros import _ros2

    pendulum = jd.models.Pendulum()
    bus = lcm.LCM("memq://")
    LcmNode(pendulum, bus, rate=100.0, x0=[1.0, 0.0], log_path=tmp_path / "plant.log").run(max_ticks=30)
    route = Route.parse(TO_ROS, "PendulumState", "/pendulum/state", "sensor_msgs/JointState",
                        "state_of=jaxdrake.models:Pendulum")
    logged = [(e.timestamp, *SignalCoder(pendulum.state_frame).decode(e.data))
              for e in lcm.EventLog(str(tmp_path / "plant.log"), "r") if e.channel == "PendulumState"]
    counts = lcm_log_to_bag(tmp_path / "plant.log", tmp_path / "plant.bag", [route])
    assert counts == {"/pendulum/state": 30, "malformed": 0}
    with AnyReader([tmp_path / "plant.bag"]) as reader:
        read = [(timestamp, reader.deserialize(raw, connection.msgtype))
                for connection, timestamp, raw in reader.messages()]
    assert [r[0] for r in read] == [log_time * 1000 for log_time, _, _ in logged]
    for (_, msg), (_, t, x) in zip(read, logged):
        assert list(msg.name) == ["theta"] and msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == round(t * 1e6) * 1000
        np.testing.assert_array_equal([msg.position[0], msg.velocity[0]], x)
    if HAVE_ROS1:
        debian = json.loads(subprocess.run([DEBIAN_PYTHON, "-c", DEBIAN_ROSBAG_READER, str(tmp_path / "plant.bag")],
                                           capture_output=True, text=True, check=True).stdout)
        assert [d[:2] for d in debian] == [["/pendulum/state", "sensor_msgs/JointState"]] * 30
        assert [d[2] for d in debian] == [round(t * 1e6) * 1000 for _, t, _ in logged]
        np.testing.assert_array_equal([d[4] + d[5] for d in debian], [x for _, _, x in logged])
        info = yaml.safe_load(subprocess.run(["rosbag", "info", "--yaml", str(tmp_path / "plant.bag")],
                                             capture_output=True, text=True, check=True).stdout)
        assert info["messages"] == 30 and info["topics"][0]["type"] == "sensor_msgs/JointState"

    times, states = [t for _, t, _ in logged], [x for _, _, x in logged]  # the simulated plant's states
    with RosBag(tmp_path / "simulation.mcap") as bag:
        for t, x in zip(times, states):
            bag.write_vector("/pendulum/state", route.message, t, x)
    assert list((tmp_path / "simulation.mcap").glob("*.mcap"))
    with AnyReader([tmp_path / "simulation.mcap"]) as reader:
        messages = [(connection.msgtype, timestamp, raw, reader.deserialize(raw, connection.msgtype))
                    for connection, timestamp, raw in reader.messages()]
    assert [m[0] for m in messages] == ["sensor_msgs/msg/JointState"] * 30
    assert [m[1] for m in messages] == [round(t * 1e6) * 1000 for t in times]
    for (_, _, raw, msg), t, x in zip(messages, times, states):
        np.testing.assert_array_equal([msg.position[0], msg.velocity[0]], x)
        assert bytes(raw) == _ros2.build(_ros2.JointState, route.message.encode(t, x)).serialize()


# ----- ROS 1: a real roscore on 127.0.0.1 -------------------------------------------------------

MAPPING = """
[[route]]
direction = "to_ros"
channel = "PendulumState"
topic = "/pendulum/state"
type = "sensor_msgs/JointState"
lcm = "state_of=jaxdrake.models:Pendulum"

[[route]]
direction = "to_lcm"
topic = "/acrobot/joint_states"
channel = "AcrobotState"
type = "sensor_msgs/JointState"
lcm = "state_of=jaxdrake.models:Acrobot"
"""
WRENCH = ("fx", "fy", "fz", "tx", "ty", "tz")
TWIST = ("vx", "vy", "vz", "wx", "wy", "wz")


@pytest.fixture(scope="module")
def ros1(tmp_path_factory):
    """A roscore at a free port on 127.0.0.1, an LCM relay, and one translator process carrying
    five routes (two from a mapping file) and recording a ROS 1 bag."""
    require_ros1()
    folder = tmp_path_factory.mktemp("ros1")
    port = free_port()
    env = ros_env(port, folder)
    (folder / "map.toml").write_text(MAPPING)
    relay = LoopbackRelay().start()
    ros1_core = []
    starting = threading.Thread(target=lambda: ros1_core.append(start_roscore(env, port)))
    starting.start()  # the translator waits for the master (its --master-timeout): both start at once
    process = translator(env, "--url", relay.url, "--map", str(folder / "map.toml"), "--record", str(folder / "out.bag"),
                         "--to-ros", "Wrench", "/wrench", "geometry_msgs/WrenchStamped", "signal=" + ",".join(WRENCH),
                         "--to-lcm", "/pendulum/setpoint", "PendulumSetpoint", "std_msgs/Float64MultiArray", "signal=theta_ref",
                         "--to-lcm", "/cmd_vel", "CmdVel", "geometry_msgs/Twist", "signal=" + ",".join(TWIST))
    starting.join()
    yield {"env": env, "relay": relay, "translator": process, "folder": folder}
    if process.poll() is None:
        process.kill()
        process.communicate()
    relay.close()
    stop_process_group(ros1_core[0])


def collect(url, channels):
    """An LCM client on `url` collecting decoded messages {channel: [(t, x)]}, with its coders."""
    bus, got = lcm.LCM(url), {name: [] for name in channels}
    for name, coder in channels.items():
        bus.subscribe(name, lambda channel, data, coder=coder: got[channel].append(coder.decode(data)))
    return bus, got


def test_rostopic_pub_reaches_an_lcm_subscriber_and_joint_states_map_by_name(ros1):
    acrobot = jd.models.Acrobot()
    bus, got = collect(ros1["relay"].url, {
        "PendulumSetpoint": SignalCoder(Frame("PendulumSetpoint", ("theta_ref",))),
        "CmdVel": SignalCoder(Frame("CmdVel", TWIST)),
        "AcrobotState": SignalCoder(acrobot.state_frame)})
    publishers = [subprocess.Popen(["rostopic", "pub", "-r", "20", topic, kind, data], env=ros1["env"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                  for topic, kind, data in (
                      ("/pendulum/setpoint", "std_msgs/Float64MultiArray", "{data: [3.25]}"),
                      ("/cmd_vel", "geometry_msgs/Twist", "{linear: {x: 0.5}, angular: {z: -1.25}}"),
                      # the acrobot's joints by name, in another order and with a joint it does not have
                      ("/acrobot/joint_states", "sensor_msgs/JointState",
                       "{header: {stamp: {secs: 7, nsecs: 250000000}}, name: [elbow, wrist, shoulder], "
                       "position: [0.2, 9.0, 0.1], velocity: [2.0, 9.0, 1.0]}"))]
    try:
        assert wait_for(lambda: all(got.values()), 60, lambda: bus.handle_timeout(50)), got
    finally:
        for publisher in publishers:
            publisher.terminate()
            publisher.wait()
    np.testing.assert_array_equal(got["PendulumSetpoint"][-1][1], [3.25])
    np.testing.assert_array_equal(got["CmdVel"][-1][1], [0.5, 0, 0, 0, 0, -1.25])
    t, x = got["AcrobotState"][-1]
    assert t == 7.25 and acrobot.state_frame.coordinates == ("shoulder", "elbow", "shoulderdot", "elbowdot")
    np.testing.assert_array_equal(x, [0.1, 0.2, 1.0, 2.0])


def test_an_lcm_publisher_reaches_rostopic_echo_with_its_stamps(ros1):
    pendulum = SignalCoder(jd.models.Pendulum().state_frame)
    wrench = SignalCoder(Frame("Wrench", WRENCH))
    bus, done = lcm.LCM(ros1["relay"].url), threading.Event()

    def publish():  # x a function of the stamp, so any echoed message can be checked
        k = 0
        while not done.is_set():
            t = 1.5 + k * 0.01
            bus.publish("PendulumState", pendulum.encode(t, [t, -t]))
            bus.publish("Wrench", wrench.encode(t, [1, 2, 3, 4, 5, t]))
            k += 1
            time.sleep(0.02)

    thread = threading.Thread(target=publish)
    thread.start()
    try:
        echoes = [subprocess.Popen(["rostopic", "echo", "-n", "1", topic], env=ros1["env"], stdout=subprocess.PIPE,
                                   text=True) for topic in ("/pendulum/state", "/wrench")]
        state, force = (yaml.safe_load(echo.communicate(timeout=60)[0].split("---")[0]) for echo in echoes)
    finally:
        done.set()
        thread.join()
    t = state["header"]["stamp"]["secs"] + state["header"]["stamp"]["nsecs"] / 1e9
    assert state["name"] == ["theta"] and state["effort"] == []
    np.testing.assert_allclose([state["position"][0], state["velocity"][0]], [t, -t], rtol=0, atol=1e-12)
    t = force["header"]["stamp"]["secs"] + force["header"]["stamp"]["nsecs"] / 1e9
    assert force["wrench"]["force"] == {"x": 1.0, "y": 2.0, "z": 3.0}
    assert force["wrench"]["torque"]["x"] == 4.0 and abs(force["wrench"]["torque"]["z"] - t) < 1e-12


BAD_ROS1_NODE = r'''
"""A ROS 1 node that sends what the translator must drop: another type on a route's topic, and
JointStates that are truncated, lack a joint, or carry a NaN; then one good JointState."""
import io, sys, time
import rospy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

class MaybeTruncated(JointState):  # the same type and md5sum; frame_id "cut" sends half the bytes
    def serialize(self, buff):
        whole = io.BytesIO()
        JointState.serialize(self, whole)
        data = whole.getvalue()
        buff.write(data[: len(data) // 2] if self.header.frame_id == "cut" else data)

rospy.init_node("bad_node", anonymous=True)
strings = rospy.Publisher("/pendulum/setpoint", String, queue_size=100)
joints = rospy.Publisher("/acrobot/joint_states", MaybeTruncated, queue_size=100)
deadline = time.time() + 30
while (strings.get_num_connections() < 1 or joints.get_num_connections() < 1) and time.time() < deadline:
    time.sleep(0.05)
def joint_state(frame_id, names, position):
    msg = MaybeTruncated(name=names, position=position, velocity=[0.0] * len(names))
    msg.header.frame_id = frame_id
    return msg
for k in range(5):
    strings.publish(String(data="not a Float64MultiArray"))
    joints.publish(joint_state("cut", ["shoulder", "elbow"], [1.0, 2.0]))
    joints.publish(joint_state("", ["shoulder"], [1.0]))
    joints.publish(joint_state("", ["shoulder", "elbow"], [1.0, float("nan")]))
joints.publish(joint_state("", ["shoulder", "elbow"], [-1.0, -2.0]))
time.sleep(1.0)
print("sent", flush=True)
'''


def test_faults_are_counted_and_dropped_and_sigterm_stops_the_translator(ros1):
    """Last of the module's ROS 1 tests: it stops the shared translator. Wrong-type, truncated,
    joint-lacking and non-finite ROS messages and garbage or foreign LCM messages are counted
    per route and dropped; good messages after them still pass; SIGTERM ends the translator
    with exit code 0, its counters, and a bag of what it carried."""
    from rosbags.highlevel import AnyReader

    acrobot_coder = SignalCoder(jd.models.Acrobot().state_frame)
    bus, got = collect(ros1["relay"].url, {"AcrobotState": acrobot_coder})
    script = ros1["folder"] / "bad_node.py"
    script.write_text(BAD_ROS1_NODE)
    bad = subprocess.run([DEBIAN_PYTHON, str(script)], env=ros1["env"], capture_output=True, text=True, timeout=120)
    assert "sent" in bad.stdout, bad.stderr
    rng = np.random.default_rng(0)
    valid = SignalCoder(jd.models.Pendulum().state_frame).encode(9.0, [1.0, 2.0])
    for k in range(300):  # garbage and truncated copies of a valid message
        bus.publish("PendulumState", rng.bytes(int(rng.integers(0, 80))) if k % 2 else valid[: int(rng.integers(0, len(valid)))])
    foreign = RobotStateCoder(["a", "b", "c"]).encode(1.0, np.zeros(6))  # another LCM type: 6 values too
    for _ in range(7):
        bus.publish("Wrench", foreign)
    bus.publish("PendulumState", valid)
    assert wait_for(lambda: any(np.array_equal(x, [-1, -2, 0, 0]) for _, x in got["AcrobotState"]), 10,
                    lambda: bus.handle_timeout(50))
    time.sleep(0.5)  # the last LCM messages reach the translator
    process = ros1["translator"]
    process.send_signal(signal.SIGTERM)
    out, _ = process.communicate(timeout=60)
    assert process.returncode == 0, out
    counts = route_counts(out)
    acrobot = counts["/acrobot/joint_states -> AcrobotState (sensor_msgs/JointState)"]
    assert acrobot["malformed"] == 15 and acrobot["wrong_type"] == 0, out
    assert counts["/pendulum/setpoint -> PendulumSetpoint (std_msgs/Float64MultiArray)"]["wrong_type"] == 5, out
    pendulum = counts["PendulumState -> /pendulum/state (sensor_msgs/JointState)"]
    assert pendulum["malformed"] == 300 and pendulum["forwarded"] == pendulum["received"] - 300 >= 1, out
    assert counts["Wrench -> /wrench (geometry_msgs/WrenchStamped)"]["malformed"] == 7, out
    with AnyReader([ros1["folder"] / "out.bag"]) as reader:
        recorded = {}
        for connection, _, _ in reader.messages():
            recorded[connection.topic] = recorded.get(connection.topic, 0) + 1
    forwarded = {route.split(" (")[0].split(" -> ")[1 if route.startswith(("Pendulum", "Wrench")) else 0]: c["forwarded"]
                 for route, c in counts.items()}
    assert recorded == {topic: n for topic, n in forwarded.items() if n}, (recorded, forwarded)


def test_no_master_is_a_named_error_with_exit_code_3(tmp_path, monkeypatch, capsys):
    """The command line in this process (no second JAX start): the master's absence is found
    before rospy starts a node."""
    require_ros1()
    from jaxdrake.ros.__main__ import main

    monkeypatch.setattr(sys, "path", list(sys.path))  # rospy's folder is appended for this test only
    ours = logging.getLogger("jaxdrake")  # and the command line's stderr handler set up for it only
    for name in ("handlers", "propagate", "level"):
        monkeypatch.setattr(ours, name, copy.copy(getattr(ours, name)))
    for key, value in ros_env(free_port(), tmp_path).items():  # nothing listens at that port
        monkeypatch.setenv(key, value)
    code = main(["--master-timeout", "0.5", "--url", "memq://", "--to-lcm", "/a", "A", "Twist", "signal=" + ",".join(TWIST)])
    assert code == 3
    assert f"MasterError: no ROS master answers at {os.environ['ROS_MASTER_URI']}" in capsys.readouterr().err


@pytest.mark.slow  # ~30 s with a roscore of its own, killed twice; the named error and exit code 3 for an
# absent master are checked by default (test_no_master_is_a_named_error_with_exit_code_3)
def test_master_killed_and_restarted_then_gone_for_good(tmp_path):
    """The master is killed (SIGKILL) and restarted at the same port: a publisher and a subscriber
    that know only the new master reach the translator's topics. Killed again and not restarted:
    after --master-timeout the translator exits with a MasterError and code 3."""
    require_ros1()
    port = free_port()
    env = ros_env(port, tmp_path)
    core = start_roscore(env, port)
    pendulum = SignalCoder(jd.models.Pendulum().state_frame)
    with LoopbackRelay() as relay:
        process = translator(env, "--url", relay.url, "--master-timeout", "8",
                             "--to-lcm", "/cmd_vel", "CmdVel", "geometry_msgs/Twist", "signal=" + ",".join(TWIST),
                             "--to-ros", "PendulumState", "/pendulum/state", "sensor_msgs/JointState",
                             "state_of=jaxdrake.models:Pendulum")
        stop_process_group(core, signal.SIGKILL)
        time.sleep(2.0)
        core = start_roscore(env, port)
        bus, got = collect(relay.url, {"CmdVel": SignalCoder(Frame("CmdVel", TWIST))})
        publisher = subprocess.Popen(["rostopic", "pub", "-r", "20", "/cmd_vel", "geometry_msgs/Twist",
                                      "{linear: {x: 0.25}}"], env=env, stdout=subprocess.DEVNULL)
        echo = subprocess.Popen(["rostopic", "echo", "-n", "1", "/pendulum/state"], env=env, stdout=subprocess.PIPE,
                                text=True)
        deadline = time.time() + 60
        while (not got["CmdVel"] or echo.poll() is None) and time.time() < deadline:
            bus.publish("PendulumState", pendulum.encode(4.0, [0.5, 0.25]))
            bus.handle_timeout(50)
        publisher.terminate()
        publisher.wait()
        echoed = yaml.safe_load(echo.communicate(timeout=10)[0].split("---")[0])
        stop_process_group(core, signal.SIGKILL)
        out, _ = process.communicate(timeout=60)
    assert got["CmdVel"] and got["CmdVel"][-1][1][0] == 0.25
    assert echoed["position"] == [0.5] and echoed["velocity"] == [0.25]
    assert "registered anew" in out and process.returncode == 3, out
    assert f"MasterError: the ROS master at {env['ROS_MASTER_URI']} has been gone for 8 s" in out
