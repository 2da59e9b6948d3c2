r"""Featherstone's algorithms on a `KinematicTree`, in JAX, level by level.

Inverse dynamics (RNEA), the mass matrix (CRBA), forward dynamics (ABA), forward kinematics
and frame Jacobians (R. Featherstone, *Rigid Body Dynamics Algorithms*, Springer 2008,
ch. 5-7), written in *world coordinates*: every spatial vector and inertia is expressed in
a fixed frame, world-aligned, whose origin O is the world's for the bodies that hang from
the world and a free body's own position for the bodies it carries (subtrees never exchange
forces in these algorithms, so each may have its own O; float32 then stays accurate however
far a robot walks and however far apart free bodies are). Then

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

import collections
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _lanes
from .._compiled import compiled_query
from ._spatial import quaternion_matrix, skew
from ._tree import KinematicTree

# ----- lanes: the batch as the trailing axis --------------------------------------------------
#
# Every quantity inside the algorithms carries the batch as its LAST axis ("lanes", size B): a
# position vector is (..., 3, B), a spatial vector (..., 6, B), a 6x6 inertia (..., 6, 6, B).
# One evaluation is a batch of one lane. Vmapped, the public functions put the batch into the
# lanes (`_in_lanes_when_vmapped`), so consecutive batch members sit side by side in memory: a GPU warp
# reads them coalesced and a CPU vectorizes over them (vmap's own rules keep the batch as the
# leading axis, where each thread strides over a member's 36 inertia entries).


# products of float32 at float32's precision where JAX's default is less (TF32 on a GPU: the
# lanes' programs are batched outside `_compiled`'s precision setting)
_EXACT = jax.lax.Precision.HIGHEST


def _mv(M, x):
    """Matrix-vector products M x, M (..., r, c, B), x (..., c, B), written as a sum over the
    (small, static) inner dimension of broadcast products: elementwise work that XLA fuses with
    its neighbours (a `dot` or a `reduce` over 3 or 6 entries would be a kernel of its own,
    costlier to compile and, batched, to run)."""
    return sum(M[..., :, k, :] * x[..., k, None, :] for k in range(x.shape[-2]))


def _mm(A, B):
    """Matrix products A B, (..., r, k, B) (..., k, c, B) (see `_mv`)."""
    return sum(A[..., :, k, None, :] * B[..., k, None, :, :] for k in range(A.shape[-2]))


def _dot(a, b):
    """Inner products over the vector axis (..., c, B) -> (..., B) (see `_mv`)."""
    return sum(a[..., k, :] * b[..., k, :] for k in range(a.shape[-2]))


def _t(M):
    """Transposes of (..., r, c, B)."""
    return jnp.swapaxes(M, -3, -2)


def _cross(a, b):
    """a x b over the vector axis of (..., 3, B)."""
    (a0, a1, a2), (b0, b1, b2) = (jnp.moveaxis(x, -2, 0) for x in (a, b))
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -2)


def _skew(w):
    """[w]x of (..., 3, B) -> (..., 3, 3, B)."""
    return jnp.moveaxis(skew(jnp.moveaxis(w, -2, -1)), -3, -1)


def _motion_cross(v, m):
    """v x m for motion vectors (..., 6, B)."""
    w, u = v[..., :3, :], v[..., 3:, :]
    return jnp.concatenate([_cross(w, m[..., :3, :]), _cross(u, m[..., :3, :]) + _cross(w, m[..., 3:, :])], -2)


def _force_cross(v, f):
    """v x* f for a motion vector v and a force f (..., 6, B)."""
    w, u = v[..., :3, :], v[..., 3:, :]
    return jnp.concatenate([_cross(w, f[..., :3, :]) + _cross(u, f[..., 3:, :]), _cross(w, f[..., 3:, :])], -2)


def _lane(x):
    """A static array (...) as one lane (..., 1), which broadcasts against any batch."""
    return x[..., None]


# ----- kinematics -----------------------------------------------------------------------------


def _rotation_about(axis, angle):
    """Rodrigues' formula: rotations by `angle[k]` (k, B) about the unit `axis[k]` (k, 3)."""
    K = skew(axis)
    s, c = jnp.sin(angle)[:, None, None, :], jnp.cos(angle)[:, None, None, :]
    return _lane(jnp.eye(3, dtype=K.dtype)) + s * _lane(K) + (1 - c) * _lane(jnp.matmul(K, K, precision=_EXACT))


