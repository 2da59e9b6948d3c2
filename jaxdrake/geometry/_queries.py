r"""Narrow-phase queries in JAX: signed distance to a point, and penetration as point pairs.

**Signed distance to a point** (Drake's `SignedDistanceToPoint`): for a point Q in a shape's
frame G, `point_distance(kind, Q, ...)` gives $\varphi(Q)$ (negative inside), a nearest
boundary point N and the unit gradient $\nabla\varphi$, with Drake's formulas: a sphere's
$|Q| - r$ (gradient $\hat x$ at the centre), a half-space's $Q_z$, a capsule's distance to
its segment minus r, a box's clamp (outside) or nearest face (inside, ties to the lowest
axis), a cylinder's box formula in (radial, axial) coordinates, a convex hull's
$\max_f (n_f \cdot Q - d_f)$ over its face planes inside it and the distance to its nearest
triangle outside (the planes alone underestimate it near edges and corners).

**Penetration** (Drake's `PenetrationAsPointPair`): any two shapes but two half-spaces give
candidate contacts, each a depth x (> 0 when they overlap), witness points
$C_a \in \partial A$, $C_b \in \partial B$ and the unit normal $\hat n_{BA}$ (from B into A),
all in the world:

- a sphere against any shape: one candidate, exactly Drake's
  (x = r - \varphi_B(A_o), $C_b$ = N, $C_a = A_o - r\,\nabla\varphi_B$);
- a capsule: its two end spheres against any shape but a capsule, and, against a box, hull
  or cylinder, the sphere about the point of its segment deepest into the other where that
  is deeper than both ends (lying across an edge; an end sphere within a radius of it is
  then left out; against a box or hull also their vertices inside it); the closest points
  of the two segments against a capsule;
- a box or a convex hull: each vertex inside the other shape (x = $-\varphi_B(v)$) against
  anything but a box or hull; between two of them, the separating-axis test and the clipped
  contact polygon (`_polytopes.py`): the corners of the overlap of two faces, weighted by
  their exterior angles (4 in all), or one point where an edge crosses an edge;
- a cylinder: four points of each rim, starting from the one deepest along the other
  shape's outward normal at the cylinder's centre (so that it stands on 4 points and lies on
  2); against a box or hull also their vertices inside it and, its round side lying across
  an edge, the sphere of its radius about the point of its axis deepest into the other
  (exact there); against a cylinder also the sphere of its radius about the point of its
  axis nearest the other's axis, where the round sides cross (exact there).

Where Drake has exact closed forms (anything with a sphere) the results equal Drake's; the
vertex, polygon and rim sets are the multi-point contact of MuJoCo and most engines, where
Drake's point contact keeps a single FCL point (which makes a box resting on a face
ill-posed). Every function is NaN-free and differentiable at a touch and at degenerate
points ("double where").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._polytopes import polytope_penetration
from ._vectors import TINY as _TINY, norm_and_direction

_X = jnp.array([1.0, 0.0, 0.0])
_Z = jnp.array([0.0, 0.0, 1.0])


def sphere_distance(radius, Q):
    direction = norm_and_direction(Q, _X.astype(Q.dtype))[1]
    N = radius * direction
    return jnp.dot(Q - N, direction), N, direction


def halfspace_distance(Q):
    return Q[2], Q.at[2].set(0.0), _Z.astype(Q.dtype)


def capsule_distance(radius, half_length, Q):
    centre = jnp.stack([0.0 * Q[0], 0.0 * Q[0], jnp.clip(Q[2], -half_length, half_length)])
    d, N, g = sphere_distance(radius, Q - centre)
    return d, N + centre, g


def _box_distance_nd(h, Q):
    """Drake's `ComputeDistanceToBox` for a box of half sizes h in any dimension."""
    clamped = jnp.clip(Q, -h, h)
    outside = jnp.any(jnp.abs(Q) > h)
    d_out, g_out = norm_and_direction(Q - clamped, jnp.zeros_like(Q).at[0].set(1.0))
    gap = h - jnp.abs(Q)
    axis = jnp.argmin(gap)
    sign = jnp.where(Q[axis] >= 0, 1.0, -1.0).astype(Q.dtype)
    one_hot = jnp.arange(Q.shape[0]) == axis
    N_in = jnp.where(one_hot, sign * h, Q)
    g_in = jnp.where(one_hot, sign, 0.0).astype(Q.dtype)
    N = jnp.where(outside, clamped, N_in)
    g = jnp.where(outside, g_out, g_in)
    d = jnp.where(outside, d_out, -gap[axis])
    return d, N, g


