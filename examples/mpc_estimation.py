"""The cart-pole balanced from noisy position-only measurements: linear MPC through an
unscented Kalman filter, against LQG, with the force on the cart limited (issue 42).

The sensor reads y = (x, θ) + v_k at 100 Hz (v_k ~ N(0, diag(σ²)), drawn from a key and the
sample's index); the velocities are never measured. Both controllers run at the sensor's
period h on the same sampled model (one RK4 step of the cart-pole), with the same weights:

- **MPC**: `UnscentedKalmanFilter` -> `linear_mpc` (N = 20 steps, |u| <= F as constraints of
  the QP, the discrete Riccati cost-to-go as the terminal cost);
- **LQG**: the steady-state Kalman filter (`kalman_filter`) -> the discrete LQR, its command
  clipped by a `Saturation` to the same |u| <= F and held by a `ZeroOrderHold` (so it acts at
  the MPC's instants).

Each controller is one system from y to u (the estimator reads the command it gave), closed
around the plant with `jd.feedback`; the plant applies each command one period after the
sample it answers (a `ZeroOrderHold` in front of the cart: the computation's and the wire's
delay), which is what the LCM loop below does. Both loops start from the same offset and see
the same noise draws. Then the MPC controller runs as an LCM node against the plant as an LCM
node, two processes on a loopback relay (tcpq://127.0.0.1, never multicast): the plant ticks
in real time at 100 Hz, the controller answers each measurement, and the plant applies the
answer from its next tick: the simulated loop, message for message, when no answer is late.

Run:  python examples/mpc_estimation.py [--out DIR]     (saves mpc_estimation.png)
"""

import functools
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import lcm
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from jaxdrake.estimation import UnscentedKalmanFilter, kalman_filter  # noqa: E402
from jaxdrake.lcm import LoopbackRelay, SignalCoder, open_lcm  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)
HERE = pathlib.Path(__file__).resolve().parent

PERIOD, HORIZON_STEPS, FORCE_LIMIT = 0.01, 20, 30.0     # s, steps, N
UPRIGHT = np.array([0.0, np.pi, 0.0, 0.0])               # [x, θ, ẋ, θ̇], θ = π balanced
START = UPRIGHT + np.array([0.0, 0.2, 0.0, 0.0])         # the pole 0.2 rad off, at rest
SIGMA = np.array([0.01, 0.02])                           # sensor noise: 1 cm, 0.02 rad
Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.array([[0.1]])
W = np.diag([1e-6, 1e-6, 1e-4, 1e-4])                    # the filters' process noise per sample
P0 = np.diag([0.05, 0.3, 0.1, 0.3]) ** 2                 # the UKF's initial covariance
SEED, DURATION = 0, 6.0
MEASUREMENT = jd.Frame("CartPoleMeasurement", ("x", "theta"))


def sensor_noise(key, t):
    """v_k for the sample k nearest t: a function of (key, k) alone, so the simulated and the
    LCM plant draw the same noise."""
    k = jnp.floor(t / PERIOD + 0.5).astype(jnp.int32)
    return jnp.asarray(SIGMA) * jax.random.normal(jax.random.fold_in(key, k), (2,))


def noisy_cart_pole(key=None):
    """The cart-pole (continuous) whose output is the measurement y = (x, θ) + v_k (the key is
    a leaf of the system: another key, the same compiled programs)."""
    cart_pole = jd.models.CartPole()
    return jd.System.from_functions(
        dynamics=_cart_pole_dynamics, output=_measurement,
        # the key's data: simulate reads every leaf as a number (a typed key is refused)
        params=dict(plant=cart_pole, key=jax.random.key_data(jax.random.key(SEED) if key is None else key)),
        num_states=4, num_inputs=1, direct_feedthrough=False, input_frame=cart_pole.input_frame,
        state_frame=cart_pole.state_frame, output_frame=MEASUREMENT)


def _cart_pole_dynamics(t, x, u, params):
    return params["plant"].dynamics(t, x, u)


def _measurement(t, x, u, params):
    return x[:2] + sensor_noise(jax.random.wrap_key_data(params["key"]), t).astype(x.dtype)


def delayed_cart_pole(key=None):
    """The noisy cart-pole behind a `ZeroOrderHold`: the command computed at t_k acts on
    (t_k+1, t_k+2], one period later (the LCM plant's timing below)."""
    plant = noisy_cart_pole(key)
    builder = jd.DiagramBuilder()
    builder.add(jd.ZeroOrderHold(PERIOD, 1), "hold")
    builder.add(plant, "cart")
    builder.connect("hold", "cart")
    builder.export_input("hold")
    builder.export_output("cart")
    return builder.build("DelayedCartPole", input_frame=plant.input_frame)


