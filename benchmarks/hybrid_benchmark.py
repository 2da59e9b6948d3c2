"""Hybrid simulation speed: jaxdrake against an event-terminated Diffrax loop and a SciPy
`solve_ivp` events loop, on the bouncing ball and the rimless wheel.

Every contender integrates with a Dormand-Prince 5(4) method at rtol = atol = 1e-8 and locates
each impact by root finding on its dense output, then applies the same reset and restarts:
Diffrax through `diffeqsolve(..., event=Event(cond_fn, optx.Newton))` inside a `lax.while_loop`
over impacts (jit-compiled, vmapped for batches), SciPy through `solve_ivp(events=...)` in a
Python loop. jaxdrake runs its `HybridSystem` in its one loop. Problems:

- bouncing ball (g = 9.81, r = 1, cor = 0.8) dropped from h0 (5 m single; uniform in [2, 8] m
  for the batch), 3.5 s (6 to 20 impacts; the impacts of a ball dropped from 2 m accumulate
  at 4.06 s);
- rimless wheel (Drake's defaults), 10 s from theta = 0 with thetadot0 (1.5 single; uniform in
  [1, 3] for the batch), about 17 impacts.

The error column is the largest final-state error against a SciPy DOP853 events loop at rtol
1e-12 (first 20 members of a batch). The SciPy batch is timed on 100 members and scaled.

    python benchmarks/hybrid_benchmark.py                          # CPU, batch 10^4
    python benchmarks/hybrid_benchmark.py --gpu --batch 10000      # accelerator: JAX rows only
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

import jaxdrake as jd
from _common import argument_parser, best_time, failures, final_state_or_nan, machine_line  # benchmarks/_common.py

jax.config.update("jax_enable_x64", True)

RTOL = ATOL = 1e-8
G, R, COR = 9.81, 1.0, 0.8
ALPHA, SLOPE = np.pi / 8, 0.08


# Each problem: flow f(y), event function (crosses zero downwards at an impact), reset.
def ball_flow(y):
    return [y[1], -G] if isinstance(y, np.ndarray) else jnp.stack([y[1], -G * jnp.ones_like(y[1])])


def ball_event(y):  # q - r while falling, positive otherwise
    return np.where(y[1] < 0, y[0] - R, 1.0) if isinstance(y, np.ndarray) else jnp.where(y[1] < 0, y[0] - R, 1.0)


def ball_reset(y):
    return np.array([y[0], -COR * y[1]]) if isinstance(y, np.ndarray) else jnp.stack([y[0], -COR * y[1]])


def wheel_flow(y):
    return [y[1], G * np.sin(y[0])] if isinstance(y, np.ndarray) else jnp.stack([y[1], G * jnp.sin(y[0])])


def wheel_event(y):  # the next spoke touches down at theta = slope + alpha
    return SLOPE + ALPHA - y[0]


def wheel_reset(y):
    c = np.cos(2 * ALPHA)
    return np.array([y[0] - 2 * ALPHA, c * y[1]]) if isinstance(y, np.ndarray) else jnp.stack([y[0] - 2 * ALPHA, c * y[1]])


PROBLEMS = {
    "ball": dict(flow=ball_flow, event=ball_event, reset=ball_reset, tf=3.5,
                 system=jd.models.BouncingBall(G, R, COR, stop_speed=0.0),
                 x0=lambda v: np.array([v, 0.0]), single=5.0, low=2.0, high=8.0),
    "wheel": dict(flow=wheel_flow, event=wheel_event, reset=wheel_reset, tf=10.0,
                  system=jd.models.RimlessWheel(),
                  x0=lambda v: np.array([0.0, v]), single=1.5, low=1.0, high=3.0),
}


def scipy_loop(problem, x0, rtol=RTOL, atol=ATOL, method="RK45"):
    event = lambda t, y: problem["event"](y)
    event.terminal, event.direction = True, -1
    t, y, tf = 0.0, np.asarray(x0, float), problem["tf"]
    for _ in range(64):
        if t >= tf:
            break
        sol = solve_ivp(lambda t, y: problem["flow"](y), (t, tf), y, method=method, rtol=rtol,
                        atol=atol, events=event)
        t, y = sol.t[-1], sol.y[:, -1]
        if sol.status == 1:
            y = problem["reset"](y)
    return y


def diffrax_runner(problem, max_events=64):
    import diffrax
    import optimistix as optx

    term = diffrax.ODETerm(lambda t, y, args: problem["flow"](y))
    event = diffrax.Event(lambda t, y, args, **kw: problem["event"](y), optx.Newton(1e-10, 1e-10))
    controller = diffrax.PIDController(rtol=RTOL, atol=ATOL)
    tf = problem["tf"]

    def one(x0):
        def cond(c):
            t, y, n = c
            return (t < tf) & (n < max_events)

        def body(c):
            t, y, n = c
            sol = diffrax.diffeqsolve(term, diffrax.Dopri5(), t, tf, None, y, event=event,
                                      stepsize_controller=controller, max_steps=4096,
                                      saveat=diffrax.SaveAt(t1=True), throw=False)
            hit = sol.event_mask
            y1 = sol.ys[-1]
            return sol.ts[-1], jnp.where(hit, problem["reset"](y1), y1), n + 1

        return jax.lax.while_loop(cond, body, (jnp.asarray(0.0), x0, 0))[1]
    return jax.jit(one), jax.jit(jax.vmap(one))


def jaxdrake_runner(problem):
    def one(x0):
        return final_state_or_nan(jd.simulate(problem["system"], (0.0, problem["tf"]), x0, rtol=RTOL, atol=ATOL,
                           dense=False, max_events=64, throw=False))
    return jax.jit(one), jax.jit(jax.vmap(one))



def run(batch, gpu, repeats):
    print(machine_line())
    print(f"{'problem':8s} {'contender':36s} {'time':>12s} {'vs jaxdrake':>12s} {'max error':>10s}")
    for name, problem in PROBLEMS.items():
        values = np.random.default_rng(0).uniform(problem["low"], problem["high"], batch)
        x0s = np.stack([problem["x0"](v) for v in values])
        x0 = problem["x0"](problem["single"])
        check = min(20, batch)
        ref_single = scipy_loop(problem, x0, 1e-12, 1e-12, "DOP853")
        ref_batch = np.stack([scipy_loop(problem, x, 1e-12, 1e-12, "DOP853") for x in x0s[:check]])
        rows = []

        def record(label, seconds, finals, kind, compile_s=None):
            ref = ref_single[None] if kind == "single" else ref_batch
            err = np.max(np.abs(np.asarray(finals)[: len(ref)] - ref))
            rows.append((label, kind, None if failures(finals) else seconds, err, compile_s))

        contenders = [("jaxdrake", jaxdrake_runner(problem))]
        try:
            contenders.append(("diffrax event loop", diffrax_runner(problem)))
        except ImportError:
            print("  (diffrax / optimistix not installed: skipped)")
        for label, (one, many) in contenders:
            xs, x = jnp.asarray(x0s), jnp.asarray(x0)
            start = time.perf_counter()
            jax.block_until_ready(many(xs))
            compile_batch = time.perf_counter() - start
            t = best_time(lambda: jax.block_until_ready(many(xs)), repeats)
            if not gpu:
                start = time.perf_counter()
                jax.block_until_ready(one(x))
                compile_single = time.perf_counter() - start
                record(f"{label} single", best_time(lambda: jax.block_until_ready(one(x)), 20),
                       one(x)[None], "single", compile_single)
            record(f"{label} batch {batch}", t, many(xs), "batch", compile_batch - t)
        if not gpu:
            record("scipy RK45 events loop single", best_time(lambda: scipy_loop(problem, x0), 3),
                   scipy_loop(problem, x0)[None], "single")
            sub = min(100, batch)
            t = best_time(lambda: [scipy_loop(problem, x) for x in x0s[:sub]], 1) * batch / sub
            record(f"scipy RK45 events loop {batch}*", t,
                   np.stack([scipy_loop(problem, x) for x in x0s[:check]]), "batch")

        base = {kind: s for label, kind, s, _, _ in rows if s is not None and label.startswith("jaxdrake")}
        for label, kind, seconds, err, compile_s in rows:
            if seconds is None:
                print(f"{name:8s} {label:36s} failed (non-finite results): not timed")
                continue
            extra = f"   (compile {compile_s:.2f} s)" if compile_s is not None else ""
            print(f"{name:8s} {label:36s} {seconds * 1e3:10.2f}ms {seconds / base.get(kind, float('nan')):11.2f}x "
                  f"{err:10.1e}{extra}")
    if not gpu:
        print("* scipy batch: 100 members timed, scaled to the batch size")


if __name__ == "__main__":
    args = argument_parser(__doc__, batch=10_000, repeats=3,
                           gpu_help="JAX rows only (for the accelerator)").parse_args()
    run(args.batch, args.gpu, args.repeats)
