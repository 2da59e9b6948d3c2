"""simulate(): closed forms, invariants, stiff systems, timing of discrete updates."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import jaxdrake as jd
from jaxdrake.models import (Pendulum, SimpleCTExample, SimpleDTExample, SimpleMixedCTDTExample,
                             VanDerPol)


def simple_ct_closed_form(x0, t):
    """xdot = -x + x^3: x(t) = x0 / sqrt(x0^2 + (1 - x0^2) e^{2t})."""
    return x0 / np.sqrt(x0**2 + (1 - x0**2) * np.exp(2 * t))


def test_simple_ct_matches_closed_form_between_steps():
    traj = jd.simulate(SimpleCTExample(), (0.0, 10.0), 0.99, rtol=1e-10, atol=1e-14)
    ts = np.linspace(0.0, 10.0, 1001)  # mostly between the solver's steps
    assert traj.num_steps < 500
    np.testing.assert_allclose(np.asarray(traj.eval(ts))[:, 0], simple_ct_closed_form(0.99, ts),
                               rtol=1e-8)
    # a single time, and the final state
    np.testing.assert_allclose(traj.eval(3.3), [simple_ct_closed_form(0.99, 3.3)], rtol=1e-8)
    np.testing.assert_allclose(traj.final_state, [simple_ct_closed_form(0.99, 10.0)], rtol=1e-8)


def test_simple_dt_is_exact():
    traj = jd.simulate(SimpleDTExample(), (0.0, 10.0), 0.99)
    x = np.float64(0.99)
    for n in range(11):
        # x[n] holds on (n - 1, n]; at t = n the left limit is x[n]. Bit for bit the iterated
        # map, and the closed form x0^(3^n) up to the rounding that cubing amplifies (3^n ulp).
        assert float(traj.eval(float(n))[0]) == x
        assert float(traj.eval(float(n))[0]) == pytest.approx(0.99 ** (3**n), rel=3**n * 2e-16)
        x = x * x * x
        if n < 10:
            assert float(traj.eval(n + 0.5)[0]) == x


def test_mixed_system_updates_at_the_sample_times():
    """x1(t + t') = x1(t)^3 for t in {0, 1, 2, ...}, t' in (0, 1]; x2 follows SimpleCT."""
    x0 = np.array([0.9, 0.5])
    traj = jd.simulate(SimpleMixedCTDTExample(), (0.0, 4.0), x0, rtol=1e-10, atol=1e-14)
    ts = np.array([0.0, 1e-9, 0.25, 0.999, 1.0, 1.0 + 1e-9, 2.5, 3.0, 3.75, 4.0])
    x = np.asarray(traj.state(ts))
    periods = np.ceil(ts)  # number of updates applied by time t: t in (k-1, k] -> k
    np.testing.assert_allclose(x[:, 0], 0.9 ** (3.0**periods), rtol=1e-14)
    np.testing.assert_allclose(x[:, 1], simple_ct_closed_form(0.5, ts), rtol=1e-8)
    # the right limit at a sample time already holds the update made there
    np.testing.assert_allclose(traj.state(1.0, side="right")[0], 0.9**9, rtol=1e-14)


def test_pendulum_conserves_energy():
    p = Pendulum(b=0.0)
    x0 = jnp.array([2.5, 0.0])  # a large swing: strongly nonlinear
    traj = jd.simulate(p, (0.0, 10.0), x0, rtol=1e-12, atol=1e-12, max_steps=8192)
    ts = np.linspace(0, 10, 501)
    energy = np.asarray(p.energy(traj.state(ts)))
    assert np.max(np.abs(energy - energy[0])) < 1e-9 * abs(energy[0])


def test_pendulum_matches_scipy_with_damping_and_input():
    p = Pendulum(m=1.3, l=0.7, b=0.25)
    u = lambda t: jnp.array([0.5 * jnp.sin(2 * t)])
    traj = jd.simulate(p, (0.0, 5.0), jnp.array([1.0, -0.5]), inputs=u, rtol=1e-11, atol=1e-12)

    def f(t, x):
        return [x[1], (0.5 * np.sin(2 * t) - 0.25 * x[1] - 1.3 * 9.81 * 0.7 * np.sin(x[0])) / (1.3 * 0.49)]

    ref = solve_ivp(f, (0, 5), [1.0, -0.5], method="DOP853", rtol=1e-13, atol=1e-13, dense_output=True)
    ts = np.linspace(0, 5, 77)
    np.testing.assert_allclose(np.asarray(traj.state(ts)), ref.sol(ts).T, rtol=1e-8, atol=1e-9)


def test_stiff_van_der_pol_with_rosenbrock():
    mu = 1000.0
    traj = jd.simulate(VanDerPol(mu), (0.0, 3000.0), jnp.array([2.0, 0.0]), solver="rosenbrock23",
                       rtol=1e-4, atol=1e-6, max_steps=4096)
    assert traj.num_steps < 2000  # an explicit method would need millions of steps here
    ref = solve_ivp(lambda t, x: [x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]], (0, 3000), [2.0, 0.0],
                    method="Radau", rtol=1e-10, atol=1e-12, dense_output=True)
    ts = np.array([100.0, 500.0, 1000.0, 2500.0])  # away from the fast jumps
    np.testing.assert_allclose(np.asarray(traj.state(ts))[:, 0], ref.sol(ts)[0], rtol=1e-3)
    # Dopri5 on the same problem runs out of steps: the status says so
    with pytest.raises(jd.SimulationError, match="max_steps"):
        jd.simulate(VanDerPol(mu), (0.0, 3000.0), jnp.array([2.0, 0.0]), max_steps=500)


def test_rosenbrock_forms_its_matrix_once_per_accepted_step():
    """A rejected step leaves the state where it was, so its retry reuses the matrix: one
    formation per accepted step, at its start (counted where the derivative rule runs)."""
    mu, formed = 1000.0, []

    @jax.custom_jvp
    def van_der_pol(x):
        return jnp.stack([x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]])

    @van_der_pol.defjvp
    def _(primals, tangents):
        (x,), (dx,) = primals, tangents
        jax.debug.callback(lambda: formed.append(1))
        J = jnp.array([[0.0, 1.0], [-2 * mu * x[0] * x[1] - 1, mu * (1 - x[0] ** 2)]])
        return van_der_pol(x), J @ dx

    system = jd.System.from_functions(dynamics=lambda t, x, u: van_der_pol(x), num_states=2)
    traj = jd.simulate(system, (0.0, 1000.0), jnp.array([2.0, 0.0]), solver="rosenbrock23", rtol=1e-4,
                       atol=1e-6, max_steps=4096)
    assert int(traj.num_rejected_steps) > 10
    assert len(formed) == int(traj.num_accepted_steps)
    reference = jd.simulate(VanDerPol(mu), (0.0, 1000.0), jnp.array([2.0, 0.0]), solver="rosenbrock23", rtol=1e-4,
                            atol=1e-6, max_steps=4096)
    np.testing.assert_array_equal(traj.final_state, reference.final_state)


@pytest.mark.parametrize("solver", [jd.simulation.Rosenbrock23, jd.simulation.Ros34PW2])
def test_rosenbrock_w_methods_keep_their_order_with_any_matrix(solver):
    """Steps of a fixed size on y' = -y + sin(3t) y^2 (non-autonomous: the T term counts),
    halved: the global error falls as h^order with the exact Jacobian and with a wrong one
    (J + 5 I, through `f_stiff` and `jacobian="stiff"`): W-methods. Also the dense output,
    between steps, to the same order."""
    def f(t, y):
        return -y + jnp.sin(3.0 * t) * y ** 2

    def wrong(t, y):   # the same values, the derivative J + 5 I
        return f(t, y) + 5.0 * (y - jax.lax.stop_gradient(y))

    reference = solve_ivp(lambda t, y: -y + np.sin(3 * t) * y ** 2, (0, 2), [0.8], method="DOP853", rtol=1e-13,
                          atol=1e-14, dense_output=True)

    @functools.partial(jax.jit, static_argnums=(0, 1))
    def run(method, steps):
        h = 2.0 / steps

        def one(y, k):
            result = method.step(f, k * h, y, lambda k0: h, f_stiff=wrong)
            middle = jnp.sum(result.coefficients * 0.5 ** jnp.arange(result.coefficients.shape[0])[:, None], 0)
            return result.y1, middle
        y, middles = jax.lax.scan(one, jnp.array([0.8]), jnp.arange(steps, dtype=jnp.float64))
        return y, middles

    for method in (solver(), solver(jacobian="stiff")):
        errors, dense_errors = [], []
        for steps in (80, 160):
            y, middles = run(method, steps)
            errors.append(abs(float(y[0]) - reference.y[0, -1]))
            times = (np.arange(steps) + 0.5) * 2.0 / steps
            dense_errors.append(np.max(np.abs(np.asarray(middles)[:, 0] - reference.sol(times)[0])))
        assert np.log2(errors[0] / errors[1]) == pytest.approx(solver.order, abs=0.2), errors
        assert np.log2(dense_errors[0] / dense_errors[1]) > solver.order - 0.3, dense_errors


def test_a_stiff_matrix_leaves_the_first_stages_derivative_to_the_vector_field():
    """With `jacobian="stiff"` and no first stage given (no first-same-as-last: events,
    discrete states, tapes), the first stage f(t0, y0) came from the stiff surrogate's
    linearization and carried its approximate derivative into jax.grad; it is f's."""
    def f(t, y):
        return jnp.stack([y[1], -jnp.sin(y[0]) - 3.0 * y[1] ** 3])

    @jax.custom_jvp
    def surrogate(y):   # f's values, a different derivative
        return f(0.0, y)

    @surrogate.defjvp
    def _(primals, tangents):
        (y,), (dy,) = primals, tangents
        return surrogate(y), jnp.array([[0.0, 1.0], [-1.0, -5.0]]) @ dy

    y0 = jnp.array([0.7, -0.4])
    for solver in (jd.simulation.Rosenbrock23(jacobian="stiff"), jd.simulation.Ros34PW2(jacobian="stiff")):
        def y1(y0, first):
            return solver.step(f, 0.0, y0, lambda k0: 0.1, first(y0), lambda t, y: surrogate(y)).y1
        without = jax.jacfwd(lambda y: y1(y, lambda y: None))(y0)
        given = jax.jacfwd(lambda y: y1(y, lambda y: f(0.0, y)))(y0)
        np.testing.assert_allclose(np.asarray(without), np.asarray(given), rtol=1e-14, atol=1e-15)


def test_ros34pw2_on_a_stiff_van_der_pol_is_accurate_in_fewer_steps_than_rosenbrock23():
    """mu = 1000 over 3000 s against SciPy's Radau at 1e-12: the third-order method at rtol
    1e-6 is more accurate than Rosenbrock23 at 1e-7, in under half its steps."""
    mu = 1000.0
    ref = solve_ivp(lambda t, x: [x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]], (0, 3000), [2.0, 0.0],
                    method="Radau", rtol=1e-12, atol=1e-12)

    def run(solver, rtol):
        traj = jd.simulate(VanDerPol(mu), (0.0, 3000.0), jnp.array([2.0, 0.0]), solver=solver, rtol=rtol,
                           atol=rtol, max_steps=20000, dense=False)
        return float(np.max(np.abs(np.asarray(traj.final_state) - ref.y[:, -1]))), int(traj.num_accepted_steps)

    (error_3, steps_3), (error_2, steps_2) = run("ros34pw2", 1e-6), run("rosenbrock23", 1e-7)
    assert error_3 < error_2 and steps_3 < steps_2 / 2, (error_3, steps_3, error_2, steps_2)


