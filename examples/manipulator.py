"""Robot manipulators (Underactuated Robotics, ch. 1): the Panda arm from its URDF.

The manipulator equations H(q) qdd + C(q, v) v + G(q) = u come from the URDF (7 joints, the
fingers welded). Three runs from the same configuration: the passive arm collapsing under
gravity; gravity compensation u = G(q) + b v, which holds it still; and computed-torque control
u = H (kp (q_d - q) - kd v) + C v + G + b v, which moves it to a target along decoupled,
critically damped joint responses. Plots the joint angles of each run and the hand's path,
writes the passive run as a movie projected onto the x-z plane and the computed-torque run as
a 3-D MeshCat scene with its meshes (one offline .html file to open in a browser).
Needs the example-robot-data package (installed with the test extras), the viz extra and,
for the 3-D .gif, the mujoco extra (MuJoCo renders it).

Run:  python examples/manipulator.py [--out DIR]
      (saves manipulator.png, manipulator_passive.gif, manipulator_computed_torque.html)
"""

import pathlib
import time

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save, save_movie  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)

Q_START = jnp.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])
Q_TARGET = jnp.array([0.8, 0.3, -0.4, -1.6, 0.5, 1.6, 0.0])
KP, KD = 25.0, 10.0  # qdd = kp e - kd v: critically damped at 5 rad/s


def controller(plant, law):
    """A static system from the arm's state [q; v] to its 7 torques."""
    n = plant.num_positions

    def torque(t, x, y, plant):
        q, v = y[:n], y[n:]
        H, Cv, G, B = plant.manipulator_dynamics(q, v)
        return law(H, Cv, G, q, v) + plant.tree.damping * v

    return jd.System.from_functions(output=torque, num_states=0, num_inputs=2 * n, num_outputs=n, params=plant)


def main(out: pathlib.Path) -> pathlib.Path:
    plant = jd.models.Panda()
    x0 = jnp.concatenate([Q_START, jnp.zeros(7)])
    runs = {
        "passive (u = 0)": plant,
        "gravity compensation": jd.feedback(plant, controller(plant, lambda H, Cv, G, q, v: G)),
        "computed torque to a target": jd.feedback(plant, controller(
            plant, lambda H, Cv, G, q, v: H @ (KP * (Q_TARGET - q) - KD * v) + Cv + G)),
    }
    T, ts = 1.5, jnp.linspace(0.0, 1.5, 151)
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.4), layout="constrained")
    hand = jax.vmap(lambda x: plant.frame_pose(x[:7], "panda_hand")[1])
    for ax, (label, system) in zip(axes[:3], runs.items()):
        start = time.perf_counter()
        traj = jd.simulate(system, (0.0, T), x0, rtol=1e-7, atol=1e-9, max_steps=20000)
        print(f"{label}: {int(traj.num_steps)} steps, {time.perf_counter() - start:.1f} s with compilation")
        if label.startswith("passive"):
            save_movie(plant, traj, out, "manipulator_passive.gif")  # 3-D, rendered by MuJoCo
        if label.startswith("computed"):
            save_movie(plant, traj, out, "manipulator_computed_torque.html")  # 3-D, in MeshCat
        qs = np.asarray(traj.state(ts))[:, :7]
        for j in range(7):
            ax.plot(ts, qs[:, j], label=f"joint {j + 1}")
        ax.set(xlabel="t (s)", ylabel="rad", title=label)
        drift = float(np.max(np.abs(qs - np.asarray(Q_START))))
        print(f"{label:30s} max |q - q_start| = {drift:.2e}, final error to target "
              f"{float(np.max(np.abs(qs[-1] - np.asarray(Q_TARGET)))):.2e}")
        p = np.asarray(hand(traj.state(ts)))
        axes[3].plot(p[:, 0], p[:, 2], label=label)
        axes[3].plot(p[0, 0], p[0, 2], "ko", ms=4)
    axes[2].plot(ts, np.tile(np.asarray(Q_TARGET), (len(ts), 1)), "k:", lw=0.8)
    axes[0].legend(fontsize=7, ncol=2)
    axes[3].set(xlabel="x (m)", ylabel="z (m)", title="the hand's path (side view)")
    axes[3].set_aspect("equal", adjustable="datalim")
    axes[3].legend(fontsize=8)
    return save(fig, out, "manipulator.png")


if __name__ == "__main__":
    run(main, __doc__)
