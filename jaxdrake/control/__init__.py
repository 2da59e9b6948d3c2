"""Control design: linearization, the LQR family, and model-predictive control."""

from ._lqr import LQRResult, LQRStatus, linearize, lqr
from ._mpc import (MPPI, LinearMPC, NonlinearMPC, RecedingHorizonController, linear_mpc, mppi, nonlinear_mpc,
                   rollout_cost, zero_order_hold)
from ._qp import QPSolution, QPStatus, QPWorkspace, qp_workspace, solve_qp
from ._swing_up import (SwitchToLQR, acrobot_spong_controller, cart_pole_swing_up_controller,
                        collocated_pfl)
from ._tvlqr import FiniteHorizonLQRResult, finite_horizon_lqr, nominal_at
from ._riccati import (solve_continuous_are, solve_continuous_lyapunov, solve_discrete_are,
                       solve_discrete_lyapunov)

__all__ = ["nominal_at", "FiniteHorizonLQRResult", "LQRResult", "LQRStatus", "finite_horizon_lqr",
           "LinearMPC", "MPPI", "NonlinearMPC", "QPSolution", "QPStatus", "QPWorkspace", "RecedingHorizonController",
           "linear_mpc", "mppi", "nonlinear_mpc", "qp_workspace", "rollout_cost", "solve_qp", "zero_order_hold",
           "SwitchToLQR", "acrobot_spong_controller", "cart_pole_swing_up_controller", "collocated_pfl", "linearize", "lqr", "solve_continuous_are",
           "solve_continuous_lyapunov", "solve_discrete_are", "solve_discrete_lyapunov"]
