"""Tasks with several features: the `features:` format and its errors, the one-feature views of
a task, the judge of a given shot on a feature (cell.planning.coverage) against the one-shot planner's
own verdict, and the multi-feature plan (cell.planning.whole_part) against an independent dense check of
every feature with the shot said to cover it."""
import json
import pickle
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cell import cli

from cell.planning import coverage, one_shot

from cell.task import loader
from cell.core.errors import TaskError
from cell.planning.whole_part import plan_features
from dense import acceptance_failures, dense_check
from test_loader import write_task

ROOT = Path(__file__).resolve().parent.parent
FEATURES = ROOT / "tests" / "tasks" / "features" / "hinge.yaml"
LEAF_A = {"name": "leaf_a", "center_m": [0.006, 0.0, 0.004], "radius_m": 0.006, "samples": 64}
LEAF_B = {"name": "leaf_b", "center_mm": [6.0, 8.0, 4.0], "radius_mm": 5.0, "samples": 32,
          "requirements": {"lamp_tolerance_rad": 0.01, "gray_band": [90, 200]}}


def features(*entries, keep_feature=False):
    """Edit of the hinge task: `features:` given as these entries (and `feature:` dropped)."""
    def edit(task, folder):
        if not keep_feature:
            del task["feature"]
        task["features"] = list(entries)
    return edit


def load(tmp_path, edit):
    return loader.load_task(write_task(tmp_path, edit))


# --- the format ---

def test_features_load_with_their_names_and_the_tasks_requirements_overridden_per_key(tmp_path):
    task = load(tmp_path, features(LEAF_A, LEAF_B))
    a, b = task.features
    assert (a.name, b.name) == ("leaf_a", "leaf_b") and (a.key, b.key) == ("features[0]", "features[1]")
    np.testing.assert_allclose(b.center_m, [0.006, 0.008, 0.004], atol=1e-12)      # mm -> m
    assert b.radius_m == pytest.approx(0.005) and b.samples == 32
    # leaf_a takes the task's requirements as they are; leaf_b replaces two of them (one in rad)
    hinge = loader.load_task(ROOT / "tasks" / "hinge.yaml")
    assert a.requirements == hinge.requirements
    assert b.requirements.lamp_tolerance_rad == 0.01 and b.requirements.gray_band == (90.0, 200.0)
    assert b.requirements.reflection == hinge.requirements.reflection
    assert b.requirements.region_margin_rad == hinge.requirements.region_margin_rad
    assert b.requirements.depth_of_field_m == hinge.requirements.depth_of_field_m


def test_the_single_feature_form_is_a_feature_named_feature():
    task = loader.load_task(ROOT / "tasks" / "hinge.yaml")
    assert len(task.features) == 1 and task.feature.name == "feature" and task.feature is task.features[0]
    assert task.requirements is task.feature.requirements


def test_a_multi_feature_task_refuses_to_pick_one_and_gives_each_as_a_task(tmp_path):
    task = load(tmp_path, features(LEAF_A, LEAF_B))
    with pytest.raises(ValueError, match="the task has 2 features; plan them with"):
        task.feature
    with pytest.raises(ValueError, match="2 features"):
        task.requirements
    one = task.with_feature(1)
    assert one.feature is task.features[1] and one.requirements.gray_band == (90.0, 200.0)
    assert one.camera is task.camera and one.part is task.part
    copy = pickle.loads(pickle.dumps(task))
    assert [f.name for f in copy.features] == ["leaf_a", "leaf_b"]
    np.testing.assert_array_equal(copy.features[1].center_m, task.features[1].center_m)


def test_a_task_is_a_whole_part_with_several_features_or_a_planned_viewpoint(tmp_path):
    """Task.whole_part (cell run goes shot by shot, cell bench gives the many-feature rows): two
    features at the fixed camera rule, or one whose viewpoint is planned; not the hinge's one
    feature at the fixed rule."""
    assert not loader.load_task(ROOT / "tasks" / "hinge.yaml").whole_part
    pair = load(tmp_path, features(LEAF_A, LEAF_B))
    assert pair.camera.viewpoint.mode == "fixed" and pair.whole_part and not pair.with_feature(0).whole_part
    bracket = loader.load_task(ROOT / "tasks" / "bracket.yaml")
    assert bracket.camera.viewpoint.mode == "planned" and bracket.with_feature(0).whole_part