def box_distance(half_sizes, Q):
    return _box_distance_nd(half_sizes, Q)


def cylinder_distance(radius, half_length, Q):
    r, radial = norm_and_direction(Q[:2], _X[:2].astype(Q.dtype))
    d, N2, g2 = _box_distance_nd(jnp.stack([radius, half_length]), jnp.stack([r, Q[2]]))
    to_xyz = lambda rz: jnp.stack([rz[0] * radial[0], rz[0] * radial[1], rz[1]])  # noqa: E731
    return d, to_xyz(N2), to_xyz(g2)


def convex_distance(planes, triangles, Q):
    """Inside the hull, max over its face planes; outside, the distance to the nearest point of
    its `triangles` (t, 3, 3): a projection onto a triangle's plane that falls inside the
    triangle, or the nearest point of an edge. `triangles=None`: the planes' value outside
    too (a lower bound, where only the inside matters: a vertex's depth)."""
    values = planes[:, :3] @ Q - planes[:, 3]
    f = jnp.argmax(values)
    n = planes[f, :3]
    depth, N_in = values[f], Q - values[f] * n
    if triangles is None:
        return depth, N_in, n
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    normal = norm_and_direction(jnp.cross(b - a, c - a), n)[1]
    projected = Q - jnp.sum((Q - a) * normal, -1)[:, None] * normal
    within = jnp.all(jnp.stack([jnp.sum(jnp.cross(e1 - e0, projected - e0) * normal, -1) >= 0
                                for e0, e1 in ((a, b), (b, c), (c, a))]), 0)
    starts, ends = jnp.concatenate([a, b, c]), jnp.concatenate([b, c, a])
    along = ends - starts
    s = jnp.clip(jnp.sum((Q - starts) * along, -1) / jnp.maximum(jnp.sum(along * along, -1), _TINY), 0.0, 1.0)
    candidates = jnp.concatenate([projected, starts + s[:, None] * along])
    squared = jnp.where(jnp.concatenate([within, jnp.ones(len(starts), bool)]),
                        jnp.sum((Q - candidates) ** 2, -1), jnp.inf)
    N_out = candidates[jnp.argmin(squared)]
    d_out, g_out = norm_and_direction(Q - N_out, n)
    outside = depth > 0
    return jnp.where(outside, d_out, depth), jnp.where(outside, N_out, N_in), jnp.where(outside, g_out, n)


def point_distance(kind: str, params, Q):
    """(distance, nearest point N, unit gradient) of point Q (shape frame) to a shape of `kind`
    with parameters `params` (`shape_parameters(shape)` gives both)."""
    size = params["size"]
    if kind == "sphere":
        return sphere_distance(size[0], Q)
    if kind == "halfspace":
        return halfspace_distance(Q)
    if kind == "capsule":
        return capsule_distance(size[0], size[1], Q)
    if kind == "box":
        return box_distance(size, Q)
    if kind == "cylinder":
        return cylinder_distance(size[0], size[1], Q)
    if kind == "convex":
        return convex_distance(params["planes"], params.get("triangles"), Q)
    raise ValueError(f"no distance function for shape kind {kind!r}")


# ----- penetration as point pairs ---------------------------------------------------------------


def _points_against(kind_b, params_b, X_B, points_W, radii, valid):
    """Candidates for spheres (centres `points_W` (k, 3), `radii` (k,); radius 0: points)
    against shape B at pose X_B = (R, p): x = r - phi_B(c), C_b = N, C_a = c - r grad."""
    R_B, p_B = X_B

    def one(c, r):
        d, N, g = point_distance(kind_b, params_b, R_B.T @ (c - p_B))
        n = R_B @ g
        return r - d, c - r * n, R_B @ N + p_B, n

    depth, pa, pb, n = jax.vmap(one)(points_W, radii)
    return jnp.where(valid, depth, -jnp.inf), pa, pb, n, jnp.ones_like(depth)


