"""How a trajectory optimization ended: `SolverStatus` (the sparse programs' IPOPT / SciPy
solves) and `ILQRStatus` (the JAX-native iLQR), each carrying its message and the usual remedy,
as `jaxdrake.SimulationStatus` does."""

from __future__ import annotations

from .._status import StatusCode


class SolverStatus(StatusCode):
    """How a nonlinear program's solve ended (IPOPT's return codes, and SciPy's mapped onto
    them). SOLVED and SOLVED_TO_ACCEPTABLE_LEVEL are successes."""

    SOLVED = 0
    SOLVED_TO_ACCEPTABLE_LEVEL = 1
    INFEASIBLE = 2
    SEARCH_DIRECTION_TOO_SMALL = 3
    DIVERGING_ITERATES = 4
    USER_REQUESTED_STOP = 5
    FEASIBLE_POINT_FOUND = 6
    MAXIMUM_ITERATIONS = 7
    RESTORATION_FAILED = 8
    ERROR_IN_STEP_COMPUTATION = 9
    MAXIMUM_TIME = 10
    NOT_ENOUGH_DEGREES_OF_FREEDOM = 11
    INVALID_PROBLEM = 12
    NONFINITE = 13
    CONSTRAINTS_VIOLATED = 14
    SOLVER_ERROR = 15



SolverStatus.describe({
    SolverStatus.SOLVED: "solved",
    SolverStatus.SOLVED_TO_ACCEPTABLE_LEVEL: "solved to acceptable level (IPOPT's looser acceptable_tol, "
                                             "after it stalled short of tol)",
    SolverStatus.INFEASIBLE: "infeasible problem detected: the iterates converged to a point of locally "
                             "least constraint violation (check that the bounds and the final state can be "
                             "met, e.g. within the duration and the input limits, or give a closer initial "
                             "guess)",
    SolverStatus.SEARCH_DIRECTION_TOO_SMALL: "search direction becomes too small (the iterate stalled; "
                                             "loosen tol or rescale the problem)",
    SolverStatus.DIVERGING_ITERATES: "diverging iterates (bound the states, the inputs or the duration)",
    SolverStatus.USER_REQUESTED_STOP: "user requested stop",
    SolverStatus.FEASIBLE_POINT_FOUND: "feasible point found (IPOPT stopped at the first feasible point, "
                                       "as an option asked)",
    SolverStatus.MAXIMUM_ITERATIONS: "maximum iterations exceeded (raise max_iterations, or give a closer "
                                     "initial guess)",
    SolverStatus.RESTORATION_FAILED: "restoration failed: no step reduced the constraint violation (give "
                                     "a closer initial guess, or check that the constraints can be met)",
    SolverStatus.ERROR_IN_STEP_COMPUTATION: "error in step computation (a singular or badly scaled "
                                            "linear system; rescale the problem)",
    SolverStatus.MAXIMUM_TIME: "maximum CPU or wall time exceeded",
    SolverStatus.NOT_ENOUGH_DEGREES_OF_FREEDOM: "not enough degrees of freedom: more equality constraints "
                                                "than free variables (fix fewer states or free the duration)",
    SolverStatus.INVALID_PROBLEM: "invalid problem definition or option (see the solver's log: verbose=True)",
    SolverStatus.NONFINITE: "invalid number detected (NaN or inf in a cost, a constraint or a derivative "
                            "at an iterate: check the functions' domains, e.g. a log or a sqrt)",
    SolverStatus.CONSTRAINTS_VIOLATED: "the solver stopped at a point that violates the constraints by more "
                                       "than the tolerance (infeasible from this guess, or it needs more "
                                       "iterations)",
    SolverStatus.SOLVER_ERROR: "the solver failed (see its log: verbose=True)",
}, successes=(SolverStatus.SOLVED, SolverStatus.SOLVED_TO_ACCEPTABLE_LEVEL))


class ILQRStatus(StatusCode):
    """How an `ilqr` solve ended. Only SUCCESS is a success."""

    SUCCESS = 0
    NONFINITE = 1
    MAXIMUM_ITERATIONS = 2
    GOAL_NOT_REACHED = 3


ILQRStatus.describe({
    ILQRStatus.SUCCESS: "converged: the cost stopped changing (tol) with the goal met (constraint_tol)",
    ILQRStatus.NONFINITE: "the cost or the knot states are not finite (NaN or inf): a non-finite x0, a rollout "
                          "that blew up or a cost undefined there (a shorter time step, a smaller input guess, "
                          "or bounds)",
    ILQRStatus.MAXIMUM_ITERATIONS: "max_iterations iLQR iterations were spent before convergence (raise "
                                   "max_iterations, or give a closer input guess)",
    ILQRStatus.GOAL_NOT_REACHED: "the final state misses the goal by more than constraint_tol after "
                                 "max_outer multiplier updates (raise max_outer or penalty, lengthen the "
                                 "horizon, or widen the input bounds)",
})


def messages(status_type: type[StatusCode], status):
    """The message of a status code, or an array of them (the shape of `status`) for a batch."""
    return status_type.message_of(status)
