"""Collision geometry (Drake's geometry/: shapes and their proximity queries) in JAX."""

from ._queries import canonical_order, norm_and_direction, penetration, point_distance
from ._shapes import (BOX_FACE_NORMALS, Box, Capsule, Convex, Cylinder, GeometryError, HalfSpace, Sphere, shape_kind,
                      shape_parameters, shape_size)

__all__ = ["BOX_FACE_NORMALS", "Box", "Capsule", "Convex", "Cylinder", "GeometryError", "HalfSpace", "Sphere",
           "canonical_order", "norm_and_direction", "penetration", "point_distance", "shape_kind", "shape_parameters",
           "shape_size"]
