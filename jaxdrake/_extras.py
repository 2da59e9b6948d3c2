"""The optional dependencies: which extra of pyproject.toml installs each, and the one error a
user meets where one is missing (`pip install jaxdrake` is the core; the rest are extras)."""

from __future__ import annotations

import importlib
import warnings

EXTRAS = {  # import name -> (what the user needs, the extra that installs it)
    "cyipopt": ("IPOPT", "solvers"),
    "clarabel": ("the Clarabel conic solver", "solvers"),
    "scs": ("the SCS conic solver", "solvers"),
    "lcm": ("LCM", "lcm"),
    "mujoco": ("MuJoCo (and MJX)", "mujoco"),
    "meshcat": ("meshcat and yourdfpy", "viz"),
    "trimesh": ("trimesh", "viz"),
    "imageio_ffmpeg": ("ffmpeg (the imageio-ffmpeg wheel)", "movies"),
    "cyclonedds": ("Cyclone DDS", "ros"),
    "rosbags": ("rosbags", "ros"),
}


class MissingExtraError(ImportError):
    """`user` needs an optional dependency that is not installed; `extra` names the extra of
    pyproject.toml that installs it."""

    def __init__(self, user: str, module: str):
        what, self.extra = EXTRAS[module]
        super().__init__(f"{user} needs {what}: pip install 'jaxdrake[{self.extra}]'", name=module)


def require(module: str, user: str):
    """`module` imported, or `MissingExtraError` naming the extra to install (the failed
    import kept as its cause: a broken install shows why)."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise MissingExtraError(user, module.split(".")[0]) from error


def require_mujoco(user: str):
    """mujoco (`require`), with MuJoCo's warnings sent to Python's `warnings` unless the user
    set a handler: MuJoCo's own handler writes MUJOCO_LOG.TXT into the working folder."""
    mujoco = require("mujoco", user)
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_mujoco_warning)
    return mujoco


def _mujoco_warning(message: str):
    warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)
