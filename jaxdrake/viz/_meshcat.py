r"""3-D scenes of URDF robots in MeshCat, the browser viewer Drake uses (meshcat-python: a
server on 127.0.0.1 that ends with its parent, `_meshcat_server.py`; the three.js viewer in
the browser, no network).

The scene holds each URDF link's `<visual>` elements (boxes, cylinders, spheres; meshes sent
as their files — `.dae`, `.obj`, `.stl` — for the browser to load), or, for a URDF without any visual, a
skeleton: a sphere at each link's origin and a rod to each link attached to it. A state x places every link at its
world pose $T_\ell(q) = [R_\ell(q), p_\ell(q)]$ (`RigidBodySystem.frame_pose`, all links in one
vmappable JAX function, `link_transforms`). A trajectory becomes a MeshCat animation: frames at
$t_k = t_0 + k/\mathrm{fps}$, played by the browser with its own controls; `save(traj,
"robot.html")` writes the scene and the animation as one self-contained file (the viewer's
JavaScript inlined, the commands base64-encoded); `save(traj, "robot.gif")` (or `.mp4`) a movie
of the same visuals rendered offscreen by MuJoCo (`_puppet.py`).

With `contact_forces=True` (a plant with collision geometry) the scene also shows each active
contact as Drake's `ContactVisualizer` does: a dot at the contact point $C$ and an arrow from it
along the force $f$ on the moving geometry (`ContactResults.force`, on the second geometry,
negated where that one is fixed to the world, so ground contacts point up), $|f|$ /
`newtons_per_meter` long; candidates not touching, or whose force is below
`force_threshold`, are hidden. The arrows are animated with the robot (position,
orientation, length, visibility per frame). MuJoCo's movies show the robot only.

The URDF is untrusted input: its XML is read without DTD or entities, its mesh files only from
inside its folder or a `package_map` folder (`jaxdrake.multibody.resolve_model_file`, the
rule `from_urdf` follows), and its names reach a saved page only escaped or base64-encoded.
"""

from __future__ import annotations

import base64
import html
import io
import pathlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._extras import MissingExtraError
from ..multibody import (ContactModel, KinematicTree, RigidBodySystem, URDFError, body_poses, frame_pose, parse_xml,
                          resolve_model_file)
from . import _meshcat_server
from ._puppet import puppet_model, render_frames
from ._urdf_visuals import SKELETON_COLOR, link_color, skeleton_radii
from ._visualizer import DRAW_PERIOD, Visualizer, _in_notebook, batched

_FORCE = 0x2CA02C
# contact arrows (m): shaft and dot radii, the head's length and radius (Drake draws 2 mm shafts)
_SHAFT, _DOT, _HEAD_LENGTH, _HEAD_RADIUS = 0.003, 0.006, 0.02, 0.008


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
        import meshcat.geometry  # noqa: F401
        import yourdfpy  # noqa: F401
    except ImportError as error:
        raise MissingExtraError("a 3-D scene", "meshcat") from error
    return meshcat


