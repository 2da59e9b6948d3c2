"""LQR solve time: jaxdrake's `control.lqr` against SciPy, python-control and Drake's
`LinearQuadraticRegulator`, on the same matrices.

Problems: the acrobot (n = 4, m = 1) and the quadrotor (n = 12, m = 4) linearized about
upright / hover. (1) Single: the Riccati solve and the gain for one (A, B, Q, R) — jaxdrake a
jitted `solve_continuous_are` + gain; the peers called from Python. (2) Batch: 10^4 parameter
variations (the acrobot's m2, the quadrotor's mass, uniform +-20%): jaxdrake linearizes and
solves all of them in one vmapped program; the peers get each (A, B) (linearized by jaxdrake,
not timed) in a Python loop. Every K is checked against SciPy's. Best of repeats; compile
times printed separately.

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


def gain_and_cost(A, B, Q, R):
    S = jd.control.solve_continuous_are(A, B, Q, R)
    return jnp.linalg.solve(R, B.T @ S), S


def peers():
    import control
    import scipy.linalg
    from pydrake.systems.controllers import LinearQuadraticRegulator

    def scipy_lqr(A, B, Q, R):
        S = scipy.linalg.solve_continuous_are(A, B, Q, R)
        return np.linalg.solve(R, B.T @ S)

    return {"SciPy solve_continuous_are": scipy_lqr,
            "python-control lqr": lambda A, B, Q, R: control.lqr(A, B, Q, R)[0],
            "Drake LinearQuadraticRegulator": lambda A, B, Q, R: LinearQuadraticRegulator(A, B, Q, R)[0]}


def main():
    parser = argument_parser(__doc__, repeats=5, batch=10_000,
                             gpu_help="JAX rows only (the peers run on the host)")
    args = parser.parse_args()
    print(machine_line())
    rng = np.random.default_rng(0)
    for name, (model, equilibrium, Q, R, nominal) in problems().items():
        plant = model(nominal)
        lin = jd.linearize(plant, *equilibrium(plant))
        A, B = np.asarray(lin.A), np.asarray(lin.B)
        Qn, Rn = np.asarray(Q), np.asarray(R)
        solve = jax.jit(gain_and_cost)
        start = time.perf_counter()
        jax.block_until_ready(solve(A, B, Q, R))
        compile_single = time.perf_counter() - start
        ours = best_time(lambda: jax.block_until_ready(solve(A, B, Q, R)), args.repeats)

        params = nominal * rng.uniform(0.8, 1.2, args.batch)

        def batch_lqr(p):
            plant = model(p)
            lin = jd.linearize(plant, *equilibrium(plant))
            return gain_and_cost(lin.A, lin.B, Q, R)[0], lin.A, lin.B

        batched = jax.jit(jax.vmap(batch_lqr))
        start = time.perf_counter()
        Ks, As, Bs = jax.block_until_ready(batched(params))
        compile_batch = time.perf_counter() - start
        ours_batch = best_time(lambda: jax.block_until_ready(batched(params)), args.repeats)
        print(f"\n{name}: jaxdrake single {ours * 1e6:8.1f} us (compile {compile_single:.2f} s); "
              f"batch of {args.batch}: {ours_batch * 1e3:8.1f} ms (linearize + solve; compile "
              f"{compile_batch:.2f} s)")
        if args.gpu:
            continue
        As, Bs, Ks = np.asarray(As), np.asarray(Bs), np.asarray(Ks)
        reference = peers()["SciPy solve_continuous_are"]
        worst = max(np.max(np.abs(Ks[i] - reference(As[i], Bs[i], Qn, Rn))) / np.max(np.abs(Ks[i]))
                    for i in range(0, args.batch, max(1, args.batch // 100)))
        print(f"  max relative difference of K from SciPy's over the batch (every 100th): {worst:.1e}")
        for peer, fn in peers().items():
            single = best_time(lambda: fn(A, B, Qn, Rn), args.repeats)
            start = time.perf_counter()
            for i in range(args.batch):
                fn(As[i], Bs[i], Qn, Rn)
            loop = time.perf_counter() - start
            print(f"  {peer:32s} single {single * 1e6:8.1f} us ({single / ours:5.2f}x ours); "
                  f"loop of {args.batch}: {loop * 1e3:8.1f} ms ({loop / ours_batch:6.1f}x ours)")


if __name__ == "__main__":
    main()
