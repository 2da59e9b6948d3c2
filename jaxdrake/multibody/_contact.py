r"""Compliant point contact, exactly Drake's continuous `MultibodyPlant` (`ContactModel.kPoint`).

For every candidate contact of a geometry pair (A, B) (`jaxdrake.geometry.penetration`), with
depth x > 0, witness points $C_a, C_b$, normal $\hat n_{BA}$ and contact point
$C = (C_a + C_b)/2$:

- normal force on A (Hunt & Crossley): $f_n = w k x (1 + d\, v_n)$, $v_n = v_{A_cB_c} \cdot
  \hat n_{BA}$ (> 0 approaching), applied where $f_n > 0$; w the candidate's weight, 1 but
  at a corner of two polytopes' contact polygon (its exterior angle's share, 4 in all);
- friction on A (Drake's regularised Stribeck law): $f_t = \mu(s)\, f_n\, \hat t$ along the
  slip $v_t = v_{A_cB_c} - v_n \hat n_{BA}$, $s = |v_t|$, $\hat t = v_t / s$, with
  $\mu(s) = \mu_s\,\mathrm{step5}(s/v_s)$ for $s < v_s$, $\mu_s - (\mu_s - \mu_d)
  \mathrm{step5}((s/v_s - 1)/2)$ for $v_s \le s < 3 v_s$, $\mu_d$ beyond
  ($\mathrm{step5}(x) = 10x^3 - 15x^4 + 6x^5$, $v_s$ the stiction tolerance, Drake's default
  $10^{-4}$ m/s); B receives the opposite force at C;
- two geometries' properties combine as Drake's do: $k = k_A k_B / (k_A + k_B)$,
  $d = (k_B d_A + k_A d_B)/(k_A + k_B)$, $\mu = 2\mu_A\mu_B/(\mu_A + \mu_B)$ (static and
  dynamic each);
- defaults (Drake's `SceneGraphConfig.default_proximity_properties`, filled in where a
  geometry lacks a value): stiffness $10^6$ N/m, dissipation 50 s/m, friction 0.5 / 0.5
  (a URDF `<collision>` without `drake:mu_*` gets 1.0 / 1.0, as from Drake's URDF parser).

The candidate pairs are fixed at construction (every pair of geometries on different bodies
that collision filtering lets through); at run time a candidate acts only where it touches.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import os
import sys
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import device_array
from ..geometry import (BOX_FACE_NORMALS, Convex, GeometryError, HalfSpace, canonical_order, norm_and_direction,
                        penetration, shape_kind, shape_size)
from . import _algorithms as alg
from ._joints import JointType

DEFAULT_STICTION_TOLERANCE = 1e-4
MIN_STIFF_CANDIDATES = 16   # the deepest candidates summed in `ContactModel.force_derivatives`, at least
_MOST_TOUCHING = 9   # ... and up to 9 of each pair against the world (two boxes: 8 polygon corners, an edge pair)
DEFAULT_STIFFNESS = 1e6
DEFAULT_DISSIPATION = 50.0
DEFAULT_FRICTION = (0.5, 0.5)
URDF_DEFAULT_FRICTION = (1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class ContactMaterial:
    """A geometry's contact properties (Drake's `drake:proximity_properties`); None: Drake's
    default, filled in where a geometry lacks a value: stiffness 1e6 N/m, dissipation 50 s/m,
    friction 0.5 / 0.5 (1.0 / 1.0 for a URDF `<collision>`, as Drake's parser gives). Two
    geometries' properties combine by Drake's rules ("The contact model" on the API page)."""

    point_contact_stiffness: float | None = None
    hunt_crossley_dissipation: float | None = None
    mu_static: float | None = None
    mu_dynamic: float | None = None

    def check(self, where: str):
        for name in ("point_contact_stiffness", "hunt_crossley_dissipation", "mu_static", "mu_dynamic"):
            value = getattr(self, name)
            if isinstance(value, jax.core.Tracer):
                raise GeometryError(
                    f"{where}: {name} is traced (a material built inside jax.grad / jit / vmap); a plant's "
                    "geometry is built once, outside: build it with a number there, then replace the leaf, "
                    "e.g. eqx.tree_at(lambda p: p.contact.mu_static, plant, new_values) (one value per "
                    "geometry, plant.contact.names; also mu_dynamic, stiffness, dissipation)")
            if value is not None and not (np.isfinite(value) and value >= 0):
                raise GeometryError(f"{where}: {name} must be a non-negative finite number, got {value}")
        mu_s, mu_d = self.friction()
        if mu_d > mu_s:
            raise GeometryError(f"{where}: mu_dynamic ({mu_d}) exceeds mu_static ({mu_s}); "
                                "as in Drake, the static coefficient must be at least the dynamic one")

    def friction(self):
        """(mu_static, mu_dynamic), one filling in for the other as Drake's parser does."""
        s, d = self.mu_static, self.mu_dynamic
        if s is None and d is None:
            return DEFAULT_FRICTION
        return (d if s is None else s), (s if d is None else d)


@dataclasses.dataclass(frozen=True)
class CollisionGeometry:
    """One collision shape on a link: `shape` placed at (R, p) in the link's frame."""

    name: str
    link: str
    shape: object
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: tuple = (0.0, 0.0, 0.0)
    material: ContactMaterial = ContactMaterial()

    def __post_init__(self):  # tuples: hashable, so a plant holding them stays a static structure
        R, p = np.asarray(self.rotation, float), np.asarray(self.translation, float)
        if R.shape != (3, 3) or p.shape != (3,):
            raise GeometryError(f"collision {self.name!r}: rotation must be a 3x3 rotation matrix and "
                                f"translation a 3-vector, got shapes {R.shape}, {p.shape}")
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0):
            raise GeometryError(f"collision {self.name!r}: rotation is not a rotation matrix (R R^T = I, det R = "
                                f"+1 to 1e-9): R R^T = {np.round(R @ R.T, 6).tolist()}, det R = {np.linalg.det(R):.6g}; "
                                "e.g. jd.multibody.rpy(roll, pitch, yaw) makes one")
        object.__setattr__(self, "rotation", tuple(map(tuple, R.tolist())))
        object.__setattr__(self, "translation", tuple(p.tolist()))


def _extents_and_thicknesses(kinds, size, vertices, valid, planes):
    """Each geometry's largest distance of its points from its frame's origin (0: a half-space,
    which sits on the world) and a lower bound on its thinnest width (a hull's: its inscribed
    ball's about the vertices' mean; inf: a half-space), over all geometries at once."""
    kind = np.asarray(kinds)
    r, half = size[:, 0], size[:, 1]
    norms = jnp.where(valid, jnp.linalg.norm(vertices, axis=-1), 0.0)
    # a hull's width is at least the diameter of the ball about its vertices' mean that its
    # faces n . x <= d leave room for
    centre = jnp.sum(jnp.where(valid[..., None], vertices, 0.0), 1) / jnp.maximum(jnp.sum(valid, 1), 1)[:, None]
    room = planes[..., 3] - jnp.einsum("gfk,gk->gf", planes[..., :3], centre)
    inscribed = 2 * jnp.min(room, axis=1, initial=jnp.inf)
    extent = jnp.select([kind == "sphere", kind == "box", kind == "capsule", kind == "cylinder", kind == "convex"],
                        [r, jnp.linalg.norm(size, axis=1), r + half, jnp.hypot(r, half), jnp.max(norms, axis=1, initial=0.0)], 0.0)
    thickness = jnp.select([(kind == "sphere") | (kind == "capsule"), kind == "box", kind == "cylinder",
                            kind == "convex"],
                           [2 * r, 2 * jnp.min(size, axis=1), 2 * jnp.minimum(r, half), inscribed],
                           jnp.inf)
    return extent, thickness


