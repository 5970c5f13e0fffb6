"""Every routine's result file says its verdict in the same keys (docs/formats.md, "Result files"):
`cell run` of one feature and of several (report.json, and each shot's), the three calibrations
(calibration.json) and `cell measure-brdf` (measurement.json), run on the simulated cell through
the command line, each once reaching its goal and once not; success and status agree with the
exit code, and the keys each file had before the shared verdict are still there."""
import json
from dataclasses import replace
from pathlib import Path

import pytest

from cell.calibration import hand_eye
from cell.cli import main
from cell.core import geometry
from cell.core.errors import GoalNotReached
from cell.run import backends
from cell.task.loader import load_task
from sim.cell import make_sim_devices

import simcell
from test_camera_constant import POWER_W, sim_task as laser_task
from test_goniometer import sim_task as goniometer_task
from test_hand_eye import believed, sim_task as board_task

ROOT = Path(__file__).resolve().parent.parent
HINGE = ROOT / "tasks" / "hinge.yaml"
PAIR = ROOT / "tests" / "tasks" / "features" / "hinge_pair.yaml"        # 3 features, 2 shots
PARTIAL = ROOT / "tests" / "tasks" / "features" / "hinge.yaml"          # end_face covered by no shot
VERDICT = {"success", "status", "message", "cause", "fault", "counters"}
# the statuses an exit code allows: 0 the goal reached, 1 not reached, 3 a device fault
STATUS_OF_EXIT = {0: {"converged", "calibrated", "measured"},
                  1: {"not_converged", "not_calibrated", "not_measured", "infeasible"}, 3: {"fault"}}


def run(tmp_path, monkeypatch):
    return main(["run", str(HINGE), "--out", str(tmp_path / "out")]), ["report.json"]


def run_out_of_iterations(tmp_path, monkeypatch):
    task = simcell.variant(tmp_path, HINGE, {"sim.truth.albedo_scale": 0.7})
    return main(["run", str(task), "--max-iterations", "1", "--out", str(tmp_path / "out")]), ["report.json"]


def run_with_a_camera_fault(tmp_path, monkeypatch):
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes: make_sim_devices(
        task, scene, faults={"camera_fail_on_capture": 2}))
    return main(["run", str(HINGE), "--out", str(tmp_path / "out")]), ["report.json"]


def run_of_several_shots(tmp_path, monkeypatch):
    code = main(["run", str(PAIR), "--out", str(tmp_path / "out")])
    return code, ["report.json", "shot-0/report.json", "shot-1/report.json"]


def run_of_a_partial_plan(tmp_path, monkeypatch):
    return main(["run", str(PARTIAL), "--out", str(tmp_path / "out")]), ["report.json"]


def reference_part(tmp_path, monkeypatch):
    return main(["calibrate", "reference-part", str(HINGE), "--out", str(tmp_path / "out")]), ["calibration.json"]


def reference_part_infeasible(tmp_path, monkeypatch):
    task = simcell.variant(tmp_path, HINGE, {"camera.shutter_range_ms": [0.01, 0.02]})
    return main(["calibrate", "reference-part", str(task), "--out", str(tmp_path / "out")]), ["calibration.json"]


def camera_constant(power_w):
    def routine(tmp_path, monkeypatch):
        argv = ["calibrate", "camera-constant", str(laser_task(tmp_path)), "--laser-power-w", str(power_w)]
        return main([*argv, "--out", str(tmp_path / "out")]), ["calibration.json"]
    return routine


def measure_brdf(goniometer_keys):
    def routine(tmp_path, monkeypatch):
        task = goniometer_task(tmp_path, goniometer_keys)
        return main(["measure-brdf", str(task), "--out", str(tmp_path / "out")]), ["measurement.json"]
    return routine


def calibrate_hand_eye(tmp_path, monkeypatch):
    argv = ["calibrate", "hand-eye", str(board_task(tmp_path)), "--poses", "10", "--out", str(tmp_path / "out")]
    return main(argv), ["calibration.json"]


