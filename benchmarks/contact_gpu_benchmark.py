"""Solo-12 quadrupeds standing for 1 s under a joint PD posture controller, a batch of
perturbed starts on one device: jaxdrake's contact plant against MJX on the same geometry.

Both sides: solo12.urdf (example-robot-data, its mesh collisions and visuals left out), the
spheres of contact_benchmark.py (feet and knees 2 cm, the base's four corners 3 cm), a floor,
friction 0.5, no joint or effort limits, and the same PD on the 12 joints,
u = KP (q_des - q) - KD qdot toward the crouched posture (HFE +-0.8, KFE -+1.6). The starts
(one per robot, the same on both sides): the posture, joints +-0.1 rad, base roll / pitch
+-0.05 rad, raised so that the lowest sphere is 0-3 cm above the floor, at rest. float32.

- jaxdrake: `RigidBodySystem.from_urdf(..., floating_base=True)` + `with_collision_geometry` +
  `with_ground()` (Drake's compliant point contact: Hunt-Crossley k = 1e6 N/m, d = 50 s/m,
  regularised Stribeck friction with stiction tolerance v_s, Drake's default 1e-4 m/s), the PD
  closed around it by `jd.feedback`, simulated by `jd.simulate(..., dense=False)` under
  `jax.vmap` over the starts. `--ours solver:rtol:atol[:v_s]`; one program per solver (the
  tolerances and v_s are traced arguments).
- MJX: the same URDF compiled by MuJoCo (`mujoco.MjSpec`; a free joint on the base, the
  spheres as geoms, a plane, `position` actuators with kp = KP, kv = KD), MuJoCo's own soft
  contact (default solref / solimp, pyramidal cone, Newton solver), Euler at 2 ms, float32;
  `lax.scan` over `mjx.step` under `vmap` ("default": MuJoCo's solver options, 100 iterations
  at most; "iter:N:L": N solver and L line-search iterations; "fast": 1 and 4, MuJoCo
  Playground's setting), and ("system") the default model as a `jd.MujocoSystem` through
  `jd.simulate`.

Per row: first call (trace + compile + run; a later row of the same solver reuses the
program) and warm time (the best of --repeats calls), robot-seconds simulated per wall second, and env-steps/s at MJX's 2 ms
(for our adaptive rows the equivalent: robots x T / 2 ms per wall second). Ours also: accepted
and rejected steps per robot (accepted counted by a dense run of the first --count members)
and the loop iterations of the slowest (the vmapped loop runs until its slowest member ends).
Stand check: base height after T within [h_nominal - 4 cm, h_nominal + 2 cm] and the base's
z axis within 18 degrees of vertical.

    python benchmarks/contact_gpu_benchmark.py [--batch 4096] [--duration 1.0]
        [--ours rosenbrock23:1e-2:1e-2:1e-2 rosenbrock23:1e-2:1e-2 dopri5:1e-2:1e-3:1e-2]
        [--mjx default iter:4:8 fast system] [--urdf solo12.urdf] [--float64 (ours only)]

Results and the tolerance's justification: benchmarks/RESULTS.md, "Contact on the GPU (issue 38)".
On a machine without libEGL, run with MUJOCO_GL=disable.
"""

from __future__ import annotations

import argparse
import copy
import pathlib
import tempfile
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import machine_line, solver_named  # benchmarks/_common.py
from contact_benchmark import SPHERES, solo_without_mesh_collisions  # the same scene as the CPU benchmark

LEGS = ("FL", "FR", "HL", "HR")
KP, KD = 5.0, 0.1          # N m / rad, N m s / rad (joint damping ratio ~1 on the knee)
FRICTION = 0.5             # Drake's default, combined as 2 mu mu / (mu + mu) = 0.5
MJX_DT = 0.002             # MuJoCo's default time step
HEIGHT_BAND = (-0.04, 0.02)
TILT = np.cos(np.radians(18.0))


