r"""The kinematic tree: a URDF (or a Pinocchio model) as arrays, a pytree.

Bodies are numbered depth first from the root, the children of a link in the order their
joints are declared in the file (Drake's and MuJoCo's order; Pinocchio sorts siblings by
joint name instead, see `docs/architecture.md`); body i hangs from body `parents[i]` (-1: the
world) through joint i, placed at (`origin_rotation[i]`, `origin_translation[i]`) in the
parent's frame. Links joined by `fixed` joints are merged into one body (their inertias
added); every URDF link stays available as a named frame. A joint whose parent is an
undeclared link named `world` hangs from the world (as Drake reads such files).

Joint coordinates (`JointType`): revolute / continuous (one angle, rad), prismatic (one
length, m), and a floating base with Pinocchio's parameterization: q = [x, y, z, qx, qy, qz,
qw] (position of the base in the world, unit quaternion of its orientation), v = [v_base;
omega_base], the linear and angular velocity of the base expressed in the base frame.

Static: names, joint types, parent indices, index layout. Leaves (differentiable): joint
axes and placements, masses, centres of mass, inertias, damping, friction, limits, gravity,
and, where a file gives them, rotor inertias (armature) and joint springs.
"""

from __future__ import annotations

import pathlib
import xml.etree.ElementTree as ET

import functools

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._numbers import device_array
from ._files import children_named, read_xml
from ._joints import JointType
from ._spatial import rpy

URDF_JOINT_TYPES = {"revolute": JointType.REVOLUTE, "continuous": JointType.REVOLUTE,
                    "prismatic": JointType.PRISMATIC, "fixed": JointType.FIXED, "floating": JointType.FLOATING}


class URDFError(ValueError):
    """A URDF that cannot describe a kinematic tree (named problem, file)."""


def _movable_joint_types(kinds) -> tuple:
    """`kinds` as `JointType`s (an unknown name refused by `JointType`), none of them fixed."""
    kinds = tuple(JointType(k) for k in kinds)
    if JointType.FIXED in kinds:
        raise ValueError("a KinematicTree holds movable joints only: merge a fixed joint's child into its "
                         "parent body (the URDF and MJCF readers do)")
    return kinds


