"""Pictures: drawn from several threads at once they come out as if drawn one after the other; a
run's plan pictures are drawn when the run has ended, never while its devices wait."""
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as plt_image
from matplotlib.colors import to_rgb

from cell.task.loader import load_task
from cell.report.pictures import FEATURE_COLORS, display_mesh, write_bench, write_cell
from cell.planning.one_shot import plan
from cell.report.recorder import write_plan

ROOT = Path(__file__).resolve().parent.parent

ROWS = [{"task": "t", "name": n, "time_s": t, "gray_error_max": e, "default": n == "default", "pareto": True}
        for n, t, e in [("coarse", 0.1, 1.8), ("default", 0.3, 0.5), ("fine", 1.5, 0.2)]]


def test_bench_plots_drawn_in_threads_equal_one_drawn_alone(tmp_path):
    """Log axes lay out their tick labels with matplotlib's shared mathtext parser."""
    write_bench(tmp_path / "alone.png", ROWS)
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda k: write_bench(tmp_path / f"{k}.png", ROWS), range(8)))
    alone = (tmp_path / "alone.png").read_bytes()
    assert all((tmp_path / f"{k}.png").read_bytes() == alone for k in range(8))




def test_a_runs_plan_pictures_are_drawn_when_it_has_ended_its_plan_json_at_once(tmp_path, monkeypatch):
    """Recorder.write_plan writes plan.json at once and keeps the pictures for the run's end (its
    own Recorder's exit, after the result file and the devices' session, which close inside it),
    a sub-run's re-plan's too, in the order they were planned."""
    from cell.report.recorder import Recorder
    task = load_task(ROOT / "tasks" / "hinge.yaml")
    planned = plan(task)
    drawn = []
    monkeypatch.setattr("cell.report.pictures.write_plan_pictures",
                        lambda plan, task, scene, folder: drawn.append(Path(folder)))
    run = tmp_path / "run"
    with Recorder(run) as rec:
        rec.write_plan(planned, task)
        with rec.sub("shot-0") as sub:
            sub.write_plan(planned, task, "replan-1")
        assert (run / "plan.json").is_file() and (run / "shot-0" / "replan-1" / "plan.json").is_file()
        assert drawn == [] and not (run / "cell.png").exists()
    assert drawn == [run, run / "shot-0" / "replan-1"]
    assert (run / "cell.png").stat().st_size > 20_000 and (run / "shot-0" / "replan-1" / "cell.html").is_file()


def test_a_picture_that_fails_as_a_run_ends_in_error_leaves_that_error_to_say(tmp_path, monkeypatch, capsys):
    from cell.report.recorder import Recorder

    def broken(plan, task, scene, folder):
        raise RuntimeError("no room on the disk")

    monkeypatch.setattr("cell.report.pictures.write_plan_pictures", broken)
    task = load_task(ROOT / "tasks" / "hinge.yaml")
    planned = plan(task)
    with pytest.raises(ValueError, match="the run's own error"):
        with Recorder(tmp_path / "run") as rec:
            rec.write_plan(planned, task)
            raise ValueError("the run's own error")
    assert "a picture was not drawn: no room on the disk" in capsys.readouterr().err
    with pytest.raises(RuntimeError, match="no room on the disk"):      # at a normal end it is the error
        with Recorder(tmp_path / "again") as rec:
            rec.write_plan(planned, task)


@pytest.mark.parametrize("az, el", [(-180.0, 87.0), (179.0, 88.0), (0.0, -30.0), (120.0, 20.0)])
def test_the_camera_is_marked_whole_and_named_inside_the_map_wherever_it_is_seen(az, el):
    """The hinge's camera, 3 deg off the normal, is seen at azimuth -180 (the map's corner, issue
    29): its square is drawn unclipped at the edge and a label inside the map points at it."""
    from matplotlib.figure import Figure
    from matplotlib.text import Annotation
    from cell.report.pictures import _mark_camera
    fig = Figure(figsize=(8, 4))
    ax = fig.add_subplot()
    ax.set_xlim(-180, 180)
    ax.set_ylim(-90, 90)
    _mark_camera(ax, (np.array(az), np.array(el)))
    square = next(line for line in ax.get_lines() if line.get_label() == "camera")
    assert not square.get_clip_on() and list(square.get_xdata()) == [az] and list(square.get_ydata()) == [el]
    label = next(a for a in ax.texts if isinstance(a, Annotation))
    assert label.get_text() == f"camera (elevation {el:.0f} deg)" and label.xy == (az, el)
    fig.canvas.draw()
    box, inside = label.get_window_extent(), ax.get_window_extent()
    assert inside.x0 <= box.x0 and box.x1 <= inside.x1 and inside.y0 <= box.y0 and box.y1 <= inside.y1
