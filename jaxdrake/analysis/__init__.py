"""Analysis: Lyapunov functions, sums-of-squares programs, regions of attraction, and the
conversions of systems into polynomial systems that they need. (Imports cvxpy.)"""

from ._lyapunov import (RegionOfAttraction, common_lyapunov_function, global_lyapunov_function,
                        polynomial_dynamics, region_of_attraction, sample_sublevel_set,
                        verify_region_of_attraction)
from ._sos import CertificateCheck, InfeasibleError, SolveError, SosProgram, SosResult, gram_basis
from ..control import solve_continuous_lyapunov, solve_discrete_lyapunov

__all__ = ["CertificateCheck", "InfeasibleError", "RegionOfAttraction", "SolveError", "SosProgram",
           "SosResult", "common_lyapunov_function", "global_lyapunov_function", "gram_basis",
           "polynomial_dynamics", "region_of_attraction", "sample_sublevel_set",
           "solve_continuous_lyapunov", "solve_discrete_lyapunov", "verify_region_of_attraction"]
