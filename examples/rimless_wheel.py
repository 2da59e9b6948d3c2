"""The rimless wheel rolling down a slope (Underactuated, ch. 4), as a hybrid system.

Stance: an inverted pendulum theta'' = (g/l) sin(theta); when the next spoke touches down
(theta = slope + alpha) the impact resets theta+ = theta- - 2 alpha, thetadot+ = cos(2 alpha)
thetadot-. From any speed that carries it over the top, the wheel converges to steady rolling,
the fixed point of the return map thetadot+ = cot(2 alpha) sqrt(4 (g/l) sin(alpha) sin(slope)).
Several initial speeds are simulated in one vmapped call.

Run:  python examples/rimless_wheel.py [--out DIR]      (saves rimless_wheel.png and .gif)
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
    wheel = jd.models.RimlessWheel()  # Drake's defaults: l = 1, g = 9.81, 8 spokes, slope 0.08
    fixed_point = float(wheel.rolling_fixed_point())
    speeds = jnp.array([0.6, 1.0, 1.5, 2.5, 3.5])
    run = lambda w0: jd.simulate(wheel, (0.0, 20.0), jnp.stack([0.0, w0]), rtol=1e-10, atol=1e-12,
                                 max_steps=16384)
    trajs = jax.jit(jax.vmap(run))(speeds)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), layout="constrained")
    alpha, slope = np.pi / wheel.num_spokes, wheel.slope
    ts = np.linspace(0.0, 20.0, 5000)
    for i, w0 in enumerate(np.asarray(speeds)):
        traj = trajs[i]
        x = np.asarray(traj.state(jnp.asarray(ts)))
        breaks = np.flatnonzero(np.abs(np.diff(x[:, 0])) > alpha) + 1  # do not draw the resets
        for k, (th, w) in enumerate(zip(np.split(x[:, 0], breaks), np.split(x[:, 1], breaks))):
            axes[0].plot(th, w, color=f"C{i}", lw=1, label=rf"$\dot\theta_0$ = {w0}" if k == 0 else None)
        ev = traj.events
        axes[1].semilogy(np.arange(1, len(ev["times"]) + 1), np.abs(ev["states"][:, 1] - fixed_point),
                         "o-", color=f"C{i}", ms=3, label=rf"$\dot\theta_0$ = {w0}")
        print(f"thetadot0 = {w0}: {len(ev['times'])} steps, last post-impact speed "
              f"{ev['states'][-1, 1]:.8f} (fixed point {fixed_point:.8f})")
    for th in (slope - alpha, slope + alpha):
        axes[0].axvline(th, color="0.5", ls=":", lw=0.8)
    axes[0].plot([slope - alpha], [fixed_point], "k*", ms=12, label="fixed point (just after impact)")
    axes[0].set(xlabel=r"$\theta$ (rad)", ylabel=r"$\dot\theta$ (rad/s)",
                title=f"Rimless wheel on a {slope} rad slope: phase portrait")
    axes[0].legend(fontsize=8, loc="upper left")
    axes[1].set(xlabel="step", ylabel=r"|post-impact $\dot\theta$ - fixed point|",
                title="convergence to steady rolling (return map contracts by cos²(2α))")
    axes[1].legend(fontsize=8)
    rolling = jd.simulate(wheel, (0.0, 8.0), jnp.array([0.0, 1.5]), rtol=1e-10, atol=1e-12)
    save_movie(wheel, rolling, out, "rimless_wheel.gif")
    return save(fig, out, "rimless_wheel.png")


if __name__ == "__main__":
    run(main, __doc__)