BAD = [
    pytest.param(features(LEAF_A, keep_feature=True), "feature, features", "found both", id="both"),
    pytest.param(lambda task, folder: task.pop("feature") and None, "features", "found nothing", id="neither"),
    pytest.param(features(), "features", "non-empty list", id="empty-list"),
    pytest.param(lambda task, folder: (task.pop("feature"), task.update(features=LEAF_A)) and None, "features",
                 "non-empty list", id="a-mapping-not-a-list"),
    pytest.param(features(LEAF_A, {**LEAF_A, "center_m": [0.0, 0.0, 0.004]}), "features[1].name",
                 "also the name of features[0]", id="duplicate-name"),
    pytest.param(features(LEAF_A, LEAF_B, {**LEAF_A, "name": "c", "radius_m": -1.0}), "features[2].radius_m",
                 "a positive number", id="bad-radius"),
    pytest.param(features({k: v for k, v in LEAF_A.items() if k != "name"}), "features[0].name",
                 "required key", id="no-name"),
    pytest.param(features(LEAF_A, "leaf"), "features[1]", "a mapping of keys", id="entry-not-a-mapping"),
    pytest.param(features(LEAF_A, {**LEAF_B, "requirements": {"gray_band": [100, 300]}}),
                 "features[1].requirements.gray_band[1]", "bit_depth 8", id="band-beyond-bit-depth"),
    pytest.param(features(LEAF_A, {**LEAF_B, "requirements": {"lamp_tolerance_deg": -1}}),
                 "features[1].requirements.lamp_tolerance_deg", "a number >= 0", id="bad-override"),
    pytest.param(features(LEAF_A, {**LEAF_B, "requirements": {"gray_bnd": [1, 2]}}),
                 "features[1].requirements.gray_bnd", "did you mean 'gray_band'", id="unknown-override"),
    pytest.param(features(LEAF_A, {**LEAF_A, "name": "high", "center_m": [0.006, 0.0, 0.009]}),
                 "features[1].center_m", "5.0 mm from the surface", id="off-surface"),
    pytest.param(features(LEAF_A, {**LEAF_A, "name": "edge", "center_m": [0.030, 0.0, 0.004]}),
                 "features[1].center_m", "runs over an edge of the part", id="over-the-edge"),   # cell check lays it
]


@pytest.mark.parametrize("edit, key, text", BAD)
def test_bad_features_are_one_line_naming_the_entry_and_key(tmp_path, capsys, edit, key, text):
    path = write_task(tmp_path, edit)
    assert cli.main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f"{path}: {key}: found" in err and text in err, err


def test_a_features_camera_inside_the_part_names_that_feature(tmp_path):
    """The camera rule puts each feature's camera 50 mm along -x from its centre: the leaf's
    (x -30..30 mm, z 0..4 mm) top feature's camera at x = -44 mm is beyond the knuckle (x -40..-28),
    the end face's at x = -20 mm, z = 2 mm inside the leaf."""
    top = {"name": "top", "center_m": [0.006, 0.0, 0.004], "radius_m": 0.004, "samples": 16}
    end = {"name": "end", "center_m": [0.030, 0.0, 0.002], "radius_m": 0.0015, "samples": 16}

    def edit(task, folder):
        features(top, end)(task, folder)
        task["camera"].update(distance_m=0.05, view_direction=[-1.0, 0.0, 0.0])
    with pytest.raises(TaskError) as caught:
        load(tmp_path, edit)
    assert caught.value.key == "camera.distance_m"
    assert caught.value.found == "[-0.02, 0.0, 0.002] m, inside the part, the camera of features[1] (end)"


# --- judging a given shot ---

@pytest.fixture(scope="module")
def hinge_plan():
    task = loader.load_task(ROOT / "tasks" / "hinge.yaml")
    return task, one_shot.plan(task)


def test_the_judge_of_a_features_own_shot_agrees_with_its_plan(hinge_plan):
    task, plan = hinge_plan
    c = coverage.judge(task, coverage.Lent.of(plan), plan.shot)
    assert c.covered is plan.feasible is True
    assert [r.name for r in c.requirements] == [r.name for r in plan.shot.requirements]
    np.testing.assert_allclose([r.value for r in c.requirements], [r.value for r in plan.shot.requirements],
                               rtol=1e-9)
    np.testing.assert_allclose(c.gray, plan.shot.gray, rtol=1e-9)
    assert c.verification.points == plan.verification.points
    assert c.verification.gray_max == pytest.approx(plan.verification.gray_max, rel=1e-9)