class KinematicTree(eqx.Module):
    """A tree of rigid bodies as arrays (body i's entries at index i; per-dof entries in
    velocity-coordinate order, per-q entries in position-coordinate order).

    Static: `robot_name`; `body_names[i]` (the URDF link of body i); `joint_names[i]` and
    `joint_types[i]` (the `JointType` of the joint from body i's parent: revolute, prismatic
    or floating);
    `parents[i]` (index of the parent body, -1 the world; parents come first);
    `frame_names[k]` (every URDF link) and `frame_bodies[k]` (the body frame k is fixed to).

    Leaves: `axes[i]` (joint axis, unit, in body i's frame); `origin_rotation[i]`,
    `origin_translation[i]` (body i's joint frame in its parent's frame at q = 0); `mass[i]`,
    `com[i]` (body frame), `inertia[i]` (3x3, about the centre of mass, body axes);
    `frame_rotation[k]`, `frame_translation[k]` (frame k in its body's frame); `damping`,
    `friction`, `effort_limit` (per velocity coordinate); `position_lower`, `position_upper`
    (per position coordinate); `gravity` (3, world).

    Optional leaves (None: none, and nothing computed for them), per velocity coordinate:
    `armature`, a rotor's inertia reflected through its transmission onto the joint (MuJoCo's
    `armature`, Drake's reflected inertia $\\rho = I_{rotor} n^2$, Pinocchio's
    `model.armature`), added to the mass matrix's diagonal, $H + \\mathrm{diag}(\\rho)$ (0 on a
    free body's coordinates: the readers refuse it there, and `aba` leaves it out);
    `spring_stiffness` k and `spring_reference` $q_s$ of joint springs on one-dof joints
    (MuJoCo's `stiffness` and `springref`), the torque $-k (q - q_s)$ (0 on a free body's
    coordinates).
    """

    robot_name: str = eqx.field(static=True)
    body_names: tuple = eqx.field(static=True)
    joint_names: tuple = eqx.field(static=True)
    joint_types: tuple = eqx.field(static=True, converter=_movable_joint_types)
    parents: tuple = eqx.field(static=True)
    frame_names: tuple = eqx.field(static=True)
    frame_bodies: tuple = eqx.field(static=True)
    axes: jnp.ndarray
    origin_rotation: jnp.ndarray
    origin_translation: jnp.ndarray
    mass: jnp.ndarray
    com: jnp.ndarray
    inertia: jnp.ndarray
    frame_rotation: jnp.ndarray
    frame_translation: jnp.ndarray
    damping: jnp.ndarray
    friction: jnp.ndarray
    position_lower: jnp.ndarray
    position_upper: jnp.ndarray
    effort_limit: jnp.ndarray
    gravity: jnp.ndarray
    armature: jnp.ndarray | None = None
    spring_stiffness: jnp.ndarray | None = None
    spring_reference: jnp.ndarray | None = None

    @property
    def num_bodies(self) -> int:
        return len(self.joint_types)

    @property
    def q_starts(self) -> tuple:
        return tuple(np.cumsum([0] + [k.num_positions for k in self.joint_types])[:-1].tolist())

    @property
    def v_starts(self) -> tuple:
        return tuple(np.cumsum([0] + [k.num_velocities for k in self.joint_types])[:-1].tolist())

    @property
    def nq(self) -> int:
        return sum(k.num_positions for k in self.joint_types)

    @property
    def nv(self) -> int:
        return sum(k.num_velocities for k in self.joint_types)

    @property
    def has_floating_base(self) -> bool:
        """Whether any body is free (a floating joint)."""
        return JointType.FLOATING in self.joint_types

    def position_names(self) -> tuple:
        return tuple(n for name, kind in zip(self.joint_names, self.joint_types) for n in kind.position_names(name))

    def velocity_names(self) -> tuple:
        return tuple(n for name, kind in zip(self.joint_names, self.joint_types) for n in kind.velocity_names(name))

    def neutral_configuration(self):
        """q with every joint at zero (the identity quaternion for a floating base)."""
        return jnp.asarray(np.array([c for kind in self.joint_types for c in kind.neutral_position], float))

    def spring_torque(self, q):
        """$-k (q - q_s)$ of the joint springs (per velocity coordinate; None without springs)."""
        if self.spring_stiffness is None:
            return None
        return -self.spring_stiffness * self._spring_stretch(q)

    def spring_energy(self, q):
        r"""$\tfrac12 \sum k (q - q_s)^2$ of the joint springs (0.0 without springs)."""
        if self.spring_stiffness is None:
            return 0.0
        return 0.5 * jnp.sum(self.spring_stiffness * self._spring_stretch(q) ** 2)

    def _spring_stretch(self, q):
        return self.joint_positions(q) - self.spring_reference

    def joint_positions(self, q):
        """q per velocity coordinate: a one-dof joint's position at its coordinate (a free
        body's coordinates hold its first positions: the springs, actuators and tendons act on
        hinges and slides alone)."""
        return q[np.asarray(self.position_of_velocity)]

    @property
    def position_of_velocity(self) -> tuple:
        """Each velocity coordinate's position coordinate: a one-dof joint's own; a free body's
        (whose coordinates differ) its first."""
        return tuple(int(q) for kind, q in zip(self.joint_types, self.q_starts) for _ in range(kind.num_velocities))

    @property
    def layout(self) -> "TreeLayout":
        """The static index layout the algorithms use (cached per tree structure)."""
        return tree_layout(self.parents, self.joint_types)


