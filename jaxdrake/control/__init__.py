"""Control design: linearization and the LQR family."""

from ._lqr import LQRResult, linearize, lqr
from ._tvlqr import FiniteHorizonLQRResult, finite_horizon_lqr
from ._riccati import solve_continuous_are, solve_discrete_are

__all__ = ["FiniteHorizonLQRResult", "LQRResult", "finite_horizon_lqr", "linearize", "lqr", "solve_continuous_are", "solve_discrete_are"]