class ContactResults(eqx.Module):
    """Every candidate contact at one state (Drake's `ContactResults` for point pairs), arrays
    over candidates: `active` (touching with a positive normal force), `depth`, `point` (C,
    world), `normal` ($\\hat n_{BA}$, from B into A), `force` (on B at C, world: Drake's
    `f_Bc_W`; A receives -force), `normal_force` ($f_n \\ge 0$, the magnitude pushing the two
    apart, times the candidate's weight), `slip_speed`, `separation_speed` ($v_n$), and the
    geometry indices `geometry_a`, `geometry_b` (static, into `ContactModel.names`:
    `plant.contact.names[res.geometry_a[i]]` names candidate i's A; which of a pair is A
    follows the shape kinds' order: a sphere before a capsule, a cylinder, a box, a hull, a
    half-space)."""

    active: jax.Array
    depth: jax.Array
    point: jax.Array
    normal: jax.Array
    force: jax.Array
    normal_force: jax.Array
    slip_speed: jax.Array
    separation_speed: jax.Array
    geometry_a: tuple = eqx.field(static=True)
    geometry_b: tuple = eqx.field(static=True)


_ROUNDED = ("sphere", "capsule")   # curved everywhere across their contacts
_FACETED = ("box", "convex")       # flat faces meeting at edges and corners


class _Features(NamedTuple):
    """A faceted geometry's features at a candidate's witness point (`ContactModel._features`)."""
    faceted: np.ndarray       # a box or hull (known at trace time)
    along_a_face: jax.Array   # the outward normal there is one of its faces' normals
    alignment: jax.Array      # the largest cosine between the outward normal and a face's through the point
    on_edge: jax.Array        # exactly two faces pass through the point
    corner: jax.Array         # three do
    direction: jax.Array      # (p, 3): the edge's direction in the world where two do, else 0

    @property
    def on_that_face(self):
        """The outward normal is the normal of a face through the point."""
        return self.alignment > 1.0 - 1e-6


