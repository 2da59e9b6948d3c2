"""Composition (notes D.3.4): cascade, feedback, parallel, diagrams; structure preservation;
mixed sample times; jit / vmap / grad through combinators."""

import fractions

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jaxdrake as jd
from jaxdrake.models import BouncingBall, Pendulum

TIGHT = dict(rtol=1e-12, atol=1e-12)

A1 = np.array([[0.0, 1.0], [-2.0, -0.3]])
B1 = np.array([[0.0, 0.5], [1.0, 0.0]])
C1 = np.array([[1.0, 0.0]])
D1 = np.zeros((1, 2))
A2 = np.array([[-1.0, 0.2], [0.0, -4.0]])
B2 = np.array([[1.0], [0.5]])
C2 = np.array([[2.0, -1.0], [0.0, 1.0]])
D2 = np.array([[0.5], [0.25]])


def transfer(A, B, C, D, s):
    """G(s) = C (sI - A)^-1 B + D: independent of the state coordinates."""
    return C @ np.linalg.solve(s * np.eye(A.shape[0]) - A, B) + D


def transfer_of(sys, s):
    return transfer(*(np.asarray(m) for m in (sys.A, sys.B, sys.C, sys.D)), s)


POINTS = [0.3 + 1.0j, -0.5 + 2.0j, 2.0, 1j]


def test_cascade_of_linear_systems_is_linear_with_the_block_formulas():
    a, b = jd.LinearSystem(A1, B1, C1, D1), jd.LinearSystem(A2, B2, C2, D2)
    c = jd.cascade(a, b)
    assert type(c) is jd.LinearSystem and not c.is_discrete
    np.testing.assert_allclose(c.A, np.block([[A1, np.zeros((2, 2))], [B2 @ C1, A2]]), atol=0)
    np.testing.assert_allclose(c.B, np.vstack([B1, B2 @ D1]), atol=0)
    np.testing.assert_allclose(c.C, np.hstack([D2 @ C1, C2]), atol=0)
    np.testing.assert_allclose(c.D, D2 @ D1, atol=0)
    for s in POINTS:  # series connection: G = G_b G_a
        np.testing.assert_allclose(transfer_of(c, s), transfer(A2, B2, C2, D2, s) @ transfer(A1, B1, C1, D1, s),
                                   rtol=1e-12)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_feedback_of_linear_systems_is_linear_with_the_closed_loop_transfer(sign):
    a = jd.LinearSystem(A2, B2, C2, D2)            # 1 input, 2 outputs, direct feedthrough
    b = jd.LinearSystem(A1, B1, C1, D1)            # 2 inputs, 1 output, none
    f = jd.feedback(a, b, sign=sign)
    assert type(f) is jd.LinearSystem
    np.testing.assert_allclose(
        f.A, np.block([[A2 + sign * B2 @ D1 @ C2, sign * B2 @ C1], [B1 @ C2, A1 + sign * B1 @ D2 @ C1]]), atol=1e-15)
    np.testing.assert_allclose(f.B, np.vstack([B2, B1 @ D2]), atol=0)
    np.testing.assert_allclose(f.C, np.hstack([C2, sign * D2 @ C1]), atol=0)
    np.testing.assert_allclose(f.D, D2, atol=0)
    for s in POINTS:  # y = G_a (u + sign G_b y)  =>  y = (I - sign G_a G_b)^-1 G_a u
        Ga, Gb = transfer(A2, B2, C2, D2, s), transfer(A1, B1, C1, D1, s)
        expected = np.linalg.solve(np.eye(2) - sign * Ga @ Gb, Ga)
        np.testing.assert_allclose(transfer_of(f, s), expected, rtol=1e-11)


