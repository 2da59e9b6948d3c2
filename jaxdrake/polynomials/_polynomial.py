r"""Multivariate polynomials, their monomial bases and Taylor polynomials.

A `Polynomial` is $p(z) = \sum_k c_k z^{\alpha_k}$ with exponent rows $\alpha_k$ (static) and
coefficients $c_k$ that are either numbers -- a JAX array of shape (m, *value_shape), so a
vector field or a matrix is one polynomial, and a polynomial is a differentiable pytree -- or
the decision variables of a convex program (an `AffineExpression` of shape (m,), scalar
polynomials only), which is how sums-of-squares programs write their unknowns. Arithmetic is
exact on the coefficients; products of two decision polynomials (bilinear) are refused.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from itertools import combinations_with_replacement

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import array_module
from ._affine import is_decision


def _numeric(c):
    """Coefficients as float arrays: JAX tracers stay traced, everything concrete becomes numpy."""
    if isinstance(c, jax.core.Tracer):
        return c.astype(float) if c.dtype != float else c
    return np.asarray(c, dtype=float)


def unique_rows(E: np.ndarray):
    """(unique rows of the int matrix E in lexicographic order, inverse indices): as
    `np.unique(E, axis=0, return_inverse=True)`, by one integer key per row (several times faster)."""
    E = np.asarray(E, int)
    if not len(E) or not E.shape[1]:
        return E[:min(len(E), 1)], np.zeros(len(E), int)
    radix = E.max(0) + 1
    if np.prod(radix.astype(float)) >= 2.0**62:  # keys would overflow: the general routine
        unique, inverse = np.unique(E, axis=0, return_inverse=True)
        return unique, inverse.ravel()
    weights = np.concatenate([np.cumprod(radix[::-1])[::-1][1:], [1]])
    _, first, inverse = np.unique(E @ weights, return_index=True, return_inverse=True)
    return E[first], inverse.ravel()


def _names(names, n: int) -> tuple[str, ...]:
    """The variables' names: given, or z0, z1, ..."""
    return tuple(names) if names is not None else tuple(f"z{i}" for i in range(n))


@functools.lru_cache(maxsize=4096)
def _exponent_array(exponents: tuple, n: int) -> np.ndarray:
    E = np.array(exponents, int).reshape(len(exponents), n)
    E.flags.writeable = False
    return E


def _sparse(rows, cols, weights, shape):
    import scipy.sparse

    return scipy.sparse.csr_matrix((np.asarray(weights, float), (rows, cols)), shape=shape)


def _concrete(c, what):
    if is_decision(c):
        raise TypeError(f"{what} needs numeric coefficients, not decision variables")
    try:
        return np.asarray(c, dtype=float)
    except jax.errors.TracerArrayConversionError:
        raise TypeError(f"{what} needs numeric (not traced) coefficients when combined with "
                        "decision variables") from None


def monomial_basis(num_variables: int, degree: int, min_degree: int = 0) -> np.ndarray:
    """All exponent rows $\\alpha$ with `min_degree` <= |alpha| <= `degree`, graded order."""
    rows = []
    for d in range(min_degree, degree + 1):
        for combo in combinations_with_replacement(range(num_variables), d):
            row = np.zeros(num_variables, int)
            np.add.at(row, list(combo), 1)
            rows.append(row)
    return np.array(rows, int).reshape(-1, num_variables)