def _kinematics(tree: KinematicTree, q, *, unroll):
    """World rotations R (n, 3, 3, B) and positions p (n, 3, B) of the body frames relative to
    their subtree's O (`_origins`), in level order, and the motion subspaces: S1 (m, 6, B), one column per one-dof body, and
    the free bodies' 6x6 S0 (F, 6, 6, B) (None without any), columns [v_lin; omega] in each
    one's frame."""
    L = tree.layout
    f = L.num_floating
    one_dof = L.order[f:]
    dtype, lanes = q.dtype, q.shape[-1]
    axis = tree.axes[one_dof].astype(dtype)
    angle = q[L.q_index]
    revolute = jnp.asarray(L.revolute, dtype)[:, None]
    origin = _lane(tree.origin_rotation[one_dof].astype(dtype))
    R_local = _mm(origin, _rotation_about(axis, angle * revolute))
    p_local = _lane(tree.origin_translation[one_dof].astype(dtype)) + _mv(
        origin, _lane(axis) * (angle * (1 - revolute))[:, None, :])
    eye = jnp.broadcast_to(_lane(jnp.eye(3, dtype=dtype)), (3, 3, lanes))
    zero3 = jnp.zeros((3, lanes), dtype)
    if f:   # the free bodies, then the world (their slots and the world slot of the depth above)
        R_root = jnp.moveaxis(quaternion_matrix(q[L.free_q[:, 3:].T]), 2, 0)
        p_root = jnp.zeros((f, 3, lanes), dtype)        # each free body: its subtree's O (`_origins`)
        pad = L.width - f
        init = (jnp.concatenate([R_root, jnp.broadcast_to(eye, (pad, 3, 3, lanes))]),
                jnp.concatenate([p_root, jnp.zeros((pad, 3, lanes), dtype)]))
    else:
        init = (jnp.broadcast_to(eye, (L.width, 3, 3, lanes)), jnp.zeros((L.width, 3, lanes), dtype))

    def one_depth(above, local):
        (R_above, p_above), (R_loc, p_loc, parent) = above, local
        R_parent, p_parent = _from_parents(L, parent, R_above), _from_parents(L, parent, p_above)
        R_new = _mm(R_parent, R_loc)
        p_new = _mv(R_parent, p_loc) + p_parent
        return (R_new, p_new), (R_new, p_new)

    if len(L.slots):
        _, (R_slots, p_slots) = _over_depths(one_depth, init, (
            _to_slots(L, R_local, eye), _to_slots(L, p_local, zero3), L.parent_of_slot), unroll=unroll)
        R, p = _from_slots(L, R_slots), _from_slots(L, p_slots)
    else:   # free bodies alone
        R, p = jnp.zeros((0, 3, 3, lanes), dtype), jnp.zeros((0, 3, lanes), dtype)
    if f:
        R, p = jnp.concatenate([R_root, R]), jnp.concatenate([p_root, p])
    axis_world = _mv(R[f:], _lane(axis))
    revolute = revolute[..., None]
    S1 = jnp.concatenate([axis_world * revolute,
                          _cross(p[f:], axis_world) * revolute + axis_world * (1 - revolute)], axis=1)
    S0 = None
    if f:   # [v_lin; omega] in the body's frame -> [omega; velocity of the body point at O]
        zero = jnp.zeros((f, 3, 3, lanes), dtype)   # (O is the free body's own origin)
        S0 = jnp.concatenate([jnp.concatenate([zero, R_root], 2), jnp.concatenate([R_root, zero], 2)], 1)
    return R, p, S1, S0


_UNROLLED_DEPTHS = 2
_UNROLLED_DEPTHS_ACCELERATOR = 8


def _over_depths(step, init, depths, *, unroll, reverse=False):
    """`lax.scan` of `step` over the tree's depths: one traced step whatever the depth, which
    keeps compile time low. Trees of at most `unroll` depths unroll it (`_in_lanes_when_vmapped`
    picks the limit): on a CPU `_UNROLLED_DEPTHS`, where the loop's overhead outweighs the small steps
    of an acrobot or a cart-pole (their collocation Hessian 9.6 -> 6.4 ms per call, compile time
    unchanged) but not a 7-dof arm's; a vmapped batch on an accelerator up to
    `_UNROLLED_DEPTHS_ACCELERATOR`, where XLA then fuses across depths (the 7-dof ABA 92M ->
    106M evaluations/s at 10^6 on an H100, first call 1.0 -> 2.6 s). `unroll=math.inf`: a
    Python loop, no scan in the jaxpr (the fused kernels evaluate it element by element)."""
    length = len(jax.tree.leaves(depths)[0])
    if unroll != math.inf:
        return jax.lax.scan(step, init, depths, reverse=reverse, unroll=length <= unroll)
    carry, outputs = init, [None] * length
    for i in (range(length - 1, -1, -1) if reverse else range(length)):
        carry, outputs[i] = step(carry, jax.tree.map(lambda d: d[i], depths))
    return carry, jax.tree.map(lambda *ys: jnp.stack(ys), *outputs)


def _to_slots(L, x, fill):
    """Per one-dof body (level order) -> padded per depth and slot (depths, width, ...)."""
    return _with_fill(L, x, fill)[_slot_rows(L)]


def _slot_rows(L):
    """(depths, width): the row of each slot in the per-one-dof-body arrays (with their fill row)."""
    return L.slots - L.num_floating


def _with_fill(L, x, fill):
    """x (k, ...) with one more row, `fill`: the value an empty slot reads (none when every
    slot holds a body, as along a chain: the copy of every per-body array that the extra row
    costs was a fifth of a GPU's ABA)."""
    if L.valid.all():
        return x
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
    """The motion subspace of every velocity coordinate, rows (nv, 6, B), in the tree's order."""
    rows = S1 if S0 is None else jnp.concatenate([jnp.moveaxis(S0, 2, 1).reshape((-1,) + S0.shape[1:2] + S0.shape[3:]), S1])
    return rows[L.dof_level_order]


def _joint_velocity(L, S1, S0, v):
    """s_i qdot_i of every body's own joint (n, 6, B), level order, from velocity coordinates v."""
    f = L.num_floating
    one = S1 * v[L.level_dofs[6 * f:]][:, None, :]
    return one if S0 is None else jnp.concatenate([_mv(S0, v[L.level_dofs[:6 * f]].reshape((f, 6) + v.shape[1:])), one])


def _subtree_sum(L, x):
    """For every body, the sum of x over its subtree (x: (n, ...), level order)."""
    return jnp.tensordot(jnp.asarray(L.subtree, x.dtype), x, axes=1, precision=_EXACT)


def _ancestor_sum(L, x):
    """For every body, the sum of x over its ancestors and itself."""
    return jnp.tensordot(jnp.asarray(L.subtree.T, x.dtype), x, axes=1, precision=_EXACT)


def _base_acceleration(tree, dtype, gravity: bool):
    """(6, 1): gravity as the base's fictitious acceleration."""
    g = tree.gravity.astype(dtype) if gravity else jnp.zeros(3, dtype)
    return _lane(jnp.concatenate([jnp.zeros(3, dtype), -g]))


