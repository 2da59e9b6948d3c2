r"""Algebraic Riccati equations in JAX, differentiable by the implicit function theorem.

Continuous (CARE): $A^T S + S A - (S B + N) R^{-1} (B^T S + N^T) + Q = 0$.
Discrete (DARE): $A^T S A - S - (A^T S B + N)(R + B^T S B)^{-1}(B^T S A + N^T) + Q = 0$.

The cross term N is removed by the usual change of variables ($\bar A = A - B R^{-1} N^T$,
$\bar Q = Q - N R^{-1} N^T$ for the CARE). The CARE is solved by the matrix sign function of
the Hamiltonian $Z = [[A, -G], [-Q, -A^T]]$, $G = B R^{-1} B^T$ (Newton's iteration
$Z \leftarrow (cZ + (cZ)^{-1})/2$ with Byers' determinant scaling $c = |\det Z|^{-1/2n}$,
stopped once $\|cZ - (cZ)^{-1}\|_1 \le \epsilon_{tol} \|Z\|_1$, usually after 6–10 steps);
S is the least-squares solution of $[W_{12}; W_{22} + I] S = -[W_{11} + I; W_{21}]$,
$W = \mathrm{sign}(Z)$. The DARE is solved by the structure-preserving doubling algorithm
(Chu, Fan, Lin 2005), stopped at convergence. Where the relative residual is not at rounding
level, Newton steps (Kleinman / Hewer) polish S.

The linear matrix equations of the polish and of the derivatives involve the stable closed
loop $A_c$ and are solved iteratively in O(n^3) per step: the Lyapunov equation
$A_c^T X + X A_c + C = 0$ by the sign function of $[[A_c^T, C], [0, -A_c]]$ (Roberts),
the Stein equation $A_c^T X A_c - X + C = 0$ by Smith's doubling
$X \leftarrow X + M^T X M$, $M \leftarrow M^2$. Derivatives: at the solution, $dS$ solves
$A_c^T dS + dS A_c = -\partial_\theta F\, d\theta$ (continuous) or
$A_c^T dS A_c - dS = -\partial_\theta F\, d\theta$ (discrete), $\partial_\theta F$ from
`jax.jvp` at fixed S: no differentiation through the iterations.

The public Lyapunov solvers accept any A without eigenvalues $\lambda_i + \lambda_j = 0$
(or $\lambda_i \lambda_j = 1$): they solve the $n^2 \times n^2$ Kronecker system (fine up to n ~ 30).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_MAX_ITERATIONS = 60
_POLISH_STEPS = 3


def _tolerance(M):
    """Stopping tolerance of the iterations: rounding level, grown with the size."""
    return 100 * M.shape[0] * jnp.finfo(M.dtype).eps


def _norm1(M):
    return jnp.sum(jnp.abs(M))


# Matrices of at most this order are multiplied and solved by elementwise operations (XLA fuses
# them into one loop over a vmapped batch); larger ones by XLA's dot and LAPACK. Measured on a
# 2-core CPU, batches of 10^4: 4x4 products 1.8 -> 0.4 ms, 4x4 solves with 8 right-hand sides
# 6.6 -> 2.8 ms; at order 6 the two ways are level, at 8 elementwise is 2-4x slower.
_ELEMENTWISE_UP_TO = 6


def _mm(A, B):
    """A @ B."""
    if max(A.shape + B.shape) > _ELEMENTWISE_UP_TO:
        return A @ B
    return jnp.sum(A[:, :, None] * B[None, :, :], axis=1)


def _solve(A, B):
    """A^-1 B (A square): Gauss-Jordan elimination with partial pivoting for a small A,
    LAPACK's LU otherwise. For the doubling steps only: unrolled, it costs compile time
    wherever it is traced (four 4x4 solves in the quadrotor's polish: 0.3 -> 0.9 s)."""
    n = A.shape[0]
    if n > _ELEMENTWISE_UP_TO:
        return jnp.linalg.solve(A, B)
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(n)[:, None]
    for j in range(n):  # unrolled: a loop costs more per step than a small column's work
        pivot = jnp.argmax(jnp.where(rows[:, 0] >= j, jnp.abs(M[:, j]), -1.0))
        pivot_row = jnp.sum(jnp.where(rows == pivot, M, 0.0), axis=0)
        M = jnp.where(rows == pivot, M[j], jnp.where(rows == j, pivot_row, M))   # swap rows j, pivot
        scaled = pivot_row / pivot_row[j]
        M = jnp.where(rows == j, scaled, M - M[:, j:j + 1] * scaled)
    return M[:, n:]


def _inverse_and_log_det(M):
    """(M^-1, log |det M|) from one LU factorization."""
    lu, _, permutation = jax.lax.linalg.lu(M)
    lower = jax.lax.linalg.triangular_solve(lu, jnp.eye(M.shape[0], dtype=M.dtype)[permutation],
                                            left_side=True, lower=True, unit_diagonal=True)
    inverse = jax.lax.linalg.triangular_solve(lu, lower, left_side=True, lower=False)
    return inverse, jnp.sum(jnp.log(jnp.abs(jnp.diagonal(lu))))


def _sign_iteration(Z, C=None):
    r"""(sign(Z), C_final) by the scaled Newton iteration. With C, the iteration runs on the
    block matrix $[[Z, C], [0, -Z^T]]$, whose upper-right block evolves as
    $C \leftarrow (cC + Z^{-1} C Z^{-T} / c)/2$ and tends to $2X$, $Z X + X Z^T + C = 0$, when
    Z is Hurwitz."""
    tolerance = _tolerance(Z)

    def step(state):
        Z, C, _, k = state
        inverse, log_det = _inverse_and_log_det(Z)
        c = jnp.exp(-log_det / Z.shape[0])
        c = jnp.where(jnp.isfinite(c) & (c > 0), c, 1.0)
        moving = _norm1(c * Z - inverse / c) > tolerance * _norm1(Z)
        if C is not None:
            C = 0.5 * (c * C + inverse @ C @ inverse.T / c)
        return 0.5 * (c * Z + inverse / c), C, moving & (k + 1 < _MAX_ITERATIONS), k + 1

    Z, C, _, _ = jax.lax.while_loop(lambda state: state[2], step, (Z, C, True, 0))
    return Z, C


def _lyapunov_by_sign(Ac, C):
    """X with Ac^T X + X Ac + C = 0, Ac Hurwitz (the sign function of [[Ac^T, C], [0, -Ac]])."""
    return 0.5 * _sign_iteration(Ac.T, C)[1]


def _stein_by_doubling(Ac, C):
    """X with Ac^T X Ac - X + C = 0, Ac Schur stable (Smith's doubling)."""
    tolerance = _tolerance(Ac)

    def step(state):
        X, M, _, k = state
        increment = _mm(_mm(M.T, X), M)
        moving = _norm1(increment) > tolerance * _norm1(X)
        return X + increment, _mm(M, M), moving & (k + 1 < _MAX_ITERATIONS), k + 1

    return jax.lax.while_loop(lambda state: state[2], step, (C, Ac, True, 0))[0]


def _linear_solve(solver, operator, Ac, C):
    """X with operator(Ac, X) + C = 0 by solver(Ac, C), transposable (the adjoint of either
    operator is the same operator of Ac^T), so reverse mode differentiates through it."""
    return jax.lax.custom_linear_solve(
        lambda X: -operator(Ac, X), C, lambda _, C: solver(Ac, C),
        transpose_solve=lambda _, C: solver(Ac.T, C))


def _lyapunov_of_stable(Ac, C):
    """X with Ac^T X + X Ac + C = 0, Ac Hurwitz; differentiable in C in either mode."""
    return _linear_solve(_lyapunov_by_sign, lambda Ac, X: Ac.T @ X + X @ Ac, Ac, C)


def _stein_of_stable(Ac, C):
    """X with Ac^T X Ac - X + C = 0, Ac Schur stable; differentiable in C in either mode."""
    return _linear_solve(_stein_by_doubling, lambda Ac, X: Ac.T @ X @ Ac - X, Ac, C)


def _symmetric(S):
    return (S + S.T) / 2


def _polish(S, residual, newton_correction):
    r"""Newton steps $S \leftarrow S + \Delta(S, F(S))$ while the relative residual
    $\|F(S)\|_1 / \mathrm{scale}$ is above $10^3 n \epsilon$ (well above the rounding level a
    correct solve reaches) and still falls."""
    tolerance = 10 * _tolerance(S)

    def relative(S):
        F, scale = residual(S)
        return F, _norm1(F) / jnp.maximum(scale, jnp.finfo(S.dtype).tiny)

    def step(state):
        S, F, error, _, k = state
        S = _symmetric(S + newton_correction(S, F))
        F, new_error = relative(S)
        return S, F, new_error, (new_error > tolerance) & (new_error < 0.5 * error) & (k + 1 < _POLISH_STEPS), k + 1

    F, error = relative(S)
    return jax.lax.while_loop(lambda state: state[3], step, (S, F, error, error > tolerance, 0))[0]


def _care_terms(S, A, G, Q):
    """(F(S), the 1-norm scale of its terms) for the CARE with G = B R^-1 B^T."""
    AtS, SGS = A.T @ S, S @ G @ S
    return AtS + AtS.T - SGS + Q, 2 * _norm1(AtS) + _norm1(SGS) + _norm1(Q)


def _care_residual(S, A, B, Q, R):
    return _care_terms(S, A, B @ jnp.linalg.solve(R, B.T), Q)[0]


@jax.custom_jvp
def _care(A, B, Q, R):
    n = A.shape[0]
    G = B @ jnp.linalg.solve(R, B.T)
    W = _sign_iteration(jnp.block([[A, -G], [-Q, -A.T]]))[0]
    eye = jnp.eye(n, dtype=A.dtype)
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + eye])
    rhs = -jnp.concatenate([W[:n, :n] + eye, W[n:, :n]])
    q, r = jnp.linalg.qr(lhs)
    S = _symmetric(jax.lax.linalg.triangular_solve(r, q.T @ rhs, left_side=True, lower=False))
    return _polish(S, lambda S: _care_terms(S, A, G, Q), lambda S, F: _lyapunov_of_stable(A - G @ S, F))


