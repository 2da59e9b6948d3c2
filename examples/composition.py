"""Combinations of systems (appendix D.3.4): a pendulum under PD control, three ways.

(1) `jd.feedback(plant, controller)` with a continuous PD law u = -kp (theta - pi) - kd thetadot
swings the pendulum up from a batch of initial angles; (2) the same law sampled by a discrete
controller (zero-order hold) at several periods, built with `DiagramBuilder` together with a
discrete first-order velocity filter running at its own rate (a multi-rate diagram); (3) the
gradient of a closed-loop tracking cost with respect to the gain kp by `jax.grad` through the
diagram, against finite differences.

Run:  python examples/composition.py [--out DIR]      (saves composition.png)
"""

import pathlib

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)

STATE = jd.models.Pendulum().state_frame
TORQUE = jd.models.Pendulum().input_frame


def pd_law(t, x, y, gains):
    """u = -kp (theta - pi) - kd thetadot, reading the pendulum's state y."""
    return jnp.atleast_1d(-gains[0] * (y[0] - jnp.pi) - gains[1] * y[1])


def continuous_pd(kp, kd):
    return jd.System.from_functions(output=pd_law, num_states=0, num_inputs=2, num_outputs=1,
                                    params=jnp.array([kp, kd]), input_frame=STATE, output_frame=TORQUE)


def sampled_loop(period, kp=10.0, kd=1.0):
    """Plant <- held PD command (period) <- filtered velocity (period / 2) <- plant."""
    controller = jd.System.from_functions(  # state: the held command; input [theta, filtered thetadot]
        update=lambda t, u, y: jnp.atleast_1d(-kp * (y[0] - jnp.pi) - kd * y[1]),
        num_states=1, num_inputs=2, sample_time=period, direct_feedthrough=False, output_frame=TORQUE)
    velocity_filter = jd.System.from_functions(  # v+ = 0.5 v + 0.5 thetadot, every period / 2
        update=lambda t, v, y: 0.5 * v + 0.5 * y, num_states=1, num_inputs=1,
        sample_time=period / 2, direct_feedthrough=False)
    builder = jd.DiagramBuilder()
    builder.add(jd.models.Pendulum(), "plant")
    builder.add(controller, "controller")
    builder.add(velocity_filter, "filter")
    builder.connect(("plant", ["thetadot"]), "filter")
    builder.connect(("plant", ["theta"]), ("controller", [0]))
    builder.connect("filter", ("controller", [1]))
    builder.connect("controller", "plant")
    builder.export_output("plant")
    return builder.build(f"SampledPD{period:g}")


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), layout="constrained")
    plant = jd.models.Pendulum()

    # (1) continuous PD, a batch of initial angles
    closed = jd.feedback(plant, continuous_pd(10.0, 1.0))
    print(f"feedback(Pendulum, PD) is a {type(closed).__name__}, state frame {closed.state_frame}")
    thetas = jnp.linspace(0.1, 2 * np.pi - 0.1, 24)
    ts = jnp.linspace(0.0, 5.0, 300)
    batch = jax.jit(jax.vmap(lambda th: jd.simulate(closed, (0.0, 5.0), jnp.stack([th, 0.0])).eval(ts)))(thetas)
    colors = plt.cm.viridis(np.linspace(0.0, 0.9, len(thetas)))
    for c, traj in zip(colors, np.asarray(batch)):
        axes[0].plot(ts, traj[:, 0], color=c, lw=1)
    axes[0].axhline(np.pi, color="k", ls=":", lw=0.8)
    axes[0].set(xlabel="t (s)", ylabel=r"$\theta$ (rad)", title="feedback(Pendulum, PD): 24 initial angles")

    # (2) sampled PD at several periods (multi-rate diagram)
    x0 = jnp.array([0.0, 0.0, 0.5, 0.0])  # [held u, filtered velocity, theta, thetadot]
    for period, color in zip((0.02, 0.06, 0.1), ("C0", "C1", "C3")):
        loop = sampled_loop(period)
        traj = jd.simulate(loop, (0.0, 5.0), x0, max_steps=8192)
        axes[1].plot(ts, np.asarray(traj.eval(ts))[:, 0], color=color,
                     label=f"controller every {period:g} s, filter every {period / 2:g} s")
    traj = jd.simulate(closed, (0.0, 5.0), x0[2:])
    axes[1].plot(ts, np.asarray(traj.eval(ts))[:, 0], "k--", lw=1, label="continuous PD")
    axes[1].axhline(np.pi, color="k", ls=":", lw=0.8)
    axes[1].set(xlabel="t (s)", ylabel=r"$\theta$ (rad)", ylim=(0.0, 5.6), title="sampled PD: a multi-rate diagram")
    axes[1].legend(fontsize=8, loc="lower right")

    # (3) d cost / d kp through the diagram
    def cost(kp):
        traj = jd.simulate(jd.feedback(plant, continuous_pd(kp, 1.0)), (0.0, 3.0), jnp.array([0.5, 0.0]),
                           rtol=1e-10, atol=1e-10)
        err = traj.state(jnp.linspace(0.0, 3.0, 61))[:, 0] - jnp.pi
        return jnp.mean(err ** 2)

    kps = np.linspace(4.0, 30.0, 60)
    values, grads = map(np.asarray, jax.vmap(jax.value_and_grad(cost))(jnp.asarray(kps)))
    axes[2].plot(kps, values, color="C0", label="mean squared tracking error")
    for kp in (6.0, 12.0, 20.0):
        value, slope = float(cost(kp)), float(jax.grad(cost)(kp))
        fd = (float(cost(kp + 1e-4)) - float(cost(kp - 1e-4))) / 2e-4
        axes[2].plot([kp - 2, kp + 2], [value - 2 * slope, value + 2 * slope], color="C1", lw=2)
        print(f"kp = {kp:4.1f}: d cost / d kp = {slope:+.6f} (jax.grad), {fd:+.6f} (finite differences)")
    axes[2].plot([], [], color="C1", lw=2, label="tangents from jax.grad")
    axes[2].set(xlabel="kp", title="gradient through feedback(Pendulum, PD)")
    axes[2].legend()
    return save(fig, out, "composition.png")


if __name__ == "__main__":
    run(main, __doc__)
