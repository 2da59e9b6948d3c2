"""Why a simulation stopped: `SimulationStatus`, its messages, and `SimulationError`."""

from __future__ import annotations

import enum


class SimulationStatus(enum.IntEnum):
    """Why a simulation stopped. SUCCESS and STOPPED_BY_RESET are not failures."""

    SUCCESS = 0
    MAX_STEPS_REACHED = 1
    NONFINITE_STATE = 2
    STEP_SIZE_TOO_SMALL = 3
    TOO_MANY_EVENTS = 4
    CONSTRAINT_PROJECTION_FAILED = 5
    STOPPED_BY_RESET = 6  # a reset asked to stop (the notes' status): not a failure

    @property
    def message(self) -> str:
        """What happened and the usual remedy."""
        return _MESSAGES[self]

    @staticmethod
    def is_success(status):
        """True for SUCCESS and STOPPED_BY_RESET; works on traced and batched status arrays."""
        return (status == SimulationStatus.SUCCESS) | (status == SimulationStatus.STOPPED_BY_RESET)


_MESSAGES = {
    SimulationStatus.SUCCESS: "the final time was reached",
    SimulationStatus.STOPPED_BY_RESET: "a reset stopped the simulation",
    SimulationStatus.MAX_STEPS_REACHED: "max_steps was reached before the final time (raise "
                                        "max_steps or loosen rtol / atol; a stiff system, e.g. strong "
                                        "damping or fast modes, takes far fewer steps with "
                                        "solver='rosenbrock23')",
    SimulationStatus.NONFINITE_STATE: "the state became non-finite (NaN or inf)",
    SimulationStatus.STEP_SIZE_TOO_SMALL: "the step size became too small: a finite-time blow-up "
                                          "(the state growing without bound), a singularity of the "
                                          "dynamics, or a stiff system (try solver='rosenbrock23')",
    SimulationStatus.TOO_MANY_EVENTS: "more than max_events events fired (Zeno behaviour or "
                                      "chattering?)",
    SimulationStatus.CONSTRAINT_PROJECTION_FAILED: "no state satisfying the state constraints "
                                                   "phi(x) = 0 was found near x0",
}


class SimulationError(RuntimeError):
    """A simulation ended with a failure status (raised by non-jitted `simulate` calls)."""

    def __init__(self, status: SimulationStatus, message: str):
        super().__init__(message)
        self.status = status
