"""Analysis: limit cycles, Lyapunov functions, sums-of-squares programs, regions of attraction, and the
conversions of systems into polynomial systems that they need."""

from ._limit_cycle import LimitCycle, LimitCycleError, limit_cycle
from ._conversions import taylor_polynomial_system, to_trig_coordinates, trig_polynomial_system
from ._lyapunov import (RegionOfAttraction, common_lyapunov_function, global_lyapunov_function,
                        RegionOfAttractionSearch, polynomial_dynamics, region_of_attraction,
                        sample_sublevel_set, search_region_of_attraction,
                        verify_region_of_attraction)
from ._conic import ConicProgram, ConicResult, ConicStatus, InfeasibleError, SolveError
from ._sos import CertificateCheck, SosProgram, SosResult, gram_basis
from ..control import solve_continuous_lyapunov, solve_discrete_lyapunov

__all__ = ["CertificateCheck", "ConicProgram", "ConicResult", "ConicStatus", "InfeasibleError", "LimitCycle", "LimitCycleError", "limit_cycle", "RegionOfAttraction", "RegionOfAttractionSearch", "SolveError", "SosProgram",
           "SosResult", "common_lyapunov_function", "global_lyapunov_function", "gram_basis",
           "polynomial_dynamics", "region_of_attraction", "sample_sublevel_set", "search_region_of_attraction",
           "solve_continuous_lyapunov", "solve_discrete_lyapunov", "taylor_polynomial_system",
           "to_trig_coordinates", "trig_polynomial_system", "verify_region_of_attraction"]
