"""Why a simulation stopped: `SimulationStatus`, its messages, and `SimulationError`."""

from __future__ import annotations

from .._status import StatusCode


class SimulationStatus(StatusCode):
    """Why a simulation stopped. SUCCESS and STOPPED_BY_RESET are not failures."""

    SUCCESS = 0
    MAX_STEPS_REACHED = 1
    NONFINITE_STATE = 2
    STEP_SIZE_TOO_SMALL = 3
    TOO_MANY_EVENTS = 4
    CONSTRAINT_PROJECTION_FAILED = 5
    STOPPED_BY_RESET = 6  # a reset asked to stop (the notes' status): not a failure
    INVALID_TIME_SPAN = 7
    NONFINITE_INITIAL_STATE = 8
    NONFINITE_INPUT = 9
    NAN_PARAMETER = 10



SimulationStatus.describe({
    SimulationStatus.SUCCESS: "the final time was reached",
    SimulationStatus.STOPPED_BY_RESET: "a reset stopped the simulation",
    SimulationStatus.MAX_STEPS_REACHED: "max_steps was reached before the final time (raise "
                                        "max_steps or loosen rtol / atol; a stiff system, e.g. strong "
                                        "damping, fast modes or stiff contact, takes far fewer steps "
                                        "with a stiff solver)",
    SimulationStatus.NONFINITE_STATE: "the state became non-finite (NaN or inf)",
    SimulationStatus.STEP_SIZE_TOO_SMALL: "the step size became too small: a finite-time blow-up "
                                          "(the state growing without bound), a singularity of the "
                                          "dynamics, or a stiff system (try a stiff solver)",
    SimulationStatus.TOO_MANY_EVENTS: "more than max_events events fired (Zeno behaviour or "
                                      "chattering?)",
    SimulationStatus.CONSTRAINT_PROJECTION_FAILED: "no state satisfying the state constraints "
                                                   "phi(x) = 0 was found near x0",
    SimulationStatus.INVALID_TIME_SPAN: "the time span (t0, tf) is not finite with t0 < tf: nothing was "
                                        "simulated",
    SimulationStatus.NONFINITE_INITIAL_STATE: "the initial state x0 is not finite (NaN or inf): nothing "
                                              "was simulated",
    SimulationStatus.NONFINITE_INPUT: "the input u(t0) is not finite (NaN or inf): nothing was simulated "
                                      "(check the input tape or function)",
    SimulationStatus.NAN_PARAMETER: "a parameter of the system is NaN: nothing was simulated (check "
                                    "the values given to the system, e.g. under vmap)",
}, successes=(SimulationStatus.SUCCESS, SimulationStatus.STOPPED_BY_RESET))


class SimulationError(RuntimeError):
    """A simulation ended with a failure status (raised by non-jitted `simulate` calls)."""

    def __init__(self, status: SimulationStatus, message: str):
        super().__init__(message)
        self.status = status