class TreeLayout:
    """The tree's structure as static index arrays, for the level-by-level algorithms.

    The algorithms work in *level order* (breadth first: the bodies of tree depth 0, then
    depth 1, ...), so that each depth is a contiguous slice and one batched operation.

    - `order[k]`: the body (tree index) at level-order position k; `position[i]` its inverse.
    - `levels[d]`: the slice of level-order positions at depth d.
    - `subtree[j, i]`: 1 where body i (level order) is in the subtree of body j (itself included).
    - `num_floating`: the free bodies (floating joints; only roots may have one), at
      positions 0 .. num_floating - 1, depth 0, each with position coordinates `free_q[k]`
      (7: x, y, z, then the quaternion) and velocity coordinates `free_v[k]` (6: linear, then
      angular, in its frame), and `free_root[i]` the free body k whose subtree holds tree body
      i (-1: none, it hangs from the world); with any of them, the
      other roots (joined to the world) count as depth 1, children of the world. The other
      bodies have one degree of freedom each, `revolute[k]` (1.0) or prismatic (0.0), with
      position coordinate `q_index[k]` (k over the one-dof bodies in level order).
    - `dof_body[c]`: the level-order position of the body that velocity coordinate c
      (the tree's own coordinate order) belongs to; `dof_level_order[c]`: c's place in the
      level-ordered list of velocity coordinates (the free bodies' six each first, then one
      per body); `level_dofs` its inverse (the coordinate at each level-ordered place).
    - `ancestor[c, c']`: 1 where coordinate c' belongs to an ancestor of (or the same body as)
      coordinate c's body.

    For the sweeps that recurse over depth (a `lax.scan`, one step per depth), the depths
    from `first_scanned` on (1 with free bodies, which are handled on their own; else 0) are
    padded to the widest, `width`: `slots[d, w]` is the level-order position in slot w of
    scanned depth d (n: an empty slot), `valid[d, w]` whether it is a body, `parent_of_slot[d, w]`
    the slot of the depth above that holds its parent (without free bodies, depth 0's parent,
    the world, is slot 0; with them, the free bodies are slots 0 .. num_floating - 1 and the
    world is slot num_floating; empty slots point at 0),
    and `unslot[k]` the flat padded index of level-order position k >= `first_scanned`'s start.
    """

    def __init__(self, parents, joint_types):
        n = len(parents)
        free = [kind == JointType.FLOATING for kind in joint_types]
        if any(f and p != -1 for f, p in zip(free, parents)):
            raise ValueError("only a root body (parent -1) may have a floating joint")
        self.num_floating = F = sum(free)
        depth = []
        for i, p in enumerate(parents):
            if not p < i:
                raise ValueError(f"body {i}'s parent {p} does not come before it")
            depth.append(depth[p] + 1 if p >= 0 else (0 if free[i] or not F else 1))
        depth = np.asarray(depth, int)
        self.order = np.argsort(depth, kind="stable")
        self.position = np.empty(n, int)
        self.position[self.order] = np.arange(n)
        counts = np.bincount(depth) if n else np.zeros(0, int)
        starts = np.concatenate([[0], np.cumsum(counts)])
        self.levels = tuple(slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:]))
        self.subtree = np.zeros((n, n))
        for i in range(n):  # walk up from every body
            j = i
            while j >= 0:
                self.subtree[self.position[j], self.position[i]] = 1.0
                j = parents[j]
        roots, one_dof = self.order[:F], self.order[F:]
        # tree order: the free body (level positions 0 .. F-1) whose subtree holds it, or -1
        held = self.subtree[:F, self.position]
        self.free_root = np.where(held.any(axis=0), held.argmax(axis=0), -1) if F else np.full(n, -1, int)
        dofs = [k.num_velocities for k in joint_types]
        v_starts = np.concatenate([[0], np.cumsum(dofs)])[:-1].astype(int)
        q_starts = np.concatenate([[0], np.cumsum([k.num_positions for k in joint_types])])[:-1]
        self.free_q = q_starts[roots].astype(int)[:, None] + np.arange(7)
        self.free_v = v_starts[roots].astype(int)[:, None] + np.arange(6)
        self.revolute = np.array([joint_types[i] == JointType.REVOLUTE for i in one_dof], float)
        self.q_index = q_starts[one_dof].astype(int)
        self.v_index = v_starts[one_dof].astype(int)
        nv = int(sum(dofs))
        self.dof_body = np.zeros(nv, int)
        self.dof_level_order = np.zeros(nv, int)
        for i in range(n):
            self.dof_body[v_starts[i]: v_starts[i] + dofs[i]] = self.position[i]
        level_dofs = list(self.free_v) + [[v_starts[i]] for i in one_dof]
        level_dofs = np.concatenate(level_dofs).astype(int) if level_dofs else np.zeros(0, int)
        self.dof_level_order[level_dofs] = np.arange(nv)
        self.level_dofs = level_dofs
        self.ancestor = self.subtree[self.dof_body[None, :], self.dof_body[:, None]]

        self.first_scanned = int(F > 0)
        scanned = self.levels[self.first_scanned:]
        world_children = F > 0 and any(p < 0 and not f for p, f in zip(parents, free))
        self.width = max(max((lv.stop - lv.start for lv in scanned), default=0), F + world_children)
        self.slots = np.full((len(scanned), self.width), n, int)
        self.parent_of_slot = np.zeros((len(scanned), self.width), int)
        for d, level in enumerate(scanned):
            count = level.stop - level.start
            self.slots[d, :count] = np.arange(level.start, level.stop)
            depth_above = d + self.first_scanned - 1
            for w in range(count):
                parent = parents[self.order[level.start + w]]
                if parent < 0:   # the world: with free bodies, the slot beside theirs
                    j = F
                else:
                    j = self.position[parent] - self.levels[depth_above].start
                self.parent_of_slot[d, w] = j
        self.valid = self.slots < n
        flat = np.full(n, -1, int)
        flat[self.slots[self.valid]] = np.nonzero(self.valid.ravel())[0]
        self.unslot = flat[self.levels[self.first_scanned].start:] if scanned else np.zeros(0, int)
        # int32 index arrays: indexing a JAX array with an int64 numpy array inside
        # `jax.enable_x64(True)` (trajectory optimization's programs) leaves jax 0.10's index
        # conversion cached as int64, and the same indexing outside x64 then fails
        for name, value in vars(self).items():
            if isinstance(value, np.ndarray) and value.dtype.kind == "i":
                setattr(self, name, value.astype(np.int32))


@functools.lru_cache(maxsize=256)
def tree_layout(parents: tuple, joint_types: tuple) -> TreeLayout:
    return TreeLayout(parents, joint_types)


# ----- URDF ---------------------------------------------------------------------------------