def test_the_judge_takes_the_shots_focus_not_the_features_distance(hinge_plan):
    """The same shot with its focus moved 30 mm: the thin lens's near limit at the shot's f-number
    falls beyond the nearest sample, so depth_of_field fails (and, as the search would say, no
    shutter within range gives that depth at the band's centre: shutter_max); the gray, at the
    same exposure, is the same."""
    from dataclasses import replace

    from cell.physics import depth_of_field as dof
    task, plan = hinge_plan
    shot, lens = plan.shot, task.camera.lens
    moved = replace(shot, exposure=replace(shot.exposure, focus_m=shot.exposure.focus_m + 0.03))
    near = dof.near_limit(moved.exposure.focus_m, lens.focal_length_m, shot.exposure.f_number,
                          lens.circle_of_confusion_m)
    assert near > plan.scene.sample_depths().min()                   # the thin lens says: out of focus
    c = coverage.judge(task, coverage.Lent.of(plan), moved)
    failing = {r.name for r in c.requirements if not r.met}
    assert not c.covered and "depth_of_field" in failing and failing <= {"depth_of_field", "shutter_max"}
    np.testing.assert_allclose(c.gray, shot.gray, rtol=1e-9)


# --- several features ---

@pytest.fixture(scope="module")
def multi():
    task = loader.load_task(FEATURES)
    return task, plan_features(task)


def test_two_shots_cover_three_features_and_the_fourth_is_named_with_its_cause(multi):
    task, plan = multi
    by = {f.name: f for f in plan.features}
    assert len(plan.shots) == 2 and plan.cover["candidate_shots"] == 4
    assert by["leaf_a"].covered_by == by["leaf_b"].covered_by != by["knuckle"].covered_by
    assert by["end_face"].covered_by is None and by["end_face"].binding == "camera_view"
    assert not plan.feasible and plan.binding == "camera_view"
    assert plan.message.startswith("feature 'end_face' is covered by no shot: camera_view binds")
    # the matrix says why two shots are the fewest: no candidate covers both leaf_a and knuckle
    covers = np.array(plan.cover["covers"])
    assert not (covers[0] & covers[2]).any() and not covers[3].any()
    for k, shot in enumerate(plan.shots):
        assert {c.feature for c in shot.covers} == {f.name for f in plan.features
                                                  if covers[[g.name for g in task.features].index(f.name),
                                                            plan.cover["chosen"][k]]}


def test_the_judge_of_each_features_own_shot_agrees_with_its_plan_feasible_or_not(multi):
    task, plan = multi
    assert [p.feasible for p in plan.plans] == [True, True, True, False]
    for i, own in enumerate(plan.plans):
        c = coverage.judge(task.with_feature(i), coverage.Lent.of(own), own.shot)
        assert c.covered is own.feasible
        np.testing.assert_allclose([r.value for r in c.requirements], [r.value for r in own.shot.requirements],
                                   rtol=1e-9)


def test_every_covered_feature_passes_the_dense_check_with_its_shot(multi):
    """tests/dense.py (NumPy physics, brute-force rays, 6000 points by area over the true patch):
    in band, lit, seen and in focus at every point, for each feature with the shot covering it."""
    task, plan = multi
    for i, f in enumerate(plan.features):
        if f.covered_by is not None:
            check = dense_check(task.with_feature(i), plan.shots[f.covered_by], count=3000)
            assert acceptance_failures(SimpleNamespace(feasible=True), check) == [], f.name


def test_a_feature_judged_on_a_shot_focused_elsewhere_is_out_of_focus_on_the_dense_check_too(multi):
    """leaf_a (z = 4 mm) on the knuckle's shot, focused on the knuckle 8 mm higher at f/1.4: the
    judge says depth_of_field, and the dense check finds points out of focus."""
    task, plan = multi
    knuckle = plan.shots[next(f.covered_by for f in plan.features if f.name == "knuckle")]
    c = coverage.judge(task.with_feature(0), coverage.Lent.of(plan.plans[0]), knuckle)
    assert "depth_of_field" in {r.name for r in c.requirements if not r.met}
    assert dense_check(task.with_feature(0), knuckle, count=2000).summary()["out_of_focus"] > 0


