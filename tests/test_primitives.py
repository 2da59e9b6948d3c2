"""Drake's primitive blocks (jd.systems): each against `pydrake.systems.primitives` (or
`controllers.PidController`) on the same states and inputs, in simulation against Drake's
Simulator (a zero-order hold and delay chain, a multi-rate pendulum loop), RandomSource by its
statistics and hold interval, and through jit / vmap / grad."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.systems import (Adder, ConstantVectorSource, Demultiplexer, DiscreteTimeDelay, FirstOrderLowPassFilter,
                              Gain, Multiplexer, PidController, RandomSource, Saturation, Sine, WrapToSystem,
                              ZeroOrderHold)

primitives = pytest.importorskip("pydrake.systems.primitives")
controllers = pytest.importorskip("pydrake.systems.controllers")
analysis = pytest.importorskip("pydrake.systems.analysis")
framework = pytest.importorskip("pydrake.systems.framework")


# ----- Drake's blocks evaluated at one (t, x, u) ------------------------------------------------


def drake_eval(system, t, x, u):
    """Drake's (derivative or next discrete state, output) at time t, state x and the input
    ports fixed to consecutive slices of u; the outputs of all ports concatenated."""
    context = system.CreateDefaultContext()
    context.SetTime(t)
    if context.num_continuous_states():
        context.SetContinuousState(x)
    elif context.num_discrete_state_groups():
        context.SetDiscreteState(x)
    offset = 0
    for i in range(system.num_input_ports()):
        size = system.get_input_port(i).size()
        system.get_input_port(i).FixValue(context, u[offset:offset + size])
        offset += size
    assert offset == len(u)
    y = np.concatenate([system.get_output_port(i).Eval(context) for i in range(system.num_output_ports())])
    if context.num_continuous_states():
        return system.EvalTimeDerivatives(context).CopyToVector(), y
    if context.num_discrete_state_groups():
        return system.EvalUniquePeriodicDiscreteUpdate(context).get_vector(0).CopyToVector(), y
    return np.zeros(0), y


def ours_eval(system, t, x, u):
    step = system.update if system.has_discrete_state else system.dynamics
    u = system.saturate(jnp.asarray(u))  # the contract: input limits act on the input
    return (step(t, jnp.asarray(x), u) if system.num_states else np.zeros(0)), system.output(t, jnp.asarray(x), u)


PI = np.pi
PX = np.array([[1.0, 0, 0.5], [0, 1.0, 0], [0, 0, 1.0], [0.2, 0, 1.0]])  # 3 estimated states -> (q, v) of 2 + 2
PY = np.array([[1.0, -2.0], [0.5, 1.0], [0.0, 3.0]])

BLOCKS = {
    "ZeroOrderHold": (lambda: ZeroOrderHold(0.1, 3), lambda: primitives.ZeroOrderHold(0.1, 3)),
    "DiscreteTimeDelay": (lambda: DiscreteTimeDelay(0.1, 3, 2), lambda: primitives.DiscreteTimeDelay(0.1, 3, 2)),
    "DiscreteTimeDelay(0 steps)": (lambda: DiscreteTimeDelay(0.2, 0, 2), lambda: primitives.DiscreteTimeDelay(0.2, 0, 2)),
    "Gain(scalar)": (lambda: Gain(-2.5, 3), lambda: primitives.Gain(-2.5, 3)),
    "Gain(vector)": (lambda: Gain([1.0, -2.0, 3.0]), lambda: primitives.Gain(np.array([1.0, -2.0, 3.0]))),
    "Adder": (lambda: Adder(3, 2), lambda: primitives.Adder(3, 2)),
    "Multiplexer(int)": (lambda: Multiplexer(3), lambda: primitives.Multiplexer(3)),
    "Multiplexer(sizes)": (lambda: Multiplexer([2, 1, 3]), lambda: primitives.Multiplexer([2, 1, 3])),
    "Demultiplexer(size)": (lambda: Demultiplexer(6, 2), lambda: primitives.Demultiplexer(6, 2)),
    "Demultiplexer(sizes)": (lambda: Demultiplexer([1, 3, 2]), lambda: primitives.Demultiplexer([1, 3, 2])),
    "Saturation": (lambda: Saturation([-1.0, -2.0, 0.0], [1.0, 0.5, 0.0]),
                   lambda: primitives.Saturation(np.array([-1.0, -2.0, 0.0]), np.array([1.0, 0.5, 0.0]))),
    "FirstOrderLowPassFilter": (lambda: FirstOrderLowPassFilter(0.3, 2),
                                lambda: primitives.FirstOrderLowPassFilter(0.3, 2)),
    "FirstOrderLowPassFilter(vector)": (lambda: FirstOrderLowPassFilter([0.1, 2.0, 0.7]),
                                        lambda: primitives.FirstOrderLowPassFilter(np.array([0.1, 2.0, 0.7]))),
    "PidController": (lambda: PidController([1.0, 2.0], [0.5, 0.1], [3.0, 0.2]),
                      lambda: controllers.PidController(np.array([1.0, 2.0]), np.array([0.5, 0.1]), np.array([3.0, 0.2]))),
    "PidController(projections)": (
        lambda: PidController([1.0, 2.0], [0.5, 0.1], [3.0, 0.2], state_projection=PX, output_projection=PY),
        lambda: controllers.PidController(PX, PY, np.array([1.0, 2.0]), np.array([0.5, 0.1]), np.array([3.0, 0.2]))),
    "ConstantVectorSource": (lambda: ConstantVectorSource([1.0, -2.0]),
                             lambda: primitives.ConstantVectorSource(np.array([1.0, -2.0]))),
    "Sine": (lambda: Sine(2.0, 3.0, 0.4, 2), lambda: primitives.Sine(2.0, 3.0, 0.4, 2)),
    "Sine(vectors, input-based)": (
        lambda: Sine([1.0, 2.0], [0.5, 3.0], [0.0, -1.0], is_time_based=False),
        lambda: primitives.Sine(np.array([1.0, 2.0]), np.array([0.5, 3.0]), np.array([0.0, -1.0]), False)),
}


def _drake_wrap():
    wrap = primitives.WrapToSystem(3)
    wrap.set_interval(0, -PI, PI)
    wrap.set_interval(2, 0.5, 2.0)
    return wrap


BLOCKS["WrapToSystem"] = (lambda: WrapToSystem(3).with_interval(0, -PI, PI).with_interval(2, 0.5, 2.0), _drake_wrap)


@pytest.mark.parametrize("name", list(BLOCKS))
def test_block_equals_drakes_dynamics_update_and_output(name):
    ours, theirs = (make() for make in BLOCKS[name])
    rng = np.random.default_rng(0)
    assert ours.name == name.split("(")[0]
    for _ in range(5):
        t = rng.uniform(0, 3)
        x = rng.normal(size=ours.num_states)
        u = 6 * rng.normal(size=ours.num_inputs)  # wide: saturation limits and wraps are crossed
        expected_step, expected_y = drake_eval(theirs, t, x, u)
        step, y = ours_eval(ours, t, x, u)
        np.testing.assert_allclose(y, expected_y, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(step, expected_step, rtol=1e-12, atol=1e-12)


def test_discrete_pid_is_an_euler_step_of_drakes_pid_integral():
    """z[n+1] = z[n] + h zdot, with zdot and y Drake's PidController's at (z, u)."""
    ours = PidController([1.0, 2.0], [0.5, 0.1], [3.0, 0.2], state_projection=PX, output_projection=PY,
                         sample_time=0.05)
    theirs = controllers.PidController(PX, PY, np.array([1.0, 2.0]), np.array([0.5, 0.1]), np.array([3.0, 0.2]))
    assert ours.sample_time == 0.05 and ours.has_discrete_state and ours.direct_feedthrough
    rng = np.random.default_rng(1)
    for _ in range(5):
        z, u = rng.normal(size=2), rng.normal(size=7)
        zdot, y = drake_eval(theirs, 0.0, z, u)
        np.testing.assert_allclose(ours.update(0.0, z, u), z + 0.05 * zdot, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ours.output(0.0, z, u), y, rtol=1e-12, atol=1e-12)


def test_lti_blocks_stay_linear_when_combined():
    """Gain, filter, PID are LinearSystems, so their combinations are; a Saturation in front of an
    LTI system becomes that system's input limits."""
    loop = jd.cascade(Gain(2.0, 1), FirstOrderLowPassFilter(0.5))
    assert type(loop) is jd.LinearSystem and loop.num_states == 1
    limited = jd.cascade(Saturation(-1.0, 1.0), FirstOrderLowPassFilter(0.5))
    assert type(limited) is jd.LinearSystem
    np.testing.assert_array_equal(limited.input_limits[0], [-1.0])
    held = jd.cascade(ZeroOrderHold(0.1, 2), DiscreteTimeDelay(0.1, 1, 2))
    assert type(held) is jd.LinearSystem and held.sample_time == 0.1


