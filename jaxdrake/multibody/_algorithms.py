r"""Featherstone's recursive algorithms on a `KinematicTree`, in JAX.

Inverse dynamics (RNEA), the mass matrix (CRBA), forward dynamics (ABA), forward kinematics
and frame Jacobians (R. Featherstone, *Rigid Body Dynamics Algorithms*, Springer 2008,
ch. 5-7). The loops over bodies are Python loops over the static tree, unrolled when traced:
one fused program per tree, no per-call Python work under `jit`, and `vmap` / `grad` apply.

Conventions: spatial vectors angular first (see `_spatial`); gravity enters as a fictitious
base acceleration $a_0 = -[0; g]$; generalized forces are those of the joint coordinates
(for a floating base, the force and torque on the base in its own frame, Pinocchio's).
"""

from __future__ import annotations

import jax.numpy as jnp

from ._spatial import (axis_angle, force_cross, motion_cross,
                       quaternion_matrix, skew, spatial_inertia, transform_force_back, transform_inertia,
                       transform_motion)
from ._tree import KinematicTree


def _joint(tree: KinematicTree, i: int, q):
    """Body i's pose in its parent's frame (R, p), and its motion subspace S (6 x dofs)."""
    kind, s = tree.joint_types[i], tree.q_starts[i]
    R_o, p_o, axis = tree.origin_rotation[i], tree.origin_translation[i], tree.axes[i]
    zero = jnp.zeros(3, q.dtype)
    if kind == "revolute":
        R_j, p_j = axis_angle(axis, q[s]), zero
        S = jnp.concatenate([axis, zero])[:, None]
    elif kind == "prismatic":
        R_j, p_j = jnp.eye(3, dtype=q.dtype), axis * q[s]
        S = jnp.concatenate([zero, axis])[:, None]
    else:  # floating: v = [v_linear; omega] in the body frame, spatial vectors angular first
        R_j, p_j = quaternion_matrix(q[s + 3: s + 7]), q[s: s + 3]
        eye, zeros = jnp.eye(3, dtype=q.dtype), jnp.zeros((3, 3), q.dtype)
        S = jnp.block([[zeros, eye], [eye, zeros]])
    return R_o @ R_j, p_o + R_o @ p_j, S


def _velocity(tree, i, v):
    s = tree.v_starts[i]
    return v[s: s + (6 if tree.joint_types[i] == "floating" else 1)]


def _body_inertia(tree, i):
    return spatial_inertia(tree.mass[i], tree.com[i], tree.inertia[i])


def _transforms(tree, q):
    """For every body i: S[i], and its pose (R, p) in its parent's frame, which makes the
    transform ^i X_parent(i) = (E, r) = (R^T, p)."""
    S, poses = [], []
    for i in range(tree.num_bodies):
        R, p, S_i = _joint(tree, i, q)
        S.append(S_i)
        poses.append((R, p))
    return S, poses


def _base_acceleration(tree, dtype, gravity: bool):
    g = tree.gravity.astype(dtype) if gravity else jnp.zeros(3, dtype)
    return jnp.concatenate([jnp.zeros(3, dtype), -g])


def rnea(tree: KinematicTree, q, v, a, *, gravity: bool = True):
    r"""Inverse dynamics: $\tau = H(q)\dot v + C(q, v) v + G(q)$ (recursive Newton-Euler),
    with the spatial products by blocks (see `aba`)."""
    S, poses = _transforms(tree, q)
    n = tree.num_bodies
    vel, acc, force = [None] * n, [None] * n, [None] * n
    a0 = _base_acceleration(tree, q.dtype, gravity)
    for i in range(n):
        p = tree.parents[i]
        E, r = poses[i][0].T, poses[i][1]
        vJ = S[i] @ _velocity(tree, i, v)
        vel[i] = (transform_motion(E, r, vel[p]) if p >= 0 else jnp.zeros(6, q.dtype)) + vJ
        acc[i] = (transform_motion(E, r, acc[p] if p >= 0 else a0) + S[i] @ _velocity(tree, i, a)
                  + motion_cross(vel[i], vJ))
        I = _body_inertia(tree, i)
        force[i] = I @ acc[i] + force_cross(vel[i], I @ vel[i])
    tau = [None] * n
    for i in reversed(range(n)):
        tau[i] = S[i].T @ force[i]
        p = tree.parents[i]
        if p >= 0:
            force[p] = force[p] + transform_force_back(poses[i][0].T, poses[i][1], force[i])
    return jnp.concatenate(tau)


