"""How a run or a step ends: the run statuses and the failure of a step at one time step."""

from __future__ import annotations

STATUS_COMPLETED = "completed"
STATUS_FAILED = "failed"
STATUS_CANCELLED = "cancelled"


class StepFailure(RuntimeError):
    """A step did not converge at this time step (the caller cuts Δt).

    `reason` names the cause for the step's diagnostics (the histogram of Δt cuts):
    `open_close` (the iteration did not converge), `held_contacts`, `reversed_friction`,
    `spring_energy`, `solve`, `displacement`, `penetration`, or `time_step` (no Δt left).
    """

    def __init__(self, message: str, reason: str = "open_close") -> None:
        super().__init__(message)
        self.reason = reason