def test_linear_cascade_and_feedback_simulate_like_the_uncombined_equations():
    a, b = jd.LinearSystem(A2, B2, C2, D2), jd.LinearSystem(A1, B1, C1, D1)
    u = lambda t: jnp.array([jnp.sin(3 * t)])
    x0 = jnp.array([1.0, -0.5, 0.3, 0.2])

    def by_hand(t, x, _):  # u_a = u + y_b, u_b = y_a, written out
        xa, xb = x[:2], x[2:]
        ua = u(t) + C1 @ xb
        ya = C2 @ xa + D2 @ ua
        return jnp.concatenate([A2 @ xa + B2 @ ua, A1 @ xb + B1 @ ya])

    ref = jd.simulate(jd.System.from_functions(by_hand, num_states=4), (0, 3), x0, **TIGHT)
    got = jd.simulate(jd.feedback(a, b), (0, 3), x0, inputs=u, **TIGHT)
    np.testing.assert_allclose(got.final_state, ref.final_state, rtol=1e-10, atol=1e-12)

    cas = jd.simulate(jd.cascade(b, a), (0, 3), x0[jnp.array([2, 3, 0, 1])], inputs=lambda t: jnp.array([jnp.sin(t), 1.0]), **TIGHT)

    def cascade_by_hand(t, x, _):
        xb, xa = x[:2], x[2:]
        ub = jnp.array([jnp.sin(t), 1.0])
        return jnp.concatenate([A1 @ xb + B1 @ ub, A2 @ xa + B2 @ (C1 @ xb + D1 @ ub)])

    ref = jd.simulate(jd.System.from_functions(cascade_by_hand, num_states=4), (0, 3), x0[jnp.array([2, 3, 0, 1])], **TIGHT)
    np.testing.assert_allclose(cas.final_state, ref.final_state, rtol=1e-10, atol=1e-12)


def test_parallel_of_linear_systems_is_block_diagonal():
    a, b = jd.LinearSystem(A1, B1, C1, D1), jd.LinearSystem(A2, B2, C2, D2)
    p = jd.parallel(a, b)
    assert type(p) is jd.LinearSystem
    for s in POINTS:
        G = transfer_of(p, s)
        np.testing.assert_allclose(G[:1, :2], transfer(A1, B1, C1, D1, s), rtol=1e-13)
        np.testing.assert_allclose(G[1:, 2:], transfer(A2, B2, C2, D2, s), rtol=1e-13)
        np.testing.assert_allclose(G[:1, 2:], 0, atol=0)
        np.testing.assert_allclose(G[1:, :2], 0, atol=0)
    assert p.input_frame.coordinates == ("LinearSystem.u0", "LinearSystem.u1", "LinearSystem2.u0")


def test_discrete_linear_systems_keep_their_sample_time():
    a = jd.LinearSystem(0.5 * A1, B1, C1, sample_time=0.1)
    b = jd.LinearSystem(0.5 * A2, B2, C2, D2, sample_time=0.1)
    c = jd.cascade(a, b)
    assert type(c) is jd.LinearSystem and c.sample_time == 0.1 and c.num_discrete_states == 4
    mixed = jd.cascade(a, jd.LinearSystem(A2, B2, C2, D2, sample_time=0.25))
    assert type(mixed) is jd.Diagram and mixed.sample_times == (0.1, 0.25) and mixed.sample_time is None
    continuous = jd.cascade(a, jd.LinearSystem(A2, B2, C2, D2))
    assert type(continuous) is jd.Diagram and continuous.sample_times == (0.1,)
    assert continuous.num_discrete_states == 2 and continuous.num_continuous_states == 2


def pd_controller(kp, kd, target=np.pi):
    """u = -kp (theta - target) - kd thetadot: static, direct feedthrough, gains as parameters."""
    return jd.System.from_functions(
        output=lambda t, x, u, k: jnp.atleast_1d(-k[0] * (u[0] - target) - k[1] * u[1]),
        num_states=0, num_inputs=2, num_outputs=1, params=jnp.array([kp, kd]))


def pendulum_closed_loop_by_hand(kp, kd, plant=Pendulum()):
    def f(t, x, u):
        tau = -kp * (x[0] - np.pi) - kd * x[1] + u[0]
        return jnp.array([x[1], (tau - plant.b * x[1] - plant.m * plant.g * plant.l * jnp.sin(x[0]))
                          / (plant.m * plant.l ** 2)])
    return jd.System.from_functions(f, num_states=2, num_inputs=1)


def test_pendulum_under_pd_feedback_simulates_like_the_closed_loop_by_hand():
    closed = jd.feedback(Pendulum(), pd_controller(10.0, 1.0))
    assert type(closed) is jd.Diagram and not closed.direct_feedthrough
    assert closed.input_frame == Pendulum().input_frame and closed.output_frame == Pendulum().output_frame
    u = lambda t: jnp.array([0.3 * jnp.cos(2 * t)])
    x0 = jnp.array([0.5, 0.0])
    got = jd.simulate(closed, (0, 5), x0, inputs=u, **TIGHT)
    ref = jd.simulate(pendulum_closed_loop_by_hand(10.0, 1.0), (0, 5), x0, inputs=u, **TIGHT)
    ts = jnp.linspace(0, 5, 41)
    np.testing.assert_allclose(got.eval(ts), ref.eval(ts), atol=1e-10)