# ----- spatial inertias ------------------------------------------------------------------------


def _world_inertias(tree, R, p):
    """Every body's spatial inertia about O, world axes, as (m, h = m c, I_bar) in level order:
    $I\\,[\\omega; v] = [\\bar I \\omega + h \\times v;\\ m v - h \\times \\omega]$."""
    L = tree.layout
    dtype = R.dtype
    m = _lane(tree.mass[L.order].astype(dtype))                     # (n, 1)
    c = _mv(R, _lane(tree.com[L.order].astype(dtype))) + p
    I_com = _mm(_mm(R, _lane(tree.inertia[L.order].astype(dtype))), _t(R))
    eye = _lane(jnp.eye(3, dtype=dtype))
    I_bar = I_com + m[:, None, None] * (_dot(c, c)[:, None, None] * eye - c[:, :, None] * c[:, None, :])
    return m, m[:, None] * c, I_bar


def _apply_inertia(inertia, v):
    m, h, I_bar = inertia
    w, u = v[..., :3, :], v[..., 3:, :]
    return jnp.concatenate([_mv(I_bar, w) + _cross(h, u), m[..., None, :] * u - _cross(h, w)], -2)


def _dense_inertia(inertia):
    """The 6x6 matrices of (m, h, I_bar)."""
    m, h, I_bar = inertia
    H = _skew(h)
    mass = m[..., None, None, :] * _lane(jnp.eye(3, dtype=I_bar.dtype))
    return jnp.concatenate([jnp.concatenate([I_bar, H], -2),
                            jnp.concatenate([_t(H), jnp.broadcast_to(mass, H.shape)], -2)], -3)


def _solve_spd6(M, b):
    """M^{-1} b for symmetric positive-definite 6x6 M (6, 6, B), by 3x3 blocks (Schur complement)."""
    A, B, C = M[:3, :3], M[:3, 3:], M[3:, 3:]
    C_inv = _inverse3(C)
    BC = _mm(B, C_inv)
    x1 = _mv(_inverse3(A - _mm(BC, _t(B))), b[:3] - _mv(BC, b[3:]))
    return jnp.concatenate([x1, _mv(C_inv, b[3:] - _mv(_t(B), x1))])


def _inverse3(M):
    """The inverses of 3x3 matrices (3, 3, B) by their adjugates."""
    a, b, c = M[0], M[1], M[2]
    adj = jnp.stack([_cross(b, c), _cross(c, a), _cross(a, b)], axis=1)
    return adj / _dot(a, _cross(b, c))


def _from_level_order(L, x):
    """Velocity-coordinate vector in level order -> the tree's coordinate order."""
    return x[L.dof_level_order]


# ----- the algorithms, on lanes ---------------------------------------------------------------


def _velocities(tree, q, v, *, unroll):
    R, p, S1, S0 = _kinematics(tree, q, unroll=unroll)
    L = tree.layout
    joint = _joint_velocity(L, S1, S0, v)
    return R, p, S1, S0, joint, _ancestor_sum(L, joint)


def _rnea(tree: KinematicTree, q, v=None, a=None, *, gravity: bool, unroll):
    """Inverse dynamics on lanes; v or a None: zero, and its terms skipped (the bias forces pass
    no a, gravity alone neither: a constant zero, broadcast into a large GPU batch's lanes, had
    XLA spend a second folding it at compile time)."""
    L = tree.layout
    if v is None:
        R, p, S1, S0 = _kinematics(tree, q, unroll=unroll)
    else:
        R, p, S1, S0, joint, V = _velocities(tree, q, v, unroll=unroll)
    inertia = _world_inertias(tree, R, p)
    A = _base_acceleration(tree, q.dtype, gravity)
    joint_acc = 0.0 if a is None else _joint_velocity(L, S1, S0, a)
    if v is not None:
        joint_acc = joint_acc + _motion_cross(V, joint)
    if v is not None or a is not None:
        A = A + _ancestor_sum(L, joint_acc)
    F = _apply_inertia(inertia, A)
    if v is not None:
        F = F + _force_cross(V, _apply_inertia(inertia, V))
    tau = _project_forces(L, S1, S0, _subtree_sum(L, F))
    if a is not None and tree.armature is not None:
        tau = tau + _lane(tree.armature.astype(tau.dtype)) * a
    return tau


def _contact_kinematics(tree: KinematicTree, q, v, *, unroll):
    """Level order, lanes: R, p (relative to each body's O), V (spatial velocities about it)
    and the dof columns (nv, 6), tree coordinate order."""
    R, p, S1, S0, _, V = _velocities(tree, q, v, unroll=unroll)
    return R, p, V, _dof_columns(tree.layout, S1, S0)


def _project_forces(L, S1, S0, F):
    """tau = S^T F per joint, in the tree's coordinate order."""
    f = L.num_floating
    tau = _dot(S1, F[f:])
    if S0 is not None:
        tau = jnp.concatenate([_mv(_t(S0), F[:f]).reshape((6 * f,) + tau.shape[1:]), tau])
    return _from_level_order(L, tau)


def _mass_matrix(tree: KinematicTree, q, *, unroll):
    L = tree.layout
    R, p, S1, S0 = _kinematics(tree, q, unroll=unroll)
    composite = tuple(_subtree_sum(L, x) for x in _world_inertias(tree, R, p))
    columns = _dof_columns(L, S1, S0)                                   # (nv, 6, B)
    per_dof = tuple(x[L.dof_body] for x in composite)
    F = _apply_inertia(per_dof, columns)                                # I^c_{b(k)} s_k
    M = _mm(F, jnp.moveaxis(columns, 0, 1))  # (a batched `dot` of these small matrices is slower on a CPU)
    ancestor = _lane(jnp.asarray(L.ancestor, M.dtype))
    same = _lane(jnp.asarray(L.ancestor * L.ancestor.T, M.dtype))
    H = ancestor * M + (_t(ancestor) - same) * _t(M)
    if tree.armature is not None:
        H = H + _lane(jnp.diag(tree.armature.astype(M.dtype)))
    return H