class ContactModel(eqx.Module):
    """The plant's collision geometry and its point-contact parameters.

    Static: geometry `names`, `links`, `kinds`, `bodies` (the tree body each is fixed to, -1
    the world) and `groups`: (kind_a, kind_b, geometry indices a, b) of the candidate pairs,
    grouped by shape kinds. Leaves: each geometry's pose in its body's frame (`rotation`,
    `translation`), `size`, convex `vertices` / `planes` / `triangles` / face `polygons` / `edges`
    with their faces' `edge_normals` (padded), and `stiffness`,
    `dissipation`, `mu_static`, `mu_dynamic`; the plant's `stiction_tolerance`.
    """

    names: tuple = eqx.field(static=True)
    links: tuple = eqx.field(static=True)
    kinds: tuple = eqx.field(static=True)
    bodies: tuple = eqx.field(static=True)
    groups: tuple = eqx.field(static=True)
    rotation: jax.Array
    translation: jax.Array
    size: jax.Array
    vertices: jax.Array
    vertex_valid: jax.Array
    planes: jax.Array
    triangles: jax.Array
    polygons: jax.Array
    polygon_valid: jax.Array
    edges: jax.Array
    edge_normals: jax.Array
    stiffness: jax.Array
    dissipation: jax.Array
    mu_static: jax.Array
    mu_dynamic: jax.Array
    stiction_tolerance: jax.Array

    # ----- queries ------------------------------------------------------------------------

    def geometry_poses(self, motion: alg.BodyMotion):
        """World (R (g, 3, 3), p (g, 3)) of every geometry, from the bodies' `motion`."""
        Rs, ps = _with_world(motion.rotation, jnp.eye(3)), _with_world(motion.position, jnp.zeros(3))
        b = np.asarray(self.bodies) + 1
        R_B, p_B = Rs[b], ps[b]
        return R_B @ self.rotation, jnp.einsum("gij,gj->gi", R_B, self.translation) + p_B

    def step_bound(self, tree, q, v):
        r"""The longest step in which no geometry moves more than half the thinnest one's
        thickness $\delta$ (of those in a candidate pair): a longer step may carry a body
        through a small obstacle between two evaluations of the force (`Rosenbrock23`, exact
        for a free fall, stepped a ball through a 10-cm sphere in one step). Geometry g's points
        move at most at $s_g = \sum_k c_{kg} |v_k|$ ($c_{kg}$: 1 for a translation that moves
        g, for a rotation the reach from its axis to g's farthest point along the tree's
        segments, a prismatic joint's at its present extension), with gravity's acceleration
        |g| (contact and joint forces are the error control's), so the step is the root of
        $s h + \tfrac12 |g| h^2 = \delta / 2$ for the fastest geometry, $s = \max_g s_g$:
        $h = \delta / (s + \sqrt{s^2 + |g| \delta})$."""
        reach, thickness = self._reach_and_thickness(tree, q)
        s = jnp.max(jnp.abs(v) @ reach.astype(v.dtype), initial=0.0)
        g = jnp.linalg.norm(tree.gravity).astype(v.dtype)
        delta = thickness.astype(v.dtype)
        return delta / (s + jnp.sqrt(s * s + g * delta))

    def moves(self) -> bool:
        """Whether a geometry of a candidate pair is fixed to a body (not all to the world;
        without pairs nothing touches, and no step is bounded)."""
        return any(self.bodies[g] >= 0 for _, _, a, b in self.groups for g in a + b)

    def _reach_and_thickness(self, tree, q):
        """(c (nv, geometries), delta) of `step_bound`."""
        L = tree.layout
        ancestors = L.subtree[np.ix_(L.position, L.position)].T   # tree order, [b, c]: c is b or an ancestor of b
        prismatic = [b for b, kind in enumerate(tree.joint_types) if kind == JointType.PRISMATIC]
        segment = jnp.linalg.norm(tree.origin_translation, axis=1).astype(q.dtype)
        if prismatic:   # a prismatic joint's segment at its present extension
            segment = segment.at[np.asarray(prismatic)].add(jnp.abs(q[np.asarray(tree.q_starts)[prismatic]]))
        along = jnp.asarray(ancestors, q.dtype) @ segment                               # root to each body
        extent, thickness = _extents_and_thicknesses(self.kinds, self.size, self.vertices, self.vertex_valid,
                                                     self.planes)
        bodies = np.asarray(self.bodies)
        body = np.maximum(bodies, 0)
        radius = jnp.linalg.norm(self.translation, axis=1) + extent                     # from its body's frame
        dof_body = L.order[L.dof_body]                                                 # tree order
        angular = np.concatenate([[False] * 3 + [True] * 3 if kind == JointType.FLOATING else [kind == JointType.REVOLUTE]
                                  for kind in tree.joint_types])
        moves = (ancestors[body][:, dof_body].T > 0) & (bodies >= 0)[None]              # [k, g]: v_k moves g
        lever = along[body][None] - along[dof_body][:, None] + radius[None]
        reach = jnp.where(moves, jnp.where(angular[:, None], lever, 1.0), 0.0)
        paired = np.zeros(len(bodies), bool)
        for _, _, a, b in self.groups:
            paired[list(a) + list(b)] = True
        return reach, jnp.min(jnp.where(paired, thickness, jnp.inf))

    def point_pairs(self, motion: alg.BodyMotion):
        """Candidate contacts of every pair: depth, C_a, C_b, n_BA, weight (arrays over
        candidates, `jd.geometry.penetration`'s) and the static geometry indices a, b of each."""
        R, p = self.geometry_poses(motion)
        params = {"size": self.size, "vertices": self.vertices, "vertex_valid": self.vertex_valid,
                  "planes": self.planes, "triangles": self.triangles, "polygons": self.polygons,
                  "polygon_valid": self.polygon_valid, "edges": self.edges, "edge_normals": self.edge_normals}
        parts, ia, ib = [], [], []
        for kind_a, kind_b, a, b in self.groups:
            a_idx, b_idx = np.asarray(a), np.asarray(b)
            pick = lambda idx: jax.tree.map(lambda x: x[idx], params)  # noqa: E731
            query = lambda pa, Ra, ta, pb, Rb, tb: penetration(kind_a, pa, (Ra, ta), kind_b, pb, (Rb, tb))  # noqa: E731
            pairs = (pick(a_idx), R[a_idx], p[a_idx], pick(b_idx), R[b_idx], p[b_idx])
            if kind_a == kind_b == "convex" and self.edges.shape[1] ** 2 > CULLED_EDGE_PAIRS:
                centre, radius = self._bounding_spheres(R, p)
                out = _where_near(query, pairs, (centre[a_idx], radius[a_idx]), (centre[b_idx], radius[b_idx]))
            else:
                out = jax.vmap(query)(*pairs)
            k = out[0].shape[1]
            parts.append(tuple(x.reshape((-1,) + x.shape[2:]) for x in out))
            ia += np.repeat(a_idx, k).tolist()
            ib += np.repeat(b_idx, k).tolist()
        if not parts:
            z = jnp.zeros((0, 3), R.dtype)
            return (jnp.zeros(0, R.dtype), z, z, z, jnp.zeros(0, R.dtype)), (), ()
        return tuple(jnp.concatenate(x) for x in zip(*parts)), tuple(ia), tuple(ib)

    def _bounding_spheres(self, R, p):
        """Each hull's bounding sphere about its vertices' mean: world centres (g, 3) (at the
        geometries' world poses R, p) and radii (g,)."""
        valid = self.vertex_valid[..., None]
        mean = jnp.sum(jnp.where(valid, self.vertices, 0.0), 1) / jnp.maximum(jnp.sum(valid, 1), 1)
        radius = jnp.max(jnp.where(valid[..., 0], jnp.linalg.norm(self.vertices - mean[:, None], axis=-1), 0.0), axis=1)
        return jnp.einsum("gij,gj->gi", R, mean) + p, radius

    def results(self, tree, q, v) -> ContactResults:
        """The contact forces at (q, v) ("The contact model" on the API page)."""
        return self._results(alg.body_motion(tree, q, v))

    def _results(self, motion: alg.BodyMotion) -> ContactResults:
        (depth, pa, pb, n, weight), ia, ib = self.point_pairs(motion)
        C = 0.5 * (pa + pb)
        V, ps = _with_world(motion.velocity, jnp.zeros(6)), _with_world(motion.position, jnp.zeros(3))
        body_a, body_b = self._pair_bodies(ia, ib)
        point_velocity = lambda b: V[b, 3:] + jnp.cross(V[b, :3], C - ps[b])  # noqa: E731
        v_AcBc = point_velocity(body_b) - point_velocity(body_a)
        f_A, (active, fn, slip, vn) = _force_on_a(depth, v_AcBc, n, *self._pair_parameters(ia, ib, weight))
        return ContactResults(active=active, depth=depth, point=C, normal=n, force=-f_A, normal_force=fn, slip_speed=slip,
                              separation_speed=vn, geometry_a=ia, geometry_b=ib)

    def _pair_bodies(self, ia, ib):
        """Rows of `_with_world` arrays (0: the world) of the bodies of every candidate's A and B."""
        bodies = np.asarray(self.bodies)
        return bodies[np.asarray(ia, int)] + 1, bodies[np.asarray(ib, int)] + 1

    def _pair_parameters(self, ia, ib, weight):
        """(k, d, mu_static, mu_dynamic, v_s) of every candidate, combined by Drake's rules; k
        times the candidate's weight (a contact polygon's corner's share)."""
        ia_, ib_ = np.asarray(ia, int), np.asarray(ib, int)
        k, d = _combined_stiffness_dissipation(self.stiffness[ia_], self.stiffness[ib_],
                                               self.dissipation[ia_], self.dissipation[ib_])
        return (weight * k, d, _harmonic(self.mu_static[ia_], self.mu_static[ib_]),
                _harmonic(self.mu_dynamic[ia_], self.mu_dynamic[ib_]), self.stiction_tolerance)

    def force_derivatives(self, tree, q, v):
        r"""The contact force's derivative: (K, D), nv x nv, with
        $d\tau_c \approx K\,\delta\nu + D\,dv$ for a change $\delta\nu$ of the
        configuration in velocity coordinates (`alg.velocity_of_configuration_change`) and dv of
        the velocity.

        With $G_c(q) = J_{B}(C_c) - J_{A}(C_c)$ (3 x nv) the Jacobian of candidate c's relative
        velocity $v_{A_cB_c} = G_c v$ at its contact point C, $\tau_c = -\sum_c G_c^T
        f_{A,c}(x_c, G_c v)$: $D = -\sum_c G_c^T F_v G_c$ and $K = -\sum_c [G_c^T (F_x \hat
        n^T G_c + F_v\, \partial_\nu(G_c) v + F_n \partial_\nu \hat n) + \partial_\nu(G_c)^T
        f_{A,c}]$, with $F_x, F_v, F_n$ the force law's derivatives in the depth (which grows
        at $\hat n \cdot v_{A_cB_c}$), the relative velocity and the normal. $\partial_\nu G$:
        the bodies' motion subspaces turn, $\partial S_k / \partial \nu_j = S_j \times S_k$ for
        a coordinate j that carries k's axis, and C moves across $\hat n$ with the centres of
        curvature $O_A, O_B$ of the two surfaces, weighted as rolling contact has it (a
        sphere's centre on a flat face or half-space, a box's corner or edge itself under a
        rolling ball, but along an edge with the ball), along $\hat n$ by half their
        approach (C is the witnesses' midpoint); a cylinder tilted on a rim rolls on it, C
        the rim's lowest point (`_rolling_rim`). Where both surfaces are curved (two round
        shapes, a ball on a corner or edge) the normal turns, $\partial \hat n = P(\partial
        O_A - \partial O_B) / (\rho_A + \rho_B)$, P the projection across $\hat n$ (and
        across an edge's direction) (a ball rolling off a box's edge: 5x fewer steps).

        Only the deepest candidates are summed, as many as there are against the world's
        geometries (the ground; at most `_MOST_TOUCHING` of each pair) and at least
        `MIN_STIFF_CANDIDATES`: one that does not touch adds nothing, and a contact's damping and
        friction slope grow with its depth, so the shallowest are the least stiff (Solo-12: 16
        of 68, which makes this 2-3x cheaper; a stack of hulls with octagonal faces, 17
        candidates a pair: 21% off its run)."""
        motion = alg.body_motion(tree, q, v)
        (depth, pa, pb, n, weight), ia, ib = self.point_pairs(motion)
        L = tree.layout
        moves = np.zeros((tree.num_bodies + 1, tree.nv))   # row 0: the world; else the ancestor mask
        moves[1 + np.arange(tree.num_bodies)] = L.subtree[L.dof_body][:, L.position].T
        body_a, body_b = self._pair_bodies(ia, ib)
        # C's motion: the centres of curvature (radius rho: a sphere's, a capsule's, a cylinder's
        # side; 0 at a polyhedron's corner or edge; B's face or half-space flat), weighted
        # rho_B : rho_A
        poses = self.geometry_poses(motion)
        (rho_a, curved_a), (rho_b, curved_b) = (self._curvature(poses[0], i, n) for i in (ia, ib))
        weight_b = jnp.where(curved_b, rho_a / jnp.where(curved_b, rho_a + rho_b, 1.0), 0.0)
        at_b = self._features(poses, ib, pb, n)
        # n meets B off its faces' normals: at a corner or an edge, which stays put on B as A rolls
        # over it; along an edge C moves with A and the normal does not turn
        on_corner = at_b.faceted & ~at_b.along_a_face
        edge = jnp.where((on_corner & ~at_b.corner)[:, None], at_b.direction, 0.0)
        # two polytopes: a corner of B on A's face is B's material point (A's flat face: rho_A
        # infinite), a corner of A on B's face A's (a box sliding on a welded box: C held in A
        # coupled its position to its turning, and the W-method took 12x the exact Jacobian's steps)
        at_a = self._features(poses, ia, pa, -n)
        corner_of_b = at_b.corner & ~at_a.corner
        # n is A's face's (the contact polygon's reference face): n is a face normal of A's to
        # rounding, B's less closely (a box landing flat on a table: B's face is the reference
        # when A is tilted by 1e-5 rad or more, and A's face normal is within 1e-6 of n there too;
        # turning n with A made the matrix's tilt columns wrong by their own size); ties: A's
        face_of_a = at_b.faceted & at_a.on_that_face & (
            at_a.alignment >= at_b.alignment - 64 * jnp.finfo(n.dtype).eps)
        # two edges crossing (a corner of the clipped polygon, or an edge across an edge)
        crossing = at_a.on_edge & at_b.on_edge
        weight_b = jnp.where(corner_of_b, 1.0, weight_b)
        on_corner = on_corner & curved_a
        edge = jnp.where(on_corner[:, None], edge, 0.0)
        weight_b = jnp.where(on_corner, 1.0, weight_b)   # a ball rolling over a corner turns about it
        # the normal turns where both surfaces are curved (B rounded, or A rounded on B's corner)
        turning = (curved_a & curved_b) | on_corner
        kinds = np.asarray(self.kinds)
        may_curve_a, may_curve_b = (np.isin(kinds[np.asarray(i, int)], _ROUNDED + ("cylinder",)) for i in (ia, ib))
        may_turn = bool(np.any(may_curve_a & (may_curve_b | np.isin(kinds[np.asarray(ib, int)], _FACETED))))
        *per_pair, stiction_tolerance = self._pair_parameters(ia, ib, weight)   # k, d, mu_s, mu_d per candidate; v_s
        rim_a = self._rolling_rim(poses, ia, pa, n)   # A's rim on a flat B, or B's on a flat A
        rim_a = None if rim_a is None else (rim_a[0] & ~curved_b,) + rim_a[1:]
        rim_b = self._rolling_rim(poses, ib, pb, -n)
        rim_b = None if rim_b is None else (rim_b[0] & ~curved_a & (True if rim_a is None else ~rim_a[0]),) + rim_b[1:]
        per_candidate = (depth, pa, pb, n, jnp.asarray(moves[body_a], pa.dtype), jnp.asarray(moves[body_b], pa.dtype),
                         rho_a, rho_b, weight_b, turning, face_of_a, edge, (rim_a, rim_b), tuple(per_pair),
                         (crossing, at_a.direction, at_b.direction, at_a.on_that_face | at_b.on_that_face))
        on_world = collections.Counter(pair for pair, a, b in zip(zip(ia, ib), body_a, body_b) if a == 0 or b == 0)
        kept = max(MIN_STIFF_CANDIDATES, sum(min(count, _MOST_TOUCHING) for count in on_world.values()))
        if kept < depth.shape[0]:
            deepest = jax.lax.top_k(jax.lax.stop_gradient(depth), kept)[1]
            per_candidate = jax.tree.map(lambda x: x[deepest], per_candidate)
        (depth, pa, pb, n, mask_a, mask_b, rho_a, rho_b, weight_b, turning, face_of_a, edge, rims, per_pair,
         crossings) = per_candidate
        params = per_pair + (stiction_tolerance,)
        C = 0.5 * (pa + pb)
        w, u = motion.columns[:, :3], motion.columns[:, 3:]                             # (nv, 3) each
        origin = alg.column_origins(tree, motion)                                        # (nv, 3)
        at = lambda point: u[None] + jnp.cross(w[None], point[:, None, :] - origin[None])  # noqa: E731
        G = at(C) * (mask_b - mask_a)[:, :, None]                                       # (P, nv, 3)
        centre_a = at(pa + rho_a[:, None] * n) * mask_a[:, :, None]                       # (P, nv_j, 3)
        centre_b = at(pb - rho_b[:, None] * n) * mask_b[:, :, None]
        dC = (1.0 - weight_b)[:, None, None] * centre_a + weight_b[:, None, None] * centre_b
        # where n is a flat face's normal (B's; A's where A's face is the reference) it turns with
        # that face's body, and C = O_A - rho_A n with it (a ball on a free box's face); the
        # world's faces, and spheres' and capsules' (none flat), never turn
        kinds_a, kinds_b = kinds[np.asarray(ia, int)], kinds[np.asarray(ib, int)]
        flat_b = np.isin(kinds_b, _FACETED + ("cylinder",))
        face_may_turn = bool(np.any((body_b != 0) & flat_b) or np.any((body_a != 0) & flat_b & np.isin(kinds_a, _FACETED)))
        dn = jnp.zeros_like(dC)
        if face_may_turn:
            dn = jnp.cross(w[None], n[:, None, :]) * jnp.where(face_of_a[:, None], mask_a, mask_b)[:, :, None]
            dC = dC - jnp.where(turning, 0.0, rho_a)[:, None, None] * dn
        along_edge = edge[:, :, None] * edge[:, None, :]
        dC = dC + (centre_a - centre_b) @ along_edge   # along an edge, C moves with A
        if np.any(np.isin(kinds_a, _FACETED) & np.isin(kinds_b, _FACETED)):
            dC, dn = _at_crossing_edges(crossings, face_of_a, n, w, centre_a, centre_b, mask_a, mask_b, dC, dn)
        # rolling on a rim: C moves with the rim's material point, and swings along the rim as its
        # cylinder turns about its axis or about its radius to C
        turn_about = lambda d: jnp.einsum("jk,pk->pj", w, d)  # noqa: E731   (P, nv): each column's turn about d
        for rim, mask, witness in zip(rims, (mask_a, mask_b), (pa, pb)):
            if rim is not None:
                rolls, axis, down, cot, radius = rim
                swing = -radius[:, None] * (turn_about(axis) + cot[:, None] * turn_about(down)) * mask
                rolled = at(witness) * mask[:, :, None] + swing[:, :, None] * jnp.cross(axis, down)[:, None, :]
                dC = jnp.where(rolls[:, None, None], rolled, dC)
        along = n[:, :, None] * n[:, None, :]   # and along n by half the centres' approach
        dC = dC - dC @ along + 0.5 * (centre_a + centre_b) @ along
        v_AcBc = jnp.sum(G * v[None, :, None], 1)
        force = lambda x, w, nn, *p: _force_on_a(x, w, nn, *p)[0]  # noqa: E731
        in_axes = (0, 0, 0) + tuple(0 if jnp.ndim(p) else None for p in params)
        f_A = force(depth, v_AcBc, n, *params)                                         # (P, 3)
        F_x, F_v, F_n = jax.vmap(jax.jacfwd(force, (0, 1, 2)), in_axes)(depth, v_AcBc, n, *params)   # (P, 3), (P, 3, 3) x2
        # sums over the candidates as single matrix products of (P x 3, nv) blocks (a batch of
        # P small products is far slower on a CPU); the 3-vectors' products elementwise.
        # the turning subspaces, summed before they are crossed (no (P, nv, nv, 3) tensor):
        # (S_j x S_k) paired with the relative twist's coordinates and with the forces' wrenches
        turns = jnp.asarray(_axis_carried_by(tree), C.dtype)                            # (nv_j, nv_k)
        relative = mask_b - mask_a                                                      # (P, nv)
        lever = C[:, None, :] - origin[None]                                           # (P, nv, 3)
        nv, P = tree.nv, C.shape[0]
        carried = (relative[:, :, None] * motion.columns[None]).transpose(1, 0, 2)     # (nv_k, P, 6)
        T = (turns * v[None]) @ carried.reshape(nv, P * 6)                              # sum_k turns v_k m_k S_k
        T = T.reshape(nv, P, 6).transpose(1, 0, 2)                                      # (P, nv_j, 6)
        Tw, Tu = T[..., :3], T[..., 3:]
        dw_v = jnp.cross(w[None], Tw)                                                   # (P, nv_j, 3)
        du_v = jnp.cross(w[None], Tu) + jnp.cross(u[None], Tw)
        omega_rel = relative @ (v[:, None] * w)                                         # (P, 3)
        dv_AcBc = du_v + jnp.cross(dw_v, lever) + jnp.cross(omega_rel[:, None, :], dC)   # (P, nv_j, 3)
        # each column k's wrench about its own O: sum_p rel_pk [(C_p - O_k) x f_p; f_p]
        wrench = relative.T @ jnp.concatenate([jnp.cross(C, f_A), f_A], 1)               # (nv_k, 6)
        wrench = wrench.at[:, :3].add(-jnp.cross(origin, wrench[:, 3:]))
        # (S_j x S_k) . W_k = (w_j x w_k) . W_k,ang + (w_j x u_k + u_j x w_k) . W_k,lin
        turned = (w @ jnp.cross(w, wrench[:, :3]).T + w @ jnp.cross(u, wrench[:, 3:]).T
                  + u @ jnp.cross(w, wrench[:, 3:]).T) * turns
        moved_by = relative.T @ jnp.cross(dC, f_A[:, None, :]).reshape(P, nv * 3)      # (nv_k, nv_j * 3)
        moved = jnp.sum(moved_by.reshape(nv, nv, 3) * w[:, None, :], -1)
        blocks = lambda X: X.transpose(0, 2, 1).reshape(P * 3, nv)  # noqa: E731  (P, nv, 3) -> (P x 3, nv)
        FG = jnp.sum(G[:, :, :, None] * F_v[:, None, :, :], 2)                         # (P, nv_k, 3): G_p^T F_v,p
        spring = jnp.sum(G * F_x[:, None, :], -1).T @ jnp.sum(G * n[:, None, :], -1)    # sum_p G^T F_x n^T G
        K = -(spring + blocks(FG).T @ blocks(dv_AcBc) + turned.T + moved)
        if may_turn:   # n = (O_a - O_b) / |O_a - O_b| between the centres of curvature, else a face's
            apart = jnp.where(turning, rho_a + rho_b, 1.0)
            across = jnp.eye(3, dtype=n.dtype) - n[:, :, None] * n[:, None, :] - along_edge   # not along an edge
            dn = jnp.where(turning[:, None, None], (centre_a - centre_b) @ across / apart[:, None, None], dn)
        if may_turn or face_may_turn:
            K = K - blocks(jnp.sum(G[:, :, :, None] * F_n[:, None, :, :], 2)).T @ blocks(dn)
        D = -(blocks(FG).T @ blocks(G))
        return K, D

    def _curvature(self, R, ids, n):
        """(rho, curved) of each candidate's geometry (world rotations R) at its contact,
        across the normal n: a sphere's or capsule's radius; a cylinder's where n is across its
        axis (its side), else flat (its caps and their rims); 0 for the rest."""
        kinds = np.asarray(self.kinds)[np.asarray(ids, int)]
        radius = self.size[np.asarray(ids, int), 0]
        curved = jnp.asarray(np.isin(kinds, _ROUNDED))
        if np.any(kinds == "cylinder"):
            axis = R[np.asarray(ids, int)][:, :, 2]
            curved = curved | ((kinds == "cylinder") & (jnp.abs(jnp.sum(axis * n, -1)) < 1e-6))
        return jnp.where(curved, radius, 0.0), curved

    def _rolling_rim(self, poses, ids, witness, toward):
        r"""(rolls, axis a, u, cot, radius r) of each candidate whose geometry (ids) is a
        cylinder touching at the point of a rim farthest along -`toward` (the other shape's
        normal n, pointing at this one), tilted: C = O + r u with u the unit projection of -n
        across a, so as the cylinder turns by $\delta\theta$, C moves as its material point
        would, less $r(\delta\theta \cdot a + \cot\vartheta\, \delta\theta \cdot u)$ along the
        rim's tangent $a \times u$ ($\cos\vartheta = n \cdot a$; the lowest point of a wheel
        turning about its axis stays put, and one of a tilted disk swings around its rim as the
        disk tips sideways). None without cylinders."""
        ids = np.asarray(ids, int)
        is_cylinder = np.asarray(self.kinds)[ids] == "cylinder"
        if not is_cylinder.any():
            return None
        R, p = poses[0][ids], poses[1][ids]
        radius, half = self.size[ids, 0], self.size[ids, 1]
        axis = R[:, :, 2]
        cos = jnp.sum(toward * axis, -1)
        sin, down = norm_and_direction(-(toward - cos[:, None] * axis), jnp.zeros_like(axis))
        offset = witness - p
        axial = jnp.sum(offset * axis, -1)
        radial, outward = norm_and_direction(offset - axial[:, None] * axis, jnp.zeros_like(axis))
        # on the rim to rounding (float32's: the witness's, and u's as the tilt goes to 0)
        size = 1e-6 * (radius + half) + 64 * jnp.finfo(axis.dtype).eps * (
            jnp.linalg.norm(p, axis=-1) + (radius + half) / jnp.maximum(sin, 1e-3))
        rolls = (jnp.asarray(is_cylinder) & (sin > 1e-3) & (jnp.abs(cos) > 1e-6)
                 & (jnp.abs(jnp.abs(axial) - half) < size) & (jnp.abs(radial - radius) < size)
                 & (jnp.sum(outward * down, -1) > 1.0 - 1e-4))
        return jax.lax.stop_gradient(rolls), axis, down, cos / jnp.where(rolls, sin, 1.0), radius

    def _faces_through(self, poses, ids, point):
        """Each candidate's faceted geometry (a box or hull; `faceted` marks them) at `point`:
        its rotation R, its faces' outward normals in its frame (p, f, 3; a box's 6 or a
        hull's, padded by repeats), and the point's signed distances to their planes (p, f)
        with the tolerance within which a face passes through it."""
        kinds = np.asarray(self.kinds)[np.asarray(ids, int)]
        faceted = np.isin(kinds, _FACETED)
        g = np.asarray(ids, int)
        R, p = poses[0][g], poses[1][g]
        faces = self.planes.shape[1]
        count = max(6, faces)
        box_normals = BOX_FACE_NORMALS[np.minimum(np.arange(count), 5)]
        box_offsets = jnp.concatenate([self.size[g], self.size[g]], 1)[:, np.minimum(np.arange(count), 5)]
        hull = self.planes[g][:, np.minimum(np.arange(count), faces - 1)].astype(point.dtype)
        is_box = np.asarray(kinds == "box")
        normals = jnp.where(is_box[:, None, None], jnp.asarray(box_normals, point.dtype)[None], hull[..., :3])
        offsets = jnp.where(is_box[:, None], box_offsets, hull[..., 3])
        values = jnp.einsum("pfk,pk->pf", normals, jnp.einsum("pji,pj->pi", R, point - p)) - offsets
        tolerance = 64 * jnp.finfo(point.dtype).eps * (1.0 + jnp.max(jnp.abs(offsets), axis=1) + jnp.linalg.norm(p, axis=1))
        return faceted, R, normals, values, tolerance

    def _features(self, poses, ids, point, outward):
        """Each candidate's faceted geometry (a box or hull) at its witness `point`, from the
        faces through it (one: a face; two distinct ones: an edge; three: a corner), with n the
        normal `outward` from the geometry there: `_Features`, all False / 0 for other shapes."""
        faceted, R, normals, values, tolerance = self._faces_through(poses, ids, point)
        if not faceted.any():
            none = jnp.zeros(len(ids), bool)
            return _Features(faceted, none, jnp.full(len(ids), -1.0, point.dtype), none, none, jnp.zeros_like(point))
        local = jnp.einsum("pji,pj->pi", R, outward)
        cosines = jnp.einsum("pfk,pk->pf", normals, local)
        along = cosines > 1.0 - 1e-6
        active = values > -tolerance[:, None]
        normal_of = lambda mask: jnp.take_along_axis(  # noqa: E731
            normals, jnp.argmax(jnp.where(mask, values, -jnp.inf), axis=1)[:, None, None], 1)[:, 0]
        distinct = lambda m: jnp.abs(jnp.einsum("pfk,pk->pf", normals, m)) < 1.0 - 1e-6  # noqa: E731
        first = normal_of(jnp.ones(values.shape, bool))
        second = normal_of(distinct(first))
        most = lambda mask: jnp.max(jnp.where(mask, values, -jnp.inf), axis=1) > -tolerance  # noqa: E731
        second_active = most(distinct(first))
        corner = faceted & most(distinct(first) & distinct(second))
        on_edge = faceted & second_active & ~corner
        direction = norm_and_direction(jnp.cross(first, second), jnp.broadcast_to(jnp.eye(3, dtype=first.dtype)[0],
                                                                                  first.shape))[1]
        direction = jnp.where(on_edge[:, None], jnp.einsum("pij,pj->pi", R, direction), 0.0)
        return _Features(faceted, faceted & jnp.any(along, 1),
                         jnp.where(faceted, jnp.max(jnp.where(active, cosines, -1.0), axis=1), -1.0), on_edge, corner,
                         direction)

    def generalized_forces(self, tree, q, v):
        r"""$\tau_c = \sum J^T f$ of all contact forces at (q, v), and the `ContactResults` (one
        forward-kinematics pass for both)."""
        motion = alg.body_motion(tree, q, v)
        res = self._results(motion)
        ps = _with_world(motion.position, jnp.zeros(3))
        body_a, body_b = self._pair_bodies(res.geometry_a, res.geometry_b)
        F = jnp.zeros((tree.num_bodies + 1, 6), res.force.dtype)
        for bodies, f in ((body_a, -res.force), (body_b, res.force)):
            F = F.at[bodies].add(jnp.concatenate([jnp.cross(res.point - ps[bodies], f), f], 1))
        return alg.external_forces(tree, motion, F[1:]), res