def read_urdf(path) -> ET.Element:
    """The URDF's root `<robot>` element, parsed as untrusted XML (`_files.parse_xml`: no
    DOCTYPE, no entities)."""
    path = pathlib.Path(path)
    root = read_xml(path, URDFError)
    if root.tag != "robot":
        raise URDFError(f"{path}: the root element is <{root.tag}>, not <robot>")
    return root


def _numbers(element, name, count, default, path, where):
    """`count` floats from attribute `name` of `element` (`default` when absent), or a
    URDFError naming the file, the element, the attribute and the text."""
    text = element.get(name) if element is not None else None
    if text is None:
        return np.array(default, float)
    try:
        values = np.array([float(v) for v in text.split()], float)
    except ValueError:
        values = None
    if values is None or values.size != count or not np.all(np.isfinite(values) | (values.size == 1)):
        tag = element.tag
        raise URDFError(f"{path}: {where}: <{tag} {name}={text!r}> is not {count} number"
                        f"{'s' if count > 1 else ''}")
    return values if count > 1 else values[0]


def tree_from_urdf(path, *, floating_base: bool = False, gravity=(0.0, 0.0, -9.81), welded=()):
    """Parse a URDF into a `KinematicTree`; also returns the names of the joints its
    `<transmission>`s actuate (empty without transmissions). Joints named in `welded` are
    treated as fixed at zero (e.g. a gripper's fingers)."""
    path = pathlib.Path(path)
    root = read_urdf(path)

    links = {}
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise URDFError(f"{path}: a <link> has no name")
        if name in links:
            raise URDFError(f"{path}: link {name!r} is defined twice")
        links[name] = _inertial(link, path)
    joints = []
    children = set()
    free_joints = {}  # <joint type="floating"> from the world: child link -> joint name
    for joint in root.findall("joint"):
        name, kind = joint.get("name"), URDF_JOINT_TYPES.get(joint.get("type"))
        where = f"joint {name!r}"
        if kind is None:
            raise URDFError(f"{path}: joint {name!r} has type {joint.get('type')!r}; supported: revolute, "
                            "continuous, prismatic, fixed, and floating from the world (a floating base)")
        unlimited = joint.get("type") == "continuous"  # URDF's revolute joint without limits
        parent, child = joint.find("parent"), joint.find("child")
        parent = parent.get("link") if parent is not None else None
        child = child.get("link") if child is not None else None
        if kind == JointType.FLOATING:
            if parent != "world":
                raise URDFError(f"{path}: joint {name!r} is floating between two links ({parent!r} and {child!r}); "
                                "a floating joint frees a body from the world: give it the parent 'world'")
            if child not in links:
                raise URDFError(f"{path}: joint {name!r} names child link {child!r}, which is not defined")
            if child in children or child in free_joints:
                raise URDFError(f"{path}: link {child!r} is the child of two joints (a kinematic loop; "
                                "declare loops as constraints instead)")
            free_joints[child] = name
            continue
        if parent == "world" and "world" not in links:  # Drake's convention: the world itself
            links["world"] = (0.0, np.zeros(3), np.zeros((3, 3)))
        for role, link in (("parent", parent), ("child", child)):
            if link not in links:
                raise URDFError(f"{path}: joint {name!r} names {role} link {link!r}, which is not defined")
        if child in children or child in free_joints:
            raise URDFError(f"{path}: link {child!r} is the child of two joints (a kinematic loop; "
                            "declare loops as constraints instead)")
        children.add(child)
        axis = _numbers(joint.find("axis"), "xyz", 3, [1.0, 0.0, 0.0], path, where)
        if kind != JointType.FIXED and not np.linalg.norm(axis) > 0:
            raise URDFError(f"{path}: joint {name!r} has a zero axis")
        limit, dynamics = joint.find("limit"), joint.find("dynamics")
        number = lambda element, attribute, default: _numbers(element, attribute, 1, default, path, where)
        joints.append(dict(
            name=name, type=JointType.FIXED if name in welded else kind, parent=parent, child=child,
            origin=_origin(joint.find("origin"), path, where), axis=axis / max(np.linalg.norm(axis), 1e-300),
            lower=-np.inf if unlimited else number(limit, "lower", -np.inf),
            upper=np.inf if unlimited else number(limit, "upper", np.inf),
            effort=number(limit, "effort", np.inf),
            damping=number(dynamics, "damping", 0.0), friction=number(dynamics, "friction", 0.0)))
    if free_joints and "world" not in links:
        links["world"] = (0.0, np.zeros(3), np.zeros((3, 3)))
    roots = [name for name in links if name not in children and name not in free_joints]
    if not roots:
        raise URDFError(f"{path}: no root link (a link that is no joint's child): the joints form a cycle")
    # the fixed root (the world's frame): 'world' if the file names it, else the robot's root
    # link unless floating_base; every other root floats, as in Drake
    if "world" in roots:
        roots.remove("world")
        fixed = "world"
        if floating_base and not roots:
            raise URDFError(f"{path}: the tree hangs from the world (its root joints name the parent "
                            "'world'), so it cannot have a floating base; load it without floating_base")
        names = {link: link for link in roots}
    else:
        fixed = None if floating_base else roots[0]
        names = {link: ("floating_base" if floating_base and i == 0 else link)
                 for i, link in enumerate(roots) if link != fixed}
    names.update(free_joints)
    free = {link: names[link] for link in links if link in names}   # in the file's order of links
    known = {j["name"]: j for j in joints}
    for name in welded:
        if name not in known:
            raise URDFError(f"{path}: cannot weld joint {name!r}: it is not defined")
    actuated = []
    for transmission in root.findall("transmission"):
        reflected = _reflected_inertia(transmission, path)
        for joint in transmission.findall("joint"):
            name = joint.get("name")
            if name not in known:
                raise URDFError(f"{path}: a <transmission> actuates joint {name!r}, which is not defined")
            if name not in welded:
                actuated.append(name)
                known[name]["armature"] = known[name].get("armature", 0.0) + reflected
    tree = _build_tree(root.get("name") or path.stem, fixed, free, links, joints, np.asarray(gravity, float), path)
    return tree, tuple(actuated)


