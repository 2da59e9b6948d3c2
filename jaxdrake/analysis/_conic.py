r"""Conic programs over affine decision expressions, handed to the solver as matrices.

$\min q^T y$ s.t. $A y + s = b$, s in a product of zero, nonnegative and positive-semidefinite
(triangle) cones: the standard form of Clarabel (the default) and SCS (the fallback). The
constraints are `LinearConstraint`s (`expr == 0`, `expr >= 0`) and PSD constraints on the
entries of symmetric matrices, all `AffineExpression`s of one decision vector, so assembling
the program is stacking their sparse rows -- no modelling layer in between.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse

from .._extras import require
from .._status import Reported, StatusCode
from ..polynomials import AffineExpression, DecisionSpace, LinearConstraint


class ConicStatus(StatusCode):
    """How a conic solve ended (Clarabel's and SCS's statuses mapped onto one list). OPTIMAL
    and OPTIMAL_INACCURATE (whose answer passed the program's own checks) are successes; a
    failure is raised as `InfeasibleError` / `SolveError` carrying its status."""

    OPTIMAL = 0
    OPTIMAL_INACCURATE = 1
    INFEASIBLE = 2
    UNBOUNDED = 3
    FAILED = 4
    UNTRUSTED = 5


ConicStatus.describe({
    ConicStatus.OPTIMAL: "optimal",
    ConicStatus.OPTIMAL_INACCURATE: "optimal to reduced accuracy (the solver's own tolerances not all met; "
                                    "the answer passed the program's checks)",
    ConicStatus.INFEASIBLE: "infeasible: no certificate of the requested form exists (raise the degrees of the "
                            "polynomials or multipliers, or ask for less)",
    ConicStatus.UNBOUNDED: "unbounded: the objective grows without bound (bound it)",
    ConicStatus.FAILED: "the solver stopped without a solution (numerical trouble or its iteration limit; try "
                        "the other solver, or rescale the program)",
    ConicStatus.UNTRUSTED: "the solver's answer failed the program's checks (coefficient residuals or Gram "
                           "eigenvalues beyond the tolerance)",
}, successes=(ConicStatus.OPTIMAL, ConicStatus.OPTIMAL_INACCURATE))


class SolveError(RuntimeError):
    """The convex solver did not return a trustworthy solution: the message, the `status` (a
    `ConicStatus`) and the `solver`."""

    def __init__(self, message: str, status: ConicStatus = ConicStatus.FAILED, solver: str = ""):
        super().__init__(message)
        self.status, self.solver = status, solver


class InfeasibleError(SolveError):
    """The program is infeasible: no certificate of the requested form exists."""

    def __init__(self, message: str, status: ConicStatus = ConicStatus.INFEASIBLE, solver: str = ""):
        super().__init__(message, status, solver)


@dataclasses.dataclass(frozen=True)
class ConicResult(Reported):
    """A solved program, kept on the host (a frozen dataclass, not a pytree: its numbers are
    read through the program's decision space, on the host): the `program`, the
    `objective_expression` (None for a feasibility program), the `solver`'s name, the `status`
    (a `ConicStatus`; `success` and `message` from it), `solve_time` (s, assembly included);
    `objective` (its value) and `value(expr)`."""

    program: ConicProgram
    objective_expression: AffineExpression | None
    solver: str
    status: ConicStatus
    solve_time: float
    status_type = ConicStatus

    @property
    def objective(self) -> float | None:
        return None if self.objective_expression is None else self.objective_expression.value

    def value(self, item):
        """The number of a decision expression."""
        return item.value if isinstance(item, AffineExpression) else item


class ConicProgram:
    """Decision variables, linear constraints and PSD constraints; `solve` minimizes or
    maximizes a scalar decision expression."""

    result_type = ConicResult

    def __init__(self):
        self.space = DecisionSpace()
        self.constraints: list[LinearConstraint] = []
        self.psd_constraints: list[tuple[AffineExpression, int]] = []

    def new_variable(self, shape=()) -> AffineExpression:
        """A scalar (shape ()) or vector (shape (m,)) decision variable."""
        return self.space.new(shape)

    def new_symmetric_matrix(self, size: int) -> AffineExpression:
        """A symmetric size x size decision matrix, as its size^2 entries (row-major), made of
        size (size + 1) / 2 variables."""
        upper = self.space.new(size * (size + 1) // 2)
        i, j = np.triu_indices(size)
        position = np.zeros((size, size), int)
        position[i, j] = position[j, i] = np.arange(len(i))
        return upper.mapped(scipy.sparse.csr_matrix(
            (np.ones(size * size), (np.arange(size * size), position.ravel())), shape=(size * size, len(i))))

    def add_constraint(self, constraint: LinearConstraint):
        """A linear constraint on decision variables, e.g. `V(z_star) == 0` or `t <= 1`."""
        if not isinstance(constraint, LinearConstraint):
            raise TypeError(f"add_constraint takes a comparison of decision expressions (==, <=, >=), "
                            f"got {constraint!r}")
        self.constraints.append(constraint)

    def add_psd_constraint(self, matrix: AffineExpression, size: int):
        """The symmetric size x size matrix whose entries (row-major) are `matrix` is PSD."""
        if not isinstance(matrix, AffineExpression) or matrix.shape != (size * size,):
            raise ValueError(f"add_psd_constraint takes the {size * size} entries of a {size} x {size} "
                             f"matrix as one decision expression, got {matrix!r}")
        self.psd_constraints.append((matrix, size))

    def _verify(self, result, tolerance: float) -> str | None:
        """A reason to distrust a solver's optimal answer, or None (subclasses check more)."""
        return None

    def solve(self, minimize=None, maximize=None, solver: str | None = None, verbose: bool = False,
              tolerance: float = 1e-6):
        """Solve; return a checked result or raise `InfeasibleError` / `SolveError`.

        `minimize` / `maximize`: a scalar decision expression (default: feasibility).
        `solver`: "CLARABEL" or "SCS"; default Clarabel, with SCS tried when it fails.
        `tolerance`: of the answer's own checks (an `SosProgram`'s coefficient residuals and
        Gram eigenvalues, relative to their scale)."""
        if minimize is not None and maximize is not None:
            raise ValueError("give minimize or maximize, not both")
        objective = maximize if maximize is not None else minimize
        if objective is not None and not (isinstance(objective, AffineExpression) and objective.shape == ()):
            raise TypeError(f"the objective must be a scalar decision expression, got {objective!r}")
        candidates = [solver.upper()] if solver else ["CLARABEL", "SCS"]
        if set(candidates) - set(_SOLVERS):
            raise ValueError(f"unknown solver {solver!r}: choose one of {sorted(_SOLVERS)}")
        sign = -1.0 if maximize is not None else 1.0
        messages, status = [], ConicStatus.FAILED
        for name in candidates:
            start = time.perf_counter()
            status, y, words = _SOLVERS[name](self.conic_data, objective, sign, verbose)
            result = self.result_type(self, objective, name, status, time.perf_counter() - start)
            if status == ConicStatus.INFEASIBLE:
                raise InfeasibleError(f"the program is infeasible ({name}: {words})", status, name)
            if status == ConicStatus.UNBOUNDED:
                raise SolveError(f"the program is unbounded ({name}: {words}); bound the objective",
                                 status, name)
            if y is None or not np.all(np.isfinite(y)):
                messages.append(f"{name}: status {words}")
                status = ConicStatus.FAILED
                continue
            self.space.solution = y
            doubt = self._verify(result, tolerance)
            if doubt is None:
                return result
            messages.append(f"{name}: status {words}, {doubt}")
            status = ConicStatus.UNTRUSTED
        raise SolveError("no trustworthy solution: " + "; ".join(messages), status, candidates[-1])

    def conic_data(self, objective, sign: float, psd_order: str):
        """(q, A, b, (zero rows, nonnegative rows, PSD sizes)) of min sign * objective s.t.
        A y + s = b, s in the cones. A PSD block is the matrix's triangle with off-diagonal
        entries scaled by sqrt 2, in `psd_order`: "upper" (column-major, Clarabel's) or "lower"
        (column-major, SCS's). Every block's s is its expression: A = -A_expr, b = b_expr."""
        size = self.space.size
        equal = [c.expression.rows(size) for c in self.constraints if c.kind == "equal"]
        nonnegative = [c.expression.rows(size) for c in self.constraints if c.kind == "nonnegative"]
        psd = []
        for matrix, N in self.psd_constraints:
            A, b = matrix.rows(size)
            S = _triangle_selection(N, psd_order)
            psd.append((S @ A, S @ b))
        blocks = equal + nonnegative + psd
        if not blocks:
            A = scipy.sparse.csc_matrix((0, size))
        elif scipy.sparse.issparse(blocks[0][0]):
            A = scipy.sparse.vstack([-a for a, _ in blocks], format="csc")
        else:  # a small program's dense rows
            A = scipy.sparse.csc_matrix(-np.concatenate([a for a, _ in blocks]))
        b = np.concatenate([b for _, b in blocks]) if blocks else np.zeros(0)
        q = np.zeros(size)
        if objective is not None:
            row = objective.rows(size)[0]
            q = sign * (row.toarray() if scipy.sparse.issparse(row) else row).ravel()
        counts = (sum(a.shape[0] for a, _ in equal), sum(a.shape[0] for a, _ in nonnegative))
        return q, A, b, counts + (tuple(N for _, N in self.psd_constraints),)


def _triangle_selection(N: int, order: str):
    """The sparse map from a symmetric matrix's N^2 entries (row-major) to its scaled triangle."""
    if order == "upper":
        pairs = [(i, j) for j in range(N) for i in range(j + 1)]
    else:
        pairs = [(i, j) for j in range(N) for i in range(j, N)]
    i, j = np.array(pairs).reshape(-1, 2).T
    weights = np.where(i == j, 1.0, np.sqrt(2.0))
    return scipy.sparse.csr_matrix((weights, (np.arange(len(pairs)), i * N + j)), shape=(len(pairs), N * N))


def _clarabel(conic_data, objective, sign, verbose):
    clarabel = require("clarabel", "solving an SOS or conic program")

    q, A, b, (zero, nonnegative, psd) = conic_data(objective, sign, "upper")
    cones = (([clarabel.ZeroConeT(zero)] if zero else [])
             + ([clarabel.NonnegativeConeT(nonnegative)] if nonnegative else [])
             + [clarabel.PSDTriangleConeT(N) for N in psd])
    settings = clarabel.DefaultSettings()
    settings.verbose = verbose
    size = len(q)
    solution = clarabel.DefaultSolver(scipy.sparse.csc_matrix((size, size)), q, A, b, cones, settings).solve()
    words = str(solution.status)
    status = {"Solved": ConicStatus.OPTIMAL, "AlmostSolved": ConicStatus.OPTIMAL_INACCURATE,
              "PrimalInfeasible": ConicStatus.INFEASIBLE, "AlmostPrimalInfeasible": ConicStatus.INFEASIBLE,
              "DualInfeasible": ConicStatus.UNBOUNDED, "AlmostDualInfeasible": ConicStatus.UNBOUNDED,
              }.get(words, ConicStatus.FAILED)
    return status, np.asarray(solution.x, float) if status.success else None, words


def _scs(conic_data, objective, sign, verbose):
    scs = require("scs", "solving an SOS or conic program")

    q, A, b, (zero, nonnegative, psd) = conic_data(objective, sign, "lower")
    solution = scs.SCS({"A": A, "b": b, "c": q}, {"z": zero, "l": nonnegative, "s": list(psd)},
                       verbose=verbose, eps_abs=1e-8, eps_rel=1e-8, max_iters=100_000).solve()
    words = solution["info"]["status"]
    status = {"solved": ConicStatus.OPTIMAL, "solved_inaccurate": ConicStatus.OPTIMAL_INACCURATE,
              "infeasible": ConicStatus.INFEASIBLE, "infeasible_inaccurate": ConicStatus.INFEASIBLE,
              "unbounded": ConicStatus.UNBOUNDED, "unbounded_inaccurate": ConicStatus.UNBOUNDED,
              }.get(words, ConicStatus.FAILED)
    return status, np.asarray(solution["x"], float) if status.success else None, words


_SOLVERS = {"CLARABEL": _clarabel, "SCS": _scs}