CULLED_EDGE_PAIRS = 4096   # hulls testing more pairs of edges than this are tested only where near


def _where_near(query, pairs, sphere_a, sphere_b):
    """`query` over the pairs one at a time, each only where the two shapes' bounding spheres
    (world centres and radii) meet; elsewhere its candidates (as many as the query's) are
    those spheres' nearest points, at depth minus their gap (no force). A broad phase for
    detailed hulls: Solo-12's 120 pairs of leg and body meshes (hulls of 32 vertices), of
    which a standing robot brings a few near, cost a test each in `jax.vmap`. Under `jax.vmap`
    of the caller every pair is tested, as before."""
    shapes = jax.eval_shape(query, *jax.tree.map(lambda x: x[0], pairs))

    def one(pair):
        arguments, (c_a, r_a), (c_b, r_b) = pair
        gap, toward_b = norm_and_direction(c_b - c_a, jnp.eye(3, dtype=c_a.dtype)[0])
        gap = gap - r_a - r_b

        def apart():
            k = shapes[0].shape[0]
            return (jnp.full(k, -gap), jnp.broadcast_to(c_a + r_a * toward_b, (k, 3)),
                    jnp.broadcast_to(c_b - r_b * toward_b, (k, 3)), jnp.broadcast_to(-toward_b, (k, 3)),
                    jnp.ones(k, c_a.dtype))

        return jax.lax.cond(gap <= 0, lambda: tuple(query(*arguments)), apart)

    return jax.lax.map(one, (pairs, sphere_a, sphere_b))


