r"""An MJCF model as a kinematic tree, MuJoCo's own compiler as the parser.

`mujoco.MjModel.from_xml_path` compiles the file (defaults, `fromto`, inertias from geoms,
angles in degrees, meshes); the compiled arrays are read here:

- **Bodies.** A body with hinge / slide joints is a chain of tree bodies, one per joint in
  the file's order (all but the last without mass, named `<body>_<joint>`); a body without
  joints is welded to its parent (its inertia merged, as a URDF fixed joint); one with a free
  joint (a body of the worldbody) is a free body, any number of them beside bodies that hang
  from the world (mocap bodies are welded where the file puts them). Every body is a
  named frame (and `world`), at MuJoCo's body frame.
- **Placements, exactly.** MuJoCo moves a body by $X = X_{parent} B \prod_j T(a_j) J_j(q_j -
  q_{0,j}) T(-a_j)$ (`body_pos` / `body_quat` B, joint anchors `jnt_pos` $a_j$ in the body
  frame, `jnt_axis`, the reference `qpos0` from `ref`). The tree's joint frame of joint j is
  placed at $T(a_j)$ (rotated by $-q_{0,j}$ about a hinge's axis, shifted by $-q_{0,j}$ along a
  slide's), so the tree body frame is MuJoCo's body frame shifted by $a_j$; centres of mass,
  children and frames are placed accordingly.
- **Inertia**: `body_mass`, `body_ipos`, `body_iquat`, `body_inertia`. **Gravity**:
  `opt.gravity` (zero when disabled). **Damping**: `dof_damping` (zero when disabled).
  **Armature**: `dof_armature` of hinges and slides, added to the mass matrix's diagonal
  (`KinematicTree.armature`; dropped with `ignore_armature=True`). **Springs**: a hinge's or
  slide's `jnt_stiffness` about `qpos_spring` (`springref`), the torque $-k (q - q_s)$
  (`KinematicTree.spring_stiffness`; none when springs are disabled); a fixed tendon's
  linear spring (`stiffness` about its `springlength`, a dead band where that is a range) and
  damper (`FixedTendons`).
  **Limits**: `jnt_range` of `jnt_limited` joints (the plant's compliant limits, not MuJoCo's
  soft constraints). `dof_frictionloss` is recorded on `tree.friction`, not applied (as a
  URDF's friction).
- **Actuators**: where every actuator is a `<motor>` on a hinge or slide joint, each makes
  its joint an input; the input is the joint's generalized force, MuJoCo's `ctrl * gear *
  gain`; its effort limit is `|gear gain| max|ctrlrange|` (when `ctrllimited`), at most
  `|gear| max|forcerange|` and the joint's `actuatorfrcrange`. Where the file has a servo
  (`<position>`, `<velocity>`, a `<general>` actuator with a fixed gain and an affine bias) or
  an actuator on a fixed tendon (`<fixed>`: joints and coefficients, its moment arms) the
  inputs are MuJoCo's `ctrl`, one per actuator in the file's order, limited to `ctrlrange`, and
  the plant applies MuJoCo's force law (`JointActuators`: gain, bias, moment arms, `forcerange`,
  the joint's `actuatorfrcrange`). Any other actuator (activation dynamics, a gain that varies,
  a spatial tendon, site or body transmission) is refused by name; pass `actuated=[joint names]` to make
  joints torque inputs instead (the actuators are then not read).
- **Joint equalities**: an active `<equality><joint joint1 joint2 polycoef="a0 a1 0 0 0">`
  between hinges or slides is the `CouplerConstraint` $q_1 = a_1 q_2 + (q_{1,0} + a_0 - a_1
  q_{2,0})$ (MuJoCo's relation holds about qpos0), enforced as the plant's constraints are
  (exactly in the accelerations, drift held by `constraint_stiffness`; MuJoCo's is soft, by its
  `solref` / `solimp`); `initial_state()` places the coupled joint on it.
- **Collision geometry** (`contact=True`): every geom whose `contype` or `conaffinity` is
  non-zero: sphere, capsule (radius, 2 x half-length), box (2 x half sizes), cylinder, a plane
  on the world (a `HalfSpace`), a mesh (the convex hull of its compiled vertices, as MuJoCo
  collides with it). Friction `geom_friction[0]` as static and dynamic coefficient (0 for
  `condim=1`), combined by Drake's rule; stiffness and dissipation are Drake's defaults:
  MuJoCo's `solref` / `solimp`, `margin`, `gap`, `priority` and torsional / rolling friction
  are not translated. Filtering as MuJoCo's: no contact between geoms of one rigid body, of a
  body and its parent (unless `filterparent` is disabled; bodies welded to the world
  excepted), of bodies named by `<exclude>`, nor where `contype_a & conaffinity_b` and
  `contype_b & conaffinity_a` are both 0; an explicit `<pair>` makes its two geoms touch
  whatever the filters say (its own friction, `condim`, `solref`, margin are not read: the
  geoms' friction combines by Drake's rule). The plant excludes pairs of bodies, so two bodies
  whose geoms pass MuJoCo's filter for some pairs and not others are refused by name.
- **Files** (`check_model_files`, before MuJoCo opens anything): the XML of the model and of
  its includes without DTD or entities, and every file it names (includes, meshes, textures,
  `<compiler meshdir assetdir texturedir>`) inside the model's folder; refused by name.

Refused, each with a named error and its remedy: ball joints (MuJoCo's compiler itself
refuses a free joint below the worldbody), armature or a spring on a free joint, an actuator's
armature (unless `ignore_armature=True`), nonlinear springs (`stiffnesspoly`), polynomial
damping, gravity compensation, fluid forces (`density`, `viscosity`), equality constraints
other than those joint equalities (connect, weld, tendon, distance, a polynomial), spatial
tendons and fixed tendons with nonlinear springs or dampers, limits or friction, flexes, and geoms of
other shapes that can collide (ellipsoid, height field, SDF).
"""