def hand_eye_without_the_board(tmp_path, monkeypatch):
    """The task's board 30 cm from the world's: no view sees it (the routine's function: the
    command line's task is the world's)."""
    task = load_task(board_task(tmp_path))
    elsewhere = replace(task.board, T_cell_centre=geometry.transform(task.board.T_cell_centre[:3, :3],
                                                                     [0.3, 0.08, 0.0]))
    try:
        hand_eye.run(replace(believed(task), board=elsewhere), tmp_path / "out",
                     lambda: make_sim_devices(task, None, board=True), tmp_path / "hand-eye.yaml", poses=10)
    except GoalNotReached as err:
        return err.exit_code, ["calibration.json"]
    return 0, ["calibration.json"]


# (routine, its status, its cause, a counter and its value: None for any count)
CASES = {
    "run": (run, "converged", None, ("iterations", None)),
    "run out of iterations": (run_out_of_iterations, "not_converged", "iterations", ("iterations", 1)),
    "run with a camera fault": (run_with_a_camera_fault, "fault", "fault", ("iterations", 0)),
    "run of several shots": (run_of_several_shots, "converged", None, ("shots", 2)),
    "run of a partial plan": (run_of_a_partial_plan, "infeasible", "infeasible", ("shots", 0)),
    "reference part": (reference_part, "calibrated", None, ("shots", 6)),
    "reference part, infeasible": (reference_part_infeasible, "infeasible", "infeasible", ("shots", 0)),
    "laser": (camera_constant(POWER_W), "calibrated", None, ("frames_used", 8)),
    "laser, saturated": (camera_constant(1e-5), "not_calibrated", "saturated", ("frames_used", 0)),
    "goniometer": (measure_brdf({"phase_deg": [30], "step_deg": 10, "max_angle_deg": 60}), "measured", None,
                   ("poses", None)),
    "goniometer, too few readings": (measure_brdf({"phase_deg": [40], "step_deg": 10, "max_angle_deg": 25}),
                                     "not_measured", "too_few_readings", ("poses", 1)),
    "hand-eye": (calibrate_hand_eye, "calibrated", None, ("views", 10)),
    "hand-eye, board not seen": (hand_eye_without_the_board, "not_calibrated", "too_few_views", ("views_used", 0)),
}


@pytest.mark.parametrize("case", CASES)
def test_every_result_file_has_the_same_verdict_keys_agreeing_with_the_exit_code(case, tmp_path, monkeypatch):
    routine, status, cause, (counter, count) = CASES[case]
    code, files = routine(tmp_path, monkeypatch)
    assert code in STATUS_OF_EXIT, case
    documents = [json.loads((tmp_path / "out" / name).read_text()) for name in files]
    for name, document in zip(files, documents):
        assert VERDICT <= document.keys(), name
        assert document["success"] is (code == 0) and document["status"] in STATUS_OF_EXIT[code], name
        assert (document["message"] == "") is (code == 0) and document["reason"] == document["message"], name
        assert (document["fault"] is not None) is (code == 3), name
        counters = document["counters"]
        assert counters and all(isinstance(n, int) and n >= 0 for n in counters.values()), name
        if name == "report.json" or name.endswith("/report.json"):      # what its readers know it by
            assert document["converged"] is document["success"], name
    run_file = documents[0]
    assert run_file["status"] == status and run_file["cause"] == cause
    assert count is None or run_file["counters"][counter] == count
    if code == 3:
        assert run_file["fault"]["device"] == "camera"


def test_the_formats_page_names_every_verdict_key_and_status_with_its_exit_code():
    from cell.report.result import STATUSES
    text = (ROOT / "docs" / "formats.md").read_text()
    start = text.index("\n## Result files")
    section = text[start:text.index("\nThe causes:", start)]     # the verdict's two tables (a run's own keys follow)
    cells = [[c.strip() for c in line.split("|")[1:-1]] for line in section.splitlines() if line.startswith("| `")]
    keys = {c[0].strip("`") for c in cells if len(c) == 2}
    statuses = {c[0].strip("`"): c[2] for c in cells if len(c) == 3}
    assert keys == VERDICT and statuses.keys() == STATUSES.keys()
    for code, allowed in STATUS_OF_EXIT.items():
        assert {s for s, exit_code in statuses.items() if exit_code == str(code)} == allowed