@pytest.mark.parametrize("solver,dt,order", [("euler", 1e-3, 1), ("rk4", 5e-2, 4)])
def test_fixed_step_solvers_converge_at_their_order(solver, dt, order):
    sys = SimpleCTExample()
    errors = []
    for h in (dt, dt / 2):
        traj = jd.simulate(sys, (0.0, 2.0), 0.5, solver=solver, dt=h)
        errors.append(abs(float(traj.final_state[0]) - simple_ct_closed_form(0.5, 2.0)))
    assert np.log2(errors[0] / errors[1]) == pytest.approx(order, abs=0.15)


def test_initial_state_defaults_to_the_system_and_zero_input():
    sys = jd.System.from_functions(dynamics=lambda t, x, u: -x + u, num_states=1, num_inputs=1,
                                   initial_state=[2.0])
    traj = jd.simulate(sys, (0.0, 1.0), rtol=1e-10, atol=1e-12)  # x0 from the system, u = 0
    np.testing.assert_allclose(traj.final_state, [2.0 * np.exp(-1.0)], rtol=1e-9)


def test_trajectory_as_input_tape():
    # xdot = u with a first-order-hold input tape through (0, 0), (1, 2), (2, 0): x(2) = 2
    tape = jd.Trajectory.from_samples([0.0, 1.0, 2.0], [0.0, 2.0, 0.0])
    np.testing.assert_allclose(tape.eval(0.25), [0.5])
    sys = jd.System.from_functions(dynamics=lambda t, x, u: u, num_states=1, num_inputs=1)
    traj = jd.simulate(sys, (0.0, 2.0), 0.0, inputs=tape, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(traj.state(1.0), [1.0], rtol=1e-9)
    np.testing.assert_allclose(traj.final_state, [2.0], rtol=1e-9)
    np.testing.assert_allclose(traj.input(0.5), [1.0])
    # zero-order hold
    zoh = jd.Trajectory.from_samples([0.0, 1.0, 2.0], [1.0, -1.0, 3.0], interpolation="zoh")
    np.testing.assert_allclose(zoh.eval(jnp.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5])),
                               [[1.0], [1.0], [-1.0], [-1.0], [3.0], [3.0]])