def _free_force(R, p, tau):
    r"""$S_0^{-T}\tau$: free bodies' generalized forces (F, 6, B) [force; torque] in their
    frames (R, p relative to O) as spatial forces about O, [torque about O; force]."""
    force = _mv(R, tau[:, :3])
    return jnp.concatenate([_mv(R, tau[:, 3:]) + _cross(p, force), force], 1)


def _free_coordinates(R, p, m):
    r"""$S_0^{-1} m$: free bodies' spatial motions (F, 6, B) [omega; v_O] as their coordinates
    [v_lin; omega] in their frames."""
    w, u = m[:, :3], m[:, 3:]
    return jnp.concatenate([_mv(_t(R), u - _cross(p, w)), _mv(_t(R), w)], 1)


def _aba(tree: KinematicTree, q, v, tau, *, gravity: bool, unroll):
    L = tree.layout
    f = L.num_floating
    R, p, S1, S0, joint, V = _velocities(tree, q, v, unroll=unroll)
    c = _motion_cross(V, joint)                      # s_dot qdot (zero for a free body)
    inertia = _world_inertias(tree, R, p)
    I_A = _dense_inertia(inertia)
    p_A = _force_cross(V, _apply_inertia(inertia, V))
    tau_level = tau[L.level_dofs]

    dtype, lanes = q.dtype, q.shape[-1]
    zero6 = jnp.zeros((6, lanes), dtype)
    unit = zero6.at[0].set(1.0)  # empty slots: an identity inertia along e_1, D = 1
    # per one-dof body, with one padding row for empty slots; each depth gathers its rows inside
    # the loop (stacking them per depth beforehand was a transposing copy of every inertia:
    # 45% of the time on a GPU)
    I_A1, p_A1, S1p, c1, tau1 = (_with_fill(L, x, fill) for x, fill in (
        (I_A[f:], _lane(jnp.eye(6, dtype=dtype))), (p_A[f:], zero6), (S1, unit), (c[f:], zero6),
        (tau_level[6 * f:], zero6[0])))
    armature = None if tree.armature is None else _with_fill(  # the one-dof joints' (none on a free body)
        L, _lane(tree.armature[L.level_dofs[6 * f:]].astype(dtype)), 0.0)

    def backward(passed, depth):
        """One depth, deepest first: the articulated inertia and bias of its bodies (their
        own plus what their children passed up), and what they pass to their parents."""
        (Ia_in, pa_in), (rows, parent, valid) = passed, depth
        IA, pA, s, c, t = I_A1[rows] + Ia_in, p_A1[rows] + pa_in, S1p[rows], c1[rows], tau1[rows]
        U = _mv(IA, s)
        D_inv = 1.0 / (_dot(s, U) if armature is None else _dot(s, U) + armature[rows])
        u = t - _dot(s, pA)
        Ia = IA - D_inv[:, None, None] * U[:, :, None] * U[:, None, :]
        pa = pA + _mv(Ia, c) + U * (D_inv * u)[:, None]
        valid = valid.astype(dtype)[:, None]
        up = (_to_parents(L, parent, Ia * valid[:, None, None]), _to_parents(L, parent, pa * valid[:, None]))
        return up, (U, D_inv, u)

    a0 = _base_acceleration(tree, dtype, gravity)
    depths = (jnp.asarray(_slot_rows(L)), L.parent_of_slot, L.valid)
    Ia_root, pa_root = jnp.zeros((L.width, 6, 6, lanes), dtype), jnp.zeros((L.width, 6, lanes), dtype)
    if len(L.slots):
        (Ia_root, pa_root), (U, D_inv, u) = _over_depths(backward, (Ia_root, pa_root), depths, reverse=True,
                                                         unroll=unroll)
    A_above = jnp.broadcast_to(a0, (L.width, 6, lanes))   # the world's slots
    if f:   # each free body: (I^A) A = S0^{-T} tau - p^A, its coordinates S0^{-1} (A - a0)
        R0, p0 = R[:f], p[:f]
        A_root = jax.vmap(_solve_spd6)(I_A[:f] + Ia_root[:f], _free_force(R0, p0, tau_level[:6 * f].reshape(
            (f, 6, lanes))) - p_A[:f] - pa_root[:f])
        qdd_root = _free_coordinates(R0, p0, A_root - a0).reshape((6 * f, lanes))
        A_above = A_above.at[:f].set(A_root)
    if not len(L.slots):   # free bodies alone
        return _from_level_order(L, qdd_root)

    def forward(A_above, depth):
        """One depth, root first: joint accelerations and body accelerations."""
        rows, U, D_inv, u, parent = depth
        A = _from_parents(L, parent, A_above) + c1[rows]
        qdd = D_inv * (u - _dot(U, A))
        return A + S1p[rows] * qdd[:, None], qdd

    _, qdd = _over_depths(forward, A_above, (depths[0], U, D_inv, u, L.parent_of_slot), unroll=unroll)
    qdd = _from_slots(L, qdd)
    if f:
        qdd = jnp.concatenate([qdd_root, qdd])
    return _from_level_order(L, qdd)


# ----- the public functions: one evaluation, or a vmapped batch in lanes ------------------------