def _reflected_inertia(transmission, path) -> float:
    r"""A transmission's reflected inertia $\rho = I_{rotor} n^2$ from its actuators'
    `<drake:rotor_inertia value>` and `<drake:gear_ratio value>` (Drake's URDF extension;
    0 and 1 where absent), the armature of the joint it drives."""
    where = f"<transmission name={transmission.get('name')!r}>"
    total = 0.0
    for actuator in transmission.findall("actuator"):
        value = lambda tag, default: [_numbers(e, "value", 1, default, path, where)  # noqa: E731
                                      for e in children_named(actuator, tag)] or [default]
        rotor, gear = value("drake:rotor_inertia", 0.0)[0], value("drake:gear_ratio", 1.0)[0]
        if not rotor >= 0:
            raise URDFError(f"{path}: {where}: <drake:rotor_inertia value={rotor}> must be >= 0")
        total += rotor * gear ** 2
    return total


def urdf_mimic_joints(path, welded=()) -> tuple:
    """The URDF's `<mimic joint=... multiplier=... offset=...>` elements as (follower, leader,
    multiplier, offset) tuples: the follower's position is multiplier * leader's + offset
    (defaults 1 and 0, as urdfdom's). Fixed followers and those named in `welded` are left out."""
    path = pathlib.Path(path)
    root = read_urdf(path)
    defined = {joint.get("name") for joint in root.findall("joint")}
    couplings = []
    for joint in root.findall("joint"):
        mimic, name = joint.find("mimic"), joint.get("name")
        if mimic is None or name in welded or URDF_JOINT_TYPES.get(joint.get("type")) == JointType.FIXED:
            continue
        where = f"joint {name!r}"
        leader = mimic.get("joint")
        if leader not in defined:
            raise URDFError(f"{path}: {where}: <mimic joint={leader!r}> names a joint the file does not define")
        couplings.append((name, leader, float(_numbers(mimic, "multiplier", 1, 1.0, path, where)),
                          float(_numbers(mimic, "offset", 1, 0.0, path, where))))
    return tuple(couplings)


def _origin(element, path, where):
    xyz = _numbers(element, "xyz", 3, [0.0, 0.0, 0.0], path, where)
    angles = _numbers(element, "rpy", 3, [0.0, 0.0, 0.0], path, where)
    return np.asarray(rpy(*angles)), xyz


def _inertial(link, path):
    inertial = link.find("inertial")
    if inertial is None:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    name = link.get("name")
    where = f"link {name!r}"
    mass = _numbers(inertial.find("mass"), "value", 1, 0.0, path, where)
    R, com = _origin(inertial.find("origin"), path, where)
    i = inertial.find("inertia")
    get = lambda k: _numbers(i, k, 1, 0.0, path, where)
    I = np.array([[get("ixx"), get("ixy"), get("ixz")], [get("ixy"), get("iyy"), get("iyz")],
                  [get("ixz"), get("iyz"), get("izz")]])
    problem = _inertia_problem(mass, I, triangle=False)  # the triangle inequality: per body, once merged
    if problem:
        raise URDFError(f"{path}: link {name!r} {problem}; fix its <inertial> (the mass and the moments "
                        "of the solid it describes, e.g. from the CAD model)")
    return mass, com, R @ I @ R.T


