"""jaxdrake's main demo: one jit-compiled simulation loop, batched with vmap, differentiated with grad.

1. The notes' simple pendulum (Drake's PendulumPlant parameters) from 1000 initial states at
   once: a phase portrait.
2. The gradient of a simulation with respect to a physical parameter: choose the damping b so
   that the pendulum, released at 2.5 rad, keeps exactly half its energy after 5 s (Newton's
   method on b, derivatives from jax.grad through the adaptive solver).
3. A torque-limited pendulum driven past its limits: saturation switching instants located as
   events.
4. The notes' bouncing ball, a hybrid system, dropped from 1000 heights in one vmapped call:
   impacts located to 1e-10, simulations stopped by the reset when the ball comes to rest.
5. A movie: 16 of the 1000 pendulums swinging, overlaid (`jd.viz`, a visualizer is a system).

Run:  python examples/demo.py [--out DIR]      (saves demo.png and demo.gif)
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
from _cli import run, save  # noqa: E402  (examples/_cli.py)
from jaxdrake.models import Pendulum  # noqa: E402

jax.config.update("jax_enable_x64", True)


def phase_portrait(ax, num=1000):
    """Simulate `num` pendulums in one vmapped call and draw a sample of them."""
    key = jax.random.key(0)
    x0 = jax.random.uniform(key, (num, 2), minval=jnp.array([-np.pi, -8.0]), maxval=jnp.array([np.pi, 8.0]))
    # max_steps sizes the dense-output buffers: 1024 pieces are plenty for 6 s
    simulate_one = lambda x0: jd.simulate(Pendulum(), (0.0, 6.0), x0, rtol=1e-8, atol=1e-10, max_steps=1024)
    batch = jax.jit(jax.vmap(simulate_one))
    start = time.perf_counter()
    trajs = jax.block_until_ready(batch(x0))
    first = time.perf_counter() - start
    start = time.perf_counter()
    trajs = jax.block_until_ready(batch(x0 + 1e-3))
    again = time.perf_counter() - start
    print(f"{num} pendulums, 6 s each: first call {first:.2f} s (with compilation), "
          f"then {again * 1e3:.0f} ms")
    ts = jnp.linspace(0.0, 6.0, 300)
    states = np.asarray(jax.vmap(lambda tr: tr.state(ts))(trajs))  # (num, 300, 2)
    energy0 = np.asarray(Pendulum().energy(x0)) + 9.81 * 0.5   # above the bottom, as the panel beside it
    cmap = plt.get_cmap("viridis")
    norm = matplotlib.colors.Normalize(energy0.min(), energy0.max())
    for s, e in zip(states[:150], energy0[:150]):
        wrapped = (s[:, 0] + np.pi) % (2 * np.pi) - np.pi
        breaks = np.flatnonzero(np.abs(np.diff(wrapped)) > np.pi) + 1  # do not draw the wrap
        for seg_theta, seg_dot in zip(np.split(wrapped, breaks), np.split(s[:, 1], breaks)):
            ax.plot(seg_theta, seg_dot, color=cmap(norm(e)), lw=0.7, alpha=0.8)
    ax.set(xlabel=r"$\theta$ (rad)", ylabel=r"$\dot\theta$ (rad/s)", xlim=(-np.pi, np.pi),
           title=f"{num} damped pendulums in one vmap (150 drawn)")
    plt.colorbar(matplotlib.cm.ScalarMappable(norm, cmap), ax=ax, label="initial energy above the bottom (J)")
    return trajs


def tune_damping(ax):
    """Newton's method on b for E(5 s; b) = E(0) / 2, with dE/db from jax.grad."""
    x0 = jnp.array([2.5, 0.0])
    e0 = Pendulum().energy(x0) + 9.81 * 0.5  # energy above the bottom, m g l (1 - cos theta)

    def energy_after(b):
        p = Pendulum(b=b)
        return p.energy(jd.simulate(p, (0.0, 5.0), x0, rtol=1e-10, atol=1e-12).final_state) + 9.81 * 0.5

    residual = lambda b: energy_after(b) - e0 / 2
    value_and_slope = jax.jit(jax.value_and_grad(residual))
    b, history = 0.01, []
    for _ in range(8):
        r, slope = value_and_slope(b)
        history.append((b, float(r)))
        if abs(r) < 1e-10:
            break
        b = float(b - r / slope)
    print(f"damping that halves the energy in 5 s: b = {b:.6f} N m s ({len(history)} Newton steps)")
    for bb, color in [(0.01, "0.6"), (b, "C3")]:
        p = Pendulum(b=bb)
        traj = jd.simulate(p, (0.0, 5.0), x0, rtol=1e-10, atol=1e-12)
        ts = np.linspace(0.0, 5.0, 400)
        ax.plot(ts, np.asarray(p.energy(traj.state(ts))) + 9.81 * 0.5, color=color,
                label=f"b = {bb:.4f}")
    ax.axhline(float(e0) / 2, color="k", ls=":", lw=1, label="half the initial energy")
    ax.set(xlabel="t (s)", ylabel="energy above the bottom (J)",
           title="Choosing b by Newton's method on jax.grad")
    ax.legend()
    return b


