"""The LCM bridge in a 1 kHz loop: a jit-compiled LQR controller (pendulum) runs as a node in
its own process (`python -m jaxdrake.lcm`); this process publishes a state message every
millisecond through a loopback tcpq relay and waits for each command. Reports the latency
from input message to output message inside the node (arrival -> publish) and the round trip
seen by the driver (publish -> reply), p50 / p99 / max, and the rate achieved.

Run:  python benchmarks/lcm_benchmark.py [--messages N]
"""

import argparse
import os
import signal
import subprocess
import sys
import time

import lcm
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "examples"))
import _lcm_nodes  # noqa: E402
from _common import machine_line  # noqa: E402

from jaxdrake.lcm import LoopbackRelay, SignalCoder  # noqa: E402
from jaxdrake.lcm._bridge import _no_delay  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=5000)
    args = parser.parse_args()
    print(machine_line())
    plant = _lcm_nodes.plant()
    state_coder = SignalCoder(plant.output_frame)
    with LoopbackRelay() as relay:
        node = subprocess.Popen([sys.executable, "-m", "jaxdrake.lcm", os.path.join(ROOT, "examples", "_lcm_nodes.py")
                                 + ":controller", "--url", relay.url, "--x64"], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        line = ""
        while not line.startswith("node "):
            line = node.stdout.readline()
        time.sleep(0.5)
        bus = lcm.LCM(relay.url)
        _no_delay(bus)
        replies = []
        bus.subscribe("PendulumInput", lambda channel, data: replies.append(time.perf_counter()))
        time.sleep(0.2)
        round_trips, start, missed = [], time.perf_counter(), 0
        for k in range(args.messages):
            due = start + k * 1e-3
            while time.perf_counter() < due:
                pass
            sent = time.perf_counter()
            count = len(replies)
            bus.publish("PendulumState", state_coder.encode(k * 1e-3, [np.pi - 0.1, 0.0]))
            while len(replies) == count and time.perf_counter() - sent < 0.1:
                bus.handle_timeout(1)
            if len(replies) > count:
                round_trips.append(replies[-1] - sent)
            else:
                missed += 1
        elapsed = time.perf_counter() - start
        node.send_signal(signal.SIGINT)
        out, _ = node.communicate(timeout=60)
        del bus
    rt = np.asarray(round_trips) * 1e6
    print(f"{args.messages} messages at 1 kHz in {elapsed:.2f} s ({args.messages / elapsed:.0f} Hz achieved), "
          f"{missed} unanswered")
    print(f"round trip (driver): p50 {np.percentile(rt, 50):.0f} us, p99 {np.percentile(rt, 99):.0f} us, "
          f"max {rt.max():.0f} us")
    print("node: " + out.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
