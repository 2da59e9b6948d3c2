"""Lyapunov / SOS analysis: the notes' chapter-11 examples against closed forms, SciPy, Drake's
`RegionOfAttraction` and simulation; infeasible programs reported as such."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jaxdrake as jd
from jaxdrake.analysis import (InfeasibleError, SosProgram, common_lyapunov_function,
                               global_lyapunov_function, region_of_attraction, sample_sublevel_set,
                               search_region_of_attraction, trig_polynomial_system,
                               verify_region_of_attraction)
from jaxdrake.polynomials import Polynomial

RNG = np.random.default_rng(3)


def reversed_van_der_pol():
    """The notes' time-reversed Van der Pol oscillator: stable origin, bounded by the limit cycle."""
    return jd.System.from_functions(lambda t, x, u: jnp.stack([-x[1], x[0] + (x[0] ** 2 - 1) * x[1]]),
                                    num_states=2, time_invariant=True)


def test_lyapunov_equations_match_scipy():
    A = RNG.normal(size=(4, 4)) - 3 * np.eye(4)
    Q = np.eye(4) + 0.1 * np.ones((4, 4))
    P = np.asarray(jd.analysis.solve_continuous_lyapunov(A, Q))
    np.testing.assert_allclose(P, scipy.linalg.solve_continuous_lyapunov(A.T, -Q), rtol=1e-10)
    Ad = A / 5
    Pd = np.asarray(jd.analysis.solve_discrete_lyapunov(Ad, Q))
    np.testing.assert_allclose(Pd, scipy.linalg.solve_discrete_lyapunov(Ad.T, Q), rtol=1e-10)


def test_cubic_system_region_is_the_unit_interval():
    # xdot = -x + x^3, V = x^2: the true region of attraction is |x| < 1, so rho = 1.
    rho = region_of_attraction(jd.models.SimpleCTExample(), [0.0], [[1.0]])
    assert abs(rho - 1.0) < 1e-4


def test_reversed_van_der_pol_matches_drake_and_converges_in_simulation():
    pytest.importorskip("pydrake")
    from pydrake.symbolic import Variable
    from pydrake.systems.analysis import RegionOfAttraction, RegionOfAttractionOptions
    from pydrake.systems.primitives import SymbolicVectorSystem

    system = reversed_van_der_pol()
    roa = region_of_attraction(system, [0.0, 0.0], return_certificate=True)
    assert roa.success and roa.status == roa.result.status and isinstance(roa.result, jd.analysis.SosResult)
    S = np.array([[1.5, -0.5], [-0.5, 1.0]])  # A'S + SA = -I for A = [[0, -1], [1, -1]]
    np.testing.assert_allclose(np.asarray(jax.hessian(roa.V)(jnp.zeros(2))) / 2, S, rtol=1e-10)

    x = np.array([Variable("x0"), Variable("x1")])
    drake_system = SymbolicVectorSystem(state=x, dynamics=[-x[1], x[0] + (x[0] ** 2 - 1) * x[1]])
    context = drake_system.CreateDefaultContext()
    context.SetContinuousState([0.0, 0.0])
    options = RegionOfAttractionOptions()
    options.lyapunov_candidate = x.dot(S @ x)
    options.state_variables = x
    V_drake = RegionOfAttraction(drake_system, context, options)  # V / rho_drake
    rho_drake = 1.5 / V_drake.Evaluate({x[0]: 1.0, x[1]: 0.0})
    assert abs(roa.rho - rho_drake) <= 0.01 * rho_drake

    # every sampled state inside the certified set converges; the true-dynamics check passes
    assert verify_region_of_attraction(system, [0.0, 0.0], S, roa.rho).ok
    starts = sample_sublevel_set(np.zeros(2), S, roa.rho, 256, seed=1)
    final = jax.vmap(lambda x0: jd.simulate(system, (0.0, 30.0), x0).final_state)(jnp.asarray(starts))
    assert np.abs(np.asarray(final)).max() < 1e-3
    # just outside the limit cycle, states diverge: the certificate is not vacuous
    outside = jd.simulate(system, (0.0, 5.0), jnp.array([2.5, 0.0]), throw=False)
    assert outside.status != 0 or np.abs(np.asarray(outside.final_state)).max() > 10