def test_linear_system_with_feedthrough_output_between_steps():
    A, B, C, D = -1.0, 1.0, 2.0, 0.5
    sys = jd.LinearSystem([[A]], [[B]], [[C]], [[D]])
    u = lambda t: jnp.array([jnp.cos(t)])
    traj = jd.simulate(sys, (0.0, 4.0), 1.0, inputs=u, rtol=1e-11, atol=1e-13)
    # xdot = -x + cos t: x = e^{-t} (x0 - 1/2) + (cos t + sin t)/2
    for t in (0.3, 1.7, 3.9):
        x = np.exp(-t) * 0.5 + (np.cos(t) + np.sin(t)) / 2
        np.testing.assert_allclose(traj.eval(t), [C * x + D * np.cos(t)], rtol=1e-9)


def test_plot_draws_every_output(tmp_path):
    traj = jd.simulate(Pendulum(), (0.0, 2.0), jnp.array([1.0, 0.0]))
    fig = traj.plot()
    ax = fig.axes[0]
    assert [line.get_label() for line in ax.get_lines()] == ["theta", "thetadot"]
    xs, ys = ax.get_lines()[0].get_data()
    np.testing.assert_allclose(ys, np.asarray(traj.eval(jnp.asarray(xs)))[:, 0])
    fig.savefig(tmp_path / "pendulum.png")
    dt = jd.simulate(SimpleDTExample(), (0.0, 5.0), 0.99).plot()
    assert len(dt.axes[0].get_lines()) == 2  # the held value and a dot per sample