def _at_crossing_edges(crossings, face_of_a, n, w, centre_a, centre_b, mask_a, mask_b, dC, dn):
    r"""dC and dn of candidates where an edge of one polytope crosses an edge of the other: C
    stays on the incident edge (direction $d_I$, moving as its body's point $\delta I$) and
    on the plane through the reference edge $d_R$ and n, so $\delta C = \delta I + d_I\,
    m \cdot (\delta R - \delta I) / (m \cdot d_I)$, $m = \hat n \times d_R$ (the corners of
    two boxes' clipped polygon twisted against each other, held in A before: the W-method took
    10x the exact Jacobian's steps); edges within 3 degrees of parallel move with the incident
    body. Where neither face is n's (an edge crossing an edge), $\hat n \propto d_A \times
    d_B$ turns with both edges."""
    crossing, d_a, d_b, either_face = crossings
    d_ref, d_inc = jnp.where(face_of_a[:, None], d_a, d_b), jnp.where(face_of_a[:, None], d_b, d_a)
    moves_ref = jnp.where(face_of_a[:, None, None], centre_a, centre_b)
    moves_inc = jnp.where(face_of_a[:, None, None], centre_b, centre_a)
    across = jnp.cross(n, d_ref)
    sine = jnp.sum(across * d_inc, -1)
    slides = crossing & (jnp.abs(sine) > 0.05)
    slide = across[:, :, None] * d_inc[:, None, :] / jnp.where(slides, sine, 1.0)[:, None, None]
    dC = jnp.where(slides[:, None, None], moves_inc + (moves_ref - moves_inc) @ slide,
                   jnp.where(crossing[:, None, None], moves_inc, dC))
    # an edge across an edge: n = +-(d_a x d_b) / |d_a x d_b|, each d turning with its body
    normal = jnp.cross(d_a, d_b)
    size, direction = norm_and_direction(normal, n)
    edges = crossing & ~either_face & (size > 0.05)
    turned = (jnp.cross(jnp.cross(w[None], d_a[:, None, :]) * mask_a[:, :, None], d_b[:, None, :])
              + jnp.cross(d_a[:, None, :], jnp.cross(w[None], d_b[:, None, :]) * mask_b[:, :, None]))
    turned = turned - (turned @ n[:, :, None]) * n[:, None, :]
    sign = jnp.sign(jnp.sum(direction * n, -1))
    dn = jnp.where(edges[:, None, None], (sign / jnp.where(edges, size, 1.0))[:, None, None] * turned, dn)
    return dC, dn


