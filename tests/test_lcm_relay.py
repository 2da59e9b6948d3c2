"""The LoopbackRelay treats every client as untrusted: patterns match in linear time outside the
hub's lock, a client that stops reading loses only its own oldest messages (counted), a refused
request is answered to that client without a traceback, the hub listens on 127.0.0.1 and shuts
down cleanly. Raw sockets speak the tcpq protocol; only 127.0.0.1 is used."""

import logging
import os
import random
import re
import socket
import struct
import threading
import time

import lcm
import pytest

from jaxdrake.lcm import LoopbackRelay
from jaxdrake.lcm import open_lcm
from jaxdrake.lcm._channels import ChannelPattern, PatternError
from jaxdrake.lcm._relay import (MAGIC_CLIENT, MAGIC_SERVER, MAX_SUBSCRIPTIONS, PUBLISH, RELAY_ERROR_CHANNEL, SUBSCRIBE,
                                 UNSUBSCRIBE, VERSION)


def recv_exactly(sock, size):
    data = bytearray()
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        assert chunk, "the relay closed the connection"
        data.extend(chunk)
    return bytes(data)


def connect(relay, rcvbuf=None):
    """A raw tcpq client, handshake done."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(5)
    sock.connect(relay.address)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.sendall(struct.pack(">II", MAGIC_CLIENT, VERSION))
    assert struct.unpack(">II", recv_exactly(sock, 8))[0] == MAGIC_SERVER
    return sock


def send(sock, kind, channel, data=b""):
    encoded = channel.encode()
    frame = struct.pack(">II", kind, len(encoded)) + encoded
    sock.sendall(frame + struct.pack(">I", len(data)) + data if kind == PUBLISH else frame)


def receive(sock):
    """The next (channel, data) the relay sends."""
    _, size = struct.unpack(">II", recv_exactly(sock, 8))
    channel = recv_exactly(sock, size).decode()
    return channel, recv_exactly(sock, struct.unpack(">I", recv_exactly(sock, 4))[0])


def subscribed(sock, pattern, channel):
    """Subscribe `sock` to `pattern` and publish `channel` from it: the relay handles one
    connection's frames in order, so once `channel` comes back the subscription is in place."""
    send(sock, SUBSCRIBE, pattern)
    send(sock, PUBLISH, channel, b"sync")
    assert receive(sock) == (channel, b"sync")


def relay_threads(relay):
    return [t for t in threading.enumerate() if t.name.startswith(f"LoopbackRelay-{relay.port}-")]


# ----- the hub -------------------------------------------------------------------------------


def test_catastrophic_pattern_and_stalled_reader_leave_others_delivered_within_100ms():
    """`(a+)+b` against a 28-character channel (2^28 steps for a backtracking matcher) and a
    subscriber to everything that never reads, under a flood of 2000 messages of 64 KiB:
    every ping between two other clients still arrives within 100 ms."""
    channel, payload = "a" * 28, bytes(64 << 10)
    with LoopbackRelay() as relay:
        catastrophic = connect(relay)
        subscribed(catastrophic, "(a+)+b", "aab")
        stalled = connect(relay, rcvbuf=4096)
        subscribed(stalled, ".*", "READY")  # the last read of this socket
        listener, pinger = connect(relay), connect(relay)
        subscribed(listener, "PING", "PING")

        def flood():
            flooder = connect(relay)
            for _ in range(2000):
                send(flooder, PUBLISH, channel, payload)
            flooder.close()

        flooding = threading.Thread(target=flood)
        flooding.start()
        latencies = []
        while flooding.is_alive() or len(latencies) < 20:
            start = time.perf_counter()
            send(pinger, PUBLISH, "PING", b"%d" % len(latencies))
            assert receive(listener) == ("PING", b"%d" % len(latencies))
            latencies.append(time.perf_counter() - start)
            time.sleep(0.005)
        flooding.join()
        assert max(latencies) < 0.1, f"slowest of {len(latencies)} pings: {max(latencies) * 1e3:.0f} ms"
        assert relay.dropped > 0  # the stalled client's own oldest messages, counted
        catastrophic.settimeout(0.2)
        with pytest.raises(socket.timeout):
            catastrophic.recv(1)  # the pattern never matched, and nothing blocked on it
        send(pinger, PUBLISH, "aaab", b"match")
        assert receive(catastrophic) == ("aaab", b"match")
    assert not relay_threads(relay)


