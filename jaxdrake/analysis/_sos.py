r"""Sums-of-squares programs: polynomial nonnegativity as semidefinite programs.

$p(z)$ is SOS iff $p(z) = m(z)^T Q\, m(z)$ for a monomial vector m and a Gram matrix
$Q \succeq 0$; matching coefficients makes that linear in Q and in p's decision
coefficients, so SOS constraints, free polynomial multipliers (the S-procedure) and linear
costs form an SDP (`ConicProgram`: Clarabel by default, SCS as the fallback). Decision
coefficients are `AffineExpression`s of one decision vector, so polynomial arithmetic on them
is sparse linear algebra and the program reaches the solver as matrices. The monomial
vector is pruned with the Newton polytope's cheap consequences: degree and per-variable
exponent bounds from half the support, then the diagonal rule (a monomial whose square cannot
appear in p has a zero Gram row).

Every solve is checked: the solver's status (infeasible -> `InfeasibleError`, anything else
short of optimal -> `SolveError` with the solver's words, unless the residuals show the
answer holds), the coefficient-matching residuals and the Gram matrices' least eigenvalues.
`SosResult.check` samples the certified polynomials at many points, which users can run too.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import scipy.sparse

from ..polynomials import AffineExpression, Polynomial, monomial_basis, unique_rows
from ._conic import ConicProgram, ConicResult, InfeasibleError


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
    """p = m' Q m with Q = `gram` (its N^2 entries, row-major, as decision expressions)."""

    polynomial: Polynomial
    basis: np.ndarray
    gram: AffineExpression
    rows: tuple  # (P, G): p's coefficients are P @ c, m'Qm's are G @ vec(Q)

    def gram_value(self) -> np.ndarray:
        N = len(self.basis)
        return np.asarray(self.gram.value, float).reshape(N, N)


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


class SosResult(ConicResult):
    """A solved `SosProgram`: `status`, `solver`, `solve_time`, `objective`, `value(...)`
    (numbers, or a numeric `Polynomial` for a decision polynomial), `residuals()`,
    `check(num_samples)`."""

    def value(self, item):
        if isinstance(item, Polynomial):
            if not item.is_decision:
                return item
            return Polynomial(item.exponent_array, np.asarray(item.coefficients.value, float), item.variables)
        return super().value(item)

    def residuals(self) -> tuple[float, float]:
        """(largest |coefficient of p - m'Qm| relative to p's scale, least Gram eigenvalue
        relative to the Gram's scale) over all SOS constraints."""
        worst_residual, worst_eig = 0.0, np.inf
        for record in self.program.sos_constraints:
            c = np.asarray(self.value(record.polynomial).coefficients, float)
            Q = record.gram_value()
            P, G = record.rows
            scale = max(1.0, np.abs(c).max(initial=0.0))
            worst_residual = max(worst_residual, np.abs(P @ c - G @ Q.ravel()).max(initial=0.0) / scale)
            worst_eig = min(worst_eig, np.linalg.eigvalsh((Q + Q.T) / 2).min() / max(1.0, np.abs(Q).max()))
        return worst_residual, (0.0 if worst_eig == np.inf else worst_eig)

    def check(self, num_samples: int = 10_000, scale: float = 1.0, tolerance: float = 1e-6,
              seed: int = 0) -> CertificateCheck:
        """Evaluate every certified polynomial at `num_samples` Gaussian points (standard
        deviation `scale`) and count where p < 0 (SOS constraints) or p != 0 (equalities)
        beyond `tolerance` times the sum of |terms| at that point."""
        if num_samples <= 0:
            return CertificateCheck(0, 0, 0.0, tolerance)
        z = _sample_points(num_samples, self.program.num_variables, float(scale), seed)
        polynomials = ([(self.value(r.polynomial), "sos") for r in self.program.sos_constraints]
                       + [(self.value(e), "eq") for e in self.program.equalities])
        if not polynomials:
            return CertificateCheck(num_samples, 0, 0.0, tolerance)
        # every polynomial's coefficients over the union of their monomials: one monomial
        # matrix per chunk of points serves them all
        union, where = unique_rows(np.concatenate([p.exponent_array for p, _ in polynomials]))
        columns = [np.asarray(p.coefficients, float).reshape(p.num_monomials, -1) for p, _ in polynomials]
        C = np.zeros((len(union), sum(c.shape[1] for c in columns)))
        row, col = 0, 0
        for c in columns:
            C[where[row:row + len(c)], col:col + c.shape[1]] += c
            row, col = row + len(c), col + c.shape[1]
        inequality = np.concatenate([np.full(c.shape[1], kind == "sos") for c, (_, kind) in zip(columns, polynomials)])
        basis = Polynomial._build(union, np.zeros(len(union)), polynomials[0][0].variables, unique=True)
        worst, violations = 0.0, 0
        for start in range(0, num_samples, 1024):  # chunks small enough to stay in cache (and, freed,
            monomials = basis.monomials(z[start:start + 1024])  # to be reused without page faults)
            values, size = monomials @ C, np.abs(monomials) @ np.abs(C) + 1e-300
            gap = np.where(inequality, -values, np.abs(values)) / size
            violations += int(np.sum(gap > tolerance))
            worst = max(worst, float(gap.max()))
        return CertificateCheck(num_samples, violations, worst, tolerance)


