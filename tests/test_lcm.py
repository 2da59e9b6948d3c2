"""LCM message types and coders: bindings kept in sync with lcm-gen, every field type round
trips, coders agree with the generated classes (and Drake's) byte for byte, and malformed
bytes are always a MessageError. Only the in-process provider (memq://) is used."""

import importlib.util
import pathlib

import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.lcm import MessageError, RobotCommandCoder, RobotStateCoder, SignalCoder, TypeCoder
from jaxdrake.lcmtypes.drake import lcmt_drake_signal
from jaxdrake.lcmtypes.jaxdrake_msgs import field_types, field_types_inner

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_generated_bindings_are_in_sync_with_the_definitions(tmp_path):
    spec = importlib.util.spec_from_file_location("generate", ROOT / "lcmtypes" / "generate.py")
    generate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generate)
    fresh = generate.generate(tmp_path)
    committed = ROOT / "jaxdrake" / "lcmtypes"
    names = sorted(p.relative_to(fresh) for p in fresh.rglob("*.py"))
    assert names == sorted(p.relative_to(committed) for p in committed.rglob("*.py"))
    for name in names:
        assert (fresh / name).read_text() == (committed / name).read_text(), f"{name} is stale: run lcmtypes/generate.py"


def full_message():
    msg = field_types()
    msg.timestamp, msg.small, msg.medium, msg.count, msg.large = 123456789, -7, -300, 70000, -(2**40)
    msg.single, msg.real, msg.flag, msg.raw, msg.label = 0.5, np.pi, True, 200, "héllo"
    msg.fixed, msg.n, msg.values = [1.0, -2.0, 3.5, 1e-300], 3, [0.1, 0.2, 0.3]
    msg.grid, msg.blob = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], bytes([0, 255, 7])
    msg.inner = field_types_inner()
    msg.inner.id, msg.inner.xyz = 9, [1.0, 2.0, 3.0]
    msg.inners = [field_types_inner() for _ in range(2)]
    for k, inner in enumerate(msg.inners):
        inner.id, inner.xyz = k, [float(k), -1.0, 0.25]
    return msg


def test_every_field_type_round_trips():
    msg = full_message()
    back = field_types.decode(msg.encode())
    for field in ("timestamp", "small", "medium", "count", "large", "real", "flag", "raw", "label", "n"):
        assert getattr(back, field) == getattr(msg, field), field
    assert back.single == np.float32(0.5)
    np.testing.assert_array_equal(back.fixed, msg.fixed)
    np.testing.assert_array_equal(back.values, msg.values)
    np.testing.assert_array_equal(back.grid, msg.grid)
    assert bytes(back.blob) == msg.blob
    assert back.inner.id == 9 and list(back.inner.xyz) == [1.0, 2.0, 3.0]
    assert [i.id for i in back.inners] == [0, 1] and list(back.inners[1].xyz) == [1.0, -1.0, 0.25]
    assert back.encode() == msg.encode()


def test_signal_coder_matches_drake_byte_for_byte():
    drake_signal = pytest.importorskip("drake").lcmt_drake_signal
    assert lcmt_drake_signal._get_packed_fingerprint() == drake_signal._get_packed_fingerprint()
    frame = jd.models.Pendulum().state_frame
    coder = SignalCoder(frame)
    data = coder.encode(2.5, [0.1, -0.2])
    theirs = drake_signal.decode(data)
    assert theirs.dim == 2 and list(theirs.val) == [0.1, -0.2]
    assert tuple(theirs.coord) == frame.coordinates and theirs.timestamp == 2_500_000
    assert theirs.encode() == data
    t, x = coder.decode(theirs.encode())
    assert t == 2.5 and list(x) == [0.1, -0.2]
    wrong = SignalCoder(jd.Frame("Other", ("a", "b")))
    with pytest.raises(MessageError, match="names"):
        wrong.decode(data)
    with pytest.raises(MessageError, match="dimension 2"):
        SignalCoder(jd.Frame("Three", ("a", "b", "c"))).decode(data)