def _into_lanes(a, accelerator: bool):
    """A batch (B, n) as lanes (n, B). On an accelerator through a product with the identity
    (exact: "highest" precision; a non-finite entry spreads only within its own member): a
    plain transpose becomes a layout change there, and every consumer then reads the batch
    with its stride (the 7-dof ABA: 97M -> 110M evaluations/s at 10^6 on an H100)."""
    if not accelerator:
        return jnp.moveaxis(a, 0, -1)
    return jnp.einsum("bn,nm->mb", a, jnp.eye(a.shape[1], dtype=a.dtype), precision="highest")


def _in_one_lane(algorithm, tree, *arrays, **static):
    """`algorithm` (on lanes) evaluated for one evaluation's arrays, as one lane; its outputs
    (an array or a tuple of them) without the lane axis."""
    out = algorithm(tree, *(jnp.asarray(a)[..., None] for a in arrays), unroll=_UNROLLED_DEPTHS, **static)
    return jax.tree.map(lambda x: x[..., 0], out)


def _jvp_of_live(fn, primals, tangents):
    """`jax.jvp(fn, primals, tangents)` over the live tangents only (parameters nobody
    differentiates cost nothing); None when every tangent is a symbolic zero."""
    flat, structure = jax.tree.flatten(primals)
    flat_tangents = structure.flatten_up_to(tangents)
    live = [i for i, t in enumerate(flat_tangents) if not isinstance(t, jax.custom_derivatives.SymbolicZero)]
    if not live:
        return None

    def of_live(*values):
        full = list(flat)
        for i, value in zip(live, values):
            full[i] = value
        return fn(*jax.tree.unflatten(structure, full))

    return jax.jvp(of_live, [flat[i] for i in live], [flat_tangents[i] for i in live])


@functools.lru_cache(maxsize=None)
def _in_lanes_when_vmapped(algorithm, **static):
    r"""`algorithm(tree, *arrays, unroll=..., **static)` on lanes as a function of one evaluation's
    arrays: evaluated as one lane; under `vmap`, with the batch moved into the lanes (a
    `custom_vmap`; a batched tree, e.g. vmapped masses, falls back to vmap's own rules).
    Returns (that function, the plain one-lane function). Not differentiable by itself: the
    public functions add a `custom_jvp`. The depth loops unroll up to `_UNROLLED_DEPTHS`, or
    `_UNROLLED_DEPTHS_ACCELERATOR` for a batch on a GPU / TPU."""

    def one(tree, *arrays):
        return _in_one_lane(algorithm, tree, *arrays, **static)

    # jitted, so that its constants stay inside its own program: a custom_vmap with constants
    # fails under the vmap of a `lax.switch` with a batched index (JAX batches them)
    batched = jax.custom_batching.custom_vmap(jax.jit(one))

    @batched.def_vmap
    def in_lanes(axis_size, in_batched, tree, *arrays):
        tree_batched, arrays_batched = in_batched[0], in_batched[1:]
        if any(jax.tree.leaves(tree_batched)):
            axes = (jax.tree.map(lambda b: 0 if b else None, tree_batched),) + tuple(
                0 if b else None for b in arrays_batched)
            return jax.vmap(one, in_axes=axes)(tree, *arrays), True
        accelerator = jax.default_backend() != "cpu"
        lanes = [_into_lanes(a, accelerator) if b else jnp.broadcast_to(a[..., None], a.shape + (axis_size,))
                 for a, b in zip(arrays, arrays_batched)]
        unroll = _UNROLLED_DEPTHS_ACCELERATOR if accelerator else _UNROLLED_DEPTHS
        return jnp.moveaxis(algorithm(tree, *lanes, unroll=unroll, **static), -1, 0), True

    return batched, one


@functools.lru_cache(maxsize=None)
def _lane_batched(algorithm, **static):
    """`_in_lanes_when_vmapped(algorithm)`, differentiated (forward or reverse, any order) by
    JAX through the one-lane program."""
    return _differentiated_through(*_in_lanes_when_vmapped(algorithm, **static))


def _differentiated_through(batched, one):
    """`batched` (a custom_vmap) with the derivatives of `one`, the same function unbatched
    (a `custom_jvp`: symbolic zero tangents skipped, any order, reverse mode by JAX)."""
    public = jax.custom_jvp(batched)

    @functools.partial(public.defjvp, symbolic_zeros=True)
    def derivative(primals, tangents):
        out_and_tangent = _jvp_of_live(one, primals, tangents)
        if out_and_tangent is None:
            out = one(*primals)
            return out, jax.tree.map(jnp.zeros_like, out)
        return out_and_tangent

    return public


@functools.lru_cache(maxsize=None)
def _forward_dynamics(gravity: bool):
    r"""ABA in lanes when vmapped, differentiated through inverse dynamics: from
    $\mathrm{ID}(\theta, q, v, \ddot q) = \tau$ at the solution,
    $d\ddot q = H(q)^{-1}\big(d\tau - \partial_{\theta, q, v}\mathrm{ID}\cdot(d\theta, dq, dv)\big)$,
    H by CRBA and a Cholesky factorization (Pinocchio's way: Carpentier & Mansard, RSS 2018).
    The tangents of RNEA and CRBA cost much less than those of ABA's articulated inertias."""
    batched, one = _in_lanes_when_vmapped(_aba, gravity=gravity)

    def with_derivative(primal):
        public = jax.custom_jvp(primal)

        @functools.partial(public.defjvp, symbolic_zeros=True)
        def derivative(primals, tangents):
            tree, q, v, tau = primals
            qdd = linearization_point(tree, q, v, tau)
            inverse_dynamics = _jvp_of_live(lambda tree, q, v: rnea(tree, q, v, qdd, gravity=gravity),
                                            (tree, q, v), tangents[:3])
            dtau = tangents[3]
            rhs = jnp.zeros_like(qdd) if isinstance(dtau, jax.custom_derivatives.SymbolicZero) else dtau
            if inverse_dynamics is not None:
                rhs = rhs - inverse_dynamics[1]
            factor = jax.scipy.linalg.cho_factor(mass_matrix(tree, q))
            return qdd, jax.scipy.linalg.cho_solve(factor, rhs)

        return public

    # the point the derivative is taken at: the one-lane ABA, differentiable by the same rule (any
    # order), vmapped by vmap's own rules (in lanes, a GPU's unrolled depths doubled the compile
    # time of a vmapped Jacobian)
    linearization_point = with_derivative(one)
    return with_derivative(batched)