def posture(joint):
    """The PD's set point for a joint name: HFE +0.8 / KFE -1.6 in front, mirrored behind."""
    leg, kind = joint.split("_")
    sign = 1.0 if leg[0] == "F" else -1.0
    return {"HAA": 0.0, "HFE": 0.8 * sign, "KFE": -1.6 * sign}[kind]


# ----- jaxdrake --------------------------------------------------------------------------------

def our_plant(path):
    plant = jd.RigidBodySystem.from_urdf(path, floating_base=True, joint_limits=False, effort_limits=False)
    for i, (link, position, radius) in enumerate(SPHERES):
        plant = plant.with_collision_geometry(link, jd.geometry.Sphere(radius), translation=position, name=f"sphere{i}")
    return plant.with_ground()


def closed_loop(plant):
    """`jd.feedback(plant, pd)`: the PD reads the plant's state (its output) and drives its inputs."""
    tree = plant.tree
    joints = plant.input_frame.coordinates
    iq = np.array([tree.q_starts[tree.joint_names.index(j)] for j in joints])
    iv = tree.nq + np.array([tree.v_starts[tree.joint_names.index(j)] for j in joints])
    q_des = np.array([posture(j) for j in joints])

    def pd(t, x, u):
        return KP * (jnp.asarray(q_des, u.dtype) - u[iq]) - KD * u[iv]

    controller = jd.System.from_functions(output=pd, num_states=0, num_inputs=plant.num_states)
    return jd.feedback(plant, controller)


def starts(plant, batch, seed=0):
    """(nominal standing state, batch of perturbed starts), in our coordinates
    (x y z qx qy qz qw, joints; velocities in the base frame)."""
    tree = plant.tree
    q = np.array(tree.neutral_configuration(), np.float64)
    for j in tree.joint_names:
        if j != tree.joint_names[0] or not tree.has_floating_base:
            q[tree.q_starts[tree.joint_names.index(j)]] = posture(j)
    with jax.ensure_compile_time_eval():
        lowest = min(float(plant.frame_pose(jnp.asarray(q, jnp.float32), f"{leg}_FOOT")[1][2]) for leg in LEGS)
    q[2] = 0.02 - lowest  # feet spheres touching
    nominal = np.concatenate([q, np.zeros(tree.nv)])
    rng = np.random.default_rng(seed)
    x = np.repeat(nominal[None], batch, axis=0)
    x[:, 7: tree.nq] += rng.uniform(-0.1, 0.1, (batch, tree.nq - 7))
    roll, pitch = rng.uniform(-0.05, 0.05, (2, batch))
    cr, sr, cp, sp = np.cos(roll / 2), np.sin(roll / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    x[:, 3:7] = np.stack([sr * cp, cr * sp, -sr * sp, cr * cp], axis=1)  # qx qy qz qw of Ry(pitch) Rx(roll)
    x[:, 2] -= lowest_sphere(plant, x)  # the lowest sphere 0-3 cm above the floor
    return nominal, x


def lowest_sphere(plant, x):
    """The height of the lowest point of any sphere at each state of a batch, minus the base's drop."""
    def lowest(xi):
        q = xi[: plant.tree.nq]
        return jnp.min(jnp.stack([plant.frame_pose(q, link)[1][2] + plant.frame_pose(q, link)[0][2] @ jnp.asarray(p)
                                  - r for link, p, r in SPHERES]))
    with jax.ensure_compile_time_eval():
        bottoms = np.asarray(jax.vmap(lowest)(jnp.asarray(x, jnp.float32)), np.float64)
    drop = np.random.default_rng(1).uniform(0.0, 0.03, x.shape[0])
    return bottoms - drop


def standing(height, up_z, nominal_height):
    lo, hi = nominal_height + HEIGHT_BAND[0], nominal_height + HEIGHT_BAND[1]
    ok = (height >= lo) & (height <= hi) & (up_z >= TILT) & np.isfinite(height)
    return ok, (lo, hi)


def up_z_xyzw(quat):
    """The z component of the base's z axis, from quaternions (x, y, z, w)."""
    x, y = quat[..., 0], quat[..., 1]
    return 1.0 - 2.0 * (x * x + y * y)


# ----- MuJoCo / MJX ----------------------------------------------------------------------------

def mujoco_model(path, joints):
    """The URDF compiled by MuJoCo with the same spheres, a plane and position actuators (kp = KP,
    kv = KD) on `joints` (in our input order)."""
    import mujoco
    spec = mujoco.MjSpec.from_string(pathlib.Path(path).read_text())
    spec.compiler.fusestatic = False  # keep the FOOT links as bodies (they carry spheres)
    spec.option.timestep = MJX_DT
    spec.body("base_link").add_freejoint()
    friction = [FRICTION, 0.005, 0.0001]
    for i, (link, position, radius) in enumerate(SPHERES):
        spec.body(link).add_geom(name=f"sphere{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0],
                                 pos=list(position), friction=friction)
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], friction=friction)
    for joint in joints:
        actuator = spec.add_actuator(name=joint, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.gainprm[0] = KP
        actuator.biasprm[0], actuator.biasprm[1], actuator.biasprm[2] = 0.0, -KP, -KD
    return spec.compile()


def to_mujoco(plant, model, x):
    """Our batch of states -> MuJoCo's (qpos with w x y z quaternions, qvel with the base's
    linear velocity in the world frame; zero here: the starts are at rest)."""
    import mujoco
    tree = plant.tree
    qpos = np.zeros((x.shape[0], model.nq))
    qpos[:, 0:3] = x[:, 0:3]
    qpos[:, 3], qpos[:, 4:7] = x[:, 6], x[:, 3:6]
    for j in tree.joint_names[1:]:
        address = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]
        qpos[:, address] = x[:, tree.q_starts[tree.joint_names.index(j)]]
    assert not np.any(x[:, tree.nq:]), "the starts are at rest"
    return qpos, np.zeros((x.shape[0], model.nv))


