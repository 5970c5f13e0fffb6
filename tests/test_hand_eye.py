"""`cell calibrate hand-eye`: the camera's focal length and T_flange_cam from views of the ChArUco
board (calibration.board), on the simulated cell with noise, black level and quantization and a
hand-eye error in the world (sim.truth.camera_offset_m / camera_rpy_deg) that the routine never
reads: it is handed the task with a neutral truth while the simulated cell renders the true one.
The expectation is the world's: the true camera frame is the reported one composed with the
truth's transform, so the true T_flange_cam is the task's hand-eye times it."""
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from cell.run import backends

from cell.core import geometry

from cell.calibration import hand_eye as routine
from cell.cli import main
from cell.core.errors import DeviceFault, GoalNotReached, TaskError
from cell.task.loader import load_task
from cell.physics.projection import intrinsics, project
from cell.task.types import Truth
from kernels.render import render_plane
from sim import board as sim_board
from sim.board import BoardView
from sim.cell import make_sim_devices

import simcell

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"
OFFSET_M, RPY_DEG = [0.0015, -0.002, 0.003], [0.8, -0.6, 1.2]
# the sensor at half the example's resolution, pixels twice as large: the same field of view, a
# quicker test (f = 25 mm / 9.3 um = 2688.2 px)
SMALL = {"camera.sensor.width_px": 516, "camera.sensor.height_px": 388, "camera.sensor.pixel_pitch_m": 9.3e-6}


def sim_task(tmp_path, **changes):
    return simcell.variant(tmp_path, HINGE, {"sim.effects": ["noise", "black_level", "quantization"],
                                             "sim.truth.camera_offset_m": OFFSET_M,
                                             "sim.truth.camera_rpy_deg": RPY_DEG, "sim.seed": 3,
                                             **SMALL, **changes})


def believed(task):
    """The task as the routine gets it: the world's truth taken away."""
    return replace(task, sim=replace(task.sim, truth=Truth()))


def true_hand_eye(task):
    return task.frames.T_flange_cam @ geometry.from_rpy(np.radians(RPY_DEG), OFFSET_M)


def pose_error(T, T_true):
    """(distance [m], angle [deg]) between two poses."""
    turn = Rotation.from_matrix(T[:3, :3].T @ T_true[:3, :3]).magnitude()
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(np.degrees(turn))


# --- the board, the textured plane and the simulator's frames ---------------------------------

def test_the_example_tasks_get_the_default_board_beside_the_part():
    for name in ("hinge", "conrod"):
        task = load_task(HINGE.parent / f"{name}.yaml")
        board = task.board
        assert board.squares == (9, 7) and board.dictionary == "DICT_5X5_100" and board.markers == 31
        low, high = task.part.mesh.bounds
        corners = geometry.apply(board.T_cell_board, [[0, 0, 0], [0.072, 0.056, 0]])
        assert corners[:, 1].min() > high[1]                     # beyond the part, nothing overlaps
        assert np.allclose(board.T_cell_board[:3, 2], [0, 0, -1])    # face up: z into the board


@pytest.mark.parametrize("changes, key, expected", [
    ({"calibration.board.marker_size_m": 0.008}, "calibration.board.marker_size_m", "less than square_size_m"),
    ({"calibration.board.dictionary": "DICT_4X4_50", "calibration.board.squares_x": 12,
      "calibration.board.squares_y": 9},
     "calibration.board.dictionary", "a dictionary of at least 54 markers"),
    ({"calibration.board.dictionary": "DICT_9X9_50"}, "calibration.board.dictionary", "one of DICT_4X4_50"),
])
def test_a_board_that_cannot_be_is_bad_input_naming_the_key(tmp_path, changes, key, expected):
    with pytest.raises(TaskError, match=f"{key}: found .*, expected {expected}"):
        load_task(simcell.variant(tmp_path, HINGE, changes))


def test_a_ray_meets_the_textured_plane_where_the_geometry_says():
    """The plane z = 1 (its x, y the world's), texels of 0.5 m: by hand, the ray (1, 0.6, 1) meets
    it at (1, 0.6, 1), texel (row 1, col 2), depth sqrt(2.36); a ray away from it misses, one
    beyond the texture gets `outside`."""
    T = geometry.transform(translation=(0.0, 0.0, 1.0))
    texture = np.arange(12.0).reshape(3, 4)
    result = render_plane([0, 0, 0], [[1.0, 0.6, 1.0], [0, 0, -1.0], [5.0, 0.1, 1.0]], T, texture, 0.5, outside=-7)
    assert result.value.tolist() == [6.0, 0.0, -7.0] and result.hit.tolist() == [True, False, True]
    assert result.depth[0] == pytest.approx(np.sqrt(2.36)) and np.isinf(result.depth[1])