def _inertia_problem(mass, inertia, *, triangle: bool):
    """Why a mass and a rotational inertia (about the centre of mass) belong to no rigid body,
    or None: a mass that is negative or not finite; an inertia not finite, or not positive
    semi-definite; with `triangle`, principal moments breaking the triangle inequality
    $I_1 + I_2 \\ge I_3$ (every body's moments obey it; relative tolerance 1e-6, absolute 1e-12)."""
    if not (np.isfinite(mass) and mass >= 0):
        return f"has mass {mass}; a mass is a finite number >= 0"
    if not np.all(np.isfinite(inertia)):
        return f"has an inertia with non-finite entries {np.asarray(inertia).tolist()}"
    eig = np.linalg.eigvalsh(inertia)
    tolerance = 1e-12 * max(1.0, np.max(np.abs(eig)))  # rounding in the file's digits
    if np.any(eig < -tolerance):
        return f"has an inertia that is not positive semi-definite (principal moments {eig})"
    if triangle and eig[0] + eig[1] < eig[2] * (1 - 1e-6) - tolerance:
        return (f"has principal moments of inertia {eig} that break the triangle inequality "
                f"(I1 + I2 = {eig[0] + eig[1]:.6g} < I3 = {eig[2]:.6g}: no mass distribution has them)")
    return None


def _combine(m1, c1, I1, m2, c2, I2):
    """Two rigidly joined inertias (in one frame) as one: masses add, the parallel-axis theorem."""
    m = m1 + m2
    c = (m1 * c1 + m2 * c2) / m if m > 0 else np.zeros(3)
    shift = lambda mi, d: mi * (np.dot(d, d) * np.eye(3) - np.outer(d, d))
    return m, c, I1 + shift(m1, c1 - c) + I2 + shift(m2, c2 - c)


def _build_tree(robot_name, fixed, free, links, joints, gravity, path):
    """The tree of the fixed root link `fixed` (the world's frame; None: none) and of the free
    root links `free` (link -> its floating joint's name), each root's subtree after it."""
    by_parent = {}
    for j in joints:
        by_parent.setdefault(j["parent"], []).append(j)
    bodies = []      # dicts: name, joint, type, parent, R, p, axis, inertial
    link_body = {}   # link -> (body index, R, p of the link in the body frame)
    joint_names = {j["name"] for j in joints if j["type"] != JointType.FIXED}   # the moving joints
    for root in ([fixed] if fixed is not None else []) + list(free):
        if root == fixed:
            link_body[root] = (-1, np.eye(3), np.zeros(3))
        else:
            if free[root] in joint_names:
                raise URDFError(f"{path}: link {root!r} floats, and its floating joint would be named "
                                f"{free[root]!r}, which a joint of the file already is: rename that joint")
            bodies.append(dict(link=root, joint=free[root], type=JointType.FLOATING, parent=-1,
                               R=np.eye(3), p=np.zeros(3), axis=np.zeros(3), inertial=links[root],
                               lower=-np.inf, upper=np.inf, effort=np.inf, damping=0.0, friction=0.0))
            link_body[root] = (len(bodies) - 1, np.eye(3), np.zeros(3))
        stack = list(reversed(by_parent.get(root, [])))
        while stack:  # depth first, the children of a link in the order the file declares their joints
            j = stack.pop()
            body, R_lb, p_lb = link_body[j["parent"]]
            R_o, p_o = j["origin"]
            R, p = R_lb @ R_o, R_lb @ p_o + p_lb  # the joint frame in the parent body's frame
            if j["type"] == JointType.FIXED:
                link_body[j["child"]] = (body, R, p)
                if body >= 0:  # merge the child's inertia into the body
                    m, c, I = links[j["child"]]
                    bodies[body]["inertial"] = _combine(*bodies[body]["inertial"], m, R @ c + p, R @ I @ R.T)
            else:
                bodies.append(dict(link=j["child"], joint=j["name"], type=j["type"], parent=body, R=R, p=p,
                                   axis=j["axis"], inertial=links[j["child"]], lower=j["lower"],
                                   upper=j["upper"], effort=j["effort"], damping=j["damping"],
                                   friction=j["friction"], armature=j.get("armature", 0.0)))
                link_body[j["child"]] = (len(bodies) - 1, np.eye(3), np.zeros(3))
            stack.extend(reversed(by_parent.get(j["child"], [])))
    if len(link_body) != len(links):
        missing = sorted(set(links) - set(link_body))
        raise URDFError(f"{path}: links {missing} are not connected to any root (the joints form a cycle)")
    if not bodies:
        if fixed not in (None, "world"):
            raise URDFError(f"{path}: the URDF has no movable joint: its root link {fixed!r} is fixed as the world's "
                            "frame (floating_base=False, the default); from_urdf(..., floating_base=True) makes it a "
                            "free body, as Drake's parser does for a root link that no joint holds")
        raise URDFError(f"{path}: the URDF has no movable joint: every link is welded to the world")
    frames = [(name, body, R, p) for name, (body, R, p) in link_body.items()]   # body -1: the world
    return assemble_tree(robot_name, bodies, frames, gravity, path)


