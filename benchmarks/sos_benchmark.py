"""SOS analysis against Drake: the time-reversed Van der Pol region of attraction and the
pendulum's global stability certificate, the same polynomials on both sides.

- Van der Pol: `jd.analysis.region_of_attraction` (V from the linearization's Lyapunov
  equation) vs Drake's `RegionOfAttraction` with the same V as `lyapunov_candidate`.
- Pendulum: `jd.analysis.global_lyapunov_function` in (s, c, thetadot) vs the notes' program
  written with Drake's `MathematicalProgram` (free quadratic V, multiplier of degree 2 on
  s^2 + c^2 = 1, dissipation 1e-4 |x - x0|^2 s^2, V(pi) = mgl) and Drake's default solver.

Both sides solve an SDP with an interior-point method (Clarabel here, whatever Drake's wheel
picks there); rows also report our solver time (program assembly from the sparse affine
coefficient maps, and Clarabel). Our calls include the checks of every answer (coefficient
residuals, Gram eigenvalues) and, where stated, the 10^4-point sampled check of the certificate.

Run:  python benchmarks/sos_benchmark.py [--repeats N]
"""

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, best_time, machine_line

jax.config.update("jax_enable_x64", True)


def drake_van_der_pol(S):
    from pydrake.symbolic import Variable
    from pydrake.systems.analysis import RegionOfAttraction, RegionOfAttractionOptions
    from pydrake.systems.primitives import SymbolicVectorSystem

    x = np.array([Variable("x0"), Variable("x1")])
    system = SymbolicVectorSystem(state=x, dynamics=[-x[1], x[0] + (x[0] ** 2 - 1) * x[1]])
    context = system.CreateDefaultContext()
    context.SetContinuousState([0.0, 0.0])
    options = RegionOfAttractionOptions()
    options.lyapunov_candidate = x.dot(S @ x)
    options.state_variables = x

    def solve():
        V = RegionOfAttraction(system, context, options)
        return 1.5 / V.Evaluate({x[0]: 1.0, x[1]: 0.0})

    return solve


def drake_pendulum(b, m=1.0, l=0.5, g=9.81):
    from pydrake.solvers import MathematicalProgram, Solve
    from pydrake.symbolic import Variables

    def solve():
        prog = MathematicalProgram()
        s, c, w = prog.NewIndeterminates(3, "x")
        x = np.array([s, c, w])
        f = [c * w, -s * w, (-b * w - m * g * l * s) / (m * l * l)]
        V = prog.NewFreePolynomial(Variables(x), 2).ToExpression()
        eps = 1e-4
        x0 = np.array([0.0, 1.0, 0.0])
        prog.AddSosConstraint(V - eps * (x - x0).dot(x - x0))
        Vdot = V.Jacobian(x).dot(f)
        L = prog.NewFreePolynomial(Variables(x), 2).ToExpression()
        prog.AddSosConstraint(-Vdot - L * (s**2 + c**2 - 1) - eps * (x - x0).dot(x - x0) * s**2)
        prog.AddLinearConstraint(V.Substitute({s: 0, c: 1, w: 0}) == 0)
        prog.AddLinearConstraint(V.Substitute({s: 1, c: 0, w: 0}) == m * g * l)
        result = Solve(prog)
        assert result.is_success()
        return result.get_solver_id().name()

    return solve


def ours_pendulum(num_check_samples=10_000):
    pendulum = jd.models.Pendulum()
    mgl = pendulum.m * pendulum.g * pendulum.l
    system = jd.analysis.trig_polynomial_system(pendulum, [0])
    s, c, w = jd.Polynomial.variables_of(3)
    dissipation = (s**2 + (c - 1) ** 2 + w**2) * s**2

    def solve():
        return jd.analysis.global_lyapunov_function(system, [0.0, 1.0, 0.0], 2, dissipation=dissipation,
                                                    normalization=([1.0, 0.0, 0.0], mgl),
                                                    num_check_samples=num_check_samples)

    return solve


