"""One run's hold on the devices: whatever ends the run, they are closed, or stopped safely first
(hardware notes), and the operator is told whether motion stopped."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from os import PathLike
from types import TracebackType
from typing import Any, Literal, Protocol

from cell.core.errors import CellError, DeviceFault


class Held(Protocol):
    """What a Session holds: cell.devices.interfaces.Devices (a module that imports this one)."""

    def close(self) -> list[str]: ...

    def safe_stop(self, fault: BaseException | None = None) -> list[str]: ...

    def releases(self) -> tuple[Callable[[], object], ...]: ...


class Session:
    """Owns the devices of one run, `with Session(on_fault) as session: session.devices =
    connect(...)`. A normal end, or a goal not reached (a CellError that is no DeviceFault), closes
    them. A DeviceFault or anything else (a bug, Ctrl-C, SIGTERM) stops them safely first (every
    light channel off too), then releases the arm's, the servos' and the lighting controller's
    connections; `fault` = {device, error, stop_failures, release_failures}, on_fault(fault) is
    called (to log it), and a DeviceFault is raised again saying whether motion stopped and, given
    `log`, where the run's log is."""

    def __init__(self, on_fault: Callable[[dict[str, Any]], object] = lambda fault: None,
                 log: str | PathLike[str] | None = None) -> None:
        self.devices: Held | None = None
        self.fault: dict[str, Any] | None = None
        self.on_fault, self.log = on_fault, log

    def __enter__(self) -> Session:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 traceback: TracebackType | None) -> Literal[False]:
        if err is None or (isinstance(err, CellError) and not isinstance(err, DeviceFault)):
            if self.devices:
                self.devices.close()
            return False
        failures = self.devices.safe_stop(err) if self.devices else []
        released = try_all(self.devices.releases()) if self.devices else []
        self.fault = {"device": getattr(err, "device", None), "error": str(err) or type(err).__name__,
                      "stop_failures": failures, "release_failures": released}
        self.on_fault(self.fault)
        if isinstance(err, DeviceFault):
            where = f"; log in {self.log}" if self.log else ""
            raise DeviceFault(err.device, f"{err.reason}; {stop_outcome(failures)}{where}") from err
        return False


def stop_outcome(failures: list[str]) -> str:
    """What a safe stop achieved, in words an operator must be able to trust."""
    return "motion stopped" if not failures else f"STOP FAILED, check the cell: {'; '.join(failures)}"


def try_all(steps: Iterable[Callable[[], object]]) -> list[str]:
    """Run every step even if one fails; returns the failures' messages, in turn."""
    failures = []
    for step in steps:
        try:
            step()
        except Exception as err:                     # a stop must not prevent the next one
            failures.append(str(err))
    return failures