@functools.cache  # one model, so lqr and linear_mpc share their compiled linearization
def sampled_model():
    """The controllers' and the filters' model: one RK4 step of the cart-pole over h, y = (x, θ)."""
    cart_pole = jd.models.CartPole()
    return jd.System.from_functions(
        update=lambda t, x, u: jd.simulation.discrete_step(cart_pole, t, x, u, PERIOD, "rk4"),
        output=lambda t, x, u: x[:2], num_states=4, num_inputs=1, sample_time=PERIOD, time_invariant=True,
        direct_feedthrough=False, input_frame=cart_pole.input_frame, state_frame=cart_pole.state_frame,
        output_frame=MEASUREMENT)


def output_feedback(estimator, policy, name):
    """The controller as one system y -> u: u = policy(x̂), the estimator reading [u; y]
    (the command the policy gave and the measurement)."""
    m = policy.num_outputs
    builder = jd.DiagramBuilder()
    builder.add(estimator, "estimator")
    builder.add(policy, "policy")
    builder.connect("estimator", "policy")
    builder.connect("policy", ("estimator", list(range(m))))
    builder.export_input(("estimator", list(range(m, estimator.num_inputs))))
    builder.export_output("policy")
    return builder.build(name, input_frame=MEASUREMENT, output_frame=policy.output_frame)


def mpc_controller():
    """UKF -> linear MPC, as one system y -> u."""
    model = sampled_model()
    ukf = UnscentedKalmanFilter(model, W, np.diag(SIGMA**2), x0=UPRIGHT, P0=P0)
    mpc = jd.control.linear_mpc(model, Q, R, HORIZON_STEPS * PERIOD, x0=UPRIGHT, input_lower=-FORCE_LIMIT,
                                input_upper=FORCE_LIMIT)
    return output_feedback(ukf, mpc, "MpcThroughUkf")


def lqg_controller():
    """Steady-state Kalman filter -> discrete LQR, clipped to the limit and held, as y -> u."""
    model = sampled_model()
    estimator = kalman_filter(model, W, np.diag(SIGMA**2), x0=UPRIGHT)
    regulator = jd.control.lqr(model, Q, R, x0=UPRIGHT)
    policy = jd.cascade(jd.cascade(regulator.controller, jd.Saturation([-FORCE_LIMIT], [FORCE_LIMIT])),
                        jd.ZeroOrderHold(PERIOD, 1))
    return output_feedback(estimator.observer, policy, "Lqg")


# ----- the two loops in simulation -----------------------------------------------------------

def simulate_loop(controller, key=None, start=START, duration=DURATION):
    """The loop `feedback(delayed_cart_pole, controller)` from `start` (the estimators start at
    the upright): per sample t_k, the cart's state x(t_k), the estimate x̂_k|k-1 the
    controller used, the measurement y_k and the force on the cart over (t_k, t_k+1]."""
    loop = jd.feedback(delayed_cart_pole(key), controller)
    cart, hold, estimator = "DelayedCartPole.cart", "DelayedCartPole.hold", f"{controller.name}.estimator"
    # the estimate x̂ (an estimator's first 4 states) starts at the upright (a Luenberger
    # observer's own initial state is the plant's, θ = 0: hanging down)
    x_hat0 = loop.subsystem(estimator).initial_state().at[:4].set(UPRIGHT)
    x0 = loop.initial_state_with({cart: start, estimator: x_hat0})
    traj = jd.simulate(loop, (0.0, duration), x0, max_steps=16 * round(duration / PERIOD))
    t = PERIOD * jnp.arange(round(duration / PERIOD))
    before, after = traj.state(t, side="left"), traj.state(t, side="right")
    return dict(t=np.asarray(t), x=np.asarray(loop.subsystem_state(cart, before)),
                x_hat=np.asarray(loop.subsystem_state(estimator, before)[:, :4]), y=np.asarray(traj.eval(t)),
                u=np.asarray(loop.subsystem_state(hold, after)))


def summary(name, run):
    """Print the final errors, the estimation error and how often the force was at its limit."""
    error = run["x"] - UPRIGHT
    estimation = run["x_hat"] - run["x"]
    late = run["t"] >= DURATION / 2
    at_limit = np.abs(run["u"][:, 0]) >= FORCE_LIMIT * (1 - 1e-9)
    fallen = np.abs(error[:, 1]) > np.pi / 2
    fell = f" (past π/2 at t = {run['t'][fallen][0]:.2f} s)" if fallen.any() else ""
    print(f"{name}: final |x - x*| = {np.abs(error[-1]).round(4)} (x, θ, ẋ, θ̇); "
          f"max |θ - π| = {np.abs(error[:, 1]).max():.3f} rad{fell}")
    print(f"  estimation error: final {np.abs(estimation[-1]).round(4)}, rms over t >= {DURATION / 2:g} s "
          f"{np.sqrt((estimation[late] ** 2).mean(0)).round(4)}")
    print(f"  |u| at the limit {FORCE_LIMIT:g} N in {at_limit.mean():.1%} of the samples "
          f"({at_limit[run['t'] < 1.0].mean():.0%} in the first second)")


