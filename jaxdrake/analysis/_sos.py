r"""Sums-of-squares programs: polynomial nonnegativity as semidefinite programs.

$p(z)$ is SOS iff $p(z) = m(z)^T Q\, m(z)$ for a monomial vector m and a Gram matrix
$Q \succeq 0$; matching coefficients makes that linear in Q and in p's decision
coefficients, so SOS constraints, free polynomial multipliers (the S-procedure) and linear
costs form an SDP, solved here with `cvxpy` (Clarabel by default, SCS as the fallback, MOSEK
when licensed). The monomial vector is pruned with the Newton polytope's cheap consequences:
degree and per-variable exponent bounds from half the support, then the diagonal rule (a
monomial whose square cannot appear in p has a zero Gram row).

Every solve is checked: the solver's status (infeasible -> `InfeasibleError`, anything else
short of optimal -> `SolveError` with the solver's words, unless the residuals show the
answer holds), the coefficient-matching residuals and the Gram matrices' least eigenvalues.
`SosResult.check` samples the certified polynomials at many points, which users can run too.
"""

from __future__ import annotations

import dataclasses
import time

import cvxpy as cp
import numpy as np
import scipy.sparse

from ..systems import Polynomial, monomial_basis
from ..systems._polynomial import is_decision


class SolveError(RuntimeError):
    """The convex solver did not return a trustworthy solution (message from the solver)."""

    def __init__(self, message: str, status: str = "", solver: str = ""):
        super().__init__(message)
        self.status, self.solver = status, solver


class InfeasibleError(SolveError):
    """The program is infeasible: no certificate of the requested form exists."""


