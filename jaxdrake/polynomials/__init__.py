"""Polynomials: multivariate polynomials with numeric or decision-variable coefficients, monomial
bases, Taylor polynomials by automatic differentiation, and the affine decision algebra of the
convex (sums-of-squares) programs that search over them."""

from ._affine import AffineExpression, DecisionSpace, LinearConstraint, is_decision
from ._polynomial import Polynomial, monomial_basis, taylor_polynomial, unique_rows

__all__ = ["AffineExpression", "DecisionSpace", "LinearConstraint", "Polynomial", "is_decision", "monomial_basis",
           "taylor_polynomial", "unique_rows"]