def _swap(candidates):
    """Candidates of (B, A) as candidates of (A, B)."""
    depth, pa, pb, n, weight = candidates
    return depth, pb, pa, -n, weight


def _concat(*parts):
    return tuple(jnp.concatenate(arrays) for arrays in zip(*parts))


def _contact_points(kind, params, X):
    """A shape's own contact points in the world, their radii and validity: a sphere's centre,
    a capsule's segment ends, a box's or hull's vertices."""
    R, p = X
    size = params["size"]
    if kind == "sphere":
        return p[None], size[:1], jnp.ones(1, bool)
    if kind == "capsule":
        ends = jnp.stack([p + size[1] * R[:, 2], p - size[1] * R[:, 2]])
        return ends, jnp.full(2, size[0]), jnp.ones(2, bool)
    if kind == "box":
        signs = jnp.asarray(np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float),
                            R.dtype)
        return (signs * size) @ R.T + p, jnp.zeros(8, R.dtype), jnp.ones(8, bool)
    if kind == "convex":
        vertices = params["vertices"]
        return vertices @ R.T + p, jnp.zeros(vertices.shape[0], R.dtype), params["vertex_valid"]
    raise ValueError(kind)


def _vertices_against(kind_b, params_b, X_B, vertices, radii, valid):
    """Points of radius 0 against shape B: only a point inside B touches, so a hull's planes
    are enough (no nearest triangle)."""
    planes_only = {k: v for k, v in params_b.items() if k != "triangles"}
    return _points_against(kind_b, planes_only, X_B, vertices, radii, valid)


def _their_vertices(kind_a, params_a, X_A, kind_b, params_b, X_B):
    """B's vertices (a box's or hull's) inside A, as candidates of (A, B)."""
    return _swap(_vertices_against(kind_a, params_a, X_A, *_contact_points(kind_b, params_b, X_B)))


def _cylinder_rim(params, X_A, n):
    """A cylinder's rim points facing a shape whose outward normal there is n: on each cap, the
    point farthest along -n and three more at quarter turns, so that a cylinder standing on a
    cap rests on 4 points and one lying on its side on 2."""
    R_A, p_A = X_A
    radius, half = params["size"][0], params["size"][1]
    axis = R_A[:, 2]
    down = -(n - jnp.dot(n, axis) * axis)
    _, u = norm_and_direction(down, R_A[:, 0])
    w = jnp.cross(axis, u)
    directions = jnp.stack([u, w, -u, -w])
    caps = jnp.stack([p_A + half * axis, p_A - half * axis])
    return (caps[:, None, :] + radius * directions[None]).reshape(8, 3)


def _rim_against(params_a, X_A, kind_b, params_b, X_B):
    """Cylinder A's rim points (facing B's outward normal at A's centre) against B."""
    R_B, p_B = X_B
    n = R_B @ point_distance(kind_b, params_b, R_B.T @ (X_A[1] - p_B))[2]
    rim = _cylinder_rim(params_a, X_A, n)
    return _vertices_against(kind_b, params_b, X_B, rim, jnp.zeros(8, rim.dtype), jnp.ones(8, bool))


def _axis_sphere_against(params_a, X_A, params_b, X_B):
    """The sphere of cylinder A's radius about the point of its axis nearest to cylinder B's
    axis, against B: where the round sides cross. Only where that point lies at least a radius
    from A's flat ends (else the sphere would stick out of them)."""
    centre = _closest_point_on_segment_a(params_a, X_A, params_b, X_B)
    radius, half = params_a["size"][0], params_a["size"][1]
    inside = jnp.abs(jnp.dot(centre - X_A[1], X_A[0][:, 2])) < half - radius
    return _points_against("cylinder", params_b, X_B, centre[None], radius[None], inside[None])


_GOLDEN = float((np.sqrt(5.0) - 1.0) / 2.0)
_SEARCH_STEPS = 60   # the bracket shrinks to 0.618^60 ~ 3e-13 of the segment


