"""Composition overhead and speed: a pendulum under PD control, as a jaxdrake `feedback`
diagram, as the same closed loop written by hand, and as a Drake diagram.

Two problems, 10 s, rtol = atol = 1e-8, 5(4) Dormand-Prince on both sides (Drake's
RungeKutta5Integrator): (1) continuous PD, u = -kp (theta - pi) - kd thetadot (Drake:
PendulumPlant + PidController + ConstantVectorSource); (2) the same PD sampled every 10 ms
and held (jaxdrake: a discrete controller whose state holds u; Drake: the PidController
through a ZeroOrderHold). Initial states uniform in theta in [0, 2pi), thetadot in [-1, 1].
JAX programs are compiled first and timed separately; each timing is the best of repeats.

    python benchmarks/compose_benchmark.py [--batch 1000]
    python benchmarks/compose_benchmark.py --gpu --batch 100000     # accelerator: JAX rows only
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, best_time, machine_line  # benchmarks/_common.py
from jaxdrake.models import Pendulum

jax.config.update("jax_enable_x64", True)

TF, RTOL, KP, KD, PERIOD = 10.0, 1e-8, 10.0, 1.0, 0.01


def pd(t, x, u):
    return jnp.atleast_1d(-KP * (u[0] - jnp.pi) - KD * u[1])


def jaxdrake_systems():
    plant = Pendulum()
    continuous = jd.feedback(plant, jd.System.from_functions(output=pd, num_states=0, num_inputs=2,
                                                             num_outputs=1))

    def by_hand(t, x, u):
        return plant.dynamics(t, x, pd(t, x, x))

    sampled = jd.feedback(plant, jd.System.from_functions(
        update=lambda t, z, u: pd(t, z, u), num_states=1, num_inputs=2, sample_time=PERIOD,
        direct_feedthrough=False))
    return {"continuous PD: feedback diagram": continuous,
            "continuous PD: closed loop by hand": jd.System.from_functions(by_hand, num_states=2),
            "sampled PD (10 ms ZOH): diagram": sampled}


def drake_runner(sampled):
    from pydrake.examples import PendulumPlant
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator
    from pydrake.systems.controllers import PidController
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold

    builder = DiagramBuilder()
    plant = builder.AddSystem(PendulumPlant())
    pid = builder.AddSystem(PidController(kp=[KP], ki=[0.0], kd=[KD]))
    target = builder.AddSystem(ConstantVectorSource([np.pi, 0.0]))
    builder.Connect(plant.get_state_output_port(), pid.get_input_port_estimated_state())
    builder.Connect(target.get_output_port(), pid.get_input_port_desired_state())
    if sampled:
        hold = builder.AddSystem(ZeroOrderHold(PERIOD, 1))
        builder.Connect(pid.get_output_port_control(), hold.get_input_port())
        builder.Connect(hold.get_output_port(), plant.get_input_port())
    else:
        builder.Connect(pid.get_output_port_control(), plant.get_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    ResetIntegratorFromFlags(simulator, "runge_kutta5", 0.1)
    simulator.get_mutable_integrator().set_target_accuracy(RTOL)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyMutableContextFromRoot(context)

    def one(x0):
        context.SetTime(0.0)
        plant_context.SetContinuousState(x0)
        if sampled:  # the hold starts at 0; the first sample (t = 0) overwrites it, as ours
            hold.GetMyMutableContextFromRoot(context).SetDiscreteState([0.0])
        simulator.Initialize()
        simulator.AdvanceTo(TF)
        return plant_context.get_continuous_state_vector().CopyToVector()
    return one


def main(batch, repeats, gpu):
    print(machine_line())
    x0s = np.random.default_rng(0).uniform([0.0, -1.0], [2 * np.pi, 1.0], (batch, 2))
    results = {}
    for label, system in jaxdrake_systems().items():
        sampled = system.sample_times != ()
        pad = (lambda x: jnp.concatenate([jnp.zeros(1), x])) if sampled else (lambda x: x)
        run = lambda x0, system=system, pad=pad: jd.simulate(
            system, (0.0, TF), pad(x0), rtol=RTOL, atol=RTOL, dense=False).final_state[-2:]
        one, many = jax.jit(run), jax.jit(jax.vmap(run))
        jax.block_until_ready(one(x0s[0])), jax.block_until_ready(many(x0s))
        results[label] = (best_time(lambda: jax.block_until_ready(one(x0s[0])), 20),
                          best_time(lambda: jax.block_until_ready(many(x0s)), repeats), many(x0s))
    print(f"{'problem':40s} {'single':>10s} {'batch ' + str(batch):>12s} {'drake single':>13s} "
          f"{'drake loop':>11s} {'batch ratio':>12s} {'max |diff|':>11s}")
    for label, (single, many_s, finals) in results.items():
        sampled = label.startswith("sampled")
        try:
            if gpu:
                raise ImportError
            drake = drake_runner(sampled)
        except ImportError:
            print(f"{label:40s} {single * 1e3:8.2f}ms {many_s * 1e3:10.1f}ms  (drake not run)")
            continue
        loop = lambda: np.stack([drake(x) for x in x0s])
        drake_single, drake_loop = best_time(lambda: drake(x0s[0]), 20), best_time(loop, 2)
        diff = np.max(np.abs(np.asarray(finals) - loop()))
        print(f"{label:40s} {single * 1e3:8.2f}ms {many_s * 1e3:10.1f}ms {drake_single * 1e3:11.2f}ms "
              f"{drake_loop * 1e3:9.0f}ms {drake_loop / many_s:11.1f}x {diff:11.1e}")


if __name__ == "__main__":
    args = argument_parser(__doc__, batch=1000, repeats=3, gpu_help="JAX rows only (no Drake)").parse_args()
    main(args.batch, args.repeats, args.gpu)
