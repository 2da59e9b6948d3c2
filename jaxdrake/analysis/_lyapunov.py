r"""Lyapunov analysis (notes, chapter "Lyapunov analysis"): common Lyapunov functions of
linear systems, global stability certificates, and regions of attraction, by SOS programs.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._progress import progress_bar
from .._status import Reported
from ..control import solve_continuous_lyapunov
from ..polynomials import Polynomial, taylor_polynomial
from ..systems import PolynomialSystem, System
from ._conic import ConicProgram, ConicStatus, InfeasibleError, SolveError
from ._sos import CertificateCheck, SosProgram, SosResult


def common_lyapunov_function(As, epsilon: float = 1e-6, solver: str | None = None) -> np.ndarray:
    r"""P with $\epsilon I \preceq P \preceq I$ and $A_i^T P + P A_i \preceq -t I$ for every A_i,
    maximising the margin t (an LMI): $V = x^T P x$ certifies stability of $\dot x = A_i x$
    under arbitrary switching among the family. Raises `InfeasibleError` when the best margin
    is below `epsilon` (no common quadratic Lyapunov function).
    """
    As = [np.asarray(A, float) for A in As]
    n = As[0].shape[0]
    if any(A.shape != (n, n) for A in As):
        raise ValueError(f"common_lyapunov_function: all A must be ({n}, {n}), got {[A.shape for A in As]}")
    prog = ConicProgram()
    P, t = prog.new_symmetric_matrix(n), prog.new_variable()
    eye = np.eye(n).ravel()  # matrices as their row-major entries
    prog.add_psd_constraint(P - epsilon * eye, n)
    prog.add_psd_constraint(eye - P, n)
    for A in As:  # -(A'P + PA) - t I >= 0, with vec(A'P) = (A' kron I) vec(P), vec(PA) = (I kron A') vec(P)
        lyapunov = np.kron(A.T, np.eye(n)) + np.kron(np.eye(n), A.T)
        prog.add_psd_constraint(-P.mapped(lyapunov) - t * eye, n)
    prog.solve(maximize=t, solver=solver)
    if t.value < epsilon:
        raise InfeasibleError(f"no common quadratic Lyapunov function: the best margin is "
                              f"t* = {t.value:.2e} < {epsilon:g}")
    P_value = P.value.reshape(n, n)
    return (P_value + P_value.T) / 2


def _check_autonomous(system: System, where: str):
    if not isinstance(system, System):
        raise TypeError(f"{where} takes a jaxdrake System, got {type(system).__name__}")
    if system.num_discrete_states or not system.num_continuous_states:
        raise ValueError(f"{where}: {system.name} must be continuous-time (it has "
                         f"{system.num_discrete_states} discrete states)")
    if system.is_hybrid or system.is_stochastic:
        raise ValueError(f"{where}: {system.name} is hybrid or stochastic; analyse one mode's dynamics")


def polynomial_dynamics(system: System, x0, u0=None, degree: int = 3) -> Polynomial:
    r"""The closed-loop vector field in error coordinates, $\dot{\bar x} = f(x_0 + \bar x, u_0)$,
    as a polynomial in $\bar x$: exact for a `PolynomialSystem` (e = I), otherwise the Taylor
    polynomial of the given degree (by autodiff) -- then certificates hold for that
    approximation, and `verify_region_of_attraction` checks them on the true dynamics.
    """
    _check_autonomous(system, "polynomial_dynamics")
    n, m = system.num_states, system.num_inputs
    x0 = jnp.asarray(x0, float).reshape(-1)
    if x0.shape != (n,):
        raise ValueError(f"x0 must have shape ({n},), got {x0.shape}")
    u0 = jnp.zeros(m) if u0 is None else jnp.asarray(u0, float).reshape(-1)
    if u0.shape != (m,):
        raise ValueError(f"u0 must have shape ({m},), got {u0.shape}")
    z = list(Polynomial.variables_of(n, [f"x{i}" for i in range(n)]))
    if isinstance(system, PolynomialSystem) and system.e is None:
        if m == 0 and not np.any(np.asarray(x0)):  # f itself, in the variables x0, x1, ...
            return Polynomial(system.f.exponent_array, np.asarray(system.f.coefficients, float), z[0].variables)
        values = [zi + float(ci) for zi, ci in zip(z, x0)] + [Polynomial.constant(float(c), n, z[0].variables) for c in u0]
        return system.f.substitute(values)
    with jax.enable_x64(True):  # analysis runs in float64 whatever the user's default
        expansion = taylor_polynomial(_dynamics_at, x0.astype(jnp.float64), degree,
                                      args=(system, u0.astype(jnp.float64)))
    return expansion.substitute([zi + float(ci) for zi, ci in zip(z, x0)])


def _dynamics_at(x, system, u):
    return system.dynamics(0.0, x, u)


def _quadratic(S, names) -> Polynomial:
    n = S.shape[0]
    E = np.array([np.eye(n, dtype=int)[i] + np.eye(n, dtype=int)[j] for i in range(n) for j in range(n)])
    return Polynomial(E, np.asarray(S, float).ravel(), names)


def _equilibrium_check(f: Polynomial, x0):
    residual = np.abs(np.asarray(f(np.zeros(f.num_variables)))).max()
    if residual > 1e-8:
        raise ValueError(f"x0 = {np.asarray(x0)} is not an equilibrium: |f(x0, u0)| = {residual:.3g}")


def _largest_level(V: Polynomial, f: Polynomial, solver, multiplier_degree=None):
    r"""The fixed-V SDP: max rho s.t. $(V - \rho)(\bar x^T\bar x)^d - \lambda\dot V$ SOS, with
    $\lambda$ free of degree deg Vdot (by default). Returns (rho, lambda, result)."""
    Vdot = V.lie_derivative(f).pruned(1e-12)
    prog = SosProgram(f.num_variables, f.variables)
    lam_degree = Vdot.degree if multiplier_degree is None else multiplier_degree
    lam = prog.new_free_polynomial(lam_degree)
    rho = prog.new_variable()
    d = (lam_degree + Vdot.degree - V.degree) // 2
    radius = sum(zi * zi for zi in prog.z)
    prog.add_sos_constraint((V - rho) * radius**d - lam * Vdot)
    result = prog.solve(maximize=rho, solver=solver)
    return float(rho.value), result.value(lam), result


def _in_state_coordinates(V: Polynomial, x0) -> Polynomial:
    """V(x - x0) as a polynomial in the state x (variables x0, x1, ...)."""
    x0 = np.asarray(x0, float).reshape(-1)
    x = Polynomial.variables_of(len(x0), [f"x{i}" for i in range(len(x0))])
    return V.substitute([xi - float(ci) for xi, ci in zip(x, x0)]).pruned()


@dataclasses.dataclass(frozen=True)
class RegionOfAttraction(Reported):
    r"""A certified region of attraction $\{x : V(x) \le \rho\}$, kept on the host (a frozen
    dataclass, as its `SosResult`): V (a numeric Polynomial in the state x), rho, the
    multiplier, the solve's `result` and the sampled `check`; `status`, `success` and `message`
    are the solve's (a failed solve or check is raised, never returned)."""

    V: Polynomial
    rho: float
    multiplier: Polynomial
    result: SosResult
    check: CertificateCheck
    status_type = ConicStatus

    @property
    def status(self) -> ConicStatus:
        return self.result.status