def test_the_multi_feature_plan_json_has_shots_features_and_cover(multi, tmp_path):
    task, plan = multi
    doc = json.loads(json.dumps(plan.to_json()))
    assert [f["name"] for f in doc["features"]] == ["leaf_a", "leaf_b", "knuckle", "end_face"]
    assert doc["features"][3] == {"name": "end_face", "covered_by": None, "binding": "camera_view",
                                  "hint": plan.features[3].hint}
    assert [len(s["covers"]) for s in doc["shots"]] == [2, 1]
    shot = doc["shots"][0]
    assert {"T_cell_cam", "position_m", "shutter_s", "f_number", "focus_m"} <= set(shot["camera"])
    assert {"position_m", "joints"} <= set(shot["lamp"])
    assert {"feature", "predicted_gray", "requirements", "verified"} <= set(shot["covers"][0])
    assert "requirements" not in doc                # two shots: no one-shot keys


def test_a_one_shot_multi_feature_plan_keeps_the_one_shot_keys_and_cell_plan_exits_0(multi, tmp_path, capsys,
                                                                                      monkeypatch):
    from dataclasses import replace
    task, _ = multi
    plan = plan_features(replace(task, features=task.features[:2]))
    doc = plan.to_json()
    assert plan.feasible and len(plan.shots) == 1 and [f.covered_by for f in plan.features] == [0, 0]
    assert {"requirements", "lamp", "camera", "predicted_gray", "verified", "search", "shots", "features"} <= set(doc)
    assert doc["lamp"] == doc["shots"][0]["lamp"]
    own = task.features[doc["cover"]["chosen"][0]].name                       # the shot's own feature's
    assert doc["requirements"] == next(c for c in doc["shots"][0]["covers"] if c["feature"] == own)["requirements"]
    monkeypatch.setattr("cell.cli.plan.plan_features", lambda task, progress, pool: plan)
    assert cli.main(["plan", str(FEATURES), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{task.name}: feasible: 1 shot covers 2 of 2 features")
    assert "max f_i" not in out and "e+" not in out and "tightest requirement: " in out


def test_cell_plan_prints_a_line_per_shot_and_feature_and_exits_1_naming_the_uncovered(multi, tmp_path,
                                                                                      capsys, monkeypatch):
    task, plan = multi
    monkeypatch.setattr("cell.cli.plan.plan_features", lambda task, progress, pool: plan)
    assert cli.main(["plan", str(FEATURES), "--out", str(tmp_path / "out")]) == 1
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0].startswith("Aluminium hinge, four features: PARTIAL: 2 shots cover 3 of 4 features "
                               "(chosen from 4 candidate shots)")
    assert sum(line.startswith("  shot ") for line in lines) == 2
    assert sum(line.startswith("  feature ") for line in lines) == 4
    assert ("feature end_face: no shot covers it: camera view of the feature fails: the camera cannot see "
            "16 of 16 feature samples" in captured.out)
    covered = [line for line in lines if line.startswith("  feature ") and "no shot" not in line]
    assert len(covered) == 3 and all("tightest requirement: " in line for line in covered)
    assert "max f_i" not in captured.out and "e+" not in captured.out and "camera_view" not in captured.out
    assert "feature end_face: no shot covers it" in captured.err
    assert json.loads((tmp_path / "out" / "plan.json").read_text())["features"][3]["covered_by"] is None
    assert (tmp_path / "out" / "feature-2" / "regions.png").stat().st_size > 10_000


def test_a_multi_feature_plan_pickles_whole(multi):
    """The later steps plan features in worker processes: the plan, its shots' coverage and each
    feature's own plan travel as plain values."""
    task, plan = multi
    copy = pickle.loads(pickle.dumps(plan))
    assert {**copy.to_json(), "timing_s": None} == {**plan.to_json(), "timing_s": None}
    np.testing.assert_array_equal(copy.plans[2].scene.points, plan.plans[2].scene.points)
    np.testing.assert_array_equal(copy.shots[0].covers[1].gray, plan.shots[0].covers[1].gray)