def closed_loop_cost(gains):
    closed = jd.feedback(Pendulum(), pd_controller(gains[0], gains[1]))
    traj = jd.simulate(closed, (0.0, 2.0), jnp.array([2.5, 0.0]), rtol=1e-10, atol=1e-10)
    err = traj.state(jnp.linspace(0.0, 2.0, 21))[:, 0] - jnp.pi
    return jnp.sum(err ** 2)


def test_gradient_of_a_closed_loop_cost_wrt_controller_gains_matches_finite_differences():
    gains = jnp.array([6.0, 1.5])
    grad = jax.grad(closed_loop_cost)(gains)
    eps = 1e-5
    for i in range(2):
        e = jnp.zeros(2).at[i].set(eps)
        fd = (closed_loop_cost(gains + e) - closed_loop_cost(gains - e)) / (2 * eps)
        np.testing.assert_allclose(grad[i], fd, rtol=1e-6)


def test_jit_and_vmap_through_combinators():
    gains = jnp.array([[4.0, 1.0], [6.0, 1.5], [10.0, 2.0]])
    batched = jax.jit(jax.vmap(closed_loop_cost))(gains)
    looped = np.array([closed_loop_cost(g) for g in gains])
    np.testing.assert_allclose(batched, looped, rtol=1e-12)
    # the combinator itself under jit, with a traced LTI parameter
    a = jd.LinearSystem(A1, B1, C1)

    @jax.jit
    def final(scale):
        b = jd.LinearSystem(scale * A2, B2, C2, D2)
        return jd.simulate(jd.feedback(b, a), (0, 1), jnp.ones(4), **TIGHT).final_state

    lin = jd.feedback(jd.LinearSystem(2.0 * A2, B2, C2, D2), a)
    np.testing.assert_allclose(final(2.0), scipy.linalg.expm(np.asarray(lin.A)) @ np.ones(4), rtol=1e-10)


def test_mixed_sample_times_match_a_hand_written_event_loop():
    """A double integrator (continuous) measured by a discrete filter every 0.15 s and driven by
    a discrete controller every 0.1 s whose output is held (ZOH). Updates at one instant are
    simultaneous: each reads the values from before that instant's updates (t = 0.3, 0.6, 0.9)."""
    plant = jd.LinearSystem([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]])
    observer = jd.System.from_functions(  # z = [smoothed y, previous y], output the velocity estimate too
        update=lambda t, z, y: jnp.array([0.6 * z[0] + 0.4 * y[0], y[0]]),
        output=lambda t, z, y: jnp.array([z[0], (z[0] - z[1]) / 0.15]),
        num_states=2, num_inputs=1, num_outputs=2, sample_time=0.15, direct_feedthrough=False)
    controller = jd.System.from_functions(  # holds u = -k1 p - k2 v computed at its last sample
        update=lambda t, u, z: jnp.array([-2.0 * z[0] - 1.5 * z[1]]),
        num_states=1, num_inputs=2, sample_time=0.1, direct_feedthrough=False)
    builder = jd.DiagramBuilder()
    for name, sys in (("plant", plant), ("observer", observer), ("controller", controller)):
        builder.add(sys, name)
    builder.connect("plant", "observer")
    builder.connect("observer", "controller")
    builder.connect("controller", "plant")
    builder.export_output("plant")
    diagram = builder.build("MultiRate")
    assert diagram.sample_times == (0.1, 0.15)
    # state layout: discrete parts first (observer z, controller u), then the plant
    assert diagram.state_frame.coordinates == ("observer.x0", "observer.x1", "controller.x0",
                                               "plant.x0", "plant.x1")
    x0 = np.array([0.2, 0.0, 0.0, 1.0, 0.5])
    T = 1.2
    traj = jd.simulate(diagram, (0, T), x0, **TIGHT)

    # reference: exact propagation between sample instants (exact rational instants)
    Ad = lambda h: scipy.linalg.expm(np.array([[0, 1, 0], [0, 0, 1], [0, 0, 0.0]]) * h)
    z, u, x = x0[:2].copy(), x0[2:3].copy(), x0[3:].copy()
    instants = sorted({fractions.Fraction(k, 10) for k in range(13)} | {fractions.Fraction(3 * k, 20) for k in range(9)})
    t = fractions.Fraction(0)
    for s in instants + [fractions.Fraction(12, 10)]:
        if s > t:
            x = (Ad(float(s - t)) @ np.concatenate([x, u]))[:2]
            t = s
        if s == fractions.Fraction(12, 10):
            break
        y = x[0]
        z_out = np.array([z[0], (z[0] - z[1]) / 0.15])
        new_z = np.array([0.6 * z[0] + 0.4 * y, y]) if s % fractions.Fraction(3, 20) == 0 else z
        new_u = np.array([-2.0 * z_out[0] - 1.5 * z_out[1]]) if s % fractions.Fraction(1, 10) == 0 else u
        z, u = new_z, new_u
    np.testing.assert_allclose(traj.final_state, np.concatenate([z, u, x]), rtol=1e-9, atol=1e-11)


