r"""The ROS–LCM translator (the notes' D.5.2): systems speak LCM, and one process carries their
channels to ROS topics and back, so `LcmNode` systems join a ROS network unchanged.

For each route (`Route`), a message arriving on the source side is read with the source's
coder, $(t, x)$, and written with the other side's: LCM -> ROS reads `coder.decode` and
publishes `message.encode(t, x)`; ROS -> LCM reads `message.decode` and publishes
`coder.encode(t, x)`, the time being the message's stamp, or the translator's clock
(`time.time()`) for a type without one. A message that cannot be read (LCM: wrong fingerprint,
truncated, wrong sizes or names, non-finite values; ROS: the same, or a publisher of another
type on the topic) is counted in its route's statistics and dropped; the first of each kind per
route is logged as a warning. SIGINT / SIGTERM end `run()` cleanly. With `bag=` every message
the translator publishes or receives on the ROS side is also written to a ROS bag (`RosBag`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import threading
import time

from ..lcm import MessageError
from ..lcm import HOST_ONLY_URL, open_lcm, restore_signals, stop_on_signals
from ._routes import TO_ROS, check_routes

log = logging.getLogger("jaxdrake.ros")


@dataclasses.dataclass
class RouteStatistics:
    """Counters of one route: messages that arrived on its source side, were passed on, or were
    dropped as malformed or of the wrong type."""

    received: int = 0
    forwarded: int = 0
    malformed: int = 0
    wrong_type: int = 0

    def __str__(self):
        return (f"{self.received} received, {self.forwarded} forwarded, {self.malformed} malformed, "
                f"{self.wrong_type} wrong type")


class Translator:
    """Bridge `routes` between the LCM network at `lcm_url` (an URL or an `lcm.LCM`) and a ROS
    `network` (`Ros1Network()` — rospy, the default — or `Ros2Network(domain_id)`).

    `stats` maps each route's text (`str(route)`) to its `RouteStatistics`. Use as a context
    manager, or call `close()`; `run(duration)` handles messages until then (or a signal).
    """

    def __init__(self, routes, lcm_url=HOST_ONLY_URL, *, network=None, bag=None):
        from ._ros1 import Ros1Network

        self.routes = check_routes(routes)
        self._lcm = open_lcm(lcm_url)
        self.network = network if network is not None else Ros1Network()
        self.stats = {str(route): RouteStatistics() for route in self.routes}
        self._lock = threading.Lock()  # ROS callbacks run on the network's threads
        self._warned = set()
        self._stop = False
        self._bag = None
        if bag is not None:
            from ._bags import RosBag

            self._bag = bag if isinstance(bag, RosBag) else RosBag(bag)
        for route in self.routes:
            if route.direction == TO_ROS:
                send = self.network.publisher(route.topic, route.message)
                self._lcm.subscribe(route.channel, functools.partial(self._from_lcm, route, send))
            else:
                self.network.subscribe(route.topic, route.message, functools.partial(self._from_ros, route),
                                       functools.partial(self._refuse, route))

    # ----- messages -------------------------------------------------------------------------

    def _count(self, route, field):
        with self._lock:
            stats = self.stats[str(route)]
            setattr(stats, field, getattr(stats, field) + 1)

    def _refuse(self, route, kind, reason):
        self._count(route, kind)
        if (str(route), kind) in self._warned:
            log.debug("%s: dropped a message: %s", route, reason)
        else:
            self._warned.add((str(route), kind))
            log.warning("%s: dropped a message (%s; further ones are counted): %s", route,
                        kind.replace("_", " "), reason)

    def _record(self, route, fields):
        if self._bag is not None:
            with self._lock:
                self._bag.write(route.topic, route.message, fields, time.time_ns())

    def _from_lcm(self, route, send, channel, data):
        self._count(route, "received")
        try:
            fields = route.message.encode(*route.coder.decode(data))
        except MessageError as error:
            return self._refuse(route, "malformed", str(error))
        send(fields)
        self._count(route, "forwarded")
        self._record(route, fields)

    def _from_ros(self, route, fields):
        self._count(route, "received")
        try:
            t, x = route.message.decode(fields)
        except (MessageError, KeyError, TypeError) as error:
            return self._refuse(route, "malformed", str(error))
        data = route.coder.encode(time.time() if t is None else t, x)
        with self._lock:
            self._lcm.publish(route.channel, data)
        self._count(route, "forwarded")
        self._record(route, fields)

    # ----- the loop -------------------------------------------------------------------------

    def stop(self):
        self._stop = True

    def run(self, duration: float | None = None):
        """Translate until `duration` seconds pass (or SIGINT / SIGTERM, or `stop()`); raises
        the network's fatal error (a `MasterError` for a ROS master gone too long). Returns
        `stats`."""
        previous = stop_on_signals(self.stop)
        start, failures = time.monotonic(), 0
        try:
            while not self._stop and (duration is None or time.monotonic() - start < duration):
                self.network.check()
                try:
                    self._lcm.handle_timeout(50)
                    failures = 0
                except OSError:  # a signal interrupts the wait; repeated, the connection is gone
                    failures += 1
                    if failures > 3 and not self._stop:
                        raise
        finally:
            restore_signals(previous)
        return self.stats

    def close(self):
        self.network.close()
        if self._bag is not None:
            self._bag.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