def gram_basis(exponents: np.ndarray) -> np.ndarray:
    """Monomials m with which a polynomial of support `exponents` could be $m^T Q m$."""
    E = np.asarray(exponents, int)
    n = E.shape[1]
    total = E.sum(1)
    low, high = int(np.ceil(total.min() / 2)), int(total.max() // 2)
    basis = monomial_basis(n, high, low)
    keep = np.all((2 * basis <= E.max(0)) & (2 * basis >= E.min(0)), axis=1)
    basis = basis[keep]
    support = {tuple(r) for r in E}
    while len(basis):
        sums = {tuple(basis[j] + basis[k]) for j in range(len(basis)) for k in range(j + 1, len(basis))}
        keep = np.array([tuple(2 * b) in support or tuple(2 * b) in sums for b in basis])
        if keep.all():
            break
        basis = basis[keep]
    return basis


@dataclasses.dataclass
class SosConstraint:
    polynomial: Polynomial
    basis: np.ndarray
    gram: cp.Variable


@dataclasses.dataclass
class CertificateCheck:
    """Result of sampling a certificate: the number of points where a claimed inequality
    (p >= 0) or identity (p = 0) fails by more than `tolerance` (relative to the size of
    p's terms there), and the worst relative violation."""

    num_samples: int
    num_violations: int
    worst_violation: float
    tolerance: float

    @property
    def ok(self) -> bool:
        return self.num_violations == 0


class SosProgram:
    r"""A sums-of-squares program in `num_variables` indeterminates z.

    ```python
    prog = SosProgram(2)
    V = prog.new_free_polynomial(degree=2)
    prog.add_sos_constraint(V - 1e-3 * (z0**2 + z1**2))
    result = prog.solve()
    V_numeric = result.value(V)
    ```
    """

    def __init__(self, num_variables: int, variables=None):
        self.z = Polynomial.variables_of(num_variables, variables)
        self.variables = self.z[0].variables
        self.sos_constraints: list[SosConstraint] = []
        self.equalities: list[Polynomial] = []
        self.constraints: list = []

    @property
    def num_variables(self) -> int:
        return len(self.z)

    def new_variable(self, shape=(), **kwargs) -> cp.Variable:
        """A plain decision variable (cvxpy keyword arguments such as `nonneg=True`)."""
        return cp.Variable(shape, **kwargs)

    def new_free_polynomial(self, degree: int, min_degree: int = 0) -> Polynomial:
        """A polynomial with every monomial of degree in [min_degree, degree], free coefficients."""
        basis = monomial_basis(self.num_variables, degree, min_degree)
        return Polynomial(basis, cp.Variable(len(basis)), self.variables)

    def new_sos_polynomial(self, degree: int, min_degree: int = 0) -> Polynomial:
        """$m^T Q m$ with $Q \\succeq 0$ over the monomials of degree in
        [ceil(min_degree/2), degree/2]."""
        p = self.new_free_polynomial(degree, min_degree)
        self.add_sos_constraint(p)
        return p

    def add_sos_constraint(self, p: Polynomial) -> SosConstraint:
        """p(z) is a sum of squares (so p >= 0 everywhere)."""
        p = self._check(p)
        E = p.exponent_array
        if not p.is_decision:
            E = p.pruned().exponent_array
        basis = gram_basis(E) if len(E) else np.zeros((0, self.num_variables), int)
        if not len(basis):
            raise InfeasibleError(f"{p!r} cannot be a sum of squares (its Newton polytope has "
                                  "no even lattice points); only the zero polynomial would be")
        gram = cp.Variable((len(basis), len(basis)), symmetric=True)
        record = SosConstraint(p, basis, gram)
        self.sos_constraints.append(record)
        return record

    def add_equality(self, p: Polynomial):
        """p(z) = 0 identically (all coefficients zero)."""
        self.equalities.append(self._check(p))

    def add_constraint(self, constraint):
        """A plain cvxpy constraint on decision variables (e.g. `V(z_star) == 0`)."""
        self.constraints.append(constraint)

    def _check(self, p):
        if not isinstance(p, Polynomial) or p.shape != ():
            raise TypeError(f"SOS constraints take scalar Polynomials, got {p!r}")
        if p.num_variables != self.num_variables:
            raise ValueError(f"polynomial in {p.num_variables} variables, program has {self.num_variables}")
        return p

    def _identity_rows(self, record):
        """(A, b, G): coefficients of p are A @ c + b; of m'Qm, G @ vec(Q), on one monomial list."""
        basis, N = record.basis, len(record.basis)
        j, k = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        pair = basis[j.ravel()] + basis[k.ravel()]
        E = record.polynomial.exponent_array
        unique, inverse = np.unique(np.concatenate([E, pair]), axis=0, return_inverse=True)
        inverse = inverse.ravel()
        P = scipy.sparse.csr_matrix((np.ones(len(E)), (inverse[:len(E)], np.arange(len(E)))),
                                    shape=(len(unique), len(E)))
        G = scipy.sparse.csr_matrix((np.ones(N * N), (inverse[len(E):], np.arange(N * N))),
                                    shape=(len(unique), N * N))
        return P, G

    def solve(self, minimize=None, maximize=None, solver: str | None = None, verbose: bool = False,
              tolerance: float = 1e-6) -> SosResult:
        """Solve the SDP; return a checked `SosResult` or raise `InfeasibleError` / `SolveError`.

        `solver`: a cvxpy solver name; default MOSEK if licensed, else Clarabel, with SCS
        tried when the first one fails. `tolerance`: the largest accepted coefficient
        residual and Gram eigenvalue violation, relative to the coefficients' scale.
        """
        constraints = list(self.constraints)
        for record in self.sos_constraints:
            P, G = self._identity_rows(record)
            c = record.polynomial.coefficients
            lhs = P @ (c if is_decision(c) else np.asarray(c))
            constraints += [lhs == G @ cp.vec(record.gram, order="C"), record.gram >> 0]
        for p in self.equalities:
            constraints.append((p.coefficients if p.is_decision else np.asarray(p.coefficients)) == 0)
        if minimize is not None and maximize is not None:
            raise ValueError("give minimize or maximize, not both")
        objective = (cp.Maximize(maximize) if maximize is not None
                     else cp.Minimize(0 if minimize is None else minimize))
        problem = cp.Problem(objective, constraints)
        candidates = [solver] if solver else (["MOSEK"] if _mosek_licensed() else []) + ["CLARABEL", "SCS"]
        messages = []
        for name in candidates:
            start = time.perf_counter()
            try:
                problem.solve(solver=name, verbose=verbose)
            except cp.error.SolverError as error:
                messages.append(f"{name}: {error}")
                continue
            result = SosResult(self, problem, name, time.perf_counter() - start)
            status = problem.status
            if status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
                raise InfeasibleError(f"the SOS program is infeasible ({name}: {status})", status, name)
            if status in (cp.UNBOUNDED, cp.UNBOUNDED_INACCURATE):
                raise SolveError(f"the SOS program is unbounded ({name}: {status}); bound the objective",
                                 status, name)
            if status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
                residual, eig = result.residuals()
                if residual <= tolerance and eig >= -tolerance:
                    return result
                messages.append(f"{name}: status {status}, coefficient residual {residual:.2e}, "
                                f"least Gram eigenvalue {eig:.2e} (tolerance {tolerance:.0e})")
            else:
                messages.append(f"{name}: status {status}")
        raise SolveError("no trustworthy solution: " + "; ".join(messages),
                         problem.status or "", candidates[-1])


def _mosek_licensed() -> bool:
    if "MOSEK" not in cp.installed_solvers():
        return False
    try:
        import mosek

        with mosek.Env() as env:
            env.checkoutlicense(mosek.feature.pts)
        return True
    except Exception:
        return False


class SosResult:
    """A solved `SosProgram`: `status`, `solver`, `solve_time`, `value(...)`, `residuals()`,
    `check(num_samples)`."""

    def __init__(self, program: SosProgram, problem: cp.Problem, solver: str, solve_time: float):
        self.program, self.problem = program, problem
        self.status, self.solver, self.solve_time = problem.status, solver, solve_time
        self.objective = problem.value

    def value(self, item):
        """The numeric value of a decision polynomial (-> numeric `Polynomial`) or expression."""
        if isinstance(item, Polynomial):
            if not item.is_decision:
                return item
            return Polynomial(item.exponent_array, np.asarray(item.coefficients.value, float), item.variables)
        return np.asarray(item.value, float) if hasattr(item, "value") else item

    def residuals(self) -> tuple[float, float]:
        """(largest |coefficient of p - m'Qm| relative to p's scale, least Gram eigenvalue
        relative to the Gram's scale) over all SOS constraints."""
        worst_residual, worst_eig = 0.0, np.inf
        for record in self.program.sos_constraints:
            p = self.value(record.polynomial)
            Q = np.asarray(record.gram.value, float)
            P, G = self.program._identity_rows(record)
            c = np.asarray(p.coefficients, float)
            scale = max(1.0, np.abs(c).max(initial=0.0))
            worst_residual = max(worst_residual, np.abs(P @ c - G @ Q.ravel()).max(initial=0.0) / scale)
            worst_eig = min(worst_eig, np.linalg.eigvalsh((Q + Q.T) / 2).min() / max(1.0, np.abs(Q).max()))
        return worst_residual, (0.0 if worst_eig == np.inf else worst_eig)

    def check(self, num_samples: int = 100_000, scale: float = 1.0, tolerance: float = 1e-6,
              seed: int = 0) -> CertificateCheck:
        """Evaluate every certified polynomial at `num_samples` Gaussian points (standard
        deviation `scale`) and count where p < 0 (SOS constraints) or p != 0 (equalities)
        beyond `tolerance` times the sum of |terms| at that point."""
        if num_samples <= 0:
            return CertificateCheck(0, 0, 0.0, tolerance)
        rng = np.random.default_rng(seed)
        z = rng.normal(scale=scale, size=(num_samples, self.program.num_variables))
        worst, violations = 0.0, 0
        for p, kind in ([(r.polynomial, "sos") for r in self.program.sos_constraints]
                        + [(e, "eq") for e in self.program.equalities]):
            p = self.value(p)
            monomials = np.asarray(p.monomials(z))
            c = np.asarray(p.coefficients, float)
            values, size = monomials @ c, np.abs(monomials) @ np.abs(c) + 1e-300
            gap = (-values if kind == "sos" else np.abs(values)) / size
            violations += int(np.sum(gap > tolerance))
            worst = max(worst, float(gap.max()))
        return CertificateCheck(num_samples, violations, worst, tolerance)
