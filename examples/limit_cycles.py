"""Limit cycles (Underactuated, ch. 4 and 13): the Van der Pol oscillator's periodic orbit by
shooting, and the passive compass gait's walking cycle as a fixed point of its return map.

- Van der Pol (mu = 1): Newton's method on (x0, T) with the flow's derivative by autodiff
  through the simulation; the period 6.6632868593..., the Floquet multipliers (1 along the
  flow, the other exp of the integral of the divergence).
- Compass gait on Drake's 0.0525 rad slope: from a push, the walker settles onto its passive
  gait; the fixed point of the heel-strike-to-heel-strike map and its eigenvalues (inside the
  unit circle: a stable walk), and how the gait's speed changes with the slope (forward-mode
  derivatives through the impacts, by the implicit-function theorem).

Run:  python examples/limit_cycles.py [--out DIR]      (saves limit_cycles.png)
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
from jaxdrake.analysis import limit_cycle  # noqa: E402

jax.config.update("jax_enable_x64", True)


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8), layout="constrained")

    vdp = jd.models.VanDerPol()
    start = time.perf_counter()
    cycle = limit_cycle(vdp, [2.0, 0.0], 6.0)
    print(f"Van der Pol: period {float(cycle.period):.10f} in {int(cycle.iterations)} Newton steps "
          f"({time.perf_counter() - start:.1f} s with compilation); Floquet multipliers "
          f"{np.round(np.asarray(cycle.floquet_multipliers).real, 8)}")
    for x0 in ([0.1, 0.0], [3.5, 2.0], [-1.0, -3.5]):
        traj = jd.simulate(vdp, (0.0, 12.0), jnp.asarray(x0))
        x = np.asarray(traj.state(jnp.linspace(0.0, 12.0, 1500)))
        axes[0].plot(x[:, 0], x[:, 1], lw=0.8, color="0.6")
    orbit = np.asarray(cycle.trajectory.state(jnp.linspace(0.0, float(cycle.period), 600)))
    axes[0].plot(orbit[:, 0], orbit[:, 1], "C3", lw=2, label=f"limit cycle, T = {float(cycle.period):.6f}")
    axes[0].plot(*np.asarray(cycle.state), "k*", ms=12, label="x0 on the section")
    axes[0].set(xlabel="q", ylabel=r"$\dot q$", title=r"Van der Pol, $\mu$ = 1: trajectories and the limit cycle")
    axes[0].legend(fontsize=8)

    gait = jd.models.CompassGait()
    walk = jd.simulate(gait, (0.0, 12.0), jnp.array([0.0, 0.0, 0.4, -2.0]), rtol=1e-10, atol=1e-10)
    events = walk.events
    start = time.perf_counter()
    fixed = limit_cycle(gait, events["states"][-1], float(np.diff(events["times"])[-1]))
    multipliers = np.asarray(fixed.floquet_multipliers)
    print(f"compass gait: {len(events['times'])} steps in 12 s; fixed point {np.asarray(fixed.state)}, step time "
          f"{float(fixed.period):.6f} s ({time.perf_counter() - start:.1f} s); return-map eigenvalue moduli "
          f"{np.round(np.abs(multipliers), 6)}")
    ts = np.linspace(0.0, 12.0, 6000)
    x = np.asarray(walk.state(jnp.asarray(ts)))
    breaks = np.flatnonzero(np.abs(np.diff(x[:, 0])) > 0.1) + 1  # do not draw the leg swaps
    for k, (st, std) in enumerate(zip(np.split(x[:, 0], breaks), np.split(x[:, 2], breaks))):
        axes[1].plot(st, std, color="0.6", lw=0.8, label="from a push (stance leg)" if k == 0 else None)
    cyc = np.asarray(fixed.trajectory.state(jnp.linspace(0.0, float(fixed.period), 400), side="left"))
    axes[1].plot(cyc[:, 0], cyc[:, 2], "C3", lw=2, label="passive limit cycle (stance)")
    axes[1].plot(cyc[:, 1], cyc[:, 3], "C0", lw=2, label="passive limit cycle (swing)")
    axes[1].set(xlabel="leg angle (rad)", ylabel="leg angular velocity (rad/s)",
                title="Compass gait on a 0.0525 rad slope")
    axes[1].legend(fontsize=8)

    slopes = np.linspace(0.03, 0.08, 4)
    guess = np.asarray(fixed.state)

    def speed(slope):  # mean walking speed along the ramp: step length / step time
        c = limit_cycle(jd.models.CompassGait(slope=slope), guess, float(fixed.period))
        step = 2 * jnp.sin((c.state[0] - c.state[1]) / 2)  # l = 1; legs' angle apart at heel strike
        return jnp.abs(step) / c.period

    start = time.perf_counter()
    values, slopes_d = [], []
    for s in slopes:
        v, dv = jax.jvp(speed, (jnp.asarray(s),), (jnp.asarray(1.0),))
        values.append(float(v))
        slopes_d.append(float(dv))
    print(f"speed vs slope: {time.perf_counter() - start:.1f} s for {len(slopes)} slopes with derivatives")
    axes[2].plot(slopes, values, "o-", label="walking speed (m/s)")
    for s, v, dv in zip(slopes, values, slopes_d):
        axes[2].plot([s - 0.003, s + 0.003], [v - 0.003 * dv, v + 0.003 * dv], "k-", lw=2)
    axes[2].set(xlabel="slope (rad)", ylabel="m/s", title="Passive gait speed vs slope (black: d/d slope by jvp)")
    axes[2].legend(fontsize=8)
    save_movie(gait, walk, out, "compass_gait.gif")
    return save(fig, out, "limit_cycles.png")


if __name__ == "__main__":
    run(main, __doc__)
