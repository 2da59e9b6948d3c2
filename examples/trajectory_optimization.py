"""Trajectory optimization (Underactuated Robotics, ch. 10): the double integrator's minimum-time
and minimum-effort problems by direct transcription and collocation, the pendulum, acrobot
and cart-pole swing-ups by Hermite-Simpson collocation, each stabilized with TVLQR, and a batch
of pendulum swing-ups solved at once by the vmapped iLQR.

Top row: the double integrator — minimum time from (-2, 0) (T against 2 sqrt 2, the bang-bang
input) and minimum effort from (1, 0) in T = 2 (u against the closed form -6/T^2 + 12 t/T^3).
Middle row: each swing-up — the optimized angles (dots: knots), the open-loop replay from a
perturbed start (dashed), and the TVLQR closed loop from the same start (solid).
Bottom: 64 pendulum swing-ups from different initial angles: one vmapped iLQR program run by
`jd.run_batch` in two chunks of 32.

Run:  python examples/trajectory_optimization.py [--out DIR]     (saves trajectory_optimization.png)
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
from jaxdrake import trajopt  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)


def double_integrator():
    plant = jd.models.DoubleIntegrator()
    runs = {}
    for label, prog in (("collocation", trajopt.DirectCollocation(plant.with_input_limits(-1.0, 1.0), 101,
                                                                  duration=(0.5, 6.0))),
                        ("transcription (RK4)", trajopt.DirectTranscription(plant.with_input_limits(-1.0, 1.0),
                                                                            41, duration=(0.5, 6.0), rule="rk4"))):
        prog.set_initial_state([-2.0, 0.0]).set_final_state([0.0, 0.0]).add_duration_cost()
        runs[label] = prog.solve()
        print(f"minimum time, {label}: T = {runs[label].duration:.6f} (2 sqrt 2 = {2 * np.sqrt(2):.6f}), "
              f"{runs[label].iterations} iterations")
    effort = trajopt.DirectCollocation(plant, 21, duration=2.0)
    effort.set_initial_state([1.0, 0.0]).set_final_state([0.0, 0.0]).add_running_cost(lambda t, x, u: u @ u)
    runs["effort"] = effort.solve()
    print(f"minimum effort: cost {runs['effort'].cost:.10f} (12/T^3 = {12 / 8:.10f})")
    return runs


SWING_UPS = {  # plant, goal, input limit, duration, knots, angle indices to plot
    "pendulum": (jd.models.Pendulum(), [np.pi, 0.0], 3.0, 4.0, 61, (0,)),
    "acrobot": (jd.models.Acrobot(), [np.pi, 0, 0, 0], 10.0, 5.0, 101, (0, 1)),
    "cart-pole": (jd.models.CartPole(), [0, np.pi, 0, 0], 50.0, 3.0, 101, (0, 1)),
}


def swing_up(name):
    plant, goal, limit, T, N, _ = SWING_UPS[name]
    n = plant.num_states
    prog = trajopt.DirectCollocation(plant, N, duration=T).add_input_bounds(-limit, limit)
    prog.set_initial_state(np.zeros(n)).set_final_state(goal).add_running_cost(lambda t, x, u: u @ u)
    start = time.perf_counter()
    result = prog.solve(hessian="limited-memory")  # guess: straight line in state, zero input
    sparsity = prog.nlp.sparsity()
    print(f"{name}: {result.message}, cost {result.cost:.4f}, {result.iterations} iterations, "
          f"{time.perf_counter() - start:.1f} s (with compilation), max defect {result.max_defect:.1e}; "
          f"Jacobian {sparsity['jacobian_nonzeros']} non-zeros of {sparsity['jacobian_dense']}")
    tvlqr = jd.control.finite_horizon_lqr(plant, 10 * jnp.eye(n), 0.1 * jnp.eye(plant.num_inputs), (0.0, T),
                                          Qf=100 * jnp.eye(n), x_nominal=result.states, u_nominal=result.inputs)
    x0 = jnp.asarray(result.knot_states[0]) + 0.05
    open_loop = jd.simulate(plant, (0.0, T), x0, inputs=result.inputs, rtol=1e-9, atol=1e-11)
    closed_loop = jd.simulate(jd.feedback(plant, tvlqr.controller), (0.0, T), x0, rtol=1e-9, atol=1e-11)
    miss = np.abs(np.asarray(closed_loop.final_state) - np.asarray(goal)).max()
    print(f"  from x0 + 0.05: TVLQR ends {miss:.1e} from the goal, open loop "
          f"{np.abs(np.asarray(open_loop.final_state) - np.asarray(goal)).max():.1e}")
    return result, open_loop, closed_loop


def pendulum_batch(num=64):
    plant = jd.models.Pendulum(input_limits=(-2.0, 2.0))
    angles = jnp.linspace(-0.8, 0.8, num)

    def solve(angle):
        return trajopt.ilqr(plant, jnp.array([angle, 0.0]), jnp.zeros((100, 1)), 0.05, lambda t, x, u: u @ u,
                            final_state=jnp.array([np.pi, 0.0]), max_iterations=1000, constraint_tol=1e-5)

    start = time.perf_counter()
    results = jd.run_batch(solve, angles, chunk_size=32)  # one program, two chunks of 32
    print(f"iLQR batch: {num} pendulum swing-ups in {time.perf_counter() - start:.1f} s (with compilation), "
          f"{int(results.success.sum())} converged, up to {int(results.iterations.max())} iterations")
    return angles, results


def main(out: pathlib.Path):
    di = double_integrator()
    swings = {name: swing_up(name) for name in SWING_UPS}
    angles, batch = pendulum_batch()

    fig = plt.figure(figsize=(13, 11), layout="constrained")
    grid = fig.add_gridspec(3, 3)
    ax = fig.add_subplot(grid[0, 0])
    for label, style in (("collocation", "-"), ("transcription (RK4)", "o")):
        r = di[label]
        ax.plot(r.knot_states[:, 0], r.knot_states[:, 1], style, ms=3, label=f"{label}: T = {r.duration:.5f}")
    ax.set(xlabel="q", ylabel="qdot", title=f"minimum time (2√2 = {2 * np.sqrt(2):.5f})")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(grid[0, 1])
    for label, style in (("collocation", "-"), ("transcription (RK4)", "o")):
        r, last = di[label], None if style == "-" else -1  # transcription's last input is unused
        ax.plot(r.times[:last], r.knot_inputs[:last, 0], style, ms=3, label=label)
    ax.set(xlabel="t", ylabel="u", title="bang-bang input, |u| ≤ 1")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(grid[0, 2])
    r, T = di["effort"], 2.0
    s = np.linspace(0, T, 200)
    ax.plot(s, -6 / T**2 + 12 * s / T**3, "k-", lw=3, alpha=0.3, label="closed form")
    ax.plot(r.times, r.knot_inputs[:, 0], "o", ms=4, label=f"collocation, cost {r.cost:.8f}")
    ax.set(xlabel="t", ylabel="u", title="minimum effort: ∫u² = 12/T³ = 1.5")
    ax.legend(fontsize=8)

    for column, (name, (result, open_loop, closed_loop)) in enumerate(swings.items()):
        ax = fig.add_subplot(grid[1, column])
        s = jnp.linspace(0.0, result.duration, 400)
        for i, color in zip(SWING_UPS[name][5], ("C0", "C1")):
            ax.plot(result.times, result.knot_states[:, i], ".", color=color, ms=4)
            ax.plot(s, np.asarray(closed_loop.state(s))[:, i], "-", color=color, label=f"x[{i}] TVLQR")
            ax.plot(s, np.asarray(open_loop.state(s))[:, i], "--", color=color, alpha=0.6, label=f"x[{i}] open loop")
        ax.set(xlabel="t", ylabel="angle", title=f"{name} swing-up: cost {result.cost:.1f}",
               ylim=(-2 * np.pi, 2 * np.pi))
        ax.legend(fontsize=7, loc="lower right")

    ax = fig.add_subplot(grid[2, :2])
    colors = plt.cm.viridis(np.linspace(0, 1, len(angles)))
    for k, color in enumerate(colors):
        ax.plot(np.asarray(batch.times[k]), np.asarray(batch.knot_states[k, :, 0]), color=color, lw=0.8)
    ax.axhline(np.pi, color="k", ls=":")
    ax.set(xlabel="t", ylabel="θ", title=f"{len(angles)} pendulum swing-ups, one vmapped iLQR (|u| ≤ 2)")
    ax = fig.add_subplot(grid[2, 2])
    ok = np.asarray(batch.success)
    ax.plot(np.asarray(angles)[ok], np.asarray(batch.cost)[ok], "o", ms=3, label="converged")
    ax.plot(np.asarray(angles)[~ok], np.asarray(batch.cost)[~ok], "x", color="C3", label="not converged")
    ax.legend(fontsize=8)
    ax.set(xlabel="initial angle", ylabel="∫u² dt", title="optimal cost by initial angle")
    save(fig, out, "trajectory_optimization.png")


if __name__ == "__main__":
    run(main, __doc__)