def torque_limits(ax):
    """A pendulum asked for 3 cos(3t) N m but limited to |tau| <= 0.8 N m."""
    p = Pendulum(input_limits=(-0.8, 0.8))
    request = lambda t: jnp.array([3.0 * jnp.cos(3.0 * t)])
    traj = jd.simulate(p, (0.0, 4.0), jnp.array([0.0, 0.0]), inputs=request, rtol=1e-4, atol=1e-6)
    ts = np.linspace(0.0, 4.0, 800)
    ax.plot(ts, 3.0 * np.cos(3.0 * ts), color="0.7", ls="--", label="requested torque")
    ax.plot(ts, np.asarray(traj.input(ts))[:, 0], color="C1", label="applied torque")
    ax.plot(ts, np.asarray(traj.eval(ts))[:, 0], color="C0", label=r"$\theta$ (rad)")
    events = traj.events["times"]
    ax.plot(events, np.asarray(traj.input(events + 1e-9))[:, 0], "k|", ms=12,
            label=f"{len(events)} switching events")
    ax.set(xlabel="t (s)", title="Input limits: switches located as events\n(rtol = 1e-4, "
           f"{traj.num_steps} steps)")
    ax.legend(fontsize=8, loc="lower left")


def bouncing_balls(ax, num=1000):
    """Hybrid systems batch too: each member keeps its own impacts and its own stop."""
    heights = jnp.linspace(1.5, 8.0, num)
    run = lambda h: jd.simulate(jd.models.BouncingBall(), (0.0, 12.0), jnp.stack([h, 0.0]),
                                rtol=1e-9, atol=1e-11, max_steps=512, max_events=64)
    balls = jax.jit(jax.vmap(run))(heights)
    stopped = np.asarray(balls.t_final)
    print(f"{num} bouncing balls: {int(np.asarray(balls.num_events).sum())} impacts located; "
          f"all stopped by the reset: {bool(np.all(np.asarray(balls.status) == jd.SimulationStatus.STOPPED_BY_RESET))}")
    ts = np.linspace(0.0, 12.0, 1200)
    cmap = plt.get_cmap("plasma")
    for i in range(0, num, num // 12):
        ball = balls[i]
        before_stop = ts <= stopped[i]  # evaluated on one grid: one compiled program for all
        ax.plot(ts[before_stop], np.asarray(ball.eval(ts))[before_stop, 0], color=cmap(i / num), lw=0.9)
        ax.plot(stopped[i], float(ball.final_state[0]), "k.", ms=4)
    ax.set(xlabel="t (s)", ylabel="height q (m)",
           title=f"BouncingBall (hybrid): {num} drops in one vmap,\n12 drawn; dots: stopped by the reset")


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(2, 2, figsize=(13, 9), layout="constrained")
    axes = axes.ravel()
    pendulums = phase_portrait(axes[0])
    start = time.perf_counter()
    movie = jd.viz.visualizer_for(Pendulum()).save(pendulums[:16], out / "demo.gif", fps=16)
    print(f"saved {movie} ({time.perf_counter() - start:.1f} s)")
    tune_damping(axes[1])
    torque_limits(axes[2])
    bouncing_balls(axes[3])
    return save(fig, out, "demo.png")


if __name__ == "__main__":
    run(main, __doc__)
