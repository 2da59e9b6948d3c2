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


def test_failures_are_named_errors():
    with pytest.raises(LimitCycleError, match="Newton's method stopped"):
        limit_cycle(jd.models.VanDerPol(), [4.0, 3.0], 3.0, max_iterations=2)
    with pytest.raises(LimitCycleError, match="converged to an equilibrium"):  # damped: no cycle
        limit_cycle(jd.models.Pendulum(b=0.5), [0.1, 0.0], 2.0)


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


@pytest.mark.slow
def test_the_fixed_point_is_differentiable_with_respect_to_the_slope():
    """d x* / d slope by the implicit-function step (jax.jacfwd) against finite differences."""
    x_star = np.asarray(limit_cycle(jd.models.CompassGait(), [-0.22, 0.32, 1.09, 0.38], 0.75).state)
    slope = jd.models.CompassGait().slope
    d_state = jax.jacfwd(lambda s: limit_cycle(jd.models.CompassGait(slope=s), x_star, 0.75).state)(slope)
    at = lambda s: np.asarray(limit_cycle(jd.models.CompassGait(slope=s), x_star, 0.75).state)
    fd = (at(slope + 1e-6) - at(slope - 1e-6)) / 2e-6
    np.testing.assert_allclose(np.asarray(d_state), fd, rtol=1e-5, atol=1e-6)


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
