"""A visualizer as an LCM node: a robot's state viewer (the notes' visualizers on the LCM
network, D.5).

It subscribes to the plant's state channel — the visualizer's input frame gives the coder
and the default channel name, the same as the channel an `LcmNode` of the plant publishes —
and draws the newest state at most `max_rate` times a second (30 Hz by default). States that
arrive between two draws are not queued: only the newest is drawn, so a fast publisher never
makes the display lag behind.
"""

from __future__ import annotations

import dataclasses
import time

from ._bridge import HOST_ONLY_URL, coder_for, open_lcm, restore_signals, stop_on_signals
from ._coders import MessageError


@dataclasses.dataclass
class ViewerStatistics:
    received: int = 0
    drawn: int = 0
    malformed: int = 0


class LcmViewer:
    """Draw the states of `visualizer`'s plant received on `channel` (default: the plant's
    state frame name) through `url`, at most `max_rate` draws per second. `show(x, t)` does
    the drawing (default `visualizer.live()`: a matplotlib window, or the MeshCat scene of a
    `MeshcatVisualizer`)."""

    def __init__(self, visualizer, url=HOST_ONLY_URL, *, channel=None, max_rate: float = 30.0, show=None):
        if not max_rate > 0:
            raise ValueError(f"max_rate must be positive, got {max_rate}")
        self.visualizer, self.max_rate = visualizer, float(max_rate)
        self.coder = coder_for(visualizer.input_frame)
        self.channel = channel or visualizer.input_frame.name
        self.show = visualizer.live() if show is None else show
        self.latest, self.stats = None, ViewerStatistics()
        self._stop = False
        self._lcm = open_lcm(url)
        self._lcm.subscribe(self.channel, self._on_state)

    def _on_state(self, channel, data):
        try:
            self.latest = self.coder.decode(data)  # (t, x)
        except MessageError:
            self.stats.malformed += 1
            return
        self.stats.received += 1

    def stop(self):
        self._stop = True

    def run(self, duration: float | None = None, max_draws: int | None = None) -> ViewerStatistics:
        """Draw until `duration` seconds pass (or `max_draws` draws, or SIGINT / SIGTERM)."""
        previous = stop_on_signals(self.stop)
        start = next_draw = time.perf_counter()
        try:
            while not self._stop:
                now = time.perf_counter()
                if (duration is not None and now - start >= duration) or \
                        (max_draws is not None and self.stats.drawn >= max_draws):
                    break
                if self.latest is not None and now >= next_draw:
                    t, x = self.latest
                    self.latest = None
                    self.show(x, t)
                    self.stats.drawn += 1
                    next_draw = now + 1 / self.max_rate
                    continue
                wait = 0.05 if self.latest is None else next_draw - now
                if self._lcm.handle_timeout(max(1, int(1000 * min(0.05, wait)))) > 0:
                    while self._lcm.handle_timeout(0) > 0:  # drain the backlog: the newest wins
                        pass
        finally:
            restore_signals(previous)
        return self.stats
