r"""Featherstone's algorithms on a `KinematicTree`, in JAX, level by level.

Inverse dynamics (RNEA), the mass matrix (CRBA), forward dynamics (ABA), forward kinematics
and frame Jacobians (R. Featherstone, *Rigid Body Dynamics Algorithms*, Springer 2008,
ch. 5-7), written in *world coordinates*: every spatial vector and inertia is expressed in
one fixed frame, world-aligned, whose origin O is the world's (the floating base's position
for a floating-base tree, which keeps float32 accurate far from the world origin). Then

$$V_i = V_{\lambda(i)} + s_i \dot q_i, \qquad
  A_i = A_{\lambda(i)} + s_i \ddot q_i + V_i \times s_i \dot q_i$$

need no coordinate transforms, so velocities, accelerations and the forces summed over
subtrees are products with the tree's static subtree matrix (one batched operation), and
the composite inertias of CRBA are subtree sums too. Only forward kinematics and the two
sweeps of ABA recurse, one batched step per tree depth (`TreeLayout`): the traced program
grows with the depth of the tree, not with the number of bodies (as MJX's scans over
depth). `vmap`, `grad` and float32 apply.

Conventions: spatial vectors angular first, $[\omega; v_O]$ with $v_O$ the velocity of the
body point at O; a spatial inertia is kept as (m, h = m c, $\bar I$ the rotational inertia
about O); gravity enters as a fictitious base acceleration $a_0 = -[0; g]$; generalized forces
are those of the joint coordinates (for a floating base, the force and torque on the base in
its own frame, Pinocchio's).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._spatial import force_cross, motion_cross, quaternion_matrix, skew
from ._tree import KinematicTree

# ----- kinematics -----------------------------------------------------------------------------


def _mv(M, x):
    """Batched matrix-vector product M x, written as a sum over the (small, static) inner
    dimension of broadcast products: elementwise work that XLA fuses with its neighbours and
    vectorizes over a vmapped batch (a `dot` or a `reduce` over 3 or 6 entries would be a
    kernel of its own, costlier to compile and, batched on a CPU, to run)."""
    return sum(M[..., :, k] * x[..., k, None] for k in range(x.shape[-1]))


def _mm(A, B):
    """Batched matrix product A B (see `_mv`)."""
    return sum(A[..., :, k, None] * B[..., k, None, :] for k in range(A.shape[-1]))


def _dot(a, b):
    """Batched inner product over the last axis (see `_mv`)."""
    return sum(a[..., k] * b[..., k] for k in range(a.shape[-1]))


def _rotation_about(axis, angle):
    """Rodrigues' formula, batched: rotations by `angle[k]` about the unit `axis[k]`."""
    K = skew(axis)
    s, c = jnp.sin(angle)[:, None, None], jnp.cos(angle)[:, None, None]
    return jnp.eye(3, dtype=K.dtype) + s * K + (1 - c) * _mm(K, K)


def _kinematics(tree: KinematicTree, q):
    """World rotations R (n, 3, 3) and positions p (n, 3) of the body frames relative to O,
    in level order, and the motion subspaces: S1 (m, 6), one column per one-dof body, and
    the floating base's 6x6 S0 (None without one), columns [v_lin; omega] in its frame."""
    L = tree.layout
    f = int(L.floating)
    one_dof = L.order[f:]
    axis = tree.axes[one_dof]
    angle = q[L.q_index]
    revolute = jnp.asarray(L.revolute, q.dtype)
    R_local = _mm(tree.origin_rotation[one_dof], _rotation_about(axis, angle * revolute))
    p_local = tree.origin_translation[one_dof] + _mv(tree.origin_rotation[one_dof],
                                                     axis * (angle * (1 - revolute))[:, None])
    if f:
        R_root, p_root = quaternion_matrix(q[3:7]), jnp.zeros(3, q.dtype)
    else:  # the world
        R_root, p_root = jnp.eye(3, dtype=q.dtype), jnp.zeros(3, q.dtype)

    def one_depth(above, local):
        (R_above, p_above), (R_loc, p_loc, parent) = above, local
        R_parent, p_parent = _from_parents(L, parent, R_above), _from_parents(L, parent, p_above)
        R_new = _mm(R_parent, R_loc)
        p_new = _mv(R_parent, p_loc) + p_parent
        return (R_new, p_new), (R_new, p_new)

    init = (jnp.broadcast_to(R_root, (L.width, 3, 3)), jnp.broadcast_to(p_root, (L.width, 3)))
    eye = jnp.eye(3, dtype=q.dtype)
    _, (R_slots, p_slots) = _over_depths(one_depth, init, (
        _to_slots(L, R_local, eye), _to_slots(L, p_local, jnp.zeros(3, q.dtype)), L.parent_of_slot))
    R, p = _from_slots(L, R_slots), _from_slots(L, p_slots)
    if f:
        R, p = jnp.concatenate([R_root[None], R]), jnp.concatenate([p_root[None], p])
    axis_world = _mv(R[f:], axis)
    S1 = jnp.concatenate([axis_world * revolute[:, None],
                          jnp.cross(p[f:], axis_world) * revolute[:, None]
                          + axis_world * (1 - revolute)[:, None]], axis=1)
    S0 = None
    if f:
        zero = jnp.zeros((3, 3), q.dtype)
        S0 = jnp.block([[zero, R[0]], [R[0], zero]])
    return R, p, S1, S0


