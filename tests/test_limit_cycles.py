"""Limit cycles (`jd.analysis.limit_cycle`) and the compass gait (`jd.models.CompassGait`):
Van der Pol's period and Floquet multiplier against known values, Liouville's formula and
finite differences; the compass gait against Drake's `CompassGait` and its passive cycle's
return map against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.analysis import LimitCycleError, limit_cycle

TIGHT = dict(rtol=1e-12, atol=1e-12, max_steps=16384)


def test_van_der_pol_period_and_floquet_multiplier():
    """mu = 1: T = 6.6632868593... (Hairer, Norsett & Wanner). The nontrivial multiplier is
    det(Phi) = exp(int_0^T div f dt) = exp(-int_0^T (q^2 - 1) dt) (Liouville), and equals the
    eigenvalue of a central-difference monodromy matrix."""
    vdp = jd.models.VanDerPol()
    cycle = limit_cycle(vdp, [2.0, 0.0], 6.0)
    assert abs(float(cycle.period) - 6.6632868593) < 1e-8
    assert float(cycle.residual) < 1e-10
    trivial, nontrivial = np.asarray(cycle.floquet_multipliers)
    assert abs(trivial - 1) < 1e-7 and abs(nontrivial.imag) < 1e-12
    ts = np.linspace(0.0, float(cycle.period), 20001)
    q = np.asarray(cycle.trajectory.state(jnp.asarray(ts)))[:, 0]
    liouville = np.exp(-np.trapezoid(q ** 2 - 1, ts))
    np.testing.assert_allclose(nontrivial.real, liouville, rtol=1e-6)
    eps, x = 1e-6, np.asarray(cycle.state)
    flow = lambda x0: np.asarray(jd.simulate(vdp, (0.0, float(cycle.period)), jnp.asarray(x0), **TIGHT).final_state)
    Phi = np.stack([(flow(x + eps * e) - flow(x - eps * e)) / (2 * eps) for e in np.eye(2)], 1)
    np.testing.assert_allclose(np.asarray(cycle.monodromy), Phi, atol=1e-6)
    np.testing.assert_allclose(sorted(abs(np.linalg.eigvals(Phi))), [nontrivial.real, 1.0], rtol=0, atol=1e-6)


# ~7 s of compiling the flow's second derivatives; a limit cycle's derivative (the rimless
# wheel's period in its slope) runs by default
@pytest.mark.slow
def test_van_der_pol_period_and_multiplier_derivatives_equal_central_differences():
    """d(period, nontrivial multiplier)/d mu by jacfwd from Python (the residual is then
    concrete, the orbit's state a tracer) against central differences of the same
    undifferentiated call; the multiplier's needs the flow's second derivatives."""
    def outputs(mu):
        cycle = limit_cycle(jd.models.VanDerPol(mu=mu), [2.0, 0.0], 6.0)
        return jnp.stack([cycle.period, cycle.floquet_multipliers[1].real])

    h = 1e-5
    np.testing.assert_allclose(np.asarray(jax.jacfwd(outputs)(1.0)),
                               (np.asarray(outputs(1.0 + h)) - np.asarray(outputs(1.0 - h))) / (2 * h), rtol=1e-5)


def test_failures_are_named_errors():
    # the first test's compiled program (tol, guesses and parameters are its arguments)
    with pytest.raises(LimitCycleError, match=r"Newton's method stopped at residual .* after 30 iterations"):
        limit_cycle(jd.models.VanDerPol(), [4.0, 3.0], 3.0, tol=1e-300)
    # the origin, an equilibrium on the phase condition's plane (the field there is vertical)
    with pytest.raises(LimitCycleError, match="converged to an equilibrium"):
        limit_cycle(jd.models.VanDerPol(), [0.1, 0.0], 2.0)


def drake_compass_gait_impacts(x0, t_final):
    """(times, pre-impact states) of Drake's CompassGait simulated from x0."""
    from pydrake.examples import CompassGait
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator
    from pydrake.systems.framework import EventStatus

    simulator = Simulator(CompassGait())
    context = simulator.get_mutable_context()
    context.SetContinuousState(x0)
    context.SetDiscreteState([0.0])
    ResetIntegratorFromFlags(simulator, "runge_kutta5", 1e-3)
    simulator.get_mutable_integrator().set_target_accuracy(1e-13)
    context.SetAccuracy(1e-13)
    log = []

    def monitor(c):  # called after each step: at a witness, before the reset is applied
        log.append((c.get_time(), c.get_continuous_state_vector().CopyToVector().copy()))
        return EventStatus.Succeeded()

    simulator.set_monitor(monitor)
    simulator.Initialize()
    simulator.AdvanceTo(t_final)
    ts, xs = np.array([t for t, _ in log]), np.array([x for _, x in log])
    swapped = np.nonzero(np.abs(np.diff(xs[:, 0])) > 0.05)[0]  # the legs swap at an impact
    return ts[swapped], xs[swapped]


def test_the_compass_gait_walks_as_drakes_compass_gait_does():
    pytest.importorskip("pydrake")
    x0 = np.array([0.0, 0.0, 0.4, -2.0])  # Drake's examples/compass_gait/simulate.cc start
    times, states = drake_compass_gait_impacts(x0, 20.0)
    traj = jd.simulate(jd.models.CompassGait(), (0.0, 20.0), jnp.asarray(x0), **TIGHT)
    ours = traj.events["times"]
    assert len(ours) == len(times) > 20
    np.testing.assert_allclose(ours, times, rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(traj.state(jnp.asarray(ours), side="left")), states, rtol=0, atol=1e-7)


@pytest.mark.slow  # ~25 s; the limit-cycle solver and its derivative are checked by default on the rimless wheel's closed form
def test_the_passive_compass_gait_limit_cycle_and_its_return_map():
    """The fixed point of the heel-strike-to-heel-strike map: residual <= 1e-10 and P(x*) = x*
    by an independent simulation; the return map's eigenvalues against central differences
    (one is 0: the event surface is the section); d x* / d slope against finite differences."""
    gait = jd.models.CompassGait()
    cycle = limit_cycle(gait, [-0.22, 0.32, 1.09, 0.38], 0.75)
    x_star = np.asarray(cycle.state)
    assert float(cycle.residual) <= 1e-10
    np.testing.assert_allclose(x_star[0] + x_star[1], 2 * gait.slope, atol=1e-12)  # just after a strike

    def P(system, x):
        return jd.simulate(system, (0.0, 2.0), jnp.asarray(x), **TIGHT).events["states"][0]

    np.testing.assert_allclose(P(gait, x_star), x_star, atol=1e-9)
    eps = 1e-6
    DP = np.stack([(P(gait, x_star + eps * e) - P(gait, x_star - eps * e)) / (2 * eps) for e in np.eye(4)], 1)
    np.testing.assert_allclose(np.asarray(cycle.monodromy), DP, atol=1e-5)
    moduli = np.abs(np.asarray(cycle.floquet_multipliers))
    np.testing.assert_allclose(moduli, np.sort(np.abs(np.linalg.eigvals(DP)))[::-1], atol=1e-5)
    assert moduli[0] < 1 and moduli[-1] < 1e-8  # stable; the section's zero


def rimless_wheel_period(slope, l=1.0, g=9.81, spokes=8):
    """The period of the rimless wheel's rolling orbit and its derivative in the slope, by
    quadrature of the closed form (independent of jaxdrake). Just after an impact theta = gamma
    - alpha with speed w, w^2 = cot(2 alpha)^2 4 (g/l) sin(alpha) sin(gamma) (the fixed point
    of the return map); energy, thetadot^2 / 2 + (g/l) cos(theta), is kept until the next spoke
    lands at theta = gamma + alpha, so T = int ds / sqrt(w^2 + 2 (g/l)(cos(gamma - alpha) -
    cos(gamma + s))) over s in [-alpha, alpha], differentiated under the integral sign."""
    from scipy.integrate import quad

    a, k = np.pi / spokes, g / l
    w2 = 4 * k * np.sin(a) * np.sin(slope) / np.tan(2 * a) ** 2
    dw2 = 4 * k * np.sin(a) * np.cos(slope) / np.tan(2 * a) ** 2
    speed2 = lambda s: w2 + 2 * k * (np.cos(slope - a) - np.cos(slope + s))  # noqa: E731
    T = quad(lambda s: speed2(s) ** -0.5, -a, a, epsabs=0, epsrel=1e-13)[0]
    dT = quad(lambda s: -0.5 * speed2(s) ** -1.5 * (dw2 + 2 * k * (np.sin(slope + s) - np.sin(slope - a))),
              -a, a, epsabs=0, epsrel=1e-13)[0]
    return T, dT


RIMLESS_GUESS = [0.08 - np.pi / 8, 1.0]


def test_the_rimless_wheel_period_and_its_slope_derivative_equal_the_closed_form():
    """dT/dslope has two terms: the flow's own (the spoke lands elsewhere) and the orbit's
    (the speed just after an impact changes with the slope); the second dominates (-25.1 of
    it), and was once dropped (+0.645). Forward mode, one compiled program (jvp) under `jit`:
    eager, `jax.jvp` of limit_cycle's program carries the tangents of all its outputs (the
    monodromy's too, second derivatives through the impact), 3.8 s of compiling against 1.3 s."""
    T, dT = rimless_wheel_period(0.08)
    period = lambda s: limit_cycle(jd.models.RimlessWheel(slope=s), RIMLESS_GUESS, 1.0).period  # noqa: E731
    value, derivative = jax.jit(lambda s: jax.jvp(period, (s,), (1.0,)))(0.08)
    np.testing.assert_allclose(float(value), T, rtol=1e-10)
    np.testing.assert_allclose(float(derivative), dT, rtol=1e-7)
    assert abs(dT + 25.107) < 1e-3


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_the_rimless_wheel_period_derivative_in_reverse_mode():
    """The same derivative by reverse mode (autodiff="reverse", jax.jacrev), with that of the
    speed on the orbit against the fixed point's closed form, w = cot(2 alpha) sqrt(4 (g/l)
    sin(alpha) sin(gamma)): dw/dgamma = w cot(gamma) / 2."""
    T, dT = rimless_wheel_period(0.08)

    def period_and_speed(s):
        cycle = limit_cycle(jd.models.RimlessWheel(slope=s), RIMLESS_GUESS, 1.0, autodiff="reverse")
        out = jnp.stack([cycle.period, cycle.state[1]])
        return out, out

    derivative, value = jax.jacrev(period_and_speed, has_aux=True)(0.08)
    w = float(jd.models.RimlessWheel().rolling_fixed_point())
    np.testing.assert_allclose(np.asarray(value), [T, w], rtol=1e-10)
    np.testing.assert_allclose(np.asarray(derivative), [dT, w / np.tan(0.08) / 2], rtol=1e-7)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_the_compass_gait_cycle_derivatives_equal_central_differences():
    """d(period, fixed point, Floquet multipliers)/dslope of the passive compass gait by the
    implicit function theorem (jax.jvp) against central differences of the same outputs (from
    the same compiled program). The period's was 0.605 where differences (here, and Drake's)
    give 0.815; the multipliers' needs the return map's second derivatives through the impact."""
    guess = jnp.array([-0.22, 0.32, 1.09, 0.38])
    slope, h = jd.models.CompassGait().slope, 1e-5

    def outputs(s):
        cycle = limit_cycle(jd.models.CompassGait(slope=s), guess, 0.75)
        return cycle.period, cycle.state, jnp.abs(cycle.floquet_multipliers[:3])  # the 4th is 0

    run = lambda s: jax.jvp(outputs, (s,), (1.0,))  # noqa: E731
    _, derivatives = run(slope)
    (plus, _), (minus, _) = run(slope + h), run(slope - h)
    for d, p, m in zip(derivatives, plus, minus):
        np.testing.assert_allclose(np.asarray(d), (np.asarray(p) - np.asarray(m)) / (2 * h), rtol=1e-5, atol=1e-5)
    assert abs(float(derivatives[0]) - 0.815) < 1e-3


def test_a_period_guess_shorter_than_the_first_event_is_named():
    with pytest.raises(LimitCycleError, match=r"needs 1 event \(of 'step forward', 'step backward'\) within "
                                              r"3 x period_guess = 0\.3 s.*found 0; event 1 comes at t = 1\.53"):
        limit_cycle(jd.models.RimlessWheel(), RIMLESS_GUESS, 0.1)
    with pytest.raises(ValueError, match="autodiff must be"):
        limit_cycle(jd.models.RimlessWheel(), RIMLESS_GUESS, 1.0, autodiff="backward")


def test_periodic_collocation_finds_the_same_van_der_pol_orbit():
    """The second route: Hermite-Simpson collocation with x(T) = x(0), a free duration, and
    the phase fixed on the section qdot = 0, q >= 1 (else x = 0, 'periodic' with any T, is
    a solution). Its period converges to the shooting period as the knots multiply (O(h^4))."""
    from jaxdrake.trajopt import DirectCollocation

    vdp = jd.models.VanDerPol()
    shooting = limit_cycle(vdp, [2.0, 0.0], 6.6)
    T = float(shooting.period)
    errors = []
    for knots in (31, 61):
        prog = DirectCollocation(vdp, knots, duration=(5.0, 8.0))
        prog.add_periodicity()
        prog.add_duration_cost(0.0)  # a feasibility problem
        prog.add_boundary_constraint(lambda x0, xf: x0[1:], np.zeros(1), np.zeros(1))
        prog.add_state_bounds([1.0, -np.inf], [np.inf, np.inf], knots=[0])
        ts = np.linspace(0.0, T, knots)
        guess = np.asarray(shooting.trajectory.state(jnp.asarray(ts))) * 1.05  # a perturbed orbit
        result = prog.solve(states=guess, duration=T * 0.97)
        assert result.success, result.message
        errors.append(abs(result.duration - T))
        np.testing.assert_allclose(result.knot_states[0], np.asarray(shooting.state), atol=10 * errors[-1] ** 0.5)
    assert errors[0] < 1e-3 and errors[1] < errors[0] / 8