def test_a_slow_reader_drops_its_own_oldest_messages_and_they_are_counted():
    count = 400
    with LoopbackRelay(queue_bytes=256 << 10) as relay:
        slow = connect(relay, rcvbuf=4096)
        subscribed(slow, "DATA|SYNC", "SYNC")
        witness = connect(relay)
        subscribed(witness, "SYNC|WITNESS", "WITNESS")
        publisher = connect(relay)
        for k in range(count):
            send(publisher, PUBLISH, "DATA", struct.pack(">I", k) + bytes(64 << 10))
        send(publisher, PUBLISH, "SYNC", b"end")
        assert receive(witness) == ("SYNC", b"end")  # the relay has queued all of them by now
        received = []
        while True:
            channel, data = receive(slow)
            if channel == "SYNC":
                break
            received.append(struct.unpack(">I", data[:4])[0])
        assert received == sorted(received) and received[-1] == count - 1  # the newest survive
        assert relay.dropped > 0 and len(received) + relay.dropped == count


def test_an_invalid_pattern_is_answered_to_that_client_without_a_traceback(capfd):
    with LoopbackRelay() as relay:
        client = connect(relay)
        for pattern, reason in [("(", "missing ')'"), ("a\\1", "backreferences"), ("(?=x)a", "lookaround"),
                                ("x" * 300, "longer than 255")]:
            send(client, SUBSCRIBE, pattern)
            channel, data = receive(client)
            assert channel == RELAY_ERROR_CHANNEL and reason in data.decode(), data
        send(client, PUBLISH, RELAY_ERROR_CHANNEL, b"spoof")
        assert "only the relay" in receive(client)[1].decode()
        send(client, PUBLISH, "c" * 256, b"")
        assert "longer than 255" in receive(client)[1].decode()
        subscribed(client, "STILL_HERE", "STILL_HERE")  # the connection lives on
        for _ in range(MAX_SUBSCRIPTIONS):  # one more than the limit, with STILL_HERE
            send(client, SUBSCRIBE, "MANY")
        assert f"more than {MAX_SUBSCRIPTIONS} subscriptions" in receive(client)[1].decode()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception in thread" not in err


def test_the_jaxdrake_client_logs_what_the_relay_refuses(caplog):
    with LoopbackRelay() as relay:
        node = open_lcm(relay.url)
        with caplog.at_level(logging.ERROR, logger="jaxdrake.lcm"):
            node.publish(RELAY_ERROR_CHANNEL, b"spoof")
            deadline = time.time() + 3
            while "refused" not in caplog.text and time.time() < deadline:
                node.handle_timeout(50)
        del node
    assert f"only the relay publishes on {RELAY_ERROR_CHANNEL}" in caplog.text


def test_one_unsubscribe_ends_one_subscription():
    """LCM's client sends one SUBSCRIBE per handler, and one UNSUBSCRIBE when one goes."""
    with LoopbackRelay() as relay:
        client, publisher = connect(relay), connect(relay)
        send(client, SUBSCRIBE, "A")
        subscribed(client, "A", "A")  # two subscriptions, one frame per message
        send(client, UNSUBSCRIBE, "A")
        subscribed(client, "B", "B")  # the UNSUBSCRIBE has been handled by now
        send(publisher, PUBLISH, "A", b"still")
        assert receive(client) == ("A", b"still")
        send(client, UNSUBSCRIBE, "A")
        subscribed(client, "C", "C")
        send(publisher, PUBLISH, "A", b"gone")
        send(publisher, PUBLISH, "B", b"next")
        assert receive(client) == ("B", b"next")


def listening_addresses(inodes):
    """Local addresses of the listening TCP sockets among `inodes` (Linux's /proc/net/tcp)."""
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for row in f.read().splitlines()[1:]:
                fields = row.split()
                if fields[3] == "0A" and int(fields[9]) in inodes:  # 0A: LISTEN
                    address, port = fields[1].split(":")
                    host = socket.inet_ntop(socket.AF_INET if len(address) == 8 else socket.AF_INET6,
                                            bytes.fromhex(address)[::-1] if len(address) == 8
                                            else b"".join(bytes.fromhex(address[i:i + 8])[::-1]
                                                          for i in range(0, 32, 8)))
                    found.append((host, int(port, 16)))
    return found


def socket_inodes():
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(int(target[8:-1]))
    return inodes


@pytest.mark.skipif(not os.path.exists("/proc/net/tcp"), reason="reads Linux's socket tables")
def test_every_server_the_lcm_package_starts_listens_on_127_0_0_1_only():
    before = socket_inodes()
    with LoopbackRelay() as relay:
        node = open_lcm(relay.url)  # a client: it must add no listening socket
        assert relay.address[0] == "127.0.0.1" and relay.url == f"tcpq://127.0.0.1:{relay.port}"
        assert listening_addresses(socket_inodes() - before) == [("127.0.0.1", relay.port)]
        del node
    with LoopbackRelay(host="127.0.0.2") as other:  # another address only when named
        assert other.address[0] == "127.0.0.2"
        send(connect(other), SUBSCRIBE, "X")


