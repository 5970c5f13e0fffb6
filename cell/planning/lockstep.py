"""Several sequential solvers (each asking its objective one point at a time, as scipy's
Nelder-Mead does) run in lockstep: each in a thread of its own, every objective call waits until
each solver still running has asked for one, and one batched call answers them all. A search's
refinement starts thus share one kernel launch per step instead of one each. Each solver sees
the values it would have seen alone when the batch's value of a point does not depend on the
other points in it (a candidate's row reads its own lamp alone).

Where each evaluation is cheap (the certificates' specular points: a closest-point query and a
few vector operations), handing the GIL from thread to thread at every point costs more than the
launches it saves: `drive` runs searches written as generators (cell.planning.nelder_mead) in
lockstep in the caller's thread instead."""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator, Iterable, Sequence
from typing import Any, Generic, TypeVar

Result = TypeVar("Result")
Point = TypeVar("Point")
Objective = Callable[[Any], float]


class _Batcher:
    """Collects one point from each running solver, then evaluates them in one `batch` call."""

    def __init__(self, batch: Callable[[list[Any]], Iterable[float]], running: int) -> None:
        self.batch, self.running = batch, running
        self.asked: dict[int, Any] = {}
        self.answers: dict[int, float] = {}
        self.error: BaseException | None = None
        self.round = 0
        self.lock = threading.Condition()

    def ask(self, solver: int, point: Any) -> float:
        with self.lock:
            self.asked[solver] = point
            current = self.round
            self._evaluate_if_complete()
            while self.round == current:
                self.lock.wait()
            if self.error is not None:
                raise self.error
            return self.answers.pop(solver)

    def finished(self) -> None:
        """A solver has returned (or raised): the others no longer wait for it."""
        with self.lock:
            self.running -= 1
            self._evaluate_if_complete()

    def _evaluate_if_complete(self) -> None:
        """Under the lock: evaluate the batch once every running solver has asked."""
        if not self.asked or len(self.asked) < self.running:
            return
        solvers = sorted(self.asked)
        try:
            values = self.batch([self.asked[k] for k in solvers])
            self.answers.update(zip(solvers, (float(v) for v in values)))
        except BaseException as error:          # every waiting solver raises it, none waits forever
            self.error = error
        self.asked.clear()
        self.round += 1
        self.lock.notify_all()


class _Run(Generic[Result]):
    def __init__(self) -> None:
        self.result: Result | None = None
        self.error: BaseException | None = None


def run(solvers: Sequence[Callable[[Objective], Result]],
        batch: Callable[[list[Any]], Iterable[float]]) -> list[Result]:
    """[solver(objective) for solver in solvers], each solver's objective calls answered by
    batch(points) (a value per point, in order) over the points every running solver asks at
    once; a solver's exception is raised here after all have ended. One solver runs in the
    caller's thread with no other."""
    if len(solvers) == 1:
        return [solvers[0](lambda point: float(next(iter(batch([point])))))]
    batcher = _Batcher(batch, len(solvers))
    runs: list[_Run[Result]] = [_Run() for _ in solvers]

    def work(k: int) -> None:
        try:
            runs[k].result = solvers[k](lambda point: batcher.ask(k, point))
        except BaseException as error:
            runs[k].error = error
        finally:
            batcher.finished()

    threads = [threading.Thread(target=work, args=(k,), name=f"lockstep-{k}") for k in range(len(solvers))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for r in runs:
        if r.error is not None:
            raise r.error
    return [r.result for r in runs]     # type: ignore[misc]  # every run ended without error: set


def drive(searches: Sequence[Generator[Point, float, Result]],
          batch: Callable[[list[tuple[int, Point]]], Iterable[float]]) -> list[Result]:
    """Each search's return value, the searches (generators that yield a point and are sent its
    value) in lockstep in this thread: each round, the points every unfinished search asks
    answered by one batch([(search's index, point), ...]) call, a value each, in order. Each
    search sees the values it would have seen alone when a point's value does not depend on the
    others in its batch."""
    results: list[Result | None] = [None] * len(searches)
    asked: dict[int, Point] = {}

    def advance(k: int, value: float | None) -> None:
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
            advance(k, float(value))
    return results      # type: ignore[return-value]  # every search returned: set
