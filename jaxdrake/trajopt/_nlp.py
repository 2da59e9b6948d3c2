r"""A sparse nonlinear program assembled from small local terms, and the solvers behind it.

$$\min_z \sum_j f_j(z) \quad\text{s.t.}\quad g^{lo} \le g(z) \le g^{up},\qquad z^{lo} \le z \le z^{up}$$

Every cost and constraint is a *term*: one small function `fn(v, k)` applied to `K` instances,
instance `k` reading the decision variables `z[idx[k]]` (a knot's state and input, a
segment's two knots, the duration, the parameters). Derivatives are dense only inside a term —
`vmap(jacfwd(fn))` gives each instance's block, `vmap(hessian(λ·fn))` its Hessian block — and
the sparsity pattern of the whole program is the union of those blocks, known before any
evaluation. This is the "structure per knot" of Betts (2010, ch. 4) that Drake's
`MultipleShooting` exploits too; no finite differences, no coloring needed.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
import warnings
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._extras import MissingExtraError, require
from .._progress import finish, progress_bar
from .._status import Reported
from ._status import SolverStatus


@dataclasses.dataclass(frozen=True)
class Term:
    """`fn(v, k) -> (r,)` on `idx.shape[0]` instances; instance k reads `z[idx[k]]`. A cost
    term's values are summed; a constraint term's are bounded by `lower`/`upper` (each
    (K, r)). Derivatives are autodiff of `fn` unless a constraint term brings its own,
    exploiting its structure: `jacobian(v, k) -> (r, L)`, and its Lagrangian Hessian split
    into the part that needs only the point and the part that needs the multipliers,
    `curvature(v, k) -> (the Jacobian block, C)` and `hessian_from(C, lam) -> (L, L)` (of
    lam . fn), so that a solver asking for the Jacobian and then the Hessian at one point
    evaluates the term's second derivatives once, in one compiled program. `size`: r when
    known (else found by tracing `fn`). A `batched` constraint term's functions take all
    instances at once (V (K, L), ks (K,), lam (K, r)) and return (K, ...), so instances can
    share work; it declares its size and all three derivatives."""

    name: str
    fn: Callable
    idx: np.ndarray
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    jacobian: Callable | None = None
    curvature: Callable | None = None
    hessian_from: Callable | None = None
    size: int | None = None
    batched: bool = False


def _float64(*args):
    return tuple(np.asarray(a, np.float64) for a in args)


def _triplets(rows, cols):
    """Unique (row, col) pairs of the raw triplets and, for each raw one, its unique slot."""
    keys = rows.astype(np.int64) * (int(cols.max(initial=0)) + 1) + cols
    unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return rows[first], cols[first], inverse, len(unique)


class NonlinearProgram:
    """The program of a list of cost and constraint `Term`s over `num_variables` with variable
    bounds; every function compiled once (float64, whatever JAX's default)."""

    def __init__(self, num_variables: int, costs: list[Term], constraints: list[Term],
                 lower: np.ndarray, upper: np.ndarray):
        self.num_variables = int(num_variables)
        self.costs, self.constraints = list(costs), list(constraints)
        for term in self.costs + self.constraints:
            if (term.curvature is None) != (term.hessian_from is None):
                raise ValueError(f"term {term.name!r} must declare both curvature and hessian_from, or neither")
            if term.batched and (any(term is cost for cost in self.costs)
                                 or None in (term.size, term.jacobian, term.curvature)):
                raise ValueError(f"batched term {term.name!r} must be a constraint declaring its size and derivatives")
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        with jax.enable_x64(True):
            sizes = [self._output_size(term) for term in self.constraints]
        self._sizes = sizes
        self.num_constraints = int(sum(term.idx.shape[0] * r for term, r in zip(self.constraints, sizes)))
        self.constraint_lower, self.constraint_upper = (
            np.concatenate([np.broadcast_to(getattr(t, side), (t.idx.shape[0], r)).ravel()
                            for t, r in zip(self.constraints, sizes)] or [np.zeros(0)])
            for side in ("lower", "upper"))
        self._jacobian_structure()
        self._hessian_structure()
        self._compile()

    # ----- structure ------------------------------------------------------------------------

    @staticmethod
    def _output_size(term: Term) -> int:
        if term.size is not None:
            return term.size
        v = jax.ShapeDtypeStruct((term.idx.shape[1],), jnp.float64)
        out = jax.eval_shape(term.fn, v, jax.ShapeDtypeStruct((), jnp.int32))
        if out.ndim != 1:
            raise ValueError(f"term {term.name!r} must return a vector, got shape {out.shape}")
        return out.shape[0]

    def _jacobian_structure(self):
        rows, cols, offset = [], [], 0
        for term, r in zip(self.constraints, self._sizes):
            K, L = term.idx.shape
            row = offset + np.arange(K)[:, None, None] * r + np.arange(r)[None, :, None]
            rows.append(np.broadcast_to(row, (K, r, L)).ravel())
            cols.append(np.broadcast_to(term.idx[:, None, :], (K, r, L)).ravel())
            offset += K * r
        rows = np.concatenate(rows or [np.zeros(0, int)])
        cols = np.concatenate(cols or [np.zeros(0, int)])
        self.jacobian_rows, self.jacobian_cols, self._jac_slot, self._jac_nnz = _triplets(rows, cols)

    def _hessian_structure(self):
        rows, cols = [], []
        for term in self.costs + self.constraints:
            K, L = term.idx.shape
            rows.append(np.broadcast_to(term.idx[:, :, None], (K, L, L)).ravel())
            cols.append(np.broadcast_to(term.idx[:, None, :], (K, L, L)).ravel())
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self._hess_lower = np.flatnonzero(rows >= cols)  # IPOPT takes the lower triangle
        (self.hessian_rows, self.hessian_cols, self._hess_slot,
         self._hess_nnz) = _triplets(rows[self._hess_lower], cols[self._hess_lower])

    def sparsity(self) -> dict:
        """Non-zeros of the constraint Jacobian and of the Lagrangian Hessian (lower triangle)
        against their dense sizes."""
        m, n = self.num_constraints, self.num_variables
        return {"variables": n, "constraints": m,
                "jacobian_nonzeros": self._jac_nnz, "jacobian_dense": m * n,
                "jacobian_density": self._jac_nnz / max(m * n, 1),
                "hessian_nonzeros": self._hess_nnz, "hessian_dense": n * (n + 1) // 2}

    # ----- compiled evaluation --------------------------------------------------------------

    def _compile(self):
        costs, constraints = self.costs, self.constraints
        jac_slot, jac_nnz = self._jac_slot, self._jac_nnz
        hess_lower, hess_slot, hess_nnz = self._hess_lower, self._hess_slot, self._hess_nnz
        sizes = self._sizes

        def apply(term, fn, z, *extra):
            ks = jnp.arange(term.idx.shape[0])
            return (fn if term.batched else jax.vmap(fn))(z[term.idx], ks, *extra)

        def objective(z):
            return sum(jnp.sum(apply(t, t.fn, z)) for t in costs)

        def summed(fn):  # a cost term's instance as a scalar
            return lambda v, k: jnp.sum(fn(v, k))

        def gradient(z):  # forward mode per block: works through forward-mode simulations too
            out = jnp.zeros_like(z)
            for t in costs:
                blocks = apply(t, jax.jacfwd(summed(t.fn)), z)
                out = out.at[t.idx].add(blocks)
            return out

        def constraint_values(z):
            return jnp.concatenate([apply(t, t.fn, z).ravel() for t in constraints] or [jnp.zeros(0)])

        def assembled_jacobian(blocks):
            return jax.ops.segment_sum(jnp.concatenate([b.ravel() for b in blocks] or [jnp.zeros(0)]),
                                       jac_slot, jac_nnz)

        def jacobian_blocks(t, z):
            return apply(t, t.jacobian or jax.jacfwd(t.fn), z)

        def jacobian_values(z):
            return assembled_jacobian([jacobian_blocks(t, z) for t in constraints])

        def jacobian_and_curvatures(z):  # the curvatures: of the terms that split their Hessian
            blocks, curvatures = [], []
            for t in constraints:
                if t.curvature is None:
                    blocks.append(jacobian_blocks(t, z))
                    curvatures.append(None)
                else:
                    block, curvature = apply(t, t.curvature, z)
                    blocks.append(block)
                    curvatures.append(curvature)
            return assembled_jacobian(blocks), curvatures

        def hessian_values(curvatures, z, multipliers, sigma):
            blocks, offset = [], 0
            for t in costs:
                blocks.append(sigma * apply(t, jax.hessian(summed(t.fn)), z).ravel())
            for t, r, curvature in zip(constraints, sizes, curvatures):
                K = t.idx.shape[0]
                lam = multipliers[offset: offset + K * r].reshape(K, r)
                offset += K * r
                if curvature is not None:
                    blocks.append((t.hessian_from if t.batched else jax.vmap(t.hessian_from))(curvature, lam).ravel())
                    continue
                blocks.append(apply(t, jax.hessian(lambda v, k, l, fn=t.fn: l @ fn(v, k)), z, lam).ravel())
            return jax.ops.segment_sum(jnp.concatenate(blocks)[hess_lower], hess_slot, hess_nnz)

        with jax.enable_x64(True):
            self._objective = jax.jit(objective)
            self._gradient = jax.jit(gradient)
            self._constraints = jax.jit(constraint_values)
            self._jacobian = jax.jit(jacobian_values)
            self._jacobian_and_curvatures = jax.jit(jacobian_and_curvatures)
            self._hessian = jax.jit(hessian_values)
        self._curvatures_at = (None, None)  # (z, the curvatures there): see jacobian_values

    def _call(self, fn, *args):
        with jax.enable_x64(True):
            return np.asarray(fn(*_float64(*args)), float)

    def objective(self, z) -> float:
        return float(self._call(self._objective, z))

    def gradient(self, z) -> np.ndarray:
        return self._call(self._gradient, z)

    def constraint_values(self, z) -> np.ndarray:
        return self._call(self._constraints, z)

    def compile_for_solver(self, z, *, exact_hessian: bool, also: tuple[Callable, ...] = ()) -> None:
        """Compile every program a solver calls, by first calls at z, and the first calls
        `also` (e.g. what builds the result). The derivative programs (the Jacobian, with the
        curvatures for exact Hessians, and the Hessian) take longest: they are traced first,
        then XLA compiles them in threads (releasing the GIL) while the others are traced and
        compiled."""
        z, = _float64(z)
        with jax.enable_x64(True):
            if exact_hessian:
                curvatures = jax.eval_shape(self._jacobian_and_curvatures, z)[1]
                derivatives = [self._jacobian_and_curvatures.trace(z).lower(),
                               self._hessian.trace(curvatures, z, *_float64(np.zeros(self.num_constraints), 1.0)).lower()]
            else:
                derivatives = [self._jacobian.trace(z).lower()]
        with concurrent.futures.ThreadPoolExecutor(len(derivatives)) as pool:
            compiling = [pool.submit(lowered.compile) for lowered in derivatives]
            for first_call in (self.objective, self.gradient, self.constraint_values):
                first_call(z)
            for first_call in also:
                first_call()
            for future in compiling:
                future.result()

    def jacobian_values(self, z, *, for_hessian: bool = False) -> np.ndarray:
        """The Jacobian's non-zeros, in the order of (`jacobian_rows`, `jacobian_cols`). With
        `for_hessian` (a solver that asks for the Hessian at the same point next, as IPOPT with
        exact Hessians does), one program evaluates the Jacobian with the terms' curvatures
        and keeps them for `hessian_values` at this z: one compiled program less and the
        second derivatives evaluated once."""
        if not for_hessian:
            return self._call(self._jacobian, z)
        return np.asarray(self._jacobian_keeping_curvatures(*_float64(z)), float)

    def _jacobian_keeping_curvatures(self, z):
        """The Jacobian's non-zeros (on the device), the curvatures at z kept."""
        with jax.enable_x64(True):
            values, curvatures = self._jacobian_and_curvatures(z)
        self._curvatures_at = (z, curvatures)
        return values

    def hessian_values(self, z, multipliers, sigma=1.0) -> np.ndarray:
        """Non-zeros of sigma ∇²f + Σ λ_i ∇²g_i (lower triangle, (`hessian_rows`, `hessian_cols`))."""
        z, multipliers, sigma = _float64(z, multipliers, sigma)
        kept_z, curvatures = self._curvatures_at
        if kept_z is None or not np.array_equal(kept_z, z):
            self._jacobian_keeping_curvatures(z)
            curvatures = self._curvatures_at[1]
        with jax.enable_x64(True):
            return np.asarray(self._hessian(curvatures, z, multipliers, sigma), float)

    def jacobian(self, z, *, for_hessian: bool = False):
        """The constraint Jacobian as a `scipy.sparse` CSR matrix (`for_hessian`: see
        `jacobian_values`)."""
        import scipy.sparse as sp

        return sp.csr_matrix((self.jacobian_values(z, for_hessian=for_hessian), (self.jacobian_rows, self.jacobian_cols)),
                             shape=(self.num_constraints, self.num_variables))

    def hessian(self, z, multipliers, sigma=1.0):
        """The full symmetric Lagrangian Hessian as a `scipy.sparse` CSR matrix."""
        import scipy.sparse as sp

        lower = sp.coo_matrix((self.hessian_values(z, multipliers, sigma), (self.hessian_rows, self.hessian_cols)),
                              shape=(self.num_variables,) * 2)
        return (lower + sp.triu(lower.T, k=1)).tocsr()

    def check_derivatives(self, z, step: float = 1e-6) -> dict:
        """Central finite differences of the constraints and of the objective gradient against
        the autodiff Jacobian and Hessian at `z` (dense: for checking, not for solving). Returns
        the largest absolute errors and the largest entries, and whether any non-zero of the
        finite-difference Jacobian falls outside the declared sparsity pattern."""
        z = np.asarray(z, float)
        n = self.num_variables
        jac_fd = np.zeros((self.num_constraints, n))
        hess_fd = np.zeros((n, n))
        multipliers = np.random.default_rng(0).standard_normal(self.num_constraints)

        def lagrangian_gradient(w):
            return self.gradient(w) + self.jacobian(w).T @ multipliers

        for j in range(n):
            e = np.zeros(n)
            e[j] = step
            jac_fd[:, j] = (self.constraint_values(z + e) - self.constraint_values(z - e)) / (2 * step)
            hess_fd[:, j] = (lagrangian_gradient(z + e) - lagrangian_gradient(z - e)) / (2 * step)
        jac = self.jacobian(z).toarray()
        pattern = np.zeros_like(jac, bool)
        pattern[self.jacobian_rows, self.jacobian_cols] = True
        hess = self.hessian(z, multipliers).toarray()
        return {"jacobian_error": float(np.max(np.abs(jac - jac_fd), initial=0.0)),
                "jacobian_scale": float(np.max(np.abs(jac_fd), initial=0.0)),
                "outside_pattern": float(np.max(np.abs(jac_fd[~pattern]), initial=0.0)),
                "hessian_error": float(np.max(np.abs(hess - hess_fd), initial=0.0)),
                "hessian_scale": float(np.max(np.abs(hess_fd), initial=0.0))}


# ----- solvers ------------------------------------------------------------------------------

class SolverResult(eqx.Module, Reported):
    """What a solver returned, on the host: the point `z`, the `status` (a `SolverStatus`;
    `success` and `message` from it), the final `cost` and `constraint_violation` (largest
    bound or constraint violation), `iterations`, `solve_time` (s), the `solver`'s name and the
    per-iteration `log` (dicts)."""

    z: np.ndarray
    status: SolverStatus
    cost: float
    constraint_violation: float
    iterations: int
    solve_time: float
    solver: str
    log: list
    status_type = SolverStatus


def constraint_violation(nlp: NonlinearProgram, z) -> float:
    g = nlp.constraint_values(z)
    parts = [nlp.lower - z, z - nlp.upper, nlp.constraint_lower - g, g - nlp.constraint_upper]
    worst = max(float(np.max(p, initial=0.0)) for p in parts)
    return worst if np.all(np.isfinite(g)) else float("nan")


class _Progress:
    """Per-iteration log, and the shared progress bar (iterations of the budget, with the
    cost, constraint violation and optimality) when `progress` is on."""

    def __init__(self, progress: bool, max_iterations: int, solver: str):
        self.log = []
        self.bar = progress_bar(progress, max_iterations, solver, "iteration")

    def __call__(self, iteration, cost, violation, optimality):
        self.log.append({"iteration": int(iteration), "cost": float(cost),
                         "constraint_violation": float(violation), "optimality": float(optimality)})
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(cost=f"{cost:.6e}", violation=f"{violation:.2e}",
                                 optimality=f"{optimality:.2e}", refresh=False)

    def close(self):
        finish(self.bar, len(self.log))


IPOPT_STATUS = {0: SolverStatus.SOLVED, 1: SolverStatus.SOLVED_TO_ACCEPTABLE_LEVEL, 2: SolverStatus.INFEASIBLE,
                3: SolverStatus.SEARCH_DIRECTION_TOO_SMALL, 4: SolverStatus.DIVERGING_ITERATES,
                5: SolverStatus.USER_REQUESTED_STOP, 6: SolverStatus.FEASIBLE_POINT_FOUND,
                -1: SolverStatus.MAXIMUM_ITERATIONS, -2: SolverStatus.RESTORATION_FAILED,
                -3: SolverStatus.ERROR_IN_STEP_COMPUTATION, -4: SolverStatus.MAXIMUM_TIME,
                -5: SolverStatus.MAXIMUM_TIME, -10: SolverStatus.NOT_ENOUGH_DEGREES_OF_FREEDOM,
                -11: SolverStatus.INVALID_PROBLEM, -12: SolverStatus.INVALID_PROBLEM,
                -13: SolverStatus.NONFINITE}  # IPOPT's ApplicationReturnStatus; others: SOLVER_ERROR


def solve_ipopt(nlp: NonlinearProgram, z0, *, tol=1e-8, max_iterations=3000, hessian="exact",
                options=None, progress=False, verbose=False) -> SolverResult:
    """IPOPT (interior point; Wächter & Biegler 2006) through `cyipopt`, fed the sparse
    Jacobian and the exact sparse Lagrangian Hessian (`hessian="limited-memory"` for L-BFGS)."""
    cyipopt = require("cyipopt", "solver='ipopt'")

    monitor = _Progress(progress, max_iterations, "IPOPT")

    class Callbacks:
        def objective(self, z):
            return nlp.objective(z)

        def gradient(self, z):
            return nlp.gradient(z)

        def constraints(self, z):
            return nlp.constraint_values(z)

        def jacobian(self, z):
            return nlp.jacobian_values(z, for_hessian=hessian == "exact")

        def jacobianstructure(self):
            return nlp.jacobian_rows, nlp.jacobian_cols

        def hessian(self, z, multipliers, sigma):
            return nlp.hessian_values(z, multipliers, sigma)

        def hessianstructure(self):
            return nlp.hessian_rows, nlp.hessian_cols

        def intermediate(self, alg_mod, iter_count, obj_value, inf_pr, inf_du, mu, d_norm,
                         regularization_size, alpha_du, alpha_pr, ls_trials):
            monitor(iter_count, obj_value, inf_pr, inf_du)

    problem = cyipopt.Problem(n=nlp.num_variables, m=nlp.num_constraints, problem_obj=Callbacks(),
                              lb=nlp.lower, ub=nlp.upper, cl=nlp.constraint_lower, cu=nlp.constraint_upper)
    settings = {"tol": tol, "max_iter": max_iterations, "print_level": 5 if verbose else 0,
                "sb": "yes", "hessian_approximation": hessian}
    settings.update(options or {})
    for key, value in settings.items():
        problem.add_option(key, value)
    start = time.perf_counter()
    try:
        z, info = problem.solve(np.asarray(z0, float))
    finally:
        monitor.close()
    elapsed = time.perf_counter() - start
    return SolverResult(z=np.asarray(z), status=IPOPT_STATUS.get(int(info["status"]), SolverStatus.SOLVER_ERROR),
                        cost=float(info["obj_val"]), constraint_violation=constraint_violation(nlp, z),
                        iterations=len(monitor.log) - 1 if monitor.log else 0, solve_time=elapsed,
                        solver="ipopt", log=monitor.log)


def solve_scipy(nlp: NonlinearProgram, z0, *, tol=1e-8, max_iterations=3000, options=None,
                progress=False, verbose=False) -> SolverResult:
    """SciPy's `trust-constr` (an interior-point / SQP trust-region method, Byrd, Hribar &
    Nocedal 1999) with the same sparse Jacobian and exact Hessians: always available, slower."""
    import scipy.optimize as so

    monitor = _Progress(progress, max_iterations, "SciPy trust-constr")
    constraints = []
    if nlp.num_constraints:
        constraints.append(so.NonlinearConstraint(
            nlp.constraint_values, nlp.constraint_lower, nlp.constraint_upper,
            jac=lambda z: nlp.jacobian(z, for_hessian=True),
            hess=lambda z, v: nlp.hessian(z, v, 0.0)))
    zero = np.zeros(nlp.num_constraints)

    def callback(z, state):
        monitor(state.nit, state.fun, state.constr_violation, state.optimality)
        return False

    free = ~(nlp.lower == nlp.upper)
    bounds = so.Bounds(np.where(free, nlp.lower, -np.inf), np.where(free, nlp.upper, np.inf))
    if np.any(~free):  # fixed variables as equality constraints (trust-constr needs lb < ub)
        import scipy.sparse as sp

        fixed = np.flatnonzero(~free)
        pick = sp.csr_matrix((np.ones(len(fixed)), (np.arange(len(fixed)), fixed)),
                             shape=(len(fixed), nlp.num_variables))
        constraints.append(so.LinearConstraint(pick, nlp.lower[fixed], nlp.upper[fixed]))
    settings = {"gtol": tol, "xtol": tol * 1e-4, "maxiter": max_iterations, "verbose": 2 if verbose else 0}
    settings.update(options or {})
    start = time.perf_counter()
    try:
        out = so.minimize(nlp.objective, np.asarray(z0, float), jac=nlp.gradient,
                          hess=lambda z: nlp.hessian(z, zero, 1.0), method="trust-constr",
                          bounds=bounds, constraints=constraints, callback=callback, options=settings)
    finally:
        monitor.close()
    elapsed = time.perf_counter() - start
    violation = constraint_violation(nlp, out.x)
    return SolverResult(z=np.asarray(out.x), status=_scipy_status(out, violation, tol),
                        cost=float(out.fun), constraint_violation=violation, iterations=int(out.nit),
                        solve_time=elapsed, solver="scipy", log=monitor.log)


def _scipy_status(out, violation: float, tol: float) -> SolverStatus:
    """trust-constr's ending as a `SolverStatus`: stopped on its gradient or step tolerance (1, 2)
    with a finite cost and the constraints met to max(1e-6, 10 tol) is SOLVED."""
    if not (np.isfinite(out.fun) and np.isfinite(violation)):
        return SolverStatus.NONFINITE
    if out.status in (1, 2):
        return SolverStatus.SOLVED if violation <= max(1e-6, 10 * tol) else SolverStatus.CONSTRAINTS_VIOLATED
    return {0: SolverStatus.MAXIMUM_ITERATIONS, 3: SolverStatus.USER_REQUESTED_STOP}.get(out.status,
                                                                                     SolverStatus.SOLVER_ERROR)


SOLVERS = {"ipopt": solve_ipopt, "scipy": solve_scipy}


def resolve_solver(solver: str) -> str:
    """"ipopt" or "scipy" for `solver`, checked before anything compiles: "ipopt" without IPOPT
    is a `MissingExtraError`; "auto" is IPOPT where installed, else SciPy with a warning naming
    the extra."""
    if solver not in (*SOLVERS, "auto"):
        raise ValueError(f"unknown solver {solver!r}; use 'ipopt', 'scipy' or 'auto'")
    if solver == "scipy":
        return solver
    try:
        require("cyipopt", "solver='ipopt'")
    except MissingExtraError as missing:
        if solver == "ipopt":
            raise
        warnings.warn(f"{missing}; solver='auto' falls back to SciPy's trust-constr (slower)", stacklevel=3)
        return "scipy"
    return "ipopt"


def solve(nlp: NonlinearProgram, z0, solver: str = "auto", **kwargs) -> SolverResult:
    """Solve with `solver`: "ipopt", "scipy", or "auto" (IPOPT where installed)."""
    return SOLVERS[resolve_solver(solver)](nlp, z0, **kwargs)