# ----- fused batches on a GPU: one Pallas kernel, a member per lane --------------------------------

_FUSED_MIN_BATCH = 16384  # the default threshold of `fused_kernels`
_FUSED = {"min_batch": _FUSED_MIN_BATCH}
_FUSED_PROGRAMS: collections.OrderedDict = collections.OrderedDict()


def fused_kernels(min_batch: int | None = _FUSED_MIN_BATCH) -> int | None:
    """Sets when vmapped `aba`, `rnea`, `bias_forces`, `gravity_forces` and `mass_matrix` run
    as one fused kernel on a GPU: batches of at least `min_batch` members, for a tree that is a
    constant of the program (closed over, not a `jit` argument); None: never. Returns the
    previous setting.

    The kernel (Pallas, Triton) gives each member a GPU thread and evaluates the algorithm as
    straight-line code with the tree's numbers folded in (`jaxdrake._lanes`): nothing goes to
    memory between the depths. The 7-dof arm's ABA at 10^6 members in float32 on an H200: 2.2e9
    evaluations/s against 1.2e8 for the lanes program, but a first call of ~22 s instead of
    ~4 s (`jd.use_compilation_cache()` keeps it for later processes). Trees over 20,000 lane
    values (Solo-12's ABA) keep the lanes program. Derivatives are unchanged: JAX's, through
    the one-lane program. A product with one of the tree's structural zeros is dropped, so a
    member with an infinite or NaN input may show it in fewer outputs than the lanes program.
    A Pallas kernel is not partitioned by `jit` across devices: spread a batch over several
    GPUs with `jd.run_batch` (a kernel per device), or turn fusion off. Programs already
    compiled keep the setting they were traced with."""
    if min_batch is not None and not (isinstance(min_batch, int) and not isinstance(min_batch, bool) and min_batch >= 1):
        raise ValueError(f"fused_kernels: min_batch must be a positive int or None, got {min_batch!r}")
    previous, _FUSED["min_batch"] = _FUSED["min_batch"], min_batch
    return previous


def _fused_kernel() -> str | None:
    """The kind of fused kernel this backend runs ("pallas" on a GPU), None elsewhere: off a
    GPU the lanes program is as fast (`_lanes.lane_map`'s "xla" kernel exists for checking)."""
    return "pallas" if jax.default_backend() == "gpu" else None


def _fused_when_batched(public, algorithm, tree, arrays, static):
    """`public(tree, *arrays)`; on a GPU with a constant tree, through `_fused_batches`. Traced
    arguments are copied (a no-op once compiled): vmap over a NumPy array leaves it NumPy inside
    its tracer, which a custom derivative under `jit` refuses (JAX's "non-canonical constant")."""
    arrays = tuple(jnp.array(a, copy=True) if isinstance(a, jax.core.Tracer) else jnp.asarray(a) for a in arrays)
    if _FUSED["min_batch"] is None or _fused_kernel() is None or any(
            isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree)):
        return public(tree, *arrays)
    key = (public, algorithm, tuple(sorted(static.items())), _lanes.value_key(tree))
    try:
        fused = _FUSED_PROGRAMS.pop(key)
    except KeyError:
        fused = _fused_batches(public, algorithm, tree, static)
    _FUSED_PROGRAMS[key] = fused
    if len(_FUSED_PROGRAMS) > 64:   # (a tree uses up to 7: each function and gravity flag)
        _FUSED_PROGRAMS.popitem(last=False)
    return fused(*arrays)


def _fused_batches(public, algorithm, tree, static):
    """`public` with `tree` a constant: its vmap of at least `fused_kernels`' batch runs
    `algorithm` in one fused kernel (`_lanes.lane_map`), built once per dtype and shapes; a
    smaller batch, or a tree too long for straight-line code, `public`'s own batching. Its
    derivatives are `public`'s."""
    kernels = {}

    def one(*arrays):
        return public(tree, *arrays)

    def kernel(arrays):
        dtype = jnp.result_type(*arrays)
        examples = [jax.ShapeDtypeStruct(a.shape[1:], dtype) for a in arrays]
        key = tuple((e.shape, str(dtype)) for e in examples)
        if key not in kernels:
            def evaluation(*xs):
                out = algorithm(tree, *(x[..., None] for x in xs), unroll=math.inf, **static)
                return jax.tree.map(lambda x: x[..., 0], out)
            budget = _lanes.Budget("fused_kernels", f"{tree.robot_name}'s {algorithm.__name__[1:]}",
                                   _FUSED_OPERATIONS, "its batches keep the lanes program", fold=True)
            try:
                kernels[key] = _lanes.lane_map(evaluation, examples, budget, kernel=_fused_kernel())
            except NotImplementedError:
                kernels[key] = None
        return kernels[key]

    batched = jax.custom_batching.custom_vmap(jax.jit(one))  # jitted: constants stay inside (see above)

    @batched.def_vmap
    def in_one_kernel(axis_size, in_batched, *arrays):
        full = [a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for a, b in zip(arrays, in_batched)]
        program = kernel(full) if axis_size >= (_FUSED["min_batch"] or math.inf) else None
        if program is None:
            return jax.vmap(one, in_axes=[0 if b else None for b in in_batched])(*arrays), True
        return program(*full), True

    return _differentiated_through(batched, one)


