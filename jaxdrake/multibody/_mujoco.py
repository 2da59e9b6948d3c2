r"""MuJoCo models as systems (the notes' D.3.3: existing models as blocks), stepped by MJX.

A `MujocoSystem` is a discrete-time system of period `opt.timestep`:
$x_{k+1} = \mathrm{mjx.step}(x_k, u_k)$ with state $x = [q_{pos}; q_{vel}; a]$ (positions,
velocities, actuator activations) and input the controls (`ctrl`, saturated to `ctrlrange`
where the model limits them). Every other quantity MJX needs is rebuilt from the model each
step. The constraint solver's warm start (the previous step's accelerations) is state only
with `warm_start=True` (x gains nv entries; then steps are identical to MJX's and C MuJoCo's
own loops); by default each step's solve starts from zero (C MuJoCo's `mjDSBL_WARMSTART`),
which changes nothing without constraints and, with a converged solver, little with them,
but matters with one solver iteration (MuJoCo Playground's setting). The model's arrays (masses, damping,
gains, geometry sizes, ...) are pytree leaves: `vmap` over them does not recompile and `grad`
reaches them. Gradients through contacts: `jax.grad` needs a one-iteration solver
(`<option iterations="1" ls_iterations="4"/>`, MuJoCo Playground's setting); with more
iterations MJX's solver is a `while_loop`, which reverse mode cannot differentiate (JAX's error
then names `while_loop`): use `simulate(..., autodiff="forward")` with `jax.jacfwd`. Needs `pip install mujoco==3.17.0 mujoco-mjx==3.17.0` (the `mujoco` extra).
"""

from __future__ import annotations

import os
import pathlib
import sys
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..systems import Frame, System

_POSITIONS = {0: ("x", "y", "z", "qw", "qx", "qy", "qz"), 1: ("qw", "qx", "qy", "qz"), 2: ("",), 3: ("",)}
_VELOCITIES = {0: ("vx", "vy", "vz", "wx", "wy", "wz"), 1: ("wx", "wy", "wz"), 2: ("dot",), 3: ("dot",)}


# MuJoCo renders offscreen without a display through EGL (where libEGL is missing, mujoco's
# import skips its GL context and only rendering is unavailable)
if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and "mujoco" not in sys.modules:
    os.environ.setdefault("MUJOCO_GL", "egl")


def renderer(model, height: int, width: int):
    """`mujoco.Renderer(model, height, width)`. Where mujoco was imported before jaxdrake on a
    Linux machine without a display, it chose GLFW, which cannot open a context there: its
    offscreen context is switched to EGL first (GLFW is never tried: a failed GLFW start can
    abort the process)."""
    mujoco, _ = _mujoco()
    try:
        if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
            from mujoco.rendering.classic import gl_context

            if getattr(gl_context.GLContext, "__module__", "").startswith("mujoco.glfw"):
                import mujoco.egl

                gl_context.GLContext = mujoco.egl.GLContext  # the module attribute the renderer reads
        return mujoco.Renderer(model, height, width)
    except Exception as error:  # noqa: BLE001 -- any GL start-up failure: name the remedy
        raise RuntimeError(f"MuJoCo's renderer did not start ({error}). Without a display, set MUJOCO_GL=egl "
                           "(or osmesa) before mujoco is first imported; EGL needs libEGL (Mesa's works on "
                           "CPU-only machines)") from error


def _mujoco():
    try:
        import mujoco
        from mujoco import mjx
    except ImportError:
        raise ImportError("MujocoSystem needs MuJoCo and MJX: pip install mujoco==3.17.0 mujoco-mjx==3.17.0 "
                          "(or pip install 'jaxdrake[mujoco]')") from None
    return mujoco, mjx