def _golden_minimum(phi, lo, hi):
    """The minimizer of a convex phi on [lo, hi] by `_SEARCH_STEPS` golden-section steps, one
    evaluation a step (a loop traced once)."""
    def shrink(_, bracket):   # [lo, hi] with probes a < b inside it
        lo, hi, a, b, phi_a, phi_b = bracket
        left = phi_a < phi_b   # the minimum is in [lo, b]: a becomes the upper probe
        lo, hi = jnp.where(left, lo, a), jnp.where(left, b, hi)
        probe = jnp.where(left, hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo))
        phi_probe = phi(probe)
        return (lo, hi, jnp.where(left, probe, b), jnp.where(left, a, probe),
                jnp.where(left, phi_probe, phi_b), jnp.where(left, phi_a, phi_probe))

    a, b = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    lo, hi, *_ = jax.lax.fori_loop(0, _SEARCH_STEPS, shrink, (lo, hi, a, b, phi(a), phi(b)))
    return 0.5 * (lo + hi)


def _deepest_axis_point(params_a, X_A, kind_b, params_b, X_B):
    """(s, phi): where along the axis of capsule or cylinder A (s in [-half, half]) B's signed
    distance is least, by a golden-section search (B's signed distance is convex along a line;
    not differentiated: the depth is stationary there), and that distance as a function of s."""
    half = params_a["size"][1]
    (R_A, p_A), (R_B, p_B), held = jax.lax.stop_gradient((X_A, X_B, params_b))
    phi = lambda s: point_distance(kind_b, held, R_B.T @ (p_A + s * R_A[:, 2] - p_B))[0]  # noqa: E731
    return _golden_minimum(phi, *jax.lax.stop_gradient((-half, half))), phi


def _deeper_than_its_ends(s, phi, X_A, X_B, half, radius):
    """Whether the axis point s lies deeper into B than both axis ends (beyond rounding)."""
    p_A, p_B = X_A[1], X_B[1]
    rounding = 64 * jnp.finfo(p_A.dtype).eps * (1.0 + jnp.linalg.norm(p_A) + jnp.linalg.norm(p_B) + half + radius)
    return phi(s) < jnp.minimum(phi(-half), phi(half)) - rounding


def _capsule_against(params_a, X_A, kind_b, params_b, X_B):
    """A capsule's two end spheres against B; against a box, hull or cylinder also the sphere
    about the point of its segment deepest into B where that point is deeper than both ends
    (a capsule lying across an edge), and then an end sphere within a radius of it is left
    out (the same contact, counted once)."""
    ends, radii, _ = _contact_points("capsule", params_a, X_A)   # at s = +half, -half
    if kind_b not in ("box", "convex", "cylinder"):
        return _points_against(kind_b, params_b, X_B, ends, radii, jnp.ones(2, bool))
    radius, half = params_a["size"][0], params_a["size"][1]
    s, phi = _deepest_axis_point(params_a, X_A, kind_b, params_b, X_B)
    middle = _deeper_than_its_ends(s, phi, X_A, X_B, half, radius)
    near = jnp.abs(s - jnp.stack([half, -half])) < radius
    centre = X_A[1] + s * X_A[0][:, 2]
    return _concat(_points_against(kind_b, params_b, X_B, ends, radii, ~(middle & near)),
                   _points_against(kind_b, params_b, X_B, centre[None], radius[None], middle[None]))


def _cylinder_side_against(params_a, X_A, kind_b, params_b, X_B):
    """Cylinder A's round side across an edge of a box or hull B: the sphere of A's radius about
    the point of its axis deepest into B, where that is deeper than both axis ends and at least
    a radius from A's flat ends (else the sphere would stick out of them); exact where the side
    meets the edge."""
    radius, half = params_a["size"][0], params_a["size"][1]
    s, phi = _deepest_axis_point(params_a, X_A, kind_b, params_b, X_B)
    across = _deeper_than_its_ends(s, phi, X_A, X_B, half, radius) & (jnp.abs(s) < half - radius)
    centre = X_A[1] + s * X_A[0][:, 2]
    return _points_against(kind_b, params_b, X_B, centre[None], radius[None], across[None])