def test_saturation_before_a_filter_switches_at_located_events_and_matches_drake():
    """u = 2 sin(3t) -> Saturation(+-1) -> 1/(1 + 0.2 s): one LinearSystem with input limits, whose
    switching instants (|u| = 1: sin(3t) = +-1/2) simulate locates as events; the output equals
    Drake's diagram of the two blocks."""
    builder = framework.DiagramBuilder()
    sine = builder.AddSystem(primitives.Sine(2.0, 3.0, 0.0, 1))
    saturation = builder.AddSystem(primitives.Saturation(np.array([-1.0]), np.array([1.0])))
    low_pass = builder.AddSystem(primitives.FirstOrderLowPassFilter(0.2))
    builder.Connect(sine.get_output_port(0), saturation.get_input_port())
    builder.Connect(saturation.get_output_port(), low_pass.get_input_port())
    ts = np.linspace(0.1, 3.0, 15)
    expected = drake_values(builder.Build(), low_pass, low_pass.get_output_port().Eval, ts)
    system = jd.cascade(Saturation(-1.0, 1.0), FirstOrderLowPassFilter(0.2))
    traj = jd.simulate(system, (0.0, 3.0), inputs=lambda t: 2 * jnp.sin(3 * t), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.eval(jnp.asarray(ts)), expected, rtol=0, atol=1e-9)
    switches = np.sort(np.concatenate([np.pi / 6 + np.pi * np.arange(3), 5 * np.pi / 6 + np.pi * np.arange(3)])) / 3
    np.testing.assert_allclose(traj.events["times"], switches, atol=1e-9)  # |2 sin 3t| = 1


