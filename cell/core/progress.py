"""Long work's progress as a person reads it (issue 29, item 7): on a terminal one live bar per
stage (tqdm), redrawn in place; anywhere else (a log file, CI, a pipe) a plain line at each
quarter of a stage (only its end when it has 8 steps or fewer), so that a run of hundreds of
poses leaves four lines, not hundreds, and no control characters.

`Progress(stream)` decides once, by `stream.isatty()`; `progress.say(line)` is a line that stays
(printed above the live bars), `with progress.stage("poses", 183) as stage: stage.advance()` a
stage (`for x in stage.each(xs)` advances a step as each x's work ends); `stage.note(text)` a
detail beside the live bar only (a terminal's, never a line); a stage whose total grows as work is
found (`stage.grow(n)`, planning's jobs) counts its quarters of the total known at the time.
Several stages may run at once (planning's overlap): tqdm stacks their bars."""

from __future__ import annotations

import io
import sys
import time
from collections.abc import Iterable, Iterator
from types import TracebackType
from typing import Literal, TextIO, TypeVar

T = TypeVar("T")

QUARTERS = 4        # plain lines per stage: at 25, 50, 75 and 100 % (a stage of 8 steps or fewer: its end)


class Progress:
    """Where long work says how far it is: bars on a terminal, a few plain lines elsewhere."""

    def __init__(self, stream: TextIO | None = None, terminal: bool | None = None, label: str = "") -> None:
        self.stream = stream if stream is not None else sys.stderr
        if terminal is None:
            isatty = getattr(self.stream, "isatty", None)
            terminal = bool(isatty and isatty())
        self.terminal = terminal
        self.label = label
        self.live: Stage | None = None        # the stage last begun and not yet closed

    @classmethod
    def silent(cls) -> Progress:
        """A Progress nobody reads (a library call's default)."""
        return cls(io.StringIO(), terminal=False)

    def labelled(self, label: str) -> Progress:
        """The same stream, every line and stage name after `label` ("hinge: ", one task of several)."""
        return Progress(self.stream, self.terminal, self.label + label)

    def say(self, line: str) -> None:
        """A line that stays: above the live bars on a terminal (tqdm redraws them below it)."""
        if self.terminal:
            from tqdm import tqdm
            tqdm.write(self.label + line, file=self.stream)
        else:
            print(self.label + line, file=self.stream, flush=True)

    def stage(self, name: str, total: int) -> Stage:
        """A stage of `total` steps named `name` ("poses", "lamp searches")."""
        return Stage(self, self.label + name, total)


class Stage:
    """One stage's bar (terminal) or its quarter lines ("poses: 46 of 183 (25 %)"); closed by its
    `with` block, the last line saying the count and the time taken."""

    def __init__(self, progress: Progress, name: str, total: int) -> None:
        self.progress, self.name, self.total = progress, name, max(int(total), 0)
        self.done, self.said, self.start, self.closed = 0, 0, time.perf_counter(), False
        self.bar = None
        if progress.terminal:
            from tqdm import tqdm
            self.bar = tqdm(total=self.total, desc=name, file=progress.stream, leave=True, dynamic_ncols=True,
                            mininterval=0.2)
        progress.live = self

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 traceback: TracebackType | None) -> Literal[False]:
        self.close()
        return False

    def grow(self, n: int) -> None:
        """n more steps found (a job handing on further jobs)."""
        self.total += n
        if self.bar is not None:
            self.bar.total = self.total
            self.bar.refresh()

    def note(self, text: str) -> None:
        """A detail beside the live bar (what the step now running does); nothing off a terminal."""
        if self.bar is not None:
            self.bar.set_postfix_str(text[:60], refresh=False)

    def each(self, items: Iterable[T]) -> Iterator[T]:
        """The items, a step advanced as each one's work ends (when the next is asked for)."""
        for item in items:
            yield item
            self.advance()

    def advance(self, n: int = 1) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
            return
        quarter = QUARTERS * self.done // self.total if self.total else QUARTERS
        if quarter > self.said and self.done < self.total and self.total > 2 * QUARTERS:
            self.said = quarter
            self._line(f"{self.name}: {self.done} of {self.total} ({100 * self.done // self.total} %)")

    def close(self) -> None:
        """The stage's end (once; again does nothing): the bar left as it stands, or its last plain
        line (the count and the time taken)."""
        if self.closed:
            return
        self.closed = True
        if self.progress.live is self:
            self.progress.live = None
        if self.bar is not None:
            self.bar.close()
        else:
            self._line(f"{self.name}: {self.done} of {self.total} in {time.perf_counter() - self.start:.1f} s")

    def _line(self, text: str) -> None:
        print(text, file=self.progress.stream, flush=True)
