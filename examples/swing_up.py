"""Swing-up and balance for the acrobot and the cart-pole (Underactuated Robotics, ch. 3).

A hybrid controller (`jd.control.SwitchToLQR`) runs an energy-shaping swing-up — Spong's for
the acrobot, as Drake's `AcrobotSpongController`; the pole's energy through the cart for the
cart-pole — until the LQR cost-to-go V = (x - x0)' S (x - x0) falls below a threshold, then
balances with LQR; the switch is an event of the simulation, located exactly. Top: one run of
each plant (angles, and V on a log scale with the switching thresholds). Bottom: a batch of
initial states near the bottom (one vmapped program): the fraction balanced against time.

Run:  python examples/swing_up.py [--out DIR] [--batch N]     (saves swing_up.png)
"""

import argparse
import pathlib

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)

Q, R = jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0])), jnp.eye(1)


def acrobot_loop():
    acrobot, goal = jd.models.Acrobot(), jnp.array([jnp.pi, 0.0, 0.0, 0.0])
    balance = jd.control.lqr(acrobot, Q, R, x0=goal)
    switch = jd.control.SwitchToLQR(jd.control.acrobot_spong_controller(acrobot), balance,
                                    angles=(0, 1), enter=300.0, leave=3000.0,
                                    output_limits=(-20.0, 20.0))
    return jd.feedback(acrobot, switch), switch, goal


def cart_pole_loop():
    cart_pole, goal = jd.models.CartPole(), jnp.array([0.0, jnp.pi, 0.0, 0.0])
    balance = jd.control.lqr(cart_pole, Q, R, x0=goal)
    switch = jd.control.SwitchToLQR(jd.control.cart_pole_swing_up_controller(cart_pole), balance,
                                    angles=(1,), enter=100.0, leave=1000.0)
    return jd.feedback(cart_pole, switch), switch, goal


def balanced(final, goal, wrapped, tol):
    err = np.asarray(final) - np.asarray(goal)
    err[:, wrapped] = np.mod(err[:, wrapped] + np.pi, 2 * np.pi) - np.pi
    return np.max(np.abs(err), axis=1) < tol


def batch(closed, goal, wrapped, T, num, tol, seed=0):
    """Runs from `num` states near the bottom; returns the success mask and the time of the
    last switch into LQR for each run."""
    starts = 0.1 * jax.random.normal(jax.random.key(seed), (num, 4))
    runs = jax.jit(jax.vmap(lambda x: jd.simulate(closed, (0.0, T), x, max_steps=16000, rtol=1e-5,
                                                  atol=1e-7, dense=False, throw=False)))(starts)
    ok = balanced(runs.final_state, goal, wrapped, tol) & np.asarray(runs.success)
    n = np.asarray(runs.num_events)
    last = np.asarray(runs.event_times)[np.arange(num), np.maximum(n - 1, 0)]
    return ok, np.where(n > 0, last, np.inf)


def plot_run(axes, closed, switch, T, x0, names, title):
    traj = jd.simulate(closed, (0.0, T), x0, max_steps=16000)
    ts = jnp.linspace(0.0, T, 2000)
    xs = np.asarray(traj.state(ts))
    for k, name in names.items():
        axes[0].plot(ts, xs[:, k], label=name)
    for t, mode in zip(traj.events["times"], traj.events["modes"]):
        for ax in axes:
            ax.axvline(t, color="k" if mode == 1 else "0.6", ls="--", lw=0.8)
    axes[0].set(title=title + " (dashed: switch into LQR)", ylabel="rad / m")
    axes[0].legend(loc="upper left", fontsize=8)
    axes[1].semilogy(ts, jax.vmap(switch.cost_to_go)(jnp.asarray(xs)), color="C3")
    axes[1].axhline(float(switch.enter), color="k", lw=0.6)
    axes[1].axhline(float(switch.leave), color="0.6", lw=0.6)
    axes[1].set(ylabel="V = (x - x0)' S (x - x0)", xlabel="t (s)", ylim=(1e-6, None))


def plot_batch(ax, ok, last, T, label):
    ts = np.linspace(0.0, T, 400)
    fraction = [(ok & (last <= t)).mean() for t in ts]
    ax.plot(ts, fraction, label=f"{label}: {ok.mean():.1%} of {len(ok)} balanced at {T:g} s")


def main(out: pathlib.Path, num: int) -> pathlib.Path:
    fig = plt.figure(figsize=(15, 9), layout="constrained")
    grid = fig.add_gridspec(3, 2, height_ratios=[1, 1, 1.1])
    acrobot, acrobot_switch, acrobot_goal = acrobot_loop()
    cart_pole, cart_pole_switch, cart_pole_goal = cart_pole_loop()
    plot_run([fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0])], acrobot, acrobot_switch, 20.0,
             jnp.array([0.1, -0.02, 0.0, 0.0]), {0: "q1 (shoulder)", 1: "q2 (elbow)"}, "acrobot")
    plot_run([fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 1])], cart_pole, cart_pole_switch, 8.0,
             jnp.array([0.0, 0.1, 0.0, 0.0]), {0: "x (cart)", 1: "theta (pole)"}, "cart-pole")

    ax = fig.add_subplot(grid[2, :])
    ok, last = batch(acrobot, acrobot_goal, [0, 1], 40.0, num, tol=1e-2)
    print(f"acrobot: {ok.mean():.1%} of {num} swung up and balanced within 40 s")
    plot_batch(ax, ok, last, 40.0, "acrobot")
    ok, last = batch(cart_pole, cart_pole_goal, [1], 10.0, num, tol=0.1)
    print(f"cart-pole: {ok.mean():.1%} of {num} swung up and balanced within 10 s")
    plot_batch(ax, ok, last, 10.0, "cart-pole")
    ax.set(xlabel="t (s)", ylabel="fraction balanced (in LQR for good)", ylim=(0, 1.02), xlim=(0, 40),
           title="batches from states near the bottom, q ~ N(0, 0.1^2)")
    ax.legend(loc="lower right")
    return save(fig, out, "swing_up.png")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("output"),
                        help="folder for the figure (default: output/)")
    parser.add_argument("--batch", type=int, default=50,
                        help="initial states per plant (the notebook runs 1000)")
    args = parser.parse_args()
    main(args.out, args.batch)