def assemble_tree(robot_name, bodies, frames, gravity, path, error=URDFError) -> KinematicTree:
    """The `KinematicTree` of `bodies` (dicts: link, joint, type, parent, R, p, axis,
    inertial = (mass, com, inertia), lower, upper, effort, damping, friction; optionally
    armature, stiffness and spring_reference, 0 where absent; parents first) and
    `frames` ((name, body, R, p), body -1 the world), shared by the URDF and MJCF readers.
    Physically impossible bodies and joints are refused here with `error` (`_check_bodies`)."""
    _check_bodies(bodies, path, error)
    _check_every_joint_moves_mass(bodies, path)
    floats = lambda values: device_array(values, float)  # converted on the host: nothing to compile
    arr = lambda key: floats([b[key] for b in bodies])
    per_q = lambda key: floats(np.concatenate([[b[key]] * JointType(b["type"]).num_positions for b in bodies]))
    per_dof = lambda key, get=dict.__getitem__: floats(np.concatenate(  # noqa: E731
        [[get(b, key)] * JointType(b["type"]).num_velocities for b in bodies]))
    optional = lambda b, key: b.get(key, 0.0)  # noqa: E731
    given = lambda key: per_dof(key, optional) if any(optional(b, key) != 0 for b in bodies) else None  # noqa: E731
    springs = given("stiffness")
    return KinematicTree(
        robot_name=robot_name, body_names=tuple(b["link"] for b in bodies), joint_names=tuple(b["joint"] for b in bodies),
        joint_types=tuple(b["type"] for b in bodies), parents=tuple(b["parent"] for b in bodies),
        frame_names=tuple(f[0] for f in frames), frame_bodies=tuple(f[1] for f in frames),
        axes=arr("axis"), origin_rotation=arr("R"), origin_translation=arr("p"),
        mass=floats([b["inertial"][0] for b in bodies]),
        com=floats([b["inertial"][1] for b in bodies]),
        inertia=floats([b["inertial"][2] for b in bodies]),
        frame_rotation=floats([f[2] for f in frames]),
        frame_translation=floats([f[3] for f in frames]),
        damping=per_dof("damping"), friction=per_dof("friction"),
        position_lower=per_q("lower"), position_upper=per_q("upper"), effort_limit=per_dof("effort"),
        gravity=floats(gravity), armature=given("armature"), spring_stiffness=springs,
        spring_reference=None if springs is None else per_dof("spring_reference", optional))


def _check_bodies(bodies, path, error):
    """Refuse what no physical joint or body has: a rigid body's (merged) mass and inertia
    (`_inertia_problem`), a negative or non-finite damping or friction, a negative or NaN
    effort limit, a NaN position limit or a lower limit above the upper."""
    for b in bodies:
        problem = _inertia_problem(b["inertial"][0], b["inertial"][2], triangle=True)
        if problem:
            raise error(f"{path}: the rigid body of link {b['link']!r} (with the links welded to it) {problem}; "
                        "fix the inertias of its links")
        where = f"{path}: joint {b['joint']!r}"
        for key in ("damping", "friction", "armature", "stiffness"):
            if not (np.isfinite(b.get(key, 0.0)) and b.get(key, 0.0) >= 0):
                raise error(f"{where} has {key} {b[key]}; it must be a finite number >= 0 (a negative {key} "
                            "feeds energy into the motion): fix it in the file (a URDF's <dynamics>)")
        if JointType(b["type"]) == JointType.FLOATING and (b.get("armature", 0.0) or b.get("stiffness", 0.0)):
            raise error(f"{where} frees a body and has armature or a spring, which the plant models on hinges and "
                        "slides alone: remove them from the free joint")
        if not b["effort"] >= 0:
            raise error(f"{where} has effort limit {b['effort']}; it must be >= 0 (or absent: unlimited)")
        if not b["lower"] <= b["upper"]:
            raise error(f"{where} has lower limit {b['lower']} above upper limit {b['upper']} (or one is NaN); "
                        "swap them, or leave the limits out for an unlimited joint")


def _check_every_joint_moves_mass(bodies, path):
    """A joint whose body and everything beyond it carry no mass and no inertia makes H(q)
    singular (the simulation would stop at t = 0 with a non-finite state): refuse it here."""
    carried = [b["inertial"][0] + np.trace(b["inertial"][2]) for b in bodies]
    for i in reversed(range(len(bodies))):
        if bodies[i]["parent"] >= 0:
            carried[bodies[i]["parent"]] += carried[i]
    for b, amount in zip(bodies, carried):
        if not amount > 0 and b["type"] == JointType.FLOATING:
            raise URDFError(f"{path}: link {b['link']!r} floats (no joint joins it to the world or to another "
                            "link) and has no mass or inertia, nor anything attached to it: give it an <inertial>, "
                            "or join it by a joint")
        if not amount > 0:
            raise URDFError(f"{path}: joint {b['joint']!r} moves link {b['link']!r}, which has no mass "
                            "or inertia, and neither has anything attached beyond it: the mass matrix "
                            "would be singular. Give the link an <inertial>, or make the joint fixed")


