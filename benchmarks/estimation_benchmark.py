"""Unscented Kalman filter step: jaxdrake's `UnscentedKalmanFilter` against filterpy's, on the
same problem in one process.

The pendulum (jd.models.Pendulum's parameters) measured by its bob's horizontal position
l sin(theta), filtered at 100 Hz (one RK4 step of the dynamics per period on both sides;
filterpy's with a NumPy RK4), scaled sigma points alpha = 1, beta = 2, kappa = 0, the same
noise covariances and the same measurement sequence (drawn by NumPy). One step = correct with
y_k, then predict with u_k. jaxdrake: (1) the jitted step called from Python once per sample
(what a real-time loop does), (2) per step inside a `lax.scan` over the whole sequence. filterpy:
`update(y)` then `predict(u=u)`. The final estimates are checked to agree; best of repeats,
first-call (compile) times next to the run times.

    python benchmarks/estimation_benchmark.py [--steps 1000]
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, best_time, machine_line  # benchmarks/_common.py

PERIOD = 0.01
M, LENGTH, DAMPING, G = 1.0, 0.5, 0.1, 9.81
W, V = np.diag([1e-6, 1e-4]), np.array([[1e-4]])
X0, P0 = np.array([0.2, 0.0]), np.diag([0.1, 0.1])


def measured_pendulum():
    pendulum = jd.models.Pendulum(m=M, l=LENGTH, b=DAMPING, g=G)
    return jd.System.from_functions(dynamics=pendulum.dynamics,
                                    output=lambda t, x, u: jnp.array([LENGTH * jnp.sin(x[0])]),
                                    num_states=2, num_inputs=1, time_invariant=True)


def numpy_rk4(x, u):
    def f(x):
        return np.array([x[1], (u[0] - DAMPING * x[1] - M * G * LENGTH * np.sin(x[0])) / (M * LENGTH**2)])
    k1 = f(x)
    k2 = f(x + PERIOD / 2 * k1)
    k3 = f(x + PERIOD / 2 * k2)
    k4 = f(x + PERIOD * k3)
    return x + PERIOD / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def measurements(steps, seed=0):
    """Inputs and noisy measurements of a simulated swing (NumPy's draws)."""
    rng = np.random.default_rng(seed)
    x, us, ys = np.array([0.8, 0.0]), [], []
    for k in range(steps):
        u = np.array([0.3 * np.sin(2 * np.pi * 0.5 * k * PERIOD)])
        ys.append([LENGTH * np.sin(x[0])] + rng.multivariate_normal(np.zeros(1), V))
        us.append(u)
        x = numpy_rk4(x, u) + rng.multivariate_normal(np.zeros(2), W)
    return np.array(us), np.array(ys)


def filterpy_run(us, ys):
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    points = MerweScaledSigmaPoints(2, alpha=1.0, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=2, dim_z=1, dt=PERIOD, points=points, fx=lambda x, dt, u: numpy_rk4(x, u),
                                hx=lambda x: np.array([LENGTH * np.sin(x[0])]))
    ukf.x, ukf.P, ukf.Q, ukf.R = X0.copy(), P0.copy(), W, V
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)  # correct first, as ours does
    for u, y in zip(us, ys):
        ukf.update(y)
        ukf.predict(u=u)
    return ukf.x


def main():
    parser = argument_parser(__doc__, repeats=5, gpu_help="unused: this benchmark is for the CPU")
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    print(machine_line())
    us, ys = measurements(args.steps)
    inputs = jnp.asarray(np.concatenate([us, ys], axis=1))
    ukf = jd.estimation.UnscentedKalmanFilter(measured_pendulum(), W, V, period=PERIOD, x0=X0, P0=P0)
    times = PERIOD * jnp.arange(args.steps)

    step = jax.jit(ukf.update)
    start = time.perf_counter()
    jax.block_until_ready(step(times[0], ukf.initial_state(), inputs[0]))
    first_step = time.perf_counter() - start
    samples = list(zip(times, inputs))  # device arrays, made before timing

    def python_loop():
        z = ukf.initial_state()
        for t, input_output in samples:
            z = step(t, z, input_output)
        return jax.block_until_ready(z)

    @jax.jit
    def scanned(z0, times, inputs):
        return jax.lax.scan(lambda z, sample: (ukf.update(sample[0], z, sample[1]), None), z0, (times, inputs))[0]

    start = time.perf_counter()
    jax.block_until_ready(scanned(ukf.initial_state(), times, inputs))
    first_scan = time.perf_counter() - start
    looped = best_time(python_loop, args.repeats) / args.steps
    in_scan = best_time(lambda: jax.block_until_ready(scanned(ukf.initial_state(), times, inputs)),
                        args.repeats) / args.steps
    peer = best_time(lambda: filterpy_run(us, ys), args.repeats) / args.steps

    ours = ukf.estimate(scanned(ukf.initial_state(), times, inputs))
    difference = np.max(np.abs(np.asarray(ours) - filterpy_run(us, ys)))
    print(f"UKF on the pendulum, {args.steps} steps at {1 / PERIOD:.0f} Hz; final estimates differ by {difference:.1e}")
    print(f"  jaxdrake, jitted step from Python  {looped * 1e6:8.1f} us/step (first call {first_step:.2f} s)")
    print(f"  jaxdrake, inside lax.scan          {in_scan * 1e6:8.1f} us/step (first call {first_scan:.2f} s)")
    print(f"  filterpy update + predict          {peer * 1e6:8.1f} us/step "
          f"({peer / looped:.1f}x the jitted step, {peer / in_scan:.0f}x the scan)")


if __name__ == "__main__":
    main()
