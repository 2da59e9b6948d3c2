"""Cubes dropped at random onto the floor in float32: how many land and come to rest.

A batch of 1-kg cubes of 10 cm (Drake's default contact: k = 1e6 N/m per geometry, d = 50
s/m, mu = 1, stiction tolerance 1e-4 m/s), each dropped from a height of 0.1-1 m with a
random orientation, sliding at 0-1 m/s and spinning at up to 2 rad/s, simulated for 1.5 s
by `jd.simulate` (the default solver for contact, float32's default tolerances) under
`jax.vmap`. A cube landing while it slides or tumbles has corners that go from sliding to
sticking under kilonewtons, where float64 takes steps of ~2e-9 s, below float32's spacing of
t (3e-8 s at t = 0.3 s): `simulate` carries float32 time as a pair for them
(`_controller.advance`). Reported: the statuses, how many rest flat at the closed-form height
0.05 - m g / (4 k / 2) (within 2e-6 m, at rest within 1e-3), first call and warm time, and
the steps of the slowest member (the vmapped loop runs until it ends).

    python benchmarks/float32_landing_benchmark.py [--batch 256] [--repeats 1]

Results: benchmarks/RESULTS.md, "Float32 time as a pair".
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import machine_line  # benchmarks/_common.py

CUBE = """<robot name="cube"><link name="cube">
  <inertial><mass value="1.0"/><inertia ixx="0.001667" iyy="0.001667" izz="0.001667" ixy="0" ixz="0" iyz="0"/></inertial>
  <collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link></robot>"""
REST_HEIGHT = 0.05 - 9.81 / (4 * 5e5)   # four corners on the floor, the two 1e6 N/m in series


def starts(batch, seed=0):
    """Random drops: [q (position, quaternion w x y z); v (linear, angular)], float32."""
    rng = np.random.default_rng(seed)
    quaternion = rng.normal(size=(batch, 4))
    quaternion /= np.linalg.norm(quaternion, axis=1, keepdims=True)
    height = rng.uniform(0.1, 1.0, batch) + 0.0866   # the half-diagonal: no corner starts inside the floor
    slide = rng.uniform(0.0, 1.0, batch)[:, None] * np.array([1.0, 0.0, 0.0])
    spin = rng.uniform(-2.0, 2.0, (batch, 3))
    q = np.concatenate([np.zeros((batch, 2)), height[:, None], quaternion], axis=1)
    return np.concatenate([q, slide, spin], axis=1).astype(np.float32)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--duration", type=float, default=1.5)
    parser.add_argument("--max-steps", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    print(machine_line())
    folder = pathlib.Path(tempfile.mkdtemp())
    (folder / "cube.urdf").write_text(CUBE)
    cube = jd.RigidBodySystem.from_urdf(folder / "cube.urdf", floating_base=True, contact=True).with_ground()
    x0 = jnp.asarray(starts(args.batch))

    @jax.jit
    def drop(x0):
        traj = jax.vmap(lambda x: jd.simulate(cube, (0.0, args.duration), x, max_steps=args.max_steps,
                                              throw=False, dense=False))(x0)
        return traj.status, traj.t_final, traj.final_state, traj.num_accepted_steps, traj.num_rejected_steps

    start = time.perf_counter()
    jax.block_until_ready(drop(x0))
    first = time.perf_counter() - start
    warm = np.inf
    for _ in range(args.repeats):
        start = time.perf_counter()
        status, t_final, x, accepted, rejected = jax.block_until_ready(drop(x0))
        warm = min(warm, time.perf_counter() - start)
    status, t_final, x = np.asarray(status), np.asarray(t_final), np.asarray(x, float)
    names = {int(s): jd.SimulationStatus(int(s)).name for s in np.unique(status)}
    counts = ", ".join(f"{names[s]} {int(np.sum(status == s))}" for s in sorted(names))
    resting = (np.abs(x[:, 2] - REST_HEIGHT) < 2e-6) & np.all(np.abs(x[:, 7:]) < 1e-3, axis=1)
    slowest = int(np.argmax(np.asarray(accepted) + np.asarray(rejected)))
    print(f"{args.batch} cubes, {args.duration} s, float32: {counts}; at rest on a face {int(resting.sum())}"
          f"; the first stopped at t = {', '.join(f'{t:.3f}' for t in np.sort(t_final[status != 0])[:8]) or '-'}")
    print(f"first call {first:.2f} s, warm {warm:.3f} s ({args.batch * args.duration / warm:,.0f} cube-seconds/s); "
          f"slowest member {int(accepted[slowest])} accepted + {int(rejected[slowest])} rejected steps; "
          f"median {int(np.median(accepted))} accepted")


if __name__ == "__main__":
    main()
