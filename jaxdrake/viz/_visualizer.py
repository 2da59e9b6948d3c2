r"""Visualizers are dynamical systems, too (the notes, D.3.7): a `Visualizer` is a stateless
system whose input is the state of the plant it draws, so `cascade(plant, visualizer)` is a
diagram like any other; `playback`, `animate` and `save` replay a simulated trajectory.

A visualizer describes a state by *shapes*: named arrays of points in the drawing plane (metres),
computed by a pure JAX function of the state — `jax.vmap` gives every frame of a movie in one
call, and the tests compare them with the plant's kinematics. Each shape has a matplotlib style:
a polyline (`kind="line"`), markers (`"points"`) or a filled polygon (`"polygon"`). Frames are
taken at $t_k = t_0 + k / \mathrm{fps}$, $k < \mathrm{round}((t_f - t_0)\,\mathrm{fps})$; a hybrid
trajectory plays through its events (the state just after each), its mode named in the title.
"""

from __future__ import annotations

import functools
import pathlib
import re
import warnings
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._extras import require
from ..systems import HybridSystem, System

DRAW_PERIOD = 1 / 32  # exact in binary


def _fit_view(ax, shapes):
    """Widen the axes' limits (the visualizer's `view`) to hold every point the movie draws,
    with a 5% margin: a ball dropped from above the default view is not clipped at its apex."""
    points = np.concatenate([np.asarray(v).reshape(-1, 2) for v in shapes.values()])
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.05 * float(np.max(high - low))
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    ax.set_xlim(min(x0, low[0] - margin), max(x1, high[0] + margin))
    ax.set_ylim(min(y0, low[1] - margin), max(y1, high[1] + margin))


def gif_durations(count: int, fps: float) -> list[int]:
    """Frame durations in ms for a GIF, which stores them in 10-ms units: frame k ends at
    1000 (k + 1) / fps rounded to 10 ms, so the movie lasts as long as the trajectory (a
    constant 30 ms for a 31.25-ms period played it 4% fast)."""
    ends = 10 * np.round(100 * np.arange(1, count + 1) / fps)
    return np.diff(ends, prepend=0.0).astype(int).tolist()


