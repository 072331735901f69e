"""The states of an exploration session, the legal transitions between them, each working
state's time limit and what makes a fault: the finite-state machine that ``controller.session``
runs."""

from __future__ import annotations

from enum import StrEnum

from controller.config import Config
from controller.motion.safety import SafetyViolation, check_force


class State(StrEnum):
    IDLE = "idle"
    CAPTURE = "capture"
    RECONSTRUCT = "reconstruct"
    SELECT = "select"
    APPROACH = "approach"
    TOUCH = "touch"
    REFINE = "refine"
    DONE = "done"
    FAULT = "fault"
    ABORTED = "aborted"


WORKING_STATES = (
    State.CAPTURE,
    State.RECONSTRUCT,
    State.SELECT,
    State.APPROACH,
    State.TOUCH,
    State.REFINE,
)
TRANSITIONS: dict[State, frozenset[State]] = {
    State.IDLE: frozenset({State.CAPTURE}),
    State.CAPTURE: frozenset({State.RECONSTRUCT}),
    State.RECONSTRUCT: frozenset({State.SELECT}),
    State.SELECT: frozenset({State.APPROACH, State.DONE}),
    # Back to select when the planner refuses the motion to a target (it is then excluded).
    State.APPROACH: frozenset({State.TOUCH, State.SELECT}),
    # A refused measurement (a bad height map) skips the refinement.
    State.TOUCH: frozenset({State.REFINE, State.SELECT, State.DONE}),
    State.REFINE: frozenset({State.SELECT, State.DONE}),
    State.DONE: frozenset({State.IDLE}),
    State.FAULT: frozenset({State.IDLE}),
    State.ABORTED: frozenset({State.IDLE}),
}
for _working in WORKING_STATES:
    TRANSITIONS[_working] |= {State.FAULT, State.ABORTED}

STEP_TIMEOUT_S = {
    State.CAPTURE: 30.0,
    State.RECONSTRUCT: 60.0,
    State.SELECT: 60.0,
    State.APPROACH: 180.0,
    State.TOUCH: 180.0,
    State.REFINE: 60.0,
}
"""Wall-clock limit of each working state; past it the session faults."""


class SessionFault(RuntimeError):
    """A session stopped on a fault; the message says which device or check."""


def check_force_or_fault(force_n: float, config: Config) -> None:
    """A force over the limit during a touch is a collision: fault."""
    try:
        check_force(force_n, config.limits)
    except SafetyViolation as violation:
        raise SessionFault(str(violation)) from None
