"""The LCM pendulum on a ROS 1 network (Underactuated Robotics, D.5.2): the plant node speaks LCM,
the ROS–LCM translator (`python -m jaxdrake.ros`) echoes its state on the ROS topic
/pendulum/state (sensor_msgs/JointState) and carries setpoints from /pendulum/setpoint
(std_msgs/Float64MultiArray) to the controller.

The plant node (`python -m jaxdrake.lcm examples/_lcm_nodes.py:plant`, 100 Hz, real time) and
the translator are processes of their own; the controller here answers each state with
u = m g l sin(θ_ref) - K (x - [θ_ref, 0]) (K: LQR about the upright, as in `lcm_pendulum.py`).
Everything runs on 127.0.0.1: a roscore at a free port (or yours, `--master URI`), LCM on a
LoopbackRelay. After 3 s the script runs `rostopic pub` to move the setpoint from π to π + 0.3
and `rostopic echo -n 1 /pendulum/state`; by hand, while it runs:

    rostopic echo /pendulum/state
    rostopic pub -r 10 /pendulum/setpoint std_msgs/Float64MultiArray "{data: [3.0]}"

Needs Debian's ROS 1 (docs/ros.md). Run:  python examples/ros_pendulum.py [--out DIR]
(saves ros_pendulum.png)
"""

import os
import pathlib
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import xmlrpc.client

import jax
import jax.numpy as jnp
import lcm
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from jaxdrake.lcm import LoopbackRelay, SignalCoder  # noqa: E402
from jaxdrake.systems import Frame  # noqa: E402
import _lcm_nodes  # noqa: E402  (examples/_lcm_nodes.py)
from _cli import run, save  # noqa: E402

jax.config.update("jax_enable_x64", True)
HERE = pathlib.Path(__file__).resolve().parent
X0, DURATION, STEP_AT, NEW_SETPOINT = [np.pi - 0.2, 0.0], 8.0, 3.0, np.pi + 0.3


def roscore(folder):
    """A roscore on 127.0.0.1 at a free port; returns (process, environment for ROS tools)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_IP="127.0.0.1",
               ROS_HOSTNAME="127.0.0.1", ROS_HOME=str(folder), ROS_LOG_DIR=str(folder / "log"))
    process = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    for _ in range(600):
        try:
            xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"]).getPid("/example")
            return process, env
        except OSError:
            time.sleep(0.1)
    raise RuntimeError("roscore did not start")


def started(command, env, marker):
    process = subprocess.Popen(command, cwd=HERE.parent, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    line = ""
    while not line.startswith(marker):
        line = process.stdout.readline()
        if not line and process.poll() is not None:
            raise RuntimeError(f"{command[2]} did not start")
    return process


class SetpointController:
    """Answers each PendulumState with u on PendulumInput, tracking the newest PendulumSetpoint."""

    def __init__(self, url):
        self.plant = _lcm_nodes.plant()
        self.K = np.asarray(jd.control.lqr(self.plant, jnp.diag(jnp.array([10.0, 1.0])), jnp.eye(1),
                                           x0=jnp.asarray(_lcm_nodes.UPRIGHT)).K)
        self.state, self.input = SignalCoder(self.plant.output_frame), SignalCoder(self.plant.input_frame)
        self.setpoint_coder = SignalCoder(Frame("PendulumSetpoint", ("theta_ref",)))
        self.theta_ref, self.stop = np.pi, threading.Event()
        self.bus = lcm.LCM(url)
        self.bus.subscribe("PendulumState", self.on_state)
        self.bus.subscribe("PendulumSetpoint", self.on_setpoint)

    def on_setpoint(self, channel, data):
        self.theta_ref = float(self.setpoint_coder.decode(data)[1][0])

    def on_state(self, channel, data):
        t, x = self.state.decode(data)
        p = self.plant
        u = p.m * p.g * p.l * np.sin(self.theta_ref) - self.K @ (x - [self.theta_ref, 0.0])
        self.bus.publish("PendulumInput", self.input.encode(t, u))

    def spin(self):
        while not self.stop.is_set():
            self.bus.handle_timeout(20)


def run_on_ros(folder):
    """The nodes, the translator and the ROS tools; returns the plant's logged (times, states),
    the time the setpoint was published, and one echoed /pendulum/state message."""
    core, env = roscore(folder)
    relay = LoopbackRelay().start()
    controller = SetpointController(relay.url)
    spinner = threading.Thread(target=controller.spin)
    spinner.start()
    nodes = HERE / "_lcm_nodes.py"
    try:
        translator = started([sys.executable, "-m", "jaxdrake.ros", "--url", relay.url,
                              "--to-ros", "PendulumState", "/pendulum/state", "sensor_msgs/JointState",
                              f"state_of={nodes}:plant",
                              "--to-lcm", "/pendulum/setpoint", "PendulumSetpoint", "std_msgs/Float64MultiArray",
                              "signal=theta_ref"], env, "translator between")
        plant = started([sys.executable, "-m", "jaxdrake.lcm", f"{nodes}:plant", "--url", relay.url, "--x64",
                         "--rate", "100", "--duration", str(DURATION), "--x0", *map(str, X0),
                         "--log", str(folder / "plant.log")], env, "node ")
        start = time.time()
        time.sleep(STEP_AT)
        publisher = subprocess.Popen(["rostopic", "pub", "-r", "10", "/pendulum/setpoint", "std_msgs/Float64MultiArray",
                                      f"{{data: [{NEW_SETPOINT}]}}"], env=env, stdout=subprocess.DEVNULL)
        stepped = time.time() - start
        echo = subprocess.run(["rostopic", "echo", "-n", "1", "/pendulum/state"], env=env, capture_output=True,
                              text=True, timeout=60).stdout
        plant.communicate(timeout=120)
        publisher.terminate()
        publisher.wait()
        translator.send_signal(signal.SIGINT)
        summary = translator.communicate(timeout=60)[0]
    finally:
        controller.stop.set()
        spinner.join()
        relay.close()
        os.killpg(core.pid, signal.SIGINT)
        core.wait()
    coder = SignalCoder(_lcm_nodes.plant().output_frame)
    times, states = zip(*(coder.decode(e.data) for e in lcm.EventLog(str(folder / "plant.log"), "r")
                          if e.channel == "PendulumState"))
    return np.array(times), np.array(states), stepped, echo, summary


def main(out: pathlib.Path):
    with tempfile.TemporaryDirectory() as tmp:
        times, states, stepped, echo, summary = run_on_ros(pathlib.Path(tmp))
    print("rostopic echo -n 1 /pendulum/state:\n" + echo.split("---")[0])
    print(summary.strip())
    late = times > stepped + 2.0
    print(f"θ after the setpoint step: {states[late, 0].mean():.4f} (setpoint {NEW_SETPOINT:.4f})")
    fig, ax = plt.subplots(figsize=(9, 4), layout="constrained")
    ax.plot(times, states[:, 0], color="C0", label="θ, logged by the plant node (LCM)")
    ax.step([0, stepped, times[-1]], [np.pi, NEW_SETPOINT, NEW_SETPOINT], where="post", color="k", ls=":",
            label="setpoint, from rostopic pub via the translator")
    ax.set(xlabel="t (s)", ylabel="θ (rad)", title="LCM pendulum on a ROS 1 network (roscore on 127.0.0.1)")
    ax.legend(fontsize=8)
    save(fig, out, "ros_pendulum.png")


if __name__ == "__main__":
    os.chdir(HERE.parent)
    run(main, __doc__)