def region_of_attraction(system: System, x0, S=None, *, u0=None, taylor_degree: int = 3,
                         multiplier_degree: int | None = None, solver: str | None = None,
                         num_check_samples: int = 10_000, return_certificate: bool = False):
    r"""The largest level $\rho$ such that $\{x : V(x) \le \rho\}$, $V = (x - x_0)^T S (x - x_0)$,
    is certified to lie in the region of attraction of the equilibrium $x_0$.

    With $\bar x = x - x_0$ and $\dot V$ along the (polynomial or Taylor-expanded) dynamics,
    one SDP, linear in $\rho$ (the notes' formulation, as Drake's `RegionOfAttraction`):

    $$\max_{\rho, \lambda} \rho \quad\text{s.t.}\quad (V - \rho)\,(\bar x^T\bar x)^d
      - \lambda(\bar x)\,\dot V(\bar x) \ \text{is SOS},$$

    $\lambda$ a free polynomial of degree $\deg \dot V$ and $d = \lfloor(\deg\lambda + \deg\dot V
    - \deg V)/2\rfloor$: wherever $\dot V = 0$ (other than at $x_0$), $V \ge \rho$. Needs
    $\dot V$'s Hessian at $x_0$ negative definite. S defaults to the solution of
    $A^T S + S A = -I$ for the linearization A. After solving, the SOS identity is sampled at
    `num_check_samples` points (`SosResult.check`); a failure is an error.

    **Returns:** rho (a float), or a `RegionOfAttraction` with `return_certificate=True`.
    """
    f = polynomial_dynamics(system, x0, u0, taylor_degree)
    _equilibrium_check(f, x0)
    n = f.num_variables
    A = np.asarray(f.jacobian()(np.zeros(n)))
    if S is None:
        if np.linalg.eigvals(A).real.max() >= 0:
            raise ValueError(f"x0 is not locally exponentially stable: the linearization has "
                             f"eigenvalues {np.linalg.eigvals(A)}")
        S = np.asarray(solve_continuous_lyapunov(A, np.eye(n)))
    S = np.asarray(S, float)
    if S.shape != (n, n):
        raise ValueError(f"S must have shape ({n}, {n}), got {S.shape}")
    if np.linalg.eigvalsh((S + S.T) / 2).min() <= 0:
        raise ValueError("S must be positive definite (V = (x - x0)' S (x - x0) > 0)")
    S = (S + S.T) / 2
    V = _quadratic(S, f.variables)
    hessian = A.T @ S + S @ A
    if np.linalg.eigvalsh(hessian).max() >= 0:
        raise ValueError("V is not a Lyapunov function of the linearization: A'S + SA has "
                         f"eigenvalues {np.linalg.eigvalsh(hessian)} (must be negative definite)")
    rho_value, lam, result = _largest_level(V, f, solver, multiplier_degree)
    if not rho_value > 0:
        raise SolveError(f"no positive level certified (rho = {rho_value:.3g})", ConicStatus.INFEASIBLE,
                         result.solver)
    check = result.check(num_check_samples, scale=float(np.sqrt(rho_value / np.linalg.eigvalsh(S).min())))
    if not check.ok:
        raise SolveError(f"the certificate fails at {check.num_violations} of {check.num_samples} sampled "
                         f"points (worst relative violation {check.worst_violation:.2e})",
                         ConicStatus.UNTRUSTED, result.solver)
    if not return_certificate:
        return rho_value
    return RegionOfAttraction(_in_state_coordinates(V, x0), rho_value, lam, result, check)


