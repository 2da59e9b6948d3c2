r"""3-D scenes of URDF robots in MeshCat, the browser viewer Drake uses (meshcat-python: a
server on 127.0.0.1, the three.js viewer in the browser, no network).

The scene holds each URDF link's `<visual>` elements (boxes, cylinders, spheres; meshes sent
as their files — `.dae`, `.obj`, `.stl` — for the browser to load, `package://` paths
resolved by yourdfpy's search next to the URDF), or, for a URDF without any visual, a
skeleton: a sphere at each link's origin and a rod to each link attached to it. A state x places every link at its
world pose $T_\ell(q) = [R_\ell(q), p_\ell(q)]$ (`RigidBodySystem.frame_pose`, all links in one
vmappable JAX function, `link_transforms`). A trajectory becomes a MeshCat animation: frames at
$t_k = t_0 + k/\mathrm{fps}$, played by the browser with its own controls; `save(traj,
"robot.html")` writes the scene and the animation as one self-contained file (the viewer's
JavaScript inlined, the commands base64-encoded); `save(traj, "robot.gif")` (or `.mp4`) a movie
of the same visuals rendered offscreen by MuJoCo (`_puppet.py`).
"""

from __future__ import annotations

import base64
import functools
import pathlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..multibody import RigidBodySystem
from ..multibody import _algorithms as alg
from ..multibody._tree import KinematicTree
from ._visualizer import DRAW_PERIOD, Visualizer, batched

_GREY, _SKELETON = 0xA0A0A8, 0x4C72B0


class SceneRecorder:
    """A MeshCat window that keeps the commands (as MeshCat lowers them: dicts) instead of
    sending them to a server: what a test inspects, and what `save(..., ".html")` writes."""

    def __init__(self):
        self.commands = []

    def send(self, command):
        self.commands.append(command.lower())


def _meshcat():
    try:
        import meshcat
        import meshcat.geometry
        import yourdfpy  # noqa: F401
    except ImportError:
        raise ImportError("3-D scenes need meshcat and yourdfpy: pip install 'jaxdrake[viz]' "
                          "(or pip install meshcat yourdfpy)") from None
    return meshcat


def _transform(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def urdf_color(visual, materials):
    """The RGBA colour of a URDF <visual> (its own material's, else the named robot material's),
    or None."""
    if visual.material is not None:
        for source in (visual.material, materials.get(visual.material.name)):
            if source is not None and source.color is not None:
                return np.asarray(source.color.rgba, float)
    return None


def _material(visual, materials):
    import meshcat.geometry as g

    color = urdf_color(visual, materials)
    if color is None:
        return g.MeshLambertMaterial(color=_GREY)
    rgb = int(np.round(color[0] * 255)) << 16 | int(np.round(color[1] * 255)) << 8 | int(np.round(color[2] * 255))
    return g.MeshLambertMaterial(color=rgb, opacity=float(color[3]), transparent=bool(color[3] < 1))


def _geometry(visual, resolve):
    """(MeshCat geometry, its 4x4 placement in the link frame) of a URDF <visual>."""
    import meshcat.geometry as g

    origin = np.eye(4) if visual.origin is None else np.asarray(visual.origin, float)
    shape = visual.geometry
    if shape.box is not None:
        return g.Box(list(map(float, shape.box.size))), origin
    if shape.sphere is not None:
        return g.Sphere(float(shape.sphere.radius)), origin
    if shape.cylinder is not None:  # URDF cylinders lie along z, three.js ones along y
        along_z = _transform(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), np.zeros(3))
        return g.Cylinder(float(shape.cylinder.length), float(shape.cylinder.radius)), origin @ along_z
    if shape.mesh is not None:
        path = pathlib.Path(resolve(shape.mesh.filename))
        kind = path.suffix.lower().lstrip(".")
        if kind not in ("dae", "obj", "stl") or not path.exists():
            raise FileNotFoundError(f"mesh {shape.mesh.filename!r}: found {path} " +
                                    ("which does not exist" if not path.exists() else f"of an unsupported kind .{kind}") +
                                    "; MeshCat loads .dae, .obj and .stl files")
        contents = path.read_bytes() if kind == "stl" else path.read_text()
        scale = np.ones(3) if shape.mesh.scale is None else np.broadcast_to(np.asarray(shape.mesh.scale, float), 3)
        return g.MeshGeometry(contents, kind), origin @ np.diag([*scale, 1.0])
    raise ValueError(f"a <visual> without geometry ({visual.name})")


