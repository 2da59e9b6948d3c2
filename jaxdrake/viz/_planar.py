"""Planar visualizers for the plants of `jd.models`, drawn from the plants' own parameters, and a
projection of any `RigidBodySystem` onto a plane; `visualizer_for(system)` picks one."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..models import Acrobot, BouncingBall, CartPole, CompassGait, DoublePendulum, Pendulum, PlanarQuadrotor, RimlessWheel
from ..multibody import JointType, RigidBodySystem, body_poses, frame_pose
from ..mujoco import MujocoSystem
from ..systems import System
from ._meshcat import MeshcatVisualizer
from ._mujoco import MujocoVisualizer
from ._visualizer import DRAW_PERIOD, Visualizer

ROD = dict(kind="line", color="C0", lw=4, solid_capstyle="round")
JOINTS = dict(kind="points", color="k", ms=6)
MASS = dict(kind="points", color="C3", ms=14)


def _circle(centre, radius, count=40):
    angles = jnp.linspace(0.0, 2 * jnp.pi, count)
    return centre + radius * jnp.stack([jnp.cos(angles), jnp.sin(angles)], 1)


def _ramp(ax, slope, length=40.0):
    """A ramp through the origin, descending to the right at `slope` rad."""
    d = _downhill(slope)
    ends = np.stack([-length * d, length * d])
    ax.fill_between(ends[:, 0], ends[:, 1], ends[:, 1].min() - 50, color="0.85", zorder=0)
    ax.plot(ends[:, 0], ends[:, 1], color="0.4", lw=1.5, zorder=0)


def _downhill(slope):
    return np.array([np.cos(slope), -np.sin(slope)])


def _ramp_marks(slope, travel, spacing=0.5, count=41):
    """Marks every `spacing` m along the ramp, as seen by a walker `travel` down it."""
    along = (np.arange(count) - count // 2) * spacing - np.linalg.norm(travel) % spacing
    return along[:, None] * _downhill(slope)


RAMP_MARKS = dict(kind="points", marker="|", color="0.3", ms=10, mew=1.5)


class PendulumVisualizer(Visualizer):
    """The simple pendulum: a rod from the pivot at the origin to the bob at
    (l sin(theta), -l cos(theta)) (theta = 0 hanging down)."""

    length: float
    STYLES = {"rod": ROD, "bob": MASS, "pivot": JOINTS}

    def __init__(self, plant: Pendulum, draw_period=DRAW_PERIOD):
        self.length = float(plant.l)
        super().__init__(plant, draw_period)

    def shapes(self, x):
        bob = self.length * jnp.stack([jnp.sin(x[0]), -jnp.cos(x[0])])
        return {"rod": jnp.stack([jnp.zeros(2, bob.dtype), bob]), "bob": bob[None], "pivot": jnp.zeros((1, 2), bob.dtype)}

    def view(self):
        r = 1.3 * self.length
        return (-r, r), (-r, r)


class PlanarRigidBodyVisualizer(Visualizer):
    """Any `RigidBodySystem` projected onto a plane (default "xz": world x right, z up, as
    Drake's planar plants): a segment from each body's joint to the joints of its children on
    revolute joints, and to every other frame fixed to it (a hand, a tip); joints as dots."""

    plant: RigidBodySystem
    plane: tuple = eqx.field(static=True)
    links: tuple = eqx.field(static=True)   # (body a or -1, frame index or body b) pairs
    STYLES = {"links": ROD, "joints": JOINTS}

    def __init__(self, plant: RigidBodySystem, plane: str = "xz", draw_period=DRAW_PERIOD):
        axes = {"x": 0, "y": 1, "z": 2}
        if len(plane) != 2 or any(c not in axes for c in plane) or plane[0] == plane[1]:
            raise ValueError(f"plane must name two world axes, e.g. 'xz', got {plane!r}")
        self.plant, self.plane = plant, tuple(axes[c] for c in plane)
        tree = plant.tree
        self.links = tuple(_link_segments(tree))
        super().__init__(plant, draw_period)

    def points(self, x):
        """World positions: every body's joint origin (n, 3) and every frame's origin (f, 3)."""
        tree = self.plant.tree
        q = x[: tree.nq]
        R, p = body_poses(tree, q)
        frames = jnp.stack([frame_pose(tree, q, name, poses=(R, p))[1] for name in tree.frame_names])
        return p, frames

    def shapes(self, x):
        bodies, frames = self.points(x)
        project = lambda v: v[..., jnp.array(self.plane)]
        ends = []
        for a, b, is_frame in self.links:
            start = jnp.zeros(3, x.dtype) if a < 0 else bodies[a]
            ends.append(jnp.stack([start, frames[b] if is_frame else bodies[b]]))
        nan = jnp.full((1, 2), jnp.nan, x.dtype)  # breaks between segments of one polyline
        segments = jnp.concatenate([jnp.concatenate([project(e), nan]) for e in ends]) if ends else nan
        return {"links": segments, "joints": project(bodies)}

    def view(self):
        extent = 1.2 * _reach(self.plant.tree)
        return (-extent, extent), (-extent, extent)


def _link_segments(tree):
    """(start body or -1 for the world origin, end index, end is a frame) for every drawn segment."""
    segments = []
    for i, (parent, kind) in enumerate(zip(tree.parents, tree.joint_types)):
        if kind == JointType.REVOLUTE:
            segments.append((parent, i, False))
    translation = np.asarray(tree.frame_translation)
    for k, body in enumerate(tree.frame_bodies):
        if body >= 0 and np.linalg.norm(translation[k]) > 1e-9:
            segments.append((body, k, True))
    return segments


def _reach(tree):
    """An upper bound on the distance of any frame from the root: the sum of every offset."""
    return float(np.sum(np.linalg.norm(np.asarray(tree.origin_translation), axis=1))
                 + np.max(np.linalg.norm(np.asarray(tree.frame_translation), axis=1), initial=0.0)) or 1.0


class CartPoleVisualizer(PlanarRigidBodyVisualizer):
    """The cart-pole: a cart on a rail (the prismatic x), the pole to its tip frame."""

    STYLES = {"cart": dict(kind="polygon", facecolor="C1", edgecolor="k"), "links": ROD, "joints": JOINTS}

    def shapes(self, x):
        drawn = super().shapes(x)
        cart = drawn["joints"][0]
        corners = jnp.array([[-0.3, -0.15], [0.3, -0.15], [0.3, 0.15], [-0.3, 0.15]], x.dtype)
        return {"cart": cart + corners, **drawn}

    def scenery(self, ax):
        ax.axhline(-0.15, color="0.4", lw=1.5, zorder=0)

    def view(self):
        return (-2.5, 2.5), (-1.0, 1.2)


class BouncingBallVisualizer(Visualizer):
    """The ball (radius r) above the ground; its height is the state's first entry."""

    radius: float
    STYLES = {"ball": dict(kind="polygon", facecolor="C3", edgecolor="k")}

    def __init__(self, plant: BouncingBall, draw_period=DRAW_PERIOD):
        self.radius = float(plant.r)
        super().__init__(plant, draw_period)

    def shapes(self, x):
        return {"ball": _circle(jnp.stack([jnp.zeros_like(x[0]), x[0]]), self.radius)}

    def scenery(self, ax):
        ax.axhspan(-10, 0, color="0.85", zorder=0)

    def view(self):
        return (-3 * self.radius, 3 * self.radius), (-0.5 * self.radius, 7 * self.radius)


class _RampWalker(Visualizer):
    """A walker on a ramp of `slope` rad: the ramp's marks move past as it travels."""

    def ground(self, travel):
        return {"marks": _ramp_marks(self.slope, travel)}


class RimlessWheelVisualizer(_RampWalker):
    """The rimless wheel on its ramp: spokes of length l at 2 alpha apart around the hub, the
    stance spoke at angle theta from vertical, its foot at the origin; in a movie the camera
    follows the wheel, one step length 2 l sin(alpha) down the ramp per impact (the ramp's
    marks move past)."""

    length: float
    slope: float
    num_spokes: int = eqx.field(static=True)
    STYLES = {"spokes": dict(kind="line", color="C0", lw=2), "hub": MASS, "marks": RAMP_MARKS}

    def __init__(self, plant: RimlessWheel, draw_period=DRAW_PERIOD):
        self.length, self.slope, self.num_spokes = float(plant.modes[0].l), float(plant.slope), plant.num_spokes
        super().__init__(plant, draw_period)

    def shapes(self, x):
        l, theta = self.length, x[0]
        hub = l * jnp.stack([jnp.sin(theta), jnp.cos(theta)])
        angles = theta + 2 * jnp.pi / self.num_spokes * jnp.arange(self.num_spokes)
        tips = hub - l * jnp.stack([jnp.sin(angles), jnp.cos(angles)], 1)
        nan = jnp.full_like(hub, jnp.nan)
        spokes = jnp.stack([x for tip in tips for x in (hub, tip, nan)])
        return {"spokes": spokes, "hub": hub[None]}

    def scenery(self, ax):
        _ramp(ax, self.slope)

    def travel(self, traj, times):
        events = traj.events
        sign = np.where(events["transitions"] == 0, 1.0, -1.0)  # step forward / backward
        steps = np.concatenate([[0.0], np.cumsum(sign)])[np.searchsorted(events["times"], times, side="right")]
        step = 2 * self.length * np.sin(np.pi / self.num_spokes)
        return steps[:, None] * step * _downhill(self.slope)

    def view(self):
        l = self.length
        return (-2.5 * l, 3.5 * l), (-2 * l, 2.5 * l)


class CompassGaitVisualizer(_RampWalker):
    """The compass gait on its ramp: the stance foot at the origin, the hip at
    l (sin(stance), cos(stance)) from it, the swing foot at l (sin(swing), cos(swing)) below the
    hip; the legs' and hip's point masses. In a movie the camera follows the walker, each step
    2 l sin(|swing - stance| / 2) long at heel strike (the ramp's marks move past)."""

    length: float
    com: float
    slope: float
    STYLES = {"legs": dict(kind="line", color="C0", lw=3), "hip": MASS,
              "leg_masses": dict(kind="points", color="C1", ms=9), "marks": RAMP_MARKS}

    def __init__(self, plant: CompassGait, draw_period=DRAW_PERIOD):
        stance = plant.modes[0]
        self.length, self.com, self.slope = float(stance.length_leg), float(stance.center_of_mass_leg), float(plant.slope)
        super().__init__(plant, draw_period)

    def shapes(self, x):
        l, b = self.length, self.com
        down = lambda angle: jnp.stack([jnp.sin(angle), jnp.cos(angle)])
        hip = l * down(x[0])
        swing_foot = hip - l * down(x[1])
        legs = jnp.stack([jnp.zeros_like(hip), hip, swing_foot])
        masses = jnp.stack([hip - b * down(x[0]), hip - b * down(x[1])])
        return {"legs": legs, "hip": hip[None], "leg_masses": masses}

    def scenery(self, ax):
        _ramp(ax, self.slope)

    def travel(self, traj, times):
        events = traj.events
        after = events["states"]
        lengths = 2 * self.length * np.sin(np.abs(after[:, 1] - after[:, 0]) / 2) if len(after) else np.zeros(0)
        travelled = np.concatenate([[0.0], np.cumsum(lengths)])[np.searchsorted(events["times"], times, side="right")]
        return travelled[:, None] * _downhill(self.slope)

    def view(self):
        l = self.length
        return (-1.5 * l, 2 * l), (-0.6 * l, 1.4 * l)


class PlanarQuadrotorVisualizer(Visualizer):
    """The planar quadrotor: a body of half-span r at (x, y) rotated by theta, with its rotors."""

    span: float
    STYLES = {"body": dict(kind="line", color="C0", lw=4), "rotors": dict(kind="line", color="C3", lw=2)}

    def __init__(self, plant: PlanarQuadrotor, draw_period=DRAW_PERIOD):
        self.span = float(plant.r)
        super().__init__(plant, draw_period)

    def shapes(self, x):
        r, c, s = self.span, jnp.cos(x[2]), jnp.sin(x[2])
        along, up = jnp.stack([c, s]), jnp.stack([-s, c])
        centre = x[:2]
        ends = jnp.stack([centre - r * along, centre + r * along])
        nan = jnp.full_like(centre, jnp.nan)
        rotors = jnp.stack([p for end in ends for p in (end + 0.08 * up - 0.3 * r * along,
                                                         end + 0.08 * up + 0.3 * r * along, nan)])
        return {"body": ends, "rotors": rotors}

    def view(self):
        return (-2.0, 2.0), (-1.5, 1.5)


# the notes' plants, each drawn from its own parameters (in the x-z plane, the rigid bodies)
_PLANAR_BY_CLASS = {Pendulum: PendulumVisualizer, BouncingBall: BouncingBallVisualizer,
                    RimlessWheel: RimlessWheelVisualizer, CompassGait: CompassGaitVisualizer,
                    PlanarQuadrotor: PlanarQuadrotorVisualizer, CartPole: CartPoleVisualizer,
                    Acrobot: PlanarRigidBodyVisualizer, DoublePendulum: PlanarRigidBodyVisualizer}


def visualizer_for(system: System, *, plane: str | None = None, draw_period=DRAW_PERIOD, camera=-1) -> Visualizer:
    """The visualizer for a plant, chosen by its class: the planar one drawn from its own
    parameters for one of the notes' plants (the pendulum, bouncing ball, rimless wheel,
    compass gait, planar quadrotor, cart-pole, acrobot, double pendulum); for any other
    `RigidBodySystem` a 3-D `MeshcatVisualizer` of its URDF's visuals (MuJoCo's renderer of its
    file for one loaded by `from_mjcf`), or its projection onto `plane` ("xz", "yz", "xy") on
    request (also for one not loaded from a file); MuJoCo's renderer for a `MujocoSystem`
    (`camera`: MuJoCo's, a name or index of the model's cameras; -1 its free camera)."""
    if isinstance(system, RigidBodySystem) and plane is not None:
        return PlanarRigidBodyVisualizer(system, plane, draw_period)
    for kind, make in _PLANAR_BY_CLASS.items():
        if isinstance(system, kind):
            return make(system, draw_period=draw_period)
    if isinstance(system, RigidBodySystem):
        if system.source is None:
            return PlanarRigidBodyVisualizer(system, draw_period=draw_period)
        if system.source_format == "mjcf":
            return MujocoVisualizer(system, draw_period=draw_period, camera=camera)
        return MeshcatVisualizer(system, draw_period=draw_period)
    if isinstance(system, MujocoSystem):
        return MujocoVisualizer(system, draw_period=draw_period, camera=camera)
    raise TypeError(f"no visualizer for {type(system).__name__} ({system.name}); subclass "
                    "jaxdrake.viz.Visualizer (shapes, STYLES, view) to draw it")
