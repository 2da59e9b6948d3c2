r"""`RigidBodySystem`: the manipulator equations as a `System` (notes, D.3.1):

$$H(q)\dot v + C(q, v) v + G(q) = B u - b \circ v + \tau_{lim}(q, v) + J_\phi^T(q) \lambda,
  \qquad \phi(q) = 0,$$

state $x = [q; v]$ ($\dot q = v$ except for a floating base's quaternion), input u through B,
URDF joint damping b, compliant joint position limits $\tau_{lim}$, and constraints
$\phi(q) = 0$ (closed kinematic loops, coupled joints) whose forces $\lambda$ come from the
KKT system, with Baumgarte stabilization $\ddot\phi + 2\omega\dot\phi + \omega^2\phi = 0$ so
that drift decays.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._compiled import compiled_query
from .._numbers import device_array
from ..geometry import HalfSpace
from ..systems import Frame, System
from . import _algorithms as alg
from ._actuators import FixedTendons, JointActuators
from ._contact import DEFAULT_STICTION_TOLERANCE, CollisionGeometry, ContactMaterial, ContactModel, build_contact_model
from ._joints import JointType
from ._tree import KinematicTree, URDFError, tree_from_pinocchio, tree_from_urdf, urdf_mimic_joints
from ._urdf_collision import URDFCollisions, read_urdf_collisions

_AXES = {"x": 0, "y": 1, "z": 2}
_WARNED_LIMITS: set = set()  # (plant name, joint name) already warned of a start past a limit


@dataclasses.dataclass(frozen=True)
class LoopConstraint:
    """Closes a kinematic loop: the origins of frames `frame_a` and `frame_b` coincide along
    the world `axes` (e.g. `("x", "z")` for a planar linkage in the x-z plane)."""

    frame_a: str
    frame_b: str
    axes: tuple = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class CouplerConstraint:
    r"""Couples two one-dof joints: $q_{joint} = \rho\, q_{leader} + \Delta q$ (Drake's
    `AddCouplerConstraint(joint, leader, gear_ratio, offset)`; a URDF `<mimic>` element read by
    `from_urdf(..., mimic=True)`). Both joints stay coordinates; the constraint force keeps
    them coupled, as a loop constraint does."""

    joint: str
    leader: str
    gear_ratio: float = 1.0
    offset: float = 0.0


class RigidBodySystem(System):
    r"""A tree of rigid bodies (from a URDF or a Pinocchio model), possibly with loop closures.

    **Construction:** `RigidBodySystem.from_urdf(path, floating_base=False, actuated=None,
    gravity=True, loops=(), contact=False)`, `RigidBodySystem.from_mjcf(path)` (MuJoCo's
    compiler as the parser) or `RigidBodySystem.from_pinocchio(model)`; each builds a
    `RigidBodySystem`. The rigid-body plants of `jaxdrake.models` (`Acrobot`, ...) are final
    subclasses built by their own constructors; the methods that return a modified copy
    (`with_collision_geometry`, `with_ground`, `without_collisions_between`, `equinox.tree_at`)
    keep the copy's class.

    - B: the joints named by the URDF's `<transmission>`s, or `actuated` (joint names), or
      else every joint but a floating base; one input per actuated joint, in that order. An
      MJCF file with servos gives `actuators` (`JointActuators`: the inputs are MuJoCo's
      ctrl, the force law MuJoCo's; B is then its slope where no force limit binds);
      `actuation(q, v, u)` is the inputs' generalized force either way.
    - State frame: joint positions then velocities (`<joint>`, `<joint>dot`; a free body's
      joint has x, y, z, qx, qy, qz, qw and vx, vy, vz, wx, wy, wz, in the body's own frame).
    - Free bodies: the robot's root link with `floating_base=True` (joint `floating_base`),
      the child of each `<joint type="floating">` from the world (the joint's name), and, as in
      Drake, every other link that no joint holds (its own name); any number, beside bodies
      that hang from the world.
    - Input limits: the actuated joints' `<limit effort>` (|u_k| <= effort, as Drake's
      parser makes actuator effort limits), unless `effort_limits=False`; the simulator
      locates the saturation instants as events.
    - Joint position limits (`<limit lower upper>`) are compliant, unless `joint_limits=False`:
      past a limit by p > 0, a joint is pushed back by $\mathrm{clip}(k p + d \dot p, 0, 2 k p)$,
      a critically damped spring of natural period `limit_period` (default 0.02 s) on the
      joint's inertia $H_{ii}$ at the neutral configuration, $k = H_{ii}\omega^2$,
      $d = 2 H_{ii}\omega$, $\omega = 2\pi/$`limit_period`, whose damper neither pulls nor
      pushes harder than the spring ($|d \dot p| \le k p$). Drake's discrete plant pushes by
      $\max(0, k p + d \dot p)$, whose damper switches on with a jump $d \dot p$ at the limit:
      harmless to a time-stepper, a discontinuity that an error-controlled integrator must
      creep through (in float32 it may not). Capped, the push grows from 0 at the limit,
      continuous in the state, as MSC Adams' IMPACT force ramps its damping up from 0 at
      contact; it is Drake's wherever $d \dot p \le k p$ (at rest, on the way out) and stays
      homogeneous in $(p, \dot p)$: a joint arriving at speed $v_0$ goes past by at most
      $v_0 e^{-1/3}/\omega$ and leaves at $v_0 e^{-4/3}$; pressed from rest by a steady
      generalized force $\tau$, it settles $\tau/k$ past the limit after going at most
      $(1 + e^{-4/3}/3)\,\tau/k$ past. Drake's continuous plant ignores limits
      (`joint_limits=False` reproduces it). `limit_stiffness`, `limit_damping` are leaves (per
      velocity coordinate; 0 for unlimited joints) that you may replace.
    - Coupled joints: `couplers=[CouplerConstraint(...)]`, or the URDF's `<mimic>` elements
      with `from_urdf(..., mimic=True)` (by default, as Pinocchio's `buildModelFromUrdf`, a
      mimic joint is an independent joint).
    - Damping acts in the dynamics; the URDF's Coulomb friction is recorded on `tree`, not applied.
    - Rotor inertia: a joint's armature $\rho$ (`tree.armature`: Drake's URDF extension
      `<drake:rotor_inertia>` times `<drake:gear_ratio>` squared in a `<transmission>`'s
      actuator, MuJoCo's `armature`, Pinocchio's `model.armature`) adds to H's diagonal.
      Joint springs (`tree.spring_stiffness`, `tree.spring_reference`: MuJoCo's `stiffness`,
      `springref`) push by $-k(q - q_s)$, and an MJCF file's fixed tendons with springs or
      dampers by theirs (`tendons`: `FixedTendons`); `passive_force(q, v)` sums them with the
      joints' damping; `energy` counts the rotors and the springs.
    - Contact (`from_urdf(..., contact=True)`, `with_collision_geometry`, `with_ground`): the
      `<collision>` shapes touch each other and the world by Drake's compliant point contact
      (Hunt-Crossley normal force, regularised Stribeck friction; "The contact model" on the API page),
      their generalized force $\sum J^T f$ added to the dynamics. `contact` holds the
      geometry's leaves (stiffness, dissipation, friction, sizes, poses) that you may
      replace; `contact_results(x)` gives the points and forces. Solvers: Drake's stiction
      tolerance (1e-4 m/s) makes resting friction stiff; `jd.simulation.Rosenbrock23(
      jacobian="stiff")` takes long steps through it on the cheap matrix of
      `stiff_linearization` (Solo-12's drop: 13x faster than Drake's RK3 at errors of 1e-7 to
      1e-5, 6x at 1e-9; 6-8 s first call); `solver="rosenbrock23"` (the exact Jacobian) costs
      3-4x more per step and compiles for 10-20 s; `dopri5` suits a stiction tolerance of ~1 cm/s
      (`stiction_tolerance=`); see benchmarks/RESULTS.md.

    The tree's masses, inertias, lengths and axes are pytree leaves: `jax.grad` with respect
    to a link mass works (system identification); build the system outside `jit`.
    """

    tree: KinematicTree
    B: jax.Array
    actuators: JointActuators | None
    limit_stiffness: jax.Array
    limit_damping: jax.Array
    loops: tuple = eqx.field(static=True, default=())
    couplers: tuple = eqx.field(static=True, default=())
    limited: tuple = eqx.field(static=True, default=())   # (q index, v index) of the joints with limits
    constraint_stiffness: float = 20.0
    source: str | None = eqx.field(static=True, default=None)  # the model file, when loaded from one
    source_format: str | None = eqx.field(static=True, default=None)  # its format: "urdf" or "mjcf"
    package_map: tuple = eqx.field(static=True, default=())  # (package, folder) pairs for its package:// files
    contact: ContactModel | None = None
    tendons: FixedTendons | None = None
    collision: URDFCollisions | None = eqx.field(static=True, default=None)  # what `contact` was built from
    stiction_tolerance: float = eqx.field(static=True, default=DEFAULT_STICTION_TOLERANCE)  # seeds contact models built later
    linearization: str = eqx.field(static=True, default="exact")  # "stiff": see stiff_linearization
    default_positions: tuple | None = eqx.field(static=True, default=None)  # the file's q (MJCF: qpos0), else neutral

    def __init__(self, tree: KinematicTree, actuated_joints=None, *, loops=(), couplers=(),
                 constraint_stiffness: float = 20.0, effort_limits: bool = True,
                 joint_limits: bool = True, limit_period: float = 0.02, source=None, collision=None,
                 stiction_tolerance: float = DEFAULT_STICTION_TOLERANCE, package_map=None,
                 default_positions=None, source_format: str | None = None,
                 actuators: JointActuators | None = None, tendons: FixedTendons | None = None):
        names = tree.joint_names
        if actuators is not None:   # MuJoCo's actuators: the inputs are their ctrl
            inputs, B = actuators.names, actuators.input_matrix()
            limits = actuators.ctrl_range if effort_limits else None
        else:
            inputs, B, limits = self._joint_force_inputs(tree, actuated_joints, effort_limits)
        self.tree, self.B, self.actuators, self.tendons = tree, device_array(B), actuators, tendons
        self.loops = tuple(loops)
        for loop in self.loops:
            for frame in (loop.frame_a, loop.frame_b):
                if frame not in tree.frame_names:
                    raise ValueError(f"{tree.robot_name}: loop constraint frame {frame!r} is not a link "
                                     f"of the tree; the links are {list(tree.frame_names)}")
            if not loop.axes or any(a not in _AXES for a in loop.axes):
                raise ValueError(f"loop constraint axes must be among 'x', 'y', 'z', got {loop.axes}")
        self.couplers = tuple(couplers)
        for coupler in self.couplers:
            for joint in (coupler.joint, coupler.leader):
                if joint not in names or tree.joint_types[names.index(joint)] == JointType.FLOATING:
                    raise ValueError(f"{tree.robot_name}: coupler constraint joint {joint!r} is not a "
                                     f"one-dof joint of the tree; the joints are {list(names)}")
        self.limited = _limited_joints(tree) if joint_limits else ()
        self.limit_stiffness, self.limit_damping = _limit_gains(tree, self.limited, limit_period)
        self.constraint_stiffness = constraint_stiffness
        self.source = None if source is None else str(source)
        if source_format not in (None, "urdf", "mjcf"):
            raise ValueError(f"source_format must be 'urdf', 'mjcf' or None, got {source_format!r}")
        self.source_format = None if source is None else (source_format or "urdf")
        self.package_map = tuple(sorted((str(k), str(v)) for k, v in dict(package_map or {}).items()))
        self.collision = collision
        self.stiction_tolerance = float(stiction_tolerance)
        if default_positions is not None and np.shape(default_positions) != (tree.nq,):
            raise ValueError(f"{tree.robot_name}: default_positions must have the {tree.nq} position coordinates "
                             f"{tree.position_names()}, got shape {np.shape(default_positions)}")
        self.default_positions = None if default_positions is None else tuple(float(x) for x in default_positions)
        self.contact = None if collision is None else build_contact_model(
            tree, collision.geometries, excluded_pairs=collision.excluded_link_pairs,
            stiction_tolerance=stiction_tolerance, source=tree.robot_name)
        state = Frame(f"{tree.robot_name}State", tree.position_names() + tree.velocity_names())
        num_loop = sum(len(loop.axes) for loop in self.loops) + len(self.couplers)
        super().__init__(num_continuous_states=tree.nq + tree.nv, num_inputs=len(inputs),
                         direct_feedthrough=False, time_invariant=True, input_limits=limits,
                         num_state_constraints=2 * num_loop + tree.layout.num_floating,
                         input_frame=Frame(f"{tree.robot_name}Input", tuple(inputs)),
                         state_frame=state, output_frame=state)

    @staticmethod
    def _joint_force_inputs(tree, actuated_joints, effort_limits):
        """(input names, B, input limits) of joint-force inputs on `actuated_joints` (default:
        every joint but a floating base), limited by the joints' effort limits."""
        names = tree.joint_names
        if actuated_joints is None:
            actuated_joints = [n for n, k in zip(names, tree.joint_types) if k != JointType.FLOATING]
        B = np.zeros((tree.nv, len(actuated_joints)))
        for col, joint in enumerate(actuated_joints):
            if joint not in names:
                raise ValueError(f"{tree.robot_name}: no joint {joint!r} to actuate; the joints are {list(names)}")
            i = names.index(joint)
            if tree.joint_types[i] == JointType.FLOATING:
                raise ValueError(f"{tree.robot_name}: the floating base cannot be actuated by a joint input")
            B[tree.v_starts[i], col] = 1.0
        effort = np.asarray(tree.effort_limit)[np.argmax(B, axis=0)] if B.size else np.zeros(0)
        limits = (-effort, effort) if effort_limits and np.any(np.isfinite(effort)) else None
        return tuple(actuated_joints), B, limits

    @staticmethod
    def from_urdf(path, *, floating_base: bool = False, actuated=None, gravity: bool = True,
                  welded=(), loops=(), mimic: bool = False, constraint_stiffness: float = 20.0,
                  effort_limits: bool = True, joint_limits: bool = True,
                  limit_period: float = 0.02, contact: bool = False, package_map=None,
                  mesh_hulls: bool = False, max_hull_vertices: int | None = None,
                  stiction_tolerance: float = DEFAULT_STICTION_TOLERANCE) -> "RigidBodySystem":
        r"""Load a URDF; joints named in `welded` are fixed at zero; `mimic=True` couples each
        `<mimic>` joint to its leader (a `CouplerConstraint`).

        `contact=True` reads the `<collision>` elements (and Drake's proximity properties and
        collision filter groups) and makes them touch: Drake's continuous point contact with
        `stiction_tolerance` (m/s) and Drake's default properties where the file gives none
        (stiffness 1e6 N/m, dissipation 50 s/m; friction 1.0 for a URDF `<collision>`, as
        Drake's URDF parser gives, 0.5 for a shape added by `with_collision_geometry` or
        `with_ground`, SceneGraph's default; two shapes touch with $2\mu_A\mu_B/(\mu_A + \mu_B)$,
        so a URDF foot on the default ground slides with 2/3). A mesh collides through its
        convex hull; a non-convex mesh is refused unless `mesh_hulls=True` (Drake's point contact
        uses the hull silently); `max_hull_vertices` simplifies each mesh's hull to at most
        that many vertices (greedily, farthest outside first: an inner approximation, as
        MuJoCo's `maxhullvert`), for detailed meshes whose hulls touch each other (two hulls
        test every pair of their edges: Solo-12's own meshes, 273-672 hull vertices, cost 172 ms
        per evaluation standing; at 64 vertices they lie within 0.65-2.1 mm of the full hulls). Mesh files are read only from the
        URDF's folder, or for `package://NAME/...` from `package_map[NAME]` (kept on the plant:
        `MeshcatVisualizer` reads its visual meshes from the same folders)."""
        with jax.ensure_compile_time_eval():  # parsing is host work, also inside jit / vmap
            path = pathlib.Path(path)
            tree, transmitted = tree_from_urdf(path, floating_base=floating_base,
                                               gravity=(0.0, 0.0, -9.81) if gravity else (0.0, 0.0, 0.0),
                                               welded=tuple(welded))
            couplers = [CouplerConstraint(*c) for c in urdf_mimic_joints(path, tuple(welded))] if mimic else []
            for coupler in couplers:
                if coupler.leader not in tree.joint_names:
                    raise URDFError(f"{path}: joint {coupler.joint!r} mimics {coupler.leader!r}, which "
                                    "is fixed or welded; weld both, or neither")
            if actuated is None and transmitted:
                actuated = list(transmitted)
            collision = read_urdf_collisions(path, package_map=package_map, mesh_hulls=mesh_hulls,
                                             max_hull_vertices=max_hull_vertices) if contact else None
            return RigidBodySystem(tree, actuated, loops=loops, couplers=couplers,
                                   constraint_stiffness=constraint_stiffness, effort_limits=effort_limits,
                                   joint_limits=joint_limits, limit_period=limit_period, source=path.resolve(),
                                   collision=collision, stiction_tolerance=stiction_tolerance, package_map=package_map,
                                   source_format="urdf")

    @staticmethod
    def from_pinocchio(model, *, actuated=None, loops=(),
                       constraint_stiffness: float = 20.0) -> "RigidBodySystem":
        """From a Pinocchio `pin.Model` (its gravity, damping and limits come along)."""
        return RigidBodySystem(tree_from_pinocchio(model), actuated, loops=loops,
                               constraint_stiffness=constraint_stiffness)

    @staticmethod
    def from_mjcf(path, *, contact: bool = False, actuated=None, ignore_armature: bool = False,
                  ctrl_inputs: bool = False, effort_limits: bool = True, joint_limits: bool = True, limit_period: float = 0.02,
                  stiction_tolerance: float = DEFAULT_STICTION_TOLERANCE) -> "RigidBodySystem":
        """Load an MJCF file (or a compiled `mujoco.MjModel`), compiled by MuJoCo: bodies, hinge /
        slide joints and a free root (the floating base), inertias, damping, gravity, ranges as
        compliant limits, `<motor>`s on joints as the inputs (joint forces, named by their
        joints), or, where the file has position / velocity servos or with `ctrl_inputs=True`
        (MuJoCo's and `MujocoSystem`'s inputs), every actuator's `ctrl` under MuJoCo's force law
        (`plant.actuators`, named by the actuators), or the joints named in `actuated`; joint equalities as coupler
        constraints; `contact=True` makes the geoms touch by Drake's point contact ("What an
        MJCF file becomes" on the API page: what is translated, what is refused by name;
        friction combines by Drake's rule, not MuJoCo's maximum; `solref` / `solimp` are not
        read). `initial_state()` is the file's configuration, MuJoCo's `qpos0`;
        `jd.viz.visualizer_for(plant)` draws its states with MuJoCo's renderer of the file.
        MuJoCo's free joint has q = [x, y, z, qw, qx, qy, qz] and a world-frame linear velocity;
        the plant's floating base has [x, y, z, qx, qy, qz, qw] and body-frame velocities."""
        from ._mjcf import plant_parts_from_mjcf

        with jax.ensure_compile_time_eval():  # parsing is host work, also inside jit / vmap
            tree, inputs, collision, qpos0, actuators, couplers, tendons = plant_parts_from_mjcf(
                path, contact=contact, actuated=actuated, ignore_armature=ignore_armature, ctrl_inputs=ctrl_inputs)
            source = pathlib.Path(path).resolve() if isinstance(path, (str, pathlib.PurePath)) else None
            return RigidBodySystem(tree, inputs, effort_limits=effort_limits, joint_limits=joint_limits,
                                   limit_period=limit_period, source=source, source_format="mjcf", collision=collision,
                                   stiction_tolerance=stiction_tolerance, default_positions=qpos0,
                                   actuators=actuators, couplers=[CouplerConstraint(*c) for c in couplers],
                                   tendons=tendons)

    @property
    def name(self) -> str:
        return self.tree.robot_name

    @property
    def num_positions(self) -> int:
        return self.tree.nq

    @property
    def num_velocities(self) -> int:
        return self.tree.nv

    # ----- the manipulator equations -------------------------------------------------------

    @compiled_query
    def manipulator_dynamics(self, q, v):
        """(H, C v, G, B) with H(q) qdd + C(q, v) v + G(q) = B u (the notes' signs)."""
        t = self.tree
        return (alg.mass_matrix(t, q), alg.bias_forces(t, q, v, gravity=False),
                alg.gravity_forces(t, q), self.B)

    @compiled_query
    def inverse_dynamics(self, q, v, qdd):
        """The generalized force H qdd + C v + G + b o v - tau_lim - tau_contact - tau_spring
        that produces qdd (damping, joint-limit, contact and joint-spring forces included;
        constraint forces not)."""
        return (alg.rnea(self.tree, q, v, qdd) - self.passive_force(q, v) - self.joint_limit_torque(q, v)
                - self.contact_force(q, v))

    # ----- contact ---------------------------------------------------------------------------

    @compiled_query
    def contact_force(self, q, v):
        r"""The generalized force of all contacts, $\sum_c J_c^T f_c$ (zero without contact)."""
        if self.contact is None:
            return jnp.zeros(self.tree.nv, v.dtype)
        return self.contact.generalized_forces(self.tree, q, v)[0]

    def contact_results(self, x):
        """The `ContactResults` at state x = [q; v]: every candidate contact's `active` flag,
        depth, point, normal and the force on its second geometry (Drake's `f_Bc_W`)."""
        if self.contact is None:
            raise ValueError(f"{self.name} has no collision geometry: load it with from_urdf(..., contact=True) "
                             "or add some with with_collision_geometry / with_ground")
        if jnp.shape(x) != (self.num_states,):
            raise ValueError(f"{self.name}.contact_results: x must be one state [q; v] of {self.num_states} "
                             f"coordinates ({self.tree.nq} q, {self.tree.nv} v), got shape {jnp.shape(x)}; "
                             "for many states, jax.vmap(plant.contact_results)")
        return _contact_results(self, x)

    def with_collision_geometry(self, link: str, shape, *, rotation=np.eye(3), translation=(0.0, 0.0, 0.0),
                                name: str | None = None, material: ContactMaterial | None = None,
                                ) -> "RigidBodySystem":
        """A copy with one more collision shape on `link` ('world' for the environment), at
        (`rotation`, `translation`) in the link's frame (Drake's `RegisterCollisionGeometry`).
        `material`: a `jd.multibody.ContactMaterial`; its values left None (and no material)
        take SceneGraph's defaults: stiffness 1e6 N/m, dissipation 50 s/m, friction 0.5 / 0.5."""
        with jax.ensure_compile_time_eval():  # host work, also inside jit / vmap
            return self._with_collision_geometry(link, shape, rotation, translation, name, material)

    def _with_collision_geometry(self, link, shape, rotation, translation, name, material):
        if material is not None and not isinstance(material, ContactMaterial):
            raise TypeError(f"{self.name}: material must be a jd.multibody.ContactMaterial, got "
                            f"{type(material).__name__}; e.g. ContactMaterial(mu_static=0.3, mu_dynamic=0.3)")
        collision = self.collision or URDFCollisions((), _joint_link_pairs(self.tree))
        name = name or f"{link}_{type(shape).__name__.lower()}_{len(collision.geometries)}"
        geometry = CollisionGeometry(name, link, shape, rotation, translation, material or ContactMaterial())
        return self._with_collision(dataclasses.replace(collision, geometries=collision.geometries + (geometry,)))

    def without_collisions_between(self, links_a, links_b=None) -> "RigidBodySystem":
        """A copy in which no geometry on a link of `links_a` touches one on a link of `links_b`
        (None: the links of `links_a` among themselves), Drake's collision filter declarations
        `ExcludeBetween` / `ExcludeWithin`; e.g. a robot's links whose collision meshes overlap
        at rest."""
        with jax.ensure_compile_time_eval():
            links_a = [links_a] if isinstance(links_a, str) else list(links_a)
            links_b = links_a if links_b is None else ([links_b] if isinstance(links_b, str) else list(links_b))
            known = set(self.tree.frame_names) | {"world"}
            for link in links_a + links_b:
                if link not in known:
                    raise ValueError(f"{self.name}: no link {link!r}; the links are {sorted(known)}")
            collision = self.collision or URDFCollisions((), _joint_link_pairs(self.tree))
            pairs = tuple((a, b) for a in links_a for b in links_b if a != b)
            return self._with_collision(dataclasses.replace(
                collision, excluded_link_pairs=collision.excluded_link_pairs + pairs))

    def _with_collision(self, collision):
        stiction = self.stiction_tolerance if self.contact is None else self.contact.stiction_tolerance
        model = build_contact_model(self.tree, collision.geometries, excluded_pairs=collision.excluded_link_pairs,
                                    stiction_tolerance=stiction, source=self.name)
        return _replace_fields(self, contact=model, collision=collision)

    def with_ground(self, height: float = 0.0, *, normal=(0.0, 0.0, 1.0), material: ContactMaterial | None = None,
                    name: str = "ground") -> "RigidBodySystem":
        r"""A copy with a half-space fixed to the world: the points p with $\hat n \cdot p \le$
        `height` (`normal` need not be unit: a slope). `material` as `with_collision_geometry`'s
        (default friction 0.5: against a URDF `<collision>`'s 1.0, the pair's is 2/3)."""
        n = np.asarray(normal, float)
        if n.shape != (3,) or not np.linalg.norm(n) > 0:
            raise ValueError(f"with_ground: normal must be a non-zero 3-vector, got {normal!r}")
        n = n / np.linalg.norm(n)
        self._warn_of_unread_collisions()
        return self.with_collision_geometry("world", HalfSpace(), rotation=_rotation_to(n),
                                            translation=height * n, name=name, material=material)

    @property
    def bounds_steps(self) -> bool:
        return self.contact is not None and self.contact.moves()

    def step_size_bound(self, t, x):
        """`ContactModel.step_bound`: no geometry moves through half the thinnest one's
        thickness within one step (inf without collision geometry on a body)."""
        if not self.bounds_steps:
            return jnp.asarray(jnp.inf, x.dtype)
        return self.contact.step_bound(self.tree, x[: self.tree.nq], x[self.tree.nq:])

    def _warn_of_unread_collisions(self):
        """A ground under a plant whose file has collision elements that were not read (loaded
        without contact=True) would touch nothing: said once, with the remedy."""
        if self.collision is not None or self.source_format != "urdf":   # an MJCF's geoms may be visual only
            return
        count = pathlib.Path(self.source).read_text(errors="replace").count("<collision")
        if count:
            warnings.warn(f"{self.name}: its file has {count} <collision> element(s), not read (the plant was loaded "
                          "without contact=True), so the ground touches nothing; load it with from_urdf(..., "
                          "contact=True)", stacklevel=5)

    def joint_limit_torque(self, q, v):
        r"""The compliant limits' generalized force: $\mathrm{clip}(k p + d\dot p, 0, 2 k p)$
        towards the allowed range for each joint past a limit by p, 0 elsewhere (see the class
        docstring)."""
        if not self.limited:
            return jnp.zeros(self.tree.nv, v.dtype)
        iq, iv = (np.array(i) for i in zip(*self.limited))
        k, d = self.limit_stiffness[iv], self.limit_damping[iv]
        qi, vi = q[iq], v[iv]
        lower, upper = self.tree.position_lower[iq], self.tree.position_upper[iq]
        up = _limit_push(k, d, lower - qi, -vi)
        down = _limit_push(k, d, qi - upper, vi)
        return jnp.zeros(self.tree.nv, v.dtype).at[iv].add(up - down)

    @compiled_query
    def forward_dynamics(self, q, v, u):
        """qdd (the time derivative of v) under input u, damping, joint limits, contact and
        constraint forces."""
        self._check_sizes(q=q, v=v, u=u)
        if self.linearization == "stiff":
            return _stiffly_linearized_forward_dynamics(self, q, v, u)
        return self._forward_dynamics(q, v, u)

    def stiff_linearization(self) -> "RigidBodySystem":
        r"""A copy whose `forward_dynamics` has the same values and the derivative
        $d\dot v = H(q)^{-1}\,d\tau$ of the applied forces $\tau = B u - b \circ v +
        \tau_{lim}(q, v) + \tau_c(q, v)$ alone, the contact force's by
        `ContactModel.force_derivatives` (its springs, dampers and friction slopes, and how the
        contact points' motion and the normals' turning change them): left out are the
        derivatives of H, of the Coriolis and gravity terms, which are not stiff. For the
        matrix of the Rosenbrock W-methods' `jacobian="stiff"` (`Rosenbrock23`, `Ros34PW2`) only;
        derivatives with respect to the plant's parameters stay exact. A plant with loop or
        coupler constraints keeps its exact derivative."""
        if self.loops or self.couplers:
            return self
        return _replace_fields(self, linearization="stiff")

    def actuation(self, q, v, u):
        """The generalized force of the inputs: B u, or the `JointActuators`' (MuJoCo's servos)."""
        return self.B @ u if self.actuators is None else self.actuators.joint_forces(self.tree.joint_positions(q), v, u)

    def passive_force(self, q, v):
        r"""The joints' damping $-b \circ v$, their springs' torque (`KinematicTree.spring_torque`)
        and the fixed tendons' springs and dampers (`FixedTendons`)."""
        tau = -self.tree.damping * v
        spring = self.tree.spring_torque(q)
        if spring is not None:
            tau = tau + spring
        return tau if self.tendons is None else tau + self.tendons.forces(self.tree.joint_positions(q), v)

    def _forward_dynamics(self, q, v, u):
        tau = (self.actuation(q, v, u) + self.passive_force(q, v) + self.joint_limit_torque(q, v)
               + self.contact_force(q, v))
        if not (self.loops or self.couplers):
            return alg.aba(self.tree, q, v, tau)
        H = alg.mass_matrix(self.tree, q)
        rhs = tau - alg.bias_forces(self.tree, q, v)
        phi = self.constraint_residual(q)
        qdot = alg.configuration_derivative(self.tree, q, v)
        J, Jdot = jax.jvp(self.constraint_jacobian, (q,), (qdot,))   # J once, as the primal
        Jdot_v = Jdot @ v
        w = self.constraint_stiffness
        k = J.shape[0]
        kkt = jnp.block([[H, J.T], [J, jnp.zeros((k, k), H.dtype)]])
        sol = jnp.linalg.solve(kkt, jnp.concatenate([rhs, -Jdot_v - 2 * w * (J @ v) - w * w * phi]))
        return sol[: self.tree.nv]

    @compiled_query
    def dynamics(self, t, x, u):
        self._check_sizes(x=x)   # u: in forward_dynamics
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        return jnp.concatenate([alg.configuration_derivative(self.tree, q, v),
                                self.forward_dynamics(q, v, u)])

    def _check_sizes(self, **arrays):
        """A named error for a state x, positions q, velocities v or input u of the wrong size
        (shapes are static: nothing is evaluated)."""
        frames = {"x": (self.num_states, self.state_frame), "u": (self.num_inputs, self.input_frame),
                  "q": (self.tree.nq, None), "v": (self.tree.nv, None)}
        for name, array in arrays.items():
            size, frame = frames[name]
            if jnp.shape(array) != (size,):
                meaning = (" (MuJoCo's ctrl, one per actuator: the file has servos)" if name == "u" and
                           self.actuators is not None else "")
                names = f": {frame.coordinates}" if frame is not None else ""
                raise ValueError(f"{self.name}: {name} has shape {jnp.shape(array)}, but needs ({size},){meaning}{names}")

    def initial_state(self):
        """At rest in the file's configuration (an MJCF's `qpos0`: its free bodies where the file
        places them, its joints at their `ref`, as MuJoCo's `mj_resetData`), else the neutral
        one; each joint outside its position limits at its nearest limit (the Panda's joint 4
        at zero), and coupled joints placed by their couplers."""
        q = (self.tree.neutral_configuration() if self.default_positions is None
             else jnp.asarray(self.default_positions))
        q = jnp.clip(q, self.tree.position_lower, self.tree.position_upper)
        for coupler in self.couplers:
            iq, lq = (self.tree.q_starts[self.tree.joint_names.index(j)] for j in (coupler.joint, coupler.leader))
            q = q.at[iq].set(coupler.gear_ratio * q[lq] + coupler.offset)
        return jnp.concatenate([q, jnp.zeros(self.tree.nv)])

    # ----- loops and constraints ------------------------------------------------------------

    def loop_residual(self, q):
        """phi(q): the stacked world-position differences of every loop's frames."""
        parts, poses = [], alg.body_poses(self.tree, q)
        for loop in self.loops:
            idx = np.array([_AXES[a] for a in loop.axes])
            pa = alg.frame_pose(self.tree, q, loop.frame_a, poses=poses)[1]
            pb = alg.frame_pose(self.tree, q, loop.frame_b, poses=poses)[1]
            parts.append((pa - pb)[idx])
        return jnp.concatenate(parts) if parts else jnp.zeros(0, q.dtype)

    def loop_jacobian(self, q):
        """d phi / d q in velocity coordinates: phi_dot = J(q) v."""
        if not self.loops:
            return jnp.zeros((0, self.tree.nv), q.dtype)
        ends = alg._frame_jacobians(self.tree, q, [f for loop in self.loops for f in (loop.frame_a, loop.frame_b)])
        return jnp.concatenate([(ends[2 * i] - ends[2 * i + 1])[3 + np.array([_AXES[a] for a in loop.axes])]
                                for i, loop in enumerate(self.loops)])

    def _coupler_rows(self, q):
        """phi and J of the couplers: q_joint - rho q_leader - offset, and its gradient in v."""
        t = self.tree
        phi, J = [], np.zeros((len(self.couplers), t.nv))
        for row, c in enumerate(self.couplers):
            i, l = t.joint_names.index(c.joint), t.joint_names.index(c.leader)
            phi.append(q[t.q_starts[i]] - c.gear_ratio * q[t.q_starts[l]] - c.offset)
            J[row, t.v_starts[i]], J[row, t.v_starts[l]] = 1.0, -c.gear_ratio
        return (jnp.stack(phi) if phi else jnp.zeros(0, q.dtype)), jnp.asarray(J, q.dtype)

    def constraint_residual(self, q):
        """phi(q): the loops' residuals, then the couplers'."""
        return jnp.concatenate([self.loop_residual(q), self._coupler_rows(q)[0]])

    def constraint_jacobian(self, q):
        """d phi / d q in velocity coordinates, rows as `constraint_residual`."""
        return jnp.concatenate([self.loop_jacobian(q), self._coupler_rows(q)[1]])

    def state_constraints(self, x):
        """[|quaternion|^2 - 1 (each free body); phi(q); J(q) v]."""
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        parts = []
        quaternions = self.tree.layout.free_q[:, 3:]
        if len(quaternions):
            parts.append(jnp.sum(q[quaternions] ** 2, 1) - 1)
        if self.loops or self.couplers:
            parts += [self.constraint_residual(q), self.constraint_jacobian(q) @ v]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, x.dtype)

    def check_initial_state(self, x0):
        """Warn once per joint when x0 starts a limited joint past its position limit: the
        compliant limit then pushes it back at once, a stiff start."""
        tree, x0 = self.tree, np.asarray(x0, float)
        try:
            lower, upper = np.asarray(tree.position_lower), np.asarray(tree.position_upper)
        except jax.errors.TracerArrayConversionError:
            return
        q_owner = {tree.q_starts[i]: name for i, name in enumerate(tree.joint_names)}
        for qi, _ in self.limited:
            name, value = q_owner[qi], x0[qi]
            past = ("lower", lower[qi]) if value < lower[qi] else ("upper", upper[qi]) if value > upper[qi] else None
            if past and (self.name, name) not in _WARNED_LIMITS:
                _WARNED_LIMITS.add((self.name, name))
                warnings.warn(f"{self.name}: the start state puts joint {name!r} at {value:.6g}, past its {past[0]} "
                              f"limit {past[1]:.6g}; the compliant limit will push it back at once (a stiff start). "
                              "Start inside the limits, or build the plant with joint_limits=False", stacklevel=4)

    def failure_hint(self, x):
        """Names a singular mass matrix H(q) at x (the joints spanning its null space), the usual
        reason a rigid body's simulation stops at once: a link moving no mass or inertia."""
        tree, x = self.tree, np.asarray(x, float)
        if x.shape != (self.num_states,) or not np.all(np.isfinite(x)):
            return None
        H = np.asarray(alg.mass_matrix(tree, x[: tree.nq]))
        eigenvalues, vectors = np.linalg.eigh((H + H.T) / 2)
        if np.all(np.isfinite(H)) and eigenvalues[0] > 1e-12 * max(eigenvalues[-1], 1e-300):
            return None
        owner = np.repeat(np.arange(len(tree.joint_names)), np.diff([*tree.v_starts, tree.nv]))
        moved = dict.fromkeys(tree.joint_names[owner[k]] for k in np.flatnonzero(np.abs(vectors[:, 0]) > 0.1))
        return (f"the mass matrix H(q) of {self.name} is singular at q = {np.round(x[: tree.nq], 6).tolist()} "
                f"(smallest eigenvalue {eigenvalues[0]:.3g}): joint(s) {', '.join(moved)} move no mass or inertia "
                "there; give the links beyond those joints mass and inertia, or weld the joints")

    # ----- energy ---------------------------------------------------------------------------

    @compiled_query
    def energy(self, x):
        """Kinetic plus gravity's and the joint springs' potential energy. The contact springs'
        energy is not in it: during an impact it rises by what they store, and it falls as
        their dissipation acts."""
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        energy = alg.kinetic_energy(self.tree, q, v) + alg.potential_energy(self.tree, q) + self.tree.spring_energy(q)
        return energy if self.tendons is None else energy + self.tendons.energy(self.tree.joint_positions(q))

    @compiled_query
    def frame_pose(self, q, frame: str):
        """World (R, p) of a named frame (a URDF link)."""
        return alg.frame_pose(self.tree, q, frame)


