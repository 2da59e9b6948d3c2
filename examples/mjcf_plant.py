"""A MuJoCo model in jaxdrake's own rigid-body plant: MJX's Shadow hand closes into a fist
under its 24 position servos, with error-controlled steps and contact between its fingers.

`RigidBodySystem.from_mjcf` compiles the file with MuJoCo and reads its bodies, hinges,
armature, damping, collision geoms and actuators; the servos keep MuJoCo's force law
(f = clip(kp (u - gear q), forcerange), `plant.actuators`), so the inputs are MuJoCo's ctrl.
Before simulating, the plant's accelerations are checked against `mj_forward` at the start.
The frames are drawn by MuJoCo's renderer of the same file (`jd.viz.visualizer_for`).

Run:  python examples/mjcf_plant.py [--out DIR]      (saves mjcf_plant.png, mjcf_plant.gif)
"""

import pathlib
import time

import jax
import jax.numpy as jnp
import matplotlib
import mujoco
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)

HAND = pathlib.Path(mujoco.__file__).parent / "mjx/test_data/shadow_hand/scene_right.xml"
T_FINAL = 0.5


def fist(plant):
    """ctrl targets: every finger's flexion (J1-J3) and the thumb's at 80% of its range toward
    closing, the rest at the middle of theirs."""
    lower, upper = (np.asarray(side) for side in plant.input_limits)
    closing = np.array(["J1" in n or "J2" in n or "J3" in n or "THJ4" in n for n in plant.input_frame.coordinates])
    return jnp.asarray(np.where(closing, lower + 0.8 * (upper - lower), 0.5 * (lower + upper)))


def resting_ball(plant):
    """The file's configuration with its ball (the free body) moved from above the palm to the
    floor beside the hand, at rest: the hand closes on its own."""
    x0 = np.array(plant.initial_state())
    ball = plant.tree.q_starts[list(plant.tree.joint_types).index(jd.multibody.JointType.FLOATING)]
    x0[ball: ball + 3] = [0.35, 0.15, -0.1 + 0.03]   # on the floor (z = -0.1), radius 3 cm
    return jnp.asarray(x0)


def check_against_mujoco(plant, u):
    """The largest |qdd - MuJoCo's qacc| at the file's configuration, at rest (the ball in the
    air, MuJoCo's own constraints off: the plant's compliant limits and contact are silent
    there; at rest and unturned, the ball's body-frame velocity coordinates are MuJoCo's)."""
    model, addresses = jd.multibody.mjcf_render_model(plant)   # MuJoCo's model; each q's qpos index
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    data = mujoco.MjData(model)
    x0 = plant.initial_state()
    data.qpos[addresses], data.ctrl[:] = np.asarray(x0[: plant.tree.nq]), np.asarray(u)
    mujoco.mj_forward(model, data)
    qdd = np.asarray(plant.dynamics(0.0, x0, u))[plant.tree.nq:]   # the bodies in MuJoCo's order: its dofs'
    return float(np.max(np.abs(qdd - data.qacc)))


def main(out: pathlib.Path) -> pathlib.Path:
    plant = jd.RigidBodySystem.from_mjcf(HAND, contact=True)
    x0, u = resting_ball(plant), fist(plant)
    print(f"{plant.name}: {plant.num_inputs} hinges under as many position servos, a free ball, "
          f"{len(plant.contact.names)} collision geoms; |qdd - mj_forward| at the start: "
          f"{check_against_mujoco(plant, u):.1e}")
    start = time.perf_counter()
    traj = jd.simulate(plant, (0.0, T_FINAL), x0, inputs=u, rtol=1e-4, atol=1e-6, max_steps=20000)
    traj.final_state.block_until_ready()
    print(f"simulated {T_FINAL} s in {time.perf_counter() - start:.1f} s (first call: compiling included), "
          f"{int(traj.num_accepted_steps)} steps + {int(traj.num_rejected_steps)} rejected")

    vis = jd.viz.visualizer_for(plant)
    times = np.linspace(0.0, T_FINAL, 4)
    frames = vis.images(np.asarray(traj.state(jnp.asarray(times))))
    fig = plt.figure(figsize=(16, 7.5), layout="constrained")
    grid = fig.add_gridspec(2, 4, height_ratios=[1.1, 1])
    for k, (t, image) in enumerate(zip(times, frames)):
        ax = fig.add_subplot(grid[0, k])
        ax.imshow(image)
        ax.set_axis_off()
        ax.set_title(f"t = {t:.2f} s")
    ts = np.linspace(0.0, T_FINAL, 300)
    q = np.asarray(traj.state(jnp.asarray(ts)))
    ax = fig.add_subplot(grid[1, :2])
    names = plant.tree.joint_names
    for finger, color in zip(("FF", "MF", "RF", "LF", "TH"), ("C0", "C1", "C2", "C3", "C4")):
        flexion = [j for j, name in enumerate(names) if finger in name and name[-1] in "123"]
        for k, j in enumerate(flexion):
            ax.plot(ts, q[:, plant.tree.q_starts[j]], color=color, lw=1.2, label=finger if k == 0 else None)
    ax.set(xlabel="t (s)", ylabel="joint angle (rad)", title="the fingers' flexion joints under their servos")
    ax.legend(fontsize=8, ncol=5)
    ax = fig.add_subplot(grid[1, 2:])
    forces = np.stack([np.asarray(plant.actuation(x[:plant.tree.nq], x[plant.tree.nq:], u))
                       for x in q[::10]])
    ax.plot(ts[::10], forces, lw=0.8)
    ax.set(xlabel="t (s)", ylabel="joint force (N m)", title="the servos' joint forces (gear x force, clipped at forcerange)")
    path = save(fig, out, "mjcf_plant.png")
    vis.save(traj, out / "mjcf_plant.gif", fps=15)
    print(f"saved {out / 'mjcf_plant.gif'}")
    return path


if __name__ == "__main__":
    run(main, __doc__)
