r"""Polynomial systems (notes, D.3.1: "(rational) polynomial systems"), and their cascade,
feedback and parallel combinations by substitution of one's output polynomial into the other's inputs."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import array_module
from ..polynomials import Polynomial
from ._frame import Frame
from ._system import System


class PolynomialSystem(System):
    r"""A (rational) polynomial system (notes, D.3.1):

    $$e(x)\,\dot x = f(x, u) \quad (\text{or } x[n+1] = f(x, u)), \qquad y = g(x, u),
      \qquad \phi(x) = 0,$$

    with $e$, $f$, $g$, $\phi$ polynomials in the variables $(x, u)$ (x first). $e$ defaults
    to the identity (a plain polynomial system), g to y = x; the announced constraints
    $\phi$ (for example $s^2 + c^2 - 1$ after a trigonometric substitution) are carried for
    analysis, which reasons modulo them. Feedback, cascade and parallel combinations of
    polynomial (or linear) systems are polynomial systems.

    **Arguments:**

    - `f`: a `Polynomial` of value shape (n,) in n + m variables (states, then inputs).
    - `g`: output polynomial of value shape (p,), or None for y = x.
    - `e`: the (n, n) mass-like polynomial matrix, or None for the identity.
    - `state_constraints`: a polynomial of value shape (k,) (inputs must not appear), or None.
    - `sample_time`: None for continuous time; else f is the discrete update.
    - frames and `input_limits` as for `System`.
    """

    f: Polynomial
    g: Polynomial | None
    e: Polynomial | None
    constraints: Polynomial | None

    def __init__(self, f: Polynomial, g: Polynomial | None = None, e: Polynomial | None = None,
                 state_constraints: Polynomial | None = None, *, sample_time: float | None = None,
                 input_limits=None, input_frame: Frame | None = None, state_frame: Frame | None = None,
                 output_frame: Frame | None = None):
        if not isinstance(f, Polynomial) or f.is_decision or len(f.shape) != 1:
            raise TypeError("PolynomialSystem: f must be a numeric Polynomial with value shape (n,)")
        n = f.shape[0]
        m = f.num_variables - n
        if m < 0:
            raise ValueError(f"PolynomialSystem: f has {n} components but only {f.num_variables} variables")
        for label, poly, shape in (("g", g, None), ("e", e, (n, n)), ("state_constraints", state_constraints, None)):
            if poly is None:
                continue
            if not isinstance(poly, Polynomial) or poly.num_variables != n + m or len(poly.shape) != (1 if shape is None else 2):
                raise ValueError(f"PolynomialSystem: {label} must be a Polynomial in the {n + m} variables "
                                 f"(x, u) with value shape {shape or '(k,)'}, got {poly!r}")
            if shape is not None and poly.shape != shape:
                raise ValueError(f"PolynomialSystem: e must have value shape {shape}, got {poly.shape}")
        if state_constraints is not None and _uses_inputs(state_constraints, n):
            raise ValueError("PolynomialSystem: state_constraints must not depend on the inputs")
        if e is not None and sample_time is not None:
            raise ValueError("PolynomialSystem: a mass-like e(x) needs continuous time")
        self.f, self.g, self.e, self.constraints = f, g, e, state_constraints
        discrete = sample_time is not None
        super().__init__(num_continuous_states=0 if discrete else n, num_discrete_states=n if discrete else 0,
                         num_inputs=m, num_outputs=n if g is None else g.shape[0], sample_time=sample_time,
                         direct_feedthrough=g is not None and _uses_inputs(g, n), time_invariant=True,
                         num_state_constraints=0 if state_constraints is None else state_constraints.shape[0],
                         input_limits=input_limits, input_frame=input_frame, state_frame=state_frame,
                         output_frame=output_frame)

    @classmethod
    def from_linear(cls, system) -> PolynomialSystem:
        """A `LinearSystem` written as a polynomial system (degree 1)."""
        n, m = system.num_states, system.num_inputs
        E = np.eye(n + m, dtype=int)
        f = Polynomial(E, jnp.concatenate([system.A, system.B], axis=1).T)
        g = Polynomial(E, jnp.concatenate([system.C, system.D], axis=1).T)
        return cls(f, g, sample_time=system.sample_time, input_limits=system.input_limits,
                   input_frame=system.input_frame, state_frame=system.state_frame,
                   output_frame=system.output_frame)

    @property
    def is_rational(self) -> bool:
        return self.e is not None

    def _xu(self, x, u):
        return jnp.concatenate([jnp.asarray(x, float).reshape(-1), jnp.asarray(u, float).reshape(-1)])

    def dynamics(self, t, x, u):
        rhs = self.f(self._xu(x, u))
        return rhs if self.e is None else jnp.linalg.solve(self.e(self._xu(x, u)), rhs)

    def update(self, t, x, u):
        return self.f(self._xu(x, u))

    def output(self, t, x, u):
        return x if self.g is None else self.g(self._xu(x, u))

    def state_constraints(self, x):
        if self.constraints is None:
            return super().state_constraints(x)
        return self.constraints(self._xu(x, jnp.zeros(self.num_inputs)))

    def output_polynomial(self) -> Polynomial:
        """g as a polynomial (the state itself when g is None)."""
        if self.g is not None:
            return self.g
        n = self.num_states
        return Polynomial(np.eye(n + self.num_inputs, dtype=int)[:n], np.eye(n), self.f.variables)


def _uses_inputs(poly: Polynomial, n: int) -> bool:
    """Whether a monomial with an input in it has a coefficient that is not exactly zero
    (traced coefficients count as non-zero)."""
    rows = poly.exponent_array[:, n:].any(1)
    if not isinstance(poly.coefficients, jax.core.Tracer):
        c = np.asarray(poly.coefficients)
        rows &= np.abs(c.reshape(len(c), -1)).max(1, initial=0.0) != 0
    return bool(rows.any())


def _stack(parts: Sequence[Polynomial]) -> Polynomial:
    """Vector polynomials (same variables) stacked into one of value shape (sum of sizes,)."""
    sizes = [p.shape[0] for p in parts]
    total, start = None, 0
    for p, k in zip(parts, sizes):
        c = array_module(p.coefficients).pad(p.coefficients, ((0, 0), (start, sum(sizes) - start - k)))
        term = Polynomial(p.exponent_array, c, p.variables)
        total, start = (term if total is None else total + term), start + k
    return total


def _block_diagonal(a: Polynomial, b: Polynomial) -> Polynomial:
    na, nb = a.shape[0], b.shape[0]
    pa = Polynomial(a.exponent_array, array_module(a.coefficients).pad(a.coefficients, ((0, 0), (0, nb), (0, nb))), a.variables)
    pb = Polynomial(b.exponent_array, array_module(b.coefficients).pad(b.coefficients, ((0, 0), (na, 0), (na, 0))), b.variables)
    return pa + pb


def _entries(p: Polynomial) -> list[Polynomial]:
    return [p[i] for i in range(p.shape[0])]


def combine_polynomial_systems(kind: str, a: PolynomialSystem, b: PolynomialSystem, sign: float = 1.0,
                               **frames) -> PolynomialSystem:
    r"""`cascade` / `feedback` / `parallel` of two polynomial systems, by substituting one's
    output polynomial into the other's inputs: a polynomial system in $(x_a, x_b, u)$, with
    $e = \mathrm{blockdiag}(e_a, e_b)$ and the constraints of both."""
    na, nb, ma, mb = a.num_states, b.num_states, a.num_inputs, b.num_inputs
    m = ma + mb if kind == "parallel" else ma
    z = Polynomial.variables_of(na + nb + m)
    xa, xb, u = list(z[:na]), list(z[na:na + nb]), list(z[na + nb:])
    zero = [Polynomial.constant(0.0, len(z))] * mb
    if kind == "parallel":
        ua, ub = u[:ma], u[ma:]
        y = _stack([a.output_polynomial().substitute(xa + ua), b.output_polynomial().substitute(xb + ub)])
    elif kind == "cascade":
        ua = u
        ub = _entries(a.output_polynomial().substitute(xa + ua))
        y = b.output_polynomial().substitute(xb + ub)
    elif not b.direct_feedthrough:  # feedback: b's output first, then a's
        yb = _entries(b.output_polynomial().substitute(xb + zero))
        ua = [ui + sign * yi for ui, yi in zip(u, yb)]
        y = a.output_polynomial().substitute(xa + ua)
        ub = _entries(y)
    else:  # a has no feedthrough: a's output first
        y = a.output_polynomial().substitute(xa + [Polynomial.constant(0.0, len(z))] * ma)
        ub = _entries(y)
        yb = _entries(b.output_polynomial().substitute(xb + ub))
        ua = [ui + sign * yi for ui, yi in zip(u, yb)]
    f = _stack([a.f.substitute(xa + ua), b.f.substitute(xb + ub)])
    e = None
    if a.e is not None or b.e is not None:
        eye = lambda n: Polynomial(np.zeros((1, len(z)), int), np.eye(n)[None])
        e = _block_diagonal(eye(na) if a.e is None else a.e.substitute(xa + ua),
                            eye(nb) if b.e is None else b.e.substitute(xb + ub))
    constraints = [s.constraints.substitute(xs + [Polynomial.constant(0.0, len(z))] * s.num_inputs)
                   for s, xs in ((a, xa), (b, xb)) if s.constraints is not None]
    return PolynomialSystem(f, y, e, _stack(constraints) if constraints else None,
                            sample_time=a.sample_time, **frames)
