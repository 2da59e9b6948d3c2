"""Run a system as an LCM node from the command line (a bridge process).

    python -m jaxdrake.lcm SYSTEM [--url URL] [--rate HZ] [--input-channel C] [--output-channel C]
        [--duration S | --max-ticks N] [--lockstep] [--input-timeout S] [--safe-input U ...]
        [--log FILE]
    python -m jaxdrake.lcm SYSTEM --view [--plane xz] [--max-rate HZ] [--input-channel C] [--url URL]

With `--view`, the node is SYSTEM's state viewer instead: it draws the states received on
SYSTEM's state channel (or `--input-channel`) with `jaxdrake.viz.visualizer_for(SYSTEM)` at
up to `--max-rate` (30) Hz: a matplotlib window, or a MeshCat scene for a URDF robot.

SYSTEM names a `jaxdrake.System`, or a function returning one, as `module:name` (e.g.
`jaxdrake.models:Pendulum`) or `path/to/file.py:name`. The default URL is LCM's multicast group
with ttl=0 (host only); `tcpq://127.0.0.1:PORT` with `jaxdrake.lcm.LoopbackRelay` needs no
multicast at all.
SIGINT / SIGTERM stop the node cleanly; it then prints its counters and latencies.
"""

import argparse
import logging

import numpy as np


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m jaxdrake.lcm", description=__doc__.splitlines()[0])
    parser.add_argument("system", help="the system: module:name or file.py:name (a System or a function returning one)")
    parser.add_argument("--url", default=None, help="LCM URL (default: the multicast group with ttl=0, host only)")
    parser.add_argument("--rate", type=float, help="ticks per second (default: a discrete system's sample rate, 100 for a continuous one; a stateless one answers each input)")
    parser.add_argument("--input-channel", help="channel of the input messages (default: the input frame's name)")
    parser.add_argument("--output-channel", help="channel of the output messages (default: the output frame's name)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--max-ticks", type=int, help="stop after this many ticks")
    parser.add_argument("--lockstep", action="store_true", help="tick k waits for the input stamped with tick k's time (no message lost, reproducible)")
    parser.add_argument("--input-timeout", type=float, default=0.5, help="seconds without input before the safe input is used (0.5)")
    parser.add_argument("--safe-input", type=float, nargs="+", help="the input applied while inputs are stale (default: hold the last one)")
    parser.add_argument("--x0", type=float, nargs="+", help="initial state (default the system's)")
    parser.add_argument("--log", help="write every message the node sends and receives to this LCM log file")
    parser.add_argument("--x64", action="store_true", help="run the system in float64")
    parser.add_argument("--view", action="store_true", help="draw SYSTEM's received states instead")
    parser.add_argument("--plane", help="with --view: project a URDF robot onto this plane (xz, yz, xy)")
    parser.add_argument("--max-rate", type=float, default=30.0, help="with --view: draws per second at most")
    args = parser.parse_args(argv)
    # the node's own messages at INFO; JAX's (e.g. its probe for a TPU backend) only if they warn
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("jaxdrake").setLevel(logging.INFO)
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from . import HOST_ONLY_URL, LcmNode, load_system

    args.url = args.url or HOST_ONLY_URL
    try:
        system = load_system(args.system)
    except ValueError as error:
        parser.error(str(error))
    if args.view:
        return view(system, args)
    node = LcmNode(system, args.url, rate=args.rate, input_channel=args.input_channel,
                   output_channel=args.output_channel, lockstep=args.lockstep, input_timeout=args.input_timeout,
                   safe_input=args.safe_input, log_path=args.log, x0=args.x0)
    print(f"node {node.system.name} on {args.url}: in {node.input_channel if node.input_coder else '-'}, "
          f"out {node.output_channel}, rate {node.rate or 'on input'}", flush=True)
    stats = node.run(duration=args.duration, max_ticks=args.max_ticks)
    line = (f"stopped: {stats.ticks} ticks, {stats.received} received, {stats.published} published, "
            f"{stats.malformed} malformed, {stats.stale_events} stale")
    if stats.latencies:
        lat = np.asarray(stats.latencies) * 1e6
        line += (f"; latency input->output p50 {np.percentile(lat, 50):.0f} us, "
                 f"p99 {np.percentile(lat, 99):.0f} us, max {lat.max():.0f} us")
    print(line, flush=True)


def view(system, args):
    from ..viz import MeshcatVisualizer, visualizer_for
    from ._viewer import LcmViewer

    visualizer = visualizer_for(system, plane=args.plane)
    viewer = LcmViewer(visualizer, args.url, channel=args.input_channel, max_rate=args.max_rate)
    where = visualizer.url() if isinstance(visualizer, MeshcatVisualizer) else "a matplotlib window"
    print(f"viewer of {system.name} on {args.url}: states from {viewer.channel}, drawn in {where} "
          f"at up to {viewer.max_rate:g} Hz", flush=True)
    stats = viewer.run(duration=args.duration)
    print(f"stopped: {stats.received} received, {stats.drawn} drawn, {stats.malformed} malformed", flush=True)


if __name__ == "__main__":
    main()
