r"""Collision shapes (Drake's `geometry::Shape` family), each in its own frame G.

- `Sphere(radius)`: centred at G's origin.
- `Box(x, y, z)`: full side lengths along G's axes, centred at the origin.
- `Capsule(radius, length)`: a segment of `length` along G's z axis, centred, swept by a
  sphere of `radius` (URDF's `<capsule>` / Drake's `<drake:capsule>`).
- `Cylinder(radius, length)`: along G's z axis, centred (URDF's `<cylinder>`).
- `HalfSpace()`: the set $z \le 0$ of G (its boundary plane through the origin, outward
  normal $+z$), Drake's `HalfSpace`.
- `Convex(vertices)`: the convex hull of points (a `.obj` / `.stl` mesh reduced to its hull,
  as Drake's `Convex`), kept as its vertices and its faces' planes
  $n_f \cdot p \le d_f$; its faces as polygons and its edges follow from them.

Shapes are frozen host values (static structure); their sizes become pytree leaves of the
plant's contact model, so `jax.grad` with respect to a radius works.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib

import jax.numpy as jnp
import numpy as np

from .._extras import require


class GeometryError(ValueError):
    """A collision shape that cannot be used (named shape, element and remedy)."""


@dataclasses.dataclass(frozen=True)
class Sphere:
    """A sphere of `radius` about its frame's origin."""

    radius: float

    def __post_init__(self):
        _positive(self, "radius")


@dataclasses.dataclass(frozen=True)
class Box:
    """A box of full side lengths x, y, z along its frame's axes, centred."""

    x: float
    y: float
    z: float

    def __post_init__(self):
        for name in ("x", "y", "z"):
            _positive(self, name)

    @property
    def half_sizes(self):
        return np.array([self.x, self.y, self.z]) / 2

    def vertices(self):
        """The 8 corners, (8, 3)."""
        return BOX_CORNER_SIGNS * self.half_sizes


# a box's corners as signs of its half sizes, and its faces' outward normals (+x, +y, +z, -x,
# -y, -z; the face along normal i is n_i . p <= half size i mod 3)
BOX_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
BOX_FACE_NORMALS = np.vstack([np.eye(3), -np.eye(3)])


@dataclasses.dataclass(frozen=True)
class Capsule:
    """A segment of `length` along its frame's z axis, centred, swept by a sphere of `radius`
    (its total length is length + 2 radius)."""

    radius: float
    length: float

    def __post_init__(self):
        _positive(self, "radius")
        _positive(self, "length", allow_zero=True)


@dataclasses.dataclass(frozen=True)
class Cylinder:
    """A cylinder of `radius` and `length` along its frame's z axis, centred."""

    radius: float
    length: float

    def __post_init__(self):
        _positive(self, "radius")
        _positive(self, "length")