def test_ports_name_their_coordinates_and_wire_a_diagram():
    """Multi-port blocks: one port's coordinates by index or name, as DiagramBuilder.connect takes them."""
    adder = Adder(2, 2)
    assert adder.input_port(1) == adder.input_port("u1") == ("u1[0]", "u1[1]")
    assert Demultiplexer([1, 2]).output_port("y1") == ("y1[0]", "y1[1]")
    assert PidController(1.0, 0.0, 0.0).input_port("desired_state") == ("desired_state[0]", "desired_state[1]")
    with pytest.raises(KeyError, match="no port 'u7'"):
        adder.input_port("u7")
    builder = jd.DiagramBuilder()
    builder.add(ConstantVectorSource([1.0, 2.0]), "a")
    builder.add(ConstantVectorSource([10.0, 20.0]), "b")
    builder.add(adder, "adder")
    split = Demultiplexer([1, 1])
    builder.add(split, "split")
    builder.connect("a", ("adder", adder.input_port(0)))
    builder.connect("b", ("adder", adder.input_port(1)))
    builder.connect("adder", "split")
    builder.export_output(("split", split.output_port(1)))
    diagram = builder.build()
    np.testing.assert_allclose(diagram.output(0.0, jnp.zeros(0), jnp.zeros(0)), [22.0])


