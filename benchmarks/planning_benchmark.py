"""Planning: fitted value iteration against Drake's FittedValueIteration, and RRT against
OMPL's RRT, on the same problems in one process.

- Value iteration: the double integrator's minimum-time problem (the notes' ch. 9 example:
  9 inputs in [-1, 1], dt = 0.01, cost 1 outside x'x < 0.05, tol 1e-4) on meshes from
  31 x 51 up to 1001 x 1001 (10^6 states). jaxdrake: first call (compile + run) and second
  call; Drake: one call (C++). The max |J - J_drake| is printed as a check.
- RRT: the unit square with four circular obstacles (examples/rrt.py), step 0.05, goal bias
  0.05, goal tolerance 0.05; the fraction of seeds at the goal within k samples, for 1000
  seeds each (jaxdrake: one vmapped call; OMPL: its RRT, one seed after another, stopped by an
  iteration count), and plans per second.

    python benchmarks/planning_benchmark.py [--sizes 31x51 101x101 ...] [--seeds 1000]
    python benchmarks/planning_benchmark.py --gpu      # accelerator: jaxdrake rows only
"""

from __future__ import annotations

import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, machine_line  # benchmarks/_common.py
from jaxdrake.planning import fitted_value_iteration, rrt

CENTRES = np.array([[0.5, 0.5], [0.25, 0.75], [0.75, 0.25], [0.8, 0.7]])
RADII = np.array([0.2, 0.1, 0.1, 0.08])
START, GOAL = np.array([0.1, 0.1]), np.array([0.9, 0.9])
STEP, BIAS = 0.05, 0.05
U_GRID = np.linspace(-1, 1, 9)


def mesh(size):
    nq, nqd = (int(s) for s in size.split("x"))
    return np.linspace(-3, 3, nq), np.linspace(-3, 3, nqd)


def ours_value_iteration(qs, qds):
    run = lambda: fitted_value_iteration(jd.models.DoubleIntegrator(), _min_time, [qs, qds], [U_GRID], 0.01)
    start = time.perf_counter()
    result = run()
    jax.block_until_ready(result.J)
    first = time.perf_counter() - start
    start = time.perf_counter()
    result = run()
    jax.block_until_ready(result.J)
    return np.asarray(result.J), int(result.iterations), first, time.perf_counter() - start


def _min_time(x, u):
    return jnp.where(x @ x < 0.05, 0.0, 1.0)


def drake_value_iteration(qs, qds):
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.controllers import DynamicProgrammingOptions, FittedValueIteration
    from pydrake.systems.primitives import LinearSystem

    logging.getLogger("drake").setLevel(logging.WARNING)
    plant = LinearSystem(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.zeros((2, 1)))

    def cost(context):
        x = context.get_continuous_state_vector().CopyToVector()
        return 0.0 if x.dot(x) < 0.05 else 1.0

    options = DynamicProgrammingOptions()
    options.convergence_tol = 1e-4
    start = time.perf_counter()
    _, J = FittedValueIteration(Simulator(plant), cost, [set(qs), set(qds)], [set(U_GRID)], 0.01, options)
    return np.asarray(J).reshape(len(qs), len(qds), order="F"), time.perf_counter() - start


def ours_rrt(seeds):
    grow = jax.jit(jax.vmap(lambda k: rrt(START, GOAL, ([0.0, 0.0], [1.0, 1.0]), k, obstacles=(CENTRES, RADII),
                                          step_size=STEP, goal_bias=BIAS, goal_tolerance=STEP, max_nodes=600)))
    keys = jax.random.split(jax.random.key(0), seeds)
    start = time.perf_counter()
    trees = jax.block_until_ready(grow(keys))
    first = time.perf_counter() - start
    start = time.perf_counter()
    trees = jax.block_until_ready(grow(jax.random.split(jax.random.key(1), seeds)))
    second = time.perf_counter() - start
    return np.where(np.asarray(trees.success), np.asarray(trees.iterations), np.inf), first, second


def ompl_rrt(seeds, budget=600):
    from ompl import base as ob, geometric as og, util as ou

    ou.setLogLevel(ou.LOG_NONE)
    ou.RNG.setSeed(1)
    space = ob.RealVectorStateSpace(2)
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0.0)
    bounds.setHigh(1.0)
    space.setBounds(bounds)
    info = ob.SpaceInformation(space)
    info.setStateValidityChecker(lambda s: bool(np.all((CENTRES[:, 0] - s[0]) ** 2 + (CENTRES[:, 1] - s[1]) ** 2
                                                       > RADII ** 2)))
    info.setStateValidityCheckingResolution(0.002)  # of the space's extent: edges checked every ~3 mm
    info.setup()
    start_state, goal_state = space.allocState(), space.allocState()
    start_state[0], start_state[1] = START
    goal_state[0], goal_state[1] = GOAL
    samples, begin = [], time.perf_counter()
    for _ in range(seeds):
        problem = ob.ProblemDefinition(info)
        problem.setStartAndGoalStates(start_state, goal_state, STEP)
        planner = og.RRT(info)
        planner.setRange(STEP)
        planner.setGoalBias(BIAS)
        planner.setProblemDefinition(problem)
        planner.setup()
        count = [0]

        def stop():  # evaluated once per RRT iteration (one sample)
            count[0] += 1
            return count[0] > budget

        planner.solve(ob.PlannerTerminationCondition(stop))
        samples.append(count[0] if problem.hasExactSolution() else np.inf)
    return np.asarray(samples, float), time.perf_counter() - begin


def main():
    parser = argument_parser(__doc__, repeats=1, gpu_help="jaxdrake rows only (for the accelerator)")
    parser.add_argument("--sizes", nargs="*", default=["31x51", "101x101", "301x301", "1001x1001"])
    parser.add_argument("--seeds", type=int, default=1000)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(machine_line())
    print(f"{'value iteration':18s} {'states':>9s} {'sweeps':>7s} {'jaxdrake first':>15s} {'second':>9s} "
          f"{'Drake':>9s} {'Drake/ours':>11s} {'max |dJ|':>9s}")
    for size in args.sizes:
        qs, qds = mesh(size)
        J, sweeps, first, second = ours_value_iteration(qs, qds)
        line = f"{size:18s} {J.size:9d} {sweeps:7d} {first:14.2f}s {second:8.2f}s"
        if not args.gpu:
            J_drake, drake = drake_value_iteration(qs, qds)
            line += f" {drake:8.2f}s {drake / second:10.2f}x {np.max(np.abs(J - J_drake)):9.1e}"
        print(line, flush=True)

    samples, first, second = ours_rrt(args.seeds)
    print(f"\nRRT, {args.seeds} seeds: jaxdrake vmapped {first:.2f} s first call, {second:.3f} s next "
          f"({args.seeds / second:.0f} plans/s)")
    curves = {"jaxdrake": samples}
    if not args.gpu:
        ompl_samples, ompl_time = ompl_rrt(args.seeds)
        curves["OMPL RRT"] = ompl_samples
        print(f"OMPL RRT (C++ planner, Python validity checker), one seed at a time: {ompl_time:.2f} s "
              f"({args.seeds / ompl_time:.0f} plans/s)")
    print(f"{'samples k':>10s} " + " ".join(f"{name:>10s}" for name in curves))
    for k in (100, 150, 200, 300, 400, 600):
        print(f"{k:10d} " + " ".join(f"{np.mean(s <= k):10.3f}" for s in curves.values()))
    print("median samples " + " ".join(f"{np.median(s):10.0f}" for s in curves.values()))


if __name__ == "__main__":
    main()
