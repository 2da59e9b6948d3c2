"""LQR solve time: jaxdrake's `control.lqr` against SciPy, python-control and Drake's
`LinearQuadraticRegulator` / `DiscreteTimeLinearQuadraticRegulator`, on the same matrices.

Problems: the acrobot (n = 4, m = 1) and the quadrotor (n = 12, m = 4) linearized about
upright / hover, continuous (CARE) and zero-order-hold discretized at dt = 0.01 s (DARE).
(1) Single: the Riccati solve and the gain for one (A, B, Q, R) — jaxdrake a jitted
`solve_*_are` + gain; the peers called from Python. (2) Batch: 10^4 parameter variations
(the acrobot's m2, the quadrotor's mass, uniform +-20%): jaxdrake linearizes (and
discretizes) and solves all of them in one vmapped program; the peers get each (A, B)
(computed by jaxdrake, not timed) in a Python loop. Every K is checked against SciPy's. Best
of repeats; first-call (compile) times printed next to the run times.

    python benchmarks/lqr_benchmark.py [--batch 10000]
    python benchmarks/lqr_benchmark.py --gpu --batch 10000          # accelerator: JAX rows only
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, best_time, machine_line  # benchmarks/_common.py

jax.config.update("jax_enable_x64", True)

DT = 0.01  # the discrete problems' sample time


def problems():
    """name -> (model(parameter), equilibrium(plant) -> (x0, u0), Q, R, nominal parameter)."""
    return {
        "acrobot (n=4, m=1)": (lambda p: jd.models.Acrobot(m2=p),
                               lambda plant: (jnp.array([jnp.pi, 0.0, 0.0, 0.0]), jnp.zeros(1)),
                               jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0])), jnp.eye(1), 1.0),
        "quadrotor (n=12, m=4)": (lambda p: jd.models.Quadrotor(m=p),
                                  lambda plant: (jnp.zeros(12), jnp.full(4, plant.m * plant.g / 4)),
                                  jnp.eye(12), jnp.eye(4), 0.775),
    }


def zero_order_hold(A, B):
    """(Ad, Bd) of x' = A x + B u held over DT: the exponential of [[A, B], [0, 0]] DT."""
    n, m = B.shape
    M = jax.scipy.linalg.expm(jnp.block([[A, B], [jnp.zeros((m, n + m))]]) * DT)
    return M[:n, :n], M[:n, n:]


def gain_and_cost(A, B, Q, R, discrete=False):
    if discrete:
        S = jd.control.solve_discrete_are(A, B, Q, R)
        return jnp.linalg.solve(R + B.T @ S @ B, B.T @ S @ A), S
    S = jd.control.solve_continuous_are(A, B, Q, R)
    return jnp.linalg.solve(R, B.T @ S), S


def peers(discrete):
    import control
    import scipy.linalg
    from pydrake.systems.controllers import DiscreteTimeLinearQuadraticRegulator, LinearQuadraticRegulator

    if discrete:
        def scipy_lqr(A, B, Q, R):
            S = scipy.linalg.solve_discrete_are(A, B, Q, R)
            return np.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)

        return {"SciPy solve_discrete_are": scipy_lqr,
                "python-control dlqr": lambda A, B, Q, R: control.dlqr(A, B, Q, R)[0],
                "Drake DiscreteTimeLQR": lambda A, B, Q, R: DiscreteTimeLinearQuadraticRegulator(A, B, Q, R)[0]}

    def scipy_lqr(A, B, Q, R):
        S = scipy.linalg.solve_continuous_are(A, B, Q, R)
        return np.linalg.solve(R, B.T @ S)

    return {"SciPy solve_continuous_are": scipy_lqr,
            "python-control lqr": lambda A, B, Q, R: control.lqr(A, B, Q, R)[0],
            "Drake LinearQuadraticRegulator": lambda A, B, Q, R: LinearQuadraticRegulator(A, B, Q, R)[0]}


def first_call_and_best(fn, args, repeats):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    return out, first, best_time(lambda: jax.block_until_ready(fn(*args)), repeats)


def main():
    parser = argument_parser(__doc__, repeats=5, batch=10_000,
                             gpu_help="JAX rows only (the peers run on the host)")
    args = parser.parse_args()
    print(machine_line())
    rng = np.random.default_rng(0)
    for name, (model, equilibrium, Q, R, nominal) in problems().items():
        params = nominal * rng.uniform(0.8, 1.2, args.batch)
        for discrete in (False, True):
            plant = model(nominal)
            lin = jd.linearize(plant, *equilibrium(plant))
            A, B = zero_order_hold(lin.A, lin.B) if discrete else (lin.A, lin.B)
            A, B, Qn, Rn = (np.asarray(M) for M in (A, B, Q, R))
            solve = jax.jit(gain_and_cost, static_argnums=4)
            _, compile_single, ours = first_call_and_best(solve, (A, B, Qn, Rn, discrete), 20 * args.repeats)

            def batch_lqr(p):
                plant = model(p)
                lin = jd.linearize(plant, *equilibrium(plant))
                A, B = zero_order_hold(lin.A, lin.B) if discrete else (lin.A, lin.B)
                return gain_and_cost(A, B, Q, R, discrete)[0], A, B

            (Ks, As, Bs), compile_batch, ours_batch = first_call_and_best(
                jax.jit(jax.vmap(batch_lqr)), (params,), args.repeats)
            label = f"{name}, {'DARE dt = 0.01' if discrete else 'CARE'}"
            print(f"\n{label}: jaxdrake single {ours * 1e6:8.1f} us (first call {compile_single:.2f} s); "
                  f"batch of {args.batch}: {ours_batch * 1e3:8.1f} ms (linearize + solve; first call "
                  f"{compile_batch:.2f} s)")
            if args.gpu:
                continue
            As, Bs, Ks = np.asarray(As), np.asarray(Bs), np.asarray(Ks)
            reference = next(iter(peers(discrete).values()))
            worst = max(np.max(np.abs(Ks[i] - reference(As[i], Bs[i], Qn, Rn))) / np.max(np.abs(Ks[i]))
                        for i in range(0, args.batch, max(1, args.batch // 100)))
            print(f"  max relative difference of K from SciPy's over the batch (every 100th): {worst:.1e}")
            for peer, fn in peers(discrete).items():
                single = best_time(lambda: fn(A, B, Qn, Rn), 20 * args.repeats)
                start = time.perf_counter()
                for i in range(args.batch):
                    fn(As[i], Bs[i], Qn, Rn)
                loop = time.perf_counter() - start
                print(f"  {peer:32s} single {single * 1e6:8.1f} us ({single / ours:5.2f}x ours); "
                      f"loop of {args.batch}: {loop * 1e3:8.1f} ms ({loop / ours_batch:6.1f}x ours)")


if __name__ == "__main__":
    main()
