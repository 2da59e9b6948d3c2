"""Collision geometry (Drake's geometry/: shapes and their proximity queries) in JAX."""

from ._queries import SUPPORTED_PAIRS, canonical_order, norm_and_direction, penetration, point_distance, supported
from ._shapes import Box, Capsule, Convex, Cylinder, GeometryError, HalfSpace, Sphere

__all__ = ["Box", "Capsule", "Convex", "Cylinder", "GeometryError", "HalfSpace", "SUPPORTED_PAIRS", "Sphere",
           "canonical_order", "norm_and_direction", "penetration", "point_distance", "supported"]
