"""The operator at the cell: told what to set by hand (a manual lamp radius, the lens, the reference
part), confirming with Enter on the console."""

from __future__ import annotations

import sys
from typing import TextIO

from cell.core.errors import DeviceFault


class Operator:
    """Tells the operator what to set by hand and waits for Enter; `yes` confirms for them
    (tests, `--yes`), and so does `simulated` (the simulated cell has nobody to act: its lines say
    "(simulated: nothing to confirm)", where --yes's say "(confirmed automatically: --yes)").
    Without either a prompt needs an interactive stdin, else it is a fault."""

    def __init__(self, yes: bool = False, stdin: TextIO | None = None, stdout: TextIO | None = None,
                 simulated: bool = False) -> None:
        self.yes = yes or simulated
        self.simulated, self.given_yes = simulated, yes
        self._stdin, self._stdout = stdin, stdout

    @property
    def stdin(self) -> TextIO:
        return self._stdin or sys.stdin

    @property
    def stdout(self) -> TextIO:
        return self._stdout or sys.stdout

    @property
    def interactive(self) -> bool:
        """Whether someone can answer at stdin: a terminal (not a file, a pipe, or none at all,
        as when started with stdin closed, `<&-`)."""
        try:
            return self.stdin is not None and self.stdin.isatty()
        except (ValueError, OSError):           # a closed or broken stream
            return False

    def require(self, device: str, what: str) -> None:
        """Fail now, before anything moves, if a later prompt could not be answered."""
        if not (self.yes or self.interactive):
            raise DeviceFault(device, f"{what} needs the operator, but stdin is not a terminal: "
                                      "run with --yes to confirm operator steps")

    def confirm(self, device: str, instruction: str) -> None:
        print(f"{device}: {instruction}", file=self.stdout, flush=True)
        if self.yes:
            print("  (confirmed automatically: --yes)" if self.given_yes else "  (simulated: nothing to confirm)",
                  file=self.stdout, flush=True)
            return
        self.require(device, f"'{instruction}'")
        print("  press Enter when done", file=self.stdout, flush=True)
        if not self.stdin.readline():
            raise DeviceFault(device, f"stdin closed before the operator confirmed: {instruction}")