def test_float32_runs():
    ref = jd.simulate(Pendulum(), (0.0, 2.0), jnp.array([1.0, 0.0]), rtol=1e-10, atol=1e-12)
    with jax.enable_x64(False):
        x0 = jnp.array([1.0, 0.0], dtype=jnp.float32)
        traj = jd.simulate(Pendulum(), (0.0, 2.0), x0, rtol=1e-5, atol=1e-6)
        final = traj.final_state
        assert final.dtype == jnp.float32 and traj.eval(1.0).dtype == jnp.float32
    np.testing.assert_allclose(final, ref.final_state, rtol=1e-3, atol=1e-4)


def test_double_integrator_closed_form():
    di = jd.models.DoubleIntegrator()
    assert di.state_frame.coordinates == ("q", "qdot") and di.input_frame.coordinates == ("u",)
    traj = jd.simulate(di, (0.0, 2.0), jnp.array([1.0, -0.5]), inputs=lambda t: jnp.array([0.75]),
                       rtol=1e-12, atol=1e-12)
    for t in (0.4, 1.3, 2.0):
        np.testing.assert_allclose(traj.state(t), [1.0 - 0.5 * t + 0.375 * t**2, -0.5 + 0.75 * t], rtol=1e-11)


def test_van_der_pol_limit_cycle_amplitude():
    # for mu = 1 the limit cycle reaches |q| = 2.00861986 (the classical value)
    traj = jd.simulate(VanDerPol(1.0), (0.0, 40.0), jnp.array([0.1, 0.0]), rtol=1e-10, atol=1e-12)
    q = np.asarray(traj.state(np.linspace(30.0, 40.0, 20001)))[:, 0]
    assert q.max() == pytest.approx(2.00861986, abs=1e-6)


