"""LQR for the acrobot, the cart-pole and the quadrotor (Underactuated Robotics, ch. 3 and 8).

Each plant is linearized about its upright (hover) equilibrium by automatic differentiation,
the Riccati equation is solved in JAX, and the controller u = u0 - K (x - x0) is closed around
the nonlinear plant with `jd.feedback`. From a batch of perturbed initial states (vmap), the
plots show the angles of the acrobot and the cart-pole and the quadrotor's position
returning to the equilibrium, with the cost-to-go (x - x0)' S (x - x0) falling.

Run:  python examples/lqr.py [--out DIR]      (saves lqr.png)
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


def stabilise(plant, x0, u0, Q, R, spread, T, num=12, seed=0):
    result = jd.control.lqr(plant, Q, R, x0=x0, u0=u0)
    closed = jd.feedback(plant, result.controller)
    starts = x0 + spread * jax.random.normal(jax.random.key(seed), (num, len(x0)))
    ts = jnp.linspace(0.0, T, 300)
    paths = jax.jit(jax.vmap(lambda x: jd.simulate(closed, (0.0, T), x, max_steps=8192).state(ts)))(starts)
    cost = jax.vmap(jax.vmap(lambda x: (x - x0) @ result.S @ (x - x0)))(paths)
    return result, np.asarray(ts), np.asarray(paths), np.asarray(cost)


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(2, 3, figsize=(16, 7.5), layout="constrained", sharex="col")
    acrobot = jd.models.Acrobot()
    res, ts, paths, cost = stabilise(acrobot, jnp.array([np.pi, 0, 0, 0]), jnp.zeros(1),
                                     jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0])), jnp.eye(1),
                                     spread=jnp.array([0.05, 0.05, 0.1, 0.1]), T=4.0)
    print("acrobot K =", np.asarray(res.K).round(2))
    axes[0, 0].plot(ts, paths[:, :, 0].T - np.pi, color="C0", lw=0.8)
    axes[0, 0].plot(ts, paths[:, :, 1].T, color="C1", lw=0.8)
    axes[0, 0].set(ylabel="rad", title=r"acrobot: $q_1 - \pi$ (blue), $q_2$ (orange)")

    cartpole = jd.models.CartPole()
    res, ts_c, paths_c, cost_c = stabilise(cartpole, jnp.array([0, np.pi, 0, 0]), jnp.zeros(1),
                                           jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0])), jnp.eye(1),
                                           spread=jnp.array([0.2, 0.1, 0.1, 0.1]), T=20.0)
    print("cart-pole K =", np.asarray(res.K).round(2))
    axes[0, 1].plot(ts_c, paths_c[:, :, 0].T, color="C0", lw=0.8)
    axes[0, 1].plot(ts_c, paths_c[:, :, 1].T - np.pi, color="C1", lw=0.8)
    axes[0, 1].set(title=r"cart-pole: $x$ (blue), $\theta - \pi$ (orange)")

    quad = jd.models.Quadrotor()
    hover = jnp.full(4, quad.m * quad.g / 4)
    res, ts_q, paths_q, cost_q = stabilise(quad, jnp.zeros(12), hover, jnp.eye(12), jnp.eye(4),
                                           spread=jnp.concatenate([jnp.full(3, 0.5), jnp.full(3, 0.2),
                                                                   jnp.full(6, 0.1)]), T=8.0)
    for k, color in enumerate(("C0", "C1", "C2")):
        axes[0, 2].plot(ts_q, paths_q[:, :, k].T, color=color, lw=0.8)
    axes[0, 2].set(title="quadrotor: x, y, z (blue, orange, green)")

    for ax, t, c in ((axes[1, 0], ts, cost), (axes[1, 1], ts_c, cost_c), (axes[1, 2], ts_q, cost_q)):
        ax.semilogy(t, c.T, color="0.3", lw=0.8)
        ax.set(xlabel="t (s)", ylabel=r"$(x - x_0)^T S (x - x_0)$")
    return save(fig, out, "lqr.png")


if __name__ == "__main__":
    run(main, __doc__)
