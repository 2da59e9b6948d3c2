r"""A dense convex QP solver in JAX: OSQP's ADMM on a cached factorization, an active-set
polish, and derivatives by the implicit function theorem (what `linear_mpc` solves each step).

$$\min_x\ \tfrac12 x^T P x + q^T x \quad\text{s.t.}\quad l \le A x \le u, \qquad P \succ 0.$$

**The iteration** (Stellato et al., *OSQP: an operator splitting solver for quadratic
programs*, 2020, Algorithm 1), on the problem equilibrated by Ruiz scaling ($\bar P = c D P D$,
$\bar A = E A D$): with the relaxation $\alpha = 1.6$,

$$\tilde x = (\bar P + \sigma I + \rho \bar A^T \bar A)^{-1}(\sigma x - \bar q + \bar A^T(\rho z - y)),\quad
  x \leftarrow \alpha \tilde x + (1-\alpha) x,\quad
  z \leftarrow \Pi_{[l,u]}(\hat z + y/\rho),\quad y \leftarrow y + \rho(\hat z - z),$$

$\hat z = \alpha \bar A \tilde x + (1 - \alpha) z$. The inverse of the KKT matrix depends on
P, A and ρ only, so `qp_workspace` computes it once (an MPC controller: at construction) and
every iteration of every solve is three small matrix-vector products. ρ is adapted as OSQP
does, by the ratio of the scaled residuals every `CHECK_EVERY` iterations, but over a ladder of
values $\rho_0 10^{k/2}$, $|k| \le 6$, whose inverses are all made with the workspace: a
solve factors nothing (under `vmap` a refactorization would run for every member at every
check). A solve stops when the residuals
$\|Ax - z\|_\infty$, $\|Px + q + A^T y\|_\infty$ meet `tolerance` (absolute and relative), or
when $\delta y$ certifies primal infeasibility ($A^T \delta y = 0$,
$u^T \delta y_+ + l^T \delta y_- < 0$). It then **polishes**: the active set read from (z, y)
gives an equality-constrained QP solved exactly (regularized KKT system, two steps of
iterative refinement); the polished point is kept when it is feasible and its multipliers
have the right signs, i.e. when it satisfies the KKT conditions, which makes the answer exact
to rounding instead of to the ADMM tolerance. At a degenerate vertex (more active rows than
free directions, common in MPC when an input bound and a state bound meet) the least-norm
multipliers may take a wrong sign; a few primal-dual active-set corrections then find the
right set.

**Derivatives**: the solution satisfies $Px + q + A_a^T y_a = 0$, $A_a x = b_a$ on the
active rows a ($b$ the bound that is active), $y_i = 0$ elsewhere; differentiating gives one
linear system with the same KKT matrix, the JVP of `solve_qp` (and, transposed by JAX, its
VJP). Unrolling the iterations instead would differentiate an approximation whose derivative
converges more slowly than the iterates, costs memory per iteration, and cannot run in
reverse through a `while_loop`.

**Why our own** (~200 lines): `jaxopt` (its `BoxOSQP` did this) is no longer maintained;
`qpax` (maintained, interior point) refactors $P + G^T \mathrm{diag}(z/s) G$ at every
iteration, cannot use a warm start, returns a converged flag without an infeasibility
certificate, and defines only a VJP (no forward mode); `mpax` (PDHG) targets large sparse LPs
and QPs without a factorization and has no derivative of the solution. An MPC step is a small
dense QP whose matrices never change and whose previous solution is an excellent start: ADMM
on a cached inverse is the method that fits.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._status import StatusCode

CHECK_EVERY = 10  # ADMM iterations between residual checks
_UNROLL = 2  # two iterations per loop trip: ~2x faster than none, and compiles 2x faster than 10
_RUIZ_ITERATIONS = 15
_POLISH_PASSES = 4
RHO_LADDER = 10.0 ** (np.arange(-6, 7) / 2)  # multiples of the first rho, each with its inverse
_ALPHA = 1.6


class QPStatus(StatusCode):
    """How a QP solve ended (`QPSolution.status`)."""

    SOLVED = 0
    MAX_ITERATIONS = 1
    PRIMAL_INFEASIBLE = 2
    NONFINITE = 3


QPStatus.describe({
    QPStatus.SOLVED: "solved",
    QPStatus.MAX_ITERATIONS: "the iteration limit was reached before the tolerance (raise "
                             "max_iterations, or loosen tolerance): the last iterate is returned",
    QPStatus.PRIMAL_INFEASIBLE: "no point satisfies the constraints (the bounds contradict "
                                "each other from this state): widen the state bounds or make "
                                "them soft",
    QPStatus.NONFINITE: "the data or the iterates are not finite (NaN or inf in q, or in a "
                        "bound that must be finite)",
})


class QPSolution(NamedTuple):
    """`x` the minimizer, `y` the multipliers of $l \\le Ax \\le u$ (positive where the upper
    bound is active, negative at the lower), `status` a `QPStatus` code, `iterations` the
    ADMM iterations used, `polished` whether the exact active-set solution was kept."""

    x: jax.Array
    y: jax.Array
    status: jax.Array
    iterations: jax.Array
    polished: jax.Array


class QPWorkspace(eqx.Module):
    """The cached part of a QP: P and A, their Ruiz scaling, and the inverse KKT matrices of
    the ρ ladder (see `qp_workspace`). Options are static: changing one recompiles."""

    P: jax.Array
    A: jax.Array
    P_scaled: jax.Array
    A_scaled: jax.Array
    D: jax.Array
    E: jax.Array
    cost_scale: jax.Array
    kkt_inverses: jax.Array  # (len(RHO_LADDER), n, n)
    rho: float = eqx.field(static=True)
    sigma: float = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)


def _ruiz(P, A):
    """(P̄, Ā, D, E, c): D and E equilibrate the columns of [[P, Aᵀ], [A, 0]] (Ruiz 2001, as
    OSQP), c scales the cost so the mean column of P̄ has norm ~1."""
    n = P.shape[0]
    D, E = jnp.ones(n, P.dtype), jnp.ones(A.shape[0], P.dtype)

    def step(_, state):
        P, A, D, E = state
        column = jnp.maximum(jnp.max(jnp.abs(P), axis=0), jnp.max(jnp.abs(A), axis=0, initial=0.0))
        row = jnp.max(jnp.abs(A), axis=1, initial=0.0)
        d = 1 / jnp.sqrt(jnp.clip(column, 1e-4, 1e4))
        e = 1 / jnp.sqrt(jnp.clip(row, 1e-4, 1e4))
        return d[:, None] * P * d, e[:, None] * A * d, D * d, E * e

    P, A, D, E = jax.lax.fori_loop(0, _RUIZ_ITERATIONS, step, (P, A, D, E))
    c = 1 / jnp.clip(jnp.mean(jnp.max(jnp.abs(P), axis=0)), 1e-4, 1e4)
    return c * P, A, D, E, c


def _kkt_inverses(P, A, rho, sigma):
    r"""$(P + \sigma I + \rho_k A^T A)^{-1}$ for every $\rho_k$ of the ladder."""
    eye = jnp.eye(P.shape[0], dtype=P.dtype)
    K = P + sigma * eye + (rho * jnp.asarray(RHO_LADDER, P.dtype))[:, None, None] * (A.T @ A)
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(K), True), jnp.broadcast_to(eye, K.shape))


def qp_workspace(P, A, *, rho: float = 0.1, sigma: float = 1e-6, tolerance: float = 1e-3,
                 max_iterations: int = 4000) -> QPWorkspace:
    """The workspace of the QPs with Hessian `P` (n, n), positive definite, and constraint
    matrix `A` (m, n): the scaling and the cached KKT inverses. `tolerance` (absolute and
    relative, of the ADMM residuals) decides when to polish: the polished point is exact
    whatever it is, so it only has to be close enough for the active set to show (on the
    cart-pole MPC, 1e-3 and 1e-6 gave the same 512 solutions, with 60 and 140 iterations for
    the slowest); it is also the accuracy of an unpolished answer. `max_iterations` bounds the
    ADMM iterations of one solve."""
    P, A = jnp.asarray(P), jnp.asarray(A)
    with jax.default_matmul_precision("highest"):
        P_scaled, A_scaled, D, E, c = jax.lax.stop_gradient(_ruiz(P, A))
        inverses = _kkt_inverses(P_scaled, A_scaled, rho, sigma)
    return QPWorkspace(P, A, P_scaled, A_scaled, D, E, c, inverses, float(rho), float(sigma), float(tolerance),
                       int(max_iterations))


def _active_set_kkt(P, A, active, delta):
    """[[P, A_aᵀ], [A_a, -δ]] with the inactive rows' multipliers pinned to zero (unit
    diagonal): quasi-definite, so nonsingular even when active rows are dependent."""
    Aa = jnp.where(active[:, None], A, 0.0)
    corner = -jnp.diag(jnp.where(active, delta, 1.0))
    return jnp.block([[P, Aa.T], [Aa, corner]])


def _delta(P):
    return 1e-3 * jnp.sqrt(jnp.finfo(P.dtype).eps) * (1 + jnp.max(jnp.abs(P)))


@jax.custom_jvp
def _kkt_point(P, q, A, lower, upper, x, y, at_lower, at_upper):
    """(x, y), a KKT point of the QP with the given active set; its JVP is the implicit one."""
    return x, y


@_kkt_point.defjvp
def _kkt_point_jvp(primals, tangents):
    P, q, A, lower, upper, x, y, at_lower, at_upper = primals
    dP, dq, dA, dl, du = tangents[:5]
    active = at_lower | at_upper
    with jax.default_matmul_precision("highest"):
        K = _active_set_kkt(P, A, active, _delta(P))
        rhs = jnp.concatenate([-(dP @ x + dq + dA.T @ y),
                               jnp.where(active, jnp.where(at_lower, dl, du) - dA @ x, 0.0)])
        d = jnp.linalg.solve(K, rhs)
    n = x.shape[0]
    return (x, y), (d[:n], d[n:])


class _Iterate(NamedTuple):
    x: jax.Array
    z: jax.Array
    y: jax.Array
    rung: jax.Array  # index into the rho ladder
    iterations: jax.Array
    status: jax.Array  # -1 while running


def _admm(ws: QPWorkspace, q, lower, upper, x, y):
    """The ADMM iterations in the scaled problem, from the (unscaled) warm start (x, y)."""
    P, A, D, E, c, sigma = ws.P_scaled, ws.A_scaled, ws.D, ws.E, ws.cost_scale, ws.sigma
    q, lower, upper = c * D * q, E * lower, E * upper
    x, y = x / D, c * y / E
    tol = ws.tolerance
    inf_tol = jnp.asarray(tol, P.dtype)

    def iterate(_, state):
        x, z, y, dy, rho, Minv = state
        x_tilde = Minv @ (sigma * x - q + A.T @ (rho * z - y))
        z_hat = _ALPHA * (A @ x_tilde) + (1 - _ALPHA) * z
        z_new = jnp.clip(z_hat + y / rho, lower, upper)
        y_new = y + rho * (z_hat - z_new)
        return _ALPHA * x_tilde + (1 - _ALPHA) * x, z_new, y_new, y_new - y, rho, Minv

    def chunk(s: _Iterate) -> _Iterate:
        rho = ws.rho * jnp.asarray(RHO_LADDER, P.dtype)[s.rung]
        x, z, y, dy, _, _ = jax.lax.fori_loop(
            0, CHECK_EVERY, iterate, (s.x, s.z, s.y, jnp.zeros_like(s.y), rho, ws.kkt_inverses[s.rung]), unroll=_UNROLL)
        Ax, Px, Aty = A @ x, P @ x, A.T @ y
        primal = jnp.max(jnp.abs((Ax - z) / E), initial=0.0)
        primal_scale = jnp.maximum(jnp.max(jnp.abs(Ax / E), initial=0.0), jnp.max(jnp.abs(z / E), initial=0.0))
        dual = jnp.max(jnp.abs((Px + q + Aty) / D)) / c
        dual_scale = jnp.max(jnp.stack([jnp.max(jnp.abs(v / D)) for v in (Px, Aty, q)])) / c
        converged = (primal <= tol * (1 + primal_scale)) & (dual <= tol * (1 + dual_scale))
        # Farkas certificate on the change of y (scaled back): A^T dy = 0 and u^T dy+ + l^T dy- < 0
        dy_norm = jnp.max(jnp.abs(E * dy), initial=0.0)
        support = jnp.sum(jnp.where(dy > 0, upper * dy, 0.0) + jnp.where(dy < 0, lower * dy, 0.0))
        infeasible = ((jnp.max(jnp.abs((A.T @ dy) / D)) <= inf_tol * dy_norm)
                      & (support < -inf_tol * dy_norm) & (dy_norm > 0))
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(y))
        iterations = s.iterations + CHECK_EVERY
        status = jnp.select([~finite, converged, infeasible, iterations >= ws.max_iterations],
                            [QPStatus.NONFINITE, QPStatus.SOLVED, QPStatus.PRIMAL_INFEASIBLE,
                             QPStatus.MAX_ITERATIONS], -1).astype(jnp.int32)
        # OSQP's adaptive rho, rho * sqrt(relative primal / relative dual residual), on the ladder
        ratio = (primal / (primal_scale + 1e-30)) / (dual / (dual_scale + 1e-30) + 1e-30)
        steps = jnp.round(jnp.log10(jnp.where(jnp.isfinite(ratio) & (ratio > 0), ratio, 1.0)))  # half-decades of rho
        rung = jnp.clip(s.rung + steps.astype(jnp.int32), 0, len(RHO_LADDER) - 1)
        return _Iterate(x, z, y, rung, iterations, status)

    start = _Iterate(x, jnp.clip(A @ x, lower, upper), y, jnp.asarray(len(RHO_LADDER) // 2, jnp.int32),
                     jnp.asarray(0, jnp.int32), jnp.asarray(-1, jnp.int32))
    s = jax.lax.while_loop(lambda s: s.status < 0, chunk, start)
    return D * s.x, s.z / E, E * s.y / c, s.status, s.iterations


def _polish(P, q, A, lower, upper, z, y, tol):
    """The exact solution on the active set read from (z, y) (OSQP's rule: a row is at its
    lower bound when z - l < -y, at its upper when u - z < y), if it is a KKT point; when it is
    not (a degenerate vertex, where the guess holds dependent rows and the least-norm
    multipliers take a wrong sign), up to `_POLISH_PASSES - 1` primal-dual active-set
    corrections: rows with a wrong-signed multiplier leave, violated rows enter.
    Returns (x, y, at_lower, at_upper, accepted)."""
    n = q.shape[0]
    delta = _delta(P)
    equality = lower == upper

    def attempt(state):
        _, _, at_lower, at_upper, _, passes = state
        active = at_lower | at_upper
        K = _active_set_kkt(P, A, active, delta)
        exact = _active_set_kkt(P, A, active, 0.0)
        rhs = jnp.concatenate([-q, jnp.where(active, jnp.where(at_lower, lower, upper), 0.0)])
        lu = jax.scipy.linalg.lu_factor(K)
        sol = jax.scipy.linalg.lu_solve(lu, rhs)
        for _ in range(2):  # iterative refinement against the unregularized system
            sol = sol + jax.scipy.linalg.lu_solve(lu, rhs - exact @ sol)
        x, y = sol[:n], jnp.where(active, sol[n:], 0.0)
        Ax = A @ x
        slack = tol * (1 + jnp.max(jnp.abs(Ax), initial=0.0))
        sign_slack = tol * (1 + jnp.max(jnp.abs(y), initial=0.0))
        wrong_sign = ~equality & ((at_upper & (y < -sign_slack)) | (at_lower & (y > sign_slack)))
        below, above = Ax < lower - slack, Ax > upper + slack
        ok = jnp.all(jnp.isfinite(sol)) & ~jnp.any(below | above | wrong_sign)
        return (x, y, jnp.where(ok, at_lower, (at_lower & ~wrong_sign) | below),
                jnp.where(ok, at_upper, (at_upper & ~wrong_sign) | above), ok, passes + 1)

    at_lower = z - lower < -y
    at_upper = (upper - z < y) & ~at_lower
    start = (jnp.zeros_like(q), jnp.zeros_like(y), at_lower, at_upper, jnp.asarray(False), jnp.asarray(0))
    x, y, at_lower, at_upper, ok, _ = jax.lax.while_loop(lambda s: ~s[4] & (s[5] < _POLISH_PASSES), attempt, start)
    return x, y, at_lower, at_upper, ok


@jax.jit  # one kept program: called outside jit, its ADMM and polish loops are not compiled anew each call
def solve_qp(ws: QPWorkspace, q, lower, upper, warm_x=None, warm_y=None) -> QPSolution:
    """Solve $\\min \\tfrac12 x^T P x + q^T x$, lower <= A x <= upper (±inf allowed) with the
    workspace's P and A, from the warm start (warm_x, warm_y) (zeros by default). Inside
    `jit` / `vmap`; never raises: the status says how it ended (see `QPStatus`), and x is
    the last iterate unless SOLVED. Differentiable (forward and reverse) with respect to q,
    the bounds and the workspace's P and A, by the implicit function theorem at the solution
    (exact when it was polished)."""
    q = jnp.asarray(q, ws.P.dtype)
    lower, upper = (jnp.broadcast_to(jnp.asarray(b, ws.P.dtype), (ws.A.shape[0],)) for b in (lower, upper))
    x0 = jnp.zeros_like(q) if warm_x is None else warm_x
    y0 = jnp.zeros_like(lower) if warm_y is None else warm_y
    stopped = jax.lax.stop_gradient
    data = stopped((q, lower, upper))
    with jax.default_matmul_precision("highest"):  # float32 on a GPU: TF32 products would stall ADMM
        x, z, y, status, iterations = _admm(stopped(ws), *data, stopped(x0), stopped(y0))
        # a polished point is accepted as a KKT point to rounding, whatever the ADMM tolerance
        xp, yp, at_lower, at_upper, polished = _polish(stopped(ws.P), data[0], stopped(ws.A), *data[1:], z, y,
                                                       float(np.sqrt(jnp.finfo(q.dtype).eps)))
    polished = polished & (status != QPStatus.PRIMAL_INFEASIBLE) & (status != QPStatus.NONFINITE)
    x, y = jnp.where(polished, xp, x), jnp.where(polished, yp, y)
    status = jnp.where(polished, QPStatus.SOLVED, status).astype(jnp.int32)
    x, y = _kkt_point(ws.P, q, ws.A, lower, upper, x, y, at_lower, at_upper)
    return QPSolution(x, y, status, iterations, polished)
