r"""The kinematic tree: a URDF (or a Pinocchio model) as arrays, a pytree.

Bodies are numbered so that a parent comes before its children; body i hangs from body
`parents[i]` (-1: the world) through joint i, placed at (`origin_rotation[i]`,
`origin_translation[i]`) in the parent's frame. Links joined by `fixed` joints are merged
into one body (their inertias added); every URDF link stays available as a named frame.

Joint coordinates: revolute / continuous (one angle, rad), prismatic (one length, m), and a
floating base with Pinocchio's parameterization: q = [x, y, z, qx, qy, qz, qw] (position of
the base in the world, unit quaternion of its orientation), v = [v_base; omega_base], the
linear and angular velocity of the base expressed in the base frame.

Static: names, joint types, parent indices, index layout. Leaves (differentiable): joint
axes and placements, masses, centres of mass, inertias, damping, friction, limits, gravity.
"""

from __future__ import annotations

import pathlib
import re
import xml.etree.ElementTree as ET

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._spatial import rpy

JOINT_DOFS = {"revolute": (1, 1), "prismatic": (1, 1), "floating": (7, 6)}
_URDF_TYPES = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic",
               "fixed": "fixed", "floating": "floating"}


class URDFError(ValueError):
    """A URDF that cannot describe a kinematic tree (named problem, file)."""


class KinematicTree(eqx.Module):
    robot_name: str = eqx.field(static=True)
    body_names: tuple = eqx.field(static=True)
    joint_names: tuple = eqx.field(static=True)
    joint_types: tuple = eqx.field(static=True)
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

    @property
    def num_bodies(self) -> int:
        return len(self.joint_types)

    @property
    def q_starts(self) -> tuple:
        return tuple(np.cumsum([0] + [JOINT_DOFS[t][0] for t in self.joint_types])[:-1].tolist())

    @property
    def v_starts(self) -> tuple:
        return tuple(np.cumsum([0] + [JOINT_DOFS[t][1] for t in self.joint_types])[:-1].tolist())

    @property
    def nq(self) -> int:
        return sum(JOINT_DOFS[t][0] for t in self.joint_types)

    @property
    def nv(self) -> int:
        return sum(JOINT_DOFS[t][1] for t in self.joint_types)

    @property
    def has_floating_base(self) -> bool:
        return "floating" in self.joint_types

    def position_names(self) -> tuple:
        names = []
        for name, kind in zip(self.joint_names, self.joint_types):
            names += ([f"{name}_{c}" for c in ("x", "y", "z", "qx", "qy", "qz", "qw")]
                      if kind == "floating" else [name])
        return tuple(names)

    def velocity_names(self) -> tuple:
        names = []
        for name, kind in zip(self.joint_names, self.joint_types):
            names += ([f"{name}_{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
                      if kind == "floating" else [f"{name}dot"])
        return tuple(names)

    def neutral_configuration(self):
        """q with every joint at zero (the identity quaternion for a floating base)."""
        q = jnp.zeros(self.nq)
        for s, kind in zip(self.q_starts, self.joint_types):
            if kind == "floating":
                q = q.at[s + 6].set(1.0)
        return q


# ----- URDF ---------------------------------------------------------------------------------

_FORBIDDEN = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)


def read_urdf_text(path) -> str:
    """The URDF's text, refusing DOCTYPE / ENTITY declarations (entity-expansion bombs,
    external entities that would read files or the network)."""
    path = pathlib.Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise URDFError(f"cannot read URDF {path}: {e}") from None
    if _FORBIDDEN.search(data):
        raise URDFError(f"{path}: XML DOCTYPE / ENTITY declarations are not accepted in a URDF "
                        "(they allow entity-expansion bombs and external entities)")
    return data.decode("utf-8", errors="replace")


def _float_attr(element, name, default=0.0):
    value = element.get(name) if element is not None else None
    return float(default if value is None else value)