@dataclasses.dataclass(frozen=True)
class HalfSpace:
    """z <= 0 in its frame (outward normal +z)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Convex:
    r"""The convex hull of `points` (m, 3): `vertices` (the hull's, (v, 3)), `planes`
    (f, 4) rows $[n_f, d_f]$ with unit outward $n_f$, the hull being $n_f \cdot p \le d_f$,
    and `triangles` (t, 3, 3), its boundary (for distances outside it). `name` says where it
    came from (for messages)."""

    vertices: np.ndarray
    planes: np.ndarray
    triangles: np.ndarray
    name: str = "convex"

    @functools.cached_property
    def faces(self) -> tuple:
        """Each plane's face: the indices of the vertices on it, counter-clockwise about its
        outward normal."""
        return polygon_faces(self.vertices, self.planes, self.triangles)

    @functools.cached_property
    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """(e, 2) vertex indices of its edges, and (e, 2) the two faces meeting at each."""
        return polygon_edges(self.faces)

    def is_closed(self) -> bool:
        """Whether its faces close up: every edge shared by exactly two of them, and
        V - E + F = 2 (Euler's formula for a convex polyhedron)."""
        edges = len(self.edges[0])
        used = sum(len(face) for face in self.faces)
        return used == 2 * edges and len(self.vertices) - edges + len(self.faces) == 2

    @property
    def polytope_sizes(self) -> tuple[int, int, int]:
        """(faces, most corners of a face, edges)."""
        return len(self.faces), max(len(f) for f in self.faces), len(self.edges[0])

    def polytope_arrays(self, faces: int, corners: int, edges: int):
        """Its face polygons (faces, corners, 3) with their validity (faces, corners), and its
        edges (edges, 2, 3) with the outward normals of the two faces at each (edges, 2, 3),
        padded to the given counts by repeating the first face or edge (which changes no
        maximum) and by masked corners."""
        polygons = np.zeros((faces, corners, 3))
        valid = np.zeros((faces, corners), bool)
        for f, face in enumerate(self.faces):
            polygons[f, :len(face)], valid[f, :len(face)] = self.vertices[list(face)], True
        polygons[len(self.faces):], valid[len(self.faces):] = polygons[0], valid[0]
        index, edge_faces = self.edges
        ends, normals = np.zeros((edges, 2, 3)), np.zeros((edges, 2, 3))
        ends[:len(index)], normals[:len(index)] = self.vertices[index], self.planes[edge_faces, :3]
        ends[len(index):], normals[len(index):] = ends[0], normals[0]
        return polygons, valid, ends, normals

    @classmethod
    def from_points(cls, points, name: str = "convex", *, max_vertices: int | None = None) -> "Convex":
        """The convex hull of `points` (m, 3), m >= 4 spanning a volume (SciPy's Qhull); its
        coplanar triangles merged into one plane each. `max_vertices`: at most this many of the
        hull's vertices (at least 4; MuJoCo's `maxhullvert`), chosen greedily, each next the
        one farthest outside the hull of those chosen (`simplified_hull`): an inner
        approximation, for hulls too detailed to collide with each other at speed."""
        from scipy.spatial import ConvexHull, QhullError

        points = np.asarray(points, float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4 or not np.all(np.isfinite(points)):
            raise GeometryError(f"{name}: a convex shape needs at least 4 finite 3-D points, got "
                                f"an array of shape {points.shape}")
        if max_vertices is not None and (int(max_vertices) != max_vertices or max_vertices < 4):
            raise GeometryError(f"{name}: max_vertices must be an integer of at least 4 (a hull spanning a "
                                f"volume), got {max_vertices!r}")
        try:
            hull = ConvexHull(points)
            if max_vertices is not None and len(hull.vertices) > max_vertices:
                points = simplified_hull(points[hull.vertices], int(max_vertices))
                hull = ConvexHull(points)
        except QhullError:
            raise GeometryError(f"{name}: the points are flat (they span no volume), so they have no "
                                "convex hull to collide with; use a Box of small thickness instead") from None
        equations = np.column_stack([hull.equations[:, :3], -hull.equations[:, 3]])
        # Qhull's triangles merged into faces within the loosest tolerance whose faces close up:
        # a mesh file's rounding (float32 in an STL) tilts a flat face's triangles by up to
        # ~1e-7, and merging some of them but not others gave overlapping faces; at 0, Qhull's
        # own facets, each exactly one plane
        for tol in _MERGE_TOLERANCES:
            shape = cls(points[hull.vertices], _merge_coplanar(equations, tol), points[hull.simplices], name)
            if shape.is_closed():
                return shape
        return shape

    @classmethod
    def from_mesh_file(cls, path, scale=(1.0, 1.0, 1.0), *, require_convex: bool = True,
                       max_vertices: int | None = None) -> "Convex":
        """A `.obj` / `.stl` (or any format trimesh reads) scaled by `scale`, reduced to its hull
        (of at most `max_vertices` vertices: `from_points`). `require_convex`: refuse a mesh
        that is far from its hull (its volume below 90% of the hull's), since contact would
        then act where the surface is not."""
        trimesh = require("trimesh", "a mesh collision shape")
        path = pathlib.Path(path)
        try:
            mesh = trimesh.load(path, force="mesh", process=True)
        except Exception as error:  # trimesh raises many kinds for unreadable files
            raise GeometryError(f"cannot read the collision mesh {path}: {error}") from None
        if not hasattr(mesh, "vertices") or len(mesh.vertices) < 4:
            raise GeometryError(f"{path}: the collision mesh has no volume (fewer than 4 vertices)")
        points = np.asarray(mesh.vertices, float) * np.asarray(scale, float)
        shape = cls.from_points(points, name=path.name, max_vertices=max_vertices)
        if require_convex and mesh.is_watertight:
            hull_volume = _hull_volume(points)   # the full hull's
            if abs(mesh.volume * np.prod(scale)) < 0.9 * hull_volume:
                raise GeometryError(
                    f"{path}: the collision mesh is not convex (its volume is "
                    f"{abs(mesh.volume * np.prod(scale)) / hull_volume:.0%} of its convex hull's); point contact would "
                    "act on the hull, not the surface. Split it into convex pieces (one <collision> "
                    "each), or collide with its hull: from_urdf(..., mesh_hulls=True), or "
                    "Convex.from_mesh_file(..., require_convex=False) for a shape of your own")
        return shape


def simplified_hull(vertices, count: int) -> np.ndarray:
    """`count` of a convex hull's `vertices` (v, 3): quickhull's first tetrahedron (the two
    farthest apart along an axis, the one farthest from their line, the one farthest from
    the plane of the three), then one at a time the vertex farthest outside the hull of those
    chosen, which bounds how far the simplified hull lies inside the full one (Solo-12's leg
    and hip meshes, 273-486 hull vertices: 0.65-0.92 mm at 64 vertices, 1.6-1.9 mm at 32; its
    base 2.1 and 4.3 mm; Qhull's own early stop, its `TA` option, leaves 5-8 mm at 64)."""
    from scipy.spatial import ConvexHull

    axis = int(np.argmax(np.ptp(vertices, axis=0)))
    a, b = int(np.argmin(vertices[:, axis])), int(np.argmax(vertices[:, axis]))
    along = (vertices[b] - vertices[a]) / np.linalg.norm(vertices[b] - vertices[a])
    offsets = vertices - vertices[a]
    c = int(np.argmax(np.linalg.norm(offsets - np.outer(offsets @ along, along), axis=1)))
    normal = np.cross(along, vertices[c] - vertices[a])
    d = int(np.argmax(np.abs(offsets @ normal)))
    chosen = [a, b, c, d]
    while len(chosen) < count:
        planes = ConvexHull(vertices[chosen]).equations
        outside = np.max(vertices @ planes[:, :3].T + planes[:, 3], axis=1)
        farthest = int(np.argmax(outside))
        if outside[farthest] <= 0:
            break
        chosen.append(farthest)
    return vertices[chosen]


def polygon_faces(vertices, planes, triangles) -> tuple:
    """For each plane row [n, d] of a convex polytope, the indices of its `vertices` on that
    face, ordered counter-clockwise about n (the face is convex: by angle about its centre).
    A face's corners are those of the boundary `triangles` (t, 3, 3) that lie in its plane
    (each triangle goes to the plane nearest its own)."""
    from scipy.spatial import cKDTree

    # each triangle's own outward plane [n, d], matched to the nearest of `planes`
    n = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= np.sign(np.sum(n * (triangles[:, 0] - vertices.mean(0)), 1))[:, None]
    plane_of = cKDTree(planes).query(np.column_stack([n, np.sum(n * triangles[:, 0], 1)]))[1]
    where = {tuple(v): i for i, v in enumerate(vertices)}   # a triangle's corners are hull vertices
    index = np.array([[where[tuple(p)] for p in triangle] for triangle in triangles], int).reshape(-1, 3)
    return tuple(counter_clockwise(vertices, np.unique(index[plane_of == f]), normal)
                 for f, normal in enumerate(planes[:, :3]))


def counter_clockwise(vertices, on, n) -> tuple:
    """The indices `on` of a convex face's corners among `vertices`, ordered counter-clockwise
    about its normal n (by angle about their centre)."""
    offsets = vertices[on] - vertices[on].mean(0)
    u = np.cross(n, np.eye(3)[np.argmin(np.abs(n))])
    u /= np.linalg.norm(u)
    return tuple(int(i) for i in np.asarray(on)[np.argsort(np.arctan2(offsets @ np.cross(n, u), offsets @ u))])


def polygon_edges(faces) -> tuple[np.ndarray, np.ndarray]:
    """The edges of a closed polytope given as counter-clockwise `faces`: (e, 2) vertex indices
    and (e, 2) indices of the two faces that meet there (each edge once)."""
    seen = {}
    for f, face in enumerate(faces):
        for a, b in zip(face, face[1:] + face[:1]):
            seen.setdefault(frozenset((a, b)), []).append((f, (a, b)))
    shared = [uses for uses in seen.values() if len(uses) == 2]
    return (np.array([uses[0][1] for uses in shared], int).reshape(-1, 2),
            np.array([[uses[0][0], uses[1][0]] for uses in shared], int).reshape(-1, 2))


def _hull_volume(points) -> float:
    from scipy.spatial import ConvexHull
    return float(ConvexHull(points).volume)


_MERGE_TOLERANCES = (1e-5, 1e-7, 1e-9, 0.0)   # relative, loosest first


def _merge_coplanar(planes, tol):
    """Qhull triangulates faces: keep one row per distinct plane (the first of each)."""
    from scipy.spatial import cKDTree

    scale = tol * np.maximum(1.0, np.abs(planes[:, 3]))
    # the first row within `scale` of each row (a tree: an all-pairs table is quadratic in rows)
    first = np.array([min(near) for near in cKDTree(planes).query_ball_point(planes, scale, p=np.inf)])
    return planes[first == np.arange(len(planes))]


def _positive(shape, name, allow_zero=False):
    value = getattr(shape, name)
    ok = np.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        raise GeometryError(f"{type(shape).__name__}: {name} must be a {'non-negative' if allow_zero else 'positive'} "
                            f"finite length in metres, got {value}")


_KINDS = {Sphere: "sphere", Box: "box", Capsule: "capsule", Cylinder: "cylinder", HalfSpace: "halfspace",
          Convex: "convex"}


def shape_kind(shape) -> str:
    """The query name of a shape's kind: "sphere", "box", "capsule", "cylinder", "halfspace",
    "convex"."""
    try:
        return _KINDS[type(shape)]
    except KeyError:
        raise GeometryError(f"unsupported collision shape {shape!r}; use one of "
                            f"{', '.join(t.__name__ for t in _KINDS)}") from None


def shape_size(shape) -> list:
    """A shape's `size` parameter (3 numbers): a sphere's [r, 0, 0], a box's half sizes, a
    capsule's or cylinder's [r, length / 2, 0]; zeros for a half-space or hull (whose
    parameters are arrays)."""
    if isinstance(shape, Sphere):
        return [shape.radius, 0.0, 0.0]
    if isinstance(shape, Box):
        return list(shape.half_sizes)
    if isinstance(shape, (Capsule, Cylinder)):
        return [shape.radius, shape.length / 2, 0.0]
    return [0.0, 0.0, 0.0]


def shape_parameters(shape) -> tuple[str, dict]:
    """(kind, params) of a shape, as `penetration` and `point_distance` take them: params is
    {"size": ...} (`shape_size`), and for a `Convex` hull also its arrays in its frame:
    `vertices` with `vertex_valid`, `planes`, `triangles`, face `polygons` with
    `polygon_valid`, `edges` with their faces' `edge_normals`. E.g.
    `penetration(*shape_parameters(Sphere(0.1)), (R_a, p_a), *shape_parameters(Box(1, 1, 1)), (R_b, p_b))`
    (the kinds in `canonical_order`)."""
    kind = shape_kind(shape)
    params = {"size": jnp.asarray(shape_size(shape), float)}
    if isinstance(shape, Convex):
        polygons, polygon_valid, edges, edge_normals = shape.polytope_arrays(*shape.polytope_sizes)
        params.update(vertices=jnp.asarray(shape.vertices), vertex_valid=jnp.ones(len(shape.vertices), bool),
                      planes=jnp.asarray(shape.planes), triangles=jnp.asarray(shape.triangles),
                      polygons=jnp.asarray(polygons), polygon_valid=jnp.asarray(polygon_valid),
                      edges=jnp.asarray(edges), edge_normals=jnp.asarray(edge_normals))
    return kind, params
