r"""Run a system as a node on an LCM network (the notes' `runLCM(sys, ...)`, D.5.1).

The node subscribes to the system's input channel, holds the latest input, and at every tick
of its clock advances the jit-compiled system and publishes its output:

- a continuous system is integrated over the tick, $x(t + \Delta) = \phi_\Delta(t, x, u)$, with
  `discrete_step` (`substeps` fixed RK4 steps, the input held);
- a discrete system takes its update at its sample time (the tick is its period);
- a system without state (a controller $u = k(t, y)$) is evaluated on every input message
  (`rate=None`) or at the rate.

Each port's frame gives its coder (`Frame.with_coder`), `SignalCoder(frame)` by default; the
channel defaults to the frame's name. A malformed message is counted and dropped; an input
older than `input_timeout` is *stale*: the node logs it once, applies `safe_input` (or holds
the last input when none is given) until messages return, and logs the recovery. `lockstep`
runs a simulated plant as fast as its peer answers: tick k waits for the input stamped with
tick k's time (or the timeout), so no message is lost and the loop is reproducible.
SIGINT / SIGTERM end `run()` cleanly; every message in and out can be written to an LCM event
log (`lcm-logplayer` replays it).
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import logging
import pathlib
import signal
import sys
import time

import jax
import numpy as np

from .._extras import require
from ..simulation import discrete_step
from ..systems import System
from ..systems import require_plain_system
from ._coders import MessageError, SignalCoder
from ._relay import RELAY_ERROR_CHANNEL

log = logging.getLogger("jaxdrake.lcm")


HOST_ONLY_URL = "udpm://239.255.76.67:7667?ttl=0"  # LCM's usual group; ttl=0: never leaves the host


# the longest wait for a message between checks of the stop flag: a signal's handler runs only
# once LCM's wait returns (over tcpq a signal does not cut the wait short)
_STOP_CHECK_PERIOD = 0.1


def _no_delay(node):
    """Set TCP_NODELAY on a tcpq client's socket: LCM's C client leaves Nagle's algorithm on,
    which holds small messages back ~40 ms."""
    import os
    import socket

    sock = socket.socket(fileno=os.dup(node.fileno()))
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except OSError:
        pass
    finally:
        sock.close()


def stop_on_signals(stop) -> dict:
    """Call `stop()` on SIGINT / SIGTERM; returns the previous handlers (none off the main
    thread, where the caller's own stop is the way out)."""
    previous = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop())
    except ValueError:
        return {}
    return previous


def restore_signals(previous: dict):
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def _log_relay_error(channel, data):
    log.error("the LCM relay refused a request: %s", data.decode("utf-8", "replace"))


def load_system(spec: str):
    """The system named by `spec`: `module:name` (e.g. `jaxdrake.models:Pendulum`) or
    `path/to/file.py:name`, a `System` or a function returning one (the command lines' SYSTEM)."""

    target, _, name = spec.rpartition(":")
    if not target or not name:
        raise ValueError(f"SYSTEM must be 'module:name' or 'file.py:name', got {spec!r}")
    if target.endswith(".py"):
        path = pathlib.Path(target)
        module_spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(module_spec)
        sys.path.insert(0, str(path.parent))
        module_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(target)
    obj = getattr(module, name)
    system = obj if isinstance(obj, System) else obj()
    if not isinstance(system, System):
        raise ValueError(f"{spec} is not a jaxdrake.System nor a function returning one")
    return system


def open_lcm(url):
    """An `lcm.LCM` on `url` (or `url` itself, an existing instance); on tcpq, TCP_NODELAY set
    and the relay's refusals (`RELAY_ERROR_CHANNEL`) logged as errors when handled."""
    lcm = require("lcm", "jaxdrake.lcm")

    if isinstance(url, lcm.LCM):
        return url
    if not isinstance(url, str) or "://" not in url:
        raise ValueError(f"an LCM URL looks like 'udpm://239.255.76.67:7667?ttl=0', 'tcpq://127.0.0.1:7700' "
                         f"or 'memq://', got {url!r}")
    connection = lcm.LCM(url)
    if url.startswith("tcpq://"):
        _no_delay(connection)
        connection.subscribe(RELAY_ERROR_CHANNEL, _log_relay_error)
    return connection