def mass_matrix(tree: KinematicTree, q):
    """H(q) by the composite-rigid-body algorithm."""
    S, poses = _transforms(tree, q)
    n = tree.num_bodies
    Ic = [_body_inertia(tree, i) for i in range(n)]
    for i in reversed(range(n)):
        p = tree.parents[i]
        if p >= 0:
            Ic[p] = Ic[p] + transform_inertia(poses[i][0].T, poses[i][1], Ic[i])
    # blocks H_ij for j = i and its ancestors, then H assembled by concatenation (no scatters)
    blocks = {}
    for i in range(n):
        F = Ic[i] @ S[i]
        blocks[i, i] = S[i].T @ F
        j = i
        while tree.parents[j] >= 0:
            E, r = poses[j][0].T, poses[j][1]
            F = (transform_force_back(E, r, F[:, 0])[:, None] if F.shape[1] == 1
                 else jnp.stack([transform_force_back(E, r, f) for f in F.T], axis=1))
            j = tree.parents[j]
            blocks[i, j] = F.T @ S[j]
            blocks[j, i] = blocks[i, j].T
    dofs = [S_i.shape[1] for S_i in S]
    rows = [jnp.concatenate([blocks.get((i, j), jnp.zeros((dofs[i], dofs[j]), q.dtype)) for j in range(n)], axis=1)
            for i in range(n)]
    return jnp.concatenate(rows, axis=0)


def bias_forces(tree: KinematicTree, q, v, *, gravity: bool = True):
    """C(q, v) v + G(q) (gravity=False: C(q, v) v alone)."""
    return rnea(tree, q, v, jnp.zeros_like(v), gravity=gravity)


def gravity_forces(tree: KinematicTree, q):
    """G(q): the generalized gravity term, on the left of H qdd + C qd + G = tau."""
    return rnea(tree, q, jnp.zeros(tree.nv, q.dtype), jnp.zeros(tree.nv, q.dtype))


def aba(tree: KinematicTree, q, v, tau, *, gravity: bool = True):
    r"""Forward dynamics $\dot v = H^{-1}(\tau - C v - G)$ by the articulated-body algorithm, O(n).

    Spatial products are written by blocks ((E, r) transforms, cross products) rather than
    as 6x6 matrices, and one-dof joints use a motion-subspace vector: the vmapped batch on
    a CPU is about twice as fast as with dense 6x6 products."""
    S, poses = _transforms(tree, q)
    n = tree.num_bodies
    E = [R.T for R, _ in poses]
    r = [p for _, p in poses]
    single = [S_i.shape[1] == 1 for S_i in S]
    S = [S_i[:, 0] if one else S_i for S_i, one in zip(S, single)]
    vel, c, IA, pA = [None] * n, [None] * n, [None] * n, [None] * n
    for i in range(n):
        p = tree.parents[i]
        qd = _velocity(tree, i, v)
        vJ = S[i] * qd[0] if single[i] else S[i] @ qd
        vel[i] = (transform_motion(E[i], r[i], vel[p]) if p >= 0 else jnp.zeros(6, q.dtype)) + vJ
        c[i] = motion_cross(vel[i], vJ)
        IA[i] = _body_inertia(tree, i)
        pA[i] = force_cross(vel[i], IA[i] @ vel[i])
    U, D_inv, u = [None] * n, [None] * n, [None] * n
    for i in reversed(range(n)):
        if single[i]:
            U[i] = IA[i] @ S[i]
            D_inv[i] = 1.0 / (S[i] @ U[i])
            u[i] = tau[tree.v_starts[i]] - S[i] @ pA[i]
            Ia = IA[i] - D_inv[i] * jnp.outer(U[i], U[i])
            pa_joint = U[i] * (D_inv[i] * u[i])
        else:
            U[i] = IA[i] @ S[i]
            D_inv[i] = jnp.linalg.inv(S[i].T @ U[i])
            u[i] = _velocity(tree, i, tau) - S[i].T @ pA[i]
            Ia = IA[i] - U[i] @ D_inv[i] @ U[i].T
            pa_joint = U[i] @ (D_inv[i] @ u[i])
        p = tree.parents[i]
        if p >= 0:
            pa = pA[i] + Ia @ c[i] + pa_joint
            IA[p] = IA[p] + transform_inertia(E[i], r[i], Ia)
            pA[p] = pA[p] + transform_force_back(E[i], r[i], pa)
    acc, qdd = [None] * n, [None] * n
    a0 = _base_acceleration(tree, q.dtype, gravity)
    for i in range(n):
        p = tree.parents[i]
        a = transform_motion(E[i], r[i], acc[p] if p >= 0 else a0) + c[i]
        if single[i]:
            qdd_i = D_inv[i] * (u[i] - U[i] @ a)
            acc[i] = a + S[i] * qdd_i
            qdd[i] = qdd_i[None]
        else:
            qdd[i] = D_inv[i] @ (u[i] - U[i].T @ a)
            acc[i] = a + S[i] @ qdd[i]
    return jnp.concatenate(qdd)