def test_region_of_attraction_refuses_unstable_equilibria_and_non_equilibria():
    with pytest.raises(ValueError, match="not locally exponentially stable"):
        region_of_attraction(jd.models.Pendulum(), [np.pi, 0.0])
    with pytest.raises(ValueError, match="not an equilibrium"):
        region_of_attraction(jd.models.Pendulum(), [0.3, 0.0])


def test_region_of_attraction_of_a_taylor_expanded_pendulum_holds_on_the_true_dynamics():
    pendulum = jd.models.Pendulum()
    roa = region_of_attraction(pendulum, [0.0, 0.0], return_certificate=True)
    S = np.asarray(jax.hessian(roa.V)(jnp.zeros(2))) / 2
    assert roa.rho > 0 and verify_region_of_attraction(pendulum, [0.0, 0.0], S, roa.rho).ok


def test_damped_pendulum_has_a_global_certificate_and_the_undamped_one_is_refused():
    s, c, w = Polynomial.variables_of(3)
    x0 = np.array([0.0, 1.0, 0.0])
    dissipation = (s**2 + (c - 1) ** 2 + w**2) * s**2  # the notes' choice: zero at both equilibria
    pendulum = jd.models.Pendulum()
    mgl = pendulum.m * pendulum.g * pendulum.l
    V = global_lyapunov_function(trig_polynomial_system(pendulum, [0]), x0, 2, dissipation=dissipation,
                                 normalization=([1.0, 0.0, 0.0], mgl))
    # independent check on the circle with the true dynamics: V >= 0 = V(x0), Vdot <= 0
    theta = RNG.uniform(-np.pi, np.pi, 20_000)
    thetadot = RNG.normal(scale=5.0, size=20_000)
    states = np.stack([theta, thetadot], 1)
    z = np.stack([np.sin(theta), np.cos(theta), thetadot], 1)
    xdot = np.asarray(jax.vmap(lambda x: pendulum.dynamics(0.0, x, jnp.zeros(1)))(jnp.asarray(states)))
    zdot = np.stack([z[:, 1] * xdot[:, 0], -z[:, 0] * xdot[:, 0], xdot[:, 1]], 1)
    grad = np.asarray(jax.vmap(jax.grad(V))(jnp.asarray(z)))
    assert np.asarray(V(z)).min() >= -1e-6 and abs(float(V(x0))) < 1e-6
    assert np.einsum("ki,ki->k", grad, zdot).max() <= 1e-6
    with pytest.raises(InfeasibleError):
        global_lyapunov_function(trig_polynomial_system(jd.models.Pendulum(b=0.0), [0]), x0, 2,
                                 dissipation=dissipation, normalization=([1.0, 0.0, 0.0], mgl))


def test_common_lyapunov_function_feasible_and_infeasible_families():
    # a family built to share x'P0x: A_i = P0^-1 (-Q_i + W_i), W_i skew
    M = RNG.normal(size=(4, 4))
    P0 = M @ M.T + np.eye(4)
    family = []
    for _ in range(3):
        N, W = RNG.normal(size=(4, 4)), RNG.normal(size=(4, 4))
        family.append(np.linalg.solve(P0, -(N @ N.T + 0.5 * np.eye(4)) + (W - W.T)))
    P = common_lyapunov_function(family)
    assert np.linalg.eigvalsh(P).min() > 0
    assert max(np.linalg.eigvalsh(A.T @ P + P @ A).max() for A in family) < 0
    # two stable matrices whose switching is unstable: a product of their flows has spectral
    # radius > 1 (checked with SciPy), so no common Lyapunov function can exist
    A1, A2 = np.array([[-0.1, 1.0], [-2.0, -0.1]]), np.array([[-0.1, 2.0], [-1.0, -0.1]])
    assert max(np.linalg.eigvals(A).real.max() for A in (A1, A2)) < 0
    radius = max(np.abs(np.linalg.eigvals(scipy.linalg.expm(A2 * t2) @ scipy.linalg.expm(A1 * t1))).max()
                 for t1 in np.linspace(0.1, 3, 30) for t2 in np.linspace(0.1, 3, 30))
    assert radius > 1
    with pytest.raises(InfeasibleError):
        common_lyapunov_function([A1, A2])


