"""What a warm call from Python costs beside its compiled program: `jd.simulate` of the
pendulum, of a PD-controlled pendulum (a diagram) and of the bouncing ball (events), each
called as a user calls it in a notebook and the same program (all its outputs) through
`jax.jit`'s own dispatch; and
`traj.eval` at 101 points; `linearize` and `lqr` of the cart-pole likewise. Targets (issue
40): a warm call within 0.3 ms of its jitted time; `eval` at 101 points <= 1 ms. Last, calls a
notebook makes on a Solo-12 (example-robot-data), a Riccati solve and a QP, first call (with its
compilation) beside the warm one.

    python benchmarks/call_overhead_benchmark.py [--repeats 200]
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, machine_line, median_time  # benchmarks/_common.py

jax.config.update("jax_enable_x64", True)


def cases():
    """name: (system, x0)."""
    pendulum = jd.models.Pendulum()
    pd = jd.System.from_functions(output=lambda t, x, u: -(5.0 * (u[0:1] - np.pi) + 1.0 * u[1:2]),
                                  num_states=0, num_inputs=2)
    return {"pendulum": (pendulum, jnp.array([1.0, 0.0])),
            "PD diagram": (jd.feedback(pendulum, pd), jnp.array([1.0, 0.0])),
            "bouncing ball": (jd.models.BouncingBall(), jnp.array([1.0, 0.0]))}


def main():
    parser = argument_parser(__doc__, repeats=200, gpu_help="unused")
    args = parser.parse_args()
    print(machine_line())
    print(f"{'case':16s} {'from Python':>12s} {'inside jit':>11s} {'overhead':>9s}")
    for name, (system, x0) in cases().items():
        def python_call():
            return jd.simulate(system, (0.0, 1.0), x0).final_state

        # the same program with all its outputs (the dense trajectory too), called through
        # jax.jit's own dispatch
        jitted = jax.jit(lambda x0: eqx.filter(jd.simulate(system, (0.0, 1.0), x0), eqx.is_array))
        python = median_time(python_call, args.repeats)
        inside = median_time(lambda: jitted(x0), args.repeats)
        print(f"{name:16s} {python * 1e3:10.3f}ms {inside * 1e3:9.3f}ms {(python - inside) * 1e3:7.3f}ms", flush=True)
    traj = jd.simulate(jd.models.Pendulum(), (0.0, 1.0), jnp.array([1.0, 0.0]))
    ts = jnp.linspace(0.0, 1.0, 101)
    print(f"{'eval, 101 points':16s} {median_time(lambda: traj.eval(ts), args.repeats) * 1e3:10.3f}ms")
    # linearize and lqr of the cart-pole about its upright equilibrium, host numbers in
    cartpole, upright, u0 = jd.models.CartPole(), np.array([0.0, np.pi, 0.0, 0.0]), np.zeros(1)
    operations = {"linearize": lambda x0: jd.linearize(cartpole, x0, u0),
                  "lqr": lambda x0: jd.control.lqr(cartpole, np.eye(4), np.eye(1), x0=x0, u0=u0)}
    for name, operation in operations.items():
        jitted = jax.jit(lambda x0: eqx.filter(operation(x0), eqx.is_array))
        python = median_time(lambda: eqx.filter(operation(upright), eqx.is_array), args.repeats)
        inside = median_time(lambda: jitted(jnp.asarray(upright)), args.repeats)
        print(f"{name + ', cart-pole':16s} {python * 1e3:10.3f}ms {inside * 1e3:9.3f}ms "
              f"{(python - inside) * 1e3:7.3f}ms", flush=True)

    first_and_warm_calls(args.repeats)


def first_and_warm_calls(repeats):
    """First call (compiling) and warm call of a plant's queries outside jit, a CARE and a QP."""
    import importlib.metadata
    import pathlib
    import time

    robots = pathlib.Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")))
    solo = jd.RigidBodySystem.from_urdf(robots / "solo_description/robots/solo12.urdf", floating_base=True)
    xs = jnp.asarray(np.random.default_rng(0).uniform(-0.3, 0.3, (101, solo.num_states))).at[:, 3].add(1.0)
    u = np.zeros(solo.num_inputs)
    A, B = np.random.default_rng(1).normal(size=(2, 6, 6))
    workspace = jd.control.qp_workspace(A @ A.T + np.eye(6), B)
    calls = {"vmap(solo.energy), 101 states": lambda: jax.vmap(solo.energy)(xs),
             "solo.dynamics(t, x, u)": lambda: solo.dynamics(0.0, xs[0], u),
             "mass_matrix(solo.tree, q)": lambda: jd.multibody.mass_matrix(solo.tree, xs[0, :19]),
             "frame_jacobian(solo.tree, q, foot)": lambda: jd.multibody.frame_jacobian(solo.tree, xs[0, :19], "FL_FOOT"),
             "solve_continuous_are, 6 states": lambda: jd.control.solve_continuous_are(A, B, np.eye(6), np.eye(6)),
             "solve_qp, 6 variables": lambda: jd.control.solve_qp(workspace, B[0], -np.ones(6), np.ones(6))}
    print(f"{'call':32s} {'first call':>11s} {'warm':>10s}")
    for name, call in calls.items():
        start = time.perf_counter()
        jax.block_until_ready(call())
        first = time.perf_counter() - start
        print(f"{name:32s} {first:10.3f}s {median_time(call, repeats) * 1e3:8.3f}ms", flush=True)


if __name__ == "__main__":
    main()
