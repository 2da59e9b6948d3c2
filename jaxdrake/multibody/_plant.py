r"""`RigidBodySystem`: the manipulator equations as a `System` (notes, D.3.1):

$$H(q)\dot v + C(q, v) v + G(q) = B u - b \circ v + J_\phi^T(q) \lambda, \qquad \phi(q) = 0,$$

state $x = [q; v]$ ($\dot q = v$ except for a floating base's quaternion), input u through B,
URDF joint damping b, and closed kinematic loops as constraints $\phi(q) = 0$ whose forces
$\lambda$ come from the KKT system, with Baumgarte stabilization
$\ddot\phi + 2\omega\dot\phi + \omega^2\phi = 0$ so that drift decays.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from ..systems import Frame, System
from ..systems._system import _static
from . import _algorithms as alg
from ._tree import KinematicTree, URDFError, tree_from_pinocchio, tree_from_urdf

_AXES = {"x": 0, "y": 1, "z": 2}


@dataclasses.dataclass(frozen=True)
class LoopConstraint:
    """Closes a kinematic loop: the origins of frames `frame_a` and `frame_b` coincide along
    the world `axes` (e.g. `("x", "z")` for a planar linkage in the x-z plane)."""

    frame_a: str
    frame_b: str
    axes: tuple = ("x", "y", "z")


class RigidBodySystem(System):
    r"""A tree of rigid bodies (from a URDF or a Pinocchio model), possibly with loop closures.

    **Construction:** `RigidBodySystem.from_urdf(path, floating_base=False, actuated=None,
    gravity=True, loops=())` or `RigidBodySystem.from_pinocchio(model)`.

    - B: the joints named by the URDF's `<transmission>`s, or `actuated` (joint names), or
      else every joint but a floating base; one input per actuated joint, in that order.
    - State frame: joint positions then velocities (`<joint>`, `<joint>dot`; a floating base
      has x, y, z, qx, qy, qz, qw and vx, vy, vz, wx, wy, wz, in its own frame).
    - Input limits: the actuated joints' `<limit effort>` (|u_k| <= effort, as Drake's
      parser makes actuator effort limits), unless `effort_limits=False`; the simulator
      locates the saturation instants as events.
    - Limits, damping and friction of the URDF are on `tree`; damping acts in the dynamics,
      Coulomb friction and position limits are recorded, not applied.

    The tree's masses, inertias, lengths and axes are pytree leaves: `jax.grad` with respect
    to a link mass works (system identification); build the system outside `jit`.
    """

    tree: KinematicTree
    B: jax.Array
    loops: tuple = _static(default=())
    constraint_stiffness: float = 20.0

    def __init__(self, tree: KinematicTree, actuated_joints=None, *, loops=(),
                 constraint_stiffness: float = 20.0, effort_limits: bool = True):
        names = tree.joint_names
        if actuated_joints is None:
            actuated_joints = [n for n, k in zip(names, tree.joint_types) if k != "floating"]
        B = np.zeros((tree.nv, len(actuated_joints)))
        for col, joint in enumerate(actuated_joints):
            if joint not in names:
                raise ValueError(f"{tree.robot_name}: no joint {joint!r} to actuate; the joints are {list(names)}")
            i = names.index(joint)
            if tree.joint_types[i] == "floating":
                raise ValueError(f"{tree.robot_name}: the floating base cannot be actuated by a joint input")
            B[tree.v_starts[i], col] = 1.0
        self.tree, self.B = tree, jnp.asarray(B)
        effort = np.asarray(tree.effort_limit)[np.argmax(B, axis=0)] if B.size else np.zeros(0)
        limits = (-effort, effort) if effort_limits and np.any(np.isfinite(effort)) else None
        self.loops = tuple(loops)
        for loop in self.loops:
            for frame in (loop.frame_a, loop.frame_b):
                if frame not in tree.frame_names:
                    raise ValueError(f"{tree.robot_name}: loop constraint frame {frame!r} is not a link "
                                     f"of the tree; the links are {list(tree.frame_names)}")
            if not loop.axes or any(a not in _AXES for a in loop.axes):
                raise ValueError(f"loop constraint axes must be among 'x', 'y', 'z', got {loop.axes}")
        self.constraint_stiffness = constraint_stiffness
        state = Frame(f"{tree.robot_name}State", tree.position_names() + tree.velocity_names())
        num_loop = sum(len(loop.axes) for loop in self.loops)
        super().__init__(num_continuous_states=tree.nq + tree.nv, num_inputs=len(actuated_joints),
                         direct_feedthrough=False, time_invariant=True, input_limits=limits,
                         num_state_constraints=2 * num_loop + tree.has_floating_base,
                         input_frame=Frame(f"{tree.robot_name}Input", tuple(actuated_joints)),
                         state_frame=state, output_frame=state)

    @classmethod
    def from_urdf(cls, path, *, floating_base: bool = False, actuated=None, gravity: bool = True,
                  welded=(), loops=(), constraint_stiffness: float = 20.0,
                  effort_limits: bool = True) -> "RigidBodySystem":
        """Load a URDF (local files only: `package://` mesh paths are never resolved); joints
        named in `welded` are fixed at zero."""
        with jax.ensure_compile_time_eval():  # parsing is host work, also inside jit / vmap
            tree, transmitted = tree_from_urdf(pathlib.Path(path), floating_base=floating_base,
                                               gravity=(0.0, 0.0, -9.81) if gravity else (0.0, 0.0, 0.0),
                                               welded=tuple(welded))
        if actuated is None and transmitted:
            actuated = list(transmitted)
        return cls(tree, actuated, loops=loops, constraint_stiffness=constraint_stiffness,
                   effort_limits=effort_limits)

    @classmethod
    def from_pinocchio(cls, model, *, actuated=None, loops=(),
                       constraint_stiffness: float = 20.0) -> "RigidBodySystem":
        """From a Pinocchio `pin.Model` (its gravity, damping and limits come along)."""
        return cls(tree_from_pinocchio(model), actuated, loops=loops,
                   constraint_stiffness=constraint_stiffness)

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

    def manipulator_dynamics(self, q, v):
        """(H, C v, G, B) with H(q) qdd + C(q, v) v + G(q) = B u (the notes' signs)."""
        t = self.tree
        return (alg.mass_matrix(t, q), alg.bias_forces(t, q, v, gravity=False),
                alg.gravity_forces(t, q), self.B)

    def inverse_dynamics(self, q, v, qdd):
        """The generalized force H qdd + C v + G + b o v that produces qdd (damping included)."""
        return alg.rnea(self.tree, q, v, qdd) + self.tree.damping * v

    def forward_dynamics(self, q, v, u):
        """qdd (the time derivative of v) under input u, damping and loop-constraint forces."""
        tau = self.B @ u - self.tree.damping * v
        if not self.loops:
            return alg.aba(self.tree, q, v, tau)
        H = alg.mass_matrix(self.tree, q)
        rhs = tau - alg.bias_forces(self.tree, q, v)
        J = self.loop_jacobian(q)
        phi = self.loop_residual(q)
        qdot = alg.configuration_derivative(self.tree, q, v)
        Jdot_v = jax.jvp(lambda q_: self.loop_jacobian(q_) @ v, (q,), (qdot,))[1]
        w = self.constraint_stiffness
        k = J.shape[0]
        kkt = jnp.block([[H, J.T], [J, jnp.zeros((k, k), H.dtype)]])
        sol = jnp.linalg.solve(kkt, jnp.concatenate([rhs, -Jdot_v - 2 * w * (J @ v) - w * w * phi]))
        return sol[: self.tree.nv]

    def dynamics(self, t, x, u):
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        return jnp.concatenate([alg.configuration_derivative(self.tree, q, v),
                                self.forward_dynamics(q, v, u)])

    def initial_state(self):
        return jnp.concatenate([self.tree.neutral_configuration(), jnp.zeros(self.tree.nv)])

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
        parts = []
        for loop in self.loops:
            idx = 3 + np.array([_AXES[a] for a in loop.axes])
            parts.append((alg.frame_jacobian(self.tree, q, loop.frame_a)
                          - alg.frame_jacobian(self.tree, q, loop.frame_b))[idx])
        return jnp.concatenate(parts) if parts else jnp.zeros((0, self.tree.nv), q.dtype)

    def state_constraints(self, x):
        """[|quaternion|^2 - 1 (floating base); phi(q); J(q) v]."""
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        parts = []
        if self.tree.has_floating_base:
            s = self.tree.q_starts[self.tree.joint_types.index("floating")]
            parts.append(jnp.atleast_1d(jnp.sum(q[s + 3: s + 7] ** 2) - 1))
        if self.loops:
            parts += [self.loop_residual(q), self.loop_jacobian(q) @ v]
        return jnp.concatenate(parts) if parts else jnp.zeros(0, x.dtype)

    # ----- energy ---------------------------------------------------------------------------

    def energy(self, x):
        """Kinetic plus potential energy."""
        q, v = x[: self.tree.nq], x[self.tree.nq:]
        return alg.kinetic_energy(self.tree, q, v) + alg.potential_energy(self.tree, q)

    def frame_pose(self, q, frame: str):
        """World (R, p) of a named frame (a URDF link)."""
        return alg.frame_pose(self.tree, q, frame)


__all__ = ["LoopConstraint", "RigidBodySystem", "URDFError"]