_UNROLLED_DEPTHS = 2


def _over_depths(step, init, depths, *, reverse=False):
    """`lax.scan` of `step` over the tree's depths: one traced step whatever the depth, which
    keeps compile time low. Trees of at most `_UNROLLED_DEPTHS` depths (an acrobot, a
    cart-pole) unroll it: there the loop's overhead outweighs its small steps (the acrobot's
    collocation Hessian 9.6 -> 6.4 ms per call on a CPU, compile time unchanged). (Unrolled,
    the 7-dof ABA ran 1.1x faster on an H100 at a batch of 10^6 and the floating quadruped's
    0.85x, at twice the compile time.)"""
    length = len(jax.tree.leaves(depths)[0])
    return jax.lax.scan(step, init, depths, reverse=reverse, unroll=length <= _UNROLLED_DEPTHS)


def _to_slots(L, x, fill):
    """Per one-dof body (level order) -> padded per depth and slot (depths, width, ...)."""
    return _with_fill(x, fill)[_slot_rows(L)]


def _slot_rows(L):
    """(depths, width): the row of each slot in the per-one-dof-body arrays (with their fill row)."""
    return L.slots - L.first_scanned


def _with_fill(x, fill):
    """x (k, ...) with one more row, `fill`: the value an empty slot reads."""
    return jnp.concatenate([x, jnp.broadcast_to(fill, (1,) + x.shape[1:]).astype(x.dtype)])


def _from_slots(L, x):
    """The inverse of `_to_slots`: (depths, width, ...) -> per one-dof body, level order."""
    return x.reshape((-1,) + x.shape[2:])[L.unslot]


def _from_parents(L, parent, x):
    """Each slot's parent's value: x (width, ...) of the depth above, `parent` the slots'
    parent slots (a chain has one slot: nothing to gather)."""
    return x if L.width == 1 else x[parent]


def _to_parents(L, parent, x):
    """Sum each slot's x into its parent's slot (the transpose of `_from_parents`)."""
    return x if L.width == 1 else jax.ops.segment_sum(x, parent, num_segments=L.width)


def _dof_columns(L, S1, S0):
    """The motion subspace of every velocity coordinate, rows (nv, 6), in the tree's order."""
    rows = S1 if S0 is None else jnp.concatenate([S0.T, S1])
    return rows[L.dof_level_order]


def _joint_velocity(L, S1, S0, v):
    """s_i qdot_i of every body's own joint (n, 6), level order, from velocity coordinates v."""
    one = S1 * v[L.level_dofs[6 * int(L.floating):]][:, None]
    return one if S0 is None else jnp.concatenate([(S0 @ v[:6])[None], one])


def _subtree_sum(L, x):
    """For every body, the sum of x over its subtree (x: (n, ...), level order)."""
    return jnp.tensordot(jnp.asarray(L.subtree, x.dtype), x, axes=1)


def _ancestor_sum(L, x):
    """For every body, the sum of x over its ancestors and itself."""
    return jnp.tensordot(jnp.asarray(L.subtree.T, x.dtype), x, axes=1)


def _base_acceleration(tree, dtype, gravity: bool):
    g = tree.gravity.astype(dtype) if gravity else jnp.zeros(3, dtype)
    return jnp.concatenate([jnp.zeros(3, dtype), -g])


# ----- spatial algebra, batched over the leading axis ----------------------------------------