from __future__ import annotations

import functools
import pathlib
from typing import NamedTuple

import numpy as np

from .._extras import require_mujoco
from ..geometry import Box, Capsule, Convex, Cylinder, GeometryError, HalfSpace, Sphere
from ._actuators import FixedTendons, JointActuators
from ._contact import CollisionGeometry, ContactMaterial
from ._files import parse_xml, read_xml, resolve_model_file
from ._joints import JointType
from ._tree import KinematicTree, _combine, assemble_tree
from ._urdf_collision import URDFCollisions


class _Actuator(NamedTuple):
    """One actuator as the reader sees it (`_Reader.actuators`): its `target` (a joint id, or a
    tendon id for "law" on a tendon), its `kind` ("motor", "law" or "refused"), a motor's joint
    force `bound`, a refused one's `reason`."""

    name: str
    target: int
    kind: str
    bound: float | None = None
    reason: str | None = None


class MJCFError(ValueError):
    """An MJCF model the plant cannot represent (named element, file, remedy)."""


def tree_from_mjcf(source, *, contact: bool = False, actuated=None, ignore_armature: bool = False):
    """Read an MJCF file (or a compiled `mujoco.MjModel`) into a `KinematicTree` (module doc).

    **Returns:** `(tree, actuated_joints, collision)`: the tree; the names of the joints that
    are inputs (the motors' joints in the order of their actuators, or `actuated`); and the
    `URDFCollisions` record of the collision geometry (None without `contact`)."""
    return plant_parts_from_mjcf(source, contact=contact, actuated=actuated, ignore_armature=ignore_armature)[:3]


def plant_parts_from_mjcf(source, *, contact: bool = False, actuated=None, ignore_armature: bool = False,
                          ctrl_inputs: bool = False):
    """`tree_from_mjcf`'s `(tree, actuated_joints, collision)`, the file's configuration
    (MuJoCo's `qpos0`: each free body where the file places it, each hinge and slide at its
    `ref`, where `mj_resetData` starts) in the tree's coordinates, and the `JointActuators`
    where the file has servos or `ctrl_inputs` (and `actuated` is None), else None, its
    joint equalities' coupler constraints as (joint, leader, gear ratio, offset), and its fixed
    tendons' springs and dampers (`FixedTendons`, or None)."""
    mujoco = _mujoco()
    model, where = _compile(mujoco, source)
    reader = _Reader(mujoco, model, where)
    reader.check_supported(ignore_armature)
    joints = reader.actuated_joints() if actuated is None else list(actuated)
    tree = reader.tree(ignore_armature)
    actuators = reader.joint_actuators(tree) if actuated is None and (ctrl_inputs or reader.needs_force_law()) else None
    return (tree, joints, (reader.collisions() if contact else None), reader.default_positions(tree), actuators,
            reader.couplers(), reader.fixed_tendons(tree))


def mjcf_render_model(plant):
    """(MuJoCo's compiled model of the MJCF file `plant` was loaded from, the qpos address of
    each of the plant's position coordinates), for MuJoCo's renderer to draw the plant's states."""
    if plant.source_format != "mjcf":
        raise ValueError(f"{plant.name} was not loaded from an MJCF file (RigidBodySystem.from_mjcf(path))")
    mujoco = _mujoco()
    model, where = _compile(mujoco, plant.source)
    addresses = _Reader(mujoco, model, where).qpos_addresses(plant.tree)
    return model, addresses


def _mujoco():
    return require_mujoco("from_mjcf")


def _compile(mujoco, source):
    if isinstance(source, mujoco.MjModel):
        return source, "the MjModel"
    path = pathlib.Path(source)
    if path.is_file():  # a missing file: MuJoCo's own message
        check_model_files(path)
    try:
        return mujoco.MjModel.from_xml_path(str(path)), str(path)
    except ValueError as error:
        raise MJCFError(f"{path}: MuJoCo's compiler refused the model: {error}") from None


_DIRECTORY = {"mesh": "meshdir", "skin": "meshdir", "hfield": "meshdir", "texture": "texturedir"}


