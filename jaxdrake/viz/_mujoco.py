"""MuJoCo models (a `MujocoSystem`, or a rigid-body plant loaded from MJCF) drawn by MuJoCo's
own renderer: the planar visualizers' interface (`draw`, `animate`, `playback`, `save` to
.gif / .mp4 / .html) with each frame an image of the model's
scene at that state (`mj_forward`, then the offscreen renderer). On a machine without a
display MuJoCo renders through EGL (Mesa's software EGL works on CPU-only machines); importing
jaxdrake sets `MUJOCO_GL=egl` there unless you chose a backend, and where mujoco was imported
first (so chose GLFW) its offscreen context is switched to EGL.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

from ..multibody import RigidBodySystem, mjcf_render_model
from ..mujoco import MujocoSystem, import_mujoco, mujoco_renderer
from ._visualizer import DRAW_PERIOD, Visualizer


class MujocoVisualizer(Visualizer):
    """Frames of a `MujocoSystem`, or of a `RigidBodySystem` loaded by `from_mjcf(path)`,
    rendered by MuJoCo from the model file (`width` x `height` pixels, from `camera`: a camera
    name or index of the model, -1 for the free camera). A rigid-body plant's state is drawn
    through its positions alone, each placed at its qpos address (a free body's quaternion
    reordered)."""

    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    camera: int | str = eqx.field(static=True)
    mj_model: object = eqx.field(static=True)  # the plant's C model (MuJoCo renders from it)
    sizes: tuple = eqx.field(static=True)  # (nq, nv, na)
    qpos_addresses: tuple | None = eqx.field(static=True)  # a rigid-body plant's: each position's qpos index

    def __init__(self, plant: MujocoSystem | RigidBodySystem, *, width: int = 640, height: int = 480, camera=-1,
                 draw_period: float = DRAW_PERIOD):
        if isinstance(plant, RigidBodySystem) and plant.source_format == "mjcf":
            model, addresses = mjcf_render_model(plant)
            self.mj_model, self.sizes = model, (int(model.nq), int(model.nv), int(model.na))
            self.qpos_addresses = tuple(int(a) for a in addresses)
        elif isinstance(plant, MujocoSystem):
            self.mj_model, self.sizes, self.qpos_addresses = plant.mj_model, plant.sizes, None
        else:
            raise TypeError(f"MujocoVisualizer draws a MujocoSystem or a RigidBodySystem loaded from an MJCF file "
                            f"(from_mjcf(path)), not {type(plant).__name__} {plant.name!r}")
        super().__init__(plant, draw_period)
        self.width, self.height, self.camera = int(width), int(height), camera

    def images(self, xs) -> np.ndarray:
        """RGB images (n, height, width, 3) of the states xs (n, num_states)."""
        mujoco, _ = import_mujoco()
        model = self.mj_model
        nq, nv, na = self.sizes
        data = mujoco.MjData(model)
        frames = []
        with mujoco_renderer(model, self.height, self.width) as scene:
            for x in np.asarray(xs, float)[:, : self.num_inputs]:  # a diagram's state starts with the plant's
                if self.qpos_addresses is None:
                    data.qpos[:], data.qvel[:], data.act[:] = x[:nq], x[nq: nq + nv], x[nq + nv: nq + nv + na]
                else:
                    data.qpos[list(self.qpos_addresses)] = x[: len(self.qpos_addresses)]
                mujoco.mj_forward(model, data)
                scene.update_scene(data, self.camera)
                frames.append(scene.render().copy())
        return np.stack(frames)

    def _figure_with_image(self, image, ax=None):
        import matplotlib.pyplot as plt

        if ax is None:
            fig, ax = plt.subplots(figsize=(self.width / 100, self.height / 100), dpi=100)
            fig.subplots_adjust(0, 0, 1, 1)
        ax.set_axis_off()
        return ax.figure, ax.imshow(image)

    def draw(self, x, ax=None):
        """The model at state x, as a matplotlib figure of MuJoCo's image."""
        return self._figure_with_image(self.images(np.asarray(x)[None])[0], ax)[0]

    def render(self, traj, fps=None):
        """The movie's frames (n, height, width, 3), rendered by MuJoCo."""
        return self.images(self.frames(traj, fps, single=True)[1])

    def animate(self, traj, fps=None, rate: float = 1.0, ax=None):
        """A matplotlib `FuncAnimation` of the rendered frames."""
        from matplotlib.animation import FuncAnimation

        fps = 1 / self.draw_period if fps is None else float(fps)
        frames = self.render(traj, fps)
        fig, image = self._figure_with_image(frames[0], ax)

        def update(k):
            image.set_data(frames[k])
            return [image]

        return FuncAnimation(fig, update, frames=len(frames), interval=1000 / (fps * rate), blit=False)

    def live(self):
        """`show(x, t=None)`: redraw the model at state x in one kept window."""
        import matplotlib.pyplot as plt

        fig, image = self._figure_with_image(np.zeros((self.height, self.width, 3), np.uint8))
        plt.show(block=False)

        def show(x, t=None):
            image.set_data(self.images(np.asarray(x)[None])[0])
            fig.canvas.draw_idle()
            fig.canvas.flush_events()

        show.figure = fig
        return show