def sample_sublevel_set(x0, S, rho, num_samples: int, seed: int = 0) -> np.ndarray:
    """Points uniformly distributed in the ellipsoid (x - x0)' S (x - x0) <= rho."""
    rng = np.random.default_rng(seed)
    n = S.shape[0]
    directions = rng.normal(size=(num_samples, n))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(size=(num_samples, 1)) ** (1 / n)
    L = np.linalg.cholesky(np.linalg.inv(S))
    return np.asarray(x0, float) + np.sqrt(rho) * radii * directions @ L.T


def verify_region_of_attraction(system: System, x0, S, rho, *, u0=None, num_samples: int = 100_000,
                                seed: int = 0) -> CertificateCheck:
    r"""Sample `num_samples` states uniformly in $\{V \le \rho\}$, $V = (x-x_0)^T S (x-x_0)$, and
    count those where $\dot V = 2 (x - x_0)^T S f(x, u_0) \ge 0$ with the system's **true**
    dynamics (x_0 itself excluded): a check of the claim independent of the SOS program and of
    any Taylor approximation."""
    _check_autonomous(system, "verify_region_of_attraction")
    S = np.asarray(S, float)
    x0 = np.asarray(x0, float).reshape(-1)
    u0 = jnp.zeros(system.num_inputs) if u0 is None else jnp.asarray(u0, float)
    x = sample_sublevel_set(x0, S, rho, num_samples, seed)
    xdot = np.asarray(jax.jit(jax.vmap(lambda xi: system.dynamics(0.0, xi, u0)))(jnp.asarray(x)))
    e = x - x0
    Vdot = 2 * np.einsum("ki,ij,kj->k", e, S, xdot)
    size = 2 * np.einsum("ki,ij,kj->k", np.abs(e), np.abs(S), np.abs(xdot)) + 1e-300
    gap = Vdot / size
    bad = gap >= 0
    return CertificateCheck(num_samples, int(bad.sum()), float(gap.max()), 0.0)