def _world_inertias(tree, R, p):
    """Every body's spatial inertia about O, world axes, as (m, h = m c, I_bar) in level order:
    $I\\,[\\omega; v] = [\\bar I \\omega + h \\times v;\\ m v - h \\times \\omega]$."""
    L = tree.layout
    m = tree.mass[L.order].astype(R.dtype)
    c = _mv(R, tree.com[L.order]) + p
    I_com = _mm(_mm(R, tree.inertia[L.order]), jnp.swapaxes(R, 1, 2))
    eye = jnp.eye(3, dtype=R.dtype)
    I_bar = I_com + m[:, None, None] * (jnp.sum(c * c, -1)[:, None, None] * eye - c[:, :, None] * c[:, None, :])
    return m, m[:, None] * c, I_bar


def _apply_inertia(inertia, v):
    m, h, I_bar = inertia
    w, u = v[..., :3], v[..., 3:]
    return jnp.concatenate([_mv(I_bar, w) + jnp.cross(h, u),
                            m[..., None] * u - jnp.cross(h, w)], -1)


def _dense_inertia(inertia):
    """The 6x6 matrices of (m, h, I_bar)."""
    m, h, I_bar = inertia
    H = skew(h)
    eye = jnp.eye(3, dtype=I_bar.dtype)
    return jnp.concatenate([jnp.concatenate([I_bar, H], -1),
                            jnp.concatenate([jnp.swapaxes(H, -1, -2), m[..., None, None] * eye], -1)], -2)


def _solve_spd6(M, b):
    """M^{-1} b for one symmetric positive-definite 6x6 M, by 3x3 blocks (Schur complement)."""
    A, B, C = M[:3, :3], M[:3, 3:], M[3:, 3:]
    C_inv = _inverse3(C)
    BC = B @ C_inv
    x1 = _inverse3(A - BC @ B.T) @ (b[:3] - BC @ b[3:])
    return jnp.concatenate([x1, C_inv @ (b[3:] - B.T @ x1)])


def _inverse3(M):
    """The inverse of a 3x3 matrix by its adjugate."""
    a, b, c = M[0], M[1], M[2]
    adj = jnp.stack([jnp.cross(b, c), jnp.cross(c, a), jnp.cross(a, b)], axis=1)
    return adj / jnp.dot(a, jnp.cross(b, c))


def _from_level_order(L, x):
    """Velocity-coordinate vector in level order -> the tree's coordinate order."""
    return x[L.dof_level_order]


# ----- the algorithms ---------------------------------------------------------------------------


def _velocities(tree, q, v):
    R, p, S1, S0 = _kinematics(tree, q)
    L = tree.layout
    joint = _joint_velocity(L, S1, S0, v)
    return R, p, S1, S0, joint, _ancestor_sum(L, joint)


def rnea(tree: KinematicTree, q, v, a, *, gravity: bool = True):
    r"""Inverse dynamics $\tau = H(q)\dot v + C(q, v) v + G(q)$ (recursive Newton-Euler): the
    body velocities and accelerations are ancestor sums, the joint forces subtree sums."""
    L = tree.layout
    R, p, S1, S0, joint, V = _velocities(tree, q, v)
    joint_acc = _joint_velocity(L, S1, S0, a) + motion_cross(V, joint)
    A = _ancestor_sum(L, joint_acc) + _base_acceleration(tree, q.dtype, gravity)
    inertia = _world_inertias(tree, R, p)
    F = _subtree_sum(L, _apply_inertia(inertia, A) + force_cross(V, _apply_inertia(inertia, V)))
    return _project_forces(L, S1, S0, F)


def _project_forces(L, S1, S0, F):
    """tau = S^T F per joint, in the tree's coordinate order."""
    f = int(L.floating)
    tau = _dot(S1, F[f:])
    if S0 is not None:
        tau = jnp.concatenate([S0.T @ F[0], tau])
    return _from_level_order(L, tau)


def mass_matrix(tree: KinematicTree, q):
    r"""H(q) by composite rigid bodies: with $I^c_i$ the inertia of body i's subtree,
    $H_{kl} = s_k^T I^c_{b(k)} s_l$ when coordinate l's body is an ancestor of (or is)
    coordinate k's body $b(k)$, its transpose in the other case, and 0 otherwise."""
    L = tree.layout
    R, p, S1, S0 = _kinematics(tree, q)
    composite = tuple(_subtree_sum(L, x) for x in _world_inertias(tree, R, p))
    columns = _dof_columns(L, S1, S0)                                   # (nv, 6)
    per_dof = tuple(x[L.dof_body] for x in composite)
    F = _apply_inertia(per_dof, columns)                                # I^c_{b(k)} s_k
    M = _mm(F, columns.T)  # (a batched `dot` of these small matrices is slower on a CPU)
    ancestor = jnp.asarray(L.ancestor, M.dtype)
    same = jnp.asarray(L.ancestor * L.ancestor.T, M.dtype)
    return ancestor * M + (ancestor.T - same) * M.T