def body_poses(tree: KinematicTree, q):
    """World rotation and position of every body frame: arrays (n, 3, 3) and (n, 3)."""
    Rs, ps = [], []
    for i in range(tree.num_bodies):
        R, p, _ = _joint(tree, i, q)
        parent = tree.parents[i]
        if parent >= 0:
            R, p = Rs[parent] @ R, Rs[parent] @ p + ps[parent]
        Rs.append(R)
        ps.append(p)
    return jnp.stack(Rs), jnp.stack(ps)


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


def frame_jacobian(tree: KinematicTree, q, frame: str, *, poses=None):
    r"""The 6 x nv Jacobian of a named frame, world-aligned: $[\omega; \dot p] = J(q)\, v$ with
    $\omega$ the frame's angular velocity and $\dot p$ the velocity of its origin, both in
    world coordinates. `poses` as for `frame_pose`."""
    k = _frame_index(tree, frame)
    Rs, ps = body_poses(tree, q) if poses is None else poses
    body = tree.frame_bodies[k]
    J = jnp.zeros((6, tree.nv), q.dtype)
    if body < 0:
        return J
    p_frame = Rs[body] @ tree.frame_translation[k] + ps[body]
    j = body
    while j >= 0:
        s, R, p = tree.v_starts[j], Rs[j], ps[j]
        kind = tree.joint_types[j]
        if kind == "revolute":
            w = R @ tree.axes[j]
            J = J.at[:, s].set(jnp.concatenate([w, jnp.cross(w, p_frame - p)]))
        elif kind == "prismatic":
            J = J.at[3:, s].set(R @ tree.axes[j])
        else:
            J = J.at[3:, s: s + 3].set(R)
            J = J.at[:3, s + 3: s + 6].set(R)
            J = J.at[3:, s + 3: s + 6].set(-skew(p_frame - p) @ R)
        j = tree.parents[j]
    return J


def _frame_index(tree, frame):
    try:
        return tree.frame_names.index(frame)
    except ValueError:
        raise KeyError(f"no frame {frame!r}; the frames are {list(tree.frame_names)}") from None


def kinetic_energy(tree: KinematicTree, q, v):
    return 0.5 * v @ mass_matrix(tree, q) @ v


def potential_energy(tree: KinematicTree, q):
    """-sum_i m_i g . c_i, c_i the world position of body i's centre of mass."""
    Rs, ps = body_poses(tree, q)
    centres = jnp.einsum("nij,nj->ni", Rs, tree.com) + ps
    return -jnp.sum(tree.mass * (centres @ tree.gravity))


def configuration_derivative(tree: KinematicTree, q, v):
    r"""$\dot q$ from v: the identity for revolute and prismatic joints; for a floating base
    $\dot p = R v_{lin}$ and $\dot{\mathbf q} = \tfrac12 \mathbf q \otimes (0, \omega)$."""
    parts = []
    for i, kind in enumerate(tree.joint_types):
        s, sv = tree.q_starts[i], tree.v_starts[i]
        if kind != "floating":
            parts.append(v[sv: sv + 1])
            continue
        quat = q[s + 3: s + 7]
        x, y, z, w = quat
        R = quaternion_matrix(quat)
        wx, wy, wz = v[sv + 3], v[sv + 4], v[sv + 5]
        quat_dot = 0.5 * jnp.stack([w * wx + y * wz - z * wy, w * wy + z * wx - x * wz,
                                    w * wz + x * wy - y * wx, -(x * wx + y * wy + z * wz)])
        parts += [R @ v[sv: sv + 3], quat_dot]
    return jnp.concatenate(parts)
