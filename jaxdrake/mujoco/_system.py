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
reaches them. Gradients through contacts: `jax.grad` of a simulation goes through MJX's
solver whatever its iteration count (its `while_loop` is differentiated by forward
sensitivities, for up to 32 differentiated scalars); more scalars (the discrete adjoint),
`autodiff="adjoint"`, and `jax.grad` of `discrete_update` alone, need a
one-iteration solver
(`<option iterations="1" ls_iterations="4"/>`, MuJoCo Playground's setting). Needs `pip install mujoco==3.17.0 mujoco-mjx==3.17.0` (the `mujoco` extra).

MuJoCo derives constants from the model's arrays when it compiles a model (`mj_setConst`):
subtree masses, the inverse weights that scale constraints (`body_invweight0`,
`dof_invweight0`, `tendon_invweight0`), `dof_M0`, `actuator_acc0` (muscles), rest lengths,
camera and light offsets, connect and weld anchors, geom bounds. MJX 3.17 has no JAX
counterpart (only its Warp backend has one), so `set_const` computes them in JAX, as
`mj_setConst` does, and every step whose model arrays differ from the compiled model's uses
them: a model whose arrays are replaced (a mass by `eqx.tree_at`, or under `vmap`) steps as C
MuJoCo does after `mj_setConst` (once, the compiled constants were kept: 2e-2 off after 1.5 s). XLA drops the ones a step does not read; tracing
them adds about a second to a first compile.
"""

from __future__ import annotations

import contextlib
import io
import os
import pathlib
import sys
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._extras import MissingExtraError, require_mujoco
from ..systems import Frame, System
from ..multibody import check_model_files

_POSITIONS = {0: ("x", "y", "z", "qw", "qx", "qy", "qz"), 1: ("qw", "qx", "qy", "qz"), 2: ("",), 3: ("",)}
_VELOCITIES = {0: ("vx", "vy", "vz", "wx", "wy", "wz"), 1: ("wx", "wy", "wz"), 2: ("dot",), 3: ("dot",)}


# MuJoCo renders offscreen without a display through EGL (where libEGL is missing, mujoco's
# import skips its GL context and only rendering is unavailable)
if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and "mujoco" not in sys.modules:
    os.environ.setdefault("MUJOCO_GL", "egl")


def mujoco_renderer(model, height: int, width: int):
    """`mujoco.Renderer(model, height, width)`. Where mujoco was imported before jaxdrake on a
    Linux machine without a display, it chose GLFW, which cannot open a context there: its
    offscreen context is switched to EGL first (GLFW is never tried: a failed GLFW start can
    abort the process)."""
    mujoco, _ = import_mujoco()
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


def import_mujoco():
    """mujoco and mjx, imported without MJX's "Failed to import warp" lines (Warp is an optional
    GPU backend, used only by `MujocoSystem(impl="warp")`), and with MuJoCo's warnings sent to Python's `warnings`
    (MuJoCo's own handler writes MUJOCO_LOG.TXT into the working folder) unless the user set
    a handler."""
    mujoco = require_mujoco("MujocoSystem")
    try:
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            from mujoco import mjx
    except ImportError as error:
        raise MissingExtraError("MujocoSystem", "mujoco") from error
    for line in printed.getvalue().splitlines():
        if not line.startswith(("Failed to import warp", "Failed to import mujoco_warp")):
            print(line)
    return mujoco, mjx


class MujocoSystem(System):
    """A MuJoCo model as a discrete-time jaxdrake system, stepped by MJX (see the module doc).

    **Construction:** `MujocoSystem.from_xml(text_or_path, assets=None)` (MJCF, or a URDF that
    MuJoCo imports) or `MujocoSystem(mj_model)` for a `mujoco.MjModel`. `output="state"`
    (default) or `"sensors"` (`sensordata`, named by the model's sensors); `warm_start=True`
    carries the solver's warm start in the state (see the module doc).

    `impl="warp"` steps the model with MuJoCo Warp (MJX's Warp implementation, `mjx.put_model(...,
    impl="warp")`; `pip install 'jaxdrake[mujoco-warp]'`, an NVIDIA GPU for speed): float32 steps,
    the model's constants as compiled (its arrays are not differentiable leaves there, and no
    gradient passes a Warp step), `vmap` over states and inputs. `warp_sizes`: MJX's
    `make_data` capacities for Warp, e.g. `{"naconmax": ..., "njmax": ...}`: `naconmax` counts
    the contacts of all the worlds a `vmap` steps at once (MuJoCo Warp prints an overflow
    warning and drops contacts when it is too small), `njmax` the constraints of one world.

    `mj_model` keeps the C model (for C MuJoCo, rendering); `model` is the `mjx.Model`.
    """

    model: Any
    mj_model: Any = eqx.field(static=True)
    sizes: tuple = eqx.field(static=True)  # (nq, nv, na)
    sensors: bool = eqx.field(static=True)
    warm_start: bool = eqx.field(static=True)
    impl: str = eqx.field(static=True)
    warp_sizes: tuple = eqx.field(static=True)  # ((name, capacity), ...) for make_data with impl="warp"

    def __init__(self, mj_model, *, output: str = "state", warm_start: bool = False, impl: str = "jax",
                 warp_sizes=None):
        mujoco, mjx = import_mujoco()
        if not isinstance(mj_model, mujoco.MjModel):
            raise TypeError(f"MujocoSystem needs a mujoco.MjModel (or use MujocoSystem.from_xml), "
                            f"got {type(mj_model).__name__}")
        if output not in ("state", "sensors"):
            raise ValueError(f"output must be 'state' or 'sensors', got {output!r}")
        if output == "sensors" and mj_model.nsensordata == 0:
            raise ValueError("output='sensors', but the model declares no <sensor>")
        if mj_model.nq + mj_model.nv + mj_model.na == 0:
            raise ValueError("the MuJoCo model has no degrees of freedom (no joint and no actuator state): there "
                             "is nothing to simulate; give a body a <joint> or <freejoint>")
        if impl not in ("jax", "warp"):
            raise ValueError(f"impl must be 'jax' (MJX in JAX) or 'warp' (MuJoCo Warp), got {impl!r}")
        if impl == "warp":
            try:
                import mujoco_warp  # noqa: F401
                import warp  # noqa: F401
            except ImportError as error:   # not in the test extra: 150 MB of GPU kernels' compiler
                raise ImportError("MujocoSystem(impl='warp') needs MuJoCo Warp: pip install "
                                  "'jaxdrake[mujoco-warp]' (mujoco-warp and warp-lang)") from error
        unknown = set(warp_sizes or {}) - {"naconmax", "naccdmax", "njmax", "nvmax"}
        if unknown or (warp_sizes and impl != "warp"):
            raise ValueError(f"warp_sizes takes naconmax, naccdmax, njmax, nvmax, with impl='warp' only; got "
                             f"{dict(warp_sizes)} with impl={impl!r}")
        self.impl, self.warp_sizes = impl, tuple(sorted((warp_sizes or {}).items()))
        self.mj_model, self.model = mj_model, mjx.put_model(mj_model, impl=impl)
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
    def from_xml(cls, text_or_path, assets=None, *, output: str = "state", warm_start: bool = False,
                 impl: str = "jax", warp_sizes=None) -> "MujocoSystem":
        """From MJCF text or a file path (an `.xml` MJCF or a `.urdf`); `assets`: {file name: bytes}.
        The files a model names are read only from inside its folder (the working directory for
        text) or from `assets`; its XML without DTD or entities (`multibody.check_model_files`)."""
        mujoco, _ = import_mujoco()
        text = str(text_or_path)
        if text.lstrip().startswith("<"):
            check_model_files(text=text, assets=assets)
            model = mujoco.MjModel.from_xml_string(text, assets or {})
        else:
            path = pathlib.Path(text)
            if not path.exists():
                raise FileNotFoundError(f"no MuJoCo model file {path}")
            check_model_files(path, assets=assets)
            model = mujoco.MjModel.from_xml_path(str(path), assets or {})
        return cls(model, output=output, warm_start=warm_start, impl=impl, warp_sizes=warp_sizes)

    def stepped_model(self):
        """The `mjx.Model` each step uses: `model`, its derived constants recomputed from its
        arrays (`set_const`, as C MuJoCo's `mj_setConst`) where those differ from the compiled
        model's (`mj_model`); where they do not, the compiled constants themselves (to the bit:
        a one-iteration solver turns a last-bit change of `body_invweight0` into 1e-3 in 300
        steps). With `impl="warp"`, `model` as it is."""
        if self.impl == "warp":   # Warp's kernels take float32 (simulate may have widened the leaves)
            return jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, self.model)
        fresh = set_const(self.model, self.mj_model)
        compiled = _as_compiled(self.model, self.mj_model)
        return fresh.replace(**{name: jnp.where(compiled, getattr(self.model, name), getattr(fresh, name))
                                for name in DERIVED_CONSTANTS})

    def _data(self, model, t, x, u):
        _, mjx = import_mujoco()
        nq, nv, na = self.sizes
        if self.impl == "warp":   # Warp's data is built from the C model, in float32
            data = mjx.make_data(self.mj_model, impl="warp", **dict(self.warp_sizes))
            x, u = x.astype(jnp.float32), u.astype(jnp.float32)
        else:
            data = mjx.make_data(model)
        data = data.replace(time=jnp.asarray(t, x.dtype), qpos=x[:nq], qvel=x[nq: nq + nv],
                            act=x[nq + nv: nq + nv + na], ctrl=u.astype(x.dtype))
        return data.replace(qacc_warmstart=x[nq + nv + na:]) if self.warm_start else data

    def update(self, t, x, u):
        _, mjx = import_mujoco()
        model = self.stepped_model()
        data = mjx.step(model, self._data(model, t, x, u))
        parts = [data.qpos, data.qvel, data.act] + ([data.qacc_warmstart] if self.warm_start else [])
        return jnp.concatenate(parts).astype(x.dtype)

    def output(self, t, x, u):
        if not self.sensors:
            return x
        _, mjx = import_mujoco()
        model = self.stepped_model()
        return mjx.forward(model, self._data(model, t, x, u)).sensordata.astype(x.dtype)

    def initial_state(self):
        """The model's qpos0 at rest, activations (and warm start) zero: MuJoCo's reset state."""
        nq, nv, na = self.sizes
        return jnp.concatenate([jnp.asarray(self.mj_model.qpos0, float), jnp.zeros(nv + na + self.warm_start * nv)])

    def render(self, x, *, width: int = 640, height: int = 480, camera=-1):
        """An RGB image (height, width, 3) of state x by MuJoCo's own renderer (needs an OpenGL
        context: `MUJOCO_GL=egl` or `osmesa` on a machine without a display)."""
        mujoco, _ = import_mujoco()
        nq, nv, _ = self.sizes
        data = mujoco.MjData(self.mj_model)
        x = np.asarray(x, float)
        data.qpos[:], data.qvel[:], data.act[:] = x[:nq], x[nq: nq + nv], x[nq + nv: nq + nv + self.sizes[2]]
        mujoco.mj_forward(self.mj_model, data)
        with mujoco_renderer(self.mj_model, height, width) as scene:
            scene.update_scene(data, camera)
            return scene.render()


DERIVED_CONSTANTS = ("body_subtreemass", "dof_M0", "body_invweight0", "dof_invweight0", "tendon_invweight0",
                     "tendon_length0", "actuator_acc0", "cam_pos0", "cam_poscom0", "cam_mat0", "light_pos0",
                     "light_poscom0", "light_dir0", "eq_data", "geom_aabb", "geom_rbound")
_SOURCES = ("qpos0", "body_", "jnt_", "dof_", "geom_", "site_", "cam_", "light_", "tendon_", "wrap_", "actuator_")


def _as_compiled(model, mj_model):
    """Whether the arrays the derived constants come from (those of bodies, joints, dofs,
    geoms, sites, cameras, lights, tendons, actuators, `qpos0`, the given part of `eq_data`)
    are still the compiled model's: a traced boolean (per member under `vmap`)."""
    same = [jnp.asarray(True)]
    for name in dir(mj_model):
        if not name.startswith(_SOURCES) or name in DERIVED_CONSTANTS:
            continue
        value = getattr(model, name, None)
        if not eqx.is_inexact_array(value):
            continue
        original = np.asarray(getattr(mj_model, name))
        if original.size == value.size:
            same.append(jnp.all(value == jnp.asarray(original.reshape(value.shape), value.dtype)))
    if mj_model.neq:  # the anchors and scales given, not those derived
        given = np.r_[0:3, 10:mj_model.eq_data.shape[1]]
        same.append(jnp.all(model.eq_data[:, given] == jnp.asarray(mj_model.eq_data[:, given], model.eq_data.dtype)))
    return jnp.all(jnp.stack(same))


def set_const(model, mj_model):
    """`model` (an `mjx.Model`) with the constants C MuJoCo's `mj_setConst` derives from a
    model's arrays recomputed in JAX (differentiable, `vmap`-able); `mj_model`, the C model
    it was made from, gives the static structure MJX does not keep (light bodies).

    Recomputed: `body_subtreemass` and `geom_aabb` / `geom_rbound` (primitive geoms; meshes
    and height fields keep theirs) from the arrays; from the kinematics and the mass matrix M
    at `qpos0` (mocap bodies at their `body_pos`): `dof_M0` = diag(M) without tendon armature,
    `dof_invweight0` (diag(M^-1), averaged over a ball joint's and over a free joint's
    translational and rotational dofs), `body_invweight0` (the mean diagonal of J M^-1 J^T over
    the translational and over the rotational rows of the Jacobian at the body's centre of
    mass; zero for bodies welded to the world), `tendon_invweight0` (J M^-1 J^T),
    `tendon_length0`, `actuator_acc0` (|M^-1 moment|), camera and light offsets (`*_pos0`,
    `*_poscom0`, `cam_mat0`, `light_dir0`), and the second anchor of connect constraints and
    the relative pose of marked welds between bodies (`eq_data`). Checked against C to 1e-12
    (tests/test_mujoco.py); `actuator_length0`, `dof_length` and BVHs, which MJX does not
    keep, are not."""
    _, mjx = import_mujoco()
    # MJX's own kinematic helpers and enums (private modules of the pinned mujoco-mjx 3.17)
    from mujoco.mjx._src.math import quat_inv, quat_mul
    from mujoco.mjx._src.support import local_to_global
    from mujoco.mjx._src.types import EqType, GeomType, JointType, ObjType

    dtype = model.body_mass.dtype
    parent = np.asarray(model.body_parentid)
    subtreemass = model.body_mass
    for i in range(model.nbody - 1, 0, -1):  # children after parents: accumulate leaves first
        subtreemass = subtreemass.at[parent[i]].add(subtreemass[i])

    data = mjx.make_data(model).replace(qpos=model.qpos0)
    mocap = np.asarray(model.body_mocapid) >= 0
    if mocap.any():
        order = np.argsort(np.asarray(model.body_mocapid)[mocap])
        data = data.replace(mocap_pos=model.body_pos[mocap][order], mocap_quat=model.body_quat[mocap][order])
    data = mjx.kinematics(model, data)
    data = mjx.com_pos(model, data)
    data = mjx.tendon(model, data)
    data = mjx.crb(model, data)
    dof_M0 = jnp.diagonal(mjx.full_m(model, data)) if model.nv else jnp.zeros(0, dtype)
    data = mjx.tendon_armature(model, data)
    data = mjx.transmission(model, data)
    changes = dict(body_subtreemass=subtreemass, dof_M0=dof_M0, tendon_length0=data.ten_length)

    if model.nv:
        factor = jax.scipy.linalg.cho_factor(mjx.full_m(model, data))
        quadratic = lambda J: jnp.sum(J * jax.scipy.linalg.cho_solve(factor, J.T).T, axis=-1)  # noqa: E731
        A = quadratic(jnp.eye(model.nv, dtype=dtype))
        dof_invweight0 = A
        for j, kind in enumerate(np.asarray(model.jnt_type)):
            a = int(model.jnt_dofadr[j])
            groups = {JointType.FREE: ((a, a + 3), (a + 3, a + 6)), JointType.BALL: ((a, a + 3),)}.get(kind, ())
            for lo, hi in groups:
                dof_invweight0 = dof_invweight0.at[lo:hi].set(jnp.mean(A[lo:hi]))
        jacp, jacr = jax.vmap(lambda point, b: mjx.jac(model, data, point, b))(data.xipos, jnp.arange(model.nbody))
        rows = jnp.concatenate([jacp, jacr], axis=2).transpose(0, 2, 1).reshape(6 * model.nbody, model.nv)
        diag = quadratic(rows).reshape(model.nbody, 6)
        trans, rot = jnp.mean(diag[:, :3], axis=1), jnp.mean(diag[:, 3:], axis=1)
        static = (np.arange(model.nbody) == 0) | (np.asarray(model.body_weldid) == 0)
        changes.update(dof_invweight0=dof_invweight0,
                       body_invweight0=jnp.where(static[:, None], 0.0, jnp.stack([trans, rot], axis=1)))
        if model.ntendon:
            changes["tendon_invweight0"] = quadratic(data._impl.ten_J)
        if model.nu:
            moments = data._impl.actuator_moment
            changes["actuator_acc0"] = jnp.linalg.norm(jax.scipy.linalg.cho_solve(factor, moments.T), axis=0)

    def offsets(body, target, xpos):
        """(xpos - the body's origin, xpos - the subtree com of the target, or of the body)."""
        return xpos - data.xpos[body], xpos - data.subtree_com[np.where(target >= 0, target, body)]

    if model.ncam:
        body, target = np.asarray(model.cam_bodyid), np.asarray(model.cam_targetbodyid)
        xpos, xmat = jax.vmap(local_to_global)(data.xpos[body], data.xquat[body], model.cam_pos, model.cam_quat)
        pos0, poscom0 = offsets(body, target, xpos)
        changes.update(cam_pos0=pos0, cam_poscom0=poscom0, cam_mat0=xmat)
    if mj_model.nlight:
        body, target = np.asarray(mj_model.light_bodyid), np.asarray(mj_model.light_targetbodyid)
        xpos = data.xpos[body] + jnp.einsum("lij,lj->li", data.xmat[body], model.light_pos)
        pos0, poscom0 = offsets(body, target, xpos)
        changes.update(light_pos0=pos0, light_poscom0=poscom0,
                       light_dir0=jnp.einsum("lij,lj->li", data.xmat[body], model.light_dir))

    if model.neq:
        eq_data = model.eq_data
        for k in range(model.neq):
            if int(model.eq_objtype[k]) != ObjType.BODY:
                continue
            b1, b2, kind = int(model.eq_obj1id[k]), int(model.eq_obj2id[k]), int(model.eq_type[k])
            if kind == EqType.CONNECT:  # the anchor in body 1's frame, seen from body 2
                p = data.xpos[b1] + data.xmat[b1] @ eq_data[k, 0:3]
                eq_data = eq_data.at[k, 3:6].set(data.xmat[b2].T @ (p - data.xpos[b2]))
            elif kind == EqType.WELD and float(mj_model.eq_data[k, 11]) != 0:  # marked: pose from qpos0
                p = data.xpos[b2] + data.xmat[b2] @ eq_data[k, 0:3]
                relative = quat_mul(quat_inv(data.xquat[b1]), data.xquat[b2])
                eq_data = eq_data.at[k, 3:6].set(data.xmat[b1].T @ (p - data.xpos[b1])).at[k, 6:10].set(relative)
        changes["eq_data"] = eq_data

    if model.ngeom:
        changes.update(_geom_bounds(model, GeomType))
    return model.replace(**changes)


def _geom_bounds(model, GeomType):
    """geom_aabb (centre, half sizes) and geom_rbound of primitive and height-field geoms from
    their sizes, as mj_setConst; meshes and SDFs keep theirs."""
    kinds = np.asarray(model.geom_type)
    size = model.geom_size
    half = {GeomType.SPHERE: (jnp.stack([size[:, 0]] * 3, 1), size[:, 0]),
            GeomType.CAPSULE: (jnp.stack([size[:, 0], size[:, 0], size[:, 0] + size[:, 1]], 1), size[:, 0] + size[:, 1]),
            GeomType.CYLINDER: (jnp.stack([size[:, 0], size[:, 0], size[:, 1]], 1), jnp.hypot(size[:, 0], size[:, 1])),
            GeomType.ELLIPSOID: (size, jnp.max(size, axis=1)),
            GeomType.BOX: (size, jnp.linalg.norm(size, axis=1))}
    aabb, rbound = model.geom_aabb, model.geom_rbound
    for kind, (hi, r) in half.items():
        chosen = kinds == kind
        if chosen.any():
            aabb = aabb.at[chosen].set(jnp.concatenate([jnp.zeros_like(hi), hi], 1)[chosen])
            rbound = rbound.at[chosen].set(r[chosen])
    planes = kinds == GeomType.PLANE
    if planes.any():  # unbounded below z = 0
        big = sys.modules["mujoco"].mjMAXVAL
        lo, hi = np.array([-big, -big, -big]), np.array([big, big, 0.0])
        aabb = aabb.at[planes].set(jnp.asarray(np.concatenate([(hi + lo) / 2, (hi - lo) / 2]), aabb.dtype))
        rbound = rbound.at[planes].set(0.0)
    return dict(geom_aabb=aabb, geom_rbound=rbound)


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