# ----- Pinocchio ---------------------------------------------------------------------------


def tree_from_pinocchio(model) -> KinematicTree:
    """A `KinematicTree` from a Pinocchio `pin.Model` (revolute, continuous, prismatic joints
    on any axis, and a free-flyer root as the floating base); its frames become named frames."""
    bodies, q_index = [], []
    for i in range(1, model.njoints):
        joint = model.joints[i]
        kind = joint.shortname()
        if kind == "JointModelFreeFlyer":
            jtype, axis = JointType.FLOATING, np.zeros(3)
        else:
            data = joint.createData()
            joint.calc(data, np.asarray(_pin_neutral(model)))
            S = np.asarray(data.S).ravel()
            if joint.nv != 1 or (np.linalg.norm(S[:3]) > 0) == (np.linalg.norm(S[3:]) > 0):
                raise ValueError(f"Pinocchio joint {model.names[i]!r} ({kind}) is not supported: "
                                 "revolute, continuous, prismatic and free-flyer joints are")
            jtype, axis = ((JointType.PRISMATIC, S[:3]) if np.linalg.norm(S[:3]) > 0
                           else (JointType.REVOLUTE, S[3:]))
        placement, inertia = model.jointPlacements[i], model.inertias[i]
        bodies.append(dict(
            link=model.names[i], joint=model.names[i], type=jtype, parent=model.parents[i] - 1,
            R=np.asarray(placement.rotation), p=np.asarray(placement.translation), axis=axis,
            inertial=(float(inertia.mass), np.asarray(inertia.lever), np.asarray(inertia.inertia))))
        q_index.append((joint.idx_q, joint.nq, joint.idx_v, joint.nv, jtype))
    lower, upper = np.asarray(model.lowerPositionLimit), np.asarray(model.upperPositionLimit)
    q_lower, q_upper = [], []
    for iq, nq, _, _, jtype in q_index:
        if jtype != JointType.FLOATING and nq == 2:  # a continuous joint: (cos, sin) in Pinocchio
            q_lower.append([-np.inf]), q_upper.append([np.inf])
        else:
            q_lower.append(lower[iq: iq + nq]), q_upper.append(upper[iq: iq + nq])
    v_order = np.concatenate([np.arange(iv, iv + nv) for _, _, iv, nv, _ in q_index])
    frames = [(f.name, f.parentJoint - 1, np.asarray(f.placement.rotation), np.asarray(f.placement.translation))
              for f in model.frames if f.parentJoint > 0 or f.name != "universe"]
    dtype_arr = lambda rows: jnp.asarray(np.array(rows, float))
    return KinematicTree(
        robot_name=model.name or "pinocchio_model", body_names=tuple(b["link"] for b in bodies),
        joint_names=tuple(b["joint"] for b in bodies), joint_types=tuple(b["type"] for b in bodies),
        parents=tuple(b["parent"] for b in bodies), frame_names=tuple(f[0] for f in frames),
        frame_bodies=tuple(f[1] for f in frames), axes=dtype_arr([b["axis"] for b in bodies]),
        origin_rotation=dtype_arr([b["R"] for b in bodies]),
        origin_translation=dtype_arr([b["p"] for b in bodies]),
        mass=dtype_arr([b["inertial"][0] for b in bodies]), com=dtype_arr([b["inertial"][1] for b in bodies]),
        inertia=dtype_arr([b["inertial"][2] for b in bodies]),
        frame_rotation=dtype_arr([f[2] for f in frames]), frame_translation=dtype_arr([f[3] for f in frames]),
        damping=jnp.asarray(np.asarray(model.damping)[v_order], float),
        friction=jnp.asarray(np.asarray(model.friction)[v_order], float),
        position_lower=jnp.asarray(np.concatenate(q_lower), float),
        position_upper=jnp.asarray(np.concatenate(q_upper), float),
        effort_limit=jnp.asarray(np.asarray(model.effortLimit)[v_order], float),
        gravity=jnp.asarray(np.asarray(model.gravity.linear), float),
        armature=_pin_armature(model, q_index, v_order))


def _pin_armature(model, q_index, v_order):
    """Pinocchio's `model.armature` per velocity coordinate (None when all zero); refused on a
    free flyer, where the plant does not model it."""
    armature = np.asarray(model.armature, float)[v_order]
    free = np.concatenate([np.arange(iv, iv + nv) for _, _, iv, nv, kind in q_index if kind == JointType.FLOATING]
                          + [np.zeros(0, int)]).astype(int)
    if np.any(np.asarray(model.armature, float)[free] != 0):
        raise ValueError("Pinocchio model: armature on the free flyer's coordinates, which the plant models on "
                         "revolute and prismatic joints alone: set it to zero there")
    return jnp.asarray(armature) if np.any(armature != 0) else None


def _pin_neutral(model):
    import pinocchio as pin
    return pin.neutral(model)