def test_the_board_s_white_is_eq_17_and_its_corners_land_where_the_true_camera_projects_them(tmp_path):
    """No effects: a white pixel's gray is c A E a t / (8 kappa^2) by hand; the ChArUco corners
    the detector finds in every other of the routine's 10 views lie within 0.15 px rms (0.35 px at worst) of the
    board's corners projected through the true camera pose (the reported one composed with the
    hand-eye error)."""
    task = load_task(simcell.variant(tmp_path, HINGE, {**SMALL, "sim.effects": [],
                                                       "sim.truth.camera_offset_m": OFFSET_M,
                                                       "sim.truth.camera_rpy_deg": RPY_DEG}))
    view = BoardView(task)
    K = intrinsics(task.camera.sensor, task.camera.lens)
    white = 1.5e16 * (9.3e-6) ** 2 * sim_board.AMBIENT_IRRADIANCE * sim_board.PRINT_WHITE * 2e-3 / (8 * 64)
    errors = []
    for T in routine.viewpoints(task.board, routine.viewing_distance(task), 10)[::2]:
        image = view(T, None, None, 2e-3, 8.0)
        assert image.max() == pytest.approx(white, rel=1e-9)
        obj, img, _, _ = routine.detect(task.board, np.clip(image * 200 / white, 0, 255).astype(np.uint8))
        uv, _ = project(K, T @ geometry.from_rpy(np.radians(RPY_DEG), OFFSET_M),
                        geometry.apply(task.board.T_cell_board, obj))
        assert len(obj) >= 20
        errors.append(np.linalg.norm(img - uv, axis=1))
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.15 and errors.max() < 0.35


# --- the routine on the simulated cell ---------------------------------------------------------

@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """One run of the CLI on the simulated cell (10 viewpoints) and the same run by routine.run
    with the truth taken away from the task: (task, the CLI's --json, its run folder, the result)."""
    tmp_path = tmp_path_factory.mktemp("hand-eye")
    path = sim_task(tmp_path)
    task = load_task(path)
    result = routine.run(believed(task), tmp_path / "direct", lambda: make_sim_devices(task, None, board=True),
                         tmp_path / "direct.yaml", poses=10)
    return task, path, result, tmp_path


def test_the_hand_eye_is_the_world_s_within_1_mm_and_0_2_deg_and_f_within_0_5_percent(calibrated):
    task, _, result, _ = calibrated
    distance, angle = pose_error(result.hand_eye.T_flange_cam, true_hand_eye(task))
    assert distance < 1e-3 and angle < 0.2
    assert result.hand_eye.focal_length_px == pytest.approx(0.025 / 9.3e-6, rel=0.005)
    assert result.intrinsics.focal_length_px == pytest.approx(0.025 / 9.3e-6, rel=0.005)
    assert result.intrinsics.rms_px < 0.3 and result.hand_eye.reprojection_error_px < 0.3
    # the world's error is far larger than what is left: the routine measured it, not the task's
    assert pose_error(task.frames.T_flange_cam, true_hand_eye(task))[0] > 3e-3


def test_every_method_is_compared_and_the_refined_result_reprojects_best(calibrated):
    _, _, result, _ = calibrated
    assert set(result.methods) == set(routine.METHODS)
    for linear in result.methods.values():
        assert pose_error(linear.T_flange_cam, result.hand_eye.T_flange_cam)[0] < 5e-3
        assert result.hand_eye.reprojection_error_px <= linear.reprojection_error_px + 1e-9
    assert result.hand_eye.board_spread_m < 1e-3 and result.refinement["success"]


def test_the_run_folder_holds_the_evidence_and_the_hand_eye_file_is_the_task_s_keys(calibrated, tmp_path):
    task, path, result, folder = calibrated
    run = folder / "direct"
    written = json.loads((run / "calibration.json").read_text())
    assert written["hand_eye_position_m"] == pytest.approx(result.hand_eye.position_m.tolist())
    assert {m["method"] for m in written["methods"].values()} == set(routine.METHODS)
    assert len(written["views"]) == 10 and written["refused"] == []
    for view in written["views"]:
        picture = cv2.imread(str(run / f"board-{view['pose']}.png"))
        assert picture.shape == (388, 516, 3) and view["corners"] >= routine.MIN_CORNERS
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert steps[0] == "setup" and steps[-1] == "done" and steps.count("board") == 10
    assert len(list(run.glob("capture-*.png"))) == steps.count("capture") >= 10      # every frame, as taken
    # a task takes the file as cell.arm.hand_eye (relative to the task file), or its keys copied
    keys = yaml.safe_load((folder / "direct.yaml").read_text())["cell"]["arm"]
    copied = load_task(simcell.variant(tmp_path, path, {"cell.arm.hand_eye_position_m": keys["hand_eye_position_m"],
                                                        "cell.arm.hand_eye_rpy_deg": keys["hand_eye_rpy_deg"]}))
    referencing = load_task(simcell.variant(folder, path, {"cell.arm.hand_eye": "direct.yaml"}))
    assert referencing.cell.devices.arm.hand_eye_file == folder / "direct.yaml"
    for fixed in (copied, referencing):
        distance, angle = pose_error(fixed.frames.T_flange_cam, result.hand_eye.T_flange_cam)
        assert distance < 1e-6 and angle < 1e-3