def test_a_combination_with_a_hybrid_system_is_hybrid():
    """A bouncing ball's height through a first-order sensor filter: the diagram is hybrid (the
    ball's transitions), the impacts are those of the ball alone, and the filter's state is
    that of the filter driven by the ball's simulated height as an input tape."""
    ball = BouncingBall()
    sensor = jd.LinearSystem([[-20.0]], [[20.0]], [[1.0]])
    chain = jd.cascade(ball, sensor)
    assert type(chain) is jd.Diagram and chain.is_hybrid and chain.num_modes == ball.num_modes
    assert chain.transitions == ball.transitions
    x0 = jnp.array([2.0, 0.0, 0.0])  # centre 1 m above the ground (r = 1)
    got = jd.simulate(chain, (0, 2.0), x0, rtol=1e-11, atol=1e-12)
    alone = jd.simulate(ball, (0, 2.0), x0[:2], rtol=1e-11, atol=1e-12)
    n = int(alone.num_events)
    assert n >= 2 and int(got.num_events) == n
    np.testing.assert_allclose(got.event_times[:n], alone.event_times[:n], rtol=1e-12)
    filtered = jd.simulate(sensor, (0, 2.0), jnp.zeros(1), inputs=alone, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(got.final_state[2], filtered.final_state[0], atol=1e-8)
    np.testing.assert_allclose(got.final_state[:2], alone.final_state, atol=1e-10)


def test_two_hybrid_systems_combine_into_the_product_of_their_modes():
    b1, b2 = BouncingBall(), BouncingBall(cor=0.5)
    both = jd.parallel(b1, b2)
    assert both.is_hybrid and both.num_modes == b1.num_modes * b2.num_modes
    got = jd.simulate(both, (0, 2.0), jnp.array([2.0, 0.0, 1.7, 0.0]), rtol=1e-11, atol=1e-12)
    e1 = jd.simulate(b1, (0, 2.0), jnp.array([2.0, 0.0]), rtol=1e-11, atol=1e-12)
    e2 = jd.simulate(b2, (0, 2.0), jnp.array([1.7, 0.0]), rtol=1e-11, atol=1e-12)
    assert int(e1.num_events) >= 2 and int(e2.num_events) >= 2
    expected = np.sort(np.concatenate([e1.event_times[: int(e1.num_events)], e2.event_times[: int(e2.num_events)]]))
    # the softer ball stops (its reset says so) and with it the diagram's simulation
    assert int(got.status) == jd.SimulationStatus.STOPPED_BY_RESET == int(e2.status)
    np.testing.assert_allclose(got.t_final, e2.t_final, rtol=1e-12)
    expected = expected[expected <= float(e2.t_final)]
    np.testing.assert_allclose(got.event_times[: int(got.num_events)], expected, rtol=1e-10)
    np.testing.assert_allclose(got.final_state, np.concatenate([e1.state(got.t_final), e2.final_state]), atol=1e-9)


def test_frame_conversion_is_applied_when_connecting():
    polar = jd.Frame("PolarTest", ("r", "phi"))
    cartesian = jd.Frame("CartesianTest", ("px", "py"))
    jd.add_frame_conversion(polar, cartesian, lambda y: jnp.array([y[0] * jnp.cos(y[1]), y[0] * jnp.sin(y[1])]))
    rotating = jd.System.from_functions(lambda t, x, u: jnp.array([0.0, 1.0]), num_states=2,
                                        state_frame=polar, output_frame=polar)
    sink = jd.System.from_functions(lambda t, x, u: u, num_states=2, num_inputs=2, input_frame=cartesian)
    traj = jd.simulate(jd.cascade(rotating, sink), (0, 2.0), jnp.array([2.0, 0.0, 0.0, 0.0]), **TIGHT)
    # integral of (2 cos t, 2 sin t) over [0, 2]
    np.testing.assert_allclose(traj.final_state[2:], [2 * np.sin(2.0), 2 * (1 - np.cos(2.0))], rtol=1e-10)


def test_mismatched_frames_raise_an_error_naming_both():
    polar = jd.Frame("PolarMismatch", ("r", "phi"))
    other = jd.Frame("Wheel", ("left", "right"))
    a = jd.System.from_functions(lambda t, x, u: x, num_states=2, output_frame=polar, state_frame=polar)
    b = jd.System.from_functions(lambda t, x, u: u, num_states=2, num_inputs=2, input_frame=other)
    with pytest.raises(ValueError, match=r"PolarMismatch\(r, phi\).*Wheel\(left, right\)"):
        jd.cascade(a, b)


def test_wrong_sizes_raise_an_error():
    a = jd.LinearSystem(A1, B1, C1)       # 1 output
    b = jd.LinearSystem(A2, np.eye(2))    # 2 inputs
    with pytest.raises(ValueError, match="sizes differ"):
        jd.cascade(a, b)
    builder = jd.DiagramBuilder()
    builder.add(a, "a"), builder.add(b, "b")
    with pytest.raises(ValueError, match="sizes differ"):
        builder.connect(("a", [0]), ("b", ["u0", "u1"]))


def test_algebraic_loops_are_detected_and_named():
    gain = lambda k: jd.LinearSystem(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), [[k]])
    with pytest.raises(ValueError, match="algebraic loop"):
        jd.feedback(gain(2.0), gain(0.5))
    builder = jd.DiagramBuilder()
    for name in ("first", "second", "third"):
        builder.add(gain(1.0), name)
    builder.connect("first", "second")
    builder.connect("second", "third")
    builder.connect("third", "first")
    builder.export_output("third")
    with pytest.raises(ValueError, match=r"algebraic loop: (first|second|third) -> .* -> .*"):
        builder.build()
    # a system with state on the loop breaks it
    ok = jd.feedback(jd.LinearSystem([[-1.0]], [[1.0]], [[1.0]]), gain(0.5))
    assert type(ok) is jd.LinearSystem


