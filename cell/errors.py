"""The project's one exception hierarchy; the CLI turns each into one line and an exit code."""


class CellError(Exception):
    """Base of every error the CLI reports as one line."""

    exit_code = 1


class TaskError(CellError):
    """Bad input: a task, mesh, material table, data file or CLI argument (exit 2)."""

    exit_code = 2

    def __init__(self, file, key, found, expected):
        self.file, self.key, self.found, self.expected = str(file), key, found, expected
        where = f"{self.file}: {key}" if key else self.file
        super().__init__(f"{where}: found {found}, expected {expected}")


class PlanInfeasible(CellError):
    """Physics says no: the goal cannot be reached with the given cell (exit 1)."""

    exit_code = 1


class GoalNotReached(CellError):
    """The closed loop ran but the feature's gray did not reach the band; says why (exit 1)."""

    exit_code = 1


class DeviceFault(CellError):
    """A device failed or refused a command; motion has been stopped (exit 3)."""

    exit_code = 3

    def __init__(self, device, reason):
        self.device, self.reason = device, reason
        super().__init__(f"{device}: {reason}")