def check_model_files(path=None, *, text=None, assets=None):
    """Refuse, before MuJoCo reads anything, a model file that names files outside its folder.

    The model: the MJCF (or URDF, for MuJoCo's importer) at `path`, or MJCF `text` (its
    folder: the working directory, where MuJoCo looks). Its XML and that of every
    `<include>`d file is parsed by `parse_xml` (no DTD, no entities); every `file*` attribute
    (includes, `<model>`, meshes, skins, height fields, textures and their cube faces; a URDF's
    `<mesh filename>`, by its base name unless `strippath="false"`) must name a file inside the
    folder, taken from the folder of the main file and from that of the file naming it (MuJoCo
    looks in both), under `<compiler meshdir texturedir assetdir>`, themselves inside it.
    Names found in `assets` ({name: bytes}, read from memory) are not looked up on disk;
    included ones are checked the same way. Refusals: `MJCFError` naming the file, the element
    and the remedy."""
    assets = assets or {}
    main = pathlib.Path(path) if path is not None else pathlib.Path.cwd() / "(MJCF text)"
    documents, pending, seen = [], [("", None if path is None else main, text)], set()
    while pending:  # the model and the files it includes; `prefix` names an included one
        prefix, file, data = pending.pop()
        if data is None:
            root = read_xml(file, MJCFError)
        else:
            root = parse_xml(data.encode() if isinstance(data, str) else data, prefix or main, MJCFError)
        documents.append((prefix, file, root))
        for include in root.iter("include"):
            name = include.get("file")
            if name in assets:
                pending.append((f"{name}: ", None, assets[name]))
                continue
            for target in _model_paths(name, main, file, "", f"{prefix}<include>"):
                if target.is_file() and target not in seen:
                    seen.add(target)
                    pending.append((f"{name}: ", target, None))
    dirs, strip = {}, any(root.tag == "robot" for _, _, root in documents)  # MuJoCo strips a URDF's mesh paths
    for prefix, file, root in documents:
        for compiler in root.iter("compiler"):
            for key in ("meshdir", "texturedir", "assetdir"):
                if compiler.get(key) is not None:
                    _model_paths(compiler.get(key), main, file, "", f"{prefix}<compiler {key}>")
                    dirs[key] = compiler.get(key)
            strip = compiler.get("strippath", str(strip)).lower() in ("true", "1")
    for prefix, file, root in documents:
        for element in root.iter():
            for attribute, name in element.attrib.items():
                if not attribute.startswith("file") or element.tag == "include":
                    continue
                if strip:
                    name = pathlib.PurePosixPath(name.replace("\\", "/")).name
                if name in assets:
                    continue
                directory = dirs.get(_DIRECTORY[element.tag], dirs.get("assetdir", "")) if element.tag in _DIRECTORY else ""
                label = "" if element.get("name") is None else f" name={element.get('name')!r}"
                _model_paths(name, main, file, directory, f"{prefix}<{element.tag}{label} {attribute}>")


def _model_paths(name, main, file, directory, where):
    """Where MuJoCo may look for `name` (a file of `directory`, from the folder of the main
    model and from that of the `file` that names it), each checked inside the main folder."""
    folders = {main.resolve().parent} | ({file.resolve().parent} if file is not None else set())
    return [resolve_model_file(name, main, where, MJCFError, base=folder / directory, must_exist=False)
            for folder in sorted(folders)]


def _quaternion_matrix(wxyz):
    w, x, y, z = np.asarray(wxyz, float) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _rotation_about(axis, angle):
    a = np.asarray(axis, float)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