def test_builder_errors_name_the_problem():
    builder = jd.DiagramBuilder()
    builder.add(Pendulum(), "plant")
    with pytest.raises(KeyError, match="no subsystem named 'plnat'"):
        builder.connect("plnat", "plant")
    with pytest.raises(KeyError, match="no coordinate 'omega'"):
        builder.export_output(("plant", ["omega"]))
    with pytest.raises(ValueError, match=r"input coordinates \['tau'\] of 'plant'.*not connected"):
        builder.build()
    with pytest.raises(ValueError, match="already added"):
        builder.add(Pendulum(), "plant")


def test_diagram_input_limits_are_located_as_events_when_the_input_feeds_a_limited_port():
    plant = Pendulum(input_limits=(-1.0, 1.0))
    chain = jd.cascade(plant, jd.LinearSystem([[-1.0]], [[1.0, 0.0]], [[1.0]]))
    np.testing.assert_allclose(chain.input_limits[1], [1.0])
    traj = jd.simulate(chain, (0, 3), jnp.zeros(3), inputs=lambda t: jnp.array([2 * jnp.sin(t)]), **TIGHT)
    # 2 sin t = 1 at t = pi/6 and 5 pi/6
    np.testing.assert_allclose(traj.events["times"], [np.pi / 6, 5 * np.pi / 6], rtol=1e-9)


def test_hybrid_modes_inherit_the_hybrid_systems_frames():
    height = jd.Frame("Height", ("h",))
    flight = jd.System.from_functions(lambda t, x, u: jnp.array([x[1], -9.81]), num_states=2,
                                      num_outputs=1, output=lambda t, x, u: x[:1])  # generic output frame
    bounce = jd.Transition(0, lambda s, t, x, u: x[0], lambda s, t, x, u: jnp.array([x[0], -x[1]]), 0)
    hybrid = jd.HybridSystem([flight], [bounce], output_frame=height)
    assert hybrid.output_frame == height
    named = jd.System.from_functions(lambda t, x, u: jnp.array([x[1], -9.81]), num_states=2, num_outputs=1,
                                     output=lambda t, x, u: x[:1], output_frame=jd.Frame("Altitude", ("z",)))
    with pytest.raises(ValueError, match=r"mode 0.*output frame Altitude\(z\).*Height\(h\)"):
        jd.HybridSystem([named], [bounce], output_frame=height)