def test_device_places_a_call_from_python_and_is_ignored_inside_jit():
    cpu = jax.devices("cpu")[0]
    x0 = jnp.array([1.0, 0.0])
    placed = jd.simulate(Pendulum(), (0.0, 1.0), x0, device=cpu)
    assert placed.final_state.devices() == {cpu}
    np.testing.assert_array_equal(placed.final_state, jd.simulate(Pendulum(), (0.0, 1.0), x0).final_state)
    inside = jax.jit(lambda x: jd.simulate(Pendulum(), (0.0, 1.0), x, device=cpu).final_state)(x0)
    np.testing.assert_array_equal(inside, placed.final_state)


@pytest.mark.gpu
def test_a_call_from_python_runs_on_the_host_when_the_default_device_is_a_gpu():
    """One simulation is launch-bound on a GPU (H100: the pendulum 3.4x, a double pendulum
    5.9x slower than the host, benchmarks/placement_benchmark.py): from Python it runs on the
    host unless a device is named or an argument is committed to the GPU."""
    gpu = jax.devices("gpu")[0]
    x0 = jnp.array([1.0, 0.0])
    where = lambda traj: traj.coefficients.devices()  # noqa: E731  (where the program ran)
    assert where(jd.simulate(Pendulum(), (0.0, 1.0), x0)) == {jax.devices("cpu")[0]}
    assert where(jd.simulate(Pendulum(), (0.0, 1.0), x0, device=gpu)) == {gpu}
    assert where(jd.simulate(Pendulum(), (0.0, 1.0), jax.device_put(x0, gpu))) == {gpu}


def test_float32_time_is_carried_as_an_exact_pair_and_float64_time_as_one_number():
    """`advance`: (t + t_low) + h as Knuth's two-sum, so that float32 steps of 4e-8 s at t = 1
    (a third of t's spacing) add up exactly, under jit as eagerly (XLA must not reassociate
    the sum), t the float at or below the sum; float64 keeps one number, and t carries all of
    time's derivative."""
    from jaxdrake.simulation._controller import advance
    run = jax.jit(lambda t, h: jax.lax.fori_loop(0, 25, lambda i, c: advance(c[0], c[1], h), (t, jnp.zeros_like(t))))
    t, low = run(jnp.float32(1.0), jnp.float32(4e-8))
    exact = 1.0 + 25 * float(np.float32(4e-8))
    assert float(t) <= exact < float(np.nextafter(t, np.float32(np.inf))) and float(low) >= 0
    assert abs(float(t) + float(low) - exact) < 1e-13
    t, low = advance(jnp.float64(1.0), jnp.float64(0.0), jnp.float64(1e-17))
    assert float(t) == 1.0 and float(low) == 0.0
    tangent = jax.jvp(lambda t0: advance(t0, jnp.float32(1e-8), jnp.float32(1e-8)), (jnp.float32(1.0),), (jnp.float32(1.0),))[1]
    assert (float(tangent[0]), float(tangent[1])) == (1.0, 0.0)


def test_whether_a_vector_field_reads_time_is_followed_into_jit_and_custom_derivatives():
    """`_jaxprs.reads_argument` (the loop's test for steps below t's spacing): a jitted
    function, a custom derivative or a switch of modes (a hybrid system: every multi-mode one
    counted as reading t, and its float32 drops stopped) that ignores t does not read it; one
    that passes t through a loop is taken to read it (conservative), as is any arithmetic on
    it."""
    from jaxdrake._jaxprs import reads_argument

    @jax.jit
    def inner(t, x):
        return -x

    @jax.custom_jvp
    def smooth(t, x):
        return jnp.tanh(x)

    smooth.defjvp(lambda primals, tangents: (smooth(*primals), tangents[1] / jnp.cosh(primals[1]) ** 2))
    looped = lambda t, x: jax.lax.fori_loop(0, 3, lambda i, c: c + 0.0 * t, x)  # noqa: E731

    def switched(t, x, reading):   # a hybrid system's modes: a switch whose index is a state's
        return jax.lax.switch(jnp.int32(x[0] > 0), [lambda t, x: -x, lambda t, x: x * (t if reading else 2.0)], t, x)

    args = (jnp.float32(0.5), jnp.ones(3, jnp.float32))
    assert not reads_argument(inner, args, 0) and reads_argument(inner, args, 1)
    assert not reads_argument(smooth, args, 0)
    assert reads_argument(looped, args, 0) and reads_argument(lambda t, x: x * jnp.sin(t), args, 0)
    assert not reads_argument(lambda t, x: switched(t, x, False), args, 0)
    assert reads_argument(lambda t, x: switched(t, x, True), args, 0)


