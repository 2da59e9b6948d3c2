"""Which solver a contact plant should get by default: dopri5 against the stiff W-method
(`Rosenbrock23(jacobian="stiff")`) and the exact-Jacobian Rosenbrock23, at `simulate`'s
default tolerances (rtol 1e-6, atol 1e-9, float64), on six scenes of everyday contact.

Each row: status, accepted + rejected steps, the first call (compile included, in this
process) and the warm run (best of 2), and the error: the largest difference of the final
state from Ros34PW2 (exact Jacobian) at rtol 1e-10.

    python benchmarks/contact_solver_benchmark.py [--scenes 0 1 ...] [--rtol 1e-6] [--solvers ...]
"""

import argparse
import pathlib
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import best_time, machine_line
from contact_benchmark import initial_state, ours, solo_without_mesh_collisions

DATA = pathlib.Path(__file__).resolve().parent.parent / "tests" / "data"
BOX_URDF = """<robot name="box"><link name="box"><inertial><mass value="0.5"/>
  <inertia ixx="0.0017" iyy="0.0017" izz="0.0017" ixy="0" ixz="0" iyz="0"/></inertial>
  <collision><geometry><box size="0.2 0.2 0.2"/></geometry></collision></link></robot>"""


def _box(folder):
    path = pathlib.Path(folder) / "box.urdf"
    path.write_text(BOX_URDF)
    return jd.RigidBodySystem.from_urdf(path, floating_base=True, contact=True)


def scenes(folder):
    """name -> (plant, x0, duration)."""
    tilt = np.array([0.3, 0.1, 0.2, 0.9])
    tilt /= np.linalg.norm(tilt)
    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground()
    box = _box(folder)
    solo = ours(solo_without_mesh_collisions(folder))
    floor = jd.multibody.ContactMaterial(point_contact_stiffness=1e5, hunt_crossley_dissipation=10.0, mu_static=1.0,
                                         mu_dynamic=0.8)
    hopper = jd.RigidBodySystem.from_urdf(DATA / "contact_hopper.urdf", floating_base=True, contact=True)
    hopper = hopper.with_collision_geometry("world", jd.geometry.Box(4.0, 4.0, 0.5), translation=(0, 0, -0.25),
                                            name="floor", material=floor)
    rng = np.random.default_rng(1)   # legs swinging, feet at Drake's stiction tolerance
    hopper_start = np.concatenate([[0, 0, 0.6, 0, 0, 0, 1], 0.3 * rng.normal(size=4), 0.5 * rng.normal(size=10)])
    return {
        "ball bouncing (0.5 m, 0.5 m/s sideways)": (ball, [0, 0, 0.5, 0, 0, 0, 1, 0.5, 0, 0, 0, 0, 0], 1.5),
        "box sliding (1 m/s)": (box.with_ground(), [0, 0, 0.1, 0, 0, 0, 1, 1.0, 0, 0, 0, 0, 0], 1.0),
        "box tumbling onto the floor": (box.with_ground(), [0, 0, 0.3, *tilt, 0, 0, 0, 1.0, 0.5, 0], 1.5),
        "box tumbling onto a table (box on box)": (
            box.with_collision_geometry("world", jd.geometry.Box(1.0, 1.0, 0.1), translation=(0, 0, -0.05), name="table"),
            [0, 0, 0.3, *tilt, 0, 0, 0, 1.0, 0.5, 0], 1.5),
        "Solo-12 dropped (0.5 s)": (solo, initial_state(solo), 0.5),
        "two-legged hopper landing (1 s)": (hopper, hopper_start, 1.0),
    }


SOLVERS = {"dopri5": "dopri5", "rosenbrock23/stiff": jd.simulation.Rosenbrock23(jacobian="stiff"),
           "rosenbrock23": "rosenbrock23", "ros34pw2/stiff": jd.simulation.Ros34PW2(jacobian="stiff")}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--atol", type=float, default=1e-9)
    parser.add_argument("--max-steps", type=int, default=400_000)
    parser.add_argument("--solvers", nargs="+", default=list(SOLVERS)[:3], choices=list(SOLVERS))
    parser.add_argument("--scenes", nargs="+", type=int, help="which scenes (0-5), all by default")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(machine_line())
    print(f"rtol {args.rtol}, atol {args.atol}")
    print("| scene | solver | status | steps (accepted + rejected) | first call (s) | warm (s) | error |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        chosen = list(scenes(folder).items())
        for name, (plant, x0, duration) in (chosen if args.scenes is None else [chosen[i] for i in args.scenes]):
            x0 = jnp.asarray(x0, float)
            reference = jd.simulate(plant, (0.0, duration), x0, solver=jd.simulation.Ros34PW2(), rtol=1e-10,
                                    atol=1e-12, max_steps=2_000_000, dense=False).final_state
            for solver in args.solvers:
                def run():
                    return jd.simulate(plant, (0.0, duration), x0, solver=SOLVERS[solver], rtol=args.rtol,
                                       atol=args.atol, max_steps=args.max_steps, dense=False, throw=False)
                start = time.perf_counter()
                traj = run()
                traj.final_state.block_until_ready()
                first = time.perf_counter() - start
                warm = best_time(lambda: run().final_state.block_until_ready(), 2)
                status = jd.simulation.SimulationStatus(int(traj.status)).name
                error = float(jnp.max(jnp.abs(traj.final_state - reference)))
                print(f"| {name} | {solver} | {status} | {int(traj.num_accepted_steps)} + {int(traj.num_rejected_steps)} "
                      f"| {first:.2f} | {warm:.3f} | {error:.1e} |", flush=True)


if __name__ == "__main__":
    main()
