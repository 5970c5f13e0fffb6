"""One result shape for every routine (`cell run`, the calibrations, `cell measure-brdf`), like
scipy's OptimizeResult: each result file a routine writes (report.json, calibration.json,
measurement.json) carries the same verdict keys, beside the routine's own (docs/formats.md,
"Result files"):

    success   true when the routine reached its goal (exit 0)
    status    one word of STATUSES
    message   why not, one line ("" on success)
    cause     a short key of why not (a run's loop.CAUSES key, a calibration's; "fault",
              "infeasible", "interrupted"), null on success or when the status says all
    fault     the device fault with its safe stop's outcome (devices.session), else null
    counters  what the routine counted: iterations, captures, frames, poses, views...
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, TypeVar, cast

STATUSES = {
    "converged": "a run: every feature pixel in its gray band",
    "calibrated": "a calibration: its fit made (and its file written)",
    "measured": "measure-brdf: the material fitted and written",
    "not_converged": "a run ended without the goal (cause: why)",
    "not_calibrated": "a calibration's series or views could not be fitted (cause: why)",
    "not_measured": "measure-brdf: too few readings to fit (cause: why)",
    "infeasible": "the plan (or a re-plan) cannot meet the requirements",
    "fault": "a device fault ended it, after the safe stop of every device",
    "interrupted": "anything else ended it: an unexpected error",
}
ENDINGS = ("fault", "infeasible", "interrupted")   # causes that are their own status

R = TypeVar("R", bound="Result")
T = TypeVar("T")


class Result:
    """The verdict every routine's result carries: `success`, `message`, `cause` and `fault`
    (the subclass's dataclass fields), `status` (derived: SUCCEEDED on success, else the ending's
    cause when it is one of ENDINGS or there was a fault, else NOT_REACHED) and `counters`.
    to_json() is the routine's own keys (`details`) and the verdict's."""

    SUCCEEDED: ClassVar[str] = "converged"
    NOT_REACHED: ClassVar[str] = "not_converged"

    success: bool
    message: str
    cause: str | None
    fault: dict[str, Any] | None

    @property
    def status(self) -> str:
        if self.success:
            return self.SUCCEEDED
        if self.fault:
            return "fault"
        return self.cause if self.cause in ENDINGS else self.NOT_REACHED

    @property
    def counters(self) -> dict[str, int]:
        """What the routine counted (names as its file's lists say them)."""
        raise NotImplementedError

    def details(self) -> dict[str, Any]:
        """The routine's own keys of its result file."""
        raise NotImplementedError

    def ended(self: R, cause: str | None) -> R:
        """This result with `cause` (cell.report.recorder.Ending's) when it names none of its own
        (the subclass is a frozen dataclass with a `cause` field)."""
        return self if self.cause or not cause else dataclasses.replace(cast(Any, self), cause=cause)

    def _made(self, value: T | None, what: str) -> T:
        """value, a field a routine fills when it succeeds (`what` names it, for the error): for the
        properties that give a successful result's fit or file without its Optional. Raises
        ValueError, with the verdict, on a result that has none (the routine did not succeed)."""
        if value is None:
            why = f": {self.message}" if self.message else ""
            raise ValueError(f"no {what}: the routine ended {self.status}{why}")
        return value

    def verdict(self) -> dict[str, Any]:
        """success, status, message, cause, fault and counters: the same keys in every result file."""
        return {"success": self.success, "status": self.status, "message": self.message, "cause": self.cause,
                "fault": self.fault, "counters": self.counters}

    def to_json(self) -> dict[str, Any]:
        """details(), the verdict and `reason` (the message, as result files said it before the
        verdict was shared)."""
        return self.details() | self.verdict() | {"reason": self.message}