@jax.tree_util.register_pytree_node_class
class Polynomial:
    r"""$p(z) = \sum_k c_k z^{\alpha_k}$ in `num_variables` indeterminates.

    Build from variables (`x, y = Polynomial.variables(2)`, then `x**2 + 3*x*y`), from exponent
    rows and coefficients, or by `taylor_polynomial`. Supports `+ - * **`, evaluation
    `p(z)` (z of shape (..., n); batched and differentiable), `derivative`, `jacobian`,
    `lie_derivative`, `substitute` and value indexing `p[i]` for vector / matrix polynomials.
    A pytree: the coefficients are its leaf, the exponents and names static.

    **Arguments:**

    - `exponents`: (m, n) non-negative ints, one row per monomial (duplicates are merged).
    - `coefficients`: (m, *value_shape) numbers, or an `AffineExpression` of decision
      variables of shape (m,) (`SosProgram.new_free_polynomial` makes these).
    - `variables`: names of the n indeterminates (for printing); default z0, z1, ...
    """

    __slots__ = ("coefficients", "exponents", "variables")

    def __init__(self, exponents, coefficients, variables: Sequence[str] | None = None):
        E = np.asarray(exponents, dtype=int)
        if E.ndim != 2 or (E.size and E.min() < 0):
            raise ValueError(f"Polynomial: exponents must be an (m, n) array of non-negative ints, "
                             f"got shape {E.shape}")
        n = E.shape[1]
        variables = _names(variables, n)
        if len(variables) != n:
            raise ValueError(f"Polynomial: {len(variables)} variable names for {n} variables")
        if not is_decision(coefficients):
            coefficients = _numeric(coefficients)
        if coefficients.shape[:1] != (E.shape[0],) or (is_decision(coefficients) and coefficients.ndim != 1):
            raise ValueError(f"Polynomial: {E.shape[0]} monomials but coefficients of shape "
                             f"{coefficients.shape} (decision coefficients must be a vector)")
        self._set(E, coefficients, variables)

    def _set(self, E, coefficients, variables):
        unique, inverse = unique_rows(E)
        if len(unique) < len(E):  # merge repeated monomials
            coefficients = _combine(coefficients, np.arange(len(E)), None, inverse, len(unique))
            E = unique
        self.exponents = _rows_tuple(E)
        self.coefficients = coefficients
        self.variables = tuple(variables)

    def __hash__(self):  # as an equinox Module: by field values (traced coefficients hash by identity)
        return hash((self.coefficients, self.exponents, self.variables))

    def __eq__(self, other):
        return type(other) is type(self) and eqx.tree_equal(self, other)

    def tree_flatten(self):
        return (self.coefficients,), (self.exponents, self.variables)

    @classmethod
    def tree_unflatten(cls, static, children):
        self = object.__new__(cls)
        self.exponents, self.variables = static
        self.coefficients = children[0]
        return self

    # ----- construction ---------------------------------------------------------------------

    @classmethod
    def _build(cls, E, coefficients, variables, unique: bool = False) -> Polynomial:
        """The internal constructor of arithmetic results, whose exponent rows E are valid and
        match the coefficients (repeated rows are merged, unless `unique` says there are none)."""
        self = object.__new__(cls)
        coefficients = coefficients if is_decision(coefficients) else _numeric(coefficients)
        if unique:
            self.exponents, self.coefficients, self.variables = _rows_tuple(E), coefficients, tuple(variables)
        else:
            self._set(np.asarray(E, int), coefficients, variables)
        return self

    @classmethod
    def variables_of(cls, n: int, names: Sequence[str] | None = None) -> tuple[Polynomial, ...]:
        """The n indeterminates $z_0, \\dots, z_{n-1}$ as polynomials."""
        names = _names(names, n)
        return tuple(cls._build(np.eye(n, dtype=int)[i:i + 1], [1.0], names, unique=True) for i in range(n))

    @classmethod
    def constant(cls, value, n: int, names: Sequence[str] | None = None) -> Polynomial:
        if is_decision(value):
            if value.shape != ():
                raise ValueError(f"a constant polynomial takes a scalar decision expression, got shape {value.shape}")
            return cls._build(np.zeros((1, n), int), value.as_vector(), _names(names, n), unique=True)
        return cls._build(np.zeros((1, n), int), _numeric(value)[None], _names(names, n), unique=True)

    # ----- facts ----------------------------------------------------------------------------

    @property
    def exponent_array(self) -> np.ndarray:
        """The exponent rows as a read-only (m, n) int array."""
        return _exponent_array(self.exponents, len(self.variables))

    @property
    def num_variables(self) -> int:
        return len(self.variables)

    @property
    def num_monomials(self) -> int:
        return len(self.exponents)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.coefficients.shape[1:])

    @property
    def degree(self) -> int:
        return int(self.exponent_array.sum(1).max()) if self.num_monomials else 0

    @property
    def is_decision(self) -> bool:
        return is_decision(self.coefficients)

    def pruned(self, tol: float = 0.0) -> Polynomial:
        """Drop monomials whose coefficients are all within `tol` of zero (numeric only)."""
        c = _concrete(self.coefficients, "pruned()")
        keep = np.abs(c.reshape(len(c), -1)).max(1, initial=0.0) > tol
        return Polynomial._build(self.exponent_array[keep], c[keep], self.variables, unique=True)

    # ----- evaluation -----------------------------------------------------------------------

    def monomials(self, z):
        """The monomial values $z^{\\alpha_k}$, shape (..., m), by products of powers."""
        xp = array_module(z)
        z = xp.asarray(z, dtype=float) if xp is np else z
        E = self.exponent_array
        if z.shape[-1:] != (self.num_variables,):
            raise ValueError(f"Polynomial in {self.num_variables} variables evaluated at a point of "
                             f"shape {z.shape}")
        top = int(E.max(initial=0))
        columns = xp.moveaxis(z, -1, 0)
        columns = np.ascontiguousarray(columns) if xp is np else columns
        out = xp.ones((len(E),) + z.shape[:-1], dtype=z.dtype)
        for i, zi in enumerate(columns):  # batch axes last, contiguous: 5x faster in numpy
            powers = [xp.ones_like(zi)]
            for _ in range(top):
                powers.append(powers[-1] * zi)
            out = out * xp.stack(powers)[E[:, i]]
        return xp.moveaxis(out, 0, -1)

    def __call__(self, z):
        if self.is_decision:
            return self.coefficients.mapped(self.monomials(np.asarray(z, float)))
        xp = array_module(z, self.coefficients)
        return xp.tensordot(self.monomials(z), self.coefficients, axes=1)

    # ----- arithmetic -----------------------------------------------------------------------

    def _lift(self, other) -> Polynomial:
        if isinstance(other, Polynomial):
            if other.num_variables != self.num_variables:
                raise ValueError(f"polynomials in {self.num_variables} and {other.num_variables} "
                                 "variables cannot be combined")
            return other
        return Polynomial.constant(other, self.num_variables, self.variables)

    def __add__(self, other):
        other = self._lift(other)
        unique, inverse = _sum_structure(self.exponents, other.exponents, self.num_variables)
        a, b = self.coefficients, other.coefficients
        if not (is_decision(a) or is_decision(b)):  # numbers: a common value shape
            xp = array_module(a, b)
            shape = np.broadcast_shapes(a.shape[1:], b.shape[1:])
            a, b = xp.broadcast_to(a, a.shape[:1] + shape), xp.broadcast_to(b, b.shape[:1] + shape)
        m = a.shape[0]
        total = (_combine(a, np.arange(m), None, inverse[:m], len(unique))
                 + _combine(b, np.arange(b.shape[0]), None, inverse[m:], len(unique)))
        return Polynomial._build(unique, total, self.variables, unique=True)

    __radd__ = __add__

    def __neg__(self):
        return Polynomial._build(self.exponent_array, -self.coefficients, self.variables, unique=True)

    def __sub__(self, other):
        return self + (-self._lift(other))

    def __rsub__(self, other):
        return self._lift(other) - self

    def __mul__(self, other):
        other = self._lift(other)
        i, j, unique, inverse = _product_structure(self.exponents, other.exponents, self.num_variables)
        a, b = self.coefficients, other.coefficients
        if is_decision(a) and is_decision(b):
            raise ValueError("product of two polynomials with decision-variable coefficients is "
                             "bilinear; fix one of them (e.g. alternate) to keep the program convex")
        if not (is_decision(a) or is_decision(b)):
            nd = max(a.ndim, b.ndim)
            a = a.reshape(a.shape[:1] + (1,) * (nd - a.ndim) + a.shape[1:])
            b = b.reshape(b.shape[:1] + (1,) * (nd - b.ndim) + b.shape[1:])
            products = a[i] * b[j]
            return Polynomial._build(unique, _combine(products, np.arange(len(products)), None, inverse, len(unique)),
                                     self.variables, unique=True)
        if is_decision(b):  # make `a` the decision side
            a, b, i, j = b, a, j, i
        weights = _concrete(b, "a product")
        if weights.ndim != 1:
            raise ValueError("decision polynomials can only be multiplied by scalar polynomials")
        coefficients = _combine(a, i, weights[j], inverse, len(unique))
        return Polynomial._build(unique, coefficients, self.variables, unique=True)

    __rmul__ = __mul__

    def __truediv__(self, number):
        return self * (1.0 / number)

    def __pow__(self, k: int):
        if not isinstance(k, (int, np.integer)) or k < 0:
            raise ValueError(f"polynomial powers must be non-negative ints, got {k!r}")
        result, base = Polynomial.constant(1.0, self.num_variables, self.variables), self
        while k:
            if k & 1:
                result = result * base
            base, k = base * base, k >> 1
        return result

    def __getitem__(self, index):
        if self.is_decision:
            raise TypeError("decision polynomials are scalar")
        index = index if isinstance(index, tuple) else (index,)
        return Polynomial._build(self.exponent_array, self.coefficients[(slice(None),) + index], self.variables,
                                 unique=True)

    def sum(self) -> Polynomial:
        """The sum of a vector / matrix polynomial's entries."""
        c = self.coefficients
        return Polynomial._build(self.exponent_array, c.reshape(c.shape[0], -1).sum(1), self.variables, unique=True)

    # ----- calculus and composition ---------------------------------------------------------

    def derivative(self, i: int) -> Polynomial:
        r"""$\partial p / \partial z_i$."""
        E = self.exponent_array
        keep = np.flatnonzero(E[:, i] > 0)
        if not len(keep):
            return Polynomial._build(np.zeros((1, self.num_variables), int),
                                     _combine(self.coefficients, np.zeros(0, int), np.zeros(0), np.zeros(0, int), 1),
                                     self.variables, unique=True)
        D = E[keep].copy()
        D[:, i] -= 1  # distinct rows stay distinct
        return Polynomial._build(D, _combine(self.coefficients, keep, E[keep, i].astype(float),
                                             np.arange(len(keep)), len(keep)), self.variables, unique=True)

    def jacobian(self) -> Polynomial:
        r"""$\partial p / \partial z$: value shape (*shape, n) (numeric polynomials)."""
        n = self.num_variables
        total = None
        for i in range(n):
            d = self.derivative(i)
            unit = np.eye(n)[i]
            term = Polynomial._build(d.exponent_array, d.coefficients[..., None] * unit, self.variables, unique=True)
            total = term if total is None else total + term
        return total

    def lie_derivative(self, f: Polynomial) -> Polynomial:
        r"""$\dot p = \sum_i \frac{\partial p}{\partial z_i} f_i(z)$ along the vector field f."""
        if f.shape != (self.num_variables,):
            raise ValueError(f"lie_derivative: the vector field must have shape ({self.num_variables},), "
                             f"got {f.shape}")
        total = Polynomial.constant(0.0, self.num_variables, self.variables)
        for i in range(self.num_variables):
            total = total + self.derivative(i) * f[i]
        return total

    def substitute(self, values: Sequence[Polynomial]) -> Polynomial:
        r"""$p(q_0(w), \dots, q_{n-1}(w))$ for scalar polynomials $q_i$ in new variables w."""
        values = list(values)
        if len(values) != self.num_variables or not all(isinstance(q, Polynomial) for q in values):
            raise ValueError(f"substitute needs {self.num_variables} Polynomials, got {len(values)}")
        w = values[0]
        E = self.exponent_array
        powers = [[Polynomial.constant(1.0, w.num_variables, w.variables)] for _ in values]
        for q, listed, top in zip(values, powers, E.max(0, initial=0)):
            for _ in range(int(top)):
                listed.append(listed[-1] * q)
        columns = []
        for row in E:
            factors = [listed[k] for listed, k in zip(powers, row) if k]
            term = factors[0] if factors else powers[0][0]
            for factor in factors[1:]:
                term = term * factor
            columns.append(term)
        unique, inverse = unique_rows(np.concatenate([t.exponent_array for t in columns]))
        cols = np.repeat(np.arange(len(columns)), [t.num_monomials for t in columns])
        weights = [t.coefficients for t in columns]
        c = self.coefficients
        if self.is_decision or array_module(c, *weights) is np:  # new coefficients = M c, M sparse
            M = _sparse(inverse, cols, np.concatenate([_concrete(t, "substitute") for t in weights]),
                        (len(unique), len(columns)))
            new = c.mapped(M) if self.is_decision else (M @ c.reshape(len(c), -1)).reshape((len(unique),) + c.shape[1:])
            return Polynomial._build(unique, new, w.variables, unique=True)
        M = jnp.zeros((len(unique), len(columns))).at[inverse, cols].add(jnp.concatenate(weights))
        return Polynomial._build(unique, jnp.tensordot(M, c, axes=1), w.variables, unique=True)

    # ----- display ---------------------------------------------------------------------------

    def __repr__(self):
        if self.is_decision or self.shape or isinstance(self.coefficients, jax.core.Tracer):
            return (f"Polynomial({self.num_monomials} monomials in {', '.join(self.variables)}, "
                    f"degree {self.degree}, value shape {self.shape}"
                    f"{', decision coefficients' if self.is_decision else ''})")
        terms = []
        for row, c in zip(self.exponent_array, np.asarray(self.coefficients)):
            if c == 0:
                continue
            mono = "*".join(v if k == 1 else f"{v}^{k}" for v, k in zip(self.variables, row) if k)
            terms.append(f"{c:.6g}" + (f"*{mono}" if mono else ""))
        return " + ".join(terms).replace("+ -", "- ") or "0"