def ours_pendulum_as_drake(b, m=1.0, l=0.5, g=9.81, num_check_samples=10_000):
    """Drake's program above, term for term, written with `jd.analysis.SosProgram`."""
    def solve():
        prog = jd.analysis.SosProgram(3, ["s", "c", "w"])
        s, c, w = prog.z
        f = [c * w, -s * w, (-b * w - m * g * l * s) / (m * l * l)]
        V = prog.new_free_polynomial(2)
        eps = 1e-4
        distance = s**2 + (c - 1.0) ** 2 + w**2
        prog.add_sos_constraint(V - eps * distance)
        Vdot = sum(V.derivative(i) * fi for i, fi in enumerate(f))
        L = prog.new_free_polynomial(2)
        prog.add_sos_constraint(-Vdot - L * (s**2 + c**2 - 1.0) - eps * distance * s**2)
        prog.add_constraint(V(np.array([0.0, 1.0, 0.0])) == 0)
        prog.add_constraint(V(np.array([1.0, 0.0, 0.0])) == m * g * l)
        result = prog.solve()
        assert result.check(num_check_samples).ok
        return result

    return solve


def main():
    args = argument_parser(__doc__, repeats=5, gpu_help="(no effect: the SDPs run on the CPU)").parse_args()
    print(machine_line())
    vdp = jd.System.from_functions(lambda t, x, u: jnp.stack([-x[1], x[0] + (x[0] ** 2 - 1) * x[1]]),
                                   num_states=2, time_invariant=True)
    S = np.array([[1.5, -0.5], [-0.5, 1.0]])
    polynomial_vdp = jd.analysis.taylor_polynomial_system(vdp, jnp.zeros(2), degree=3)

    start = time.perf_counter()
    roa = jd.analysis.region_of_attraction(vdp, [0.0, 0.0], S, return_certificate=True)
    first = time.perf_counter() - start
    roa = jd.analysis.region_of_attraction(polynomial_vdp, [0.0, 0.0], S, return_certificate=True)  # warm
    ours_any = best_time(lambda: jd.analysis.region_of_attraction(vdp, [0.0, 0.0], S), args.repeats)
    ours_poly = best_time(lambda: jd.analysis.region_of_attraction(polynomial_vdp, [0.0, 0.0], S),
                          args.repeats)
    unchecked = best_time(lambda: jd.analysis.region_of_attraction(polynomial_vdp, [0.0, 0.0], S,
                                                                   num_check_samples=0), args.repeats)
    drake_solve = drake_van_der_pol(S)
    rho_drake = drake_solve()
    drake = best_time(drake_solve, args.repeats)
    print(f"Van der Pol ROA: rho jaxdrake {roa.rho:.8f}, Drake {rho_drake:.8f} "
          f"(relative difference {abs(roa.rho - rho_drake) / rho_drake:.1e})")
    print(f"  jaxdrake, PolynomialSystem       {ours_poly * 1e3:8.1f} ms  (assembly + Clarabel {roa.result.solve_time * 1e3:.1f} ms, "
          f"incl. the 1e4-point certificate check)   {ours_poly / drake:5.1f}x Drake")
    print(f"  jaxdrake, any System (Taylor)    {ours_any * 1e3:8.1f} ms  (first call {first:.2f} s, compiling "
          f"the Taylor expansion)   {ours_any / drake:5.1f}x Drake")
    print(f"  jaxdrake, PolynomialSystem, no sampled check {unchecked * 1e3:5.1f} ms   {unchecked / drake:5.1f}x Drake")
    print(f"  Drake RegionOfAttraction         {drake * 1e3:8.1f} ms")

    ours = best_time(ours_pendulum(), args.repeats)
    unchecked = best_time(ours_pendulum(0), args.repeats)
    drake_solve = drake_pendulum(0.1)
    solver = drake_solve()
    drake = best_time(drake_solve, args.repeats)
    same = best_time(ours_pendulum_as_drake(0.1), args.repeats)
    same_unchecked = best_time(ours_pendulum_as_drake(0.1, num_check_samples=0), args.repeats)
    print(f"pendulum global certificate, Drake's program (feasibility, one multiplier): jaxdrake SosProgram "
          f"{same * 1e3:.1f} ms (Clarabel), Drake {drake * 1e3:.1f} ms ({solver})   {same / drake:.1f}x Drake; "
          f"without the sampled check {same_unchecked * 1e3:.1f} ms ({same_unchecked / drake:.1f}x)")
    print(f"  jd.analysis.global_lyapunov_function (maximises the dissipation margin, multipliers on both "
          f"constraints: a larger SDP) {ours * 1e3:.1f} ms   {ours / drake:.1f}x Drake; without the sampled "
          f"check {unchecked * 1e3:.1f} ms ({unchecked / drake:.1f}x)")


if __name__ == "__main__":
    main()