@functools.lru_cache(maxsize=16)
def _sample_points(num_samples: int, n: int, scale: float, seed: int) -> np.ndarray:
    """The check's Gaussian points (kept: a family of programs is checked on the same points)."""
    z = np.random.default_rng(seed).normal(scale=scale, size=(num_samples, n))
    z.flags.writeable = False
    return z


class SosProgram(ConicProgram):
    r"""A sums-of-squares program in `num_variables` indeterminates z.

    ```python
    prog = SosProgram(2)
    z0, z1 = prog.z
    V = prog.new_free_polynomial(degree=2)
    prog.add_sos_constraint(V - 1e-3 * (z0**2 + z1**2))
    prog.add_constraint(V(np.zeros(2)) == 0)
    result = prog.solve()
    V_numeric = result.value(V)
    ```

    Decision variables (`new_variable`, the coefficients of `new_free_polynomial`) are
    `AffineExpression`s: add, scale and compare them (`==`, `<=`, `>=` give constraints);
    `.value` after the solve.
    """

    result_type = SosResult

    def __init__(self, num_variables: int, variables=None):
        super().__init__()
        self.z = Polynomial.variables_of(num_variables, variables)
        self.variables = self.z[0].variables
        self.sos_constraints: list[SosConstraint] = []
        self.equalities: list[Polynomial] = []

    @property
    def num_variables(self) -> int:
        return len(self.z)

    def new_free_polynomial(self, degree: int, min_degree: int = 0) -> Polynomial:
        """A polynomial with every monomial of degree in [min_degree, degree], free coefficients."""
        basis = monomial_basis(self.num_variables, degree, min_degree)
        return Polynomial(basis, self.space.new(len(basis)), self.variables)

    def new_sos_polynomial(self, degree: int, min_degree: int = 0) -> Polynomial:
        """$m^T Q m$ with $Q \\succeq 0$ over the monomials of degree in
        [ceil(min_degree/2), degree/2]."""
        p = self.new_free_polynomial(degree, min_degree)
        self.add_sos_constraint(p)
        return p

    def add_sos_constraint(self, p: Polynomial) -> SosConstraint:
        """p(z) is a sum of squares (so p >= 0 everywhere): p's coefficients equal those of
        m' Q m, Q a new PSD Gram matrix over the pruned monomials m."""
        p = self._check(p)
        E = p.exponent_array
        if not p.is_decision:
            p = p.pruned()
            E = p.exponent_array
        basis = gram_basis(E) if len(E) else np.zeros((0, self.num_variables), int)
        if not len(basis):
            raise InfeasibleError(f"{p!r} cannot be a sum of squares (its Newton polytope has "
                                  "no even lattice points); only the zero polynomial would be")
        P, G = _identity_rows(E, basis)
        record = SosConstraint(p, basis, self.new_symmetric_matrix(len(basis)), (P, G))
        self.sos_constraints.append(record)
        c = p.coefficients
        self.add_constraint(record.gram.mapped(G) == (c.mapped(P) if p.is_decision else P @ np.asarray(c)))
        self.add_psd_constraint(record.gram, len(basis))
        return record

    def add_equality(self, p: Polynomial):
        """p(z) = 0 identically (all coefficients zero)."""
        p = self._check(p)
        if not p.is_decision:
            raise TypeError(f"add_equality needs decision coefficients; {p!r} is a number")
        self.equalities.append(p)
        self.add_constraint(p.coefficients == 0)

    def _check(self, p):
        if not isinstance(p, Polynomial) or p.shape != ():
            raise TypeError(f"SOS constraints take scalar Polynomials, got {p!r}")
        if p.num_variables != self.num_variables:
            raise ValueError(f"polynomial in {p.num_variables} variables, program has {self.num_variables}")
        return p

    def _verify(self, result, tolerance: float) -> str | None:
        residual, eig = result.residuals()
        if residual <= tolerance and eig >= -tolerance:
            return None
        return f"coefficient residual {residual:.2e}, least Gram eigenvalue {eig:.2e} (tolerance {tolerance:.0e})"


def _identity_rows(E, basis):
    """(P, G): for p with monomials E, its coefficients are P @ c and m'Qm's are G @ vec(Q),
    on one list of monomials (m the Gram basis)."""
    N = len(basis)
    j, k = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    pair = basis[j.ravel()] + basis[k.ravel()]
    unique, inverse = unique_rows(np.concatenate([E, pair]))
    P = scipy.sparse.csr_matrix((np.ones(len(E)), (inverse[:len(E)], np.arange(len(E)))),
                                shape=(len(unique), len(E)))
    G = scipy.sparse.csr_matrix((np.ones(N * N), (inverse[len(E):], np.arange(N * N))),
                                shape=(len(unique), N * N))
    return P, G