@_care.defjvp
def _care_jvp(primals, tangents):
    A, B, Q, R = primals
    S = _care(A, B, Q, R)
    dF = jax.jvp(lambda *p: _care_residual(S, *p), primals, tangents)[1]
    return S, _lyapunov_of_stable(A - B @ jnp.linalg.solve(R, B.T @ S), dF)


def _dare_gain(S, A, B, R):
    BtS = _mm(B.T, S)
    return jnp.linalg.solve(R + _mm(BtS, B), _mm(BtS, A))


def _dare_terms(S, A, B, Q, R):
    """(F(S), the 1-norm scale of its terms) for the DARE."""
    AtSA = _mm(_mm(A.T, S), A)
    return AtSA - S - _mm(_mm(_mm(B.T, S), A).T, _dare_gain(S, A, B, R)) + Q, _norm1(AtSA) + _norm1(S) + _norm1(Q)


def _dare_residual(S, A, B, Q, R):
    return _dare_terms(S, A, B, Q, R)[0]


@jax.custom_jvp
def _dare(A, B, Q, R):
    G = B @ jnp.linalg.solve(R, B.T)
    eye = jnp.eye(A.shape[0], dtype=A.dtype)
    tolerance = _tolerance(A)

    def doubling(state):
        Ak, Gk, Hk, _, k = state
        MA, MG = jnp.split(_solve(eye + _mm(Gk, Hk), jnp.concatenate([Ak, Gk], axis=1)), 2, axis=1)
        increment = _mm(Ak.T, _mm(Hk, MA))
        moving = _norm1(increment) > tolerance * _norm1(Hk)
        return (_mm(Ak, MA), Gk + _mm(_mm(Ak, MG), Ak.T), Hk + increment, moving & (k + 1 < _MAX_ITERATIONS), k + 1)

    S = _symmetric(jax.lax.while_loop(lambda state: state[3], doubling, (A, G, Q, True, 0))[2])
    return _polish(S, lambda S: _dare_terms(S, A, B, Q, R),
                   lambda S, F: _stein_of_stable(A - B @ _dare_gain(S, A, B, R), F))