class _Reader:
    """The compiled model's arrays, read once into bodies, frames, inputs and geometry."""

    def __init__(self, mujoco, model, where):
        self.mj, self.m, self.where = mujoco, model, where
        self.body_name = [self._name(mujoco.mjtObj.mjOBJ_BODY, b, f"body{b}") for b in range(model.nbody)]
        self.body_name[0] = "world"
        self.joint_name = [self._name(mujoco.mjtObj.mjOBJ_JOINT, j, f"joint{j}") for j in range(model.njnt)]
        self.disabled = lambda flag: bool(model.opt.disableflags & getattr(mujoco.mjtDisableBit, flag))

    def _name(self, kind, index, fallback):
        return self.mj.mj_id2name(self.m, kind, index) or fallback

    def springs_on(self) -> bool:
        return not self.disabled("mjDSBL_SPRING")

    def _joint(self, j):
        return f"{self.where}: joint {self.joint_name[j]!r} (body {self.body_name[self.m.jnt_bodyid[j]]!r})"

    def _joint_type(self, j) -> JointType:
        """Joint j's kind: a free joint floats, a hinge revolves, a slide is prismatic (a ball
        joint is refused by `check_supported`)."""
        J = self.mj.mjtJoint
        return {int(J.mjJNT_FREE): JointType.FLOATING, int(J.mjJNT_HINGE): JointType.REVOLUTE,
                int(J.mjJNT_SLIDE): JointType.PRISMATIC}[int(self.m.jnt_type[j])]

    # ----- what the plant cannot represent ------------------------------------------------------

    def check_supported(self, ignore_armature):
        m, where, J = self.m, self.where, self.mj.mjtJoint
        for j in range(m.njnt):
            kind = m.jnt_type[j]
            if kind == J.mjJNT_BALL:
                raise MJCFError(f"{self._joint(j)} is a ball joint; the plant has hinge, slide and one free "
                                "(floating-base) joint. Replace it by three hinges with orthogonal axes in "
                                "the same body (same pos)")
            dofs = slice(m.jnt_dofadr[j], m.jnt_dofadr[j] + self._joint_type(j).num_velocities)
            if self._joint_type(j) == JointType.FLOATING and np.any(m.dof_armature[dofs] != 0) and not ignore_armature:
                raise MJCFError(f"{self._joint(j)} is a free joint with armature {m.dof_armature[dofs].max():g}; the "
                                "plant models armature on hinges and slides alone. Remove it from the free joint, "
                                "or pass ignore_armature=True to drop all armature")
            if self.springs_on() and self._joint_type(j) == JointType.FLOATING and m.jnt_stiffness[j] != 0:
                raise MJCFError(f"{self._joint(j)} is a free joint with a spring (stiffness {m.jnt_stiffness[j]:g}); "
                                "the plant models springs on hinges and slides alone: remove it")
            if self.springs_on() and np.any(m.jnt_stiffnesspoly[j] != 0):
                raise MJCFError(f"{self._joint(j)} has a nonlinear spring (stiffnesspoly), which the plant does "
                                "not model; keep only its linear stiffness")
            if np.any(m.dof_dampingpoly[dofs] != 0) and not self.disabled("mjDSBL_DAMPER"):
                raise MJCFError(f"{self._joint(j)} has polynomial damping, which the plant does not model; "
                                "keep only its linear damping")
        for t in range(m.ntendon):
            self._check_tendon(t)
        if np.any(m.body_gravcomp != 0):
            b = int(np.flatnonzero(m.body_gravcomp)[0])
            raise MJCFError(f"{where}: body {self.body_name[b]!r} has gravcomp {m.body_gravcomp[b]:g}; the plant "
                            "has no gravity compensation: remove it and compensate with the input instead")
        if m.opt.density != 0 or m.opt.viscosity != 0:
            raise MJCFError(f"{where}: <option density={m.opt.density:g} viscosity={m.opt.viscosity:g}> asks "
                            "for fluid forces, which the plant does not model; set both to 0")
        for e in range(m.neq):
            self._check_equality(e)
        if m.nflex:
            raise MJCFError(f"{where}: the model has {m.nflex} flexes (deformable bodies), which the plant does not "
                            "represent; remove them")
        if np.any(m.actuator_armature != 0) and not ignore_armature:
            raise MJCFError(f"{where}: an actuator has armature, which the plant does not model; remove it, or "
                            "pass ignore_armature=True")

    def _check_equality(self, e):
        """A joint equality between two hinges or slides, linear in the second (polycoef
        a0, a1, 0, 0, 0), active from the start, is read as a `CouplerConstraint`; any other
        equality (connect, weld, tendon, distance, one joint alone, a polynomial) is refused by name."""
        m, mj = self.m, self.mj
        where = f"{self.where}: equality {self._name(mj.mjtObj.mjOBJ_EQUALITY, e, f'equality{e}')!r}"
        kind = int(m.eq_type[e])
        if kind != int(mj.mjtEq.mjEQ_JOINT):
            raise MJCFError(f"{where} is a {mj.mjtEq(kind).name.removeprefix('mjEQ_').lower()} constraint, which the "
                            "plant does not read; it reads joint equalities (couplers). Close loops with "
                            "RigidBodySystem(tree, loops=[LoopConstraint(...)]) instead")
        problem = None
        if m.eq_obj2id[e] < 0:
            problem = "holds one joint alone (weld the joint in the file instead)"
        elif np.any(m.eq_data[e, 2:5] != 0):
            problem = f"is a polynomial of degree > 1 (polycoef {m.eq_data[e, :5].tolist()})"
        elif not m.eq_active0[e]:
            problem = "starts inactive"
        elif any(self._joint_type(int(j)) == JointType.FLOATING for j in (m.eq_obj1id[e], m.eq_obj2id[e])):
            problem = "involves a free joint"
        if problem:
            raise MJCFError(f"{where} {problem}; the plant reads an active joint equality between two hinges or "
                            "slides, linear in the second (polycoef a0 a1 0 0 0), as a coupler constraint")

    def couplers(self) -> list:
        """Every joint equality as (joint, leader, gear ratio, offset), a `CouplerConstraint`'s
        fields: MuJoCo's $q_1 - q_{1,0} = a_0 + a_1 (q_2 - q_{2,0})$ about qpos0, so the offset
        is $q_{1,0} + a_0 - a_1 q_{2,0}$."""
        m, couplers = self.m, []
        for e in range(m.neq):
            j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
            q1, q2 = (m.qpos0[m.jnt_qposadr[j]] for j in (j1, j2))
            a0, a1 = m.eq_data[e, 0], m.eq_data[e, 1]
            couplers.append((self.joint_name[j1], self.joint_name[j2], float(a1), float(q1 + a0 - a1 * q2)))
        return couplers

    def _check_tendon(self, t):
        """A fixed tendon (a linear combination of joint positions) is read as an actuator's
        transmission, with its linear spring and damper; a spatial tendon, or one with a
        nonlinear spring or damper, limits, friction, armature or an actuator force range, is
        refused by name."""
        m, mj = self.m, self.mj
        where = f"{self.where}: tendon {self._name(mj.mjtObj.mjOBJ_TENDON, t, f'tendon{t}')!r}"
        wraps = range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t])
        if any(int(m.wrap_type[w]) != int(mj.mjtWrap.mjWRAP_JOINT) for w in wraps):
            raise MJCFError(f"{where} is a spatial tendon (through sites or around geoms), which the plant does not "
                            "model; the plant reads fixed tendons (<fixed>, joints and coefficients) as actuator "
                            "transmissions: remove it, or actuate the joints instead")
        passive = {"a nonlinear spring (stiffnesspoly)": np.any(m.tendon_stiffnesspoly[t] != 0),
                   "nonlinear damping (dampingpoly)": np.any(m.tendon_dampingpoly[t] != 0),
                   "limits": bool(m.tendon_limited[t]), "friction": m.tendon_frictionloss[t] != 0,
                   "armature": m.tendon_armature[t] != 0, "an actuator force range": bool(m.tendon_actfrclimited[t])}
        for what, present in passive.items():
            if present:
                raise MJCFError(f"{where} has {what}, which the plant does not model on a tendon (it reads a fixed "
                                "tendon's linear spring and damper, and actuators on it): remove it from the tendon")

    def _coefficients(self, t, tree) -> np.ndarray:
        """Fixed tendon t's coefficients over the tree's velocity coordinates."""
        m, coefficients = self.m, np.zeros(tree.nv)
        for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]):
            coefficients[tree.v_starts[tree.joint_names.index(self.joint_name[int(m.wrap_objid[w])])]] += m.wrap_prm[w]
        return coefficients

    def fixed_tendons(self, tree) -> FixedTendons | None:
        """The fixed tendons with a spring or a damper (springs and dampers disabled by the
        file's flags are left out), or None."""
        m = self.m
        stiffness = m.tendon_stiffness if self.springs_on() else np.zeros(m.ntendon)
        damping = m.tendon_damping if not self.disabled("mjDSBL_DAMPER") else np.zeros(m.ntendon)
        kept = [t for t in range(m.ntendon) if stiffness[t] != 0 or damping[t] != 0]
        if not kept:
            return None
        return FixedTendons(
            names=[self._name(self.mj.mjtObj.mjOBJ_TENDON, t, f"tendon{t}") for t in kept],
            coefficients=np.stack([self._coefficients(t, tree) for t in kept]),
            stiffness=stiffness[kept], damping=damping[kept], spring_range=m.tendon_lengthspring[kept])

    def _moment(self, a, tree) -> np.ndarray:
        """Actuator a's moment arms over the tree's velocity coordinates: its gear at its
        joint's, or its gear times its fixed tendon's coefficients."""
        m, mj = self.m, self.mj
        target = int(m.actuator_trnid[a, 0])
        if int(m.actuator_trntype[a]) == int(mj.mjtTrn.mjTRN_TENDON):
            return m.actuator_gear[a, 0] * self._coefficients(target, tree)
        moment = np.zeros(tree.nv)
        moment[tree.v_starts[tree.joint_names.index(self.joint_name[target])]] = m.actuator_gear[a, 0]
        return moment

    # ----- bodies and joints ------------------------------------------------------------------

    def tree(self, ignore_armature: bool = False) -> KinematicTree:
        m = self.m
        bodies, frames = [], [("world", -1, np.eye(3), np.zeros(3))]
        place = {0: (-1, np.eye(3), np.zeros(3))}  # MuJoCo body -> (tree body, R, p of it in the tree body)
        damping_on = not self.disabled("mjDSBL_DAMPER")
        effort = self._effort_limits()
        armature = np.zeros(m.nv) if ignore_armature else m.dof_armature
        stiffness = m.jnt_stiffness if self.springs_on() else np.zeros(m.njnt)
        for b in range(1, m.nbody):
            parent, R_p, p_p = place[m.body_parentid[b]]
            R_B = _quaternion_matrix(m.body_quat[b])
            R, p = R_p @ R_B, R_p @ m.body_pos[b] + p_p  # body frame before its joints, in `parent`
            joints = range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
            for k, j in enumerate(joints):
                dof = m.jnt_dofadr[j]
                common = dict(joint=self.joint_name[j], inertial=(0.0, np.zeros(3), np.zeros((3, 3))),
                              damping=m.dof_damping[dof] if damping_on else 0.0, friction=m.dof_frictionloss[dof],
                              effort=effort.get(j, np.inf), lower=-np.inf, upper=np.inf, armature=armature[dof],
                              stiffness=stiffness[j], spring_reference=m.qpos_spring[m.jnt_qposadr[j]])
                kind = self._joint_type(j)
                if kind == JointType.FLOATING:   # a free body of the worldbody (MuJoCo allows no other)
                    bodies.append(dict(common, link=self.body_name[b], type=JointType.FLOATING, parent=-1, R=np.eye(3),
                                       p=np.zeros(3), axis=np.zeros(3)))
                    parent, R, p = len(bodies) - 1, np.eye(3), np.zeros(3)  # MuJoCo ignores body_pos for a free body
                    continue
                anchor, axis = m.jnt_pos[j], m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j])
                ref = m.qpos0[m.jnt_qposadr[j]]
                R_o, p_o = R, R @ anchor + p  # the joint frame at the anchor, turned back by ref
                if kind == JointType.REVOLUTE:
                    R_o = R_o @ _rotation_about(axis, -ref)
                else:
                    p_o = p_o - ref * (R_o @ axis)
                limited = bool(m.jnt_limited[j])
                last = k == len(joints) - 1
                bodies.append(dict(
                    common, link=self.body_name[b] if last else f"{self.body_name[b]}_{self.joint_name[j]}",
                    type=kind, parent=parent,
                    R=R_o, p=p_o, axis=axis, lower=m.jnt_range[j, 0] if limited else -np.inf,
                    upper=m.jnt_range[j, 1] if limited else np.inf))
                if not last:
                    frames.append((bodies[-1]["link"], len(bodies) - 1, np.eye(3), np.zeros(3)))
                parent, R, p = len(bodies) - 1, np.eye(3), -anchor  # MuJoCo's body frame in the new body
            place[b] = (parent, R, p)
            frames.append((self.body_name[b], parent, R, p))
            if parent >= 0:  # the body's inertia, in the tree body's frame
                R_i = R @ _quaternion_matrix(m.body_iquat[b])
                inertia = R_i @ np.diag(m.body_inertia[b]) @ R_i.T
                bodies[parent]["inertial"] = _combine(*bodies[parent]["inertial"], m.body_mass[b],
                                                      R @ m.body_ipos[b] + p, inertia)
        if not bodies:
            raise MJCFError(f"{self.where}: the model has no joint (nothing moves)")
        names = [f[0] for f in frames]
        if len(set(names)) != len(names):
            raise MJCFError(f"{self.where}: body names must be unique (with `<body>_<joint>` for the extra "
                            f"bodies of a multi-joint body); repeated: {sorted({n for n in names if names.count(n) > 1})}")
        self.place = place
        gravity = np.zeros(3) if self.disabled("mjDSBL_GRAVITY") else np.array(m.opt.gravity, float)
        robot_name = bytes(m.names[: list(m.names).index(0)]).decode() if m.nnames else "mjcf_model"
        return assemble_tree(robot_name or "mjcf_model", bodies, frames, gravity, self.where, MJCFError)

    def default_positions(self, tree) -> np.ndarray:
        """MuJoCo's `qpos0` in the tree's coordinates (`qpos_addresses`)."""
        return np.asarray(self.m.qpos0, float)[self.qpos_addresses(tree)]

    def qpos_addresses(self, tree) -> np.ndarray:
        """Where each of the tree's position coordinates sits in MuJoCo's qpos: a free joint's
        [x y z qx qy qz qw] at its [x y z qw qx qy qz], a hinge's or slide's value as it is
        (the tree's joint frames take `ref` into account)."""
        addresses = np.zeros(tree.nq, int)
        for name, kind, start in zip(tree.joint_names, tree.joint_types, tree.q_starts):
            a = self.m.jnt_qposadr[self.joint_name.index(name)]
            if kind == JointType.FLOATING:
                addresses[start: start + 7] = [a, a + 1, a + 2, a + 4, a + 5, a + 6, a + 3]
            else:
                addresses[start] = a
        return addresses

    # ----- actuators ----------------------------------------------------------------------------

    @functools.cached_property
    def actuators(self) -> list:
        """Every actuator as an `_Actuator`: a `<motor>` on a hinge or slide ("motor": its joint
        force's bound), one that needs MuJoCo's force law ("law": a servo, or any actuator on a
        fixed tendon), or one the plant cannot model ("refused", with the reason)."""
        m, mj = self.m, self.mj
        actuators = []
        for a in range(m.nu):
            name = self._name(mj.mjtObj.mjOBJ_ACTUATOR, a, f"actuator{a}")
            j = int(m.actuator_trnid[a, 0])
            on_tendon = int(m.actuator_trntype[a]) == int(mj.mjtTrn.mjTRN_TENDON)   # fixed: `_check_tendon`
            on_joint = (int(m.actuator_trntype[a]) in (int(mj.mjtTrn.mjTRN_JOINT), int(mj.mjtTrn.mjTRN_JOINTINPARENT))
                        and int(m.jnt_type[j]) in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)))
            unmodelled = None if (on_joint or on_tendon) else "does not act on a hinge, a slide or a fixed tendon"
            unmodelled = unmodelled or (f"has {self._not_affine(a)}" if self._not_affine(a) else None)
            if unmodelled:
                actuators.append(_Actuator(name, j, "refused", reason=unmodelled))
            elif m.actuator_biastype[a] != mj.mjtBias.mjBIAS_NONE or on_tendon:
                actuators.append(_Actuator(name, j, "law"))
            else:
                gear = abs(m.actuator_gear[a, 0])
                bound = gear * abs(m.actuator_gainprm[a, 0]) * np.abs(m.actuator_ctrlrange[a]).max() \
                    if m.actuator_ctrllimited[a] else np.inf
                if m.actuator_forcelimited[a]:
                    bound = min(bound, gear * np.abs(m.actuator_forcerange[a]).max())
                actuators.append(_Actuator(name, j, "motor", bound=bound))
        return actuators

    def _not_affine(self, a) -> str | None:
        """What makes actuator a's force other than affine in (ctrl, length, velocity) (a fixed
        gain, an affine bias or none, no activation dynamics, damping or delay), or None."""
        m, mj = self.m, self.mj
        name = lambda enum, value, prefix: enum(int(value)).name.removeprefix(prefix).lower()  # noqa: E731
        if int(m.actuator_dyntype[a]) != int(mj.mjtDyn.mjDYN_NONE):
            return (f"activation dynamics (dyntype {name(mj.mjtDyn, m.actuator_dyntype[a], 'mjDYN_')}: a servo's "
                    "timeconst, an integrated velocity, a muscle, ...)")
        if int(m.actuator_gaintype[a]) != int(mj.mjtGain.mjGAIN_FIXED):
            return f"a gain that is not a constant (gaintype {name(mj.mjtGain, m.actuator_gaintype[a], 'mjGAIN_')})"
        if int(m.actuator_biastype[a]) not in (int(mj.mjtBias.mjBIAS_NONE), int(mj.mjtBias.mjBIAS_AFFINE)):
            return f"a bias that is not affine (biastype {name(mj.mjtBias, m.actuator_biastype[a], 'mjBIAS_')})"
        if m.actuator_damping[a] != 0 or m.actuator_delay[a] != 0:
            return "damping or a delay"
        return None

    def needs_force_law(self) -> bool:
        """Whether an actuator needs MuJoCo's force law (`JointActuators`): a servo, or any
        actuator on a fixed tendon."""
        return any(actuator.kind == "law" for actuator in self.actuators)

    def actuated_joints(self) -> list:
        """The joints of the motors, in the order of their actuators (a named error for any other
        actuator)."""
        for actuator in self.actuators:
            if actuator.kind == "refused":
                raise MJCFError(f"{self.where}: actuator {actuator.name!r} {actuator.reason}, which the plant does not "
                                "model. Pass actuated=[joint names] to make joints torque inputs (and close the "
                                "actuator's loop around the plant yourself), or make it a <motor>, <position> or "
                                "<velocity> on a joint")
        return list(dict.fromkeys(self.joint_name[a.target] for a in self.actuators if a.kind == "motor"))

    def joint_actuators(self, tree) -> JointActuators:
        """Every actuator (motors and servos on hinges, slides and fixed tendons) as `JointActuators`:
        the inputs are MuJoCo's ctrl."""
        self.actuated_joints()   # the named error for an actuator the plant cannot model
        m = self.m
        inf = np.array([-np.inf, np.inf])
        force_range = [m.actuator_forcerange[a] if m.actuator_forcelimited[a] else inf for a in range(m.nu)]
        joint_range = np.tile(inf, (tree.nv, 1))
        for name, i in zip(tree.joint_names, tree.v_starts):
            j = self.joint_name.index(name)
            if self.m.jnt_actfrclimited[j]:
                joint_range[i] = self.m.jnt_actfrcrange[j]
        limited = np.asarray(m.actuator_ctrllimited, bool)
        ctrl = np.where(limited[:, None], m.actuator_ctrlrange, inf)
        return JointActuators(
            names=[actuator.name for actuator in self.actuators],
            gain=m.actuator_gainprm[:, 0], bias=m.actuator_biasprm[:, :3],
            moment=np.stack([self._moment(a, tree) for a in range(m.nu)]).reshape(m.nu, tree.nv),
            force_range=force_range, joint_force_range=joint_range,
            ctrl_range=(ctrl[:, 0], ctrl[:, 1]) if limited.any() else None)

    def _effort_limits(self) -> dict:
        """Joint id -> the largest generalized force its motors together apply, at most the
        joint's `actuatorfrcrange` (joints with motors)."""
        bound = {}
        for actuator in self.actuators:
            if actuator.kind == "motor":
                bound[actuator.target] = bound.get(actuator.target, 0.0) + actuator.bound
        for j in bound:
            if self.m.jnt_actfrclimited[j]:
                bound[j] = min(bound[j], np.abs(self.m.jnt_actfrcrange[j]).max())
        return bound

    # ----- collision geometry ----------------------------------------------------------------

    def collisions(self) -> URDFCollisions:
        m, G = self.m, self.mj.mjtGeom
        geometries, owners = [], []
        paired = set(m.pair_geom1.tolist()) | set(m.pair_geom2.tolist())
        for g in range(m.ngeom):
            if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0 and g not in paired:
                continue  # visual only: it can never collide
            b = m.geom_bodyid[g]
            link = self.body_name[b]
            name = self._name(self.mj.mjtObj.mjOBJ_GEOM, g, f"{link}_geom{g}")
            size, kind = m.geom_size[g], m.geom_type[g]
            where = f"{self.where}: geom {name!r} (body {link!r})"
            try:
                if kind == G.mjGEOM_SPHERE:
                    shape = Sphere(size[0])
                elif kind == G.mjGEOM_CAPSULE:
                    shape = Capsule(size[0], 2 * size[1])
                elif kind == G.mjGEOM_CYLINDER:
                    shape = Cylinder(size[0], 2 * size[1])
                elif kind == G.mjGEOM_BOX:
                    shape = Box(*(2 * size))
                elif kind == G.mjGEOM_PLANE:
                    if self.place[b][0] >= 0:
                        raise MJCFError(f"{where}: a plane on a moving body; a plane collides as a half-space "
                                        "fixed to the world: use a box on a moving body")
                    shape = HalfSpace()
                elif kind == G.mjGEOM_MESH:
                    mesh = m.geom_dataid[g]
                    start = m.mesh_vertadr[mesh]
                    shape = Convex.from_points(m.mesh_vert[start: start + m.mesh_vertnum[mesh]], name=name)
                else:
                    raise MJCFError(f"{where} has type=\"{G(kind).name.removeprefix('mjGEOM_').lower()}\", which the "
                                    "plant cannot collide; use a sphere, capsule, box, cylinder, plane or mesh, "
                                    "or make the geom visual only (contype=\"0\" conaffinity=\"0\")")
            except GeometryError as error:
                raise MJCFError(f"{where}: {error}") from None
            mu = 0.0 if m.geom_condim[g] == 1 else float(m.geom_friction[g, 0])
            geometries.append(CollisionGeometry(
                name=name, link=link, shape=shape, rotation=_quaternion_matrix(m.geom_quat[g]),
                translation=np.array(m.geom_pos[g], float), material=ContactMaterial(mu_static=mu, mu_dynamic=mu)))
            owners.append(g)
        return URDFCollisions(tuple(geometries), self._excluded_body_pairs(owners))

    def _excluded_body_pairs(self, geoms) -> tuple:
        """The pairs of bodies (frame names) between which MuJoCo's filters pass no geom pair (a
        named error where they pass some and not others)."""
        m = self.m
        name = lambda g: self._name(self.mj.mjtObj.mjOBJ_GEOM, g, f"{self.body_name[m.geom_bodyid[g]]}_geom{g}")  # noqa: E731
        excluded_bodies = {(s >> 16, s & 0xFFFF) for s in m.exclude_signature}
        weld = m.body_weldid
        filter_parent = not self.disabled("mjDSBL_FILTERPARENT")
        tree_body = lambda b: self.place[b][0]  # noqa: E731

        explicit = {frozenset(pair) for pair in zip(m.pair_geom1.tolist(), m.pair_geom2.tolist())}

        def passes(g1, g2):
            if frozenset((g1, g2)) in explicit:   # a <pair> bypasses every filter
                return True
            b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
            w1, w2 = weld[b1], weld[b2]
            if filter_parent and w1 != 0 and w2 != 0 and (w1 == weld[m.body_parentid[w2]] or w2 == weld[m.body_parentid[w1]]):
                return False
            if (b1, b2) in excluded_bodies or (b2, b1) in excluded_bodies:
                return False
            return bool(m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1])

        verdicts = {}
        for i, g1 in enumerate(geoms):
            for g2 in geoms[i + 1:]:
                b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
                if tree_body(b1) == tree_body(b2):
                    continue  # one rigid body: never in contact, here as in MuJoCo
                key = (min(b1, b2), max(b1, b2))
                touch = passes(g1, g2)
                verdicts.setdefault(key, set()).add((touch, g1, g2))
        excluded = []
        for (b1, b2), results in verdicts.items():
            passed = {r[0] for r in results}
            if passed == {False}:
                excluded.append((self.body_name[b1], self.body_name[b2]))
            elif passed == {True, False}:
                g1, g2 = next((r[1], r[2]) for r in results if not r[0])
                raise MJCFError(
                    f"{self.where}: bodies {self.body_name[b1]!r} and {self.body_name[b2]!r}: MuJoCo's contype / "
                    f"conaffinity let some of their geoms touch but not others (e.g. {name(g1)!r} and {name(g2)!r}); "
                    "the plant filters contact by pairs of bodies. Give the geoms of each body one contype / "
                    "conaffinity, or make the geoms that must not touch visual only (contype=\"0\" conaffinity=\"0\")")
        return tuple(excluded)