def global_lyapunov_function(system: System, x0, degree: int = 2, *, u0=None, epsilon: float = 1e-4,
                             dissipation: Polynomial | None = None, multiplier_degree: int | None = None,
                             normalization=None, solver: str | None = None, num_check_samples: int = 10_000):
    r"""Search for a global Lyapunov function of the polynomial system's equilibrium $x_0$:
    V of the given degree in x with the largest dissipation margin $t \le 1$ such that

    $$V(x_0) = 0,\quad V - \epsilon\,|x - x_0|^2 - \textstyle\sum_i \mu_i\phi_i \ \text{SOS},\quad
      -\dot V - t\,w(x) - \textstyle\sum_i \lambda_i \phi_i \ \text{SOS},$$

    $\phi_i(x) = 0$ the system's announced state constraints (e.g. $s^2 + c^2 = 1$ after
    `trig_polynomial_system`), $\mu_i, \lambda_i$ free polynomial multipliers and $w \ge 0$
    the shape of the required dissipation (default $|x - x_0|^2$: global asymptotic
    stability). A certificate needs $t \ge \epsilon$. Maximising the margin, rather than
    asking a solver to detect infeasibility, keeps the SDP well posed on both sides: an
    undamped pendulum gives $t^* = 0$, which is reported as infeasible.
    `normalization = (x, value)` fixes V at one more point (the notes' pendulum: V(pi) = mgl).

    **Returns:** V as a numeric `Polynomial` in x. Raises `InfeasibleError` when no such V
    exists at this degree.
    """
    _check_autonomous(system, "global_lyapunov_function")
    if not isinstance(system, PolynomialSystem) or system.e is not None:
        raise TypeError("global_lyapunov_function needs a PolynomialSystem with e = I (convert with "
                        "taylor_polynomial_system or trig_polynomial_system); a Taylor polynomial "
                        "says nothing global")
    n, m = system.num_states, system.num_inputs
    x0 = np.asarray(x0, float).reshape(-1)
    u0 = np.zeros(m) if u0 is None else np.asarray(u0, float).reshape(-1)
    names = system.f.variables[:n]
    x = list(Polynomial.variables_of(n, names))
    f = system.f.substitute(x + [Polynomial.constant(float(c), n, names) for c in u0])
    _equilibrium_check(f.substitute([xi + float(c) for xi, c in zip(x, x0)]), x0)
    prog = SosProgram(n, names)
    V = prog.new_free_polynomial(degree)
    margin = prog.new_variable()
    prog.add_constraint(V(x0) == 0)
    prog.add_constraint(margin <= 1)
    if normalization is not None:
        point, value = normalization
        prog.add_constraint(V(np.asarray(point, float)) == value)
    distance = sum((xi - float(c)) ** 2 for xi, c in zip(x, x0))
    w = distance if dissipation is None else dissipation
    positivity, decrease = V - epsilon * distance, -V.lie_derivative(f) - w * margin
    if system.constraints is not None:
        phi = system.constraints.substitute(x + [Polynomial.constant(0.0, n, names)] * m)
        k = multiplier_degree if multiplier_degree is not None else max(0, degree)
        for i in range(phi.shape[0]):
            positivity = positivity - prog.new_free_polynomial(k) * phi[i]
            decrease = decrease - prog.new_free_polynomial(k) * phi[i]
    prog.add_sos_constraint(positivity)
    prog.add_sos_constraint(decrease)
    result = prog.solve(maximize=margin, solver=solver)
    if float(margin.value) < epsilon:
        raise InfeasibleError(f"no Lyapunov function of degree {degree} with the required dissipation: "
                              f"the largest margin is t* = {float(margin.value):.2e} < epsilon = {epsilon:g}",
                              solver=result.solver)
    check = result.check(num_check_samples)
    if not check.ok:
        raise SolveError(f"the certificate fails at {check.num_violations} sampled points",
                         ConicStatus.UNTRUSTED, result.solver)
    return result.value(V).pruned(1e-9)


@dataclasses.dataclass(frozen=True)
class RegionOfAttractionSearch(Reported):
    r"""The result of `search_region_of_attraction`, kept on the host: the certified region
    $\{x : V(x) \le 1\}$ (V a numeric Polynomial in x), the inscribed level $\beta$ of the shape
    $p = (x - x_0)^T S (x - x_0)$ (so $\{p \le \beta\} \subseteq \{V \le 1\}$), $\beta$
    after each iteration, and the `result` of the final V's certification; `status`, `success`
    and `message` are that solve's (a failed one is raised, never returned)."""

    V: Polynomial
    beta: float
    history: list
    result: SosResult
    status_type = ConicStatus

    @property
    def status(self) -> ConicStatus:
        return self.result.status


