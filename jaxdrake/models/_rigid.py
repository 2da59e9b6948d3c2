"""Rigid-body plants of the notes, loaded from the URDF files shipped in `models/urdf/`, with
their physical parameters written into the kinematic tree (pytree leaves).

Each is a final subclass of `RigidBodySystem` (Drake's `AcrobotPlant` is a class, too), so
that code which must recognise a model (`jaxdrake.viz.visualizer_for`) asks its type; the
methods that return a modified copy (`with_ground`, `with_collision_geometry`,
`equinox.tree_at`) keep the class.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import final

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._numbers import array_module, device_array
from ..multibody import RigidBodySystem

URDF_DIR = pathlib.Path(__file__).parent / "urdf"


def _adopt(model: RigidBodySystem, plant: RigidBodySystem, **replaced) -> None:
    """Give a model (in its `__init__`) the fields of `plant`, loaded from the model's URDF,
    some `replaced` (its `tree`, with the model's parameters written in): the file's structure,
    actuation and joint-limit gains, the model's masses and lengths."""
    for field in dataclasses.fields(plant):
        setattr(model, field.name, replaced.get(field.name, getattr(plant, field.name)))


def _planar_inertia(xp, I):
    """A rotational inertia I about the y axis (the axis of the planar joints)."""
    return xp.diag(xp.stack([I, I, 0.0 * I]))


@final
class Acrobot(RigidBodySystem):
    r"""The acrobot (Underactuated ch. 3) from `acrobot.urdf`, with Drake's defaults: two links
    hanging from a passive shoulder, the elbow actuated. State $[q_1, q_2, \dot q_1, \dot q_2]$,
    angles from hanging straight down, $q_2$ relative to the upper link; `Ic1`, `Ic2` are the
    moments of inertia about the centres of mass. `l2` places the hand frame."""

    def __init__(self, m1=1.0, m2=1.0, l1=1.0, l2=2.0, lc1=0.5, lc2=1.0, Ic1=0.083, Ic2=0.33, b1=0.1, b2=0.1,
                 g=9.81):
        xp = array_module(m1, m2, l1, l2, lc1, lc2, Ic1, Ic2, b1, b2, g)
        plant = RigidBodySystem.from_urdf(URDF_DIR / "acrobot.urdf")
        tree = plant.tree
        values = (xp.stack([m1, m2]) * 1.0,
                  xp.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]) * xp.stack([lc1, lc2])[:, None],
                  xp.stack([_planar_inertia(xp, Ic1), _planar_inertia(xp, Ic2)]),
                  xp.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]) * l1,
                  xp.stack([b1, b2]) * 1.0, xp.array([0.0, 0.0, -1.0]) * g,
                  _hand_frame(xp, tree, "hand", l2))
        _adopt(self, plant, tree=eqx.tree_at(lambda t: (t.mass, t.com, t.inertia, t.origin_translation, t.damping,
                                                   t.gravity, t.frame_translation), tree, tuple(map(device_array, values))))


@final
class CartPole(RigidBodySystem):
    r"""The cart-pole (Underactuated ch. 3) from `cartpole.urdf`, with Drake's defaults: a cart
    of mass `mc` pushed along x, a pole with a point mass `mp` at distance `l`, theta from
    hanging straight down. State $[x, \theta, \dot x, \dot\theta]$, input the force on the cart
    (unlimited, as in the notes: the URDF's effort limit is not applied)."""

    def __init__(self, mc=10.0, mp=1.0, l=0.5, g=9.81):
        xp = array_module(mc, mp, l, g)
        plant = RigidBodySystem.from_urdf(URDF_DIR / "cartpole.urdf", effort_limits=False)
        tree = plant.tree
        values = (xp.stack([mc, mp]) * 1.0, xp.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]) * l,
                  xp.array([0.0, 0.0, -1.0]) * g, _hand_frame(xp, tree, "pole_tip", l))
        _adopt(self, plant, tree=eqx.tree_at(lambda t: (t.mass, t.com, t.gravity, t.frame_translation), tree,
                                        tuple(map(device_array, values))))


@final
class DoublePendulum(RigidBodySystem):
    """A planar double pendulum of two uniform 1 kg, 1 m rods (`double_pendulum.urdf`), both
    joints actuated; angles from hanging straight down, the second relative to the first."""

    def __init__(self):
        _adopt(self, RigidBodySystem.from_urdf(URDF_DIR / "double_pendulum.urdf"))


def _hand_frame(xp, tree, name, length):
    k = tree.frame_names.index(name)
    if xp is np:
        frames = np.array(tree.frame_translation)
        frames[k] = np.array([0.0, 0.0, -1.0]) * length
        return frames
    return tree.frame_translation.at[k].set(jnp.array([0.0, 0.0, -1.0]) * length)


@final
class Panda(RigidBodySystem):
    """The Franka Emika Panda arm (the notes' "robot manipulators" example, ch. 1: a multi-link
    arm from a URDF), from the `example-robot-data` package (`pip install example-robot-data`;
    installed with the test extras). 7 revolute joints; the two prismatic fingers are welded
    unless `fingers=True`. URDF joint damping included; every joint actuated."""

    def __init__(self, fingers: bool = False):
        import importlib.metadata

        try:
            root = importlib.metadata.distribution("example-robot-data").locate_file(
                "cmeel.prefix/share/example-robot-data/robots")
        except importlib.metadata.PackageNotFoundError:
            raise ImportError("Panda() reads panda.urdf from the example-robot-data package: "
                              "pip install example-robot-data") from None
        welded = () if fingers else ("panda_finger_joint1", "panda_finger_joint2")
        root = pathlib.Path(str(root))  # its meshes are package://example-robot-data/robots/...
        _adopt(self, RigidBodySystem.from_urdf(root / "panda_description/urdf/panda.urdf", welded=welded,
                                               package_map={"example-robot-data": root.parent}))