def _rotation_to(n):
    """A rotation whose z axis is the unit vector n."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, n)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(n, x), n])


def _joint_link_pairs(tree) -> tuple:
    """(parent link, child link) of every one-dof joint whose parent is not the world (Drake
    filters their collisions)."""
    pairs = []
    for i, (kind, parent) in enumerate(zip(tree.joint_types, tree.parents)):
        if kind != JointType.FLOATING and parent >= 0:
            pairs.append((tree.body_names[parent], tree.body_names[i]))
    return tuple(pairs)


def _replace_fields(module, **fields):
    """A copy of an equinox module with some fields (static ones too) replaced."""
    copy = object.__new__(type(module))
    for field in dataclasses.fields(module):
        object.__setattr__(copy, field.name, fields.get(field.name, getattr(module, field.name)))
    return copy


def _limit_push(k, d, p, p_dot):
    """clip(k p + d p_dot, 0, 2 k p) for a joint past its limit by p (0 when p <= 0): the
    damper neither pulls nor outpushes the spring, so the push is 0 at the limit whatever p_dot."""
    spring = k * jnp.maximum(p, 0.0)
    # `where`, not the clip alone: inside the limits clip(d p_dot, 0, 0) is 0, but at rest
    # (p_dot = 0) its ties would give the linearization a derivative d/4 in p_dot
    return jnp.where(p > 0, jnp.clip(spring + d * p_dot, 0.0, 2 * spring), 0.0)


def _limited_joints(tree) -> tuple:
    """(q index, v index) of every one-dof joint with a finite lower or upper position limit
    (every one-dof joint when the limits are traced values)."""
    one_dof = [i for i, kind in enumerate(tree.joint_types) if kind != JointType.FLOATING]
    try:
        lower, upper = np.asarray(tree.position_lower), np.asarray(tree.position_upper)
    except jax.errors.TracerArrayConversionError:
        finite = [True] * len(one_dof)
    else:
        finite = [np.isfinite(lower[tree.q_starts[i]]) or np.isfinite(upper[tree.q_starts[i]]) for i in one_dof]
    return tuple((tree.q_starts[i], tree.v_starts[i]) for i, f in zip(one_dof, finite) if f)


def _limit_gains(tree, limited, period):
    """Per velocity coordinate: k = H_ii w^2, d = 2 H_ii w (w = 2 pi / period, H at the neutral
    configuration) for the limited joints, 0 for the others."""
    if not period > 0:
        raise ValueError(f"limit_period must be a positive time in seconds, got {period}")
    omega = 2 * np.pi / period
    iv = np.array([v for _, v in limited], int)
    try:  # on the host (nothing to compile) ...
        inertia = np.asarray(_neutral_joint_inertias(tree))[iv] if limited else np.zeros(0)
        stiffness, damping = np.zeros(tree.nv), np.zeros(tree.nv)
        stiffness[iv], damping[iv] = inertia * omega ** 2, 2 * inertia * omega
        return device_array(stiffness), device_array(damping)
    except jax.errors.TracerArrayConversionError:  # ... or, for traced leaves, the same numbers traced
        inertia = jnp.diagonal(alg.mass_matrix(tree, tree.neutral_configuration()))[iv]
        zeros = jnp.zeros(tree.nv, inertia.dtype)
        return zeros.at[iv].set(inertia * omega ** 2), zeros.at[iv].set(2 * inertia * omega)


def _neutral_joint_inertias(tree):
    r"""diag H(q_0) in NumPy, for a revolute joint with world axis a at point o the sum over its
    subtree of $a^T \bar I_b a + m_b |a \times (c_b - o)|^2$, for a prismatic joint the
    subtree's mass. Host work at construction, kept beside the JAX kinematics because it is
    cheap where they are not: 1.4 ms (cart-pole) to 8 ms (Solo-12, 18 dof), against 0.5-1.5 s
    to compile the JAX mass matrix once per tree structure and 3-9 s to run it eagerly."""
    R = np.zeros((tree.num_bodies, 3, 3))
    p = np.zeros((tree.num_bodies, 3))
    for i, (parent, kind) in enumerate(zip(tree.parents, tree.joint_types)):
        if kind == JointType.FLOATING:  # at the neutral configuration: the world frame
            R[i] = np.eye(3)
            continue
        R_up, p_up = (R[parent], p[parent]) if parent >= 0 else (np.eye(3), np.zeros(3))
        R[i], p[i] = R_up @ np.asarray(tree.origin_rotation[i]), R_up @ np.asarray(tree.origin_translation[i]) + p_up
    mass = np.asarray(tree.mass)
    centre = np.einsum("nij,nj->ni", R, np.asarray(tree.com)) + p
    inertia = np.einsum("nij,njk,nlk->nil", R, np.asarray(tree.inertia), R)
    layout = tree.layout
    H = np.zeros(tree.nv)
    for i, kind in enumerate(tree.joint_types):
        if kind == JointType.FLOATING:
            continue
        subtree = layout.order[np.flatnonzero(layout.subtree[layout.position[i]])]
        a = R[i] @ np.asarray(tree.axes[i])
        if kind == JointType.PRISMATIC:
            H[tree.v_starts[i]] = mass[subtree].sum()
        else:
            arm = np.cross(a, centre[subtree] - p[i])
            H[tree.v_starts[i]] = np.einsum("i,nij,j->", a, inertia[subtree], a) + np.sum(mass[subtree] * np.sum(arm ** 2, 1))
    return H if tree.armature is None else H + np.asarray(tree.armature)


def _stiffly_linearized_forward_dynamics(plant, q, v, u):
    """`plant.forward_dynamics` with the derivative of `RigidBodySystem.stiff_linearization`."""
    arrays, static = eqx.partition(plant, eqx.is_array)  # numbers stay static, as in the plant's queries
    return _stiff_forward_dynamics(static, arrays, q, v, u)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _stiff_forward_dynamics(static, arrays, q, v, u):
    return _exact(static, arrays).forward_dynamics(q, v, u)


def _exact(static, arrays):
    """The plant with its exact derivative: its queries' programs (traced once per structure)
    are the ones the other evaluations of the dynamics use."""
    return _replace_fields(eqx.combine(arrays, static), linearization="exact")


@functools.partial(_stiff_forward_dynamics.defjvp, symbolic_zeros=True)
def _stiff_derivative(static, primals, tangents):
    arrays, q, v, u = primals
    d_arrays, dq, dv, du = tangents
    zero = lambda t, like: jnp.zeros_like(like) if isinstance(t, jax.custom_derivatives.SymbolicZero) else t  # noqa: E731
    dq, dv, du = zero(dq, q), zero(dv, v), zero(du, u)
    plant = _exact(static, arrays)
    tree = plant.tree
    dtau = (jax.jvp(plant.actuation, (q, v, u), (dq, dv, du))[1] + jax.jvp(plant.passive_force, (q, v), (dq, dv))[1]
            + jax.jvp(plant.joint_limit_torque, (q, v), (dq, dv))[1])
    if plant.contact is not None:
        K, D = plant.contact.force_derivatives(tree, q, v)
        dtau = dtau + K @ alg.velocity_of_configuration_change(tree, q, dq) + D @ dv
    dqdd = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(alg.mass_matrix(tree, q)), dtau)
    of_parameters = alg._jvp_of_live(lambda a: _exact(static, a).forward_dynamics(q, v, u), (arrays,), (d_arrays,))
    if of_parameters is None:
        return plant.forward_dynamics(q, v, u), dqdd
    qdd, exact_in_parameters = of_parameters
    return qdd, dqdd + exact_in_parameters


@compiled_query
def _contact_results(plant, x):
    """`contact_results`, compiled once per plant structure (eager, the narrow phase and the
    kinematics cost seconds op by op; inside a trace this is inlined)."""
    return plant.contact.results(plant.tree, x[: plant.tree.nq], x[plant.tree.nq:])


__all__ = ["CouplerConstraint", "LoopConstraint", "RigidBodySystem", "URDFError"]
