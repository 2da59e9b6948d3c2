"""Feedback cancellation on the double pendulum (Underactuated Robotics, ch. 1).

With both joints actuated (B = I) the controller u = H(q) qdd_d + C(q, v) v + G(q) cancels
the arm's own dynamics and imposes any accelerations qdd_d we like. Here qdd_d makes the
2-m arm swing like a simple pendulum of length l = 1 m, qdd_1 = -(g / l) sin q_1, while a
PD term holds the elbow straight, qdd_2 = -kp q_2 - kd qdot_2. The closed loop is
`jd.feedback(DoublePendulum(), controller)`; the controller reads H, C v, G from the plant's
URDF model. Plots the shoulder angle against a simple pendulum simulated on its own, the
elbow, the torques, and the passive (chaotic) double pendulum for contrast.

Run:  python examples/feedback_cancellation.py [--out DIR]      (saves feedback_cancellation.png)
"""

import pathlib

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save, save_movie  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)

LENGTH, KP, KD = 1.0, 100.0, 20.0


def cancellation_controller(plant: jd.RigidBodySystem) -> jd.System:
    """u = H qdd_d + C v + G: a static system from the plant's state to its torques."""
    g = -plant.tree.gravity[2]

    def torque(t, x, y, plant):
        q, v = y[:2], y[2:]
        H, Cv, G, B = plant.manipulator_dynamics(q, v)
        qdd_desired = jnp.stack([-(g / LENGTH) * jnp.sin(q[0]), -KP * q[1] - KD * v[1]])
        return jnp.linalg.solve(B, H @ qdd_desired + Cv + G)

    return jd.System.from_functions(output=torque, num_states=0, num_inputs=4, num_outputs=2,
                                    params=plant, input_frame=plant.output_frame,
                                    output_frame=plant.input_frame)


def main(out: pathlib.Path) -> pathlib.Path:
    plant = jd.models.DoublePendulum()
    controller = cancellation_controller(plant)
    closed = jd.feedback(plant, controller)
    T, ts = 10.0, jnp.linspace(0.0, 10.0, 1001)
    x0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    tight = dict(rtol=1e-11, atol=1e-12, max_steps=20000)
    arm = jd.simulate(closed, (0.0, T), x0, **tight)
    simple = jd.simulate(jd.models.Pendulum(m=1.0, l=LENGTH, b=0.0, g=9.81), (0.0, T), x0[jnp.array([0, 2])], **tight)
    bent = jd.simulate(closed, (0.0, T), jnp.array([1.0, 0.8, 0.0, 0.0]), **tight)
    passive = jd.simulate(plant, (0.0, T), x0, **tight)
    gap = float(jnp.max(jnp.abs(arm.state(ts)[:, 0] - simple.state(ts)[:, 0])))
    print(f"max |q1 - theta_simple| over {T:g} s: {gap:.2e} (elbow held at {float(jnp.max(jnp.abs(arm.state(ts)[:, 1]))):.1e})")

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), layout="constrained")
    t = np.asarray(ts)
    axes[0].plot(t, arm.state(ts)[:, 0], lw=3, alpha=0.5, label="double pendulum under cancellation: $q_1$")
    axes[0].plot(t, simple.state(ts)[:, 0], "k--", lw=1, label=f"simple pendulum, l = {LENGTH:g} m")
    axes[0].plot(t, bent.state(ts)[:, 0], color="C2", lw=1, label="cancellation from a bent elbow: $q_1$")
    axes[0].plot(t, bent.state(ts)[:, 1], color="C3", lw=1, label="... its elbow $q_2$")
    axes[0].set(xlabel="t (s)", ylabel="angle (rad)", title=f"the arm swings as a {LENGTH:g}-m pendulum "
                f"(max gap {gap:.0e})")
    axes[0].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)

    u = jax.vmap(lambda x: controller.output(0.0, jnp.zeros(0), x))(arm.state(ts))
    axes[1].plot(t, u[:, 0], label="shoulder torque")
    axes[1].plot(t, u[:, 1], label="elbow torque")
    axes[1].set(xlabel="t (s)", ylabel="N m", title="the torques doing the cancelling")
    axes[1].legend()

    axes[2].plot(t, passive.state(ts)[:, 0], label="$q_1$")
    axes[2].plot(t, passive.state(ts)[:, 1], label="$q_2$")
    axes[2].set(xlabel="t (s)", ylabel="angle (rad)", title="the passive double pendulum (u = 0), same start")
    axes[2].legend()
    save_movie(plant, bent, out, "feedback_cancellation.gif")
    return save(fig, out, "feedback_cancellation.png")


if __name__ == "__main__":
    run(main, __doc__)