def bias_forces(tree: KinematicTree, q, v, *, gravity: bool = True):
    """C(q, v) v + G(q) (gravity=False: C(q, v) v alone)."""
    return rnea(tree, q, v, jnp.zeros_like(v), gravity=gravity)


def gravity_forces(tree: KinematicTree, q):
    """G(q): the generalized gravity term, on the left of H qdd + C qd + G = tau."""
    return rnea(tree, q, jnp.zeros(tree.nv, q.dtype), jnp.zeros(tree.nv, q.dtype))


def aba(tree: KinematicTree, q, v, tau, *, gravity: bool = True):
    r"""Forward dynamics $\dot v = H^{-1}(\tau - C v - G)$ by the articulated-body algorithm.

    Backward over the depths (deepest first), for the one-dof bodies of a depth at once:
    $U = I^A s$, $D = s^T U$, $u = \tau - s^T p^A$, and the parent receives
    $I^A - U U^T / D$ and $p^A + I^a c + U u / D$ (no transforms: world coordinates).
    Forward: $A = A_{\lambda} + c$, $\ddot q = (u - U^T A) / D$, $A \mathrel{+}= s \ddot q$.
    A floating base's acceleration is $(I^A)^{-1}(S_0 \tau_0 - p^A)$."""
    L = tree.layout
    f = int(L.floating)
    R, p, S1, S0, joint, V = _velocities(tree, q, v)
    c = motion_cross(V, joint)                       # s_dot qdot (zero for the floating base)
    inertia = _world_inertias(tree, R, p)
    I_A = _dense_inertia(inertia)
    p_A = force_cross(V, _apply_inertia(inertia, V))
    tau_level = tau[L.level_dofs]

    dtype, zero6 = q.dtype, jnp.zeros(6, q.dtype)
    unit = jnp.zeros(6, dtype).at[0].set(1.0)  # empty slots: an identity inertia along e_1, D = 1
    # per one-dof body, with one padding row for empty slots; each depth gathers its rows inside
    # the loop (stacking them per depth beforehand was a transposing copy of every inertia:
    # 45% of the time on a GPU)
    I_A1, p_A1, S1p, c1, tau1 = (_with_fill(x, fill) for x, fill in (
        (I_A[f:], jnp.eye(6, dtype=dtype)), (p_A[f:], zero6), (S1, unit), (c[f:], zero6),
        (tau_level[6 * f:], jnp.zeros((), dtype))))

    def backward(passed, depth):
        """One depth, deepest first: the articulated inertia and bias of its bodies (their
        own plus what their children passed up), and what they pass to their parents."""
        (Ia_in, pa_in), (rows, parent, valid) = passed, depth
        IA, pA, s, c, t = I_A1[rows] + Ia_in, p_A1[rows] + pa_in, S1p[rows], c1[rows], tau1[rows]
        U = _mv(IA, s)
        D_inv = 1.0 / _dot(s, U)
        u = t - _dot(s, pA)
        Ia = IA - D_inv[:, None, None] * U[:, :, None] * U[:, None, :]
        pa = pA + _mv(Ia, c) + U * (D_inv * u)[:, None]
        valid = valid.astype(IA.dtype)
        up = (_to_parents(L, parent, Ia * valid[:, None, None]), _to_parents(L, parent, pa * valid[:, None]))
        return up, (U, D_inv, u)

    depths = (jnp.asarray(_slot_rows(L)), L.parent_of_slot, L.valid)
    init = (jnp.zeros((L.width, 6, 6), dtype), jnp.zeros((L.width, 6), dtype))
    (Ia_root, pa_root), (U, D_inv, u) = _over_depths(backward, init, depths, reverse=True)

    a0 = _base_acceleration(tree, dtype, gravity)
    if f:
        A_root = _solve_spd6(I_A[0] + Ia_root[0], S0 @ tau_level[:6] - p_A[0] - pa_root[0])
        qdd_root = S0.T @ (A_root - a0)
    else:
        A_root = a0

    def forward(A_above, depth):
        """One depth, root first: joint accelerations and body accelerations."""
        rows, U, D_inv, u, parent = depth
        A = _from_parents(L, parent, A_above) + c1[rows]
        qdd = D_inv * (u - _dot(U, A))
        return A + S1p[rows] * qdd[:, None], qdd

    _, qdd = _over_depths(forward, jnp.broadcast_to(A_root, (L.width, 6)),
                          (depths[0], U, D_inv, u, L.parent_of_slot))
    qdd = _from_slots(L, qdd)
    if f:
        qdd = jnp.concatenate([qdd_root, qdd])
    return _from_level_order(L, qdd)