# the most lane values one fused evaluation may make (`_lanes.Budget`): the 7-dof ABA makes 14,088
# (a 17-s Triton compile on an H200), Solo-12's 28,587 (124 s: its batches keep the lanes program)
_FUSED_OPERATIONS = 20_000


def rnea(tree: KinematicTree, q, v, a, *, gravity: bool = True):
    r"""Inverse dynamics $\tau = H(q)\dot v + C(q, v) v + G(q)$ (recursive Newton-Euler): the
    body velocities and accelerations are ancestor sums, the joint forces subtree sums."""
    return _fused_when_batched(_lane_batched(_rnea, gravity=gravity), _rnea, tree, (q, v, a), {"gravity": gravity})


def mass_matrix(tree: KinematicTree, q):
    r"""H(q) by composite rigid bodies: with $I^c_i$ the inertia of body i's subtree,
    $H_{kl} = s_k^T I^c_{b(k)} s_l$ when coordinate l's body is an ancestor of (or is)
    coordinate k's body $b(k)$, its transpose in the other case, and 0 otherwise.
    (Vmapped, it keeps vmap's own batching: in lanes, the quadruped's CRBA at a batch of 1000
    took 3.5 ms on a CPU instead of 1.7-2.0; on a GPU, a large batch runs fused: `fused_kernels`.)"""
    return _fused_when_batched(_one_lane_mass_matrix, _mass_matrix, tree, (q,), {})


@compiled_query
def _one_lane_mass_matrix(tree: KinematicTree, q):
    return _in_one_lane(_mass_matrix, tree, q)


def bias_forces(tree: KinematicTree, q, v, *, gravity: bool = True):
    """C(q, v) v + G(q) (gravity=False: C(q, v) v alone): inverse dynamics at zero acceleration."""
    return _fused_when_batched(_lane_batched(_rnea, gravity=gravity), _rnea, tree, (q, v), {"gravity": gravity})


def gravity_forces(tree: KinematicTree, q):
    """G(q): the generalized gravity term, on the left of H qdd + C qd + G = tau."""
    return _fused_when_batched(_lane_batched(_rnea, gravity=True), _rnea, tree, (q,), {"gravity": True})


def aba(tree: KinematicTree, q, v, tau, *, gravity: bool = True):
    r"""Forward dynamics $\dot v = H^{-1}(\tau - C v - G)$ by the articulated-body algorithm.

    Backward over the depths (deepest first), for the one-dof bodies of a depth at once:
    $U = I^A s$, $D = s^T U + \rho$ (the joint's armature), $u = \tau - s^T p^A$, and the parent receives
    $I^A - U U^T / D$ and $p^A + I^a c + U u / D$ (no transforms: world coordinates).
    Forward: $A = A_{\lambda} + c$, $\ddot q = (u - U^T A) / D$, $A \mathrel{+}= s \ddot q$.
    A floating base's acceleration is $(I^A)^{-1}(S_0 \tau_0 - p^A)$. Derivatives come through
    inverse dynamics (`_forward_dynamics`)."""
    return _fused_when_batched(_forward_dynamics(gravity), _aba, tree, (q, v, tau), {"gravity": gravity})


class BodyMotion(NamedTuple):
    r"""One kinematics pass, what forces applied to bodies need: every body's world `rotation`
    (n, 3, 3), `position` (n, 3) and spatial velocity `velocity` (n, 6) rows
    $[\omega_B; v_{B_o}]$ (tree order), the velocity coordinates' motion subspaces `columns`
    (nv, 6, world axes), and each body's `origin` (n, 3, world): the point O its subtree's
    spatial quantities are taken about (its free body's position, or the world's origin), about
    which the columns of the coordinates that move it are taken (`column_origins`)."""

    rotation: jax.Array
    position: jax.Array
    velocity: jax.Array
    columns: jax.Array
    origin: jax.Array


@compiled_query
def body_motion(tree: KinematicTree, q, v) -> BodyMotion:
    """Poses, velocities and motion subspaces from one forward-kinematics pass (`BodyMotion`)."""
    R, p, V, columns = _in_one_lane(_contact_kinematics, tree, q, v)
    position = tree.layout.position
    R, p, V = R[position], p[position], V[position]
    w = V[:, :3]
    origin = _origins(tree, q)
    return BodyMotion(R, p + origin, jnp.concatenate([w, V[:, 3:] + jnp.cross(w, p)], 1), columns, origin)


def external_forces(tree: KinematicTree, motion: BodyMotion, F):
    r"""The generalized force $\tau = \sum_B J_B^T F_B$ of spatial forces on the bodies: F (n, 6)
    rows $[\tau_{B_o}; f_B]$ (the torque about the body frame's origin and the force, world
    axes, tree order: Drake's `F_BBo_W`), moved to the origin O and summed over subtrees:
    $\tau_k = s_k \cdot \sum_{B \in \mathrm{subtree}(k)} F_B^O$."""
    L = tree.layout
    torque, force = F[:, :3], F[:, 3:]
    at_origin = jnp.concatenate([torque + jnp.cross(motion.position - motion.origin, force), force], 1)
    subtree_sums = jnp.asarray(L.subtree, F.dtype) @ at_origin[L.order]
    return jnp.sum(motion.columns * subtree_sums[L.dof_body], 1)


# ----- frames -----------------------------------------------------------------------------------


def _origins(tree, q):
    """Each body's O in world coordinates (n, 3), tree order: the position of the free body
    whose subtree holds it, else the world origin."""
    L = tree.layout
    if not L.num_floating:
        return jnp.zeros((tree.num_bodies, 3), q.dtype)
    return jnp.where(L.free_root[:, None] >= 0, q[L.free_q[np.maximum(L.free_root, 0), :3]], 0.0)


