r"""Contact between two polytopes (boxes, convex hulls): the separating-axis test and a clipped
contact polygon, as most engines do it (MuJoCo's box-box, ODE, Bullet).

Along each candidate axis the two shapes' separation is measured: A's face normals (against
B's vertices), B's, and the cross products of an edge of A with an edge of B where the two
edges' normal arcs cross on the unit sphere (Gauss map: only those edge pairs make a face of
the Minkowski difference, so one O(1) product gives their separation). The largest separation
is the penetration's least depth.

- **A face axis** (the common case: resting, sliding, crossed planks): the face of the other
  shape most opposed to the reference face is clipped by the reference face's side planes
  (Sutherland-Hodgman, fixed-size arrays, one loop over the reference face's edges); the
  clipped polygon's corners below the reference face are candidates, at their depth below it,
  along its normal, each weighted by its share of the polygon's turning (exterior angles, 4 in
  all). So a box on a larger box rests on its 4 corners, two crossed planks on the corners of
  their overlap, and two equal boxes twisted by 45 degrees on the 8 corners of theirs, of
  weight 1/2 each, with no jump as the twist grows from 0.
- **An edge axis**, at most half as deep as every face axis (`_EDGE_MARGIN`), or the only
  touching feature: one candidate at the closest points of the two edges (an edge crossing
  an edge), along their common normal.

The edge pairs cost O(E_A E_B) products per evaluation (a box's 12 edges; a mesh's hull of a
few hundred vertices, about a thousand).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._shapes import BOX_CORNER_SIGNS, BOX_FACE_NORMALS, counter_clockwise, polygon_edges
from ._vectors import TINY as _TINY, norm_and_direction


# an edge axis is chosen over the best face only where its penetration is half as deep or
# less, and B's face over A's where 2% shallower. A face's separation counts the other's
# vertices beyond the face's own extent (its plane is infinite), so a plank resting across a
# ridge, turned 1e-5 rad along it, has its face 1.2x deeper than the edge crossing under its
# end; the face's clipped polygon then gives both ends (the edge, one). Gregorius ("Robust
# contact creation for physics simulations", GDC 2015) uses 0.90 and 0.98. Ties (a face on an
# edge, equal boxes stacked) choose the same feature however rounding turns the bodies.
_EDGE_MARGIN = 0.5
_FACE_MARGIN = 0.98


@functools.cache
def _box_tables():
    """A box's faces (6, 4) and edges (12, 2) as indices into `BOX_CORNER_SIGNS`, and the two
    faces meeting at each edge (12, 2)."""
    faces = tuple(counter_clockwise(BOX_CORNER_SIGNS, np.flatnonzero(BOX_CORNER_SIGNS @ n > 0), n)
                  for n in BOX_FACE_NORMALS)
    edges, edge_faces = polygon_edges(faces)
    return np.array(faces), edges, edge_faces


def _polytope(kind, params, X):
    """A box's or hull's vertices (v, 3) with validity, face normals (f, 3) and offsets (f,),
    face polygons (f, m, 3) with validity, edges (e, 2, 3) and their faces' normals (e, 2, 3),
    all in the world at pose X = (R, p)."""
    R, p = X
    if kind == "box":
        faces, edges, edge_faces = _box_tables()
        h = params["size"]
        signs, normals = (jnp.asarray(a, R.dtype) for a in (BOX_CORNER_SIGNS, BOX_FACE_NORMALS))
        local = (signs * h, jnp.ones(8, bool), normals, jnp.concatenate([h, h]), (signs * h)[faces],
                 jnp.ones(faces.shape, bool), (signs * h)[edges], normals[edge_faces])
    else:
        planes = params["planes"]
        local = (params["vertices"], params["vertex_valid"], planes[:, :3], planes[:, 3], params["polygons"],
                 params["polygon_valid"], params["edges"], params["edge_normals"])
    vertices, vertex_valid, normals, offsets, polygons, polygon_valid, edges, edge_normals = local
    to_world = lambda x: x @ R.T + p  # noqa: E731
    return (to_world(vertices), vertex_valid, normals @ R.T, offsets + normals @ R.T @ p, to_world(polygons),
            polygon_valid, to_world(edges), edge_normals @ R.T)


def _face_separations(normals, offsets, vertices, valid):
    """For each face plane of one shape, the largest distance by which the other's vertices all
    lie outside it: min over vertices of n . v - d."""
    values = vertices @ normals.T - offsets
    return jnp.min(jnp.where(valid[:, None], values, jnp.inf), axis=0)


def _edge_separations(edges_a, normals_a, centre_a, edges_b, normals_b):
    """The separation (ea, eb) along m = d_a x d_b (d: the edges' directions), oriented out of
    A, of every edge pair whose normal arcs cross (-inf elsewhere): the distance along m from
    A's edge to B's. Triple products as matrix products, (d_a x d_b) . x = d_a . (d_b x x)
    = d_b . (x x d_a), so no (ea, eb, 3) array is formed."""
    a1, a2 = normals_a[:, 0], normals_a[:, 1]
    c, d = -normals_b[:, 0], -normals_b[:, 1]   # the Minkowski difference A - B holds -B's normals
    ba, dc = jnp.cross(a2, a1), jnp.cross(d, c)
    cba, dba = (c @ ba.T).T, (d @ ba.T).T         # (ea, eb)
    adc, bdc = a1 @ dc.T, a2 @ dc.T
    crossing = (cba * dba < 0) & (adc * bdc < 0) & (cba * bdc > 0)
    start_a, start_b = edges_a[:, 0], edges_b[:, 0]
    along_a, along_b = edges_a[:, 1] - start_a, edges_b[:, 1] - start_b
    squared = jnp.sum(along_a ** 2, -1)[:, None] * jnp.sum(along_b ** 2, -1)[None] - (along_a @ along_b.T) ** 2
    # near-parallel pairs out: sin^2 of their angle above rounding (squared loses eps |a|^2 |b|^2)
    parallel = max(1e-12, 64 * float(jnp.finfo(squared.dtype).eps))
    crossing = crossing & (squared > parallel * jnp.sum(along_a ** 2, -1)[:, None] * jnp.sum(along_b ** 2, -1)[None])
    outward = jnp.sign(jnp.cross(start_a - centre_a, along_a) @ along_b.T)   # m . (a - centre) > 0
    gap = along_a @ jnp.cross(along_b, start_b).T - jnp.cross(start_a, along_a) @ along_b.T   # m . (b - a)
    return jnp.where(crossing, outward * gap / jnp.sqrt(jnp.where(crossing, squared, 1.0)), -jnp.inf)


def _edge_axis(edge_a, edge_b, centre_a):
    """The unit d_a x d_b of two edges, pointing out of A."""
    along_a = edge_a[1] - edge_a[0]
    n = norm_and_direction(jnp.cross(along_a, edge_b[1] - edge_b[0]), jnp.eye(3, dtype=along_a.dtype)[0])[1]
    return jnp.where(jnp.dot(n, edge_a[0] - centre_a) < 0, -n, n)


def _clip(polygon, valid, reference, reference_valid, normal, tolerance):
    """Sutherland-Hodgman: the convex `polygon` (m, 3) (its first `valid` corners) clipped by
    the side planes of the convex `reference` polygon (m, 3) (counter-clockwise about
    `normal`), as (2m, 3) points of which the first `count` are the result."""
    size = 2 * polygon.shape[0]
    points = jnp.zeros((size, 3), polygon.dtype).at[:polygon.shape[0]].set(polygon)
    count, corners = jnp.sum(valid), jnp.sum(reference_valid)
    index = jnp.arange(size)

    def by_side(k, state):
        points, count = state
        start, end = reference[k], reference[jnp.where(k + 1 < corners, k + 1, 0)]
        side = norm_and_direction(jnp.cross(end - start, normal), normal)[1]   # outward
        values = (points - start) @ side
        following = points[jnp.where(index + 1 < count, index + 1, 0)]
        values_next = (following - start) @ side
        present = index < count
        # a point within `tolerance` of the plane is on it: kept, and no crossing next to it (a
        # corner repeated)
        inside, beyond, beyond_next = values <= tolerance, values > tolerance, values_next > tolerance
        within, within_next = values < -tolerance, values_next < -tolerance
        keep, cut = present & inside, present & ((within & beyond_next) | (beyond & within_next))
        span = jnp.where(cut, values - values_next, 1.0)
        t = jnp.clip(jnp.where(cut, values / span, 0.0), 0.0, 1.0)
        crossing = points + t[:, None] * (following - points)
        at = jnp.cumsum(keep.astype(int) + cut) - keep - cut
        clipped = (jnp.zeros_like(points).at[jnp.where(keep, at, size)].set(points, mode="drop")
                   .at[jnp.where(cut, at + keep, size)].set(crossing, mode="drop"))
        used = k < corners
        return jnp.where(used, clipped, points), jnp.where(used, jnp.sum(keep) + jnp.sum(cut), count)

    points, count = jax.lax.fori_loop(0, reference.shape[0], by_side, (points, count))
    return points, index < count


def _corner_weights(points, in_polygon, normal):
    r"""Each corner's share of the clipped polygon's turning, scaled to 4 in all: $w_i = 4
    \theta_i / 2\pi$, $\theta_i$ its exterior angle (edges projected across the reference
    face's `normal`). A rectangle's corners weigh 1 each (a box on a face rests on 4 corners of
    weight 1, on an edge on 2); a square turned a little over an equal one clips to an octagon
    of 4 corners of about 1 and 4 nearly straight ones of about 0 (where their sides cross), and
    one turned by 45 degrees to 8 corners of 1/2. The exterior angles are a measure that moves
    continuously with the polygon, so the force does not jump where corners appear, merge or
    straighten (keeping 4 of the 8 corners made it jump with which 4: a twisted stack of boxes
    stalled). A degenerate edge takes its predecessor's direction, so a corner repeated by the
    clipping splits its angle with its twins."""
    count = jnp.sum(in_polygon)
    index = jnp.arange(points.shape[0])
    following = jnp.where(index + 1 < count, index + 1, 0)
    previous = jnp.where(index > 0, index - 1, jnp.maximum(count - 1, 0))
    edges = points[following] - points
    edges = edges - (edges @ normal)[:, None] * normal
    length, direction = norm_and_direction(edges, jnp.broadcast_to(jnp.eye(3, dtype=edges.dtype)[0], edges.shape))
    # a degenerate edge takes the direction of the last proper one before it (cyclically)
    proper = in_polygon & (length > 0)
    last = jax.lax.cummax(jnp.where(proper, index, -1))
    last = jnp.where(last < 0, jnp.max(jnp.where(proper, index, -1)), last)
    direction = jnp.where(proper[last][:, None], direction[jnp.maximum(last, 0)], 0.0)
    before = direction[previous]
    sine, cosine = jnp.cross(before, direction) @ normal, jnp.sum(before * direction, -1)
    defined = proper[jnp.maximum(last, 0)]   # no proper edge (one point): arctan2's derivative is NaN at 0
    turning = jnp.arctan2(jnp.where(defined, sine, 0.0), jnp.where(defined, cosine, 1.0))
    turning = jnp.where(in_polygon, turning, 0.0)
    total = jnp.sum(turning)   # +-2 pi (the clipped polygon runs either way about the normal)
    closed = jnp.abs(total) > np.pi
    shares = 4 * turning / jnp.where(closed, total, 1.0)
    return jnp.where(in_polygon, jnp.where(closed, shares, 4.0 / jnp.maximum(count, 1)), 0.0)


def _closest_points_of_segments(a0, a1, b0, b1):
    """The closest points of segments [a0, a1] and [b0, b1] (clamped parameters)."""
    da, db, r = a1 - a0, b1 - b0, a0 - b0
    aa, bb, ab = jnp.dot(da, da), jnp.dot(db, db), jnp.dot(da, db)
    ar, br = jnp.dot(da, r), jnp.dot(db, r)
    denom = aa * bb - ab * ab
    s = jnp.clip(jnp.where(denom > _TINY * aa * bb, (ab * br - bb * ar) / jnp.where(denom > _TINY * aa * bb, denom, 1.0),
                           0.5), 0.0, 1.0)
    t = jnp.clip((ab * s + br) / jnp.maximum(bb, _TINY), 0.0, 1.0)
    s = jnp.clip((ab * t - ar) / jnp.maximum(aa, _TINY), 0.0, 1.0)
    return a0 + s * da, b0 + t * db


def _pad_corners(polygons, valid, corners):
    extra = corners - polygons.shape[1]
    return (jnp.pad(polygons, ((0, 0), (0, extra), (0, 0))), jnp.pad(valid, ((0, 0), (0, extra))))


def polytope_penetration(kind_a, params_a, X_A, kind_b, params_b, X_B):
    """Candidate contacts (depth, C_a, C_b, n_BA, weight) between two polytopes (box or hull):
    the clipped contact polygon's touching corners, weighted by their shares of its turning
    (`_corner_weights`), and one more (weight 1) for an edge crossing an edge; those not in
    use have depth -inf."""
    Va, va, Na, da, Pa, pa_valid, Ea, ENa = _polytope(kind_a, params_a, X_A)
    Vb, vb, Nb, db, Pb, pb_valid, Eb, ENb = _polytope(kind_b, params_b, X_B)
    corners = max(Pa.shape[1], Pb.shape[1])
    (Pa, pa_valid), (Pb, pb_valid) = _pad_corners(Pa, pa_valid, corners), _pad_corners(Pb, pb_valid, corners)
    scale = 1.0 + jnp.max(jnp.where(va[:, None], jnp.abs(Va), 0.0)) + jnp.max(jnp.where(vb[:, None], jnp.abs(Vb), 0.0))
    tolerance = 64 * jnp.finfo(Va.dtype).eps * scale
    centre_a = jnp.sum(jnp.where(va[:, None], Va, 0.0), 0) / jnp.sum(va)
    # the axes are chosen on values held constant (trailing _), and the chosen ones'
    # separations recomputed (differentiated through one face or edge pair, not every one)
    Na_, da_, Va_, Nb_, db_, Vb_, Ea_, ENa_, Eb_, ENb_, centre_a_ = jax.lax.stop_gradient(
        (Na, da, Va, Nb, db, Vb, Ea, ENa, Eb, ENb, centre_a))
    fa = jnp.argmax(_face_separations(Na_, da_, Vb_, vb))
    fb = jnp.argmax(_face_separations(Nb_, db_, Va_, va))
    sep_e = _edge_separations(Ea_, ENa_, centre_a_, Eb_, ENb_)
    i = jnp.argmax(jnp.max(sep_e, 1))   # by rows: a flat argmax over all pairs is several times slower
    j = jnp.argmax(sep_e[i])
    sep_a = _face_separations(Na[fa, None], da[fa, None], Vb, vb)[0]
    sep_b = _face_separations(Nb[fb, None], db[fb, None], Va, va)[0]
    face_separation = jnp.maximum(sep_a, sep_b)
    axis = _edge_axis(Ea[i], Eb[j], centre_a)
    edge_separation = jnp.where(jnp.isfinite(sep_e[i, j]), jnp.dot(axis, Eb[j, 0] - Ea[i, 0]), -jnp.inf)
    # faces are preferred within a margin (`_EDGE_MARGIN`)
    edge_shallower = edge_separation > _EDGE_MARGIN * face_separation + tolerance
    least_depth = -jnp.maximum(face_separation, edge_separation)
    # the reference face (A's where A's face separates at least as much) and the incident face
    # of the other shape, the one most opposed to it
    a_refers = ~(sep_b > _FACE_MARGIN * sep_a + tolerance)   # A's face unless B's is clearly shallower
    normal = jnp.where(a_refers, Na[fa], Nb[fb])
    offset = jnp.where(a_refers, da[fa], db[fb])
    reference = jnp.where(a_refers, Pa[fa], Pb[fb])
    reference_valid = jnp.where(a_refers, pa_valid[fa], pb_valid[fb])
    incident_a, incident_b = jnp.argmin(Na @ normal), jnp.argmin(Nb @ normal)
    incident = jnp.where(a_refers, Pb[incident_b], Pa[incident_a])
    incident_valid = jnp.where(a_refers, pb_valid[incident_b], pa_valid[incident_a])
    points, in_polygon = _clip(incident, incident_valid, reference, reference_valid, normal, tolerance)
    weight = _corner_weights(points, in_polygon, normal)
    depth = offset - points @ normal
    depth = jnp.where(least_depth > 0, depth, jnp.minimum(depth, least_depth))   # apart along some axis: none touches
    kept = in_polygon & (depth > 0)
    # the edge also where the two overlap but no clipped point touches
    use_edge = jnp.isfinite(edge_separation) & (edge_shallower | (~jnp.any(kept) & (least_depth > 0)))
    on_reference = points + depth[:, None] * normal
    face_depth = jnp.where(kept & ~use_edge, depth, -jnp.inf)
    face_a = jnp.where(a_refers, on_reference.T, points.T).T
    face_b = jnp.where(a_refers, points.T, on_reference.T).T
    face_n = jnp.broadcast_to(jnp.where(a_refers, -normal, normal), points.shape)
    # an edge crossing an edge
    edge_a, edge_b = _closest_points_of_segments(Ea[i, 0], Ea[i, 1], Eb[j, 0], Eb[j, 1])
    edge_depth = jnp.where(use_edge, -edge_separation, -jnp.inf)
    return (jnp.concatenate([face_depth, edge_depth[None]]), jnp.concatenate([face_a, edge_a[None]]),
            jnp.concatenate([face_b, edge_b[None]]), jnp.concatenate([face_n, -axis[None]]),
            jnp.concatenate([weight, jnp.ones(1, weight.dtype)]))