class MeshcatVisualizer(Visualizer):
    """A 3-D view of a `RigidBodySystem` (from a URDF) in MeshCat; the same interface as the
    planar visualizers: `draw(x)`, `animate(traj)` (a MeshCat animation in the scene),
    `playback(traj, rate)`, `save(traj, "robot.html")`.

    `scene`: the `meshcat.Visualizer` to draw into (for instance one built on a
    `SceneRecorder` window); by default one that starts its own server on 127.0.0.1 at the
    first draw (its address: `url()`). `urdf`: the file whose `<visual>` elements to show
    (default: the one the plant was loaded from). `prefix`: the scene path of this robot.
    `save(traj, "robot.gif" or ".mp4")` writes a movie (`width` x `height`) rendered offscreen
    by MuJoCo from the same visuals (`render`, `images`).
    """

    tree: KinematicTree
    links: tuple = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    _connection: dict = eqx.field(static=True)

    def __init__(self, plant: RigidBodySystem, *, urdf=None, scene=None, prefix: str | None = None,
                 width: int = 640, height: int = 480, draw_period: float = DRAW_PERIOD):
        if not isinstance(plant, RigidBodySystem):
            raise TypeError(f"MeshcatVisualizer draws a RigidBodySystem (a URDF robot), not "
                            f"{type(plant).__name__}; use jaxdrake.viz.visualizer_for for the notes' plants")
        urdf = plant.source if urdf is None else urdf
        if urdf is None:
            raise ValueError(f"{plant.name} was not loaded from a URDF file: pass urdf=PATH for its visuals")
        _meshcat()
        super().__init__(plant, draw_period)
        self.tree, self.links = plant.tree, tuple(plant.tree.frame_names)
        self.width, self.height = int(width), int(height)
        self._connection = {"urdf": pathlib.Path(urdf), "scene": scene,
                            "prefix": prefix or plant.name, "loaded": False}

    # ----- kinematics (JAX) -----------------------------------------------------------------

    def link_transforms(self, x):
        """The world pose of every link (`links` order) in state x: (num_links, 4, 4)."""
        tree = self.tree
        q = x[: tree.nq]
        poses = alg.body_poses(tree, q)
        R, p = (jnp.stack(part) for part in zip(*(alg.frame_pose(tree, q, link, poses=poses) for link in self.links)))
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], R.dtype), (len(self.links), 1, 4))
        return jnp.concatenate([jnp.concatenate([R, p[:, :, None]], axis=2), bottom], axis=1)

    def frame_transforms(self, xs):
        """`link_transforms` of a batch of states (n, num_states), on the host: (n, links, 4, 4)."""
        xs = jnp.asarray(xs)[..., : self.num_inputs]
        return np.asarray(batched(self, "link_transforms")(xs), dtype=float)  # MeshCat packs Python floats

    # ----- the scene --------------------------------------------------------------------------

    @property
    def scene(self):
        """The `meshcat.Visualizer` (started, and the robot's geometry sent, on first use)."""
        connection = self._connection
        if connection["scene"] is None:
            meshcat = _meshcat()
            connection["scene"] = meshcat.Visualizer()
        if not connection["loaded"]:
            self._load(connection["scene"][connection["prefix"]])
            connection["loaded"] = True
        return connection["scene"]

    def url(self) -> str:
        """The address of the live viewer (open it in a browser)."""
        return self.scene.url()

    def _urdf_visuals(self):
        """({link: its <visual> elements}, {material name: material}, the mesh path resolver)
        of the URDF, read by yourdfpy."""
        import yourdfpy

        path = self._connection["urdf"]
        model = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False,
                                   filename_handler=functools.partial(yourdfpy.filename_handler_magic, dir=str(path.parent)))
        return ({link.name: link.visuals for link in model.robot.links}, {m.name: m for m in model.robot.materials},
                model._filename_handler)

    def _load(self, robot):
        import meshcat.geometry as g

        visuals, materials, resolve = self._urdf_visuals()
        if any(visuals.values()):
            for name in self.links:
                for k, visual in enumerate(visuals.get(name, [])):
                    geometry, placement = _geometry(visual, resolve)
                    robot[name][f"visual{k}"].set_object(geometry, _material(visual, materials))
                    robot[name][f"visual{k}"].set_transform(placement)
            return
        skeleton = self._skeleton()
        for name in self.links:
            robot[name]["joint"].set_object(g.Sphere(0.03), g.MeshLambertMaterial(color=_SKELETON))
            for k, offset in enumerate(skeleton.get(name, [])):
                length = float(np.linalg.norm(offset))
                y = offset / length  # a three.js cylinder along y, centred: turn y onto the offset
                x = np.cross(y, [0.0, 0.0, 1.0]) if abs(y[2]) < 0.9 else np.cross(y, [1.0, 0.0, 0.0])
                x /= np.linalg.norm(x)
                robot[name][f"rod{k}"].set_object(g.Cylinder(length, 0.015), g.MeshLambertMaterial(color=_SKELETON))
                robot[name][f"rod{k}"].set_transform(_transform(np.column_stack([x, y, np.cross(x, y)]), offset / 2))

    def _neutral_transforms(self):
        """`link_transforms` at the neutral configuration, at rest (links, 4, 4)."""
        tree = self.tree
        return self.frame_transforms(jnp.concatenate([tree.neutral_configuration(), jnp.zeros(tree.nv)])[None])[0]

    def _skeleton(self):
        """{link: offsets (in its frame) of the origins of the links attached to it (child
        bodies' joints, fixed frames)} at the neutral configuration."""
        tree = self.tree
        T = self._neutral_transforms()
        own = {b: k for k, b in enumerate(tree.frame_bodies) if b >= 0 and tree.frame_names[k] == tree.body_names[b]}
        rods = {}
        for k, b in enumerate(tree.frame_bodies):
            if b < 0:
                continue
            anchor = own[b] if own.get(b) != k else own.get(tree.parents[b])
            if anchor is None:
                continue
            offset = T[anchor, :3, :3].T @ (T[k, :3, 3] - T[anchor, :3, 3])
            if np.linalg.norm(offset) > 1e-6:
                rods.setdefault(self.links[anchor], []).append(offset)
        return rods

    # ----- the visualizer interface -----------------------------------------------------------

    def draw(self, x, ax=None):
        """Place the robot at state x in the scene; returns the `meshcat.Visualizer`."""
        scene = self.scene
        robot = scene[self._connection["prefix"]]
        for name, T in zip(self.links, self.frame_transforms(jnp.asarray(x)[None])[0]):
            robot[name].set_transform(T)
        return scene

    def live(self):
        """`show(x, t=None)`: place the robot at state x in the live scene."""
        return lambda x, t=None: self.draw(x)

    def animate(self, traj, fps=None, rate: float = 1.0, ax=None):
        """Send the trajectory to the scene as a MeshCat animation (frames at `fps`, played
        `rate` times faster by the browser, with its own controls); returns it."""
        from meshcat.animation import Animation

        times, xs, _, fps = self.frames(traj, fps, single=True)
        transforms = self.frame_transforms(xs)
        scene = self.scene
        robot = scene[self._connection["prefix"]]
        animation = Animation(default_framerate=fps * rate)
        for k in range(len(times)):
            with animation.at_frame(robot, k) as frame:
                for name, T in zip(self.links, transforms[k]):
                    frame[name].set_transform(T)
        scene.set_animation(animation, play=True, repetitions=1)
        return animation

    def playback(self, traj, rate: float = 1.0, fps=None):
        """Play the trajectory in the live viewer (real time, `rate` times faster); returns its URL."""
        self.animate(traj, fps, rate)
        return self.url()

    def render(self, traj, fps=None):
        """The movie's frames (n, height, width, 3): the robot's visuals rendered offscreen by
        MuJoCo (needs `pip install 'jaxdrake[mujoco]'`), links placed by jaxdrake's kinematics."""
        return self.images(self.frames(traj, fps, single=True)[1])

    def images(self, xs) -> np.ndarray:
        """RGB images (n, height, width, 3) of the states xs (n, num_states), rendered by MuJoCo."""
        from ._puppet import puppet_model, render_frames

        connection = self._connection
        if "puppet" not in connection:
            visuals, materials, resolve = self._urdf_visuals()
            skeleton = {} if any(visuals.values()) else self._skeleton()
            connection["puppet"] = puppet_model(self.links, visuals, materials, resolve, skeleton,
                                                 self._neutral_transforms(), self.tree.has_floating_base)
        model, camera = connection["puppet"]
        return render_frames(model, camera, self.frame_transforms(xs), self.height, self.width)

    def save(self, traj, path, fps=None) -> pathlib.Path:
        """Write the scene with the trajectory's animation as one self-contained `.html` file,
        or a `.gif` / `.mp4` movie rendered by MuJoCo."""
        path = pathlib.Path(path)
        if path.suffix.lower() != ".html":
            return super().save(traj, path, fps)
        meshcat = _meshcat()
        recorder = SceneRecorder()
        live = dict(self._connection)
        self._connection.update(scene=meshcat.Visualizer(window=recorder), loaded=False)
        try:  # the same robot and animation, drawn into a recorder
            first = traj if np.ndim(traj.t_final) == 0 else traj[0]
            self.draw(first.state(first.t0))
            self.animate(traj, fps)
        finally:
            self._connection.update(live)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(scene_html(recorder.commands, title=self.plant_name))
        return path


def scene_html(commands, title: str = "jaxdrake") -> str:
    """A standalone HTML page replaying MeshCat `commands` (lowered dicts) in the viewer, whose
    JavaScript is inlined: it opens offline."""
    import umsgpack

    _meshcat()
    import meshcat.servers.zmqserver as server

    viewer = (pathlib.Path(server.VIEWER_ROOT) / "main.min.js").read_text()
    encoded = ",\n".join(f'"{base64.b64encode(umsgpack.packb(c)).decode()}"' for c in commands)
    return f"""<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>{title}</title>
<style>body {{ margin: 0; }} #meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}</style></head>
<body>
<div id="meshcat-pane"></div>
<script>
{viewer}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
var commands = [
{encoded}
];
for (var i = 0; i < commands.length; i++) {{
  viewer.handle_command_bytearray(Uint8Array.from(atob(commands[i]), function (c) {{ return c.charCodeAt(0); }}));
}}
</script>
</body>
</html>
"""
