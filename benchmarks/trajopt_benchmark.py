"""Trajectory optimization: acrobot and cart-pole swing-ups against Drake's DirectCollocation, and
the batched iLQR's throughput.

Same problem on both sides: N knots over a fixed duration T (Drake: every time step fixed to
T/(N-1)), from hanging at rest to upright at rest, |u| <= limit, min integral of u^2, initial
guess the straight line in state space with zero input, IPOPT (Drake's wheel ships it) with
its limited-memory Hessian as Drake runs it, and ours also with the exact sparse Hessian. The
running-cost quadratures differ (Drake: trapezoid on the knots; ours: Simpson on the cubic), so
the costs agree to discretization error, not to the last digit. Times are warm (the second
solve; our first solve also compiles, reported separately).

Batched: pendulum swing-ups (100 steps of 0.05 s, |u| <= 2) from a spread of initial angles,
one `jax.vmap`ped `trajopt.ilqr` program; problems per second, warm. With --chunk C, the same
batch also through `jd.run_batch(chunk_size=C)` (the chunking overhead against one call).

Run:  python benchmarks/trajopt_benchmark.py [--batch B] [--chunk C] [--gpu]
"""

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, machine_line
from jaxdrake import trajopt
from jaxdrake.models._rigid import URDF_DIR

PROBLEMS = {"acrobot": ([np.pi, 0, 0, 0], 10.0, 5.0), "cart-pole": ([0, np.pi, 0, 0], 50.0, 3.0)}
N = 101


def ours(name, hessian):
    plant = jd.models.Acrobot() if name == "acrobot" else jd.models.CartPole()
    goal, limit, T = PROBLEMS[name]
    prog = trajopt.DirectCollocation(plant, N, duration=T).add_input_bounds(-limit, limit)
    prog.set_initial_state(np.zeros(4)).set_final_state(goal).add_running_cost(lambda t, x, u: u @ u)
    start = time.perf_counter()
    prog.solve(hessian=hessian)
    first = time.perf_counter() - start
    result = prog.solve(hessian=hessian)
    return result, first


def drake(name):
    from pydrake.all import (DirectCollocation, IpoptSolver, MultibodyPlant, Parser,
                             PiecewisePolynomial)
    from pydrake.examples import AcrobotPlant

    goal, limit, T = PROBLEMS[name]
    if name == "acrobot":
        system = AcrobotPlant()
        context = system.CreateDefaultContext()
        port = system.get_input_port(0).get_index()
    else:
        system = MultibodyPlant(0.0)
        Parser(system).AddModels(str(URDF_DIR / "cartpole.urdf"))
        system.WeldFrames(system.world_frame(), system.GetFrameByName("world_rail"))
        system.Finalize()
        context = system.CreateDefaultContext()
        port = system.get_actuation_input_port().get_index()
    h = T / (N - 1)
    prog = DirectCollocation(system, context, N, h, h, input_port_index=port)
    prog.AddEqualTimeIntervalsConstraints()
    u = prog.input()
    prog.AddConstraintToAllKnotPoints(u[0] <= limit)
    prog.AddConstraintToAllKnotPoints(-limit <= u[0])
    prog.prog().AddBoundingBoxConstraint(np.zeros(4), np.zeros(4), prog.initial_state())
    prog.prog().AddBoundingBoxConstraint(goal, goal, prog.final_state())
    prog.AddRunningCost(u[0] ** 2)
    guess = PiecewisePolynomial.FirstOrderHold([0.0, T], np.column_stack([np.zeros(4), goal]))
    prog.SetInitialTrajectory(PiecewisePolynomial(), guess)
    solver = IpoptSolver()
    times, result = [], None
    for _ in range(2):
        start = time.perf_counter()
        result = solver.Solve(prog.prog())
        times.append(time.perf_counter() - start)
    iterations = result.get_solver_details().iteration_count if hasattr(result.get_solver_details(),
                                                                         "iteration_count") else -1
    return result.is_success(), result.get_optimal_cost(), times[-1], iterations


def batched(batch, chunk=None):
    """Warm and first times of one vmapped call, or of `jd.run_batch` in chunks of `chunk`."""
    plant = jd.models.Pendulum(input_limits=(-2.0, 2.0))

    def solve(angle):
        return trajopt.ilqr(plant, jnp.stack([angle, 0.0 * angle]), jnp.zeros((100, 1), angle.dtype), 0.05,
                            lambda t, x, u: u @ u, final_state=jnp.array([np.pi, 0.0]), max_iterations=1000,
                            constraint_tol=1e-5)

    angles = jnp.linspace(-0.5, 0.5, batch)
    if chunk is None:
        run = jax.jit(jax.vmap(solve))
    else:
        def run(members):
            return jd.run_batch(solve, members, chunk_size=chunk)
    start = time.perf_counter()
    jax.block_until_ready(run(angles))
    first = time.perf_counter() - start
    start = time.perf_counter()
    results = jax.block_until_ready(run(angles))
    warm = time.perf_counter() - start
    return warm, first, int(results.success.sum()), int(results.iterations.max())


def main():
    parser = argument_parser(__doc__, repeats=1, gpu_help="batched iLQR only (no Drake), on the GPU", batch=64)
    parser.add_argument("--chunk", type=int, help="also run the batch through jd.run_batch in chunks of this size")
    args = parser.parse_args()
    if not args.gpu:
        jax.config.update("jax_enable_x64", True)
    print(machine_line())
    if not args.gpu:
        print(f"| problem (N = {N}) | solver | success | cost | iterations | warm time | ours/Drake |")
        print("|---|---|---|---|---|---|---|")
        for name in PROBLEMS:
            ok, cost, drake_time, drake_iterations = drake(name)
            print(f"| {name} | Drake DirectCollocation + IPOPT | {ok} | {cost:.4f} | {drake_iterations} | "
                  f"{drake_time * 1e3:.0f} ms | 1 |", flush=True)
            for hessian in ("limited-memory", "exact"):
                result, first = ours(name, hessian)
                print(f"| {name} | jaxdrake + IPOPT ({hessian}) | {result.success} | {result.cost:.4f} | "
                      f"{result.iterations} | {result.solve_time * 1e3:.0f} ms (first solve {first:.1f} s) | "
                      f"{result.solve_time / drake_time:.2f} |", flush=True)
    for chunk in (None,) if args.chunk is None else (None, args.chunk):
        warm, first, converged, iterations = batched(args.batch, chunk)
        how = "one vmapped call" if chunk is None else f"jd.run_batch, chunks of {chunk}"
        print(f"batched iLQR ({how}): {args.batch} pendulum swing-ups in {warm * 1e3:.0f} ms warm "
              f"({first:.1f} s first), {args.batch / warm:.0f} problems/s, {converged} converged, "
              f"up to {iterations} iterations")


if __name__ == "__main__":
    main()