def test_the_cli_answers_its_prompt_with_yes_prints_the_json_keys_and_never_overwrites(calibrated, capsys):
    task, path, _, folder = calibrated
    out, hand_eye_file = folder / "cli", folder / "cli.yaml"
    args = ["calibrate", "hand-eye", str(path), "--out", str(out), "--hand-eye-file", str(hand_eye_file),
            "--poses", "10", "--yes", "--json"]
    assert main(args) == 0
    captured = capsys.readouterr()
    printed = json.loads(captured.out)
    assert {"hand_eye_position_m", "hand_eye_rpy_deg", "focal_length_px", "reprojection_error_px"} <= printed.keys()
    T = geometry.from_rpy(np.radians(printed["hand_eye_rpy_deg"]), printed["hand_eye_position_m"])
    distance, angle = pose_error(T, true_hand_eye(task))
    assert distance < 1e-3 and angle < 0.2
    assert "lay the ChArUco board" in captured.err and "confirmed automatically: --yes" in captured.err
    before = hand_eye_file.read_text()
    assert main(args[:3] + ["--out", str(folder / "again")] + args[5:]) == 2
    assert capsys.readouterr().err.startswith(f"cell calibrate: command line: --hand-eye-file: found {hand_eye_file}, "
                                              "a file that exists, expected a new file, or --force")
    assert hand_eye_file.read_text() == before and not (folder / "again").exists()


def test_fewer_than_10_poses_is_bad_input(capsys):
    assert main(["calibrate", "hand-eye", str(HINGE), "--poses", "9"]) == 2
    assert "--poses: found 9, expected an integer >= 10" in capsys.readouterr().err


def test_a_device_fault_stops_the_cell_and_is_recorded(tmp_path):
    task, stops = load_task(sim_task(tmp_path)), []
    with pytest.raises(DeviceFault, match="protective stop during move 3.*motion stopped"):
        routine.run(believed(task), tmp_path / "run", lambda: simcell.record_stops(
            make_sim_devices(task, None, board=True, faults={"arm_fail_on_move": 3}), stops),
                    tmp_path / "hand-eye.yaml", poses=10)
    assert stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    written = json.loads((tmp_path / "run" / "calibration.json").read_text())
    assert written["fault"]["device"] == "arm" and written["hand_eye"] is None
    assert json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[-1])["step"] == "fault"
    assert not (tmp_path / "hand-eye.yaml").exists()


def test_a_board_not_where_the_task_says_is_refused_with_the_reason(tmp_path):
    """The world's board at the default place, the task's 30 cm off: no view sees it (exit 1)."""
    task = load_task(sim_task(tmp_path))
    elsewhere = replace(task.board, T_cell_centre=geometry.transform(task.board.T_cell_centre[:3, :3],
                                                                     [0.3, 0.08, 0.0]))
    with pytest.raises(GoalNotReached, match=r"the board was seen at 0 of 10 viewpoints \(\d+ refused by the arm, "
                                             r"\d+ with fewer than 8 corners\)"):
        routine.run(replace(believed(task), board=elsewhere), tmp_path / "run",
                    lambda: make_sim_devices(task, None, board=True), tmp_path / "hand-eye.yaml", poses=10)


def test_the_cli_turns_a_camera_fault_into_exit_3_and_one_line_after_stopping_the_cell(tmp_path, monkeypatch, capsys):
    stops = []
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes, board: simcell.record_stops(
        make_sim_devices(task, scene, board=board, faults={"camera_fail_on_capture": 3}), stops))
    out = tmp_path / "run"
    assert main(["calibrate", "hand-eye", str(sim_task(tmp_path)), "--out", str(out), "--poses", "10"]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell calibrate: camera: capture timed out") and "motion stopped" in last
    assert stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    assert json.loads((out / "calibration.json").read_text())["fault"]["device"] == "camera"
    assert json.loads((out / "log.jsonl").read_text().splitlines()[-1])["step"] == "fault"
    assert not (tmp_path / "hand-eye.yaml").exists()


def test_on_the_real_cell_the_operator_lays_the_board_before_anything(tmp_path, monkeypatch, capsys):
    connected = []
    monkeypatch.setattr(backends, "open_devices", lambda *a, **k: connected.append(a))
    task = sim_task(tmp_path, **{"cell.backend": "hw", "cell.arm.host": "127.0.0.1", "cell.pan_tilt.port": "/dev/null"})
    assert main(["calibrate", "hand-eye", str(task), "--out", str(tmp_path / "r")]) == 3     # stdin: no terminal
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "lay the ChArUco board" in last and "run with --yes" in last and connected == []
    assert not (tmp_path / "r").exists()
