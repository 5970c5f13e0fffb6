"""`cell run` of a multi-shot plan (cell.run.inspection) on the simulated cell: every feature of a
coverable task converges, with fixed and planned viewpoints; the shots' order is the shortest
by brute force; features sharing a capture are measured in regions that never merge, and one
exposure serves them (or the run says they disagree); the run folder holds a folder per shot
and a report per feature; a partial plan is refused before anything moves; a fault in the
second shot exits 3 and keeps the first shot's measurements."""
import itertools
import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from cell import cli

from cell.run import control, inspection, measurement, route
from cell.core.errors import CellError
from cell.task.loader import load_task
from cell.planning.scene import build_scene
from simcell import disk_pixels, recording_connect

ROOT = Path(__file__).resolve().parent.parent
PAIR = ROOT / "tests" / "tasks" / "features" / "hinge_pair.yaml"        # 3 features, 2 shots, fixed camera
PLANNED = ROOT / "tests" / "tasks" / "features" / "hinge_planned.yaml"  # 2 features, 2 planned viewpoints
PARTIAL = ROOT / "tests" / "tasks" / "features" / "hinge.yaml"          # end_face covered by no shot


def read(out):
    out = Path(out)
    return SimpleNamespace(out=out, report=json.loads((out / "report.json").read_text()),
                           log=[json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("pair") / "run"
    code = cli.main(["run", str(PAIR), "--out", str(out)])
    return SimpleNamespace(code=code, task=load_task(PAIR), **vars(read(out)))


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    out = tmp_path_factory.mktemp("planned") / "run"
    code = cli.main(["run", str(PLANNED), "--out", str(out)])
    return SimpleNamespace(code=code, task=load_task(PLANNED), **vars(read(out)))


def shot_pose(run, s):
    return np.array(run.report["plan"]["shots"][s]["camera"]["T_cell_cam"])


# --- every feature converges ----------------------------------------------------------------

def test_every_feature_of_a_coverable_task_converges_with_its_pixels_in_band(pair):
    assert pair.code == 0 and pair.report["converged"]
    by = {f["name"]: f for f in pair.report["features"]}
    assert list(by) == ["leaf_a", "leaf_b", "knuckle"]
    assert (by["leaf_a"]["shot"], by["leaf_b"]["shot"]) == (0, 0) and by["knuckle"]["shot"] == 1
    for f, name in enumerate(by):
        result = by[name]
        assert result["converged"] and result["in_band"] and result["reason"] == ""
        low, high = pair.task.features[f].requirements.gray_band
        assert low <= result["measured_gray"]["min"] <= result["measured_gray"]["max"] <= high
        image = cv2.imread(str(pair.out / result["capture"]), cv2.IMREAD_UNCHANGED)
        pixels = image[disk_pixels(pair.task, f, shot_pose(pair, result["shot"]), image.shape, 0.9)]
        assert len(pixels) > 500 and low <= pixels.min() and pixels.max() <= high


def test_planned_viewpoints_run_with_the_arm_carrying_the_camera_to_each_shots_pose(planned):
    assert planned.code == 0 and planned.report["converged"]
    assert [f["converged"] for f in planned.report["features"]] == [True, True]
    for shot in planned.report["shots"]:
        assert shot["camera_error"]["position_m"] < 1e-9 and shot["camera_error"]["angle_deg"] < 1e-6
        moved = next(line for line in planned.log if line["step"] == "move_camera" and line["shot"] == shot["shot"])
        np.testing.assert_allclose(moved["position_m"], shot_pose(planned, shot["shot"])[:3, 3], atol=1e-9)
    # the end face's camera 0.5 m out along +x looks back along -x: a pose the fixed rule never gives
    end = planned.report["features"][1]
    assert end["name"] == "end_face" and shot_pose(planned, end["shot"])[0, 3] > 0.4
    assert shot_pose(planned, end["shot"])[0, 2] < -0.9


# --- the order of the shots ----------------------------------------------------------------

def test_the_run_visits_the_shots_in_the_shortest_order_from_the_start_pose(pair):
    """The plan's checked route (here every move direct): the order shortest from the home pose
    (where the plan cannot know the lamp: its first leg counts the camera's travel alone), the
    travel as the run made it, the lamp's from where it read back."""
    route_line = next(line for line in pair.log if line["step"] == "route")
    shots = [line["shot"] for line in pair.log if line["step"] == "shot"]
    assert shots == route_line["order"] == pair.report["order"] == [m["to"] for m in pair.report["plan"]["moves"]]
    assert all(m["via"] == [] for m in route_line["moves"])
    camera = np.array(route_line["start"]["camera_m"])
    stops = [(np.array(s["camera"]["position_m"]), np.array(s["lamp"]["position_m"]))
             for s in pair.report["plan"]["shots"]]
    planned = route.travel_matrix((camera, None), stops)
    assert route.length(planned, shots) == pytest.approx(min(route.length(planned, p) for p in
                                                             itertools.permutations(range(len(stops)))))
    made = route.travel_matrix((camera, np.array(route_line["start"]["lamp_m"], float)), stops)
    assert pair.report["travel_m"] == pytest.approx(route.length(made, shots))


# --- features sharing a capture ------------------------------------------------------------

def shared_capture(pair):
    """The capture of the shot of leaf_a and leaf_b and each feature's Measurement in it."""
    image = cv2.imread(str(pair.out / "shot-0" / "capture-1.png"), cv2.IMREAD_UNCHANGED).astype(float)
    T = shot_pose(pair, 0)
    points = [build_scene(pair.task.with_feature(f), T_cell_cam=T).points for f in (0, 1)]
    return image, T, points


def test_two_features_close_together_are_measured_in_regions_of_their_own(pair):
    image, T, points = shared_capture(pair)
    tasks = [pair.task.with_feature(f) for f in (0, 1)]
    a, b = (measurement.measure_feature(image, t, T, p, 255) for t, p in zip(tasks, points))
    assert a.region.sum() > 3000 and b.region.sum() > 3000
    assert not (a.region & b.region).any()                 # never merged, nothing shared
    # each region lies on its own feature's disk (1 px of rounding beyond its rim) and off the other's
    for m, own, other in ((a, 0, 1), (b, 1, 0)):
        assert not (m.region & ~disk_pixels(pair.task, own, T, image.shape, 1.02)).any()
        assert not (m.region & disk_pixels(pair.task, other, T, image.shape, 1.0)).any()
    # the annotated captures of the run: one per feature
    assert (pair.out / "shot-0" / "capture-1-leaf_a.png").is_file()
    assert (pair.out / "shot-0" / "capture-1-leaf_b.png").is_file()


def test_a_gray_error_in_one_feature_does_not_leak_into_the_other(pair):
    image, T, points = shared_capture(pair)
    tasks = [pair.task.with_feature(f) for f in (0, 1)]
    before = [measurement.measure_feature(image, t, T, p, 255) for t, p in zip(tasks, points)]
    wrong = np.where(before[0].region, 0.5 * image, image)         # leaf_a half as bright
    after = [measurement.measure_feature(wrong, t, T, p, 255) for t, p in zip(tasks, points)]
    assert after[0].stats()["mean"] == pytest.approx(0.5 * before[0].stats()["mean"], rel=1e-9)
    assert after[1].stats() == before[1].stats()
    np.testing.assert_array_equal(after[1].surface, before[1].surface)


def measured(m):
    """(Iteration, Measurement, predicted) as loop.measure_capture gives them, the model exact."""
    return None, m, np.where(np.isfinite(m.sample_gray), m.sample_gray, 100.0)


def test_one_exposure_serves_features_that_agree_and_the_run_says_so_when_they_disagree(pair):
    image, T, points = shared_capture(pair)
    tasks = [pair.task.with_feature(f) for f in (0, 1)]
    base = [measurement.measure_feature(image, t, T, p, 255) for t, p in zip(tasks, points)]
    limits = [control.Limits((60.0, 250.0), (1e-5, 0.02), (1.4, 16.0))] * 2
    black = measurement.BlackLevel(0.0, 0.0, "task")
    names = ["leaf_a", "leaf_b"]
    # both a third as bright as measured (111-129 -> 37-43): one gain brightens both into the band
    dim = np.where(base[0].region | base[1].region, image / 3, image)
    ms = [measurement.measure_feature(dim, t, T, p, 255) for t, p in zip(tasks, points)]
    c = control.shared_correction(names, [measured(m) for m in ms], limits, 0.002, 1.4, black)
    assert c.action == "exposure"
    gain = c.shutter_s / c.f_number**2 / (0.002 / 1.4**2)
    lo, hi = min(m.min for m in ms), max(m.max for m in ms)
    # the joined range's geometric mean to the band's centre, its low end at least a quarter of
    # the high: sqrt(62.5 x 250) (evaluate.target_gray)
    assert gain == pytest.approx(np.sqrt(62.5 * 250) / np.sqrt(lo * hi), rel=1e-6)
    for m in ms:
        assert 60 <= gain * m.min and gain * m.max <= 250
    # leaf_a 5x brighter than leaf_b: each alone fits the band's 250/60 = 4.2, together they do not
    split = np.where(base[0].region, 1.6 * image, np.where(base[1].region, 0.35 * image, image))
    ms = [measurement.measure_feature(split, t, T, p, 255) for t, p in zip(tasks, points)]
    assert all(m.max / m.min < 250 / 60 for m in ms) and ms[0].max / ms[1].min > 250 / 60
    c = control.shared_correction(names, [measured(m) for m in ms], limits, 0.002, 1.4, black)
    assert c.action == "stop" and c.cause == "features"
    assert c.reason.startswith("the shot's features disagree: leaf_a") and "each alone would fit" in c.reason


def test_a_feature_that_stops_alone_is_named(pair):
    image, T, points = shared_capture(pair)
    tasks = [pair.task.with_feature(f) for f in (0, 1)]
    ms = [measurement.measure_feature(image, t, T, p, 255) for t, p in zip(tasks, points)]
    limits = [control.Limits((60.0, 250.0), (1e-5, 0.02), (1.4, 16.0))] * 2
    # leaf_b predicted 100x brighter than measured: an albedo x0.01, outside x0.1-x10
    wrong = [measured(ms[0]), (None, ms[1], 100 * measured(ms[1])[2])]
    c = control.shared_correction(["leaf_a", "leaf_b"], wrong, limits, 0.002, 1.4,
                                     measurement.BlackLevel(0.0, 0.0, "task"))
    assert c.action == "stop" and c.cause == "albedo" and c.reason.startswith("leaf_b: ")


# --- the run folder ------------------------------------------------------------------------

def test_a_folder_per_shot_with_its_captures_log_and_report(pair):
    for shot in pair.report["shots"]:
        folder = pair.out / shot["folder"]
        own = json.loads((folder / "report.json").read_text())
        assert own["shot"] == shot["shot"] and own["converged"] and own["features"] == shot["features"]
        assert {it["feature"] for it in own["iterations"]} == set(shot["features"])
        for it in own["iterations"]:
            assert (folder / it["capture"]).is_file() and (folder / it["annotated"]).is_file()
        lines = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        assert lines[-1]["step"] == "done" and lines[-1]["converged"]
        # every step of the shot's log is in the run's, in order, tagged with the shot
        tagged = [{k: v for k, v in line.items() if k != "shot"} for line in pair.log if line.get("shot") == shot["shot"]
                  and line["step"] not in ("shot", "shot_done")]
        assert tagged == lines


def test_the_report_holds_each_features_result_as_its_shot_measured_it(pair):
    report = pair.report
    assert {"plan", "iterations", "converged", "captures", "features", "shots", "order"} <= set(report)
    for f in report["features"]:
        own = json.loads((pair.out / f"shot-{f['shot']}" / "report.json").read_text())
        its = [it for it in own["iterations"] if it["feature"] == f["name"]]
        assert f["iterations"] == len(its) and f["measured_gray"] == its[-1]["measured_gray"]
        assert f["capture"] == f"shot-{f['shot']}/{its[-1]['capture']}"
    assert report["black_level"]["source"] == "dark frame"        # found once, in the first shot
    first = report["order"][0]
    assert [line["shot"] for line in pair.log if line["step"] == "black_level"] == [first]
    steps = [line["step"] for line in pair.log]
    assert steps[:2] == ["plan", "route"] and steps[-1] == "done"
    assert steps.count("shot") == steps.count("shot_done") == 2


def test_a_one_feature_shot_and_a_shared_shot_print_their_lines(pair, capsys):
    # the summary the CLI printed is in the module fixture's run; the log's messages say the same
    done = [line["message"] for line in pair.log if line["step"] == "shot_done"]
    assert any("leaf_a gray" in m and "leaf_b gray" in m for m in done)
    assert any("knuckle gray" in m for m in done)
    shots = [line["message"] for line in pair.log if line["step"] == "shot"]
    assert shots[0].startswith("shot 1 of 2") and shots[1].startswith("shot 2 of 2")


# --- what stops a run ------------------------------------------------------------------------

def test_a_partial_plan_is_refused_before_anything_moves_naming_the_uncovered_feature(tmp_path, capsys,
                                                                                      monkeypatch):
    from test_features import FEATURES
    assert FEATURES == PARTIAL
    out = tmp_path / "run"
    assert cli.main(["run", str(PARTIAL), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("cell run: infeasible: feature end_face: no shot covers it: camera view of the feature fails")
    run = read(out)
    assert run.report["message"].startswith("infeasible: feature 'end_face' is covered by no shot: camera_view binds")
    assert not {"move_camera", "move_lamp", "capture"} & {line["step"] for line in run.log}
    assert not run.report["converged"] and run.report["shots"] == []
    end = next(f for f in run.report["features"] if f["name"] == "end_face")
    assert end["shot"] is None and not end["converged"] and "covered by no shot" in end["reason"]


def test_a_fault_in_the_second_shot_exits_3_and_keeps_the_first_shots_measurements(tmp_path):
    task = load_task(PAIR)
    cell = SimpleNamespace(devices=None, stops=[])
    # the first shot (the knuckle's, by the route) takes the dark frame and one capture
    with pytest.raises(CellError) as failed:
        inspection.run(task, tmp_path, recording_connect(task.with_feature(0), cell,
                                                         {"camera_fail_on_capture": 3}))
    assert failed.value.exit_code == 3 and "motion stopped" in str(failed.value)
    assert cell.stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    run = read(tmp_path)
    assert run.report["fault"]["device"] == "camera" and not run.report["converged"]
    by = {f["name"]: f for f in run.report["features"]}
    assert by["knuckle"]["converged"] and by["knuckle"]["measured_gray"]["pixels"] > 500
    for name in ("leaf_a", "leaf_b"):
        assert not by[name]["converged"] and by[name]["measured_gray"] is None
        assert "capture timed out" in by[name]["reason"]
    assert run.log[-1]["step"] == "fault"
    second = json.loads((tmp_path / "shot-0" / "report.json").read_text())
    assert not second["converged"] and "capture timed out" in second["reason"]
    first = json.loads((tmp_path / "shot-1" / "report.json").read_text())
    assert first["converged"] and first["iterations"][-1]["measured_gray"] == by["knuckle"]["measured_gray"]


def test_a_wrong_albedo_is_corrected_in_each_shot_with_one_exposure_for_the_features_it_shares(tmp_path):
    from simcell import variant
    path = variant(tmp_path, PAIR, {"sim.truth.albedo_scale": 0.4,
                                    "sim.effects": ["shadows", "quantization", "noise", "black_level"]})
    assert cli.main(["run", str(path), "--out", str(tmp_path / "run")]) == 0
    run = read(tmp_path / "run")
    assert all(f["converged"] and f["iterations"] == 2 for f in run.report["features"])
    shared = json.loads((tmp_path / "run" / "shot-0" / "report.json").read_text())["iterations"]
    first, second = [it for it in shared if it["iteration"] == 1], [it for it in shared if it["iteration"] == 2]
    assert [it["feature"] for it in first] == [it["feature"] for it in second] == ["leaf_a", "leaf_b"]
    assert not all(it["in_band"] for it in first) and all(it["in_band"] for it in second)
    assert first[0]["correction"] == first[1]["correction"] and first[0]["correction"]["action"] == "exposure"
    assert len({it["shutter_s"] for it in second}) == 1                 # one exposure for both
    # the gain on G - b: the joined range's geometric mean to the band's centre (evaluate.target_gray)
    b = run.report["black_level"]["value"]
    lo = min(it["measured_gray"]["min"] for it in first) - b
    hi = max(it["measured_gray"]["max"] for it in first) - b
    low, high = 60 - b, 250 - b
    gain = np.sqrt(max(low, 0.25 * high) * high) / np.sqrt(lo * hi)
    k = (second[0]["shutter_s"] / second[0]["f_number"] ** 2) / (first[0]["shutter_s"] / first[0]["f_number"] ** 2)
    assert k == pytest.approx(gain, rel=1e-3)


def test_a_shot_that_does_not_converge_leaves_the_others_to_run_and_the_run_exits_1_naming_each(tmp_path, capsys):
    from simcell import variant
    path = variant(tmp_path, PAIR, {"sim.truth.albedo_scale": 0.46})       # out of band at first
    assert cli.main(["run", str(path), "--out", str(tmp_path / "run"), "--max-iterations", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    run = read(tmp_path / "run")
    assert [line["step"] for line in run.log].count("shot_done") == 2      # both shots ran
    assert not any(shot["converged"] for shot in run.report["shots"])
    assert err.startswith("cell run: 3 of 3 features not in band: leaf_a (shot 0): not every feature in band "
                          "after 1 iteration")
    assert "knuckle (shot 1): not in band 60-250 after 1 iteration" in err
    by = {f["name"]: f for f in run.report["features"]}
    # leaf_b alone read in band (61-64 at 0.46 of the albedo; leaf_a 56-59), but its shot did not
    # converge: not converged, with the shot's reason
    assert by["leaf_b"]["in_band"] and not by["leaf_b"]["converged"] and "leaf_a" in by["leaf_b"]["reason"]
    # the iterations ran out in each shot: each shot's cause, and the run's (its first feature's shot's)
    for shot in run.report["shots"]:
        assert json.loads((tmp_path / "run" / shot["folder"] / "report.json").read_text())["cause"] == "iterations"
    assert run.report["cause"] == "iterations" and run.report["status"] == "not_converged"


def test_the_rotation_angle_between_two_poses():
    from cell.core import geometry
    a = geometry.from_rpy(np.radians([10.0, -20.0, 30.0]), [1.0, 2.0, 3.0])
    turn = geometry.from_rpy(np.radians([0.0, 0.0, 25.0]))
    assert np.degrees(geometry.rotation_angle(a, a @ turn)) == pytest.approx(25.0, abs=1e-9)
    assert geometry.rotation_angle(a, a) == pytest.approx(0.0, abs=1e-6)


def test_features_whose_bands_share_nothing_are_not_corrected_toward_either(pair):
    image, T, points = shared_capture(pair)
    tasks = [pair.task.with_feature(f) for f in (0, 1)]
    ms = [measurement.measure_feature(image, t, T, p, 255) for t, p in zip(tasks, points)]
    limits = [control.Limits((60.0, 100.0), (1e-5, 0.02), (1.4, 16.0)),
              control.Limits((150.0, 250.0), (1e-5, 0.02), (1.4, 16.0))]
    c = control.shared_correction(["leaf_a", "leaf_b"], [measured(m) for m in ms], limits, 0.002, 1.4,
                                     measurement.BlackLevel(0.0, 0.0, "task"))
    assert c.action == "stop" and c.cause == "bands"
    assert "leaf_a 60-100, leaf_b 150-250" in c.reason


@pytest.mark.long
def test_a_part_offset_found_in_one_shot_is_applied_to_the_next_before_it_moves(tmp_path):
    """The hinge pair's part 12 mm x and 9 mm y off its fixture: the first shot visited (the
    knuckle's; at 8, 6 mm its registration alone follows the part and it converges without
    localizing) localizes it (two views) and carries its features along with the part; the second
    moves to its pose carried by the estimate without localizing again, and finds its feature
    where that model puts it."""
    from simcell import variant
    offset = [0.012, 0.009, 0.0]
    path = variant(tmp_path, PAIR, {"sim.truth.part_offset_m": offset})
    cli.main(["run", str(path), "--out", str(tmp_path / "run")])
    run = read(tmp_path / "run")
    first, second = run.report["order"]
    found = run.report["localization"]
    assert found["followed"] and found["part_offset_m"] == pytest.approx(offset, abs=1e-3)
    shots = {s: read(tmp_path / "run" / f"shot-{s}") for s in (first, second)}
    assert [line["step"] for line in shots[first].log].count("localize") == 1
    assert "localize" not in [line["step"] for line in shots[second].log]
    moved = next(line for line in shots[second].log if line["step"] == "move_camera")
    planned = shot_pose(run, second)[:3, 3]
    # carried along with the part: by the offset, and the estimate's turn about the first feature
    # (0.3 deg at 0.5 m: 2.6 mm)
    assert np.array(moved["position_m"]) == pytest.approx(planned + offset, abs=3e-3)
    for it in shots[second].report["iterations"]:
        assert it["registration"]["offset_m"] < 1e-3


@pytest.mark.long                       # one shot, 2 + 2 captures: 35 s at a load of 9
def test_a_shot_of_two_patches_with_bands_apart_is_rebalanced_on_basis_captures(tmp_path):
    """tests/tasks/features/plate_bar.yaml (one shot: the left patch asks 60-100, the right
    150-210, nothing in common) with the right bar giving 70 % of its model's light: the first
    capture leaves the right patch below its band, one basis capture per channel on measures
    each channel's share (the bar's 0.7, the spot's 1), the drives are re-solved with each sample
    in its own patch's band, and the second capture has both patches in their bands, each read
    here on its own pixels."""
    from simcell import variant
    path = variant(tmp_path, ROOT / "tests/tasks/features/plate_bar.yaml",
                   {"sim.truth.channel_power_scale": {2: 0.7}})
    assert cli.main(["run", str(path), "--out", str(tmp_path / "run"), "--yes"]) == 0
    run = read(tmp_path / "run")
    shot = json.loads((tmp_path / "run" / "shot-0" / "report.json").read_text())
    first = {it["feature"]: it for it in shot["iterations"] if it["iteration"] == 1}
    second = {it["feature"]: it for it in shot["iterations"] if it["iteration"] == 2}
    assert set(first) == set(second) == {"left", "right"}
    assert first["right"]["measured_gray"]["min"] < 150 and not first["right"]["in_band"]
    correction = first["left"]["correction"]
    assert correction == first["right"]["correction"] and correction["action"] == "drives"
    assert correction["channel_scale"]["2"] == pytest.approx(0.7, rel=0.03)
    assert correction["channel_scale"]["3"] == pytest.approx(1.0, rel=0.03)
    (basis,) = [line for line in run.log if line["step"] == "basis"]
    assert basis["channel_scale"] == correction["channel_scale"]
    assert second["left"]["drives"] == pytest.approx({k: float(v) for k, v in correction["drives"].items()}, abs=1e-3)
    task = load_task(path)
    image = cv2.imread(str(tmp_path / "run" / "shot-0" / second["left"]["capture"]), cv2.IMREAD_UNCHANGED)
    T = np.array(run.report["plan"]["shots"][0]["camera"]["T_cell_cam"])
    for f, (low, high) in ((0, (60, 100)), (1, (150, 210))):
        it = second[task.features[f].name]
        assert it["in_band"] and low <= it["measured_gray"]["min"] <= it["measured_gray"]["max"] <= high
        pixels = image[disk_pixels(task, f, T, image.shape, 0.8)]
        assert len(pixels) > 1000 and low <= pixels.min() and pixels.max() <= high
    assert all(f["converged"] and f["iterations"] == 2 for f in run.report["features"])
