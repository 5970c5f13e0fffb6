"""Several sequential searches run in lockstep in one thread: each written as a generator that
yields the point whose value it needs, or a batch of points, and is sent that value, or theirs
(cell.planning.nelder_mead: scipy's Nelder-Mead step for step), every round what all the searches
still running ask answered by one batched call. A search's refinement starts thus share their
evaluations (one kernel launch and one pass of the requirements over all their poses a round).
Each search sees the values it would have seen alone when a point's value does not depend on the
other points in its batch (a candidate's row reads its own lamp alone).

One thread, not one per search: an evaluation of a few poses costs about a millisecond of Python,
and handing the GIL from thread to thread at every point costs a good part of that (120
searches of some 80 us a point in groups of 4 took longer in threads than one at a time)."""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterable, Sequence
from typing import TypeVar

Result = TypeVar("Result")
Point = TypeVar("Point")
Value = TypeVar("Value")


def drive(searches: Sequence[Generator[Point, Value, Result]],
          batch: Callable[[list[tuple[int, Point]]], Iterable[Value]]) -> list[Result]:
    """Each search's return value, the searches (generators that yield a point, or a batch of
    points, and are sent its value, or theirs) in lockstep in this thread: each round, what every
    unfinished search asks answered by one batch([(search's index, what it asks), ...]) call, an
    answer each, in order. Each search sees the values it would have seen alone when a point's
    value does not depend on the others in its batch."""
    results: list[Result | None] = [None] * len(searches)
    asked: dict[int, Point] = {}

    def advance(k: int, value: Value | None) -> None:
        try:
            asked[k] = next(searches[k]) if value is None else searches[k].send(value)
        except StopIteration as stop:
            results[k] = stop.value
            asked.pop(k, None)

    for k in range(len(searches)):
        advance(k, None)
    while asked:
        order = sorted(asked)
        for k, value in zip(order, list(batch([(k, asked[k]) for k in order]))):
            advance(k, value)
    return results      # type: ignore[return-value]  # every search returned: set
