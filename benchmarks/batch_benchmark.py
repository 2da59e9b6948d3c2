"""`jd.run_batch`: pendulum simulations (10 s, rtol 1e-8, final state only) in chunks,
sharded over the local devices; against one `jit(vmap)` call on one device.

Rows: one call of the whole batch on one device (when it fits); run_batch on one device in
chunks (the chunking overhead); run_batch on every local device (the scaling); with --grid, fitted value iteration on one
device and on every local device. Times are the best of --repeats warm calls, their range in
brackets (the first call compiles; its time is printed too).

    python benchmarks/batch_benchmark.py [--batch 10000000] [--chunk 1000000] [--grid 1001]
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, failures, final_state_or_nan, machine_line  # benchmarks/_common.py

PENDULUM = jd.models.Pendulum()


def final_state(x0):
    return final_state_or_nan(jd.simulate(PENDULUM, (0.0, 10.0), x0, rtol=1e-8, atol=1e-8, dense=False, throw=False))


def timed(fn, repeats):
    """fn's result, its first call's time, and the best and the range of `repeats` warm calls."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    warm = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        warm.append(time.perf_counter() - start)
    if failures(out):
        raise SystemExit(f"{failures(out)} of {len(out)} simulations failed: no time is reported")
    return out, first, min(warm), f"[{min(warm):.3f}-{max(warm):.3f}]"


def main():
    parser = argument_parser(__doc__, repeats=3, gpu_help="unused: the rows use every local device", batch=10_000_000)
    parser.add_argument("--chunk", type=int, default=1_000_000, help="members per device per chunk")
    parser.add_argument("--single", type=int, default=2_000_000, help="batch of the one-call row")
    parser.add_argument("--grid", type=int, default=0, help="value-iteration rows on a grid of this many "
                        "points per axis (0: none)")
    args = parser.parse_args()
    print(machine_line(), f"| {jax.local_device_count()} devices")
    x0 = np.asarray(jax.random.uniform(jax.random.key(0), (args.batch, 2), minval=-3.0, maxval=3.0))
    one = jax.local_devices()[:1]

    single = jax.jit(jax.vmap(final_state))
    n = min(args.single, args.batch)
    _, first, second, spread = timed(lambda: single(jnp.asarray(x0[:n])), args.repeats)
    print(f"one jit(vmap) call, {n:>9d} members, 1 device : {second:8.3f} s {spread} ({n / second:12.0f} sims/s), "
          f"first {first:.2f} s")
    for devices in (one, jax.local_devices()):
        chunk = args.chunk * len(devices)
        out, first, second, spread = timed(lambda: jd.run_batch(final_state, x0, chunk_size=chunk, devices=devices,
                                                                progress=False), args.repeats)
        print(f"run_batch, {args.batch:>9d} members, {len(devices)} device{'s' if len(devices) > 1 else ' '}: "
              f"{second:8.3f} s {spread} ({args.batch / second:12.0f} sims/s), first {first:.2f} s, "
              f"chunks of {chunk}")
        if len(devices) == 1:
            reference = out
    np.testing.assert_array_equal(out, reference)  # the sharded run equals the one-device run
    if args.grid:
        value_iteration_rows(args.grid, one, args.repeats)


def value_iteration_rows(points_per_axis, one, repeats):
    """Fitted value iteration of the pendulum swing-up on a points_per_axis^2 mesh, 9 inputs,
    transitions by RK4 over 0.05 s, 200 sweeps (tol=0): one device, then every local device."""
    from jaxdrake.planning import fitted_value_iteration

    grids = [np.linspace(0.0, 2 * np.pi, points_per_axis), np.linspace(-8.0, 8.0, points_per_axis)]

    def cost(x, u):
        return (x[0] - np.pi) ** 2 + x[1] ** 2 + u[0] ** 2

    results = []
    for devices in (one, jax.local_devices()):
        def solve():
            return fitted_value_iteration(PENDULUM, cost, grids, [np.linspace(-3.0, 3.0, 9)], 0.05, tol=0.0,
                                          max_iterations=200, periodic=[(0, 0.0, 2 * np.pi)], devices=devices).J
        J, first, second, spread = timed(solve, repeats)
        print(f"value iteration, {points_per_axis}^2 = {points_per_axis ** 2} points x 9 inputs, 200 sweeps, "
              f"{len(devices)} device{'s' if len(devices) > 1 else ' '}: {second:8.3f} s {spread}, first {first:.2f} s")
        results.append(np.asarray(J))
    np.testing.assert_array_equal(results[0], results[-1])


if __name__ == "__main__":
    main()
