"""The LCM bridge: two OS processes close a plant / controller loop over loopback TCP, fuzzed
messages never stop a node, a stale input triggers the safe behaviour and recovery, SIGINT
stops a node cleanly. Only 127.0.0.1 (a LoopbackRelay) and log files are used."""

import logging
import os
import signal
import subprocess
import sys
import threading
import time

import jax
import jax.numpy as jnp
import lcm
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.lcm import LcmNode, LoopbackRelay, SignalCoder

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NODES = os.path.join(ROOT, "examples", "_lcm_nodes.py")
sys.path.insert(0, os.path.join(ROOT, "examples"))
import _lcm_nodes  # noqa: E402

X0 = [np.pi - 0.3, 0.0]


def node_process(name, url, *extra):
    return subprocess.Popen([sys.executable, "-m", "jaxdrake.lcm", f"{NODES}:{name}", "--url", url, "--x64", *extra],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_until_running(process, timeout=120):
    """Read the node's output until its start line (printed once compiled and subscribed)."""
    deadline, line = time.time() + timeout, ""
    while not line.startswith("node ") and time.time() < deadline:
        line = process.stdout.readline()
    time.sleep(0.5)  # past the node's settling time


def read_log(path):
    events = {}
    for event in lcm.EventLog(str(path), "r"):
        events.setdefault(event.channel, []).append(event.data)
    return events


def test_two_processes_close_the_loop_without_losing_a_message(tmp_path):
    ticks, rate = 2_000, 100.0  # 20 s of the loop in lockstep: every message of each, none lost
    with LoopbackRelay() as relay:
        controller = node_process("controller", relay.url, "--log", str(tmp_path / "controller.log"))
        wait_until_running(controller)
        plant = node_process("plant", relay.url, "--rate", str(rate), "--lockstep", "--max-ticks", str(ticks),
                             "--input-timeout", "30", "--x0", *map(str, X0), "--log", str(tmp_path / "plant.log"))
        plant_out, _ = plant.communicate(timeout=600)
        controller.send_signal(signal.SIGINT)
        controller_out, _ = controller.communicate(timeout=60)
    assert plant.returncode == 0, plant_out
    assert controller.returncode == 0 and "stopped:" in controller_out, controller_out
    assert f"{ticks} ticks" in plant_out and "0 malformed, 0 stale" in plant_out, plant_out

    plant_log, controller_log = read_log(tmp_path / "plant.log"), read_log(tmp_path / "controller.log")
    assert len(plant_log["PendulumState"]) == ticks and plant_log["PendulumState"] == controller_log["PendulumState"]
    assert len(plant_log["PendulumInput"]) == ticks and plant_log["PendulumInput"] == controller_log["PendulumInput"]

    pendulum, lqr = _lcm_nodes.plant(), _lcm_nodes.controller()
    state_coder, input_coder = SignalCoder(pendulum.output_frame), SignalCoder(pendulum.input_frame)
    times, states = zip(*(state_coder.decode(d) for d in plant_log["PendulumState"]))
    inputs = np.array([input_coder.decode(d)[1] for d in plant_log["PendulumInput"]])
    np.testing.assert_allclose(np.diff(times), 1 / rate, atol=1e-6)

    # the same sampled loop in one process: u_k = k(x_k), x_{k+1} = RK4 over the tick, u held
    def sampled_loop(dt, steps):
        @jax.jit
        def run(x0):
            def step(x, k):
                u = lqr.output(k * dt, jnp.zeros(0), x)
                x_next = jd.simulate(pendulum, (k * dt, k * dt + dt), x, inputs=lambda s: u, solver="rk4",
                                     dt=dt / 10, dense=False).final_state
                return x_next, (x, u)
            return jax.lax.scan(step, x0, jnp.arange(steps))[1]
        return run(jnp.asarray(X0))

    xs, us = sampled_loop(1 / rate, 200)
    np.testing.assert_allclose(np.array(states[:200]), xs, atol=1e-9)
    np.testing.assert_allclose(inputs[:200], us, atol=1e-9)
    # and the continuous closed loop, to the sample-and-hold's first-order error: halving the
    # tick halves the gap
    continuous = jd.simulate(jd.feedback(pendulum, lqr), (0.0, 2.0), jnp.asarray(X0), rtol=1e-10, atol=1e-12)
    gap = np.max(np.abs(np.asarray(continuous.state(jnp.asarray(times[:200]))) - np.array(states[:200])))
    finer, _ = sampled_loop(0.5 / rate, 400)
    finer_gap = np.max(np.abs(np.asarray(continuous.state(jnp.arange(400) * 0.5 / rate)) - np.asarray(finer)))
    assert 1.6 < gap / finer_gap < 2.4, (gap, finer_gap)
    assert np.abs(states[-1] - np.array([np.pi, 0.0])).max() < 1e-6


def test_fuzzed_messages_never_stop_a_node(tmp_path):
    rng = np.random.default_rng(1)
    pendulum = _lcm_nodes.plant()
    bus = lcm.LCM("memq://")
    node = LcmNode(_lcm_nodes.controller(), bus)
    replies = []
    bus.subscribe("PendulumInput", lambda channel, data: replies.append(data))
    state_coder = SignalCoder(pendulum.output_frame)
    valid = state_coder.encode(0.0, X0)
    for k in range(10_000):
        data = rng.bytes(int(rng.integers(0, 120))) if k % 2 else valid[: int(rng.integers(0, len(valid)))]
        bus.publish("PendulumState", data)
        node.handle()
    assert node.stats.malformed == 10_000 and node.stats.received == 0 and not replies
    bus.publish("PendulumState", valid)
    node.handle()
    node.handle()  # memq delivers the node's reply on the next dispatch
    assert node.stats.received == 1 and len(replies) == 1
    u = SignalCoder(pendulum.input_frame).decode(replies[0])[1]
    np.testing.assert_allclose(u, _lcm_nodes.controller().output(0.0, jnp.zeros(0), jnp.asarray(X0)), atol=1e-12)


def test_stale_input_applies_the_safe_input_and_recovers(caplog):
    with LoopbackRelay() as relay:
        node = LcmNode(_lcm_nodes.plant(), relay.url, rate=200.0, input_timeout=0.1, safe_input=[0.0],
                       x0=[0.0, 0.0])
        publisher = lcm.LCM(relay.url)
        coder = SignalCoder(node.system.input_frame)

        def publish_with_a_gap():
            for phase_end, active in ((0.4, True), (0.9, False), (1.4, True)):
                while time.perf_counter() - start < phase_end:
                    if active:
                        publisher.publish("PendulumInput", coder.encode(0.0, [1.0]))
                    time.sleep(0.01)

        start = time.perf_counter()
        thread = threading.Thread(target=publish_with_a_gap)
        with caplog.at_level(logging.WARNING, logger="jaxdrake.lcm"):
            thread.start()
            stats = node.run(duration=1.6)
            thread.join()
    assert stats.stale_events >= 1 and stats.received > 50
    messages = [r.getMessage() for r in caplog.records]
    assert any("applying the safe input" in m for m in messages), messages
    assert any("resumed" in m for m in messages), messages


def test_sigint_stops_a_node_cleanly(tmp_path):
    with LoopbackRelay() as relay:
        node = node_process("plant", relay.url, "--rate", "100", "--log", str(tmp_path / "plant.log"))
        wait_until_running(node)
        node.send_signal(signal.SIGINT)
        out, _ = node.communicate(timeout=60)
    assert node.returncode == 0 and "stopped:" in out, out
    events = read_log(tmp_path / "plant.log")
    assert len(events["PendulumState"]) > 10  # the log was closed properly and replays


def test_sigint_stops_a_lockstep_node_while_it_waits_for_its_input():
    """No controller answers: the node waits up to its 30-s input timeout each tick, and a
    signal still ends it at once (its handler runs between slices of the wait)."""
    with LoopbackRelay() as relay:
        node = node_process("plant", relay.url, "--rate", "100", "--lockstep", "--input-timeout", "30")
        wait_until_running(node)
        start = time.perf_counter()
        node.send_signal(signal.SIGINT)
        out, _ = node.communicate(timeout=60)
        waited = time.perf_counter() - start
    assert node.returncode == 0 and "stopped: 1 ticks" in out, out
    assert waited < 5.0, waited  # 29 s before: the wait for the input was one uninterrupted call


def test_node_refuses_a_missing_url():
    with pytest.raises(ValueError, match="an LCM URL looks like"):
        LcmNode(_lcm_nodes.plant(), "")


def test_discrete_system_node_updates_at_its_period():
    """x+ = 0.5 x + u at 100 Hz with no input arriving (the last input, zero, is held): the
    published outputs are x0 0.5^k at t = k / 100."""
    system = jd.System.from_functions(update=lambda t, x, u: 0.5 * x + u, num_states=1, num_inputs=1,
                                      sample_time=0.01)
    bus = lcm.LCM("memq://")
    node = LcmNode(system, bus, x0=[8.0], input_timeout=10.0)
    outputs = []
    bus.subscribe(system.output_frame.name, lambda channel, data: outputs.append(SignalCoder(system.output_frame).decode(data)))
    node.run(max_ticks=6)
    bus.handle_timeout(10)
    while bus.handle_timeout(0):
        pass
    times, values = zip(*outputs)
    np.testing.assert_allclose(times, 0.01 * np.arange(len(times)), atol=1e-12)
    np.testing.assert_allclose(np.ravel(values), 8.0 * 0.5 ** np.arange(len(values)))
    assert len(values) >= 5


def test_killed_and_restarted_controller_process(caplog):
    """The plant node (here) loses its controller process (SIGKILL): it reports the stale
    input, applies the safe input, and resumes when a new controller process answers."""
    with LoopbackRelay() as relay:
        node = LcmNode(_lcm_nodes.plant(), relay.url, rate=100.0, input_timeout=0.3, safe_input=[0.0],
                       x0=X0)
        events = []

        def controller_life():
            for life in range(2):
                process = node_process("controller", relay.url)
                wait_until_running(process)
                time.sleep(1.0)
                events.append(node.stats.received)
                process.kill()
                process.wait()
                time.sleep(1.0)
            node.stop()

        thread = threading.Thread(target=controller_life)
        with caplog.at_level(logging.WARNING, logger="jaxdrake.lcm"):
            thread.start()
            stats = node.run(duration=120)
            thread.join()
    messages = [r.getMessage() for r in caplog.records]
    assert sum("applying the safe input" in m for m in messages) >= 2, messages
    assert sum("resumed" in m for m in messages) == 2, messages
    assert events[0] > 20 and events[1] > events[0] + 20  # answered in both lives
    assert stats.malformed == 0


def test_state_viewer_draws_the_newest_state_at_its_rate():
    """A publisher sends pendulum states at ~1 kHz; the viewer (its matplotlib display) draws at
    most 20 per second, each the newest state, never a backlog, the bob where the state puts it."""
    import matplotlib

    matplotlib.use("Agg")
    pendulum = jd.models.Pendulum(l=0.7)
    visualizer = jd.viz.visualizer_for(pendulum)
    bus = lcm.LCM("memq://")
    window, drawn = visualizer.live(), []
    window(np.zeros(2), 0.0)  # the first draw builds the figure: not part of the rate under test

    def show(x, t):
        drawn.append((t, np.asarray(x), time.perf_counter()))
        window(x, t)

    viewer = jd.lcm.LcmViewer(visualizer, bus, max_rate=20.0, show=show)
    coder = SignalCoder(pendulum.state_frame)

    start = time.perf_counter()

    sent = []

    def publish():
        for k in range(600):
            bus.publish("PendulumState", coder.encode(k / 1000, np.array([k / 100, 0.0])))
            sent.append((k / 1000, time.perf_counter()))
            time.sleep(max(0.0, start + (k + 1) / 1000 - time.perf_counter()))

    publisher = threading.Thread(target=publish)
    publisher.start()
    # the viewer runs 0.9 s past the publisher, so a draw after the last message happens even on a
    # loaded machine where one matplotlib draw takes a few hundred milliseconds
    stats = viewer.run(duration=1.5)
    publisher.join()
    times, walls = (np.array([d[i] for d in drawn]) for i in (0, 2))
    assert stats.received == 600 and 3 <= stats.drawn <= 1.5 * 20 + 1 and stats.drawn == len(drawn)
    # at most 20 draws per second: the viewer spaces its draws' starts by 1/20 s by its own clock;
    # `show` stamps them a few microseconds later, by an amount that varies from draw to draw
    assert np.all(np.diff(walls) >= 0.05 - 1e-3)
    stamps, published = np.array(sent).T
    for t, wall in zip(times, walls):  # each draw shows the newest state published 10 ms before it, not a backlog
        assert t >= stamps[published < wall - 0.01].max(initial=0.0)
    assert times[-1] == stamps[-1]  # the display caught up with the last state
    t, x, _ = drawn[-1]
    np.testing.assert_allclose(x, [t * 10, 0.0])
    bob = next(a for a in window.figure.axes[0].get_children() if a.get_gid() == "bob")
    np.testing.assert_allclose(np.stack(bob.get_data(), 1)[0], 0.7 * np.array([np.sin(x[0]), -np.cos(x[0])]), atol=1e-12)