def tree_from_urdf(path, *, floating_base: bool = False, gravity=(0.0, 0.0, -9.81), welded=()):
    """Parse a URDF into a `KinematicTree`; also returns the names of the joints its
    `<transmission>`s actuate (empty without transmissions). Joints named in `welded` are
    treated as fixed at zero (e.g. a gripper's fingers)."""
    path = pathlib.Path(path)
    text = read_urdf_text(path)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise URDFError(f"{path}: not well-formed XML: {e}") from None
    if root.tag != "robot":
        raise URDFError(f"{path}: the root element is <{root.tag}>, not <robot>")

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
    for joint in root.findall("joint"):
        name, kind = joint.get("name"), joint.get("type")
        if kind not in _URDF_TYPES or kind == "floating":
            raise URDFError(f"{path}: joint {name!r} has type {kind!r}; supported: revolute, "
                            "continuous, prismatic, fixed (a floating base: from_urdf(..., floating_base=True))")
        parent, child = joint.find("parent"), joint.find("child")
        parent = parent.get("link") if parent is not None else None
        child = child.get("link") if child is not None else None
        for role, link in (("parent", parent), ("child", child)):
            if link not in links:
                raise URDFError(f"{path}: joint {name!r} names {role} link {link!r}, which is not defined")
        if child in children:
            raise URDFError(f"{path}: link {child!r} is the child of two joints (a kinematic loop; "
                            "declare loops as constraints instead)")
        children.add(child)
        axis = np.array([float(a) for a in (joint.find("axis").get("xyz").split()
                                            if joint.find("axis") is not None else "1 0 0".split())])
        if _URDF_TYPES[kind] != "fixed" and not np.linalg.norm(axis) > 0:
            raise URDFError(f"{path}: joint {name!r} has a zero axis")
        limit, dynamics = joint.find("limit"), joint.find("dynamics")
        joints.append(dict(
            name=name, type="fixed" if name in welded else _URDF_TYPES[kind], continuous=kind == "continuous", parent=parent, child=child,
            origin=_origin(joint.find("origin")), axis=axis / max(np.linalg.norm(axis), 1e-300),
            lower=_float_attr(limit, "lower", -np.inf) if kind != "continuous" else -np.inf,
            upper=_float_attr(limit, "upper", np.inf) if kind != "continuous" else np.inf,
            effort=_float_attr(limit, "effort", np.inf),
            damping=_float_attr(dynamics, "damping"), friction=_float_attr(dynamics, "friction")))
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise URDFError(f"{path}: a URDF tree has exactly one root link (a link that is no joint's "
                        f"child); found {roots or 'none (the joints form a cycle)'}")
    known = {j["name"] for j in joints}
    for name in welded:
        if name not in known:
            raise URDFError(f"{path}: cannot weld joint {name!r}: it is not defined")
    actuated = []
    for transmission in root.findall("transmission"):
        for joint in transmission.findall("joint"):
            if joint.get("name") not in welded:
                actuated.append(joint.get("name"))
    for name in actuated:
        if name not in known:
            raise URDFError(f"{path}: a <transmission> actuates joint {name!r}, which is not defined")
    tree = _build_tree(root.get("name") or path.stem, roots[0], links, joints, floating_base,
                       np.asarray(gravity, float), path)
    return tree, tuple(actuated)


def _origin(element):
    xyz = np.array([float(v) for v in element.get("xyz", "0 0 0").split()]) if element is not None else np.zeros(3)
    angles = np.array([float(v) for v in element.get("rpy", "0 0 0").split()]) if element is not None else np.zeros(3)
    return np.asarray(rpy(*angles)), xyz


def _inertial(link, path):
    inertial = link.find("inertial")
    if inertial is None:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    mass = _float_attr(inertial.find("mass"), "value")
    R, com = _origin(inertial.find("origin"))
    i = inertial.find("inertia")
    get = lambda k: _float_attr(i, k)
    I = np.array([[get("ixx"), get("ixy"), get("ixz")], [get("ixy"), get("iyy"), get("iyz")],
                  [get("ixz"), get("iyz"), get("izz")]])
    name = link.get("name")
    if not (mass >= 0 and np.isfinite(mass)):
        raise URDFError(f"{path}: link {name!r} has mass {mass}; it must be >= 0")
    eig = np.linalg.eigvalsh(I)
    tol = 1e-12 * max(1.0, np.max(np.abs(eig)))
    if np.any(eig < -tol) or not np.all(np.isfinite(I)):
        raise URDFError(f"{path}: link {name!r} has an inertia that is not positive semi-definite "
                        f"(principal moments {eig})")
    return mass, com, R @ I @ R.T


def _combine(m1, c1, I1, m2, c2, I2):
    """Two rigidly joined inertias (in one frame) as one: masses add, the parallel-axis theorem."""
    m = m1 + m2
    c = (m1 * c1 + m2 * c2) / m if m > 0 else np.zeros(3)
    shift = lambda mi, d: mi * (np.dot(d, d) * np.eye(3) - np.outer(d, d))
    return m, c, I1 + shift(m1, c1 - c) + I2 + shift(m2, c2 - c)