def test_float32_feedback_diagram_runs():
    with jax.enable_x64(False):
        closed = jd.feedback(Pendulum(), pd_controller(10.0, 1.0))
        traj = jd.simulate(closed, (0.0, 5.0), jnp.array([0.5, 0.0], jnp.float32), dense=False)
        assert traj.final_state.dtype == jnp.float32 and bool(traj.success)
        np.testing.assert_allclose(traj.final_state[0], np.pi, atol=1e-2)


# ~2.5 s each: the three combinators' structure-preserving LinearSystem algebra, and a Diagram
# in its most intricate wiring (feedback) by default
@pytest.mark.parametrize("combinator, linear", [(c, linear) if linear or c is jd.feedback else
                                                pytest.param(c, linear, marks=pytest.mark.slow)
                                                for linear in (True, False) for c in (jd.cascade, jd.feedback, jd.parallel)],
                         ids=lambda v: {True: "LinearSystem", False: "Diagram"}.get(v, getattr(v, "__name__", None)))
def test_gradient_through_each_combinator_matches_finite_differences(combinator, linear):
    def final(k):
        a = (jd.LinearSystem([[0.0, 1.0], [-1.0, -k]], [[0.0], [1.0]]) if linear
             else Pendulum(b=k))
        b = jd.LinearSystem([[-2.0 * k]], [[1.0, 0.5]], [[k]])
        combined = combinator(a, b)
        assert (type(combined) is jd.LinearSystem) == linear
        traj = jd.simulate(combined, (0.0, 2.0), jnp.array([1.0, 0.0, 0.5]), rtol=1e-11, atol=1e-12)
        return jnp.sum(traj.final_state ** 2)

    k = 0.7
    fd = (final(k + 1e-5) - final(k - 1e-5)) / 2e-5
    np.testing.assert_allclose(jax.grad(final)(k), fd, rtol=1e-6)


def test_direct_feedthrough_is_inferred_from_the_output():
    """A plant without `output` (y = x) has no direct feedthrough, so the most common loop,
    feedback(plant, lqr(...).controller), is no algebraic loop; it matches exp((A - BK) t)."""
    plant = jd.System.from_functions(dynamics=lambda t, x, u: jnp.stack([x[1], u[0]]), num_states=2, num_inputs=1)
    assert not plant.direct_feedthrough
    result = jd.control.lqr(plant, jnp.eye(2), jnp.eye(1))
    x0 = jnp.array([1.0, -0.5])
    final = jd.simulate(jd.feedback(plant, result.controller), (0.0, 2.0), x0, rtol=1e-10, atol=1e-12).final_state
    A, B = np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]])
    np.testing.assert_allclose(final, scipy.linalg.expm(2.0 * (A - B @ np.asarray(result.K))) @ np.asarray(x0),
                               rtol=1e-8, atol=1e-10)

    class Subclassed(jd.System):
        def __init__(self):
            super().__init__(num_continuous_states=2, num_inputs=1)

        def dynamics(self, t, x, u):
            return jnp.stack([x[1], u[0]])

    class ReadsInput(Subclassed):
        def output(self, t, x, u):
            return x + jnp.concatenate([u, u])

    discrete = jd.System.from_functions(update=lambda t, x, u: 0.5 * x + u, num_states=1, num_inputs=1,
                                        sample_time=0.1)
    gain = jd.System.from_functions(output=lambda t, x, u: -2.0 * u, num_states=0, num_inputs=1, num_outputs=1)
    unused = jd.System.from_functions(output=lambda t, x, u: jnp.ones(1) + 0.0 * x.sum(), num_states=0,
                                      num_inputs=1, num_outputs=1)
    declared = jd.System.from_functions(dynamics=lambda t, x, u: -x + u, num_states=1, num_inputs=1,
                                        direct_feedthrough=True)
    assert not Subclassed().direct_feedthrough and not discrete.direct_feedthrough
    assert ReadsInput().direct_feedthrough and gain.direct_feedthrough and declared.direct_feedthrough
    assert not unused.direct_feedthrough
    with pytest.raises(ValueError, match="direct_feedthrough=False"):
        jd.feedback(gain, gain)


