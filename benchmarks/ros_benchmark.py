"""Latency of the ROS–LCM translator: LCM -> ROS 1 -> LCM at 1 kHz.

Two translator processes (`python -m jaxdrake.ros`) on a roscore at a free port of 127.0.0.1:
the first carries LCM channel BENCH_PING to the ROS topic /jaxdrake_bench
(std_msgs/Float64MultiArray), the second carries that topic back to LCM channel BENCH_PONG. This
process publishes 10^4 pings at 1 kHz (after a warm-up) on a LoopbackRelay (tcpq on 127.0.0.1) and
times each pong's arrival against its ping's departure: two LCM hops, two translations and one
TCPROS hop between processes. Goal: p99 < 2 ms, no message lost.

Run:  python benchmarks/ros_benchmark.py [--messages 10000] [--rate 1000]
"""

import argparse
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from test_ros import free_port, ros_env, start_roscore, stop_process_group, translator  # noqa: E402

from jaxdrake.lcm import LoopbackRelay, SignalCoder  # noqa: E402
from jaxdrake.lcm import open_lcm  # noqa: E402
from jaxdrake.systems import Frame  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=10_000)
    parser.add_argument("--rate", type=float, default=1000.0)
    args = parser.parse_args()
    coder = SignalCoder(Frame("BENCH", ("k",)))
    with tempfile.TemporaryDirectory() as home:
        port = free_port()
        env = ros_env(port, pathlib.Path(home))
        core = start_roscore(env, port)
        relay = LoopbackRelay().start()
        route = ["std_msgs/Float64MultiArray", "signal=k"]
        there = translator(env, "--url", relay.url, "--to-ros", "BENCH_PING", "/jaxdrake_bench", *route)
        back = translator(env, "--url", relay.url, "--to-lcm", "/jaxdrake_bench", "BENCH_PONG", *route)
        bus, arrivals = open_lcm(relay.url), {}  # TCP_NODELAY on this client too
        bus.subscribe("BENCH_PONG", lambda c, d: arrivals.setdefault(int(coder.decode(d)[1][0]), time.perf_counter()))
        try:
            k = -1  # warm-up: negative numbers until pongs come back, then 200 more
            warm_until = None
            while warm_until is None or k > warm_until:
                bus.publish("BENCH_PING", coder.encode(0.0, [k]))
                bus.handle_timeout(5)
                if warm_until is None and arrivals:
                    warm_until = k - 200
                k -= 1
            departures = np.empty(args.messages)
            start = time.perf_counter()
            for k in range(args.messages):
                due = start + k / args.rate
                while (now := time.perf_counter()) < due:
                    bus.handle_timeout(0) or time.sleep(min(due - now, 2e-4))
                departures[k] = time.perf_counter()
                bus.publish("BENCH_PING", coder.encode(0.0, [k]))
            deadline = time.perf_counter() + 2.0
            while time.perf_counter() < deadline:
                bus.handle_timeout(10)
        finally:
            for process in (there, back):
                process.send_signal(signal.SIGINT)
                process.communicate(timeout=60)
            relay.close()
            stop_process_group(core)
    got = np.array([k for k in arrivals if 0 <= k < args.messages], dtype=int)
    latency = (np.array([arrivals[k] for k in got]) - departures[got]) * 1e3
    lost = args.messages - len(got)
    p50, p99 = np.percentile(latency, [50, 99])
    print(f"LCM -> ROS 1 -> LCM, {args.messages} messages at {args.rate:g} Hz: p50 {p50:.3f} ms, p99 {p99:.3f} ms, "
          f"max {latency.max():.3f} ms, lost {lost}  (goal: p99 < 2 ms, 0 lost; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