def _force_on_a(depth, v_AcBc, n, k, d, mu_static, mu_dynamic, stiction_tolerance):
    """The force on A at C (module docstring) of candidates at depth x along n, with B's point
    moving at v_AcBc relative to A's; and (active, f_n, slip speed, v_n)."""
    vn = jnp.sum(v_AcBc * n, -1)
    touching = depth > 0
    fn = k * jnp.where(touching, depth, 0.0) * (1.0 + d * vn)
    active = touching & (fn > 0)
    fn = jnp.where(active, fn, 0.0)
    vt = v_AcBc - vn[..., None] * n
    slip, t_hat = norm_and_direction(vt, jnp.zeros_like(vt).at[..., 0].set(1.0))  # mu(0) = 0: no force
    mu = stribeck(slip, mu_static, mu_dynamic, stiction_tolerance)
    return fn[..., None] * n + (mu * fn)[..., None] * t_hat, (active, fn, slip, vn)


def _axis_carried_by(tree) -> np.ndarray:
    r"""(nv, nv): 1 where velocity coordinate j moves the body that carries coordinate k's axis
    (a joint's axis is fixed in its parent body; a floating base's six, in its own frame, in
    the base itself), so that there $\partial S_k/\partial\nu_j = S_j \times S_k$."""
    L = tree.layout
    carried = np.zeros((tree.nv, tree.nv))
    for k in range(tree.nv):
        body = int(L.order[L.dof_body[k]])
        carrier = body if L.dof_body[k] < L.num_floating else tree.parents[body]
        if carrier >= 0:
            carried[:, k] = L.subtree[L.dof_body, L.position[carrier]]
    return carried


