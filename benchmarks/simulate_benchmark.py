"""Simulation speed: jaxdrake against SciPy solve_ivp, Diffrax and Drake, on the same problems.

Problems: the pendulum (Drake's PendulumPlant parameters, u = 0) and the Van der Pol
oscillator (mu = 1), 10 s at rtol = atol = 1e-8, with a 5(4) Dormand-Prince method on every
side (SciPy RK45, Diffrax Dopri5, Drake RungeKutta5Integrator). Each is run once alone and as a
batch of initial states (jaxdrake: `jax.vmap(simulate)` and `simulate_ensemble`, one lane per
member). JAX programs are compiled first and timed separately
(`block_until_ready`); every timing is the best of several repeats. Each row also reports the
final-state error against a SciPy DOP853 reference at rtol 1e-13, so that speed is compared at
equal accuracy.

    python benchmarks/simulate_benchmark.py                  # CPU: everything
    python benchmarks/simulate_benchmark.py --gpu --batch 100000   # accelerator: JAX rows only
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import jaxdrake as jd
from _common import argument_parser, best_time, failures, final_state_or_nan, machine_line  # benchmarks/_common.py
from jaxdrake.models import Pendulum, VanDerPol

jax.config.update("jax_enable_x64", True)

TF, RTOL, ATOL = 10.0, 1e-8, 1e-8


def pendulum_rhs(t, x, m=1.0, l=0.5, b=0.1, g=9.81):
    return np.array([x[1], (-b * x[1] - m * g * l * np.sin(x[0])) / (m * l * l)])


def vdp_rhs(t, x, mu=1.0):
    return np.array([x[1], -mu * (x[0] ** 2 - 1) * x[1] - x[0]])


PROBLEMS = {
    "pendulum": dict(system=Pendulum(), rhs=pendulum_rhs, low=[-2.5, -3.0], high=[2.5, 3.0]),
    "vanderpol": dict(system=VanDerPol(1.0), rhs=vdp_rhs, low=[-2.0, -2.0], high=[2.0, 2.0]),
}



def reference(rhs, x0s):
    return np.stack([solve_ivp(rhs, (0, TF), x0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
                     for x0 in x0s])


# ----- the contenders --------------------------------------------------------------------------


def jaxdrake_runner(system, autodiff):
    def one(x0):
        return final_state_or_nan(jd.simulate(system, (0.0, TF), x0, rtol=RTOL, atol=ATOL, dense=False,
                           autodiff=autodiff, max_steps=4096, throw=False))
    return jax.jit(one), jax.jit(jax.vmap(one))


def diffrax_runner(system):
    import diffrax

    term = diffrax.ODETerm(lambda t, x, args: system.dynamics(t, x, jnp.zeros(system.num_inputs)))
    controller = diffrax.PIDController(rtol=RTOL, atol=ATOL)

    def one(x0):
        sol = diffrax.diffeqsolve(term, diffrax.Dopri5(), 0.0, TF, None, x0,
                                  stepsize_controller=controller, max_steps=4096,
                                  saveat=diffrax.SaveAt(t1=True))
        return sol.ys[-1]
    return jax.jit(one), jax.jit(jax.vmap(one))


def drake_runner(name):
    from pydrake.examples import PendulumPlant, VanDerPolOscillator
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator

    plant = PendulumPlant() if name == "pendulum" else VanDerPolOscillator()
    simulator = Simulator(plant)
    ResetIntegratorFromFlags(simulator, "runge_kutta5", 0.1)
    integrator = simulator.get_mutable_integrator()
    integrator.set_target_accuracy(RTOL)
    simulator.set_publish_every_time_step(False)
    context = simulator.get_mutable_context()
    if name == "pendulum":
        plant.get_input_port().FixValue(context, [0.0])

    def one(x0):
        context.SetTime(0.0)
        context.SetContinuousState(x0)
        simulator.Initialize()
        simulator.AdvanceTo(TF)
        return context.get_continuous_state_vector().CopyToVector()
    return one


def scipy_runner(rhs):
    return lambda x0: solve_ivp(rhs, (0, TF), x0, method="RK45", rtol=RTOL, atol=ATOL).y[:, -1]


# ----- the run ---------------------------------------------------------------------------------


def run(batch, gpu, repeats):
    print(machine_line())
    print(f"{'problem':10s} {'contender':32s} {'time':>10s} {'vs jaxdrake':>12s} {'max error':>10s}")
    for name, problem in PROBLEMS.items():
        system = problem["system"]
        x0s = np.random.default_rng(0).uniform(problem["low"], problem["high"], (batch, 2))
        check = min(batch, 200)  # the error is measured on the first members of the batch
        ref = reference(problem["rhs"], x0s[:check])
        rows = []

        def record(label, seconds, finals, compile_s=None):
            err = np.max(np.abs(np.asarray(finals)[:check] - ref[: len(np.asarray(finals)[:check])]))
            rows.append((label, None if failures(finals) else seconds, err, compile_s))

        # jaxdrake, single and batch, both loop kinds
        for autodiff in ("reverse", "forward"):
            one, many = jaxdrake_runner(system, autodiff)
            x0 = jnp.asarray(x0s[0])
            start = time.perf_counter()
            jax.block_until_ready(one(x0))
            compile_single = time.perf_counter() - start
            if not gpu:
                t = best_time(lambda: jax.block_until_ready(one(x0)), 20)
                record(f"jaxdrake single ({autodiff})", t, one(x0)[None], compile_single)
            xs = jnp.asarray(x0s)
            start = time.perf_counter()
            jax.block_until_ready(many(xs))
            compile_batch = time.perf_counter() - start
            t = best_time(lambda: jax.block_until_ready(many(xs)), repeats)
            record(f"jaxdrake batch {batch} ({autodiff})", t, many(xs), compile_batch - t)

        # the same batch as one lane per member (simulate_ensemble: Pallas on a GPU)
        xs = jnp.asarray(x0s)
        ensemble = lambda: jd.simulate_ensemble(system, (0.0, TF), xs, rtol=RTOL, atol=ATOL).final_state  # noqa: E731
        start = time.perf_counter()
        jax.block_until_ready(ensemble())
        compile_ensemble = time.perf_counter() - start
        t = best_time(lambda: jax.block_until_ready(ensemble()), repeats)
        record(f"jaxdrake simulate_ensemble {batch}", t, ensemble(), compile_ensemble - t)

        try:
            one, many = diffrax_runner(system)
            xs = jnp.asarray(x0s)
            jax.block_until_ready(many(xs))
            if not gpu:
                jax.block_until_ready(one(xs[0]))
                record("diffrax single", best_time(lambda: jax.block_until_ready(one(xs[0])), 20),
                       one(xs[0])[None])
            record(f"diffrax batch {batch}", best_time(lambda: jax.block_until_ready(many(xs)), repeats),
                   many(xs))
        except ImportError:
            print("  (diffrax not installed: skipped)")

        if not gpu:
            try:
                drake = drake_runner(name)
                record("drake single", best_time(lambda: drake(x0s[0]), 20), drake(x0s[0])[None])
                loop = lambda: np.stack([drake(x) for x in x0s])
                record(f"drake loop over {batch}", best_time(loop, 3), loop())
            except ImportError:
                print("  (drake not installed: skipped)")
            scipy_one = scipy_runner(problem["rhs"])
            record("scipy RK45 single", best_time(lambda: scipy_one(x0s[0]), 5), scipy_one(x0s[0])[None])
            loop = lambda: np.stack([scipy_one(x) for x in x0s])
            record(f"scipy RK45 loop over {batch}", best_time(loop, 1), loop())

        base = {kind: s for label, s, _, _ in rows for kind in ("single", "batch")
                if s is not None and (label == f"jaxdrake {kind} (reverse)"
                                      or label.startswith(f"jaxdrake {kind} {batch} (reverse)"))}
        for label, seconds, err, compile_s in rows:
            if seconds is None:
                print(f"{name:10s} {label:32s} failed (non-finite results): not timed")
                continue
            kind = "single" if "single" in label else "batch"
            ratio = seconds / base[kind] if kind in base else float("nan")
            extra = f"   (compile {compile_s:.2f} s)" if compile_s is not None else ""
            print(f"{name:10s} {label:32s} {seconds * 1e3:8.2f}ms {ratio:11.2f}x {err:10.1e}{extra}")


if __name__ == "__main__":
    args = argument_parser(__doc__, batch=1000, repeats=5,
                           gpu_help="JAX rows only (for the accelerator)").parse_args()
    run(args.batch, args.gpu, args.repeats)