@pytest.mark.parametrize("make, message", [
    (lambda: ZeroOrderHold(0.1, 2, offset_sec=0.05), "offset_sec"),
    (lambda: ZeroOrderHold(-0.1, 2), "period_sec must be a positive"),
    (lambda: DiscreteTimeDelay(0.1, -1, 2), "delay_time_steps"),
    (lambda: Demultiplexer(5, 2), "not a multiple"),
    (lambda: Adder(0, 2), "num_inputs must be a positive int"),
    (lambda: Gain([1.0, 2.0], 3), "k must be a scalar or shape"),
    (lambda: Saturation([1.0], [0.0]), "u_min <= u_max"),
    (lambda: Saturation(2), "needs min_value and max_value"),
    (lambda: FirstOrderLowPassFilter([0.1, -1.0]), "time constants must be positive"),
    (lambda: PidController([1.0, 2.0], [1.0, 2.0, 3.0], [1.0, 2.0]), "ki must be"),
    (lambda: PidController(1.0, 1.0, 1.0, state_projection=np.eye(3)), "state_projection must have 2 rows"),
    (lambda: RandomSource("poisson", 1, 0.1), "unknown distribution 'poisson'"),
    (lambda: WrapToSystem(2).with_interval(0, 1.0, 1.0), "finite low < high"),
    (lambda: WrapToSystem(2).with_interval(2, 0.0, 1.0), "out of range"),
    (lambda: Sine([1.0, 2.0], 1.0, [0.0, 1.0, 2.0]), "vectors of one size"),
])
def test_bad_arguments_are_named(make, message):
    with pytest.raises((ValueError, TypeError, IndexError), match=message):
        make()


# ----- simulation against Drake's Simulator ------------------------------------------------------


def drake_values(diagram, subsystem, read, ts, x0=None):
    """Drake's Simulator (RK5, accuracy 1e-13) advanced to each of `ts`; `read(context of
    subsystem)` there. `x0`: the subsystem's initial continuous state."""
    simulator = analysis.Simulator(diagram)
    analysis.ResetIntegratorFromFlags(simulator, "runge_kutta5", 0.01)
    simulator.get_mutable_integrator().set_target_accuracy(1e-13)
    context = simulator.get_mutable_context()
    if x0 is not None:
        subsystem.GetMyMutableContextFromRoot(context).SetContinuousState(x0)
    simulator.Initialize()
    values = []
    for t in ts:
        simulator.AdvanceTo(t)
        values.append(read(subsystem.GetMyContextFromRoot(context)))
    return np.array(values)


def test_zero_order_hold_and_delay_chain_matches_drakes_simulator():
    """Sine -> ZeroOrderHold -> DiscreteTimeDelay: the held, delayed samples at every time."""
    h, steps = 0.1, 3
    builder = framework.DiagramBuilder()
    sine = builder.AddSystem(primitives.Sine(1.0, 3.0, 0.2, 2))
    zoh = builder.AddSystem(primitives.ZeroOrderHold(h, 2))
    delay = builder.AddSystem(primitives.DiscreteTimeDelay(h, steps, 2))
    builder.Connect(sine.get_output_port(0), zoh.get_input_port())
    builder.Connect(zoh.get_output_port(), delay.get_input_port())
    drake_diagram = builder.Build()
    ts = np.arange(1, 40) * 0.0371  # off the sample instants (left-continuous there)
    expected = drake_values(drake_diagram, delay, delay.get_output_port().Eval, ts)

    ours = jd.DiagramBuilder()
    our_sine = Sine(1.0, 3.0, 0.2, 2)
    ours.add(our_sine, "sine")
    ours.add(ZeroOrderHold(h, 2), "zoh")
    ours.add(DiscreteTimeDelay(h, steps, 2), "delay")
    ours.connect(("sine", our_sine.output_port(0)), "zoh")
    ours.connect("zoh", "delay")
    ours.export_output("delay")
    traj = jd.simulate(ours.build(), (0.0, 1.5))
    np.testing.assert_allclose(traj.eval(jnp.asarray(ts)), expected, rtol=0, atol=1e-14)
    assert np.any(expected != 0)  # the delay has passed: samples arrived