class MujocoSystem(System):
    """A MuJoCo model as a discrete-time jaxdrake system, stepped by MJX (see the module doc).

    **Construction:** `MujocoSystem.from_xml(text_or_path, assets=None)` (MJCF, or a URDF that
    MuJoCo imports) or `MujocoSystem(mj_model)` for a `mujoco.MjModel`. `output="state"`
    (default) or `"sensors"` (`sensordata`, named by the model's sensors); `warm_start=True`
    carries the solver's warm start in the state (see the module doc).

    `mj_model` keeps the C model (for C MuJoCo, rendering); `model` is the `mjx.Model`.
    """

    model: Any
    mj_model: Any = eqx.field(static=True)
    sizes: tuple = eqx.field(static=True)  # (nq, nv, na)
    sensors: bool = eqx.field(static=True)
    warm_start: bool = eqx.field(static=True)

    def __init__(self, mj_model, *, output: str = "state", warm_start: bool = False):
        mujoco, mjx = _mujoco()
        if not isinstance(mj_model, mujoco.MjModel):
            raise TypeError(f"MujocoSystem needs a mujoco.MjModel (or use MujocoSystem.from_xml), "
                            f"got {type(mj_model).__name__}")
        if output not in ("state", "sensors"):
            raise ValueError(f"output must be 'state' or 'sensors', got {output!r}")
        if output == "sensors" and mj_model.nsensordata == 0:
            raise ValueError("output='sensors', but the model declares no <sensor>")
        self.mj_model, self.model = mj_model, mjx.put_model(mj_model)
        self.sizes = (mj_model.nq, mj_model.nv, mj_model.na)
        self.sensors = output == "sensors"
        self.warm_start = bool(warm_start)
        name = "".join(c for c in mj_model.names[: mj_model.names.find(b"\0")].decode().title() if c.isalnum())
        name = name or "MujocoModel"
        names = _state_names(mujoco, mj_model)
        if self.warm_start:
            names += tuple(f"{v}_warmstart" for v in names[mj_model.nq: mj_model.nq + mj_model.nv])
        state = Frame(f"{name}State", names)
        inputs = Frame(f"{name}Input", tuple(_name(mujoco, mj_model, mujoco.mjtObj.mjOBJ_ACTUATOR, i, "u")
                                             for i in range(mj_model.nu)))
        limited = np.asarray(mj_model.actuator_ctrllimited, bool)
        ranges = np.asarray(mj_model.actuator_ctrlrange, float).reshape(-1, 2)
        limits = None
        if limited.any():
            limits = (np.where(limited, ranges[:, 0], -np.inf), np.where(limited, ranges[:, 1], np.inf))
        outputs = state
        if self.sensors:
            outputs = Frame(f"{name}Sensors", _sensor_names(mujoco, mj_model))
        super().__init__(num_discrete_states=sum(self.sizes) + self.warm_start * mj_model.nv, num_inputs=mj_model.nu,
                         num_outputs=len(outputs.coordinates), sample_time=float(mj_model.opt.timestep),
                         time_invariant=True, input_limits=limits, state_frame=state,
                         input_frame=inputs, output_frame=outputs)

    @classmethod
    def from_xml(cls, text_or_path, assets=None, *, output: str = "state", warm_start: bool = False) -> "MujocoSystem":
        """From MJCF text or a file path (an `.xml` MJCF or a `.urdf`); `assets`: {file name: bytes}."""
        mujoco, _ = _mujoco()
        text = str(text_or_path)
        if text.lstrip().startswith("<"):
            model = mujoco.MjModel.from_xml_string(text, assets or {})
        else:
            path = pathlib.Path(text)
            if not path.exists():
                raise FileNotFoundError(f"no MuJoCo model file {path}")
            model = mujoco.MjModel.from_xml_path(str(path), assets or {})
        return cls(model, output=output, warm_start=warm_start)

    def _data(self, t, x, u):
        _, mjx = _mujoco()
        nq, nv, na = self.sizes
        data = mjx.make_data(self.model)
        data = data.replace(time=jnp.asarray(t, x.dtype), qpos=x[:nq], qvel=x[nq: nq + nv],
                            act=x[nq + nv: nq + nv + na], ctrl=u.astype(x.dtype))
        return data.replace(qacc_warmstart=x[nq + nv + na:]) if self.warm_start else data

    def update(self, t, x, u):
        _, mjx = _mujoco()
        data = mjx.step(self.model, self._data(t, x, u))
        parts = [data.qpos, data.qvel, data.act] + ([data.qacc_warmstart] if self.warm_start else [])
        return jnp.concatenate(parts).astype(x.dtype)

    def output(self, t, x, u):
        if not self.sensors:
            return x
        _, mjx = _mujoco()
        return mjx.forward(self.model, self._data(t, x, u)).sensordata.astype(x.dtype)

    def initial_state(self):
        """The model's qpos0 at rest, activations (and warm start) zero: MuJoCo's reset state."""
        nq, nv, na = self.sizes
        return jnp.concatenate([jnp.asarray(self.mj_model.qpos0, float), jnp.zeros(nv + na + self.warm_start * nv)])

    def render(self, x, *, width: int = 640, height: int = 480, camera=-1):
        """An RGB image (height, width, 3) of state x by MuJoCo's own renderer (needs an OpenGL
        context: `MUJOCO_GL=egl` or `osmesa` on a machine without a display)."""
        mujoco, _ = _mujoco()
        nq, nv, _ = self.sizes
        data = mujoco.MjData(self.mj_model)
        x = np.asarray(x, float)
        data.qpos[:], data.qvel[:], data.act[:] = x[:nq], x[nq: nq + nv], x[nq + nv: nq + nv + self.sizes[2]]
        mujoco.mj_forward(self.mj_model, data)
        with renderer(self.mj_model, height, width) as scene:
            scene.update_scene(data, camera)
            return scene.render()


def _name(mujoco, model, kind, i, fallback):
    return mujoco.mj_id2name(model, kind, i) or f"{fallback}{i}"


def _state_names(mujoco, model):
    positions, velocities = [], []
    for j in range(model.njnt):
        name = _name(mujoco, model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint")
        kind = int(model.jnt_type[j])
        positions += [f"{name}_{c}" if c else name for c in _POSITIONS[kind]]
        velocities += [f"{name}{c}" if c == "dot" else f"{name}_{c}" for c in _VELOCITIES[kind]]
    activations = [f"{_name(mujoco, model, mujoco.mjtObj.mjOBJ_ACTUATOR, i, 'u')}_act"
                   for i in range(model.nu) if model.actuator_actnum[i]]
    return tuple(positions + velocities + activations)


def _sensor_names(mujoco, model):
    names = []
    for s in range(model.nsensor):
        name = _name(mujoco, model, mujoco.mjtObj.mjOBJ_SENSOR, s, "sensor")
        dim = int(model.sensor_dim[s])
        names += [name] if dim == 1 else [f"{name}_{k}" for k in range(dim)]
    return tuple(names)