def test_sos_program_reports_infeasibility_and_its_certificate_check_catches_lies():
    x, y = Polynomial.variables_of(2)
    prog = SosProgram(2)
    prog.add_sos_constraint(x**2 - 1.0)  # negative at the origin: not SOS
    with pytest.raises(InfeasibleError) as caught:
        prog.solve()
    assert caught.value.status == jd.analysis.ConicStatus.INFEASIBLE and caught.value.solver == "CLARABEL"
    # a genuine SOS polynomial: (x - y)^2 + x^2 y^2
    prog = SosProgram(2)
    record = prog.add_sos_constraint((x - y) ** 2 + x**2 * y**2)
    result = prog.solve()
    assert result.success and result.status == jd.analysis.ConicStatus.OPTIMAL and result.message == "optimal"
    assert result.check(20_000).ok
    assert sorted(map(tuple, record.basis)) == [(0, 1), (1, 0), (1, 1)]  # Newton polytope pruning
    assert np.allclose(record.gram_value(), record.gram_value().T)
    prog.space.solution = -prog.space.solution  # a wrong Gram matrix (-Q) is caught by the residuals
    residual, eig = result.residuals()
    assert residual > 1e-3 and eig < 0


def test_searching_for_the_region_of_attraction_enlarges_it(capsys):
    system = reversed_van_der_pol()
    quadratic = region_of_attraction(system, [0.0, 0.0])
    search = search_region_of_attraction(system, [0.0, 0.0], degree=4, iterations=4, progress=True)
    shown = capsys.readouterr().err  # the progress bar, on stderr, with the last beta
    assert "region of attraction" in shown and f"beta={search.history[-1]:.6g}" in shown
    assert all(b2 >= b1 * (1 - 1e-6) for b1, b2 in zip(search.history, search.history[1:]))
    assert search.beta > 1.2 * quadratic  # the quartic region contains a larger ellipse
    assert search.success and search.result.check().ok
    # states in the new region (rejection-sampled from a box) converge in simulation
    box = RNG.uniform(-2.5, 2.5, size=(4000, 2))
    inside = box[np.asarray(search.V(box)) <= 1.0][:256]
    final = jax.vmap(lambda x0: jd.simulate(system, (0.0, 30.0), x0).final_state)(jnp.asarray(inside))
    assert len(inside) > 100 and np.abs(np.asarray(final)).max() < 1e-3


@pytest.mark.parametrize("solver, dense_columns", [("CLARABEL", 1024), ("SCS", 1024), ("CLARABEL", 0), ("SCS", 0)])
def test_conic_program_solves_an_lmi_and_an_lp_to_their_closed_forms(solver, dense_columns, monkeypatch):
    """min t s.t. [[t, 1], [1, t]] PSD is t = 1; max x + y on x, y >= 0, x + 2y <= 4, 3x + y <= 6
    is the vertex (8/5, 6/5), value 14/5. The PSD block goes through each solver's own
    triangle layout (Clarabel's upper, SCS's lower); the program's maps dense (small programs)
    and sparse."""
    from jaxdrake.analysis import ConicProgram
    from jaxdrake.polynomials import _affine

    monkeypatch.setattr(_affine, "DENSE_COLUMNS", dense_columns)

    prog = ConicProgram()
    t = prog.new_variable()
    prog.add_psd_constraint(t * np.eye(2).ravel() + np.array([0.0, 1.0, 1.0, 0.0]), 2)
    prog.solve(minimize=t, solver=solver)
    assert abs(t.value - 1.0) < 1e-5
    prog = ConicProgram()
    xy = prog.new_variable(2)
    for constraint in (xy >= 0, xy[0] + 2 * xy[1] <= 4, 3 * xy[0] + xy[1] <= 6):
        prog.add_constraint(constraint)
    result = prog.solve(maximize=xy.sum(), solver=solver)
    np.testing.assert_allclose(xy.value, [1.6, 1.2], atol=1e-5)
    assert abs(result.objective - 2.8) < 1e-5 and result.success and result.solver == solver
    prog = ConicProgram()
    xy = prog.new_variable(2)
    prog.add_constraint(xy >= 0)
    with pytest.raises(jd.analysis.SolveError, match="unbounded") as caught:  # x + y has no maximum on x, y >= 0
        prog.solve(maximize=xy.sum(), solver=solver)
    assert caught.value.status == jd.analysis.ConicStatus.UNBOUNDED