def _with_world(per_body, world_value):
    """Per-body rows with the world's (index 0, body -1) in front."""
    return jnp.concatenate([jnp.broadcast_to(world_value, (1,) + per_body.shape[1:]).astype(per_body.dtype), per_body])


def stribeck(slip, mu_static, mu_dynamic, stiction_tolerance):
    """Drake's regularised Stribeck friction coefficient of a slip speed (module docstring)."""
    s = slip / stiction_tolerance
    step5 = lambda x: x ** 3 * (10 + x * (6 * x - 15))  # noqa: E731
    low = mu_static * step5(jnp.clip(s, 0.0, 1.0))
    mid = mu_static - (mu_static - mu_dynamic) * step5(jnp.clip((s - 1) / 2, 0.0, 1.0))
    return jnp.where(s >= 3, mu_dynamic, jnp.where(s >= 1, mid, low))


def _safe_divide(num, den):
    return jnp.where(den == 0, 0.0, num / jnp.where(den == 0, 1.0, den))


def _harmonic(a, b):
    return _safe_divide(2 * a * b, a + b)


def _combined_stiffness_dissipation(k1, k2, d1, d2):
    return _safe_divide(k1 * k2, k1 + k2), _safe_divide(k2, k1 + k2) * d1 + _safe_divide(k1, k1 + k2) * d2


# ----- construction ---------------------------------------------------------------------------


def build_contact_model(tree, geometries, *, excluded_pairs=(), stiction_tolerance=DEFAULT_STICTION_TOLERANCE,
                        source="") -> ContactModel:
    """A `ContactModel` for `geometries` (`CollisionGeometry`, on links of `tree` or 'world').

    Collision filtering as Drake's: no pair on one body (links welded together, the world's
    geometries among themselves), none whose link pair is in `excluded_pairs` (links joined by
    a joint whose parent is not the world; collision filter groups)."""
    if not (np.isfinite(stiction_tolerance) and stiction_tolerance > 0):
        raise ValueError(f"stiction_tolerance must be a positive speed in m/s, got {stiction_tolerance}")
    link_body = {name: body for name, body in zip(tree.frame_names, tree.frame_bodies)}
    link_body.setdefault("world", -1)
    bodies, kinds = [], []
    for g in geometries:
        where = f"{source}: link {g.link!r}, collision {g.name!r}" if source else f"link {g.link!r}, collision {g.name!r}"
        if g.link not in link_body:
            raise GeometryError(f"{where}: no link {g.link!r} in the tree; the links are {list(tree.frame_names)}")
        g.material.check(where)
        kinds.append(shape_kind(g.shape))
        body = link_body[g.link]
        if body >= 0 and not _body_has_mass(tree, body):
            raise GeometryError(f"{where}: the link carries no mass or inertia (nor does anything welded to "
                                "it), so a contact force on it has nothing to accelerate. Give the link an "
                                "<inertial>, or put the collision on the massive link it belongs to")
        if isinstance(g.shape, HalfSpace) and body >= 0:
            raise GeometryError(f"{where}: a half-space must be fixed to the world (it is infinite); "
                                "use a Box on a moving link")
        bodies.append(body)
    names = tuple(g.name for g in geometries)
    if len(set(names)) != len(names):
        raise GeometryError(f"{source}: collision geometry names must be unique; repeated: "
                            f"{sorted({n for n in names if names.count(n) > 1})}")
    excluded = {frozenset(p) for p in excluded_pairs}
    groups = {}
    for i in range(len(geometries)):
        for j in range(i + 1, len(geometries)):
            gi, gj = geometries[i], geometries[j]
            if bodies[i] == bodies[j] or frozenset((gi.link, gj.link)) in excluded:
                continue
            a, b = (i, j) if canonical_order(kinds[i], kinds[j]) else (j, i)
            key = (kinds[a], kinds[b])
            groups.setdefault(key, ([], []))
            groups[key][0].append(a)
            groups[key][1].append(b)
    _check_hull_pairs(geometries, groups.get(("convex", "convex"), ([], []))[0], source)
    floats = lambda x: device_array(np.asarray(x, float))  # noqa: E731
    convex = [g.shape for g in geometries if isinstance(g.shape, Convex)]
    nv = max((len(c.vertices) for c in convex), default=0)
    nf = max((len(c.planes) for c in convex), default=1)
    nt = max((len(c.triangles) for c in convex), default=1)
    vertices = np.zeros((len(geometries), nv, 3))
    valid = np.zeros((len(geometries), nv), bool)
    planes = np.tile(np.array([0.0, 0.0, 1.0, 0.0]), (len(geometries), nf, 1))
    triangles = np.tile(np.eye(3), (len(geometries), nt, 1, 1))
    polytope_sizes = np.max([c.polytope_sizes for c in convex] or [(1, 1, 1)], axis=0)
    polygons = np.zeros((len(geometries), *polytope_sizes[:2], 3))
    polygon_valid = np.zeros((len(geometries), *polytope_sizes[:2]), bool)
    edges = np.zeros((len(geometries), polytope_sizes[2], 2, 3))
    edge_normals = np.zeros((len(geometries), polytope_sizes[2], 2, 3))
    for i, g in enumerate(geometries):
        if isinstance(g.shape, Convex):   # padded by repeating a first entry (no mask needed)
            m, f, t = len(g.shape.vertices), len(g.shape.planes), len(g.shape.triangles)
            vertices[i, :m], valid[i, :m] = g.shape.vertices, True
            vertices[i, m:] = g.shape.vertices[0]
            planes[i, :f], planes[i, f:] = g.shape.planes, g.shape.planes[0]
            triangles[i, :t], triangles[i, t:] = g.shape.triangles, g.shape.triangles[0]
            polygons[i], polygon_valid[i], edges[i], edge_normals[i] = g.shape.polytope_arrays(*polytope_sizes)
    value = lambda x, default: default if x is None else x  # noqa: E731
    rotation, translation = _poses_in_bodies(tree, geometries)
    return ContactModel(
        names=names, links=tuple(g.link for g in geometries), kinds=tuple(kinds), bodies=tuple(bodies),
        groups=tuple((ka, kb, tuple(a), tuple(b)) for (ka, kb), (a, b) in sorted(groups.items())),
        rotation=rotation, translation=translation,
        size=floats([shape_size(g.shape) for g in geometries]).reshape(-1, 3),
        vertices=floats(vertices), vertex_valid=jax.device_put(valid), planes=floats(planes),
        triangles=floats(triangles), polygons=floats(polygons), polygon_valid=jax.device_put(polygon_valid),
        edges=floats(edges), edge_normals=floats(edge_normals),
        stiffness=floats([value(g.material.point_contact_stiffness, DEFAULT_STIFFNESS) for g in geometries]),
        dissipation=floats([value(g.material.hunt_crossley_dissipation, DEFAULT_DISSIPATION) for g in geometries]),
        mu_static=floats([g.material.friction()[0] for g in geometries]),
        mu_dynamic=floats([g.material.friction()[1] for g in geometries]),
        stiction_tolerance=floats(stiction_tolerance))


