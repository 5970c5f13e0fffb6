"""tests/tasks/features/plate_dome.yaml: a dome light over a painted plate, the camera looking in
through the dome's hole. It plans with the camera's body reaching below the hole's inner edge,
its clearance the closed form of its corners to the hole's wall; the dome lights the plate; the
run converges on the simulated cell through via points down the dome's axis, which the
simulator's own check lets through (its paths densely checked: tests/test_moves.py); the dome
hung higher, the arm's wrist meets the shell round the hole and the plan is refused naming the
dome."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.cli import main
from cell.collision.bodies import BOX_TOLERANCE_M
from cell.collision.scene import CollisionScene
from cell.core import geometry
from cell.planning.whole_part import plan_features
from cell.task.loader import load_task
from cell.task.types import HOUSING_DEPTH_M

from simcell import variant

DOME = Path(__file__).parent / "tasks" / "features" / "plate_dome.yaml"


@pytest.fixture(scope="module")
def dome_plan():
    task = load_task(DOME)
    return task, plan_features(task)


def hole_edges(light):
    """The heights [m] (cell frame) of the hole's inner and outer edges: where its cylinder meets the
    dome's inner sphere (radius_m about the point radius_m below the pole) and its outer one
    (HOUSING_DEPTH_M thicker: the task leaves housing_depth_m at its default)."""
    centre = light.position_m[2] - light.radius_m
    return tuple(centre + np.sqrt(rho**2 - light.hole_radius_m**2) for rho in (light.radius_m, light.radius_m + HOUSING_DEPTH_M))


def test_the_camera_reaches_through_the_domes_hole_clear_of_its_wall(dome_plan):
    task, plan = dome_plan
    dome, shot = task.lights[0], plan.shots[0]
    assert plan.feasible and len(plan.shots) == 1
    camera = CollisionScene.of(task).camera_body(task.frames.T_cell_flange(shot.T_cell_cam))
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    corners = geometry.apply(camera.T_cell_box, signs * camera.half_m)
    inner, outer = hole_edges(dome)
    assert corners[:, 2].min() < inner < outer < corners[:, 2].max()       # through the hole, out of it above
    gap = dome.hole_radius_m - np.hypot(corners[:, 0], corners[:, 1]).max()   # the box's upright edges to the wall
    assert gap > task.cell.collision.padding_m
    assert shot.clearance is not None and shot.clearance.bodies == ("dome", "camera_body")
    assert gap - BOX_TOLERANCE_M - 1e-9 <= shot.clearance.distance_m <= gap + 1e-9


def test_the_dome_lights_the_plate_and_the_spot_is_off(dome_plan):
    """A matte paint's diffuse term dominates wherever the dome is seen from the plate (48-78 deg up)."""
    _, plan = dome_plan
    drive = {light.name: light.drive for light in plan.shots[0].lights}
    assert drive["dome"] > 0.5 and drive["lamp"] == 0.0


def test_the_dome_hung_higher_is_refused_naming_it(tmp_path, capsys):
    """Its pole 150 mm higher: the camera still passes the hole's wall 12.6 mm off, the arm's wrist
    (wider, off the axis) meets the shell round the hole."""
    raw = yaml.safe_load(DOME.read_text())
    raw["lights"][0]["position_m"][2] += 0.15
    path = variant(tmp_path, DOME, {"lights": raw["lights"]})
    assert main(["plan", str(path), "--out", str(tmp_path / "plan")]) == 1
    out, err = capsys.readouterr()
    err = err.strip().splitlines()[-1]
    plan = json.loads((tmp_path / "plan" / "plan.json").read_text())
    assert not plan["feasible"] and plan["binding"] == "collision"
    assert all(r["met"] for r in plan["requirements"]) and plan["verified"]["holds"]     # the optics held
    assert "collision" in err and "dome and wrist" in err, err
    # the headline: the collision with both bodies first, then that the optics held
    headline = out.splitlines()[0]
    assert headline.startswith(f"{plan['task']}: INFEASIBLE: collision: dome and wrist_2 "), headline
    assert "the lighting, exposure and view meet every requirement" in headline and "tightest" not in headline


def test_the_dome_hung_higher_is_refused_by_cell_run_before_anything_moves_naming_the_shots_bodies(tmp_path, capsys):
    """`cell run` checks the planned shot's bodies as `cell plan` does: the wrist in the dome's hole
    is the cause, not the first contact on the move there (the camera body passing the shell)."""
    raw = yaml.safe_load(DOME.read_text())
    raw["lights"][0]["position_m"][2] += 0.15
    path = variant(tmp_path, DOME, {"lights": raw["lights"]})
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("cell run: infeasible: collision: dome and wrist_2 touch or overlap"), err
    plan = json.loads((out / "plan.json").read_text())
    assert plan["binding"] == "collision" and plan["clearance_bodies"] == ["dome", "wrist_2"]
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert not {"move_camera", "move_lamp", "move_via", "capture"} & set(steps)


@pytest.mark.long          # 1-5 min: the run, the simulated arm's own check stepping finely near the dome
def test_the_run_converges_through_via_points_down_the_domes_axis(tmp_path):
    """From the home pose over the dome, onto its axis above the hole, down to the shot; the
    simulator's own check never stops it."""
    out = tmp_path / "run"
    assert main(["run", str(DOME), "--out", str(out)]) == 0
    log = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    via = [np.asarray(line["position_m"]) for line in log if line["step"] == "move_via"]
    assert len(via) == 2 and via[0][2] > via[1][2] > hole_edges(load_task(DOME).lights[0])[1]   # over the dome, then
    assert np.allclose(via[1][:2], 0.0, atol=1e-9)                                # on its axis, above the hole
    assert not any(line["step"] == "fault" for line in log)
    assert json.loads((out / "report.json").read_text())["converged"]
