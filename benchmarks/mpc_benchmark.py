"""Model-predictive control: jaxdrake's `linear_mpc` step against OSQP called from Python on the
same QP, a vmapped batch of steps, and an MPPI step.

Problem: the cart-pole (jd.models.CartPole(), mc = 10, mp = 1) linearized upright and held
over 20 ms (ZOH), N = 20 steps, Q = diag(10, 10, 1, 1), R = 0.01, |u| <= 30 N (active during
the first steps of the run below). (1) Warm step: the closed loop of the discretised model from
x = top + (0.5 m, 0.25 rad), 200 steps (the bound active in the first ~37); each step is one `controller.update` (ADMM from the
previous plan shifted, polish), jitted, called from Python — against OSQP 1.x (set up once,
then per step `update(q, l, u)` and `solve()`, warm-started, eps 1e-6, polished). The plans are
compared step by step. (2) Batch: 4096 states around the top, one vmapped update. (3) MPPI,
1024 samples x 50 steps of the nonlinear cart-pole (one RK4 step per 20 ms), one update, with
the rigid-body model and with the closed-form equations of the same cart-pole.
Best of repeats for (2) and (3); medians per step for (1); first-call (compile) times printed.

    python benchmarks/mpc_benchmark.py [--batch 4096]
    python benchmarks/mpc_benchmark.py --gpu --batch 4096 [--float32]   # accelerator: JAX rows only
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, best_time, machine_line  # benchmarks/_common.py

PERIOD, N, U_MAX = 0.02, 20, 30.0
TOP = np.array([0.0, np.pi, 0.0, 0.0])
Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.array([[0.01]])


def controller_and_model():
    plant = jd.models.CartPole()
    # the top is an equilibrium; in float32, sin(pi) leaves a residual of 2e-6 > linearize's 1e-6
    controller = jd.control.linear_mpc(plant, Q, R, N * PERIOD, period=PERIOD, x0=TOP, input_lower=-U_MAX,
                                       input_upper=U_MAX, check_equilibrium=False)
    lin = jd.linearize(plant, TOP, np.zeros(1), check_equilibrium=False)
    Ad, Bd = jd.control.zero_order_hold(lin.A, lin.B, PERIOD)
    return plant, controller, np.asarray(Ad), np.asarray(Bd)


def warm_steps(controller, Ad, Bd, steps=200):
    """Our closed loop, one jitted update per step from Python: (per-step seconds, states, plans)."""
    update = jax.jit(controller.update)
    x, memory = TOP + np.array([0.5, 0.25, 0.0, 0.0]), controller.initial_state()
    start = time.perf_counter()
    jax.block_until_ready(update(0.0, memory, jnp.asarray(x)))
    compile_s = time.perf_counter() - start
    times, states, plans = [], [], []
    for _ in range(steps):
        xj = jnp.asarray(x)
        start = time.perf_counter()
        memory = jax.block_until_ready(update(0.0, memory, xj))
        times.append(time.perf_counter() - start)
        states.append(x)
        plans.append(np.asarray(controller.plan(memory)).reshape(-1))
        x = TOP + Ad @ (x - TOP) + Bd @ np.asarray(memory[:1])
    return np.array(times), np.array(states), np.array(plans), compile_s


def osqp_steps(controller, states):
    """OSQP on the same QPs (the states our loop visited), warm-started: (per-step seconds, plans)."""
    import osqp
    import scipy.sparse as sp

    P, q, A, l, u = (np.asarray(v) for v in controller.qp(states[0]))
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(np.triu(P)), q, sp.csc_matrix(A), l, u, eps_abs=1e-6, eps_rel=1e-6,
                 polishing=True, warm_starting=True, verbose=False)
    times, plans = [], []
    for x in states:
        _, q, _, l, u = (np.asarray(v) for v in controller.qp(x))
        start = time.perf_counter()
        solver.update(q=q, l=l, u=u)
        result = solver.solve(raise_error=False)
        times.append(time.perf_counter() - start)
        plans.append(result.x)
    return np.array(times), np.array(plans)


def batch(controller, size, repeats):
    """One vmapped update of `size` states around the top: (best seconds, compile seconds, solved)."""
    key = jax.random.key(1)
    states = jnp.asarray(TOP) + jax.random.uniform(key, (size, 4), minval=-1, maxval=1) * jnp.array([0.5, 0.2, 0.5, 0.5])
    memory = jnp.broadcast_to(controller.initial_state(), (size, controller.num_states))
    update = jax.jit(jax.vmap(controller.update, in_axes=(None, 0, 0)))
    start = time.perf_counter()
    memory = jax.block_until_ready(update(0.0, memory, states))  # cold, and the warm start of the timed ones
    compile_s = time.perf_counter() - start
    seconds = best_time(lambda: jax.block_until_ready(update(0.0, memory, states)), repeats)
    solved = int(np.sum(np.asarray(controller.status(update(0.0, memory, states))) == 0))
    return seconds, compile_s, solved


class ClosedFormCartPole(jd.System):
    """The notes' cart-pole equations (Underactuated ch. 3, mc = 10, mp = 1, l = 0.5), state
    [x, theta, xdot, thetadot]: the same dynamics as `jd.models.CartPole()` (checked in `main`)
    in a few dozen operations instead of the rigid-body algorithms, to show what the model
    costs MPPI's rollouts."""

    def __init__(self):
        super().__init__(num_continuous_states=4, num_inputs=1, time_invariant=True)

    def dynamics(self, t, x, u):
        mc, mp, l, g = 10.0, 1.0, 0.5, 9.81
        s, c = jnp.sin(x[1]), jnp.cos(x[1])
        d = mc + mp * s ** 2
        xdd = (u[0] + mp * s * (l * x[3] ** 2 + g * c)) / d
        tdd = (-u[0] * c - mp * l * x[3] ** 2 * c * s - (mc + mp) * g * s) / (l * d)
        return jnp.stack([x[2], x[3], xdd, tdd])