def multi_rate_loop_ours(kp, h_sensor, h_control):
    """The pendulum raised to TARGET and held by a discrete PID on a delayed, sampled sensor, its held
    output saturated: pendulum -> ZOH(h_sensor) -> delay(2 samples) -> [x; x_d] -> PID(h_control)
    -> ZOH(h_control) -> + feedforward -> Saturation -> pendulum."""
    builder = jd.DiagramBuilder()
    builder.add(jd.models.Pendulum(), "pendulum")
    builder.add(ZeroOrderHold(h_sensor, 2), "sensor")
    builder.add(DiscreteTimeDelay(h_sensor, 2, 2), "delay")
    builder.add(ConstantVectorSource([TARGET, 0.0]), "target")
    mux = Multiplexer([2, 2])
    builder.add(mux, "mux")
    builder.add(PidController(kp, 2.0, 1.5, sample_time=h_control), "pid")
    builder.add(ZeroOrderHold(h_control, 1), "hold")
    builder.add(ConstantVectorSource([0.5]), "feedforward")
    adder = Adder(2, 1)
    builder.add(adder, "adder")
    builder.add(Saturation(-3.0, 3.0), "saturation")
    builder.connect("pendulum", "sensor")
    builder.connect("sensor", "delay")
    builder.connect("delay", ("mux", mux.input_port(0)))
    builder.connect("target", ("mux", mux.input_port(1)))
    builder.connect("mux", "pid")
    builder.connect("pid", "hold")
    builder.connect("hold", ("adder", adder.input_port(0)))
    builder.connect("feedforward", ("adder", adder.input_port(1)))
    builder.connect("adder", "saturation")
    builder.connect("saturation", "pendulum")
    builder.export_output("pendulum")
    return builder.build("MultiRateLoop")


def multi_rate_loop_drake(kp, h_sensor, h_control):
    """The same loop of Drake blocks; the discrete PID written out as Drake's PID law with a
    DiscreteTimeIntegrator: e = x_d - x, y = kp e_q + kd e_v + ki z, z[n+1] = z[n] + h e_q[n]."""
    examples = pytest.importorskip("pydrake.examples")
    builder = framework.DiagramBuilder()
    pendulum = builder.AddSystem(examples.PendulumPlant())
    sensor = builder.AddSystem(primitives.ZeroOrderHold(h_sensor, 2))
    delay = builder.AddSystem(primitives.DiscreteTimeDelay(h_sensor, 2, 2))
    target = builder.AddSystem(primitives.ConstantVectorSource(np.array([TARGET, 0.0])))
    error = builder.AddSystem(primitives.Adder(2, 2))
    negate = builder.AddSystem(primitives.Gain(-1.0, 2))
    split = builder.AddSystem(primitives.Demultiplexer(2, 1))
    integral = builder.AddSystem(primitives.DiscreteTimeIntegrator(1, h_control))
    gains = [builder.AddSystem(primitives.Gain(k, 1)) for k in (kp, 1.5, 2.0)]  # e_q, e_v, z
    pid = builder.AddSystem(primitives.Adder(3, 1))
    hold = builder.AddSystem(primitives.ZeroOrderHold(h_control, 1))
    feedforward = builder.AddSystem(primitives.ConstantVectorSource(np.array([0.5])))
    total = builder.AddSystem(primitives.Adder(2, 1))
    saturation = builder.AddSystem(primitives.Saturation(np.array([-3.0]), np.array([3.0])))
    builder.Connect(pendulum.get_state_output_port(), sensor.get_input_port())
    builder.Connect(sensor.get_output_port(), delay.get_input_port())
    builder.Connect(delay.get_output_port(), negate.get_input_port())
    builder.Connect(target.get_output_port(), error.get_input_port(0))
    builder.Connect(negate.get_output_port(), error.get_input_port(1))
    builder.Connect(error.get_output_port(), split.get_input_port())
    builder.Connect(split.get_output_port(0), gains[0].get_input_port())
    builder.Connect(split.get_output_port(1), gains[1].get_input_port())
    builder.Connect(split.get_output_port(0), integral.get_input_port())
    builder.Connect(integral.get_output_port(), gains[2].get_input_port())
    for k, gain in enumerate(gains):
        builder.Connect(gain.get_output_port(), pid.get_input_port(k))
    builder.Connect(pid.get_output_port(), hold.get_input_port())
    builder.Connect(hold.get_output_port(), total.get_input_port(0))
    builder.Connect(feedforward.get_output_port(), total.get_input_port(1))
    builder.Connect(total.get_output_port(), saturation.get_input_port())
    builder.Connect(saturation.get_output_port(), pendulum.get_input_port())
    return builder.Build(), pendulum


def pendulum_state(context):
    return context.get_continuous_state_vector().CopyToVector()


H_SENSOR, H_CONTROL = 1 / 64, 1 / 32  # binary fractions: common instants coincide exactly in both
TARGET = 0.5  # rad: held by 4.9 sin(0.5) = 2.3 N m, within the saturation; reached saturated