def _transform(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _y_onto(d):
    """A rotation taking +y (the axis of three.js cylinders) onto the unit vector d."""
    x = np.cross(d, [0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.cross(d, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, d, np.cross(x, d)])


def _material(color):
    """A MeshCat material of an RGBA colour."""
    import meshcat.geometry as g

    rgb = int(np.round(color[0] * 255)) << 16 | int(np.round(color[1] * 255)) << 8 | int(np.round(color[2] * 255))
    return g.MeshLambertMaterial(color=rgb, opacity=float(color[3]), transparent=bool(color[3] < 1))


def _geometry(visual, mesh_file):
    """(MeshCat geometry, its 4x4 placement in the link frame) of a URDF <visual>; `mesh_file`:
    its mesh's filename -> the file (checked)."""
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
        path = mesh_file(shape.mesh.filename)
        kind = path.suffix.lower().lstrip(".")
        if kind not in ("dae", "obj", "stl"):
            raise ValueError(f"mesh {shape.mesh.filename!r} is a .{kind} file; MeshCat loads .dae, .obj and .stl files")
        contents = path.read_bytes() if kind == "stl" else path.read_text()
        scale = np.ones(3) if shape.mesh.scale is None else np.broadcast_to(np.asarray(shape.mesh.scale, float), 3)
        return g.MeshGeometry(contents, kind), origin @ np.diag([*scale, 1.0])
    raise ValueError(f"a <visual> without geometry ({visual.name})")


class MeshcatVisualizer(Visualizer):
    """A 3-D view of a `RigidBodySystem` (from a URDF) in MeshCat; the same interface as the
    planar visualizers: `draw(x)`, `animate(traj)` (a MeshCat animation in the scene),
    `playback(traj, rate)`, `save(traj, "robot.html")`.

    `scene`: the `meshcat.Visualizer` to draw into (for instance one built on a
    `SceneRecorder` window); by default one that starts its own server at the first draw,
    listening on `host` (127.0.0.1: this machine only) and ending with this process or at
    `close()` (its address: `url()`). `urdf`: the file whose `<visual>` elements to show
    (default: the one the plant was loaded from); its meshes are read from its folder, or
    for `package://NAME/...` from `package_map[NAME]` (default: the plant's, given to
    `from_urdf`), nowhere else.
    `prefix`: the scene path of this robot.
    `save(traj, "robot.gif" or ".mp4")` writes a movie (`width` x `height`) rendered offscreen
    by MuJoCo from the same visuals (`render`, `images`).

    `contact_forces=True` draws the contacts of a plant with collision geometry (module
    docstring): arrows `newtons_per_meter` N per metre (Drake's `ContactVisualizerParams`
    default, 10), forces below `force_threshold` N (0.01) hidden; `contact_arrows(x)` gives
    what is drawn.
    """

    tree: KinematicTree
    contact: ContactModel | None
    links: tuple = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    newtons_per_meter: float = eqx.field(static=True)
    force_threshold: float = eqx.field(static=True)
    _connection: dict = eqx.field(static=True)

    def __init__(self, plant: RigidBodySystem, *, urdf=None, scene=None, prefix: str | None = None,
                 package_map=None, host: str = "127.0.0.1",
                 width: int = 640, height: int = 480, draw_period: float = DRAW_PERIOD,
                 contact_forces: bool = False, newtons_per_meter: float = 10.0, force_threshold: float = 0.01):
        if not isinstance(plant, RigidBodySystem):
            raise TypeError(f"MeshcatVisualizer draws a RigidBodySystem (a URDF robot), not "
                            f"{type(plant).__name__}; use jaxdrake.viz.visualizer_for for the notes' plants")
        if urdf is None and plant.source_format == "mjcf":
            raise ValueError(f"{plant.name} was loaded from an MJCF file, whose visuals MeshCat does not read: draw it "
                             "with jaxdrake.viz.MujocoVisualizer(plant) (MuJoCo's renderer), or pass urdf=PATH")
        urdf = plant.source if urdf is None else urdf
        if urdf is None:
            raise ValueError(f"{plant.name} was not loaded from a URDF file: pass urdf=PATH for its visuals")
        _meshcat()
        super().__init__(plant, draw_period)
        self.tree, self.links = plant.tree, tuple(plant.tree.frame_names)
        self.width, self.height = int(width), int(height)
        if contact_forces and plant.contact is None:
            raise ValueError(f"contact_forces=True: {plant.name} has no collision geometry; load it with "
                             "from_urdf(..., contact=True) or add some with with_collision_geometry / with_ground")
        if not (np.isfinite(newtons_per_meter) and newtons_per_meter > 0 and force_threshold >= 0):
            raise ValueError(f"newtons_per_meter must be positive and force_threshold non-negative, got "
                             f"{newtons_per_meter} and {force_threshold}")
        self.contact = plant.contact if contact_forces else None
        self.newtons_per_meter, self.force_threshold = float(newtons_per_meter), float(force_threshold)
        self._connection = {"urdf": pathlib.Path(urdf), "scene": scene, "package_map": dict(plant.package_map if package_map is None else package_map),
                            "host": str(host), "server": None, "prefix": prefix or plant.name, "loaded": False,
                            "arrows_loaded": False}

    # ----- kinematics (JAX) -----------------------------------------------------------------

    def link_transforms(self, x):
        """The world pose of every link (`links` order) in state x: (num_links, 4, 4)."""
        tree = self.tree
        q = x[: tree.nq]
        poses = body_poses(tree, q)
        R, p = (jnp.stack(part) for part in zip(*(frame_pose(tree, q, link, poses=poses) for link in self.links)))
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], R.dtype), (len(self.links), 1, 4))
        return jnp.concatenate([jnp.concatenate([R, p[:, :, None]], axis=2), bottom], axis=1)

    def frame_transforms(self, xs):
        """`link_transforms` of a batch of states (n, num_states), on the host: (n, links, 4, 4)."""
        xs = jnp.asarray(xs)[..., : self.num_inputs]
        return np.asarray(batched(self, "link_transforms")(xs), dtype=float)  # MeshCat packs Python floats

    def contact_arrows(self, x):
        """What `contact_forces=True` draws in state x: every candidate contact's point C (c, 3),
        force on its moving geometry (c, 3, world: `ContactResults.force`, on the second
        geometry, negated where that one is the world's) and whether it is shown (c,) (JAX)."""
        tree, contact = self.tree, self.contact
        results = contact.results(tree, x[: tree.nq], x[tree.nq: tree.nq + tree.nv])
        on_world = np.asarray(contact.bodies)[np.asarray(results.geometry_b, int)] < 0  # static
        force = results.force * jnp.asarray(np.where(on_world, -1.0, 1.0), results.force.dtype)[:, None]
        shown = results.active & (jnp.sum(force ** 2, axis=-1) > self.force_threshold ** 2)
        return results.point, force, shown

    def _arrow_frames(self, xs):
        """The arrows of a batch of states, on the host: (n, c, 4, 4) placements (origin at C,
        +y along f) and (n, c) lengths (0 where hidden)."""
        xs = jnp.asarray(xs)[..., : self.num_inputs]
        points, forces, shown = (np.asarray(a) for a in batched(self, "contact_arrows")(xs))
        size = np.linalg.norm(forces, axis=-1)
        lengths = np.where(shown, size, 0.0) / self.newtons_per_meter
        placements = np.tile(np.eye(4), points.shape[:2] + (1, 1))
        placements[..., :3, 3] = points
        for k, c in zip(*np.nonzero(shown)):
            placements[k, c, :3, :3] = _y_onto(forces[k, c] / size[k, c])
        return placements.astype(float), lengths.astype(float)

    # ----- the scene --------------------------------------------------------------------------

    @property
    def scene(self):
        """The `meshcat.Visualizer` (started, and the robot's geometry sent, on first use)."""
        connection = self._connection
        if connection["scene"] is None:
            meshcat = _meshcat()
            connection["server"], zmq_url, _ = _meshcat_server.start(connection["host"])
            connection["scene"] = meshcat.Visualizer(zmq_url=zmq_url)
        if not connection["loaded"]:
            self._load(connection["scene"][connection["prefix"]])
            connection["loaded"] = True
        return connection["scene"]

    def url(self) -> str:
        """The address of the live viewer (open it in a browser)."""
        return self.scene.url()

    def close(self) -> None:
        """Stop the server this visualizer started (if any); the next draw starts a new one."""
        connection = self._connection
        if connection["server"] is not None:
            _meshcat_server.stop(connection["server"])
            connection.update(server=None, scene=None, loaded=False, arrows_loaded=False)

    def _urdf_visuals(self):
        """({link: its <visual> elements}, {material name: material}, `mesh_file(link, filename)`)
        of the URDF: the text checked by `parse_xml` (no DTD, no entities), then read by
        yourdfpy from that same text, without touching any file."""
        import yourdfpy

        path = self._connection["urdf"]
        try:
            data = path.read_bytes()
        except OSError as e:
            raise URDFError(f"cannot read URDF {path}: {e}") from None
        parse_xml(data, path, URDFError)
        model = yourdfpy.URDF.load(io.BytesIO(data), build_scene_graph=False, load_meshes=False,
                                   filename_handler=yourdfpy.filename_handler_null)
        return ({link.name: link.visuals for link in model.robot.links}, {m.name: m for m in model.robot.materials},
                self._mesh_file)

    def _mesh_file(self, link: str, filename: str) -> pathlib.Path:
        """The mesh file a `<visual>` of `link` names, inside the URDF's folder or a `package_map`
        folder (else a `URDFError` naming the link and the remedy); a `.dae` (XML) also parsed
        without DTD or entities before a reader sees it."""
        path = resolve_model_file(filename, self._connection["urdf"], f"link {link!r}: <visual> <mesh>", URDFError,
                                  package_map=self._connection["package_map"])
        if path.suffix.lower() == ".dae":
            parse_xml(path.read_bytes(), path, URDFError)
        return path

    def _arrow_nodes(self, count: int):
        """The scene node of this robot's `count` contact arrows (one per candidate contact,
        named by its index); on first use each gets a dot, a shaft (a unit cylinder along +y
        under a node scaled by the arrow's length) and a head (a cone moved to the shaft's end)."""
        import meshcat.geometry as g

        arrows = self.scene["contact_forces"][self._connection["prefix"]]
        if not self._connection["arrows_loaded"]:
            green = g.MeshLambertMaterial(color=_FORCE)
            for c in range(count):
                arrow = arrows[str(c)]
                arrow["dot"].set_object(g.Sphere(_DOT), green)
                arrow["shaft"]["cylinder"].set_object(g.Cylinder(1.0, _SHAFT), green)
                arrow["shaft"]["cylinder"].set_transform(_transform(np.eye(3), [0.0, 0.5, 0.0]))
                arrow["head"]["cone"].set_object(g.Cylinder(_HEAD_LENGTH, radiusTop=0.0, radiusBottom=_HEAD_RADIUS),
                                                 green)
                arrow["head"]["cone"].set_transform(_transform(np.eye(3), [0.0, _HEAD_LENGTH / 2, 0.0]))
            self._connection["arrows_loaded"] = True
        return arrows

    def _load(self, robot):
        import meshcat.geometry as g

        visuals, materials, mesh_file = self._urdf_visuals()
        if any(visuals.values()):
            for i, name in enumerate(self.links):
                for k, visual in enumerate(visuals.get(name, [])):
                    geometry, placement = _geometry(visual, lambda filename: mesh_file(name, filename))
                    robot[name][f"visual{k}"].set_object(geometry, _material(link_color(visual, materials, i)))
                    robot[name][f"visual{k}"].set_transform(placement)
            return
        skeleton = self._skeleton()
        joint_radius, rod_radius = skeleton_radii(skeleton)
        for name in self.links:
            robot[name]["joint"].set_object(g.Sphere(joint_radius), _material(SKELETON_COLOR))
            for k, offset in enumerate(skeleton.get(name, [])):
                length = float(np.linalg.norm(offset))  # a three.js cylinder along y, centred
                robot[name][f"rod{k}"].set_object(g.Cylinder(length, rod_radius), _material(SKELETON_COLOR))
                robot[name][f"rod{k}"].set_transform(_transform(_y_onto(offset / length), offset / 2))

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
        xs = jnp.asarray(x)[None]
        arrows = None if self.contact is None else tuple(a[0] for a in self._arrow_frames(xs))
        self._place(self.frame_transforms(xs)[0], arrows)
        return self.scene

    def _place(self, transforms, arrows=None):
        """Place the links at `transforms` (links, 4, 4) and the contact arrows at (placements
        (c, 4, 4), lengths (c,)), those of length 0 hidden."""
        robot = self.scene[self._connection["prefix"]]
        for name, T in zip(self.links, transforms):
            robot[name].set_transform(T)
        if arrows is None:
            return
        placements, lengths = arrows
        nodes = self._arrow_nodes(len(lengths))
        for c, (T, length) in enumerate(zip(placements, lengths)):
            arrow = nodes[str(c)]
            arrow.set_property("visible", bool(length > 0))
            if length > 0:
                arrow.set_transform(T)
                arrow["shaft"].set_transform(np.diag([1.0, length, 1.0, 1.0]))
                arrow["head"].set_transform(_transform(np.eye(3), [0.0, length, 0.0]))

    def live(self):
        """`show(x, t=None)`: place the robot at state x in the live scene."""
        return lambda x, t=None: self.draw(x)

    def animate(self, traj, fps=None, rate: float = 1.0, ax=None):
        """Send the trajectory to the scene as a MeshCat animation (frames at `fps`, played
        `rate` times faster by the browser, with its own controls), the scene placed at its
        first frame; returns it."""
        from meshcat.animation import Animation

        times, xs, _, fps = self.frames(traj, fps, single=True)
        transforms = self.frame_transforms(xs)
        arrows = None if self.contact is None else self._arrow_frames(xs)
        self._place(transforms[0], None if arrows is None else (arrows[0][0], arrows[1][0]))
        scene = self.scene
        robot = scene[self._connection["prefix"]]
        animation = Animation(default_framerate=fps * rate)
        for k in range(len(times)):
            with animation.at_frame(robot, k) as frame:
                for name, T in zip(self.links, transforms[k]):
                    frame[name].set_transform(T)
        if arrows is not None:  # the candidates that touch at some frame; the others stay hidden
            placements, lengths = arrows
            nodes = self._arrow_nodes(lengths.shape[1])
            for c in np.nonzero(np.any(lengths > 0, axis=0))[0]:
                for k in range(len(times)):
                    with animation.at_frame(nodes[str(c)], k) as frame:
                        frame.set_property("visible", "boolean", bool(lengths[k, c] > 0))
                        frame.set_transform(placements[k, c])
                        frame["shaft"].set_property("scale", "vector3", [1.0, max(lengths[k, c], 1e-9), 1.0])
                        frame["head"].set_property("position", "vector3", [0.0, lengths[k, c], 0.0])
        scene.set_animation(animation, play=True, repetitions=1)
        return animation

    def playback(self, traj, rate: float = 1.0, fps=None):
        """Play the trajectory (real time, `rate` times faster): inline in a notebook (returns the
        self-contained scene of `save(..., ".html")` to display, no server), else in the live
        viewer (returns its URL)."""
        if _in_notebook():
            from IPython.display import HTML

            page = html.escape(self._page(traj, fps, rate))  # as an attribute's text
            return HTML(f'<div><iframe srcdoc="{page}" style="width: 100%; height: {self.height}px; '
                        'border: none"></iframe></div>')
        self.animate(traj, fps, rate)
        return self.url()

    def render(self, traj, fps=None):
        """The movie's frames (n, height, width, 3): the robot's visuals rendered offscreen by
        MuJoCo (needs `pip install 'jaxdrake[mujoco]'`), links placed by jaxdrake's kinematics."""
        return self.images(self.frames(traj, fps, single=True)[1])

    def images(self, xs) -> np.ndarray:
        """RGB images (n, height, width, 3) of the states xs (n, num_states), rendered by MuJoCo."""
        connection = self._connection
        if "puppet" not in connection:
            visuals, materials, mesh_file = self._urdf_visuals()
            skeleton = {} if any(visuals.values()) else self._skeleton()
            connection["puppet"] = puppet_model(self.links, visuals, materials, mesh_file, skeleton,
                                                 self._neutral_transforms())
        model, camera = connection["puppet"]
        return render_frames(model, camera, self.frame_transforms(xs), self.height, self.width,
                             follow=self.tree.layout.num_floating == 1 and self.tree.parents.count(-1) == 1)

    def save(self, traj, path, fps=None) -> pathlib.Path:
        """Write the scene with the trajectory's animation as one self-contained `.html` file,
        or a `.gif` / `.mp4` movie rendered by MuJoCo."""
        path = pathlib.Path(path)
        if path.suffix.lower() != ".html":
            return super().save(traj, path, fps)
        page = self._page(traj, fps)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(page)
        return path

    def _page(self, traj, fps=None, rate: float = 1.0) -> str:
        """The scene with the trajectory's animation as a self-contained HTML page."""
        meshcat = _meshcat()
        recorder = SceneRecorder()
        live = dict(self._connection)
        self._connection.update(scene=meshcat.Visualizer(window=recorder), loaded=False, arrows_loaded=False)
        try:  # the same robot and animation, drawn into a recorder
            self.animate(traj, fps, rate)
        finally:
            self._connection.update(live)
        return scene_html(recorder.commands, title=self.plant_name)


def scene_html(commands, title: str = "jaxdrake") -> str:
    """A standalone HTML page replaying MeshCat `commands` (lowered dicts) in the viewer, whose
    JavaScript is inlined: it opens offline. The title (a robot's name) is escaped; the
    commands travel base64-encoded, never as markup."""
    import umsgpack

    _meshcat()
    import meshcat.servers.zmqserver as server

    viewer = (pathlib.Path(server.VIEWER_ROOT) / "main.min.js").read_text()
    encoded = ",\n".join(f'"{base64.b64encode(umsgpack.packb(c)).decode()}"' for c in commands)
    return f"""<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>{html.escape(title)}</title>
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
