"""The run folder a person can open and a machine can read: `log.jsonl` (one JSON line per step:
time, step, message, data; appended, flushed and fsync'd so that a crash loses nothing measured;
each step also a line on stderr, or inside a long stage (`Recorder.stage`: measure-brdf's poses) only
the stage's bar or quarter lines, cell.core.progress), plan.json with the plan's pictures, every capture,
and the result file (cell.report.result's shape), written however the run ends."""
from __future__ import annotations

import os
import re
import sys
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Callable, Generic, Literal, TextIO, TypeVar

import cv2
import numpy as np

from cell.core import jsonio
from cell.core.errors import CellError, GoalNotReached, PlanInfeasible
from cell.core.progress import Progress, Stage
from cell.devices.session import Session, stop_outcome
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.planning.plan import Plan
    from cell.task.types import Task


R = TypeVar("R", bound=Result)


def write_plan(plan: Plan, task: Task, folder: str | os.PathLike[str]) -> Path:
    """plan.json into folder (created), and a multi-feature plan's own plan of each feature i into
    folder/feature-i, or with planned viewpoints each candidate shot k's into folder/candidate-k;
    no pictures (draw_plan draws them, once nothing waits for them). Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / "plan.json", plan.to_json())
    for k, own, i, sub in _own_plans(plan, folder):
        write_plan(own, task.with_feature(i), sub)
    return folder


def draw_plan(plan: Plan, task: Task, folder: str | os.PathLike[str], pictures: str = "chosen",
              cell_picture: bool = True) -> None:
    """The pictures of a plan written by write_plan into folder: a one-shot plan's maps
    (visibility_brdf.png, regions.png, cost.png; lights.png where the task has lights besides the
    spot), cell.png (its shots in the cell) and cell.html (the same in 3D, cell.report.cell_view);
    of a multi-feature plan's own plans those of its chosen shots (`pictures` "chosen": what a
    person reads), or every candidate's ("all"), without cell.png (the plan's own shows the chosen
    shots)."""
    from cell.report.cell_view import write_cell_view
    from cell.report.pictures import write_cell, write_lights, write_plan_pictures
    folder = Path(folder)
    if plan.plans:
        chosen = set(plan.cover["chosen"]) if plan.cover is not None else set()
        for k, own, i, sub in _own_plans(plan, folder):
            if pictures == "all" or k in chosen:
                draw_plan(own, task.with_feature(i), sub, pictures, cell_picture=False)
    else:
        write_plan_pictures(plan, task, plan.planned_scene, folder)
        if task.lights:
            write_lights(folder / "lights.png", plan, task)
    if cell_picture:
        write_cell(folder / "cell.png", plan, task)
        write_cell_view(folder / "cell.html", plan, task)


def _own_plans(plan: Plan, folder: Path) -> list[tuple[int, Plan, int, Path]]:
    """(k, candidate k's own plan, its feature's index, its folder) of a multi-feature plan (none
    of a one-shot plan)."""
    if not plan.plans:
        return []
    if plan.cover is None:           # cell.planning.whole_part gives every multi-feature plan its cover
        raise ValueError("a multi-feature plan without its set cover's numbers (plan.cover)")
    planned = plan.cover.get("candidate_features")
    return [(k, own, k if planned is None else planned[k],
             folder / (f"feature-{k}" if planned is None else f"candidate-{k}")) for k, own in enumerate(plan.plans)]


def write_json(path: str | os.PathLike[str], document: Any) -> None:
    Path(path).write_text(jsonio.dumps(document, indent=2) + "\n")


def file_name(text: str) -> str:
    """text as part of a file name: what is not a letter, digit, '.', '-' or '_' becomes '_'."""
    return re.sub(r"[^\w.-]", "_", text)


class Recorder:
    """A run folder and its log; `with Recorder(folder) as rec:` closes the log however it ends.
    A sub-run's (`rec.sub("shot-0", shot=0)`) has its own folder and log, and every step it logs
    is also appended to the parent's log with `tags` (shot=0). Its lines go to `out` (stderr's
    Progress unless given; a sub-run's is its parent's)."""

    def __init__(self, folder: str | os.PathLike[str], parent: Recorder | None = None, out: Progress | None = None,
                 **tags: Any) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.log: TextIO = open(self.folder / "log.jsonl", "a", encoding="utf-8")
        self.plan: dict[str, Any] | None = None     # the run folder's plan.json, once written
        self.parent, self.tags = parent, tags
        self.out: Progress = out or (parent.out if parent is not None else Progress(sys.stderr))
        # pictures to draw when the run has ended (its devices stopped): a sub-run's are the run's
        self.pictures: list[Callable[[], object]] = [] if parent is None else parent.pictures

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 traceback: TracebackType | None) -> Literal[False]:
        """Close the log; the run's own Recorder then draws the pictures it kept for the end (after
        its result file and its devices' session, which close inside it). A picture that fails
        while an error ends the run is said on stderr, not raised over that error."""
        self.log.close()
        if self.parent is None:
            while self.pictures:
                draw = self.pictures.pop(0)
                try:
                    draw()
                except Exception as failed:
                    if err is None:
                        raise
                    print(f"a picture was not drawn: {failed}", file=sys.stderr, flush=True)
        return False

    def later(self, draw: Callable[[], object]) -> None:
        """Draw a picture when the run has ended, not while its devices wait."""
        self.pictures.append(draw)

    def sub(self, name: str, **tags: Any) -> Recorder:
        """The Recorder of a sub-run in folder/name, its steps also in this log with tags."""
        return Recorder(self.folder / name, self, **tags)

    def step(self, step: str, message: str, iteration: int | None = None, **data: Any) -> None:
        """One step; `iteration` (the capture it belongs to) is left out when None."""
        where = {} if iteration is None else {"iteration": iteration}
        line = {"t": datetime.now(timezone.utc).isoformat(timespec="milliseconds"), "step": step,
                "message": message, **where, **data}
        self._append(line)
        if self.out.live is None:
            self.out.say(f"{'' if iteration is None else iteration:>2} {step:<12} {message}")
        else:                               # in a long stage: the log has it, the bar shows it in passing
            self.out.live.note(message)

    def stage(self, name: str, total: int) -> Stage:
        """A long stage of `total` steps (`with rec.stage("poses", 183) as stage: ... stage.advance()`):
        while it lasts the steps are logged but not printed, its bar or quarter lines stand for them."""
        return self.out.stage(name, total)

    def _append(self, line: dict[str, Any]) -> None:
        """line to the log, flushed and fsync'd, and with the tags to the parent's."""
        self.log.write(jsonio.dumps(line) + "\n")
        self.log.flush()
        os.fsync(self.log.fileno())
        if self.parent is not None:
            self.parent._append({**self.tags, **line})

    def progress(self, message: str) -> None:
        """A progress line on stderr only (the planner's stages), indented under the steps."""
        self.out.say(f"{'':16}{message}")

    def write_plan(self, plan: Plan, task: Task, subfolder: str = "") -> Path:
        """plan.json now and its pictures when the run has ended (draw_plan), in the run folder (its
        plan, `self.plan`) or a subfolder of it (a re-plan's); returns that folder."""
        if not subfolder:
            self.plan = plan.to_json()
        folder = write_plan(plan, task, self.folder / subfolder)
        self.later(lambda: draw_plan(plan, task, folder))
        return folder

    def write_image(self, name: str, image: np.ndarray) -> str:
        """An image file in the run folder (PNG: lossless, 8 or 16 bit); returns its name."""
        cv2.imwrite(str(self.folder / name), image)
        return name

    def write_json(self, name: str, document: Any) -> None:
        write_json(self.folder / name, document)

    def fault(self, fault: dict[str, Any]) -> None:
        """The fault step, after the safe stop (session.Session's fault record)."""
        self.step("fault", f"{fault['error']}: {stop_outcome(fault['stop_failures'])}", **fault)


class Ending(Generic[R]):
    """How a routine's run ends, whatever ends it: `with Recorder(out) as rec, Ending(rec, "no fit",
    "calibration.json", result) as end:` holds the run's device Session (`end.session`). An error
    logs the "done" step, `failed: error` with its reason (a fault the Session logged already is
    not logged twice), and is raised again; then, or at a normal end, `end.result = result(reason,
    fault)` (reason '' and fault None when it finished; the routine logs its own "done" step),
    its cause the ending's (`cause`) unless it names its own, is written to the run folder as
    `name`; `end.error` is what ended it (None at a normal end)."""

    def __init__(self, recorder: Recorder, failed: str, name: str,
                 result: Callable[[str, dict[str, Any] | None], R], **failed_data: Any) -> None:
        self.recorder, self.failed, self.name, self.make = recorder, failed, name, result
        self.failed_data = failed_data
        self._result: R | None = None
        self.error: BaseException | None = None
        self.session = Session(on_fault=recorder.fault, log=recorder.log.name)

    def __enter__(self) -> Ending[R]:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 traceback: TracebackType | None) -> Literal[False]:
        reason = "" if err is None or kind is None else str(err) or kind.__name__
        self.error = err
        if err is not None and not self.session.fault:     # the goal was not reached: the devices are fine
            said = err.said if isinstance(err, CellError) else str(err)    # words; report.json keeps the message
            self.recorder.step("done", f"{self.failed}: {said}", **self.failed_data, reason=reason)
        self._result = self.make(reason, self.session.fault).ended(self.cause)
        self.recorder.write_json(self.name, self._result.to_json())
        return False

    @property
    def result(self) -> R:
        """The routine's result, once it has ended."""
        if self._result is None:
            raise RuntimeError(f"{self.name} is written when the routine ends")
        return self._result

    @property
    def cause(self) -> str | None:
        """What ended the routine short of its goal, as a result's cause: None at a normal end,
        "fault" (the Session stopped the devices), "infeasible" (PlanInfeasible), a
        GoalNotReached's own cause (None when it names none), else "interrupted"."""
        if self.error is None:
            return None
        if self.session.fault:
            return "fault"
        if isinstance(self.error, PlanInfeasible):
            return "infeasible"
        if isinstance(self.error, GoalNotReached):
            return self.error.cause
        return "interrupted"