def penetration(kind_a: str, params_a, X_A, kind_b: str, params_b, X_B):
    """Candidate contacts (depth (k,), C_a (k, 3), C_b (k, 3), n_BA (k, 3), weight (k,)) between
    shape A at world pose X_A = (R, p) and shape B at X_B; a candidate touches where depth > 0,
    and its force is its weight times one point contact's (1 but at the corners of a contact
    polygon, `_polytopes._corner_weights`). Each shape as (kind, params), which
    `shape_parameters(shape)` gives. The pair must be in the order `canonical_order` gives
    (any two shapes but two half-spaces)."""
    if kind_a == "sphere":
        return _points_against(kind_b, params_b, X_B, *_contact_points(kind_a, params_a, X_A))
    if kind_a == "capsule" and kind_b != "capsule":
        own = _capsule_against(params_a, X_A, kind_b, params_b, X_B)
        if kind_b in ("box", "convex"):
            return _concat(own, _their_vertices(kind_a, params_a, X_A, kind_b, params_b, X_B))
        if kind_b == "cylinder":
            return _concat(own, _swap(_rim_against(params_b, X_B, "capsule", params_a, X_A)))
        return own
    if kind_a == "capsule" and kind_b == "capsule":
        c_a = _closest_point_on_segment_a(params_a, X_A, params_b, X_B)
        return _points_against("capsule", params_b, X_B, c_a[None], params_a["size"][:1], jnp.ones(1, bool))
    if kind_a == "cylinder":
        own = _rim_against(params_a, X_A, kind_b, params_b, X_B)
        if kind_b in ("box", "convex"):
            return _concat(own, _cylinder_side_against(params_a, X_A, kind_b, params_b, X_B),
                           _their_vertices(kind_a, params_a, X_A, kind_b, params_b, X_B))
        if kind_b == "cylinder":
            return _concat(own, _axis_sphere_against(params_a, X_A, params_b, X_B),
                           _swap(_rim_against(params_b, X_B, "cylinder", params_a, X_A)))
        return own
    if kind_a in ("box", "convex"):
        if kind_b in ("box", "convex"):
            return polytope_penetration(kind_a, params_a, X_A, kind_b, params_b, X_B)
        return _vertices_against(kind_b, params_b, X_B, *_contact_points(kind_a, params_a, X_A))
    raise ValueError(f"unsupported shape pair ({kind_a}, {kind_b})")


def _closest_point_on_segment_a(params_a, X_A, params_b, X_B):
    """The point of capsule A's segment closest to capsule B's segment (clamped parameters;
    parallel segments take the middle of their overlap); B's capsule distance does the rest."""
    (R_A, p_A), (R_B, p_B) = X_A, X_B
    ha, hb = params_a["size"][1], params_b["size"][1]
    da, db = R_A[:, 2], R_B[:, 2]
    r = p_A - p_B
    b = jnp.dot(da, db)
    c, f = jnp.dot(da, r), jnp.dot(db, r)
    denom = 1.0 - b * b
    parallel = denom < 1e-12
    safe = jnp.where(parallel, 1.0, denom)
    s = jnp.where(parallel, 0.0, (b * f - c) / safe)
    s = jnp.clip(s, -ha, ha)
    t = jnp.clip(b * s + f, -hb, hb)
    s = jnp.clip(b * t - c, -ha, ha)
    # parallel: the middle of the overlap of the projections onto A's axis
    lo = jnp.maximum(-ha, -jnp.abs(b) * hb - c)
    hi = jnp.minimum(ha, jnp.abs(b) * hb - c)
    s = jnp.where(parallel, jnp.clip(0.5 * (lo + hi), -ha, ha), s)
    return p_A + s * da


# ----- which pairs, in which order --------------------------------------------------------------

_RANK = {"sphere": 0, "capsule": 1, "cylinder": 2, "box": 3, "convex": 4, "halfspace": 5}


def canonical_order(kind_a: str, kind_b: str) -> bool:
    """Whether (a, b) is already in the order `penetration` takes (else swap them)."""
    return _RANK[kind_a] <= _RANK[kind_b]
