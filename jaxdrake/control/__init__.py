"""Control design: linearization and the LQR family."""

from ._lqr import LQRResult, linearize, lqr
from ._swing_up import (SwitchToLQR, acrobot_spong_controller, cart_pole_swing_up_controller,
                        collocated_pfl)
from ._tvlqr import FiniteHorizonLQRResult, finite_horizon_lqr
from ._riccati import (solve_continuous_are, solve_continuous_lyapunov, solve_discrete_are,
                       solve_discrete_lyapunov)

__all__ = ["FiniteHorizonLQRResult", "LQRResult", "finite_horizon_lqr",
           "SwitchToLQR", "acrobot_spong_controller", "cart_pole_swing_up_controller", "collocated_pfl", "linearize", "lqr", "solve_continuous_are",
           "solve_continuous_lyapunov", "solve_discrete_are", "solve_discrete_lyapunov"]