def _build_tree(robot_name, root, links, joints, floating_base, gravity, path):
    by_parent = {}
    for j in joints:
        by_parent.setdefault(j["parent"], []).append(j)
    bodies = []      # dicts: name, joint, type, parent, R, p, axis, inertial
    frames = []      # (link name, body index, R, p) with body -1 the world
    link_body = {}   # link -> (body index, R, p of the link in the body frame)

    if floating_base:
        bodies.append(dict(link=root, joint="floating_base", type="floating", parent=-1,
                           R=np.eye(3), p=np.zeros(3), axis=np.zeros(3), inertial=links[root],
                           lower=-np.inf, upper=np.inf, effort=np.inf, damping=0.0, friction=0.0))
        link_body[root] = (0, np.eye(3), np.zeros(3))
    else:
        link_body[root] = (-1, np.eye(3), np.zeros(3))
    stack = [root]
    while stack:  # depth first: parents before children
        link = stack.pop()
        body, R_lb, p_lb = link_body[link]
        for j in reversed(by_parent.get(link, [])):
            R_o, p_o = j["origin"]
            R, p = R_lb @ R_o, R_lb @ p_o + p_lb  # the joint frame in the parent body's frame
            if j["type"] == "fixed":
                link_body[j["child"]] = (body, R, p)
                if body >= 0:  # merge the child's inertia into the body
                    m, c, I = links[j["child"]]
                    bodies[body]["inertial"] = _combine(*bodies[body]["inertial"], m, R @ c + p, R @ I @ R.T)
            else:
                bodies.append(dict(link=j["child"], joint=j["name"], type=j["type"], parent=body, R=R, p=p,
                                   axis=j["axis"], inertial=links[j["child"]], lower=j["lower"],
                                   upper=j["upper"], effort=j["effort"], damping=j["damping"],
                                   friction=j["friction"]))
                link_body[j["child"]] = (len(bodies) - 1, np.eye(3), np.zeros(3))
            stack.append(j["child"])
    if len(link_body) != len(links):
        missing = sorted(set(links) - set(link_body))
        raise URDFError(f"{path}: links {missing} are not connected to the root {root!r}")
    if not bodies:
        raise URDFError(f"{path}: the URDF has no movable joint")
    for name, (body, R, p) in link_body.items():
        frames.append((name, body, R, p))
    arr = lambda key: jnp.asarray(np.array([b[key] for b in bodies], float))
    dofs = lambda b: 1 if b["type"] != "floating" else 6
    per_dof = lambda key: jnp.asarray(np.concatenate([[b[key]] * dofs(b) for b in bodies]), float)
    per_q = lambda key: jnp.asarray(np.concatenate([[b[key]] * (1 if b["type"] != "floating" else 7)
                                                    for b in bodies]), float)
    return KinematicTree(
        robot_name=robot_name, body_names=tuple(b["link"] for b in bodies), joint_names=tuple(b["joint"] for b in bodies),
        joint_types=tuple(b["type"] for b in bodies), parents=tuple(b["parent"] for b in bodies),
        frame_names=tuple(f[0] for f in frames), frame_bodies=tuple(f[1] for f in frames),
        axes=arr("axis"), origin_rotation=arr("R"), origin_translation=arr("p"),
        mass=jnp.asarray([b["inertial"][0] for b in bodies], float),
        com=jnp.asarray(np.array([b["inertial"][1] for b in bodies]), float),
        inertia=jnp.asarray(np.array([b["inertial"][2] for b in bodies]), float),
        frame_rotation=jnp.asarray(np.array([f[2] for f in frames]), float),
        frame_translation=jnp.asarray(np.array([f[3] for f in frames]), float),
        damping=per_dof("damping"), friction=per_dof("friction"),
        position_lower=per_q("lower"), position_upper=per_q("upper"), effort_limit=per_dof("effort"),
        gravity=jnp.asarray(gravity, float))


# ----- Pinocchio ---------------------------------------------------------------------------


def tree_from_pinocchio(model) -> KinematicTree:
    """A `KinematicTree` from a Pinocchio `pin.Model` (revolute, continuous, prismatic joints
    on any axis, and a free-flyer root as the floating base); its frames become named frames."""
    bodies, q_index = [], []
    for i in range(1, model.njoints):
        joint = model.joints[i]
        kind = joint.shortname()
        if kind == "JointModelFreeFlyer":
            jtype, axis = "floating", np.zeros(3)
        else:
            data = joint.createData()
            joint.calc(data, np.asarray(_pin_neutral(model)))
            S = np.asarray(data.S).ravel()
            if joint.nv != 1 or (np.linalg.norm(S[:3]) > 0) == (np.linalg.norm(S[3:]) > 0):
                raise ValueError(f"Pinocchio joint {model.names[i]!r} ({kind}) is not supported: "
                                 "revolute, continuous, prismatic and free-flyer joints are")
            jtype, axis = ("prismatic", S[:3]) if np.linalg.norm(S[:3]) > 0 else ("revolute", S[3:])
        placement, inertia = model.jointPlacements[i], model.inertias[i]
        bodies.append(dict(
            link=model.names[i], joint=model.names[i], type=jtype, parent=model.parents[i] - 1,
            R=np.asarray(placement.rotation), p=np.asarray(placement.translation), axis=axis,
            inertial=(float(inertia.mass), np.asarray(inertia.lever), np.asarray(inertia.inertia))))
        q_index.append((joint.idx_q, joint.nq, joint.idx_v, joint.nv, jtype))
    lower, upper = np.asarray(model.lowerPositionLimit), np.asarray(model.upperPositionLimit)
    q_lower, q_upper = [], []
    for iq, nq, _, _, jtype in q_index:
        if jtype != "floating" and nq == 2:  # a continuous joint: (cos, sin) in Pinocchio
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
        gravity=jnp.asarray(np.asarray(model.gravity.linear), float))


def _pin_neutral(model):
    import pinocchio as pin
    return pin.neutral(model)