# ----- frames -----------------------------------------------------------------------------------


def _offset(tree, q):
    """O in world coordinates: the floating base's position, else the world origin."""
    return q[:3] if tree.layout.floating else jnp.zeros(3, q.dtype)


def body_poses(tree: KinematicTree, q):
    """World rotation and position of every body frame: arrays (n, 3, 3) and (n, 3)."""
    R, p, _, _ = _kinematics(tree, q)
    position = tree.layout.position
    return R[position], p[position] + _offset(tree, q)


def frame_pose(tree: KinematicTree, q, frame: str, *, poses=None):
    """World rotation and position of a named frame (any URDF link). `poses`: the bodies'
    `body_poses(tree, q)`, when the caller already has them."""
    k = _frame_index(tree, frame)
    body = tree.frame_bodies[k]
    R_f, p_f = tree.frame_rotation[k], tree.frame_translation[k]
    if body < 0:
        return R_f, p_f
    Rs, ps = body_poses(tree, q) if poses is None else poses
    return Rs[body] @ R_f, Rs[body] @ p_f + ps[body]


def frame_jacobian(tree: KinematicTree, q, frame: str):
    r"""The 6 x nv Jacobian of a named frame, world-aligned: $[\omega; \dot p] = J(q)\, v$ with
    $\omega$ the frame's angular velocity and $\dot p$ the velocity of its origin, both in
    world coordinates: the columns $[s_\omega; s_v + s_\omega \times p]$ of the frame body's
    ancestors' joints."""
    k = _frame_index(tree, frame)
    body = tree.frame_bodies[k]
    if body < 0:
        return jnp.zeros((6, tree.nv), q.dtype)
    L = tree.layout
    R, p, S1, S0 = _kinematics(tree, q)
    b = L.position[body]
    point = R[b] @ tree.frame_translation[k] + p[b]
    columns = _dof_columns(L, S1, S0)
    columns = jnp.concatenate([columns[:, :3], columns[:, 3:] + jnp.cross(columns[:, :3], point)], 1)
    moves = jnp.asarray(L.subtree[L.dof_body, b], q.dtype)   # coordinate's body is an ancestor
    return (columns * moves[:, None]).T


def _frame_index(tree, frame):
    try:
        return tree.frame_names.index(frame)
    except ValueError:
        raise KeyError(f"no frame {frame!r}; the frames are {list(tree.frame_names)}") from None


# ----- energy and the configuration derivative ------------------------------------------------


def kinetic_energy(tree: KinematicTree, q, v):
    r"""$\tfrac12 \sum_i V_i^T I_i V_i$."""
    R, p, _, _, _, V = _velocities(tree, q, v)
    return 0.5 * jnp.sum(V * _apply_inertia(_world_inertias(tree, R, p), V))


def potential_energy(tree: KinematicTree, q):
    """-sum_i m_i g . c_i, c_i the world position of body i's centre of mass."""
    Rs, ps = body_poses(tree, q)
    centres = jnp.einsum("nij,nj->ni", Rs, tree.com) + ps
    return -jnp.sum(tree.mass * (centres @ tree.gravity))


def configuration_derivative(tree: KinematicTree, q, v):
    r"""$\dot q$ from v: the identity for revolute and prismatic joints; for a floating base
    $\dot p = R v_{lin}$ and $\dot{\mathbf q} = \tfrac12 \mathbf q \otimes (0, \omega)$."""
    if not tree.layout.floating:
        return v
    x, y, z, w = q[3], q[4], q[5], q[6]
    wx, wy, wz = v[3], v[4], v[5]
    quat_dot = 0.5 * jnp.stack([w * wx + y * wz - z * wy, w * wy + z * wx - x * wz,
                                w * wz + x * wy - y * wx, -(x * wx + y * wy + z * wz)])
    return jnp.concatenate([quaternion_matrix(q[3:7]) @ v[:3], quat_dot, v[6:]])
