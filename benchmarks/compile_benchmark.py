"""First-call cost: how long the first call of a jitted program takes (trace + compile + run),
set beside the compile of `jax.jit(system.dynamics)` alone, in one process.

For each system the first call of
- `jax.jit(system.dynamics)` (the reference: what the vector field alone costs),
- `simulate(system, (0, 1), x0)` with the default solver (Dormand-Prince 5(4)),
- `simulate(..., solver="euler", dt=1e-3)`,
- `jax.jit(jax.grad(loss))`, loss = |x(1)|^2 of a default simulation, w.r.t. x0,
and the second call of each (the compiled program kept); "first - second" is the first call
less one run, trace and compile alone (a stiff fall's run is most of a second). Targets (issue 17): default
simulate <= 1.5 x dynamics + 1 s; gradient <= 3 x dynamics + 1 s; the bouncing ball <= 1.5 s;
the pendulum <= 0.6 s.

    python benchmarks/compile_benchmark.py [--systems pendulum acrobot panda solo12 xarm7 go1 ball]
"""

from __future__ import annotations

import importlib.metadata
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, failures, final_state_or_nan, machine_line  # benchmarks/_common.py

jax.config.update("jax_enable_x64", True)


def robot(relative, **kwargs):
    root = importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")
    return jd.RigidBodySystem.from_urdf(pathlib.Path(root) / relative, **kwargs)


def systems():
    """name: (factory, x0 factory[, simulate's keyword arguments])."""
    def standing(plant):
        """At rest, the first three joints turned by 0.1 rad, every joint at least 5% of its
        range inside its limits (the Panda's joint 4 and fingers sit on theirs at zero)."""
        tree = plant.tree
        q = np.asarray(plant.initial_state())[: tree.nq].copy()
        q[:3] += 0.1
        lower, upper = np.asarray(tree.position_lower), np.asarray(tree.position_upper)
        margin = np.where(np.isfinite(upper - lower), 0.05 * (upper - lower), 0.0)
        return np.concatenate([np.clip(q, lower + margin, upper - margin), np.zeros(tree.nv)])

    def floating(plant):
        x0 = np.zeros(plant.num_states)
        x0[6] = 1.0  # unit quaternion qw
        x0[7:plant.tree.nq] = 0.1
        return x0

    return {
        "pendulum": (jd.models.Pendulum, lambda p: np.array([1.0, 0.0])),
        "acrobot": (jd.models.Acrobot, lambda p: np.array([0.1, 0.2, 0.0, 0.0])),
        "panda": (lambda: robot("panda_description/urdf/panda.urdf"), standing),
        "solo12": (lambda: robot("solo_description/robots/solo12.urdf", floating_base=True), floating),
        # strong joint damping on light links: stiff (4443 dopri5 steps for 1 s)
        "xarm7": (lambda: robot("xarm_description/urdf/xarm7.urdf"), standing, dict(max_steps=20000)),
        "go1": (lambda: robot("go1_description/urdf/go1.urdf", floating_base=True), floating),
        "ball": (jd.models.BouncingBall, lambda p: np.array([5.0, 0.0])),
    }


def first_and_second(fn):
    """(first call, second call) in seconds, or None when the result is not finite (a failed
    simulation: no time is reported for it)."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return None if failures(out) else (first, time.perf_counter() - start)


def measure(name, make, make_x0, options=None, autodiff=("reverse",)):
    options = options or {}
    plant = make()
    x0 = jnp.asarray(make_x0(plant))
    u = jnp.zeros(plant.num_inputs)
    rows = {}
    if name != "ball":
        dynamics = jax.jit(lambda t, x, u: plant.dynamics(t, x, u))
        rows["jit(dynamics)"] = first_and_second(lambda: dynamics(0.0, x0, u))
    rows["simulate (dopri5)"] = first_and_second(
        lambda: jd.simulate(plant, (0.0, 1.0), x0, **options).final_state)
    if name != "ball":
        rows["simulate (euler)"] = first_and_second(
            lambda: final_state_or_nan(jd.simulate(plant, (0.0, 1.0), x0, solver="euler", dt=1e-2, throw=False)))
    for mode in autodiff:
        loss = jax.jit(jax.grad(lambda x: jnp.sum(
            jd.simulate(plant, (0.0, 1.0), x, autodiff=mode, **options).final_state ** 2)))
        rows["jit(grad(simulate))" + ("" if mode == "reverse" else f" {mode}")] = first_and_second(lambda: loss(x0))
    return rows


def main():
    parser = argument_parser(__doc__, repeats=1, gpu_help="unused")
    parser.add_argument("--systems", nargs="*", default=list(systems()))
    parser.add_argument("--autodiff", nargs="*", default=["reverse"], choices=["reverse", "adjoint"],
                        help="the reverse modes whose gradient rows are timed")
    args = parser.parse_args()
    print(machine_line())
    print(f"{'system':10s} {'program':35s} {'first call':>11s} {'second':>9s} {'first - second':>15s} {'/ dynamics':>11s}")
    for name in args.systems:
        rows = measure(name, *systems()[name], autodiff=args.autodiff)
        reference = (rows.get("jit(dynamics)") or (None,))[0]
        for program, times in rows.items():
            if times is None:
                print(f"{name:10s} {program:35s} {'failed (non-finite result): not timed':>33s}", flush=True)
                continue
            first, second = times
            ratio = f"{first / reference:10.1f}x" if reference else ""
            print(f"{name:10s} {program:35s} {first:10.2f}s {second * 1e3:7.1f}ms {first - second:14.2f}s {ratio:>11s}",
                  flush=True)
        jax.clear_caches()


if __name__ == "__main__":
    main()
