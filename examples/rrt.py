"""Planning with a random tree (Underactuated, ch. 15): RRT among circular obstacles, a
thousand trees grown at once under vmap, and a kinodynamic RRT that swings a torque-limited
pendulum up by simulating it.

- Geometric RRT in the unit square (goal bias 5 %, steps of 0.05): one tree and its path, and
  the fraction of 1000 random seeds that has reached the goal after k samples.
- Kinodynamic RRT for the pendulum (|u| <= 2 N m, m g l = 4.9 N m: it must pump energy): each
  edge is one simulated RK4 step of 0.1 s under one of 8 random torques; the angle wraps.

Run:  python examples/rrt.py [--out DIR]      (saves rrt.png)
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
from jaxdrake.planning import kinodynamic_rrt, rrt  # noqa: E402

jax.config.update("jax_enable_x64", True)

CENTRES = np.array([[0.5, 0.5], [0.25, 0.75], [0.75, 0.25], [0.8, 0.7]])
RADII = np.array([0.2, 0.1, 0.1, 0.08])
START, GOAL, BOX = np.array([0.1, 0.1]), np.array([0.9, 0.9]), ([0.0, 0.0], [1.0, 1.0])


def plan(key):
    return rrt(START, GOAL, BOX, key, obstacles=(CENTRES, RADII), step_size=0.05, max_nodes=600)


def draw_tree(ax, result, color="0.6"):
    nodes, parents = np.asarray(result.nodes), np.asarray(result.parents)
    for k in range(1, int(result.num_nodes)):
        ax.plot(*np.stack([nodes[parents[k]], nodes[k]]).T, color=color, lw=0.6)


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(1, 3, figsize=(17, 5), layout="constrained")
    tree = plan(jax.random.key(0))
    draw_tree(axes[0], tree)
    path = tree.path()
    axes[0].plot(path[:, 0], path[:, 1], "C3.-", lw=2, label=f"path: {len(path) - 1} steps, {int(tree.iterations)} samples")
    for c, r in zip(CENTRES, RADII):
        axes[0].add_patch(plt.Circle(c, r, color="k", alpha=0.6))
    axes[0].plot(*START, "go", ms=9)
    axes[0].plot(*GOAL, "r*", ms=14)
    axes[0].set(xlim=(0, 1), ylim=(0, 1), aspect="equal", title="RRT among circular obstacles")
    axes[0].legend(fontsize=8, loc="lower right")

    grow_many = jax.jit(jax.vmap(plan))
    keys = jax.random.split(jax.random.key(1), 1000)
    start = time.perf_counter()
    trees = grow_many(keys)
    jax.block_until_ready(trees)
    first = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(grow_many(jax.random.split(jax.random.key(2), 1000)))
    print(f"1000 trees: {first:.1f} s first call, {time.perf_counter() - start:.2f} s next "
          f"({1000 / (time.perf_counter() - start):.0f} plans/s); all reached the goal: {bool(trees.success.all())}")
    samples = np.sort(np.asarray(trees.iterations)[np.asarray(trees.success)])
    axes[1].plot(samples, np.arange(1, len(samples) + 1) / len(keys), "C0")
    axes[1].set(xlabel="samples drawn", ylabel="fraction of seeds at the goal",
                title=f"1000 seeds at once (vmap): median {int(np.median(samples))} samples")

    pendulum = jd.models.Pendulum()
    start = time.perf_counter()
    swing = kinodynamic_rrt(pendulum, [0.0, 0.0], [np.pi, 0.0], ([-np.pi, -8.0], [np.pi, 8.0]), (-2.0, 2.0), 0.1,
                            jax.random.key(0), periodic=[(0, -np.pi, np.pi)], weights=[1.0, 0.1],
                            goal_tolerance=0.3, max_nodes=5000)
    print(f"pendulum: reached the top: {bool(swing.success)} with {int(swing.num_nodes)} nodes "
          f"({time.perf_counter() - start:.1f} s with compilation)")
    nodes, parents = np.asarray(swing.nodes), np.asarray(swing.parents)
    for k in range(1, int(swing.num_nodes)):
        a, b = nodes[parents[k]], nodes[k]
        if abs(a[0] - b[0]) < np.pi:  # do not draw an edge across the wrap
            axes[2].plot([a[0], b[0]], [a[1], b[1]], color="0.7", lw=0.5)
    route = swing.path()
    jumps = np.flatnonzero(np.abs(np.diff(route[:, 0])) > np.pi) + 1
    for k, piece in enumerate(np.split(route, jumps)):
        axes[2].plot(piece[:, 0], piece[:, 1], "C3.-", lw=1.5, ms=3, label="plan: hanging to upright" if k == 0 else None)
    axes[2].plot(0, 0, "go", ms=9)
    axes[2].plot([np.pi, -np.pi], [0, 0], "r*", ms=14)
    axes[2].set(xlabel=r"$\theta$ (rad)", ylabel=r"$\dot\theta$ (rad/s)",
                title=f"Kinodynamic RRT: pendulum, |u| <= 2 N m, {int(swing.num_nodes)} nodes")
    axes[2].legend(fontsize=8)
    return save(fig, out, "rrt.png")


if __name__ == "__main__":
    run(main, __doc__)