def test_a_loop_built_inside_jit_and_vmap_with_traced_controller_gains():
    """feedback(plant, controller) built under jit(vmap) over the controller's gain, as a user
    sweeping gains writes it: the plant's feedthrough is still inferred (it had been taken as
    True inside a trace), the controller's output size comes from its function, and
    x' = -k x gives x0 exp(-k t)."""
    plant = jd.System.from_functions(dynamics=lambda t, x, u: u, num_states=1, num_inputs=1)

    def final(k):
        gain = jd.System.from_functions(output=lambda t, x, u, k: -k * u, num_states=0, num_inputs=1, params=k)
        assert gain.num_outputs == 1
        return jd.simulate(jd.feedback(plant, gain), (0.0, 1.5), jnp.ones(1), rtol=1e-10, atol=1e-12).final_state[0]

    ks = jnp.array([0.5, 1.0, 3.0])
    np.testing.assert_allclose(jax.jit(jax.vmap(final))(ks), np.exp(-1.5 * np.asarray(ks)), rtol=1e-8)
    with pytest.raises(ValueError, match="atleast_1d"):
        jd.System.from_functions(output=lambda t, x, u: u.sum(), num_states=0, num_inputs=2)


def test_cascading_an_input_tape_with_a_system():
    """The notes' D.3.6 idiom: cascade(trajectory, system) simulates x' = -x + u(t) with a ramp
    tape u = t on [0, 1], then 1: x(2) = 1 + (e^-1 - 1) e^-1 from x(0) = 0."""
    tape = jd.Trajectory.from_samples(jnp.array([0.0, 1.0, 2.0]), jnp.array([[0.0], [1.0], [1.0]]))
    plant = jd.System.from_functions(dynamics=lambda t, x, u: -x + u, num_states=1, num_inputs=1)
    driven = jd.cascade(tape, plant)
    assert driven.num_inputs == 0 and driven.num_states == 1
    final = jd.simulate(driven, (0.0, 2.0), jnp.zeros(1), rtol=1e-10, atol=1e-12).final_state
    np.testing.assert_allclose(final, [1 + (np.exp(-1.0) - 1) * np.exp(-1.0)], rtol=1e-8)
    with pytest.raises(TypeError, match="can only come first"):
        jd.cascade(plant, tape)
    with pytest.raises(ValueError, match="2 coordinates"):
        jd.cascade(jd.Trajectory.from_samples(jnp.array([0.0, 1.0]), jnp.zeros((2, 2))), plant)


def test_a_cascaded_tape_stops_steps_at_its_breakpoints_like_inputs():
    """cascade(tape, system) takes exactly the steps of simulate(system, inputs=tape): each ends on
    the zero-order-hold tape's jumps, and the state agrees with it to 1e-9 (it differed by 1e-6
    when the cascade's step-size control had to resolve the jumps)."""
    oscillator = jd.System.from_functions(
        dynamics=lambda t, x, u: jnp.array([x[1], -x[0] - 0.3 * x[1] + u[0]]), num_states=2, num_inputs=1)
    tape = jd.Trajectory.from_samples(jnp.linspace(0.0, 3.0, 7), jnp.array([[0.0], [1.0], [-1.0], [2.0], [0.5], [0.0], [1.0]]),
                                      interpolation="zoh")
    x0, ts = jnp.array([0.1, 0.0]), np.linspace(0.0, 3.0, 61)
    taped = jd.simulate(oscillator, (0.0, 3.0), x0, inputs=tape, rtol=1e-8, atol=1e-10)
    cascaded = jd.simulate(jd.cascade(tape, oscillator), (0.0, 3.0), x0, rtol=1e-8, atol=1e-10)
    assert int(cascaded.num_accepted_steps) == int(taped.num_accepted_steps)
    assert set(np.round(np.linspace(0.5, 2.5, 5), 12)) <= set(np.round(cascaded.breakpoints(), 12))
    np.testing.assert_allclose(cascaded.state(ts), taped.state(ts), atol=1e-9)
    np.testing.assert_allclose(cascaded.eval(ts)[:, 0], taped.state(ts)[:, 0], atol=1e-9)


def _held_pendulum():
    """A sub-diagram whose discrete part (the hold) and continuous part (the pendulum) lie apart
    in any diagram's stacked state [x_d...; x_c...]."""
    builder = jd.DiagramBuilder()
    builder.add(jd.ZeroOrderHold(0.1, 1), "hold")
    builder.add(Pendulum(), "plant")
    builder.connect("hold", "plant")
    builder.export_input("hold")
    builder.export_output("plant")
    return builder.build("HeldPendulum")