MANY_EDGE_PAIRS = 1_000_000   # above this over all pairs of hulls, they are warned of at construction
# memory per edge pair in float64: Solo-12's own meshes (120 hull pairs, every hull padded to
# 1398 edges) asked XLA for one buffer of 38.4 GB, 164 bytes per edge pair
BYTES_PER_EDGE_PAIR = 164


def _check_hull_pairs(geometries, hull_pairs, source):
    """Two hulls touch through every pair of their edges (`geometry/_polytopes.py`), every hull
    padded to the most edges of any: warn once where the pairs that may touch test more than
    `MANY_EDGE_PAIRS` in all (the Panda's own meshes: 28 pairs of hulls of up to 152 vertices,
    5.7 million, 17 ms per evaluation of the narrow phase), and refuse a model whose pairs
    tested at once (one at a time past `CULLED_EDGE_PAIRS`, `_where_near`) would need more
    memory than this machine has, with the remedies."""
    if not hull_pairs:
        return
    detailed = max((g for g in geometries if isinstance(g.shape, Convex)), key=lambda g: len(g.shape.edges[0]))
    edges = len(detailed.shape.edges[0])
    per_pair, total = edges * edges, len(hull_pairs) * edges * edges
    if total <= MANY_EDGE_PAIRS:
        return
    need = (per_pair if per_pair > CULLED_EDGE_PAIRS else total) * BYTES_PER_EDGE_PAIR
    message = (f"{source + ': ' if source else ''}{len(hull_pairs)} pair(s) of hulls may touch, each testing {per_pair:,} "
               f"pairs of edges where near (every hull is padded to the {edges} edges of the most detailed, "
               f"{detailed.name!r}, of {len(detailed.shape.vertices)} vertices): up to {total:,} per evaluation, a "
               f"few milliseconds per million on a CPU core, {need / 1e9:.1f} GB at once in float64. Simplify the "
               "hulls (from_urdf(..., max_hull_vertices=64), Convex.from_points(..., max_vertices=64), or the meshes "
               "themselves), or exclude pairs that cannot touch (a collision filter group, without_collisions_between)")
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):   # no sysconf (Windows): warn only
        memory = float("inf")
    if need > memory:
        raise GeometryError(f"{message}; this machine has {memory / 1e9:.1f} GB")
    _warn_once(message)


@functools.lru_cache(maxsize=None)
def _warn_once(message):
    """A warning said once per process (the model is built again by `with_ground` and each
    `with_collision_geometry`), at the caller's line outside jaxdrake and equinox."""
    frame, level = sys._getframe(1), 2
    while frame is not None and any(f"{os.sep}{package}{os.sep}" in frame.f_code.co_filename
                                    for package in ("jaxdrake", "equinox")):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, stacklevel=level)


def _poses_in_bodies(tree, geometries):
    """Each geometry's pose in its body's frame: its pose in its link's frame composed with the
    link's frame in the body (a link merged into its parent by a fixed joint, a MuJoCo body
    whose joint axis does not pass through its origin, sits at a pose in its body)."""
    R_g = np.array([g.rotation for g in geometries], float).reshape(-1, 3, 3)
    p_g = np.array([g.translation for g in geometries], float).reshape(-1, 3)
    k = np.array([tree.frame_names.index(g.link) if g.link in tree.frame_names else -1 for g in geometries], int)
    if not np.any(k >= 0):
        return device_array(R_g), device_array(p_g)
    try:  # on the host ...
        R_f, p_f, xp = np.asarray(tree.frame_rotation), np.asarray(tree.frame_translation), np
    except jax.errors.TracerArrayConversionError:  # ... or traced, for a tree of traced leaves
        R_f, p_f, xp = tree.frame_rotation, tree.frame_translation, jnp
    R_f = xp.concatenate([R_f, xp.eye(3, dtype=R_f.dtype)[None]])  # index -1: 'world', the identity
    p_f = xp.concatenate([p_f, xp.zeros((1, 3), p_f.dtype)])
    R, p = R_f[k] @ R_g, xp.einsum("gij,gj->gi", R_f[k], p_g) + p_f[k]
    return (device_array(R), device_array(p)) if xp is np else (R, p)


def _body_has_mass(tree, body) -> bool:
    """Whether the body, or anything beyond it, moves mass or inertia (else H is singular there):
    the tree layout's subtree sums."""
    L = tree.layout
    moved = np.asarray(tree.mass) + np.trace(np.asarray(tree.inertia), axis1=1, axis2=2)
    return bool((L.subtree @ moved[L.order])[L.position[body]] > 0)