def contact_pairs(model):
    """Geom pairs MuJoCo may test (contype / conaffinity; welded and parent-child bodies filtered
    unless one is the world), by name."""
    import mujoco
    pairs = []
    for a in range(model.ngeom):
        for b in range(a + 1, model.ngeom):
            ba, bb = model.geom_bodyid[a], model.geom_bodyid[b]
            if ba == bb or not ((model.geom_contype[a] & model.geom_conaffinity[b])
                                or (model.geom_contype[b] & model.geom_conaffinity[a])):
                continue
            wa, wb = model.body_weldid[ba], model.body_weldid[bb]
            parent_child = (model.body_weldid[model.body_parentid[wa]] == wb
                            or model.body_weldid[model.body_parentid[wb]] == wa)
            if wa == wb or (wa != 0 and wb != 0 and parent_child):  # the world's children do collide
                continue
            pairs.append((mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, a),
                          mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, b)))
    return pairs


# ----- timing ----------------------------------------------------------------------------------

def timed(fn, *args, repeats=1):
    """(first call, the best of `repeats` warm calls, the output)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    warm = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        warm = min(warm, time.perf_counter() - start)
    return first, warm, out


def row(label, setting, first, warm, batch, duration, extra=""):
    robot_seconds = batch * duration / warm
    number = lambda v: f"{v:,.0f}" if v >= 100 else f"{v:.3g}"  # noqa: E731
    print(f"| {label} | {setting} | {first:.1f} | {warm:.3f} | {number(robot_seconds)} | "
          f"{number(robot_seconds / MJX_DT)} | {extra} |", flush=True)
    return robot_seconds


def stand_summary(height, up_z, nominal_height):
    ok, (lo, hi) = standing(height, up_z, nominal_height)
    return (f"stand {ok.sum()}/{ok.size}, base z {np.nanmin(height):.3f}-{np.nanmax(height):.3f} "
            f"(mean {np.nanmean(height):.3f}; band {lo:.3f}-{hi:.3f})")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--ours", nargs="*", default=["rosenbrock23:1e-2:1e-2:1e-2", "rosenbrock23:1e-2:1e-2",
                                                      "dopri5:1e-2:1e-3:1e-2"],
                        help="solver:rtol:atol[:stiction tolerance in m/s, default Drake's 1e-4]; solver "
                             "rosenbrock23/stiff: Rosenbrock23(jacobian='stiff')")
    parser.add_argument("--mjx", nargs="*", default=["default", "iter:4:8", "fast", "system"],
                        help="default / fast / iter:N:L: lax.scan(mjx.step) with MuJoCo's / Playground's / N "
                             "solver and L line-search iterations; system: MujocoSystem (default options) "
                             "through jd.simulate")
    parser.add_argument("--count", type=int, default=32, help="members of the dense run counting accepted steps")
    parser.add_argument("--max-steps", type=int, default=30000)
    parser.add_argument("--urdf", default=None, help="solo12.urdf (default: example-robot-data's)")
    parser.add_argument("--repeats", type=int, default=1, help="warm calls per row, the best one reported")
    parser.add_argument("--float64", action="store_true",
                        help="our rows in float64 (the same float32-built starts); MJX's rows are timed in float32, "
                             "so run them in a call of their own (--mjx with no names here)")
    args = parser.parse_args()
    if args.float64 and args.mjx:
        parser.error("--float64 times our rows only: give --mjx no names, and time MJX (float32) in another call")
    if args.float64:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64 if args.float64 else jnp.float32
    print(machine_line())
    batch, duration = args.batch, args.duration
    with tempfile.TemporaryDirectory() as folder:
        path = solo_without_mesh_collisions(folder, args.urdf)
        plant = our_plant(path)
        nominal, x0 = starts(plant, batch)
        h_nom = float(nominal[2])
        joints = plant.input_frame.coordinates
        model = mujoco_model(path, joints)
    print(f"batch {batch}, {duration} s, PD kp {KP} kd {KD}; nominal base height {h_nom:.4f} m; "
          f"our candidate pairs {sum(len(g[2]) for g in plant.contact.groups)}, "
          f"MuJoCo geom pairs {len(contact_pairs(model))}")
    print("| simulator | setting | first call (s) | warm (s) | robot-s / s | env-steps/s at 2 ms | notes |")
    print("|---|---|---|---|---|---|---|")
    rates = {}
    xs = jnp.asarray(x0, dtype)
    if args.mjx:
        from mujoco import mjx
        qpos0, qvel0 = to_mujoco(plant, model, x0)
        qpos0, qvel0 = jnp.asarray(qpos0, jnp.float32), jnp.asarray(qvel0, jnp.float32)
        ctrl = jnp.asarray([posture(j) for j in joints], jnp.float32)
        steps = int(round(duration / MJX_DT))
        for variant in args.mjx:
            m = copy.copy(model)
            if variant == "fast":
                m.opt.iterations, m.opt.ls_iterations = 1, 4
            elif variant.startswith("iter:"):  # iter:N:L, N solver and L line-search iterations
                m.opt.iterations, m.opt.ls_iterations = (int(n) for n in variant.split(":")[1:])
            if variant == "system":
                sys_ = jd.MujocoSystem(m, warm_start=True)
                nx = sys_.num_states

                def ours_mj(qp, qv):
                    x = jnp.concatenate([qp, qv, jnp.zeros(nx - qp.shape[0] - qv.shape[0], qp.dtype)])
                    r = jd.simulate(sys_, (0.0, steps * MJX_DT), x, inputs=lambda t: ctrl, dense=False, throw=False)
                    return r.final_state[: m.nq]

                fn = jax.jit(jax.vmap(ours_mj))
                label, setting = "jd.simulate(MujocoSystem)", "MJX default options, warm start"
            else:
                mx = mjx.put_model(m)

                def rollout(qp, qv, mx=mx):
                    data = mjx.make_data(mx).replace(qpos=qp, qvel=qv, ctrl=ctrl)
                    data = jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), data, None, length=steps)[0]
                    return data.qpos

                fn = jax.jit(jax.vmap(rollout))
                label = "MJX lax.scan(mjx.step)"
                setting = (f"{variant}: Euler {MJX_DT * 1e3:g} ms, {m.opt.iterations} solver / "
                           f"{m.opt.ls_iterations} line-search iterations")
            first, warm, qpos = timed(fn, qpos0, qvel0, repeats=args.repeats)
            qpos = np.asarray(qpos)
            up = 1.0 - 2.0 * (qpos[:, 4] ** 2 + qpos[:, 5] ** 2)  # w x y z
            note = f"{steps} steps of {MJX_DT * 1e3:g} ms; " + stand_summary(qpos[:, 2], up, h_nom)
            rates[f"{label} {variant}"] = row(label, setting, first, warm, batch, steps * MJX_DT, note)
    compiled = {}
    for spec in args.ours:
        solver, rtol, atol, *stiction = spec.split(":")
        rtol, atol = float(rtol), float(atol)
        stiction = float(stiction[0]) if stiction else float(plant.contact.stiction_tolerance)
        if solver not in compiled:  # one program per solver: tolerances and stiction are traced
            def simulate(x, rtol, atol, stiction, dense=False, max_steps=args.max_steps, solver=solver):
                loop = closed_loop(eqx.tree_at(lambda p: p.contact.stiction_tolerance, plant, stiction))
                return jd.simulate(loop, (0.0, duration), x, solver=solver_named(solver), rtol=rtol, atol=atol,
                                   max_steps=max_steps, dense=dense, throw=False)

            timed_run = jax.jit(jax.vmap(lambda *a: (lambda r: (r.final_state, r.num_rejected_steps, r.status))(
                simulate(*a)), in_axes=(0, None, None, None)))
            counting_run = jax.jit(jax.vmap(lambda *a: (lambda r: (r.num_segments, r.num_rejected_steps))(
                simulate(*a, dense=True)), in_axes=(0, None, None, None)))
            compiled[solver] = timed_run, counting_run
        timed_run, counting_run = compiled[solver]
        parameters = tuple(jnp.asarray(v, dtype) for v in (rtol, atol, stiction))
        first, warm, (final, rejected, status) = timed(timed_run, xs, *parameters, repeats=args.repeats)
        final, rejected, status = np.asarray(final), np.asarray(rejected), np.asarray(status)
        steps_note = ""
        if args.count:
            segments, rej = (np.asarray(a) for a in counting_run(xs[: args.count], *parameters))
            accepted = segments - 1
            iterations = accepted + rej
            steps_note = (f"first {args.count}: accepted steps/robot mean {accepted.mean():.0f} (min {accepted.min()}, "
                          f"max {accepted.max()}), rejected mean {rej.mean():.0f}, iterations of the slowest "
                          f"{iterations.max()}; accepted steps/s {batch * accepted.mean() / warm:,.0f}; ")
        ok = np.asarray(jd.SimulationStatus.is_success(status))
        failures = {jd.SimulationStatus(int(k)).name: int(np.sum(status == k)) for k in np.unique(status[~ok])}
        note = (steps_note + f"all: rejected/robot mean {rejected.mean():.0f}, max {rejected.max()}; "
                f"reached {duration} s {int(np.sum(ok))}/{batch}{' ' + str(failures) if failures else ''}; "
                + stand_summary(final[:, 2], up_z_xyzw(final[:, 3:7]), h_nom))
        setting = f"{solver} rtol {rtol:g} atol {atol:g}, stiction tol. {stiction:g} m/s"
        rates[f"jaxdrake {setting}"] = row("jaxdrake", setting, first, warm, batch, duration, note)
    print("ratios (robot-seconds per wall second, ours / MJX):")
    for a, ra in rates.items():
        if a.startswith("jaxdrake"):
            print("  " + a + ": " + ", ".join(f"{ra / rb:.2f}x vs {b}" for b, rb in rates.items()
                                              if not b.startswith("jaxdrake")))


if __name__ == "__main__":
    main()
