"""One simulation called from Python on a machine whose default device is a GPU: where
`simulate` runs it by default (the host CPU, `simulate`'s `device=None`) against the same
call forced onto the GPU (`device=jax.devices("gpu")[0]`), warm, median of repeats; the
pendulum (issue 44: one simulation on a GPU within 2x the host's time) and a 9-dof arm.

    python benchmarks/placement_benchmark.py [--repeats 20]
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

import jaxdrake as jd
from _common import argument_parser, machine_line, median_time  # benchmarks/_common.py


def main():
    parser = argument_parser(__doc__, repeats=20, gpu_help="unused")
    args = parser.parse_args()
    print(machine_line())
    accelerators = [d for d in jax.devices() if d.platform != "cpu"]
    if not accelerators:
        print("no accelerator: nothing to compare")
        return
    cases = {"pendulum, 10 s": (jd.models.Pendulum(), jnp.array([1.0, 0.0]), 10.0),
             "double pendulum, 10 s": (jd.models.DoublePendulum(), jnp.array([1.0, 0.5, 0.0, 0.0]), 10.0)}
    print(f"{'case':24s} {'default (host)':>15s} {'on the GPU':>11s} {'GPU / host':>11s}")
    for name, (system, x0, tf) in cases.items():
        host = median_time(lambda: jd.simulate(system, (0.0, tf), x0).final_state, args.repeats)
        gpu = median_time(lambda: jd.simulate(system, (0.0, tf), x0, device=accelerators[0]).final_state,
                          args.repeats)
        print(f"{name:24s} {host * 1e3:13.2f}ms {gpu * 1e3:9.2f}ms {gpu / host:10.1f}x", flush=True)


if __name__ == "__main__":
    main()
