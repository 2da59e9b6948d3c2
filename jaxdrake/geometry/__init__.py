"""Collision geometry (Drake's geometry/: shapes and their proximity queries) in JAX."""

from ._queries import SUPPORTED_PAIRS, penetration, point_distance
from ._shapes import Box, Capsule, Convex, Cylinder, GeometryError, HalfSpace, Sphere

__all__ = ["Box", "Capsule", "Convex", "Cylinder", "GeometryError", "HalfSpace", "SUPPORTED_PAIRS", "Sphere",
           "penetration", "point_distance"]
