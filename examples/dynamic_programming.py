"""Dynamic programming (Underactuated, ch. 9): the grid world, the double integrator's
minimum-time problem and the pendulum swing-up, by value iteration.

- Grid world: a robot moving one cell at a time around obstacles; J is the number of steps
  to the goal, the policy follows it downhill.
- Double integrator, qddot = u, |u| <= 1, minimum time to the origin: fitted value iteration
  on a 31 x 51 mesh with barycentric interpolation (Drake's FittedValueIteration, same
  numbers), beside the exact bang-bang minimum time.
- Pendulum with |u| <= 3 N m < m g l: quadratic cost on a periodic 51 x 51 mesh; the mesh
  policy closed around the plant swings it up from hanging.

Run:  python examples/dynamic_programming.py [--out DIR]      (saves dynamic_programming.png)
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
from jaxdrake.planning import fitted_value_iteration, grid_world  # noqa: E402

jax.config.update("jax_enable_x64", True)


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(1, 4, figsize=(21, 4.6), layout="constrained")

    blocked = np.zeros((12, 16), bool)
    blocked[2:10, 8] = True
    blocked[6, 2:8] = True
    world = grid_world(blocked, goal=(3, 12), obstacle_cost=100.0)
    shown = np.where(blocked, np.nan, np.asarray(world.J))
    axes[0].imshow(shown, cmap="viridis")
    path = world.path((10, 2))
    axes[0].plot(path[:, 1], path[:, 0], "w.-", label=f"policy from (10, 2): {len(path) - 1} steps")
    axes[0].imshow(np.where(blocked, 1.0, np.nan), cmap="Greys", vmin=0, vmax=1.2)
    axes[0].plot(12, 3, "r*", ms=14, label="goal")
    axes[0].set(title="Grid world: cost-to-go (steps) and the greedy path")
    axes[0].legend(fontsize=8, loc="lower right")

    qs, qds = np.linspace(-3, 3, 31), np.linspace(-3, 3, 51)
    start = time.perf_counter()
    di = fitted_value_iteration(jd.models.DoubleIntegrator(), lambda x, u: jnp.where(x @ x < 0.05, 0.0, 1.0),
                                [qs, qds], [np.linspace(-1, 1, 9)], 0.01)
    print(f"double integrator: {int(di.iterations)} sweeps, {time.perf_counter() - start:.1f} s with compilation")
    Q, QD = np.meshgrid(qs, qds, indexing="ij")
    right = Q + QD * np.abs(QD) / 2 > 0
    exact = np.where(right, QD + 2 * np.sqrt(np.maximum(Q + QD ** 2 / 2, 0)),
                     -QD + 2 * np.sqrt(np.maximum(-Q + QD ** 2 / 2, 0)))
    levels = np.linspace(0, 8, 17)
    contour = axes[1].contourf(qs, qds, np.asarray(di.J).T, levels=levels, cmap="viridis")
    axes[1].contour(qs, qds, exact.T, levels=levels[::2], colors="w", linewidths=0.8)
    switch = np.linspace(-3, 3, 200)
    axes[1].plot(-switch * np.abs(switch) / 2, switch, "r--", lw=1, label="switching curve")
    axes[1].set(xlabel="q", ylabel=r"$\dot q$", xlim=(-3, 3), ylim=(-3, 3),
                title="Double integrator: J by value iteration (white: exact minimum time)")
    axes[1].legend(fontsize=8, loc="lower left")
    fig.colorbar(contour, ax=axes[1], label="time to the origin (s)")

    plant = jd.models.Pendulum(input_limits=(-3.0, 3.0))
    thetas, thetadots = np.linspace(0, 2 * np.pi, 51), np.linspace(-10, 10, 51)
    start = time.perf_counter()
    pend = fitted_value_iteration(plant, lambda x, u: 2 * (x[0] - np.pi) ** 2 + x[1] ** 2 + u[0] ** 2,
                                  [thetas, thetadots], [np.linspace(-3, 3, 9)], 0.01, periodic=[(0, 0.0, 2 * np.pi)])
    print(f"pendulum: {int(pend.iterations)} sweeps, {time.perf_counter() - start:.1f} s with compilation")
    image = axes[2].imshow(np.asarray(pend.policy_table)[..., 0].T, origin="lower", aspect="auto", cmap="coolwarm",
                           extent=(0, 2 * np.pi, -10, 10))
    traj = jd.simulate(jd.feedback(plant, pend.policy), (0.0, 10.0), jnp.array([0.1, 0.0]))
    ts = jnp.linspace(0.0, 10.0, 2001)
    x = np.asarray(traj.state(ts))
    axes[2].plot(np.mod(x[:, 0], 2 * np.pi), x[:, 1], "k.", ms=1.5, label="closed loop from hanging")
    axes[2].set(xlabel=r"$\theta$ (mod $2\pi$)", ylabel=r"$\dot\theta$", title="Pendulum: the DP policy u(x) (N m)")
    axes[2].legend(fontsize=8)
    fig.colorbar(image, ax=axes[2])
    axes[3].plot(ts, x[:, 0], label=r"$\theta$")
    axes[3].plot(ts, x[:, 1], label=r"$\dot\theta$")
    axes[3].axhline(np.pi, color="k", ls=":", lw=0.8)
    axes[3].axhline(-np.pi, color="k", ls=":", lw=0.8)
    axes[3].set(xlabel="t (s)", title="Pendulum swing-up under the DP policy")
    axes[3].legend(fontsize=8)
    print(f"pendulum final state: {x[-1]}")
    save_movie(plant, traj, out, "pendulum_swing_up.gif")
    return save(fig, out, "dynamic_programming.png")


if __name__ == "__main__":
    run(main, __doc__)
