"""Solo-12 with its own collision meshes (example-robot-data), dropped on the floor for 0.3 s:
the hull-against-hull narrow phase with and without its broad phase (RESULTS.md, "A robot's
own meshes").

`from_urdf(solo12.urdf, floating_base=True, contact=True, mesh_hulls=True,
max_hull_vertices=N)` and `with_ground()`, the neutral configuration at a base height of
0.45 m, `simulate`'s defaults (max_steps raised). "every pair in one vmap" sets
`CULLED_EDGE_PAIRS` past any hull, as before the broad phase. Each variant in its own process
(the first call is the compile): first call and one warm run.

    python benchmarks/mesh_contact_benchmark.py [--vertices 32] [--variants broad vmap]
"""

import argparse
import importlib.metadata
import pathlib
import subprocess
import sys
import time

T_FINAL = 0.3


def drop(vertices: int, variant: str):
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import jaxdrake as jd
    from jaxdrake.multibody import _contact

    if variant == "vmap":
        _contact.CULLED_EDGE_PAIRS = 10 ** 12
    root = pathlib.Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")))
    plant = jd.RigidBodySystem.from_urdf(root / "solo_description/robots/solo12.urdf", floating_base=True,
                                         contact=True, mesh_hulls=True, max_hull_vertices=vertices,
                                         package_map={"example-robot-data": str(root.parent)}).with_ground()
    x0 = plant.initial_state().at[2].set(0.45)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        traj = jd.simulate(plant, (0.0, T_FINAL), x0, max_steps=100_000)
        traj.final_state.block_until_ready()
        times.append(time.perf_counter() - start)
    steps = f"{int(traj.num_accepted_steps)} + {int(traj.num_rejected_steps)}"
    print(f"{variant:6s} {vertices}-vertex hulls: {steps} steps, first call {times[0]:.1f} s, warm {times[1]:.1f} s, "
          f"base at {np.asarray(traj.final_state[:3])}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vertices", type=int, default=32, help="max_hull_vertices")
    parser.add_argument("--variants", nargs="+", default=["broad", "vmap"], choices=["broad", "vmap"])
    parser.add_argument("--one", help=argparse.SUPPRESS)   # a variant run in this process
    args = parser.parse_args()
    if args.one:
        drop(args.vertices, args.one)
        return
    import jax

    jax.config.update("jax_enable_x64", True)   # as the runs (for the machine line)
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    from _common import machine_line
    print(machine_line())
    for variant in args.variants:
        subprocess.run([sys.executable, __file__, "--vertices", str(args.vertices), "--one", variant], check=True)


if __name__ == "__main__":
    main()
