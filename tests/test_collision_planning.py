"""Collision checking in planning: every shot of the bracket's plan keeps the padding, by a dense
brute force that shares no distance code with cell.collision (trimesh's surface samples of each
body and a k-d tree); a shot that puts the camera inside a fixture is refused with both bodies
named, and `cell plan` exits 1."""
import json
import re
from itertools import combinations
from pathlib import Path
from types import SimpleNamespace as Of

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cell.cli import main
from cell.collision.scene import MAY_TOUCH, Clearance, CollisionScene, arm_links
from cell.core import geometry
from cell.devices import ur5e
from cell.planning.whole_part import plan_features, uncovered_verdict
from cell.task.loader import load_task

from simcell import variant

ROOT = Path(__file__).resolve().parent.parent
HINGE, BRACKET = ROOT / "tasks" / "hinge.yaml", ROOT / "tasks" / "bracket.yaml"
PITCH = 0.002


def surface(mesh):
    return trimesh.sample.sample_surface_even(mesh, int(mesh.area / PITCH ** 2), radius=0.5 * PITCH, seed=5)[0]


def brute_clearance(task, T_cell_cam, q, lamp):
    """The smallest distance between bodies that may not touch, each body's surface sampled by
    trimesh (boxes and capsules as trimesh primitives), the nearest pairs by a k-d tree."""
    c, frames = task.cell.collision, task.frames
    T_flange = frames.T_cell_flange(T_cell_cam)
    bodies = {"part": task.part.mesh.copy().apply_transform(frames.T_cell_part),
              "camera_body": trimesh.creation.box(extents=c.camera_size_m, transform=T_flange @ geometry.transform(
                  translation=(0.0, 0.0, c.camera_offset_m)))}
    z = geometry.unit(task.lamp.rig.pivot_m - lamp)
    x = geometry.unit(np.cross((0.0, 0.0, 1.0), z))
    bodies["lamp_body"] = trimesh.creation.box(extents=c.lamp_size_m, transform=geometry.transform(
        np.column_stack([x, np.cross(z, x), z]), lamp - 0.5 * c.lamp_size_m[2] * z))
    for link in arm_links(frames.T_cell_base, q):
        axis = link.b - link.a
        m = trimesh.creation.capsule(height=float(np.linalg.norm(axis)), radius=link.radius_m, count=[24, 24])
        bodies[link.name] = m.apply_transform(geometry.transform(geometry.frame_from_normal(geometry.unit(axis)),
                                                                 link.center))
    points = {name: surface(m) for name, m in bodies.items()}
    return min(cKDTree(points[a]).query(points[b])[0].min()
               for a, b in combinations(points, 2) if frozenset((a, b)) not in MAY_TOUCH)


@pytest.fixture(scope="module")
def bracket():
    task = load_task(BRACKET)
    return task, plan_features(task)


@pytest.mark.long          # 25 s; the default run keeps the refusal with both bodies named
def test_every_shot_of_the_bracket_keeps_the_padding_by_a_dense_brute_force(bracket):
    task, plan = bracket
    document = plan.to_json()
    assert plan.feasible and document["cover"]["rejected"] == {"collision": 0}
    for shot, written in zip(plan.shots, document["shots"]):
        brute = brute_clearance(task, shot.T_cell_cam, shot.arm_joints, shot.lamp_position)
        assert written["clearance_m"] == shot.clearance.distance_m
        assert brute >= task.cell.collision.padding_m
        assert brute - 0.002 - 2 * PITCH <= shot.clearance.distance_m <= brute + PITCH, (brute, shot.clearance)
    for view in document["cover"]["viewpoints"]:
        assert "collision" in view["pruned"]