class Visualizer(System):
    """A stateless system drawing the plant whose state is its input.

    Subclasses give `shapes(x)` (a dict of (k, 2) point arrays, JAX), `STYLES` (a class-level
    dict of matplotlib keyword dicts with a `kind`), `view()` ((xmin, xmax), (ymin, ymax)), and may
    draw fixed `scenery(ax)`; a walker gives its `travel(traj, times)` and the `ground(travel)`
    that moves past it (the camera follows the walker).
    """

    draw_period: float = eqx.field(static=True)
    plant_name: str = eqx.field(static=True)

    def __init__(self, plant: System, draw_period: float = DRAW_PERIOD):
        if not draw_period > 0:
            raise ValueError(f"draw_period must be positive, got {draw_period}")
        self.draw_period = float(draw_period)
        self.plant_name = plant.name
        super().__init__(num_inputs=plant.num_states, num_outputs=0, direct_feedthrough=False,
                         time_invariant=True, input_frame=plant.state_frame)

    # ----- what a subclass describes ----------------------------------------------------------

    STYLES: ClassVar[dict] = {}  # {shape name: {"kind": ..., matplotlib kwargs}}

    def shapes(self, x) -> dict:
        raise NotImplementedError

    def view(self):
        raise NotImplementedError

    def scenery(self, ax):
        """Fixed background (ground, ramp, rail); nothing by default."""

    def travel(self, traj, times):
        """How far a walker has gone at each frame time (n, 2): zero for plants that stay in view.
        A movie keeps the walker in view and moves `ground(travel)` past it instead."""
        return np.zeros((len(times), 2))

    def ground(self, travel):
        """Shapes of the ground seen from a walker that has gone `travel` (numpy); none by default."""
        return {}

    # ----- drawing ----------------------------------------------------------------------------

    def output(self, t, x, u):
        return jnp.zeros(0, u.dtype)

    def frame_shapes(self, xs):
        """Every shape for a batch of states xs (n, num_states): {name: (n, k, 2)}, on the host."""
        xs = jnp.asarray(xs)[..., : self.num_inputs]
        return {k: np.asarray(v) for k, v in batched(self, "shapes")(xs).items()}

    def _artists(self, ax, alpha=1.0, names=None):
        from matplotlib.lines import Line2D
        from matplotlib.patches import Polygon

        artists = {}
        for name, style in self.STYLES.items():
            if names is not None and name not in names:
                continue
            style = dict(style)
            kind = style.pop("kind", "line")
            if kind == "polygon":
                artist = Polygon(np.zeros((3, 2)), closed=True, alpha=alpha * style.pop("alpha", 1.0), **style)
                ax.add_patch(artist)
            else:
                if kind == "points":
                    style.setdefault("linestyle", "none")
                    style.setdefault("marker", "o")
                artist = Line2D([], [], alpha=alpha * style.pop("alpha", 1.0), **style)
                ax.add_line(artist)
            artist.set_gid(name)  # find an artist by its shape's name
            artists[name] = artist
        return artists

    @staticmethod
    def _place(artists, shapes, k):
        for name, artist in artists.items():
            points = shapes[name][k]
            if hasattr(artist, "set_xy"):
                artist.set_xy(points)
            else:
                artist.set_data(points[:, 0], points[:, 1])

    def _figure(self, ax=None, figsize=(6.4, 4.8)):
        import matplotlib.pyplot as plt

        if ax is None:
            fig, ax = plt.subplots(figsize=figsize, dpi=100)
        (x0, x1), (y0, y1) = self.view()
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        self.scenery(ax)
        return ax.figure, ax

    def draw(self, x, ax=None):
        """Draw the plant in state x; returns the matplotlib figure."""
        fig, ax = self._figure(ax)
        shapes = self.frame_shapes(jnp.asarray(x)[None]) | {k: v[None] for k, v in self.ground(np.zeros(2)).items()}
        self._place(self._artists(ax, names=shapes), shapes, 0)
        ax.set_title(self.plant_name)
        return fig

    def live(self):
        """`show(x, t=None)`: redraw the plant in state x in one window, kept between calls
        (what an LCM viewer node calls for each state it draws)."""
        import matplotlib.pyplot as plt

        fig, ax = self._figure()
        title, artists = ax.set_title(self.plant_name), {}

        def show(x, t=None):
            shapes = self.frame_shapes(jnp.asarray(x)[None]) | {k: v[None] for k, v in self.ground(np.zeros(2)).items()}
            if not artists:
                artists.update(self._artists(ax, names=shapes))
            self._place(artists, shapes, 0)
            if t is not None:
                title.set_text(f"{self.plant_name}: t = {float(t):.2f} s")
            fig.canvas.draw_idle()
            fig.canvas.flush_events()

        with warnings.catch_warnings():  # a non-interactive backend (Agg) only draws
            warnings.simplefilter("ignore", UserWarning)
            plt.show(block=False)
        show.figure = fig
        return show

    def frames(self, traj, fps=None, single: bool = False):
        """The frame times, states (n, [batch,] num_states) and mode labels of a trajectory
        (`single`: one trajectory only, not a vmapped batch)."""
        fps = 1 / self.draw_period if fps is None else float(fps)
        batched = np.ndim(traj.t_final) == 1
        if batched and single:
            raise ValueError(f"{type(self).__name__} draws one trajectory; index the batch (traj[i])")
        first = traj[0] if batched else traj
        t0, tf = float(first.t0), float(np.max(np.asarray(traj.t_final)))
        times = t0 + np.arange(int(round((tf - t0) * fps))) / fps
        if len(times) == 0:
            raise ValueError(f"the trajectory is shorter than one frame (1/{fps:g} s)")
        if batched:
            xs = np.swapaxes(np.asarray(jax.vmap(lambda member: member.state(jnp.asarray(times)))(traj)), 0, 1)
        else:
            xs = np.asarray(traj.state(jnp.asarray(times)))
        labels = [""] * len(times)
        if isinstance(first.system, HybridSystem) and first.system.num_modes > 1 and not batched:
            names = [m.name for m in first.system.modes]
            labels = [f", {names[int(m)]}" for m in np.asarray(first.mode(jnp.asarray(times)))]
        return times, xs, labels, fps

    def _scene(self, traj, fps, ax=None):
        """A figure holding the first frame, and `update(k)` that moves its artists to frame k."""
        times, xs, labels, fps = self.frames(traj, fps)
        fig, ax = self._figure(ax)
        members = xs.shape[1] if xs.ndim == 3 else 1
        states = xs.reshape(len(times) * members, -1)
        shapes = {k: v.reshape(len(times), members, *v.shape[1:]) for k, v in self.frame_shapes(states).items()}
        _fit_view(ax, shapes)
        travel = self.travel(traj, times) if members == 1 else np.zeros((len(times), 2))
        grounds = [self.ground(step) for step in travel]
        ground = {name: np.stack([g[name] for g in grounds]) for name in grounds[0]}
        alpha = 1.0 if members == 1 else max(0.1, 1 / np.sqrt(members))
        layers = [self._artists(ax, alpha, names=set(shapes) | set(ground)) for _ in range(members)]
        title = ax.set_title("")
        moving = [a for artists in layers for a in artists.values()] + [title]

        def update(k):
            for j, artists in enumerate(layers):
                drawn = {n: v[:, j] for n, v in shapes.items()} | ground
                self._place(artists, drawn, k)
            title.set_text(f"{self.plant_name}: t = {times[k]:.2f} s{labels[k]}")
            return moving

        update(0)
        return fig, update, moving, len(times), fps

    def animate(self, traj, fps=None, rate: float = 1.0, ax=None):
        """A matplotlib `FuncAnimation` of a simulated trajectory (of the plant, or of a diagram
        whose state starts with the plant's); a vmapped batch is drawn as overlaid ghosts.
        `rate`: playback speed (2.0 plays twice as fast)."""
        from matplotlib.animation import FuncAnimation

        fig, update, _, count, fps = self._scene(traj, fps, ax)
        return FuncAnimation(fig, update, frames=count, interval=1000 / (fps * rate), blit=False)

    def render(self, traj, fps=None):
        """The movie's frames as RGB arrays (n, height, width, 3): the axes, ticks and scenery
        drawn once, then only the moving artists per frame (matplotlib blitting)."""
        import matplotlib.pyplot as plt

        fig, update, moving, count, fps = self._scene(traj, fps)
        try:
            for artist in moving:
                artist.set_animated(True)
            canvas = fig.canvas
            canvas.draw()
            background = canvas.copy_from_bbox(fig.bbox)
            frames = []
            for k in range(count):
                canvas.restore_region(background)
                for artist in update(k):
                    fig.draw_artist(artist)
                frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
        finally:
            plt.close(fig)
        return np.stack(frames)

    def save(self, traj, path, fps=None) -> pathlib.Path:
        """Write a movie of the trajectory: `.gif` (Pillow), `.mp4` (the ffmpeg of
        `imageio-ffmpeg`; no system ffmpeg needed) or `.html` (self-contained, no network)."""
        import matplotlib.pyplot as plt

        path = pathlib.Path(path)
        suffix = path.suffix.lower()
        if suffix not in (".gif", ".mp4", ".html"):
            raise ValueError(f"cannot write {path.name}: choose .gif, .mp4 or .html")
        fps = 1 / self.draw_period if fps is None else float(fps)
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".html":
            animation = self.animate(traj, fps)
            try:
                path.write_text(_offline(animation.to_jshtml(fps=fps, default_mode="once")))
            finally:
                plt.close(animation._fig)
            return path
        if suffix == ".mp4":
            imageio_ffmpeg = require("imageio_ffmpeg", "saving .mp4 (not .gif or .html)")
        frames = self.render(traj, fps)
        if suffix == ".gif":
            from PIL import Image

            # one palette for the movie, from a few frames side by side (per-frame palettes take seconds)
            sample = Image.fromarray(np.concatenate(frames[:: max(1, len(frames) // 4)], axis=1))
            palette = sample.quantize(colors=128, method=Image.Quantize.MEDIANCUT)
            images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
            images[0].save(path, save_all=True, append_images=images[1:], duration=gif_durations(len(images), fps),
                           loop=0)
        else:
            with warnings.catch_warnings():  # JAX warns of any fork; ffmpeg's process execs at once
                warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
                writer = imageio_ffmpeg.write_frames(str(path), (frames.shape[2], frames.shape[1]), fps=fps,
                                                     codec="libx264", pix_fmt_out="yuv420p", macro_block_size=8)
                writer.send(None)
                for frame in frames:
                    writer.send(np.ascontiguousarray(frame))
                writer.close()
        return path

    def playback(self, traj, rate: float = 1.0, fps=None):
        """Play the trajectory in real time (`rate` times faster): inline in a notebook (returns
        the HTML player to display), in a window otherwise."""
        import matplotlib.pyplot as plt

        animation = self.animate(traj, fps, rate)
        if _in_notebook():
            from IPython.display import HTML

            plt.close(animation._fig)
            return HTML(_offline(animation.to_jshtml(fps=(1 / self.draw_period if fps is None else fps) * rate)))
        plt.show()
        return animation


@functools.lru_cache(maxsize=64)
def batched(visualizer, method: str):
    """`visualizer.method` vmapped over states and compiled, once per visualizer."""
    return jax.jit(jax.vmap(getattr(visualizer, method)))


_BUTTONS = {"fa-plus": "+", "fa-minus": "\u2212", "fa-fast-backward": "\u23ee", "fa-step-backward": "\u23f4",
            "fa-play fa-flip-horizontal": "\u25c0", "fa-pause": "\u23f8", "fa-play": "\u25b6",
            "fa-step-forward": "\u23f5", "fa-fast-forward": "\u23ed"}


def _offline(html: str) -> str:
    """matplotlib's HTML player without its one network resource (the Font Awesome stylesheet
    from a CDN): the buttons' icons become Unicode symbols."""
    html = re.sub(r'<link rel="stylesheet"\s*href="https?://[^"]*"\s*/?>', "", html)
    return re.sub(r'<i class="fa ([^"]*)"></i>', lambda m: _BUTTONS.get(m.group(1), ""), html)


def _in_notebook() -> bool:
    try:
        from IPython import get_ipython
    except ImportError:
        return False
    shell = get_ipython()
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"