def column_origins(tree, motion: "BodyMotion"):
    """The point (nv, 3) about which each velocity coordinate's column of `motion.columns` is
    taken: the O of the body it moves."""
    L = tree.layout
    return motion.origin[L.order[L.dof_body]]


@compiled_query
def body_poses(tree: KinematicTree, q):
    """World rotation and position of every body frame: arrays (n, 3, 3) and (n, 3)."""
    R, p, _, _ = _in_one_lane(_kinematics, tree, q)
    position = tree.layout.position
    return R[position], p[position] + _origins(tree, q)


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


@compiled_query
def frame_jacobian(tree: KinematicTree, q, frame: str):
    r"""The 6 x nv Jacobian of a named frame, world-aligned: $[\omega; \dot p] = J(q)\, v$ with
    $\omega$ the frame's angular velocity and $\dot p$ the velocity of its origin, both in
    world coordinates: the columns $[s_\omega; s_v + s_\omega \times p]$ of the frame body's
    ancestors' joints."""
    return _frame_jacobians(tree, q, (frame,))[0]


def _frame_jacobians(tree: KinematicTree, q, frames) -> jax.Array:
    """`frame_jacobian` of each of `frames` (names), (len(frames), 6, nv), from one pass of
    the kinematics."""
    L = tree.layout
    indices = [_frame_index(tree, frame) for frame in frames]
    if all(tree.frame_bodies[k] < 0 for k in indices):
        return jnp.zeros((len(indices), 6, tree.nv), q.dtype)
    R, p, S1, S0 = _in_one_lane(_kinematics, tree, q)
    columns = _dof_columns(L, S1, S0)
    jacobians = []
    for k in indices:
        body = tree.frame_bodies[k]
        if body < 0:
            jacobians.append(jnp.zeros((6, tree.nv), q.dtype))
            continue
        b = L.position[body]
        point = R[b] @ tree.frame_translation[k] + p[b]
        moved = jnp.concatenate([columns[:, :3], columns[:, 3:] + jnp.cross(columns[:, :3], point)], 1)
        moves = jnp.asarray(L.subtree[L.dof_body, b], q.dtype)   # coordinate's body is an ancestor
        jacobians.append((moved * moves[:, None]).T)
    return jnp.stack(jacobians)


def _frame_index(tree, frame):
    try:
        return tree.frame_names.index(frame)
    except ValueError:
        raise KeyError(f"no frame {frame!r}; the frames are {list(tree.frame_names)}") from None


# ----- energy and the configuration derivative ------------------------------------------------


@compiled_query
def kinetic_energy(tree: KinematicTree, q, v):
    r"""$\tfrac12 \sum_i V_i^T I_i V_i$ (plus the rotors' $\tfrac12 \sum_k \rho_k v_k^2$ of an armature)."""
    R, p, _, _, _, V = _velocities(tree, q[:, None], v[:, None], unroll=_UNROLLED_DEPTHS)
    energy = 0.5 * jnp.sum(V * _apply_inertia(_world_inertias(tree, R, p), V))
    return energy if tree.armature is None else energy + 0.5 * jnp.sum(tree.armature * v ** 2)


@compiled_query
def potential_energy(tree: KinematicTree, q):
    """-sum_i m_i g . c_i, c_i the world position of body i's centre of mass."""
    Rs, ps = body_poses(tree, q)
    centres = jnp.einsum("nij,nj->ni", Rs, tree.com) + ps
    return -jnp.sum(tree.mass * (centres @ tree.gravity))


def configuration_derivative(tree: KinematicTree, q, v):
    r"""$\dot q$ from v: the identity for revolute and prismatic joints; for a free body
    $\dot p = R v_{lin}$ and $\dot{\mathbf q} = \tfrac12 \mathbf q \otimes (0, \omega)$."""
    L = tree.layout
    if not L.num_floating:
        return v

    def free(quat, v_lin, omega):
        x, y, z, w = quat
        wx, wy, wz = omega
        quat_dot = 0.5 * jnp.stack([w * wx + y * wz - z * wy, w * wy + z * wx - x * wz,
                                    w * wz + x * wy - y * wx, -(x * wx + y * wy + z * wz)])
        return jnp.concatenate([quaternion_matrix(quat) @ v_lin, quat_dot])

    per_root = jax.vmap(free)(q[L.free_q[:, 3:]], v[L.free_v[:, :3]], v[L.free_v[:, 3:]])
    return jnp.zeros(tree.nq, v.dtype).at[L.q_index].set(v[L.v_index]).at[L.free_q].set(per_root)


def velocity_of_configuration_change(tree: KinematicTree, q, dq):
    r"""The velocity-coordinate change $\delta\nu$ with configuration_derivative(q, $\delta\nu$)
    = dq (the inverse of that linear map; for a free body, of a quaternion change tangent
    to the unit sphere): $\delta\nu_{lin} = R^T dp$ and $\delta\omega = 2\,\mathrm{vec}(
    \bar{\mathbf q} \otimes d\mathbf q)$."""
    L = tree.layout
    if not L.num_floating:
        return dq

    def free(quat, dp, dquat):
        x, y, z, w = quat
        dx, dy, dz, dw = dquat
        omega = 2.0 * jnp.stack([w * dx - dw * x - y * dz + z * dy, w * dy - dw * y - z * dx + x * dz,
                                 w * dz - dw * z - x * dy + y * dx])
        return jnp.concatenate([quaternion_matrix(quat).T @ dp, omega])

    per_root = jax.vmap(free)(q[L.free_q[:, 3:]], dq[L.free_q[:, :3]], dq[L.free_q[:, 3:]])
    return jnp.zeros(tree.nv, dq.dtype).at[L.v_index].set(dq[L.q_index]).at[L.free_v].set(per_root)

