"""MuJoCo models as jaxdrake systems (the notes' D.3.3: existing models as blocks): `MujocoSystem`
(stepped by MJX), the loader that imports MuJoCo and MJX quietly (`import_mujoco`), the
offscreen renderer (`mujoco_renderer`) and MuJoCo's derived constants recomputed in JAX
(`set_const`). Needs the `mujoco` extra (`pip install 'jaxdrake[mujoco]'`)."""

from ._system import DERIVED_CONSTANTS, MujocoSystem, import_mujoco, mujoco_renderer, set_const

__all__ = ["DERIVED_CONSTANTS", "MujocoSystem", "import_mujoco", "mujoco_renderer", "set_const"]