def _combine(c, src, weights, dest, num):
    r"""new[k] = sum over rows r with dest[r] = k of weights[r] * c[src[r]] (weights None = 1)."""
    if is_decision(c):
        return c.combined(dest, src, np.ones(len(src)) if weights is None else weights, num)
    rows = c[src]
    if weights is not None:
        rows = rows * np.asarray(weights).reshape((-1,) + (1,) * (c.ndim - 1))
    if array_module(c) is jnp:
        return jax.ops.segment_sum(rows, jnp.asarray(dest, int), num_segments=num)
    out = np.zeros((num,) + c.shape[1:])
    np.add.at(out, np.asarray(dest, int), rows)
    return out


@functools.lru_cache(maxsize=4096)
def _sum_structure(a: tuple, b: tuple, n: int):
    """(unique rows, inverse) of the exponents of a + b (kept per structure)."""
    unique, inverse = unique_rows(np.concatenate([_exponent_array(a, n), _exponent_array(b, n)]))
    unique.flags.writeable = inverse.flags.writeable = False
    return unique, inverse


@functools.lru_cache(maxsize=4096)
def _product_structure(a: tuple, b: tuple, n: int):
    """(i, j, unique rows, inverse): the monomials of a * b are a[i] + b[j], merged (kept per
    structure)."""
    Ea, Eb = _exponent_array(a, n), _exponent_array(b, n)
    i, j = np.meshgrid(np.arange(len(Ea)), np.arange(len(Eb)), indexing="ij")
    i, j = i.ravel(), j.ravel()
    unique, inverse = unique_rows(Ea[i] + Eb[j])
    for array in (i, j, unique, inverse):
        array.flags.writeable = False
    return i, j, unique, inverse