# ----- the MPC controller as an LCM node ------------------------------------------------------

def node(name, url, *extra):
    """Start `python -m jaxdrake.lcm examples/mpc_estimation.py:name`; return once it has
    compiled and subscribed."""
    process = subprocess.Popen([sys.executable, "-m", "jaxdrake.lcm", f"{HERE / 'mpc_estimation.py'}:{name}",
                                "--url", url, "--x64", *extra], cwd=HERE.parent, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    line = ""
    while not line.startswith("node "):
        line = process.stdout.readline()
        if not line and process.poll() is not None:
            raise RuntimeError(f"the {name} node did not start")
    return process


def mpc_over_lcm(ticks: int):
    """The plant node ticks in real time at 1/h, publishing y_k and integrating over
    [t_k, t_k+1) with the last command received; the controller node (`--lockstep`) waits for
    each y_k, updates and publishes its answer, stamped t_k+1, which the plant applies from
    t_k+1 on. From the plant's log: per tick the time y_k was sent and its answer received
    (wall clock, s), the true (x, θ) (y_k − v_k), the command stamped t_k; and the nodes'
    summaries."""
    with tempfile.TemporaryDirectory() as tmp, LoopbackRelay() as relay:
        folder = pathlib.Path(tmp)
        # its first wait lasts until the plant node has compiled and ticks: a long input timeout
        controller = node("mpc_controller", relay.url, "--lockstep", "--input-timeout", "600",
                          "--log", str(folder / "controller.log"))
        plant = node("noisy_cart_pole", relay.url, "--rate", f"{1 / PERIOD:g}", "--max-ticks", str(ticks),
                     "--x0", *map(str, START), "--log", str(folder / "plant.log"))
        plant_out, _ = plant.communicate(timeout=600)
        controller.send_signal(signal.SIGINT)
        # a lockstep node notices the signal when its wait for a message ends: send it one
        open_lcm(relay.url).publish(MEASUREMENT.name, SignalCoder(MEASUREMENT).encode(1e9, START[:2]))
        controller_out, _ = controller.communicate(timeout=60)
        events = [(e.channel, e.timestamp * 1e-6, e.data) for e in lcm.EventLog(str(folder / "plant.log"), "r")]
    measurement, command = SignalCoder(MEASUREMENT), SignalCoder(sampled_model().input_frame)
    sent, y, commands = [], [], {}  # commands: {k: (received, u)} for the command stamped t_k
    for channel, when, data in events:
        t, value = (measurement if channel == MEASUREMENT.name else command).decode(data)
        if channel == MEASUREMENT.name:
            sent.append(when)
            y.append(value)
        else:
            commands[round(t / PERIOD)] = (when, value[0])
    t = PERIOD * np.arange(len(sent))
    noise = np.asarray(jax.vmap(lambda s: sensor_noise(jax.random.key(SEED), s))(jnp.asarray(t)))
    answered = np.array([commands.get(k + 1, (np.nan,))[0] for k in range(len(t))])
    return dict(t=t, sent=np.array(sent), x=np.array(y) - noise, answered=answered,
                late=np.flatnonzero(~(answered[:-1] <= np.array(sent[1:]))),  # answered after the next tick
                u=np.array([commands.get(k, (np.nan, 0.0))[1] for k in range(len(t))]),
                summaries=[next(line for line in out.splitlines() if line.startswith("stopped:"))
                           for out in (plant_out, controller_out)])


def lcm_report(over_lcm, simulated):
    """Print the nodes' summaries, the plant's rate, the round trip y_k -> answer, the answers
    that came after the next tick, and the gap to the simulated loop."""
    print("plant node:     ", over_lcm["summaries"][0])
    print("controller node:", over_lcm["summaries"][1])
    sent, trips = over_lcm["sent"], (over_lcm["answered"] - over_lcm["sent"])[:-1] * 1e3
    intervals = np.diff(sent) * 1e3
    late = over_lcm["late"]
    print(f"LCM plant: {len(sent)} ticks at {(len(sent) - 1) / (sent[-1] - sent[0]):.1f} Hz (tick interval "
          f"p50 {np.median(intervals):.2f} ms, p99 {np.percentile(intervals, 99):.2f} ms, max {intervals.max():.2f} ms)")
    print(f"LCM round trip y_k -> its answer: p50 {np.nanmedian(trips):.2f} ms, p99 "
          f"{np.nanpercentile(trips, 99):.2f} ms, max {np.nanmax(trips):.2f} ms; {len(late)} of {len(trips)} "
          f"answers after the next tick{f' (ticks {late[:5].tolist()}...)' if len(late) else ''}")
    K = min(len(sent), len(simulated["t"]))
    print("LCM loop vs the simulated loop (same start, same noise): max |(x, θ) gap| = "
          f"{np.abs(over_lcm['x'][:K] - simulated['x'][:K, :2]).max():.2e}")


# ----- main ----------------------------------------------------------------------------------

@functools.cache
def controllers():
    """{name: controller y -> u}, built once."""
    return {"MPC + UKF": mpc_controller(), "LQG (saturated)": lqg_controller()}


def figure(runs, over_lcm):
    """States and estimates, forces against the limits, the velocities' estimation errors, and
    the LCM loop against the simulated one."""
    fig, axes = plt.subplots(3, 2, figsize=(13, 10), layout="constrained", sharex=True)
    colors, layer = dict(zip(runs, ("C0", "C1"))), dict(zip(runs, (3, 2)))  # the MPC's lines on top
    mpc = runs["MPC + UKF"]
    axes[0, 0].plot(mpc["t"], mpc["y"][:, 1] - np.pi, ".", color="0.6", ms=2, label="measured θ (MPC run)")
    axes[0, 1].plot(mpc["t"], mpc["y"][:, 0], ".", color="0.6", ms=2, label="measured x (MPC run)")
    for name, r in runs.items():
        for ax, i, offset in ((axes[0, 0], 1, np.pi), (axes[0, 1], 0, 0.0)):
            ax.plot(r["t"], r["x"][:, i] - offset, color=colors[name], label=f"{name}: true")
            ax.plot(r["t"], r["x_hat"][:, i] - offset, "--", color=colors[name], lw=1, label=f"{name}: estimate")
        axes[1, 0].step(r["t"], r["u"][:, 0], where="post", color=colors[name], zorder=layer[name], label=name)
        error = r["x_hat"] - r["x"]
        axes[1, 1].plot(r["t"], error[:, 3], color=colors[name], lw=1, zorder=layer[name],
                        label=f"{name}: θ̇ estimate − θ̇ (rad/s)")
        axes[1, 1].plot(r["t"], error[:, 2], ":", color=colors[name], lw=1, zorder=layer[name],
                        label=f"{name}: ẋ estimate − ẋ (m/s)")
    axes[0, 0].set(ylabel="θ − π (rad)", title="pole angle: true (solid), estimated (dashed), measured (dots)")
    axes[0, 1].set(ylabel="x (m)", title="cart position")
    for limit in (-FORCE_LIMIT, FORCE_LIMIT):
        axes[1, 0].axhline(limit, color="k", ls=":", lw=1)
    axes[1, 0].set(ylabel="u (N)", title=f"force on the cart, limits ±{FORCE_LIMIT:g} N (dotted)")
    axes[1, 1].set_yscale("symlog", linthresh=0.1)
    axes[1, 1].set(title="errors of the estimated velocities (symlog: linear within ±0.1)")
    axes[2, 0].plot(mpc["t"], mpc["x"][:, 1] - np.pi, "k-", lw=3, alpha=0.25, label="MPC + UKF simulated, one process")
    axes[2, 0].plot(over_lcm["t"][::3], over_lcm["x"][::3, 1] - np.pi, ".", color="C0", ms=3,
                    label="over LCM, two processes (from the plant's log)")
    axes[2, 0].set(xlabel="t (s)", ylabel="θ − π (rad)", title="MPC as an LCM node (tcpq on 127.0.0.1): "
                   f"{len(over_lcm['late'])} of {len(over_lcm['t']) - 1} answers late")
    axes[2, 1].step(mpc["t"], mpc["u"][:, 0], where="post", color="k", lw=3, alpha=0.25, label="simulated")
    axes[2, 1].step(over_lcm["t"], over_lcm["u"], where="post", color="C0", lw=1, label="its commands over LCM")
    axes[2, 1].set(xlabel="t (s)", ylabel="u (N)", title="force over LCM")
    for ax in axes.flat:
        ax.legend(fontsize=7)
    return fig


def main(out: pathlib.Path):
    runs = {}
    for name, controller in controllers().items():
        start = time.perf_counter()
        runs[name] = simulate_loop(controller)
        print(f"{name}: simulated in {time.perf_counter() - start:.1f} s (compiling included)")
        summary(name, runs[name])
    over_lcm = mpc_over_lcm(len(runs["MPC + UKF"]["t"]))
    lcm_report(over_lcm, runs["MPC + UKF"])
    return save(figure(runs, over_lcm), out, "mpc_estimation.png")


if __name__ == "__main__":
    os.chdir(HERE.parent)
    run(main, __doc__)
