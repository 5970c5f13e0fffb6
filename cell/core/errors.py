"""The project's one exception hierarchy; the CLI turns each into one line and an exit code."""

from __future__ import annotations

from os import PathLike


class CellError(Exception):
    """Base of every error the CLI reports as one line."""

    exit_code = 1
    _said: str | None = None

    @property
    def said(self) -> str:
        """The line a person reads on the terminal: the message (str), unless the error was given
        other words for people than its message, which result files keep (PlanInfeasible)."""
        return self._said or str(self)


class TaskError(CellError):
    """Bad input: a task, mesh, material table, data file or CLI argument (exit 2)."""

    exit_code = 2

    def __init__(self, file: str | PathLike[str], key: str, found: object, expected: object) -> None:
        self.file, self.key, self.found, self.expected = str(file), key, found, expected
        where = f"{_one_line(self.file)}: {_one_line(key)}" if key else _one_line(self.file)
        super().__init__(f"{where}: found {_one_line(found)}, expected {_one_line(expected)}")

    def __reduce__(self) -> tuple[type[TaskError], tuple[str, str, object, object]]:
        """Pickled by its own arguments: a Dask worker's error comes back to the client whole."""
        return type(self), (self.file, self.key, self.found, self.expected)


def _one_line(text):
    """text with control characters escaped (a key written as "a\nb" in a file), so that an
    error stays one line."""
    text = str(text)
    return text if text.isprintable() else text.encode("unicode_escape").decode("ascii")


class PlanInfeasible(CellError):
    """Physics says no: the goal cannot be reached with the given cell (exit 1). `message` names
    the binding requirement as plan.json does (result files keep it); `said`, where given, is the
    line in words for the terminal (cell.report.words.reason)."""

    exit_code = 1

    def __init__(self, message: str, said: str | None = None) -> None:
        self._said = said
        super().__init__(message)

    def __reduce__(self) -> tuple[type[PlanInfeasible], tuple[str, str | None]]:
        return type(self), (str(self), self._said)


class GoalNotReached(CellError):
    """The closed loop ran but the feature's gray did not reach the band; says why (exit 1) and,
    where the loop decided it, names the cause (cell.run.loop.CAUSES)."""

    exit_code = 1

    def __init__(self, message: str, cause: str | None = None, said: str | None = None) -> None:
        self.cause, self._said = cause, said
        super().__init__(message)

    def __reduce__(self) -> tuple[type[GoalNotReached], tuple[str, str | None, str | None]]:
        return type(self), (str(self), self.cause, self._said)


class DeviceFault(CellError):
    """A device failed or refused a command; motion has been stopped (exit 3)."""

    exit_code = 3

    def __init__(self, device: str, reason: str) -> None:
        self.device, self.reason = device, reason
        super().__init__(f"{device}: {reason}")

    def __reduce__(self) -> tuple[type[DeviceFault], tuple[str, str]]:
        return type(self), (self.device, self.reason)
