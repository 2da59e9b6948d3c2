r"""Decision variables of a convex program, as affine expressions $A y + b$ of one vector y.

A `DecisionSpace` hands out blocks of y; an `AffineExpression` (a scalar or a vector) is a
sparse $A$ and a dense $b$, so the sums, scalings and (sparse) matrix products that polynomial
arithmetic performs on decision coefficients stay sparse linear algebra, and a program is
assembled for its conic solver without a modelling layer in between. Comparisons
(`==`, `<=`, `>=`) make `LinearConstraint`s; after a solve, `expr.value` is the number.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse


class DecisionSpace:
    """The decision vector y of one program: blocks are added as variables are created, and
    `solution` holds y's value once the program is solved."""

    def __init__(self):
        self.size = 0
        self.solution: np.ndarray | None = None

    def new(self, shape=()) -> AffineExpression:
        """A fresh scalar (shape ()) or vector (shape (m,)) of decision variables."""
        shape = (shape,) if isinstance(shape, (int, np.integer)) else tuple(shape)
        if len(shape) > 1:
            raise ValueError(f"decision variables are scalars or vectors, got shape {shape}")
        count = shape[0] if shape else 1
        start, self.size = self.size, self.size + count
        A = scipy.sparse.csr_matrix((np.ones(count), (np.arange(count), start + np.arange(count))),
                                    shape=(count, self.size))
        return AffineExpression(self, A, np.zeros(count), scalar=not shape)


