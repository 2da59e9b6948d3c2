r"""Narrow-phase queries in JAX: signed distance to a point, and penetration as point pairs.

**Signed distance to a point** (Drake's `SignedDistanceToPoint`): for a point Q in a shape's
frame G, `point_distance(kind, Q, ...)` gives $\varphi(Q)$ (negative inside), a nearest
boundary point N and the unit gradient $\nabla\varphi$, with Drake's formulas: a sphere's
$|Q| - r$ (gradient $\hat x$ at the centre), a half-space's $Q_z$, a capsule's distance to
its segment minus r, a box's clamp (outside) or nearest face (inside, ties to the lowest
axis), a cylinder's box formula in (radial, axial) coordinates. A convex hull's is
$\max_f (n_f \cdot Q - d_f)$, exact inside the hull (where it is used: the depth of a
vertex), a lower bound outside it.

**Penetration** (Drake's `PenetrationAsPointPair`): a pair of shapes A, B gives candidate
contacts, each a depth x (> 0 when they overlap), witness points $C_a \in \partial A$,
$C_b \in \partial B$ and the unit normal $\hat n_{BA}$ (from B into A), all in the world:

- a sphere against any of sphere, half-space, box, capsule, cylinder: one candidate, exactly
  Drake's (x = r - \varphi_B(A_o), $C_b$ = N, $C_a = A_o - r\,\nabla\varphi_B$);
- a capsule: its two end spheres against a half-space or a box, the closest points of the
  two segments against another capsule;
- a box or a convex hull: each vertex inside the other shape (x = $-\varphi_B(v)$), and,
  against another box or hull, the other's vertices inside it too;
- a cylinder against a half-space: four points of each rim, starting from the deepest one.

Where Drake has exact closed forms (anything with a sphere) the results equal Drake's; the
vertex sets are the multi-point contact of MuJoCo and most engines, where Drake's point
contact keeps a single FCL point (which makes a box resting on a face ill-posed); an edge
crossing an edge (box on box, capsule across a box's edge) is not detected. Every function
is NaN-free and differentiable at a touch and at degenerate points ("double where").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_TINY = 1e-14


def norm_and_direction(v, fallback):
    """(|v|, v / |v|) with `fallback` (a unit vector) as the direction where |v| is ~0,
    differentiable everywhere."""
    sq = jnp.sum(v * v, -1)
    nonzero = sq > _TINY * _TINY
    safe = jnp.where(nonzero[..., None], v, fallback)
    norm = jnp.sqrt(jnp.sum(safe * safe, -1))
    return jnp.where(nonzero, norm, 0.0), safe / norm[..., None]


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


def convex_distance(planes, Q):
    """max over the face planes (exact inside the hull)."""
    values = planes[:, :3] @ Q - planes[:, 3]
    f = jnp.argmax(values)
    n = planes[f, :3]
    return values[f], Q - values[f] * n, n


def point_distance(kind: str, params, Q):
    """(distance, nearest point N, unit gradient) of point Q (shape frame) to a shape of `kind`
    with parameters `params` (see `ShapeParameters`)."""
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
        return convex_distance(params["planes"], Q)
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
    return jnp.where(valid, depth, -jnp.inf), pa, pb, n


def _swap(candidates):
    """Candidates of (B, A) as candidates of (A, B)."""
    depth, pa, pb, n = candidates
    return depth, pb, pa, -n


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


def _cylinder_rim_against_halfspace(params, X_A, X_B):
    """A cylinder's rim points: on each cap, the deepest point into the half-space (normal
    n) and three more at quarter turns, so that a cylinder standing on a cap rests on 4 points."""
    R_A, p_A = X_A
    radius, half = params["size"][0], params["size"][1]
    axis, n = R_A[:, 2], X_B[0][:, 2]
    down = -(n - jnp.dot(n, axis) * axis)
    _, u = norm_and_direction(down, R_A[:, 0])
    w = jnp.cross(axis, u)
    directions = jnp.stack([u, w, -u, -w])
    caps = jnp.stack([p_A + half * axis, p_A - half * axis])
    points = (caps[:, None, :] + radius * directions[None]).reshape(8, 3)
    return points


def penetration(kind_a: str, params_a, X_A, kind_b: str, params_b, X_B):
    """Candidate contacts (depth (k,), C_a (k, 3), C_b (k, 3), n_BA (k, 3)) between shape A at
    world pose X_A = (R, p) and shape B at X_B; a candidate touches where depth > 0. The pair
    must be `supported(kind_a, kind_b)` in this order (`canonical_order` gives it)."""
    if kind_a == "sphere" or (kind_a == "capsule" and kind_b in ("halfspace", "box")):
        points, radii, valid = _contact_points(kind_a, params_a, X_A)
        own = _points_against(kind_b, params_b, X_B, points, radii, valid)
        if kind_a == "capsule" and kind_b == "box":
            corners = _contact_points("box", params_b, X_B)
            return _concat(own, _swap(_points_against("capsule", params_a, X_A, *corners)))
        return own
    if kind_a == "capsule" and kind_b == "capsule":
        c_a = _closest_point_on_segment_a(params_a, X_A, params_b, X_B)
        return _points_against("capsule", params_b, X_B, c_a[None], params_a["size"][:1], jnp.ones(1, bool))
    if kind_a in ("box", "convex"):
        own = _points_against(kind_b, params_b, X_B, *_contact_points(kind_a, params_a, X_A))
        if kind_b in ("box", "convex"):
            theirs = _points_against(kind_a, params_a, X_A, *_contact_points(kind_b, params_b, X_B))
            return _concat(own, _swap(theirs))
        return own
    if kind_a == "cylinder" and kind_b == "halfspace":
        points = _cylinder_rim_against_halfspace(params_a, X_A, X_B)
        return _points_against("halfspace", params_b, X_B, points, jnp.zeros(8, points.dtype), jnp.ones(8, bool))
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
_SUPPORTED = {("sphere", k) for k in ("sphere", "capsule", "cylinder", "box", "halfspace")} | {
    ("capsule", "capsule"), ("capsule", "box"), ("capsule", "halfspace"), ("cylinder", "halfspace"),
    ("box", "box"), ("box", "convex"), ("box", "halfspace"), ("convex", "convex"), ("convex", "halfspace")}


def canonical_order(kind_a: str, kind_b: str) -> bool:
    """Whether (a, b) is already in the order `penetration` takes (else swap them)."""
    return _RANK[kind_a] <= _RANK[kind_b]


def supported(kind_a: str, kind_b: str) -> bool:
    a, b = (kind_a, kind_b) if canonical_order(kind_a, kind_b) else (kind_b, kind_a)
    return (a, b) in _SUPPORTED


SUPPORTED_PAIRS = tuple(sorted(_SUPPORTED, key=lambda p: (_RANK[p[0]], _RANK[p[1]])))
