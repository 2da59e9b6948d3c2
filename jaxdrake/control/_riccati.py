r"""Algebraic Riccati equations in JAX, differentiable by the implicit function theorem.

Continuous (CARE): $A^T S + S A - (S B + N) R^{-1} (B^T S + N^T) + Q = 0$.
Discrete (DARE): $A^T S A - S - (A^T S B + N)(R + B^T S B)^{-1}(B^T S A + N^T) + Q = 0$.

The cross term N is removed by the usual change of variables ($\bar A = A - B R^{-1} N^T$,
$\bar Q = Q - N R^{-1} N^T$ for the CARE). The CARE is solved by the matrix sign function of
the Hamiltonian (Roberts; Byers' determinant scaling), the DARE by the structure-preserving
doubling algorithm (Chu, Fan, Lin 2005); each is then polished by two Newton steps (a
Lyapunov / Stein solve). Derivatives: at the solution, $dS$ solves the linearised equation
$A_c^T dS + dS A_c = -\partial_\theta F\, d\theta$ (continuous) or
$A_c^T dS A_c - dS = -\partial_\theta F\, d\theta$ (discrete), $A_c$ the closed loop, with
$\partial_\theta F$ from `jax.jvp` at fixed S: no differentiation through the iterations.
The linear matrix equations are solved by Kronecker products (fine up to n ~ 30).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_SIGN_ITERATIONS = 60
_DOUBLING_ITERATIONS = 40


def _kron_solve(op_matrix, rhs):
    n = rhs.shape[0]
    return jnp.linalg.solve(op_matrix, rhs.reshape(-1)).reshape(n, n)


def _lyapunov_operator(Ac):
    """The matrix of X -> Ac^T X + X Ac acting on row-major vec(X)."""
    n = Ac.shape[0]
    eye = jnp.eye(n, dtype=Ac.dtype)
    return jnp.kron(Ac.T, eye) + jnp.kron(eye, Ac.T)


def _stein_operator(Ac):
    """The matrix of X -> Ac^T X Ac - X on row-major vec(X)."""
    n = Ac.shape[0]
    return jnp.kron(Ac.T, Ac.T) - jnp.eye(n * n, dtype=Ac.dtype)


def _care_residual(S, A, B, Q, R):
    return A.T @ S + S @ A - S @ B @ jnp.linalg.solve(R, B.T @ S) + Q


def _dare_residual(S, A, B, Q, R):
    BtSA = B.T @ S @ A
    return A.T @ S @ A - S - BtSA.T @ jnp.linalg.solve(R + B.T @ S @ B, BtSA) + Q


def _symmetric(S):
    return (S + S.T) / 2


@jax.custom_jvp
def _care(A, B, Q, R):
    n = A.shape[0]
    G = B @ jnp.linalg.solve(R, B.T)
    Z = jnp.block([[A, -G], [-Q, -A.T]])

    def sign_step(Z, _):
        c = jnp.abs(jnp.linalg.det(Z)) ** (-1.0 / (2 * n))  # determinant scaling
        c = jnp.where(jnp.isfinite(c) & (c > 0), c, 1.0)
        return 0.5 * (c * Z + jnp.linalg.inv(c * Z)), None

    W = jax.lax.scan(sign_step, Z, None, length=_SIGN_ITERATIONS)[0]
    eye = jnp.eye(n, dtype=A.dtype)
    lhs = jnp.concatenate([W[:n, n:], W[n:, n:] + eye])
    rhs = -jnp.concatenate([W[:n, :n] + eye, W[n:, :n]])
    S = _symmetric(jnp.linalg.lstsq(lhs, rhs)[0])
    for _ in range(2):  # Newton (Kleinman) polish
        Ac = A - G @ S
        S = _symmetric(S + _kron_solve(_lyapunov_operator(Ac), -_care_residual(S, A, B, Q, R)))
    return S


def _implicit_tangent(residual, operator, S, primals, tangents):
    """(S, dS) with dS solving operator(dS) = -(dF/dtheta) dtheta at the solution S."""
    dF = jax.jvp(lambda *p: residual(S, *p), primals, tangents)[1]
    return S, _symmetric(_kron_solve(operator, -dF))


@_care.defjvp
def _care_jvp(primals, tangents):
    A, B, Q, R = primals
    S = _care(A, B, Q, R)
    Ac = A - B @ jnp.linalg.solve(R, B.T @ S)
    return _implicit_tangent(_care_residual, _lyapunov_operator(Ac), S, primals, tangents)


@jax.custom_jvp
def _dare(A, B, Q, R):
    G = B @ jnp.linalg.solve(R, B.T)
    eye = jnp.eye(A.shape[0], dtype=A.dtype)

    def doubling(state, _):
        Ak, Gk, Hk = state
        M = jnp.linalg.inv(eye + Gk @ Hk)
        return (Ak @ M @ Ak, Gk + Ak @ M @ Gk @ Ak.T, Hk + Ak.T @ Hk @ M @ Ak), None

    S = _symmetric(jax.lax.scan(doubling, (A, G, Q), None, length=_DOUBLING_ITERATIONS)[0][2])
    for _ in range(2):  # Newton (Hewer) polish
        K = jnp.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)
        S = _symmetric(S + _kron_solve(_stein_operator(A - B @ K), -_dare_residual(S, A, B, Q, R)))
    return S


@_dare.defjvp
def _dare_jvp(primals, tangents):
    A, B, Q, R = primals
    S = _dare(A, B, Q, R)
    K = jnp.linalg.solve(R + B.T @ S @ B, B.T @ S @ A)
    return _implicit_tangent(_dare_residual, _stein_operator(A - B @ K), S, primals, tangents)


def _without_cross_term(A, B, Q, R, N):
    """(A - B R^-1 N^T, Q - N R^-1 N^T): the same Riccati equation without N."""
    if N is None:
        return A, Q
    return A - B @ jnp.linalg.solve(R, N.T), Q - N @ jnp.linalg.solve(R, N.T)


def solve_continuous_are(A, B, Q, R, N=None):
    """The stabilising solution S of the CARE (see the module doc); differentiable."""
    A, B, Q, R = (jnp.asarray(M, float) for M in (A, B, Q, R))
    A_bar, Q_bar = _without_cross_term(A, B, Q, R, None if N is None else jnp.asarray(N, float))
    return _care(A_bar, B, Q_bar, R)


def solve_discrete_are(A, B, Q, R, N=None):
    """The stabilising solution S of the DARE (see the module doc); differentiable."""
    A, B, Q, R = (jnp.asarray(M, float) for M in (A, B, Q, R))
    A_bar, Q_bar = _without_cross_term(A, B, Q, R, None if N is None else jnp.asarray(N, float))
    return _dare(A_bar, B, Q_bar, R)


def solve_continuous_lyapunov(A, Q):
    r"""P with $A^T P + P A = -Q$ (Drake's `RealContinuousLyapunovEquation`); for Hurwitz A
    and Q > 0, P > 0 and $V = x^T P x$ is a Lyapunov function of $\dot x = A x$.
    Kronecker solve; differentiable."""
    A, Q = jnp.asarray(A, float), jnp.asarray(Q, float)
    return _symmetric(_kron_solve(_lyapunov_operator(A), -Q))


def solve_discrete_lyapunov(A, Q):
    r"""P with $A^T P A - P = -Q$ (for Schur-stable A, $V = x^T P x$ decreases along
    $x[n+1] = A x[n]$). Kronecker solve; differentiable."""
    A, Q = jnp.asarray(A, float), jnp.asarray(Q, float)
    return _symmetric(_kron_solve(_stein_operator(A), -Q))
