"""Solo-12 dropped on the floor (0.5 s): jaxdrake's contact plant against Drake's continuous plant.

Both sides: solo12.urdf (example-robot-data, its mesh collisions left out), spheres at the feet
(2 cm), the knees (2 cm) and the base's four corners (3 cm), a half-space floor, Drake's default contact properties and stiction
tolerance (1e-4 m/s), no input. Each side is error-controlled at the given accuracies; the error
is the largest difference of the final state from jaxdrake at rtol 1e-10 (which equals Drake's
plant to 1e-10 in its time derivatives: tests/test_contact.py). First call (compile) and warm
times are printed separately; warm times (both sides) are the best of three runs.

    python benchmarks/contact_benchmark.py [--accuracies 1e-4 1e-6]
"""

import argparse
import importlib.metadata
import pathlib
import re
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import machine_line, solver_named

T_FINAL = 0.5
REPEATS = 3
SPHERES = ([(f"{leg}_FOOT", (0.0, 0.0, 0.0), 0.02) for leg in ("FL", "FR", "HL", "HR")]
           + [(f"{leg}_LOWER_LEG", (0.0, 0.0, 0.0), 0.02) for leg in ("FL", "FR", "HL", "HR")]
           + [("base_link", (x, y, 0.0), 0.03) for x in (-0.19, 0.19) for y in (-0.1, 0.1)])


def solo_without_mesh_collisions(folder, source=None):
    """solo12.urdf (example-robot-data's, or the file `source`) without its <collision> and
    <visual> elements (the meshes), written into `folder`."""
    if source is None:
        root = pathlib.Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
            "cmeel.prefix/share/example-robot-data/robots")))
        source = root / "solo_description/robots/solo12.urdf"
    text = pathlib.Path(source).read_text()
    text = re.sub(r"<collision>.*?</collision>", "", text, flags=re.S)
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)
    path = pathlib.Path(folder) / "solo12_spheres.urdf"
    path.write_text(text)
    return path


def ours(path):
    plant = jd.RigidBodySystem.from_urdf(path, floating_base=True, joint_limits=False, effort_limits=False)
    for i, (link, position, radius) in enumerate(SPHERES):
        plant = plant.with_collision_geometry(link, jd.geometry.Sphere(radius), translation=position, name=f"sphere{i}")
    return plant.with_ground()


def initial_state(plant):
    q = np.array(plant.tree.neutral_configuration())
    names = plant.tree.joint_names
    for name, angle in (("HFE", 0.8), ("KFE", -1.6)):
        for leg in ("FL", "FR", "HL", "HR"):
            joint = f"{leg}_{name}"
            q[plant.tree.q_starts[names.index(joint)]] = angle if leg[0] == "F" else -angle
    q[2] = 0.3
    return np.concatenate([q, np.zeros(plant.tree.nv)])


def drake(path, x0, integrator, accuracy):
    """(seconds, steps, final state in our coordinates) of Drake's simulation with `integrator`
    (a name for ResetIntegratorFromFlags) at target `accuracy`."""
    from pydrake.all import (AddMultibodyPlantSceneGraph, ContactModel, DiagramBuilder, HalfSpace, Parser,
                             ProximityProperties, ResetIntegratorFromFlags, RigidTransform, Simulator, Sphere)
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, 0.0)
    Parser(plant).AddModels(str(path))
    props = ProximityProperties()  # SceneGraph's defaults fill it in: as jaxdrake's defaults
    for i, (link, position, radius) in enumerate(SPHERES):
        plant.RegisterCollisionGeometry(plant.GetBodyByName(link), RigidTransform(position), Sphere(radius),
                                        f"sphere{i}", props)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(), HalfSpace(), "ground", props)
    plant.set_contact_model(ContactModel.kPoint)
    plant.Finalize()
    diagram = builder.Build()
    import sys
    sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "tests"))
    from _drake_contact import StateMap
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyContextFromRoot(context)
    state_map = StateMap(plant, ours(path))
    qd, vd = state_map.to_drake(x0)
    plant.SetPositions(plant_context, qd)
    plant.SetVelocities(plant_context, vd)
    ResetIntegratorFromFlags(simulator, integrator, 0.01)
    simulator.get_mutable_integrator().set_target_accuracy(accuracy)
    start = time.perf_counter()
    simulator.Initialize()
    simulator.AdvanceTo(T_FINAL)
    elapsed = time.perf_counter() - start
    steps = simulator.get_integrator().get_num_steps_taken()
    return elapsed, steps, state_map.from_drake(plant.GetPositions(plant_context), plant.GetVelocities(plant_context))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ours", nargs="+", default=["rosenbrock23/stiff:3e-3", "rosenbrock23/stiff:1e-3",
                                                      "rosenbrock23/stiff:1e-5", "rosenbrock23:1e-3", "rosenbrock23:1e-5",
                                                      "dopri5:1e-4", "dopri5:1e-6"],
                        help="solver:rtol (atol = rtol / 100); rosenbrock23/stiff: Rosenbrock23(jacobian='stiff')")
    parser.add_argument("--drake", nargs="+", default=["runge_kutta3:1e-4", "runge_kutta3:1e-6", "runge_kutta3:1e-8",
                                                       "radau3:1e-4", "radau3:1e-6"],
                        help="integrator:target accuracy (max step 0.01 s)")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)   # here, not at import: the GPU benchmark imports the scene
    print(machine_line())
    with tempfile.TemporaryDirectory() as folder:
        path = solo_without_mesh_collisions(folder)
        plant = ours(path)
        x0 = jnp.asarray(initial_state(plant))
        reference = jd.simulate(plant, (0.0, T_FINAL), x0, solver="dopri5", rtol=1e-10, atol=1e-12,
                                max_steps=200000, dense=False).final_state
        print(f"reference: jaxdrake dopri5 rtol 1e-10 (equal to Drake's RK5 at 1e-8 within 1e-7); base height at "
              f"{T_FINAL} s: {float(reference[2]):.4f} m; error = max |x(0.5) - reference|")
        print("| simulator | setting | first call (s) | run (s) | error |")
        print("|---|---|---|---|---|")
        for spec in args.ours:
            name, rtol = spec.split(":")
            solver = solver_named(name)
            run = lambda: jd.simulate(plant, (0.0, T_FINAL), x0, solver=solver, rtol=float(rtol),  # noqa: E731
                                      atol=float(rtol) * 1e-2, max_steps=200000, dense=False)
            start = time.perf_counter()
            run().final_state.block_until_ready()
            first = time.perf_counter() - start
            warm = np.inf
            for _ in range(REPEATS):   # the best of a few: the shared machine's noise only adds time
                start = time.perf_counter()
                traj = run()
                traj.final_state.block_until_ready()
                warm = min(warm, time.perf_counter() - start)
            error = float(jnp.max(jnp.abs(traj.final_state - reference)))
            steps = int(traj.num_accepted_steps) + int(traj.num_rejected_steps)
            print(f"| jaxdrake | {name} rtol {rtol} ({steps} steps) | {first:.2f} | {warm:.3f} | {error:.1e} |", flush=True)
        for spec in args.drake:
            integrator, accuracy = spec.split(":")
            runs = [drake(path, np.asarray(x0), integrator, float(accuracy)) for _ in range(REPEATS)]
            seconds, steps, final = min(runs, key=lambda run: run[0])
            error = float(np.max(np.abs(final - np.asarray(reference))))
            print(f"| Drake | {integrator} accuracy {accuracy} ({steps} steps) | - | {seconds:.2f} | {error:.1e} |",
                  flush=True)


if __name__ == "__main__":
    main()