def test_a_diagram_state_is_set_and_read_per_subsystem_by_name_object_index_or_path():
    """state_with / subsystem_state / initial_state_with (Drake's GetMutableSubsystemState) put
    each subsystem's state where the diagram's state frame names its coordinates, whether the
    subsystem is given by name, object, index or dotted path into a sub-diagram; a hybrid
    subsystem takes its initial mode's own state (padded with zeros); simulate takes the mapping."""
    held = _held_pendulum()
    controller = jd.System.from_functions(lambda t, x, u: -x + u[:1], output=lambda t, x, u: -x,
                                          num_states=1, num_inputs=2, direct_feedthrough=False)
    ramp = jd.System.from_functions(lambda t, x, u: jnp.ones(1), num_states=1)
    decay = jd.System.from_functions(lambda t, x, u: -x, num_states=2, output=lambda t, x, u: x[:1])
    growing = jd.HybridSystem([ramp, decay], [jd.Transition(0, lambda s, t, x, u: 1.0 - x[0],
                                                            lambda s, t, x, u: jnp.append(x, 0.0), 1)])
    builder = jd.DiagramBuilder()
    builder.add(held, "held"), builder.add(controller, "controller"), builder.add(growing, "growing")
    builder.connect("held", "controller")
    builder.connect("controller", "held")
    builder.export_output("held")
    loop = builder.build("Loop")
    at = lambda *names: np.array([loop.state_frame.index(n) for n in names])  # noqa: E731
    x = jnp.arange(1.0, loop.num_states + 1.0)
    parts = [("held.plant", at("held.plant.theta", "held.plant.thetadot"), [0.3, -0.2]),
             ("held.hold", at("held.hold.x0"), [5.0]), (controller, at("controller.x0"), [-7.0]),
             (2, at("growing.x0", "growing.x1"), [8.0, 9.0]), (held, at("held.hold.x0", "held.plant.theta",
                                                                     "held.plant.thetadot"), [1.5, 2.5, 3.5])]
    for which, coordinates, value in parts:
        y = loop.state_with(x, which, jnp.asarray(value))
        np.testing.assert_array_equal(y[coordinates], value)
        np.testing.assert_array_equal(np.delete(y, coordinates), np.delete(x, coordinates))
        np.testing.assert_array_equal(loop.subsystem_state(which, y), value)
    assert loop.subsystem("held.plant") is held.subsystems[1] and loop.subsystem(held) is held
    np.testing.assert_array_equal(loop.state_with(x, "growing", 0.25)[at("growing.x0", "growing.x1")], [0.25, 0.0])
    X = jax.random.normal(jax.random.key(0), (5, loop.num_states))  # a trajectory's states, stacked
    np.testing.assert_array_equal(loop.subsystem_state("held.plant", X), X[:, at("held.plant.theta",
                                                                                 "held.plant.thetadot")])
    expected = loop.initial_state().at[at("held.plant.theta", "held.plant.thetadot")].set([0.3, -0.2])
    expected = expected.at[at("controller.x0")].set(2.0)
    mapping = {held: {"plant": [0.3, -0.2]}, "controller": 2.0}
    np.testing.assert_array_equal(loop.initial_state_with(mapping), expected)
    traj = jd.simulate(loop, (0.0, 0.05), mapping, solver="rk4", dt=0.05)
    np.testing.assert_array_equal(traj.state(0.0), expected)


def test_subsystem_state_errors_name_the_subsystem_and_the_remedy():
    held = _held_pendulum()
    x = held.initial_state()
    with pytest.raises(KeyError, match="HeldPendulum has no subsystem named 'plnat'.*'hold', 'plant'"):
        held.subsystem_state("plnat", x)
    with pytest.raises(KeyError, match="Pendulum is not a subsystem of HeldPendulum.*identity"):
        held.state_with(x, Pendulum(), jnp.zeros(2))
    with pytest.raises(IndexError, match="2 subsystems, no number 2"):
        held.subsystem_state(2, x)
    with pytest.raises(ValueError, match=r"subsystem 'plant': x0 has shape \(3,\).*PendulumState\(theta, "
                                         r"thetadot\) needs shape \(2,\)"):
        held.initial_state_with({"plant": [1.0, 2.0, 3.0]})
    with pytest.raises(ValueError, match=r"x0 has shape \(2,\).*HeldPendulumState.*needs shape \(3,\)"):
        held.state_with(x[:2], "plant", jnp.zeros(2))
    pendulum = Pendulum()
    twice = jd.parallel(pendulum, pendulum)
    with pytest.raises(ValueError, match=r"added to Parallel 2 times, as \['Pendulum', 'Pendulum2'\]"):
        twice.subsystem_state(pendulum, twice.initial_state())
    second = np.array([twice.state_frame.index(f"Pendulum2.{c}") for c in ("theta", "thetadot")])
    np.testing.assert_array_equal(twice.subsystem_state("Pendulum2", jnp.arange(4.0)), jnp.arange(4.0)[second])