def mppi_step(plant, repeats, samples=1024, steps=50):
    def cost(t, x, u):
        return 10 * (x[1] - jnp.pi) ** 2 + x[0] ** 2 + 0.1 * (x[2] ** 2 + x[3] ** 2) + 0.001 * u[0] ** 2

    controller = jd.control.mppi(plant, cost, steps * PERIOD, period=PERIOD, key=jax.random.key(0),
                                 num_samples=samples, noise_std=10.0, temperature=1.0, input_lower=-U_MAX,
                                 input_upper=U_MAX)
    update = jax.jit(controller.update)
    x, memory = jnp.asarray(TOP + np.array([0.1, 0.05, 0.0, 0.0])), controller.initial_state()
    start = time.perf_counter()
    memory = jax.block_until_ready(update(0.0, memory, x))
    compile_s = time.perf_counter() - start
    return best_time(lambda: jax.block_until_ready(update(PERIOD, memory, x)), repeats), compile_s


def main():
    parser = argument_parser(__doc__, repeats=20, batch=4096, gpu_help="JAX rows only (no OSQP)")
    parser.add_argument("--float32", action="store_true", help="JAX in float32 (QP tolerance 1e-4)")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", not args.float32)
    print(machine_line())
    plant, controller, Ad, Bd = controller_and_model()
    times, states, plans, compile_s = warm_steps(controller, Ad, Bd)
    print(f"cart-pole linear MPC, N = {N}, |u| <= {U_MAX}: first call {compile_s:.1f} s")
    active = int(np.sum(np.isclose(np.abs(plans), U_MAX).any(axis=1)))
    print(f"  jaxdrake warm step (jitted update from Python): median {np.median(times) * 1e3:.3f} ms, "
          f"p90 {np.percentile(times, 90) * 1e3:.3f} ms over {len(times)} steps ({active} with a bound active; "
          f"final distance from the top {np.max(np.abs(states[-1] - TOP)):.2g})")
    if not args.gpu:
        osqp_times, osqp_plans = osqp_steps(controller, states)
        print(f"  OSQP warm step (update + solve from Python): median {np.median(osqp_times) * 1e3:.3f} ms, "
              f"p90 {np.percentile(osqp_times, 90) * 1e3:.3f} ms; ratio OSQP / ours "
              f"{np.median(osqp_times) / np.median(times):.2f}x; largest plan difference "
              f"{np.max(np.abs(osqp_plans - plans)):.1e}")
    seconds, compile_s, solved = batch(controller, args.batch, args.repeats)
    print(f"  batch of {args.batch} (vmap): {seconds * 1e3:.2f} ms = {args.batch / seconds:.3g} solves/s "
          f"({solved} solved; first call {compile_s:.1f} s)")
    closed_form = ClosedFormCartPole()
    x, u = jnp.asarray(TOP) + jnp.array([0.1, 0.3, -0.2, 0.5]), jnp.array([3.0])
    np.testing.assert_allclose(closed_form.dynamics(0.0, x, u), plant.dynamics(0.0, x, u), rtol=1e-5, atol=1e-5)
    for label, model in (("jd.models.CartPole (rigid-body algorithms)", plant), ("closed-form cart-pole", closed_form)):
        seconds, compile_s = mppi_step(model, args.repeats)
        print(f"MPPI, 1024 samples x 50 steps, {label}: {seconds * 1e3:.2f} ms per update = "
              f"{1 / seconds:.0f} Hz (first call {compile_s:.1f} s)")


if __name__ == "__main__":
    main()