def test_a_camera_inside_a_fixture_is_refused_naming_both_and_cell_plan_exits_1(tmp_path, capsys):
    """The hinge's camera 0.5 m above the leaf, a 30 mm block hung there as the fixture: wholly
    inside the camera body (from the flange at 0.55 m to 0.45 m)."""
    block = trimesh.creation.box(extents=(30.0, 30.0, 30.0), transform=geometry.transform(translation=(6, 0, 490)))
    (tmp_path / "block.stl").write_bytes(block.export(file_type="stl"))
    path = variant(tmp_path, HINGE, {"cell.collision.fixture_mesh": str(tmp_path / "block.stl")})
    assert main(["plan", str(path), "--out", str(tmp_path / "out")]) == 1
    out, err = capsys.readouterr()
    err = err.strip().splitlines()[-1]
    assert "collision" in err and "camera_body" in err and "fixture" in err
    headline = out.splitlines()[0]             # the true cause first: the optics held, the bodies did not
    assert re.match(r".*: INFEASIBLE: collision: (fixture and camera_body|camera_body and fixture) ", headline), headline
    assert headline.endswith("the lighting, exposure and view meet every requirement")


def test_a_shot_whose_optics_fail_and_that_collides_names_the_optics_first(tmp_path, capsys):
    """The hinge's fixture block as above and a shutter range too short for its band: the optics
    fail first (the binding plan.json keeps), the collision follows in the hint and the headline."""
    block = trimesh.creation.box(extents=(30.0, 30.0, 30.0), transform=geometry.transform(translation=(6, 0, 490)))
    (tmp_path / "block.stl").write_bytes(block.export(file_type="stl"))
    path = variant(tmp_path, HINGE, {"cell.collision.fixture_mesh": str(tmp_path / "block.stl"),
                                     "camera.shutter_range_ms": [0.01, 0.5]})
    assert main(["plan", str(path), "--out", str(tmp_path / "out")]) == 1
    out, _ = capsys.readouterr()
    plan = json.loads((tmp_path / "out" / "plan.json").read_text())
    failed = [r["name"] for r in plan["requirements"] if not r["met"]]
    assert plan["binding"] in failed and plan["binding"] != "collision"
    assert plan["clearance_m"] < 0.01 and "the shot also collides: collision: " in plan["hint"]
    headline = out.splitlines()[0]
    said, _, collides = headline.partition("; the shot also collides: collision: ")
    assert re.search(r": INFEASIBLE: (gray band, dark end|shutter time) fails by ", said), headline
    assert collides.startswith(("fixture and camera_body", "camera_body and fixture")), headline


def test_an_uncovered_features_cause_is_the_collision_where_every_shot_that_covers_it_optically_collides():
    """whole_part.uncovered_verdict against the rule written out: its own shot's optics failed
    (its binding not `collision`), another feature's shot lights and sees it as required and
    collides: the collision, that shot's bodies; where none lights and sees it, its own plan's
    binding."""
    own_hits = Clearance(-0.002, ("part", "camera_body"), 0.01)
    other_hits = Clearance(0.004, ("fixture", "wrist_3"), 0.01)
    own = Of(binding="gray_min", hint="too dark", shot=Of(clearance=own_hits))
    other = Of(binding="collision", hint="", shot=Of(clearance=other_hits))
    clear = Of(binding="depth_of_field", hint="", shot=Of(clearance=Clearance(0.05, ("part", "lamp_body"), 0.01)))
    v = uncovered_verdict("f", [own, other, clear], [Of(covered=False), Of(covered=True), Of(covered=False)],
                          [True, False, False], own)
    assert (v.binding, v.covered_by) == ("collision", None)
    assert v.hint.startswith("collision: fixture and wrist_3 only 4.0 mm apart") and "the one candidate shot" in v.hint
    v = uncovered_verdict("f", [own, other], [Of(covered=False), Of(covered=False)], [True, False], own)
    assert (v.binding, v.hint) == ("gray_min", "too dark")
    # its own shot's optics held (binding collision) and another's too: both counted, its own named first
    own = Of(binding="collision", hint="", shot=Of(clearance=own_hits))
    v = uncovered_verdict("f", [other, own], [Of(covered=True), Of(covered=False)], [False, True], own)
    assert v.hint.startswith("collision: part and camera_body touch or overlap") and "each of the 2 candidate" in v.hint