def test_float32_fixed_steps_add_up_to_the_time_span():
    """RK4 at dt = 1e-3 for 100 s in float32: t rounded after every step made some steps
    short, 100043 of them; time carried as a pair takes exactly T / dt, and an undamped
    pendulum ends within 1e-4 of float64's run (1.3e-4 before)."""
    pendulum = Pendulum(b=0.0)
    runs = [jd.simulate(pendulum, (0.0, 100.0), jnp.asarray([0.5, 0.0], dtype), solver="rk4", dt=1e-3,
                        max_steps=200000, dense=False) for dtype in (jnp.float32, jnp.float64)]
    assert [int(r.num_accepted_steps) for r in runs] == [100000, 100000]
    np.testing.assert_allclose(runs[0].final_state, runs[1].final_state, atol=1e-4)
    # float32(0.01) is below 0.01: the 1000th step ends 2e-7 short of tf = 10 and is stretched
    # onto it (a sliver step after it ran out of max_steps = T / dt)
    short = jd.simulate(pendulum, (0.0, 10.0), jnp.asarray([0.5, 0.0], jnp.float32), solver="rk4", dt=0.01,
                        max_steps=1000)
    assert int(short.num_accepted_steps) == 1000 and float(short.t_final) == 10.0


def test_float32_steps_over_an_input_tape_end_on_its_breakpoints():
    """x' = u, u a zero-order-hold tape switching sign every 0.1 s, RK4 at dt = 0.01 in
    float32: every step ends on the tape's breakpoints (t is never read past one), no
    sliver steps beside them, and x(tf) is the tape's integral to float32's rounding."""
    ts = (np.arange(0, 101) * 0.1).astype(np.float32)
    values = np.where(np.arange(101) % 2 == 0, 1.0, -1.0).astype(np.float32)
    tape = jd.Trajectory.from_samples(jnp.asarray(ts), jnp.asarray(values), interpolation="zoh")
    integrator = jd.System.from_functions(dynamics=lambda t, x, u: u, num_states=1, num_inputs=1)
    tf = np.float32(9.95)
    traj = jd.simulate(integrator, (0.0, float(tf)), jnp.zeros(1, jnp.float32), inputs=tape, solver="rk4", dt=0.01)
    count = int(traj.num_accepted_steps)
    widths = np.asarray(traj.state_trajectory.t_end[1:count + 1]) - np.asarray(traj.state_trajectory.t_start[1:count + 1])
    assert count == 995 and np.min(widths) > 0.009
    exact = sum(v * (min(b, tf) - a) for a, b, v in zip(ts[:-1].astype(float), ts[1:].astype(float), values) if a < tf)
    np.testing.assert_allclose(float(traj.final_state[0]), exact, atol=2e-6)


def test_float32_steps_may_be_far_below_float32_eps_early_in_time():
    """The step-size floor is 16 units of the spacing of time (MATLAB's 16*eps(t)), not a
    multiple of eps: a pulse of width 1e-6 s at t = 1e-3 needs float32 steps of ~1e-7 s, 20x
    below float32's eps. x' = a / (1 + (a (t - c))^2) integrates to arctan(a (t - c)). (At
    rtol 1e-4 one step of 2.4e-6 s across the pulse's peak may pass the error test, as
    rounding decides: 0.4% off.)"""
    a, c = 1e6, 1e-3
    pulse = jd.System.from_functions(dynamics=lambda t, x, u: a / (1 + (a * (t - c)) ** 2) + 0 * x,
                                     num_states=1)
    traj = jd.simulate(pulse, (0.0, 1.0), jnp.zeros(1, jnp.float32), rtol=1e-5, atol=1e-6, dense=False)
    assert traj.final_state.dtype == jnp.float32
    np.testing.assert_allclose(float(traj.final_state[0]), np.arctan(a * (1 - c)) + np.arctan(a * c), rtol=1e-3)