def search_region_of_attraction(system: System, x0, degree: int = 4, *, S=None, u0=None,
                                taylor_degree: int = 3, iterations: int = 10, tolerance: float = 1e-3,
                                solver: str | None = None, progress: bool = True) -> RegionOfAttractionSearch:
    r"""Search over V and the multipliers to enlarge a certified region of attraction (the
    notes' "searching for the region of attraction"; the expanding-interior alternation of
    Jarvis-Wloszek et al. 2003). With $p = \bar x^T S \bar x$ (S from the linearization's
    Lyapunov equation by default), maximise $\beta$ such that $\{p \le \beta\} \subseteq
    \{V \le 1\} \subseteq$ region of attraction:

    $$(V - 1)(\bar x^T\bar x)^d - \lambda \dot V \ \text{SOS},\qquad
      (p - \beta)(\bar x^T\bar x)^k - s\,(V - 1) \ \text{SOS},\qquad s \ \text{SOS},\qquad
      V - \epsilon|\bar x|^2 \ \text{SOS}.$$

    Bilinear, so alternate convex steps: (1) V fixed: $\lambda$ (and V rescaled to 99% of
    its largest certified level, as in `region_of_attraction`); (2) V fixed: s and $\beta$;
    (3) $\lambda$ and s fixed: V and $\beta$. Each step keeps the previous solution feasible,
    so $\beta$ never decreases; stop when it grows by less than `tolerance` (relative).
    `progress`: a progress bar (tqdm) over the alternations, showing $\beta$ (drawn once the search has run 2 s).
    """
    f = polynomial_dynamics(system, x0, u0, taylor_degree)
    _equilibrium_check(f, x0)
    n = f.num_variables
    if S is None:
        A = np.asarray(f.jacobian()(np.zeros(n)))
        S = np.asarray(solve_continuous_lyapunov(A, np.eye(n)))
    S = (np.asarray(S, float) + np.asarray(S, float).T) / 2
    names = f.variables
    z = Polynomial.variables_of(n, names)
    radius = sum(zi * zi for zi in z)
    shape = _quadratic(S, names)
    V = shape
    history = []
    bar = progress_bar(progress, iterations, "region of attraction", "alternation")
    for _ in range(iterations):
        # (1) V fixed: multiplier and largest level; normalise V to level 1.
        rho, lam, _ = _largest_level(V, f, solver)
        d = (2 * lam.degree - V.degree) // 2  # lam has the degree of Vdot
        # level 1 at 99% of the certified rho: (V/c - 1)(x'x)^d - lam Vdot/c is then the SOS
        # polynomial plus 0.01 rho (x'x)^d over c, strictly inside, which step (3) needs.
        V = V / (0.99 * rho)
        # (2) V fixed: the largest shape level inside {V <= 1}.
        prog = SosProgram(n, names)
        s = prog.new_sos_polynomial(2)
        beta = prog.new_variable()
        k = (2 + V.degree - shape.degree) // 2
        prog.add_sos_constraint((shape - beta) * radius**k - s * (V - 1.0))
        result = prog.solve(maximize=beta, solver=solver)
        s = result.value(s)
        # (3) multipliers fixed: V and beta.
        prog = SosProgram(n, names)
        V_new = prog.new_free_polynomial(degree, min_degree=2)
        beta = prog.new_variable()
        prog.add_sos_constraint((V_new - 1.0) * radius**d - lam * V_new.lie_derivative(f))
        prog.add_sos_constraint((shape - beta) * radius**k - s * V_new + s)
        prog.add_sos_constraint(V_new - 1e-6 * radius)
        result = prog.solve(maximize=beta, solver=solver)
        V = result.value(V_new).pruned(1e-12)
        history.append(float(beta.value))
        if bar is not None:
            bar.update()
            bar.set_postfix(beta=f"{history[-1]:.6g}")
        if len(history) > 1 and history[-1] - history[-2] <= tolerance * abs(history[-2]):
            break
    if bar is not None:
        bar.close()
    # certify the final V on its own (fresh multiplier), as `region_of_attraction` does
    rho, _, result = _largest_level(V, f, solver)
    check = result.check(scale=float(np.sqrt(max(history[-1], 1e-9) / np.linalg.eigvalsh(S).min())))
    if rho < 1 - 1e-6 or not check.ok:
        raise SolveError(f"the final V is not certified at level 1 (rho = {rho:.6g}, "
                         f"{check.num_violations} sampled violations)", ConicStatus.UNTRUSTED, result.solver)
    return RegionOfAttractionSearch(_in_state_coordinates(V, x0), history[-1], history, result)
