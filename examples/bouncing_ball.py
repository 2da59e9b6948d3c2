"""The notes' bouncing ball (appendix D.3.1): a hybrid system with one flight mode and an impact.

BallPlant: flight q'' = -g; when q - r <= 0 and qdot <= 0 the impact resets qdot+ = -cor qdot-,
and the simulation stops once the rebound speed is below 0.01. Plots the height with each
located impact, the phase portrait with its jumps, and the gradient of the height at a fixed
time with respect to the drop height, through the impacts (checked against finite differences).

Run:  python examples/bouncing_ball.py [--out DIR]      (saves bouncing_ball.png)
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


def main(out: pathlib.Path) -> pathlib.Path:
    ball = jd.models.BouncingBall(g=9.81, r=1.0, cor=0.8)
    traj = jd.simulate(ball, (0.0, 10.0), jnp.array([5.0, 0.0]), rtol=1e-10, atol=1e-12)
    events = traj.events
    print(f"{len(events['times'])} impacts, stopped at t = {float(traj.t_final):.4f} s "
          f"({jd.SimulationStatus(int(traj.status)).name})")

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), layout="constrained")
    ts, ys = traj.sample(2000)
    axes[0].plot(ts, ys[:, 0], color="C0", label="height q (output)")
    axes[0].plot(events["times"], events["states"][:, 0], "v", color="C3", ms=5, label="impacts")
    axes[0].axhline(ball.r, color="0.5", lw=0.8, ls=":")
    axes[0].set(xlabel="t (s)", ylabel="q (m)", title=f"BouncingBall, cor = {ball.cor}: "
                f"{len(events['times'])} impacts, then stopped")
    axes[0].legend()

    xs = np.asarray(traj.state(jnp.asarray(ts)))
    axes[1].plot(xs[:, 0], xs[:, 1], color="C0", lw=1)
    before = np.asarray(traj.state(jnp.asarray(events["times"]), side="left"))
    for (q, v_minus), v_plus in zip(before, events["states"][:, 1]):
        axes[1].plot([q, q], [v_minus, v_plus], color="C3", ls="--", lw=0.8)
    axes[1].set(xlabel="q (m)", ylabel=r"$\dot q$ (m/s)", title="phase portrait (dashed: resets)")

    # d q(T) / d h0 across impacts, for T = 3 s, by jax.grad and by finite differences
    T = 3.0
    height = lambda h0: jd.simulate(ball, (0.0, T), jnp.stack([h0, 0.0]), rtol=1e-10, atol=1e-12).eval(T)[0]
    h0s = np.linspace(2.0, 6.0, 81)
    values, grads = map(np.asarray, jax.vmap(jax.value_and_grad(height))(jnp.asarray(h0s)))
    fd = np.gradient(values, h0s)
    axes[2].plot(h0s, values, color="C0", label="q(3 s)")
    axes[2].plot(h0s, grads, color="C1", label="d q(3 s) / d h0 (jax.grad)")
    axes[2].plot(h0s[::4], fd[::4], "k.", ms=4, label="finite differences")
    axes[2].set(xlabel="drop height h0 (m)", title="gradients through the impacts")
    axes[2].legend(fontsize=8)
    print(f"d q(3 s) / d h0 at h0 = 5: {grads[np.argmin(np.abs(h0s - 5.0))]:.6f}")  # h0s holds 5.0

    save_movie(ball, traj, out, "bouncing_ball.gif")
    return save(fig, out, "bouncing_ball.png")


if __name__ == "__main__":
    run(main, __doc__)