def test_multi_rate_pendulum_loop_matches_drakes_simulator():
    ts = np.linspace(0.01, 3.0, 25)
    drake_diagram, pendulum = multi_rate_loop_drake(8.0, H_SENSOR, H_CONTROL)
    expected = drake_values(drake_diagram, pendulum, pendulum_state, ts)
    loop = multi_rate_loop_ours(8.0, H_SENSOR, H_CONTROL)
    assert loop.sample_times == (H_SENSOR, H_CONTROL)
    traj = jd.simulate(loop, (0.0, 3.0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.eval(jnp.asarray(ts)), expected, rtol=0, atol=1e-9)
    # the loop did something: the torque saturated at first, and the pendulum rose towards the target
    _, outputs = loop.signals(0, 0.02, traj.state(0.02), jnp.zeros(0))
    assert outputs[loop.names.index("adder")][0] > 3.0 and outputs[loop.names.index("saturation")][0] == 3.0
    assert 0.3 < expected[-1, 0] < 0.7


def continuous_loop_start(loop, pendulum_x0):
    """The loop's state with the pendulum's part set (the filter and the integral at 0)."""
    return loop.initial_state().at[np.array([loop.state_frame.index("pendulum.theta"),
                                             loop.state_frame.index("pendulum.thetadot")])].set(pendulum_x0)


def continuous_loop_ours(kp=6.0, ki=1.0, kd=1.2):
    """pendulum -> WrapToSystem(theta into [-pi, pi)) -> FirstOrderLowPassFilter -> PID (to the
    upright-down rest [0, 0]) -> Gain -> pendulum, all continuous."""
    builder = jd.DiagramBuilder()
    builder.add(jd.models.Pendulum(), "pendulum")
    builder.add(WrapToSystem(2).with_interval(0, -PI, PI), "wrap")
    builder.add(FirstOrderLowPassFilter(0.05, 2), "filter")
    builder.add(ConstantVectorSource([0.0, 0.0]), "target")
    pid = PidController(kp, ki, kd)
    builder.add(pid, "pid")
    builder.add(Gain(0.8, 1), "gain")
    builder.connect("pendulum", "wrap")
    builder.connect("wrap", "filter")
    builder.connect("filter", ("pid", pid.input_port("estimated_state")))
    builder.connect("target", ("pid", pid.input_port("desired_state")))
    builder.connect("pid", "gain")
    builder.connect("gain", "pendulum")
    builder.export_output("pendulum")
    return builder.build("ContinuousLoop")


def test_continuous_loop_with_wrap_filter_pid_and_gain_matches_drakes_simulator():
    """From theta = 2 pi + 0.6 the wrapped angle is 0.6: the loop brings the pendulum to 2 pi."""
    examples = pytest.importorskip("pydrake.examples")
    x0 = np.array([2 * PI + 0.6, 0.0])
    builder = framework.DiagramBuilder()
    pendulum = builder.AddSystem(examples.PendulumPlant())
    wrap = builder.AddSystem(primitives.WrapToSystem(2))
    wrap.set_interval(0, -PI, PI)
    low_pass = builder.AddSystem(primitives.FirstOrderLowPassFilter(0.05, 2))
    target = builder.AddSystem(primitives.ConstantVectorSource(np.zeros(2)))
    pid = builder.AddSystem(controllers.PidController(np.array([6.0]), np.array([1.0]), np.array([1.2])))
    gain = builder.AddSystem(primitives.Gain(0.8, 1))
    builder.Connect(pendulum.get_state_output_port(), wrap.get_input_port())
    builder.Connect(wrap.get_output_port(), low_pass.get_input_port())
    builder.Connect(low_pass.get_output_port(), pid.get_input_port_estimated_state())
    builder.Connect(target.get_output_port(), pid.get_input_port_desired_state())
    builder.Connect(pid.get_output_port_control(), gain.get_input_port())
    builder.Connect(gain.get_output_port(), pendulum.get_input_port())
    drake_diagram = builder.Build()
    ts = np.linspace(0.05, 4.0, 20)
    expected = drake_values(drake_diagram, pendulum, pendulum_state, ts, x0)

    loop = continuous_loop_ours()
    assert loop.num_continuous_states == 2 + 2 + 1 and not loop.has_discrete_state
    traj = jd.simulate(loop, (0.0, 4.0), continuous_loop_start(loop, x0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.eval(jnp.asarray(ts)), expected, rtol=0, atol=1e-9)
    assert abs(expected[-1, 0] - 2 * PI) < 0.1  # regulated to the wrapped rest


# ----- RandomSource: statistics and the hold interval ------------------------------------------

MOMENTS = {"uniform": (0.5, 1 / 12, "uniform"), "gaussian": (0.0, 1.0, "norm"), "exponential": (1.0, 1.0, "expon")}


def test_random_sources_draw_drakes_distributions_held_over_their_interval():
    """64 outputs x 100 intervals of each distribution: the hold (constant within [kh, (k+1)h),
    new at kh), the moments, the distribution (Kolmogorov-Smirnov against the exact CDF and
    against Drake's samples), no correlation between consecutive samples; the nominal signal is
    the median. Ours: a gaussian source simulated; the other distributions' outputs at the same
    held noise samples (every distribution maps the one held w)."""
    stats = pytest.importorskip("scipy.stats")
    from pydrake.common import RandomDistribution

    h, n, count = 0.05, 64, 100
    middles, lates = (np.arange(count) + 0.5) * h, (np.arange(count) + 0.95) * h
    traj = jd.simulate(RandomSource("gaussian", n, h), (0.0, count * h), key=jax.random.key(7))
    w_middle, w_late = (traj.eval(jnp.asarray(ts)) for ts in (middles, lates))
    for name, (mean, variance, scipy_name) in MOMENTS.items():
        source = RandomSource(name, n, h)
        ours = tuple(np.asarray(source.mode_output(0, 0.0, jnp.zeros(0), w.ravel())).reshape(w.shape)
                     for w in (w_middle, w_late))
        drake_source = primitives.RandomSource(getattr(RandomDistribution, "k" + name.capitalize()), n, h)
        simulator = analysis.Simulator(drake_source)
        simulator.Initialize()
        drake = {}
        for t in np.sort(np.concatenate([middles, lates])):
            simulator.AdvanceTo(t)
            drake[t] = drake_source.get_output_port().Eval(simulator.get_context())
        drake = tuple(np.array([drake[t] for t in ts]) for ts in (middles, lates))
        for middle, late in (drake, ours):
            np.testing.assert_array_equal(middle, late)  # held over each interval
            assert np.all(middle[1:] != middle[:-1])  # a new sample at each kh
            samples = middle.ravel()
            assert abs(samples.mean() - mean) < 5 * np.sqrt(variance / samples.size)
            assert abs(samples.var() / variance - 1) < 0.1
            assert stats.kstest(samples, scipy_name).pvalue > 1e-3
            assert abs(np.corrcoef(middle[1:].ravel(), middle[:-1].ravel())[0, 1]) < 5 / np.sqrt(samples.size)
        assert stats.ks_2samp(ours[0].ravel(), drake[0].ravel()).pvalue > 1e-3
        nominal = source.output(0.0, jnp.zeros(0), jnp.zeros(0))
        np.testing.assert_allclose(nominal, getattr(stats, scipy_name).median(), rtol=1e-12)


def test_random_source_into_a_filter_has_the_closed_form_variance_over_a_vmapped_batch_of_keys():
    r"""Gaussian samples held over h into 1/(1 + tau s): x[k+1] = a x[k] + (1 - a) w[k], a = exp(-h/tau),
    so x(Nh) has variance (1 - a)^2 (1 - a^(2N)) / (1 - a^2). One key per member, vmapped."""
    h, tau, steps = 0.1, 0.3, 8
    system = jd.cascade(RandomSource("gaussian", 1, h), FirstOrderLowPassFilter(tau))
    assert system.is_stochastic and system.noise_groups == ((1, h, 1.0),)
    keys = jax.random.split(jax.random.key(3), 2000)
    finals = jax.jit(jax.vmap(lambda k: jd.simulate(system, (0.0, steps * h), key=k, dense=False).final_state))(keys)
    a = np.exp(-h / tau)
    expected = (1 - a) ** 2 * (1 - a ** (2 * steps)) / (1 - a**2)
    assert float(jnp.var(finals)) == pytest.approx(expected, rel=0.1)


# ----- jit, vmap and grad ----------------------------------------------------------------------


def test_gradient_through_gain_and_filter_equals_the_closed_form():
    r"""u = sin(w t) -> Gain(k) -> FirstOrderLowPassFilter(tau) (one LinearSystem), from rest:
    $y(T) = k\,(\sin wT - \tau w \cos wT + \tau w e^{-T/\tau}) / (1 + \tau^2 w^2)$; its gradient
    in (k, tau) by reverse mode through simulate equals the closed form's."""
    w, T = 2.0, 1.5

    def simulated(params):
        system = jd.cascade(Gain(params[0], 1), FirstOrderLowPassFilter(params[1]))
        return jd.simulate(system, (0.0, T), inputs=lambda t: jnp.sin(w * t), rtol=1e-11, atol=1e-13,
                           dense=False).final_state[0]

    def closed_form(params):
        k, tau = params
        return k * (jnp.sin(w * T) - tau * w * jnp.cos(w * T) + tau * w * jnp.exp(-T / tau)) / (1 + (tau * w) ** 2)

    params = jnp.array([1.7, 0.4])
    value, grad = jax.jit(jax.value_and_grad(simulated))(params)
    assert float(value) == pytest.approx(float(closed_form(params)), abs=1e-9)
    np.testing.assert_allclose(grad, jax.grad(closed_form)(params), rtol=1e-7)


@pytest.mark.slow  # ~40 s of compiles; the default test_multi_rate_... and test_gradients_... cover simulate and grad
def test_multi_rate_loop_vmaps_over_gains_and_differentiates_in_float64_and_float32():
    """d J / d kp, J = sum of squared angle errors at the sample instants, against central
    differences; a vmapped batch of gains equal to one-at-a-time runs; float32 close to float64."""
    ts = jnp.arange(1, 97) * H_CONTROL

    def cost(kp, dtype=jnp.float64):
        loop = multi_rate_loop_ours(kp, H_SENSOR, H_CONTROL)
        traj = jd.simulate(loop, (0.0, 3.0), jnp.zeros(loop.num_states, dtype), rtol=1e-10, atol=1e-10)
        return jnp.sum((traj.eval(ts)[:, 0] - TARGET) ** 2)

    grad = jax.grad(cost)(8.0)
    eps = 1e-4
    assert float(grad) == pytest.approx(float((cost(8.0 + eps) - cost(8.0 - eps)) / (2 * eps)), rel=1e-5)
    gains = jnp.array([4.0, 8.0, 12.0])
    batch = jax.vmap(cost)(gains)
    np.testing.assert_allclose(batch, [cost(k) for k in gains], rtol=1e-10)
    assert float(cost(8.0, jnp.float32)) == pytest.approx(float(cost(8.0)), rel=1e-3)


def test_the_pid_docstrings_set_point_loop_holds_the_pendulum_where_asked():
    """The wiring PidController's docstring shows (feedback feeds one vector, the controller has
    two ports: its error names the remedy). With integral action the equilibrium is the set
    point exactly, the integral holding gravity's torque: k_i z = m g l sin(q_d)."""
    pid = jd.PidController(kp=20.0, ki=5.0, kd=4.0)
    with pytest.raises(ValueError, match="several ports; feedback feeds one vector.*DiagramBuilder"):
        jd.feedback(jd.models.Pendulum(), pid)
    builder = jd.DiagramBuilder()
    builder.add(jd.models.Pendulum(), "plant")
    builder.add(pid, "pid")
    builder.connect("plant", ("pid", pid.input_port("estimated_state")))
    builder.connect("pid", "plant")
    builder.export_input(("pid", pid.input_port("desired_state")))
    builder.export_output("plant")
    loop = builder.build("PendulumPid")
    x = jd.simulate(loop, (0.0, 100.0), inputs=lambda t: jnp.array([0.5, 0.0]), rtol=1e-9, atol=1e-12).final_state
    p = jd.models.Pendulum()
    np.testing.assert_allclose(x, [0.5, 0.0, p.m * p.g * p.l * np.sin(0.5) / 5.0], atol=1e-6)