class AffineExpression:
    """$A y + b$: a scalar (`scalar=True`, one row) or a vector of affine functions of the
    decision vector y of `space`. numpy defers its operators to this class."""

    __array_ufunc__ = None  # `array @ expr`, `2.0 * expr`, `x <= expr` come to the methods below

    def __init__(self, space: DecisionSpace, A, b, scalar: bool = False):
        A = A if isinstance(A, scipy.sparse.csr_matrix) else scipy.sparse.csr_matrix(A)
        self.space, self.A, self.b, self.scalar = space, A, np.asarray(b, float), scalar

    # ----- facts -----------------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, ...]:
        return () if self.scalar else (self.A.shape[0],)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self):
        if self.scalar:
            raise TypeError("a scalar decision expression has no length")
        return self.A.shape[0]

    @property
    def value(self):
        """The expression at the program's solution (a float for a scalar)."""
        y = self.space.solution
        if y is None:
            raise ValueError("the program has not been solved: no value yet")
        out = self.A @ y[:self.A.shape[1]] + self.b
        return float(out[0]) if self.scalar else out

    def rows(self, size: int):
        """(A with `size` columns, b): A padded with zero columns for variables made after it."""
        A = self.A
        if A.shape[1] != size:
            A = scipy.sparse.csr_matrix((A.data, A.indices, A.indptr), shape=(A.shape[0], size))
        return A, self.b

    def as_vector(self) -> AffineExpression:
        return AffineExpression(self.space, self.A, self.b)

    def __repr__(self):
        return f"AffineExpression(shape {self.shape}, {self.A.nnz} non-zeros over {self.A.shape[1]} variables)"

    # ----- linear algebra ----------------------------------------------------------------------

    def mapped(self, M) -> AffineExpression:
        """M @ self for a numeric (sparse or dense) matrix M, or a vector M (a scalar result)."""
        if self.scalar:
            raise TypeError("M @ expr needs a vector expression")
        M = np.asarray(M, float) if not scipy.sparse.issparse(M) else M
        if M.ndim == 1:
            return AffineExpression(self.space, scipy.sparse.csr_matrix(M[None]) @ self.A, [M @ self.b], True)
        return AffineExpression(self.space, M @ self.A, M @ self.b)

    __rmatmul__ = mapped

    def _other(self, other):
        """(A, b) of `other` with this expression's row count and the wider column count."""
        if isinstance(other, AffineExpression):
            if other.space is not self.space:
                raise ValueError("decision expressions of two different programs cannot be combined")
            size = max(self.A.shape[1], other.A.shape[1])
            (A, b), (A2, b2) = self.rows(size), other.rows(size)
            if A.shape[0] != A2.shape[0] and 1 not in (A.shape[0], A2.shape[0]):
                raise ValueError(f"shapes {self.shape} and {other.shape} do not match")
            rows = max(A.shape[0], A2.shape[0])  # a one-row side (a scalar) is broadcast
            (A, b), (A2, b2) = ((scipy.sparse.vstack([M] * rows).tocsr(), np.repeat(v, rows)) if M.shape[0] < rows
                                else (M, v) for M, v in ((A, b), (A2, b2)))
            return A, b, A2, b2
        number = np.asarray(other, float)
        if number.ndim > 1 or (number.ndim == 1 and number.shape[0] not in (1, self.A.shape[0])
                               and not self.scalar):
            raise ValueError(f"cannot combine a decision expression of shape {self.shape} with "
                             f"numbers of shape {number.shape}")
        if self.scalar and number.ndim == 1:  # a scalar expression plus a vector of numbers
            rows = number.shape[0]
            return scipy.sparse.vstack([self.A] * rows).tocsr(), np.repeat(self.b, rows), None, number
        return self.A, self.b, None, np.broadcast_to(number, self.b.shape)

    def _new(self, A, b, other=None):
        """The result of combining with `other`: a scalar only if both sides are."""
        scalar = self.scalar and (other.scalar if isinstance(other, AffineExpression) else np.ndim(other) == 0)
        return AffineExpression(self.space, A, b, scalar)

    def __add__(self, other):
        A, b, A2, b2 = self._other(other)
        return self._new(A if A2 is None else A + A2, b + b2, other)

    __radd__ = __add__

    def __neg__(self):
        return AffineExpression(self.space, -self.A, -self.b, self.scalar)

    def __sub__(self, other):
        return self + (-other)

    def __rsub__(self, other):
        return (-self) + other

    def __mul__(self, number):
        """By a number, or a scalar expression by a vector of numbers (a vector expression)."""
        if isinstance(number, AffineExpression):
            raise ValueError("the product of two decision expressions is not affine")
        if np.ndim(number) == 1 and self.scalar:
            column = np.asarray(number, float)[:, None]
            return AffineExpression(self.space, scipy.sparse.csr_matrix(column) @ self.A, column[:, 0] * self.b[0])
        k = float(number)
        return AffineExpression(self.space, k * self.A, k * self.b, self.scalar)

    __rmul__ = __mul__

    def __truediv__(self, number):
        return self * (1.0 / float(number))

    def __getitem__(self, index):
        if self.scalar:
            raise TypeError("a scalar decision expression cannot be indexed")
        rows = np.arange(self.A.shape[0])[index]
        return AffineExpression(self.space, self.A[np.atleast_1d(rows)], self.b[np.atleast_1d(rows)],
                                scalar=np.ndim(rows) == 0)

    def sum(self) -> AffineExpression:
        ones = np.ones(self.A.shape[0])
        return AffineExpression(self.space, scipy.sparse.csr_matrix(ones[None]) @ self.A, [ones @ self.b], True)

    # ----- constraints ---------------------------------------------------------------------------

    def __eq__(self, other):
        return LinearConstraint(self - other, "equal")

    def __le__(self, other):
        return LinearConstraint(other - self, "nonnegative")

    def __ge__(self, other):
        return LinearConstraint(self - other, "nonnegative")

    __hash__ = None


class LinearConstraint:
    """`expression == 0` (kind "equal") or `expression >= 0` (kind "nonnegative"), row-wise."""

    def __init__(self, expression: AffineExpression, kind: str):
        self.expression, self.kind = expression, kind

    def __repr__(self):
        relation = "== 0" if self.kind == "equal" else ">= 0"
        return f"LinearConstraint({self.expression.shape} {relation})"

    def __bool__(self):
        raise TypeError("a constraint on decision variables has no truth value; pass it to "
                        "SosProgram.add_constraint")