@_dare.defjvp
def _dare_jvp(primals, tangents):
    A, B, Q, R = primals
    S = _dare(A, B, Q, R)
    dF = jax.jvp(lambda *p: _dare_residual(S, *p), primals, tangents)[1]
    return S, _stein_of_stable(A - B @ _dare_gain(S, A, B, R), dF)


def _without_cross_term(A, B, Q, R, N):
    """(A - B R^-1 N^T, Q - N R^-1 N^T): the same Riccati equation without N."""
    if N is None:
        return A, Q
    return A - B @ jnp.linalg.solve(R, N.T), Q - N @ jnp.linalg.solve(R, N.T)


@jax.jit  # one kept program: called outside jit, its while loop is not compiled anew each call
def solve_continuous_are(A, B, Q, R, N=None):
    """The stabilising solution S of the CARE (see the module doc); differentiable."""
    A, B, Q, R = (jnp.asarray(M, float) for M in (A, B, Q, R))
    A_bar, Q_bar = _without_cross_term(A, B, Q, R, None if N is None else jnp.asarray(N, float))
    return _care(A_bar, B, Q_bar, R)


@jax.jit  # one kept program: called outside jit, its while loop is not compiled anew each call
def solve_discrete_are(A, B, Q, R, N=None):
    """The stabilising solution S of the DARE (see the module doc); differentiable."""
    A, B, Q, R = (jnp.asarray(M, float) for M in (A, B, Q, R))
    A_bar, Q_bar = _without_cross_term(A, B, Q, R, None if N is None else jnp.asarray(N, float))
    return _dare(A_bar, B, Q_bar, R)


def _kron_solve(op_matrix, rhs):
    n = rhs.shape[0]
    return jnp.linalg.solve(op_matrix, rhs.reshape(-1)).reshape(n, n)


def solve_continuous_lyapunov(A, Q):
    r"""P with $A^T P + P A = -Q$ (Drake's `RealContinuousLyapunovEquation`); for Hurwitz A
    and Q > 0, P > 0 and $V = x^T P x$ is a Lyapunov function of $\dot x = A x$.
    Kronecker solve; differentiable."""
    A, Q = jnp.asarray(A, float), jnp.asarray(Q, float)
    eye = jnp.eye(A.shape[0], dtype=A.dtype)
    return _symmetric(_kron_solve(jnp.kron(A.T, eye) + jnp.kron(eye, A.T), -Q))


def solve_discrete_lyapunov(A, Q):
    r"""P with $A^T P A - P = -Q$ (for Schur-stable A, $V = x^T P x$ decreases along
    $x[n+1] = A x[n]$). Kronecker solve; differentiable."""
    A, Q = jnp.asarray(A, float), jnp.asarray(Q, float)
    return _symmetric(_kron_solve(jnp.kron(A.T, A.T) - jnp.eye(A.size, dtype=A.dtype), -Q))