def test_close_stops_every_thread_even_with_a_blocked_writer_and_a_silent_peer():
    relay = LoopbackRelay(queue_bytes=1 << 20).start()
    stalled = connect(relay, rcvbuf=4096)
    subscribed(stalled, ".*", "READY")
    silent = socket.create_connection(relay.address)  # connects, never sends its handshake
    publisher = connect(relay)
    for _ in range(200):
        send(publisher, PUBLISH, "BIG", bytes(64 << 10))
    time.sleep(0.2)
    assert relay_threads(relay)
    start = time.perf_counter()
    relay.close()
    assert time.perf_counter() - start < 1.0
    assert not relay_threads(relay)
    with pytest.raises(OSError):
        socket.create_connection(relay.address, timeout=1)
    for sock in (stalled, silent, publisher):
        sock.close()


def test_the_relay_speaks_with_lcm_s_own_client():
    with LoopbackRelay() as relay:
        a, b = lcm.LCM(relay.url), lcm.LCM(relay.url)
        got = []
        b.subscribe("ROBOT_.*", lambda channel, data: got.append((channel, data)))
        time.sleep(0.1)
        deadline = time.time() + 3
        while not got and time.time() < deadline:
            a.publish("ROBOT_STATE", b"x")
            b.handle_timeout(50)
        assert got[0] == ("ROBOT_STATE", b"x")
        del a, b


# ----- the pattern language ------------------------------------------------------------------


def random_pattern(rng, depth=0):
    atoms = ["a", "b", ".", "[ab]", "[^a]", "\\.", "(a|b)", "(?:ab|)", "\\d", "[a-c]", "x", "^", "$", "[\\w.]"]
    parts = []
    for _ in range(rng.randint(1, 4)):
        atom = "(" + random_pattern(rng, depth + 1) + ")" if depth < 2 and rng.random() < 0.3 else rng.choice(atoms)
        parts.append(atom + ("" if atom in "^$" else rng.choice(["", "", "*", "+", "?", "{2}", "{1,3}", "{0,}"])))
    alternative = "|" + random_pattern(rng, depth + 1) if rng.random() < 0.2 else ""
    return "".join(parts) + alternative


def test_patterns_match_the_same_names_as_python_re():
    rng = random.Random(0)
    checked = 0
    for _ in range(400):
        text = random_pattern(rng)
        expected, pattern = re.compile(text), ChannelPattern(text)
        for _ in range(10):
            name = "".join(rng.choice("ab.x1_c") for _ in range(rng.randint(0, 7)))
            assert pattern.fullmatch(name) == bool(expected.fullmatch(name)), (text, name)
            checked += 1
    assert checked == 4000
    assert ChannelPattern("[[:upper:]]+_\\d{2}").fullmatch("ROBOT_01")
    assert not ChannelPattern("A|B").fullmatch("AB")  # the whole name, as LCM anchors it


@pytest.mark.parametrize("text", ["(a+)+b", "(a|a)*c", "(a*)*(b*)*c", "(.*){200}x"])
def test_matching_is_linear_whatever_the_pattern(text):
    pattern = ChannelPattern(text)
    start = time.perf_counter()
    assert not pattern.fullmatch("a" * 255)
    assert time.perf_counter() - start < 0.5  # a backtracking matcher: 2^255 steps


@pytest.mark.parametrize("text, reason", [
    ("(", "missing ')'"), (")", "unbalanced ')'"), ("a\\1", "backreferences"), ("(?=x)a", "lookaround"),
    ("(?i)a", "lookaround and other"), ("*a", "nothing to repeat"), ("a{3,2}", "repeat bounds"),
    ("a{256}", "repeat bounds"), ("[b-a]", "bad range"), ("[a", "missing ']'"), ("\\", "trailing"),
    ("\\q", "escape \\q"), ("[[:foo:]]", "unknown character class"), ("x" * 256, "longer than 255"),
    ("((a{200}){200})", "more than 1000"), ("((){255}){255}", "more than 1000"),
])
def test_patterns_outside_the_language_are_refused_with_the_reason(text, reason):
    with pytest.raises(PatternError, match=re.escape(reason)):
        ChannelPattern(text)


def test_every_thread_is_tracked_even_when_spawns_race(monkeypatch):
    """A reader spawning its writer while the accept thread spawns the next reader: with a slow
    `Thread.start` the window is wide, and close() must still know (and wait for) every thread."""
    start = threading.Thread.start

    def slow_start(thread):
        time.sleep(0.02)
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", slow_start)
    relay = LoopbackRelay().start()
    clients = [connect(relay) for _ in range(6)]
    time.sleep(0.1)
    assert set(relay_threads(relay)) <= set(relay._threads)
    relay.close()
    assert not relay_threads(relay)
    for sock in clients:
        sock.close()