def _rows_tuple(E) -> tuple:
    return tuple(map(tuple, np.asarray(E).tolist()))


def taylor_polynomial(fn, x0, degree: int, variables: Sequence[str] | None = None, args=()) -> Polynomial:
    r"""The Taylor polynomial of `fn(x, *args)` about `x0`, in the original variables x:

    $$p(x) = \sum_{|\alpha| \le d} \frac{D^\alpha fn(x_0)}{\alpha!}\,(x - x_0)^\alpha,$$

    the derivatives taken by nested forward-mode autodiff (no symbolic package), in one
    compiled program per (fn, degree, argument structure): pass a module-level `fn` and the
    varying data as the pytree `args` (a system, an input) to reuse the compilation. `fn`
    maps an (n,) vector to an array of any shape, which becomes the polynomial's value shape.
    """
    x0 = jnp.asarray(x0, dtype=float)
    n = x0.shape[0]
    tensors = _derivative_tensors(fn, degree, x0, args)
    E = monomial_basis(n, degree)
    coefficients = []
    for alpha in E:
        index = tuple(np.repeat(np.arange(n), alpha))
        scale = float(np.prod([math.factorial(int(a)) for a in alpha]))
        coefficients.append(tensors[len(index)][(Ellipsis,) + index] / scale)
    centered = Polynomial(E, array_module(*coefficients).stack(coefficients), variables)
    shift = [v - c for v, c in zip(Polynomial.variables_of(n, centered.variables), x0)]
    return centered.substitute(shift)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _derivative_tensors(fn, degree, x0, args):
    """[fn(x0), D fn(x0), ..., D^degree fn(x0)] by nested jacfwd."""
    g, tensors = (lambda x: fn(x, *args)), []
    for _ in range(degree + 1):
        tensors.append(jnp.asarray(g(x0)))
        g = jax.jacfwd(g)
    return tensors