def test_coder_from_type_agrees_with_the_generated_class():
    msg = full_message()
    coder = TypeCoder(field_types, sizes={"n": 3})
    expected = np.array([-7, -300, 70000, -(2**40), 0.5, np.pi, 1, 200, 1.0, -2.0, 3.5, 1e-300, 0.1, 0.2, 0.3,
                         1, 2, 3, 4, 5, 6, 0, 255, 7, 9, 1, 2, 3, 0, 0, -1, 0.25, 1, 1, -1, 0.25], float)
    assert coder.dim == len(expected) and coder.frame.coordinates[15] == "grid[0][0]"
    t, x = coder.decode(msg.encode())
    assert t == pytest.approx(123.456789)
    np.testing.assert_array_equal(x, expected)
    ours = coder.encode(123.456789, expected)
    msg.label = ""  # a coder carries numbers only; strings go out empty
    assert ours == msg.encode()
    with pytest.raises(MessageError, match="n = 3; this coder expects 2"):
        TypeCoder(field_types, sizes={"n": 2}).decode(ours)
    with pytest.raises(ValueError, match="sizes"):
        TypeCoder(field_types)


def test_robot_coders_round_trip_and_check_names():
    state = RobotStateCoder(["shoulder", "elbow"])
    assert state.frame.coordinates == ("shoulder", "elbow", "shoulderdot", "elbowdot")
    t, x = state.decode(state.encode(0.25, [1, 2, 3, 4]))
    assert t == 0.25 and list(x) == [1, 2, 3, 4]
    command = RobotCommandCoder(["elbow"])
    assert list(command.decode(command.encode(1.0, [0.5]))[1]) == [0.5]
    with pytest.raises(MessageError, match="joints"):
        RobotCommandCoder(["wrist"]).decode(command.encode(1.0, [0.5]))
    with pytest.raises(ValueError, match="4 entries"):
        state.encode(0.0, [1, 2, 3])


def test_malformed_and_truncated_messages_are_message_errors():
    """10^4 random byte strings and every truncation of valid messages: each is a
    MessageError, never another exception, never a value."""
    rng = np.random.default_rng(0)
    coders = [SignalCoder(jd.Frame("S", ("a", "b"))), RobotStateCoder(["j"]), TypeCoder(field_types, sizes={"n": 3})]
    valid = [coders[0].encode(1.0, [1, 2]), coders[1].encode(1.0, [1, 2]), full_message().encode()]
    rejected = 0
    for k in range(10_000):
        coder = coders[k % 3]
        size = int(rng.integers(0, 200))
        data = rng.bytes(size) if k % 2 else coder.message_type._get_packed_fingerprint() + rng.bytes(size)
        try:
            coder.decode(data)
        except MessageError:
            rejected += 1
    assert rejected >= 9_990  # a random tail can happen to parse; it must then be finite and sized
    for coder, data in zip(coders, valid):
        for cut in range(len(data)):
            with pytest.raises(MessageError):
                coder.decode(data[:cut])
    with pytest.raises(MessageError, match="non-finite"):
        coders[0].decode(lcmt_drake_signal_with([np.nan, 1.0]))


def lcmt_drake_signal_with(values):
    msg = lcmt_drake_signal()
    msg.dim, msg.val, msg.coord, msg.timestamp = len(values), list(values), ["a", "b"], 0
    return msg.encode()


def test_frames_carry_coders_and_messages_travel_in_process():
    import lcm

    frame = jd.models.Pendulum().state_frame
    carried = frame.with_coder(SignalCoder(frame))
    assert carried == frame and carried.coder.dim == 2
    with pytest.raises(ValueError, match="cannot carry"):
        frame.with_coder(RobotStateCoder(["a", "b"]))
    node = lcm.LCM("memq://")
    received = []
    node.subscribe("PENDULUM_STATE", lambda channel, data: received.append(carried.coder.decode(data)))
    node.publish("PENDULUM_STATE", carried.coder.encode(0.5, [1.0, 2.0]))
    node.handle_timeout(100)
    assert received and received[0][0] == 0.5 and list(received[0][1]) == [1.0, 2.0]
