"""Planning: dynamic programming on meshes and grids (ch. 9) and random trees (ch. 15)."""

from ._rrt import RRTResult, kinodynamic_rrt, rrt
from ._value_iteration import (GRID_ACTIONS, BarycentricMesh, GridWorldResult, MeshPolicy,
                               ValueIterationResult, fitted_value_iteration, grid_world)

__all__ = ["GRID_ACTIONS", "BarycentricMesh", "GridWorldResult", "MeshPolicy", "RRTResult", "ValueIterationResult",
           "fitted_value_iteration", "grid_world", "kinodynamic_rrt", "rrt"]
