"""Hybrid systems: modes, guards, resets, event location, and gradients across impacts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.models import BouncingBall, RimlessWheel

G, R, COR, H0 = 9.81, 1.0, 0.8, 5.0
TIGHT = dict(rtol=1e-11, atol=1e-12)


def ball_closed_form(h0=H0, cor=COR, g=G, r=R, bounces=10):
    """Impact k (k = 0, 1, ...) at t_k = t_0 + sum_{j<k} 2 e^{j+1} v / g; the apex after it at
    height r + (e^{k+1} v)^2 / (2 g), where v = sqrt(2 g (h0 - r)) and t_0 = v / g."""
    v = np.sqrt(2 * g * (h0 - r))
    k = np.arange(bounces)
    rebound = cor ** (k + 1) * v
    times = v / g + np.concatenate([[0.0], np.cumsum(2 * rebound[:-1] / g)])
    return times, r + rebound**2 / (2 * g), rebound


def test_bouncing_ball_event_times_and_apexes_match_the_closed_form():
    traj = jd.simulate(BouncingBall(), (0.0, 20.0), jnp.array([H0, 0.0]), **TIGHT)
    times, apexes, rebound = ball_closed_form()
    ev = traj.events
    np.testing.assert_allclose(ev["times"][:10], times, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ev["states"][:10, 1], rebound, rtol=1e-9)
    assert list(ev["transitions"][:10]) == [0] * 10 and list(ev["modes"][:10]) == [0] * 10
    apex_times = times + rebound / G
    np.testing.assert_allclose(np.asarray(traj.eval(apex_times))[:, 0], apexes, rtol=1e-9)
    # the ball's output is its height, from the flight mode
    assert traj.system.output_frame.coordinates == ("q",)


def test_bouncing_ball_stops_with_the_notes_status():
    traj = jd.simulate(BouncingBall(), (0.0, 20.0), jnp.array([H0, 0.0]), **TIGHT)
    assert int(traj.status) == jd.SimulationStatus.STOPPED_BY_RESET and bool(traj.success)
    v = np.sqrt(2 * G * (H0 - R))
    bounces = int(np.ceil(np.log(0.01 / v) / np.log(COR)))  # first k with e^k v < 0.01
    assert int(traj.num_events) == bounces
    times, _, _ = ball_closed_form(bounces=bounces)
    assert float(traj.t_final) == pytest.approx(times[-1], abs=1e-9)


def test_left_and_right_limits_at_an_impact():
    traj = jd.simulate(BouncingBall(), (0.0, 3.0), jnp.array([H0, 0.0]), **TIGHT)
    t1 = float(traj.events["times"][0])
    v = np.sqrt(2 * G * (H0 - R))
    np.testing.assert_allclose(traj.state(t1, side="left"), [R, -v], rtol=1e-9)
    np.testing.assert_allclose(traj.state(t1, side="right"), [R, COR * v], rtol=1e-9)
    assert t1 in traj.breakpoints()


def test_rimless_wheel_converges_to_the_rolling_fixed_point():
    wheel = RimlessWheel()
    traj = jd.simulate(wheel, (0.0, 30.0), jnp.array([0.0, 1.5]), max_events=512, max_steps=16384,
                       **TIGHT)
    post_impact_speeds = traj.events["states"][:, 1]
    assert len(post_impact_speeds) > 25 and np.all(traj.events["transitions"] == 0)  # forward
    fixed_point = np.sqrt(4 * 9.81 * np.sin(np.pi / 8) * np.sin(0.08)) / np.tan(np.pi / 4)
    np.testing.assert_allclose(post_impact_speeds[-1], fixed_point, rtol=1e-6)
    np.testing.assert_allclose(wheel.rolling_fixed_point(), fixed_point, rtol=1e-14)
    # each impact happens when the next spoke touches down: theta- = gamma + alpha
    theta_minus = traj.events["states"][:, 0] + 2 * np.pi / 8
    np.testing.assert_allclose(theta_minus, 0.08 + np.pi / 8, atol=1e-10)


def test_rimless_wheel_rolls_backward_uphill_when_pushed_back():
    traj = jd.simulate(RimlessWheel(), (0.0, 0.6), jnp.array([0.0, -3.0]), **TIGHT)
    assert traj.events["transitions"][0] == 1  # "step backward"
    np.testing.assert_allclose(traj.events["states"][0, 0], 0.08 - np.pi / 8 + 2 * np.pi / 8, atol=1e-10)


def central_difference(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def ball_height(h0, cor, T):
    traj = jd.simulate(BouncingBall(cor=cor), (0.0, T), jnp.stack([h0, 0.0]), **TIGHT)
    return traj.eval(T)[0]


def test_gradient_of_the_ball_height_after_three_bounces():
    times, _, _ = ball_closed_form()
    T = 0.5 * (times[2] + times[3])  # between the third and fourth impacts
    dh0, dcor = jax.grad(ball_height, argnums=(0, 1))(H0, COR, T)
    fd_h0 = central_difference(lambda h: float(ball_height(h, COR, T)), H0, 1e-5)
    fd_cor = central_difference(lambda e: float(ball_height(H0, e, T)), COR, 1e-6)
    np.testing.assert_allclose(dh0, fd_h0, rtol=1e-5)
    np.testing.assert_allclose(dcor, fd_cor, rtol=1e-5)
    # and against the closed form q(T) = r + v3 (T - t3) - g (T - t3)^2 / 2
    def closed(h0, cor):
        v = jnp.sqrt(2 * G * (h0 - R))
        t3 = v / G + 2 * (cor * v + cor**2 * v) / G  # the third impact
        return R + cor**3 * v * (T - t3) - G * (T - t3) ** 2 / 2
    np.testing.assert_allclose(ball_height(H0, COR, T), closed(H0, COR), rtol=1e-10)
    np.testing.assert_allclose([dh0, dcor], jax.grad(closed, argnums=(0, 1))(H0, COR), rtol=1e-7)


@pytest.mark.slow  # ~16 s; the gradient with the saltation term is checked by default against the closed form (three bounces)
def test_gradient_without_the_saltation_term_would_be_wrong():
    """One bounce. Without the event time's sensitivity the Jacobian is Phi(T - t1) dDelta/dx
    Phi(t1) with Phi(t) = [[1, t], [0, 1]] and dDelta/dx = diag(1, -e): d q(T) / d h0 = 1.
    The saltation matrix adds (f+ - dDelta f-) n^T / (n^T f-), n = (1, 0)."""
    T = 1.2
    v = np.sqrt(2 * G * (H0 - R))
    t1 = v / G
    assert t1 < T < t1 + 2 * COR * v / G
    dq_dh0 = float(jax.grad(ball_height)(H0, COR, T))
    fd = central_difference(lambda h: float(ball_height(h, COR, T)), H0, 1e-5)
    phi = lambda t: np.array([[1.0, t], [0.0, 1.0]])
    d_reset = np.diag([1.0, -COR])
    naive = (phi(T - t1) @ d_reset @ phi(t1))[0, 0]
    f_minus, f_plus = np.array([-v, -G]), np.array([COR * v, -G])
    n = np.array([1.0, 0.0])
    saltation = d_reset + np.outer(f_plus - d_reset @ f_minus, n) / (n @ f_minus)
    with_saltation = (phi(T - t1) @ saltation @ phi(t1))[0, 0]
    np.testing.assert_allclose(dq_dh0, fd, rtol=1e-6)
    np.testing.assert_allclose(dq_dh0, with_saltation, rtol=1e-8)
    assert abs(naive - fd) > 0.1 * abs(fd)  # the naive gradient is far off


def test_second_derivatives_through_an_impact_equal_the_closed_form():
    """One bounce, forward over forward mode: d^2/dh0^2 of the impact time t1 = v / g and of
    q(T) = r + e v (T - t1) - g (T - t1)^2 / 2 (v = sqrt(2 g (h0 - r))). The event time's
    Newton steps on the guard are differentiated whole (a step with its slope held gives the
    first derivative only)."""
    T = 1.2

    def simulated(h0):
        traj = jd.simulate(BouncingBall(), (0.0, T), jnp.stack([h0, 0.0]), autodiff="forward", **TIGHT)
        return jnp.stack([traj.event_times[0], traj.final_state[0]])

    def closed(h0):
        v = jnp.sqrt(2 * G * (h0 - R))
        t1 = v / G
        return jnp.stack([t1, R + COR * v * (T - t1) - G * (T - t1) ** 2 / 2])

    np.testing.assert_allclose(jax.jacfwd(jax.jacfwd(simulated))(H0), jax.hessian(closed)(H0), rtol=1e-7)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_gradient_of_the_wheel_speed_after_five_steps_wrt_slope():
    def speed(slope):
        traj = jd.simulate(RimlessWheel(slope=slope), (0.0, T), jnp.array([0.0, 1.5]), **TIGHT)
        return traj.state(T)[1]

    T = 3.6  # just after the fifth impact (3.36 s)
    traj = jd.simulate(RimlessWheel(), (0.0, T), jnp.array([0.0, 1.5]), **TIGHT)
    assert int(traj.num_events) == 5
    g = jax.grad(speed)(0.08)
    fd = central_difference(lambda s: float(speed(s)), 0.08, 1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-5)
    # forward mode agrees
    jf = jax.jacfwd(lambda s: jd.simulate(RimlessWheel(slope=s), (0.0, T), jnp.array([0.0, 1.5]),
                                          autodiff="forward", **TIGHT).state(T)[1])(0.08)
    np.testing.assert_allclose(jf, g, rtol=1e-9)


def test_vmap_over_drop_heights_matches_single_runs_in_one_program():
    heights = jnp.linspace(2.0, 10.0, 10_000)
    run = lambda h: jd.simulate(BouncingBall(), (0.0, 3.0), jnp.stack([h, 0.0]), dense=False,
                                throw=False, **TIGHT)
    batched = jax.jit(jax.vmap(run))
    traj = batched(heights)
    with jax.log_compiles(False):
        assert batched._cache_size() == 1
    for i in (0, 1234, 5000, 9999):
        single = run(heights[i])
        n = int(single.num_events)
        assert int(traj.num_events[i]) == n
        # the same to rounding (a batched select and a single-run branch may round differently)
        np.testing.assert_allclose(traj.event_times[i, :n], single.event_times[:n], rtol=1e-14)
    times, _, _ = ball_closed_form(h0=10.0, bounces=int(traj.num_events[-1]))
    np.testing.assert_allclose(traj.event_times[-1, : len(times)], times, atol=1e-9)


def test_a_batch_whose_members_all_have_events_at_once_matches_single_runs():
    """Under vmap the root finder runs over the members with a crossing, gathered in chunks of
    an eighth of the batch: 16 balls with the same bounces need 8 chunks in every event step."""
    heights = jnp.full(16, 5.0).at[::2].set(3.0)
    run = lambda h: jd.simulate(BouncingBall(), (0.0, 3.0), jnp.stack([h, 0.0]), dense=False,
                                throw=False, **TIGHT)
    batched = jax.jit(jax.vmap(run))(heights)
    for i in (0, 1):
        single = run(heights[i])
        n = int(single.num_events)
        assert n >= 2 and int(batched.num_events[i]) == n
        np.testing.assert_allclose(batched.event_times[i, :n], single.event_times[:n], rtol=1e-14)
    times, _, _ = ball_closed_form(h0=5.0, bounces=int(batched.num_events[1]))
    np.testing.assert_allclose(batched.event_times[1, : len(times)], times, atol=1e-9)


def test_chattering_on_the_boundary_ends_with_a_status():
    # cor = 1 and the ball at rest on the ground: the guard holds after every reset
    ball = BouncingBall(cor=1.0, stop_speed=-1.0)
    with pytest.raises(jd.SimulationError, match="max_events") as info:
        jd.simulate(ball, (0.0, 1.0), jnp.array([R, 0.0]), max_events=50)
    assert info.value.status == jd.SimulationStatus.TOO_MANY_EVENTS
    traj = jd.simulate(ball, (0.0, 1.0), jnp.array([R, 0.0]), max_events=50, throw=False)
    assert int(traj.num_events) == 50 and float(traj.t_final) == 0.0


def test_zeno_ball_without_a_stop_rule_ends_with_a_status():
    ball = BouncingBall(cor=0.5, stop_speed=0.0)
    traj = jd.simulate(ball, (0.0, 10.0), jnp.array([2.0, 0.0]), max_events=100, throw=False, **TIGHT)
    # the impacts accumulate at t = v/g (1 + 2 e / (1 - e)): the simulation cannot pass it
    v = np.sqrt(2 * G)
    assert float(traj.t_final) <= v / G * (1 + 2 * 0.5 / 0.5) + 1e-9
    assert int(traj.status) in (jd.SimulationStatus.TOO_MANY_EVENTS, jd.SimulationStatus.STEP_SIZE_TOO_SMALL)


def _reach_one(system, t, x, u):
    return 1.0 - x[0]


def _grow_state(system, t, x, u):
    return jnp.stack([x[0], 0.0 * x[0]])


def test_modes_with_different_state_sizes():
    """Mode 0: xdot = 1 (one state) until x >= 1; then mode 1: (x, y) with xdot = -x, ydot = x.
    The output is x in both modes."""
    ramp = jd.System.from_functions(dynamics=lambda t, x, u: jnp.ones(1), num_states=1)
    decay = jd.System.from_functions(dynamics=lambda t, x, u: jnp.stack([-x[0], x[0]]), num_states=2,
                                     num_outputs=1, output=lambda t, x, u: x[:1])
    system = jd.HybridSystem([ramp, decay], [jd.Transition(0, _reach_one, _grow_state, 1, "grow")])
    assert system.num_states == 2
    traj = jd.simulate(system, (0.0, 3.0), 0.25, **TIGHT)  # x0 in the initial mode's layout
    np.testing.assert_allclose(traj.events["times"], [0.75], atol=1e-10)
    assert list(traj.mode(jnp.array([0.5, 0.75, 2.0]))) == [0, 0, 1]
    assert int(traj.mode(traj.events["times"][0], side="right")) == 1
    t = 3.0 - 0.75
    np.testing.assert_allclose(traj.state(3.0), [np.exp(-t), 1 - np.exp(-t)], rtol=1e-9)
    np.testing.assert_allclose(traj.eval(jnp.array([0.5, 3.0]))[:, 0], [0.75, np.exp(-t)], rtol=1e-9)


def test_a_hybrid_system_names_its_state_as_its_modes_do():
    """Modes sharing one state frame give it to the hybrid system (Drake's names for the
    walkers, not x0, x1, ...); modes naming different ones leave the padded state generic."""
    assert RimlessWheel().state_frame.coordinates == ("theta", "thetadot")
    assert jd.models.CompassGait().state_frame.coordinates == ("stance", "swing", "stancedot", "swingdot")
    assert BouncingBall().state_frame.coordinates == ("q", "qdot")
    named = jd.System.from_functions(lambda t, x, u: -x, num_states=1, state_frame=jd.Frame("A", ("a",)))
    other = jd.System.from_functions(lambda t, x, u: -x, num_states=1, state_frame=jd.Frame("B", ("b",)))
    mixed = jd.HybridSystem([named, other], [jd.Transition(0, _reach_one, lambda s, t, x, u: x, 1)])
    assert mixed.state_frame.generic and mixed.state_frame.coordinates == ("x0",)


def test_not_guard_and_a_discrete_mode():
    """A counter that ticks (discrete, dt = 0.5) while a continuous clock runs: not_guard of
    (x_c - 1) fires when the clock passes 1 and switches to a mode that holds the count."""
    ticking = jd.System.from_functions(dynamics=lambda t, x, u: jnp.ones(1),
                                       update=lambda t, x, u: x[:1] + 1.0, num_states=2,
                                       num_discrete_states=1, sample_time=0.5)
    holding = jd.System.from_functions(dynamics=lambda t, x, u: jnp.zeros(1),
                                       update=lambda t, x, u: x[:1], num_states=2,
                                       num_discrete_states=1, sample_time=0.5)
    clock_below = lambda s, t, x, u: x[1] - 1.0  # noqa: E731
    system = jd.HybridSystem([ticking, holding],
                             [jd.Transition(0, jd.not_guard(clock_below), lambda s, t, x, u: x, 1)])
    traj = jd.simulate(system, (0.0, 3.0), jnp.array([0.0, 0.2]), **TIGHT)
    # updates at t = 0 and 0.5 in mode 0; the clock reaches 1 at t = 0.8; mode 1 holds 2
    np.testing.assert_allclose(traj.events["times"], [0.8], atol=1e-10)
    np.testing.assert_allclose(traj.state(3.0), [2.0, 1.0], rtol=1e-12)


def test_hybrid_construction_errors_are_named():
    flight = jd.models.BallFlightPhasePlant()
    with pytest.raises(ValueError, match="target mode 3"):
        jd.HybridSystem([flight], [jd.Transition(0, _reach_one, _grow_state, 3)])
    with pytest.raises(ValueError, match="same num_inputs"):
        jd.HybridSystem([flight, jd.models.Pendulum()], [])
    with pytest.raises(ValueError, match="at least two guards"):
        jd.and_guards(_reach_one)
    bad_reset = jd.HybridSystem([flight], [jd.Transition(0, _reach_one, lambda s, t, x, u: x[:1], 0)])
    with pytest.raises(ValueError, match=r"reset must return the target mode's state, shape \(2,\)"):
        jd.simulate(bad_reset, (0.0, 1.0), jnp.array([2.0, 0.0]))
    bad_guard = jd.HybridSystem([flight], [jd.Transition(0, lambda s, t, x, u: x, _grow_state, 0)])
    with pytest.raises(ValueError, match="guard must return a scalar"):
        jd.simulate(bad_guard, (0.0, 1.0), jnp.array([2.0, 0.0]))
    with pytest.raises(TypeError, match="mode_dynamics"):
        BouncingBall().dynamics(0.0, jnp.zeros(2), jnp.zeros(0))


def test_wheel_speed_after_five_steps_matches_the_return_map():
    """From theta0 = 0: w1+ = cos(2a) sqrt(w0^2 + 2 g/l (1 - cos(slope + a))), then
    w_{n+1}+ = cos(2a) sqrt(w_n+^2 + 4 g/l sin(a) sin(slope)); value and slope-derivative."""
    a = np.pi / 8

    def closed(slope, w0=1.5, g=9.81):
        w = jnp.cos(2 * a) * jnp.sqrt(w0**2 + 2 * g * (1 - jnp.cos(slope + a)))
        for _ in range(4):
            w = jnp.cos(2 * a) * jnp.sqrt(w**2 + 4 * g * jnp.sin(a) * jnp.sin(slope))
        return w

    def simulated(slope):
        traj = jd.simulate(RimlessWheel(slope=slope), (0.0, 4.0), jnp.array([0.0, 1.5]), **TIGHT)
        return traj.event_states[4, 1]

    for slope in (0.08, 0.12):
        np.testing.assert_allclose(simulated(slope), closed(slope), rtol=1e-9)
        np.testing.assert_allclose(jax.grad(simulated)(slope), jax.grad(closed)(slope), rtol=1e-7)


def _to_mode(target):
    return lambda system, t, x, u: x


def test_simultaneous_guards_resolve_to_the_lowest_index():
    """Two transitions with the same guard (and so the same located time): the first listed
    fires, whether it is located inside a step or already holds at the start."""
    clock = jd.System.from_functions(dynamics=lambda t, x, u: jnp.ones(1), num_states=1)
    first, second = _to_mode(1), _to_mode(2)
    system = jd.HybridSystem([clock, clock, clock],
                             [jd.Transition(0, _reach_one, first, 1), jd.Transition(0, _reach_one, second, 2)])
    traj = jd.simulate(system, (0.0, 2.0), 0.5, **TIGHT)
    assert list(traj.events["transitions"]) == [0] and list(traj.events["modes"]) == [1]
    np.testing.assert_allclose(traj.events["times"], [0.5], atol=1e-12)
    at_start = jd.simulate(system, (0.0, 1.0), 1.5, **TIGHT)  # both guards hold at t0
    assert list(at_start.events["transitions"]) == [0] and list(at_start.events["times"]) == [0.0]
