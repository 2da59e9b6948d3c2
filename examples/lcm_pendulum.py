"""A pendulum plant and its LQR controller as two processes closing the loop over LCM
(Underactuated Robotics, D.5.1: `runLCM`), on a loopback relay (tcpq://127.0.0.1), never a
multicast group.

The plant node (`python -m jaxdrake.lcm examples/_lcm_nodes.py:plant --lockstep ...`) integrates
the pendulum over each 10 ms tick and publishes its state on `PendulumState`; the controller
node answers each state with u = -K (x - x_upright) on `PendulumInput`. Both write LCM event
logs (replayable with `lcm-logplayer`). The plot: the trajectory decoded from the plant's log
against the same loop simulated in one process (sampled, and continuous).

Run:  python examples/lcm_pendulum.py [--out DIR]     (saves lcm_pendulum.png)
"""

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
from jaxdrake.lcm import LoopbackRelay, SignalCoder  # noqa: E402
import _lcm_nodes  # noqa: E402  (examples/_lcm_nodes.py)
from _cli import run, save  # noqa: E402

jax.config.update("jax_enable_x64", True)
HERE = pathlib.Path(__file__).resolve().parent
X0, RATE, TICKS = [np.pi - 0.6, 0.0], 100.0, 400


def node(name, url, *extra):
    process = subprocess.Popen([sys.executable, "-m", "jaxdrake.lcm", f"{HERE / '_lcm_nodes.py'}:{name}",
                                "--url", url, "--x64", *extra], cwd=HERE.parent, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    line = ""
    while not line.startswith("node "):  # compiled and subscribed
        line = process.stdout.readline()
        if not line and process.poll() is not None:
            raise RuntimeError(f"the {name} node did not start")
    return process


def closed_loop_over_lcm(folder):
    """Run both nodes; return the plant's logged (times, states, inputs) and the nodes' summaries."""
    with LoopbackRelay() as relay:
        controller = node("controller", relay.url, "--log", str(folder / "controller.log"))
        time.sleep(0.5)
        plant = node("plant", relay.url, "--rate", str(RATE), "--lockstep", "--max-ticks", str(TICKS),
                     "--input-timeout", "10", "--x0", *map(str, X0), "--log", str(folder / "plant.log"))
        plant_out, _ = plant.communicate(timeout=300)
        controller.send_signal(signal.SIGINT)
        controller_out, _ = controller.communicate(timeout=60)
    pendulum = _lcm_nodes.plant()
    states, inputs = SignalCoder(pendulum.output_frame), SignalCoder(pendulum.input_frame)
    log = {"PendulumState": [], "PendulumInput": []}
    for event in lcm.EventLog(str(folder / "plant.log"), "r"):
        log[event.channel].append(event.data)
    times, xs = zip(*(states.decode(d) for d in log["PendulumState"]))
    us = [inputs.decode(d)[1] for d in log["PendulumInput"]]
    summaries = [next(line for line in o.splitlines() if line.startswith("stopped:")) for o in (plant_out, controller_out)]
    return np.array(times), np.array(xs), np.array(us), summaries


def main(out: pathlib.Path):
    with tempfile.TemporaryDirectory() as tmp:
        times, xs, us, summaries = closed_loop_over_lcm(pathlib.Path(tmp))
    print("plant:", summaries[0])
    print("controller:", summaries[1])
    pendulum, lqr = _lcm_nodes.plant(), _lcm_nodes.controller()
    dt = 1 / RATE

    def step(x, k):  # the same sampled loop in one process
        u = lqr.output(k * dt, jnp.zeros(0), x)
        return jd.simulate(pendulum, (k * dt, k * dt + dt), x, inputs=lambda s: u, solver="rk4", dt=dt / 10,
                           dense=False).final_state, x

    sampled = np.asarray(jax.jit(lambda x0: jax.lax.scan(step, x0, jnp.arange(TICKS))[1])(jnp.asarray(X0)))
    continuous = jd.simulate(jd.feedback(pendulum, lqr), (0.0, times[-1]), jnp.asarray(X0), rtol=1e-10, atol=1e-12)
    s = jnp.linspace(0.0, times[-1], 500)
    print(f"logged vs in-process sampled loop: {np.abs(xs - sampled).max():.1e}; "
          f"vs continuous loop: {np.abs(xs - np.asarray(continuous.state(jnp.asarray(times)))).max():.1e}")

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True, layout="constrained")
    axes[0].plot(s, np.asarray(continuous.state(s))[:, 0], "k-", lw=3, alpha=0.25, label="continuous loop, one process")
    axes[0].plot(times, sampled[:, 0], "-", color="C1", label="sampled loop (10 ms), one process")
    axes[0].plot(times[::5], xs[::5, 0], ".", color="C0", label="logged over LCM, two processes")
    axes[0].axhline(np.pi, color="k", ls=":", lw=1)
    axes[0].set(ylabel="θ (rad)", title="pendulum balanced by LQR across two processes (tcpq on 127.0.0.1)")
    axes[0].legend(fontsize=8)
    axes[1].step(times, us[:, 0], where="post", color="C0", label="u from the controller's messages")
    axes[1].set(xlabel="t (s)", ylabel="u (N m)")
    axes[1].legend(fontsize=8)
    save(fig, out, "lcm_pendulum.png")


if __name__ == "__main__":
    os.chdir(HERE.parent)
    run(main, __doc__)
