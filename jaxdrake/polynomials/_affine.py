r"""Decision variables of a convex program, as affine expressions $A y + b$ of one vector y.

A `DecisionSpace` hands out blocks of y; an `AffineExpression` (a scalar or a vector) is a
matrix $A$ and a dense $b$, so the sums, scalings and matrix products that polynomial
arithmetic performs on decision coefficients are linear algebra, and a program is assembled
for its conic solver without a modelling layer in between. $A$ is a dense array while the
program has at most `DENSE_COLUMNS` decisions (numpy on small matrices costs microseconds,
each scipy.sparse construction tens of them) and sparse (CSR) beyond. Comparisons
(`==`, `<=`, `>=`) make `LinearConstraint`s; after a solve, `expr.value` is the number.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse

DENSE_COLUMNS = 1024


def _matrix(A, size: int):
    """A with `size` columns (zero columns for variables made after it): a dense array while
    size <= DENSE_COLUMNS, CSR beyond."""
    if size <= DENSE_COLUMNS:
        A = A.toarray() if scipy.sparse.issparse(A) else A
        return A if A.shape[1] == size else np.concatenate([A, np.zeros((A.shape[0], size - A.shape[1]))], 1)
    A = A.tocsr() if scipy.sparse.issparse(A) else scipy.sparse.csr_matrix(A)
    return A if A.shape[1] == size else scipy.sparse.csr_matrix((A.data, A.indices, A.indptr),
                                                                shape=(A.shape[0], size))


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
        if self.size <= DENSE_COLUMNS:
            A = np.eye(count, self.size, start)
        else:
            A = scipy.sparse.csr_matrix((np.ones(count), (np.arange(count), start + np.arange(count))),
                                        shape=(count, self.size))
        return AffineExpression(self, A, np.zeros(count), scalar=not shape)


class AffineExpression:
    """$A y + b$: a scalar (`scalar=True`, one row) or a vector of affine functions of the
    decision vector y of `space`. numpy defers its operators to this class."""

    __array_ufunc__ = None  # `array @ expr`, `2.0 * expr`, `x <= expr` come to the methods below

    def __init__(self, space: DecisionSpace, A, b, scalar: bool = False):
        A = A.tocsr() if scipy.sparse.issparse(A) else np.asarray(A, float)
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
        """(A with `size` columns, b): A padded with zero columns for variables made after it
        (dense or CSR by `size`, see `_matrix`)."""
        return _matrix(self.A, size), self.b

    def as_vector(self) -> AffineExpression:
        return AffineExpression(self.space, self.A, self.b)

    def __repr__(self):
        nonzeros = self.A.nnz if scipy.sparse.issparse(self.A) else np.count_nonzero(self.A)
        return f"AffineExpression(shape {self.shape}, {nonzeros} non-zeros over {self.A.shape[1]} variables)"

    # ----- linear algebra ----------------------------------------------------------------------

    def mapped(self, M) -> AffineExpression:
        """M @ self for a numeric (sparse or dense) matrix M, or a vector M (a scalar result)."""
        if self.scalar:
            raise TypeError("M @ expr needs a vector expression")
        M = np.asarray(M, float) if not scipy.sparse.issparse(M) else M
        vector = M.ndim == 1
        M = M[None] if vector else M
        if scipy.sparse.issparse(self.A) and not scipy.sparse.issparse(M):
            M = scipy.sparse.csr_matrix(M)  # keep a sparse expression sparse
        A = M @ self.A
        return AffineExpression(self.space, A, M @ self.b, vector)

    def combined(self, dest, src, weights, num: int) -> AffineExpression:
        """new[k] = sum over r with dest[r] = k of weights[r] * self[src[r]] (num rows): the
        merges, products and derivatives of polynomial arithmetic."""
        shape = (num, self.A.shape[0])
        if scipy.sparse.issparse(self.A):
            return self.mapped(scipy.sparse.csr_matrix((np.asarray(weights, float), (dest, src)), shape=shape))
        M = np.zeros(shape)
        np.add.at(M, (dest, src), weights)
        return self.mapped(M)

    __rmatmul__ = mapped

    def _aligned(self, other):
        """(A, b, A2, b2): this expression's rows and `other`'s (A2 None for numbers) over a
        common set of columns, a one-row side (a scalar) repeated to the other's length."""
        if isinstance(other, AffineExpression):
            if other.space is not self.space:
                raise ValueError("decision expressions of two different programs cannot be combined")
            size = max(self.A.shape[1], other.A.shape[1])
            (A, b), (A2, b2) = self.rows(size), other.rows(size)
            lengths = (A.shape[0], A2.shape[0])
        else:
            A, b, A2, b2 = self.A, self.b, None, np.asarray(other, float)
            if b2.ndim > 1:
                raise ValueError(f"cannot combine a decision expression of shape {self.shape} with "
                                 f"numbers of shape {b2.shape}")
            lengths = (A.shape[0], b2.size)
        rows = max(lengths)
        if min(lengths) not in (1, rows):
            raise ValueError(f"shapes {self.shape} and {np.shape(other)} do not match")
        if A.shape[0] < rows:
            A, b = _times_column(A, b, np.ones(rows))
        if A2 is None:
            return A, b, None, np.broadcast_to(b2, (rows,))
        if A2.shape[0] < rows:
            A2, b2 = _times_column(A2, b2, np.ones(rows))
        return A, b, A2, b2

    def _new(self, A, b, other=None):
        """The result of combining with `other`: a scalar only if both sides are."""
        scalar = self.scalar and (other.scalar if isinstance(other, AffineExpression) else np.ndim(other) == 0)
        return AffineExpression(self.space, A, b, scalar)

    def __add__(self, other):
        A, b, A2, b2 = self._aligned(other)
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
            return AffineExpression(self.space, *_times_column(self.A, self.b, np.asarray(number, float)))
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
        return self.mapped(np.ones(self.A.shape[0]))

    # ----- constraints ---------------------------------------------------------------------------

    def __eq__(self, other):
        return LinearConstraint(self - other, "equal")

    def __le__(self, other):
        return LinearConstraint(other - self, "nonnegative")

    def __ge__(self, other):
        return LinearConstraint(self - other, "nonnegative")

    __hash__ = None


def is_decision(c) -> bool:
    """Whether `c` is an affine expression of decision variables, not a number."""
    return isinstance(c, AffineExpression)


def _times_column(A, b, column):
    """The one-row (A, b) times the numbers `column`: one row per number."""
    if scipy.sparse.issparse(A):
        return scipy.sparse.csr_matrix(column[:, None]) @ A, column * b[0]
    return column[:, None] * A, column * b[0]


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