def coder_for(frame):
    return frame.coder if frame.coder is not None else SignalCoder(frame)


@dataclasses.dataclass
class NodeStatistics:
    """Counters of a node's run."""

    received: int = 0
    published: int = 0
    malformed: int = 0
    stale_events: int = 0
    ticks: int = 0
    latencies: list = dataclasses.field(default_factory=list)  # s, input message -> output publish


class LcmNode:
    """`system` as an LCM node on `url` — by default LCM's multicast group with ttl=0, which
    never leaves the host (LCM's own default, `lcm.LCM()`, has ttl=1 and reaches the LAN) — or
    on an existing `lcm.LCM` instance (e.g. one `memq://` shared in a process).

    - `input_channel` / `output_channel`: default the input / output frame's name.
    - `rate`: ticks per second (default: the sample time of a discrete system; 100 Hz for a
      continuous one; None for a stateless one, which then answers each input message).
    - `x0`: the initial state (default `system.initial_state()`); `t0` the initial time.
    - `substeps`: RK4 steps per tick for a continuous system.
    - `input_timeout` (s), `safe_input`: the stale-input behaviour (see the module doc).
    - `lockstep`: wait each tick for the input stamped with that tick's time.
    - `log_path`: write every message in and out to an LCM event log there.
    """

    def __init__(self, system: System, url=HOST_ONLY_URL, *, input_channel=None, output_channel=None, rate=None,
                 x0=None, t0=0.0, substeps: int = 10, input_timeout: float = 0.5, safe_input=None,
                 lockstep: bool = False, log_path=None):
        lcm = require("lcm", "LcmNode")

        require_plain_system(system, "LcmNode", "run a deterministic system (one mode of a hybrid one)")
        self._lcm = open_lcm(url)
        self.system, self.url = system, url if isinstance(url, str) else "an lcm.LCM instance"
        self.stateless = system.num_states == 0
        if rate is None and not self.stateless:
            rate = 1.0 / system.sample_time if system.has_discrete_state else 100.0
        self.rate = rate
        self.input_coder = coder_for(system.input_frame) if system.num_inputs else None
        self.output_coder = coder_for(system.output_frame)
        self.input_channel = input_channel or system.input_frame.name
        self.output_channel = output_channel or system.output_frame.name
        self.input_timeout, self.lockstep = float(input_timeout), bool(lockstep)
        self.safe_input = None if safe_input is None else np.asarray(safe_input, float).reshape(system.num_inputs)
        self.t = float(t0)
        self.x = np.asarray(system.initial_state() if x0 is None else x0, float).reshape(system.num_states)
        self.u = np.zeros(system.num_inputs) if self.safe_input is None else self.safe_input.copy()
        self.u_time, self.u_arrival = None, None
        self._fresh_arrival = None  # arrival time of an input not yet answered by an output
        self.stale = False
        self.stats = NodeStatistics()
        self._stop, self._failures = False, 0
        self._started = time.perf_counter()
        self._log = lcm.EventLog(str(log_path), "w", overwrite=True) if log_path else None
        if self.input_coder is not None:
            self._lcm.subscribe(self.input_channel, self._on_input)
        self._compile(substeps)

    def _compile(self, substeps):
        system = self.system
        dt = 1.0 / self.rate if self.rate else 0.0
        self._advance = jax.jit(lambda t, x, u: discrete_step(system, t, x, u, dt, "rk4", substeps))
        self._output = jax.jit(lambda t, x, u: system.output(t, x, u))
        self.dt = dt
        # compile before the first message, so the real-time loop never waits for XLA
        jax.block_until_ready((self._advance(self.t, self.x, self.u), self._output(self.t, self.x, self.u)))

    # ----- messages -------------------------------------------------------------------------

    def _record(self, channel, data):
        if self._log is not None:
            self._log.write_event(int(time.time() * 1e6), channel, data)

    def _on_input(self, channel, data):
        arrival = time.perf_counter()
        self._record(channel, data)
        try:
            t, u = self.input_coder.decode(data)
        except MessageError as error:
            self.stats.malformed += 1
            log.debug("dropped a message on %s: %s", channel, error)
            return
        self.stats.received += 1
        self.u, self.u_time, self.u_arrival, self._fresh_arrival = u, t, arrival, arrival
        if self.stale:
            self.stale = False
            log.warning("%s: input %s resumed at t = %.3f", self.system.name, self.input_channel, self.t)
        if self.stateless and self.rate is None:
            self._publish(t)

    def _publish(self, t):
        """Publish y(t); the first output after an input message times its latency."""
        y = np.asarray(self._output(t, self.x, self._applied_input()))  # numpy in: ~35 us less dispatch
        data = self.output_coder.encode(t, y)
        self._lcm.publish(self.output_channel, data)
        self._record(self.output_channel, data)
        self.stats.published += 1
        if self._fresh_arrival is not None:
            self.stats.latencies.append(time.perf_counter() - self._fresh_arrival)
            self._fresh_arrival = None

    def _applied_input(self):
        if self.stale and self.safe_input is not None:
            return self.safe_input
        return self.u

    def _check_stale(self, now):
        if self.input_coder is None or self.stale:
            return
        last = self.u_arrival if self.u_arrival is not None else self._started
        if now - last > self.input_timeout:
            self.stale = True
            self.stats.stale_events += 1
            action = "applying the safe input" if self.safe_input is not None else "holding the last input"
            log.warning("%s: no message on %s for %.3f s: %s", self.system.name, self.input_channel,
                        now - last, action)

    # ----- the loop -------------------------------------------------------------------------

    def tick(self):
        """Publish y(t), then advance the state over one tick with the input applied now."""
        self._publish(self.t)
        self._advance_one_tick()

    def _advance_one_tick(self):
        self.x = np.asarray(self._advance(self.t, self.x, self._applied_input()))
        self.t += self.dt
        self.stats.ticks += 1

    def _lockstep_tick(self):
        """Publish y(t_k), wait for the input stamped t_k (or the timeout), then advance."""
        self._publish(self.t)
        deadline = time.perf_counter() + self.input_timeout
        while (self.u_time is None or self.u_time < self.t - 1e-9) and not self._stop:
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                self._check_stale(time.perf_counter())
                break
            self.handle(min(max(remaining, 0.001), _STOP_CHECK_PERIOD))
        self._advance_one_tick()

    def handle(self, timeout: float = 0.0):
        """Handle the messages that arrive within `timeout` seconds (outside `run` too)."""
        try:
            self._lcm.handle_timeout(max(0, int(timeout * 1000)))
            self._failures = 0
        except OSError:  # a signal interrupts the wait (its handler runs after this returns)
            self._failures += 1
            if self._failures > 3 and not self._stop:  # not a signal: the connection is gone
                raise

    def stop(self):
        self._stop = True

    def run(self, duration: float | None = None, max_ticks: int | None = None) -> NodeStatistics:
        """Run until `duration` seconds of wall time (or `max_ticks`, or SIGINT / SIGTERM) pass;
        return the counters."""
        previous = stop_on_signals(self.stop)
        if self.input_coder is not None:  # let the subscription reach the network (a relay, a
            settle = time.perf_counter() + 0.2  # multicast join) before the first output
            while time.perf_counter() < settle:
                self.handle(0.05)
        self._started = start = time.perf_counter()
        next_tick = start
        try:
            while not self._stop:
                now = time.perf_counter()
                if duration is not None and now - start >= duration:
                    break
                if max_ticks is not None and self.stats.ticks >= max_ticks:
                    break
                self._check_stale(now)
                if self.rate is None:  # event-driven: answer messages
                    self.handle(0.05)
                    continue
                if self.lockstep and self.input_coder is not None:
                    self._lockstep_tick()
                    continue
                if now >= next_tick:
                    self.tick()
                    next_tick += self.dt
                    if next_tick < now:  # overrun: do not try to catch up with a burst
                        next_tick = now + self.dt
                else:
                    self.handle(next_tick - now)
        finally:
            restore_signals(previous)
            if self._log is not None:
                self._log.close()
        return self.stats
