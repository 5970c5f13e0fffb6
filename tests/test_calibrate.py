"""Camera-constant calibration: the fit on a hand-made line G = b + c x, the shutter sweep, and
`cell calibrate` end to end on the simulated cell against the world's truth (sim.world: the true
c is the task's times sim.truth.camera_constant_scale, the black level BLACK_LEVEL of full scale);
bad input exits 2, an infeasible plan 1 before anything moves, a device fault 3 after the stop."""
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cell.run import backends

from cell.calibration import reference_part
from cell.calibration.reference_part import fit_camera_constant, shutter_sweep
from cell.cli import main
from cell.core.errors import CellError, DeviceFault, PlanInfeasible
from cell.task.loader import load_task
from sim.cell import make_sim_devices

import simcell

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"
C_TASK = 1.5e16                 # tasks/hinge.yaml camera.sensor.camera_constant


HW = {"cell.backend": "hw", "cell.arm.host": "127.0.0.1", "cell.pan_tilt.port": "/dev/null"}


def variant(tmp_path, changes):
    return simcell.variant(tmp_path, HINGE, changes)


def calibrate_sim(task_path, out, faults=None, shots=6):
    """reference_part.run on the simulated cell; records the stops and closes the devices receive and
    whether `connect` was called at all."""
    task = load_task(task_path)
    cell = SimpleNamespace(devices=None, stops=[], error=None, result=None, out=Path(out))
    try:
        cell.result = reference_part.run(task, out, simcell.recording_connect(task, cell, faults), shots)
    except CellError as err:
        cell.error = err
    cell.written = json.loads((cell.out / "calibration.json").read_text())
    return cell


# --- the fit -----------------------------------------------------------------------------------

@settings(max_examples=50, deadline=None)
@given(c=st.floats(1e14, 1e18), black=st.floats(0.0, 20.0), seed=st.integers(0, 2**31 - 1))
def test_fit_recovers_constant_and_black_level_and_ignores_saturated_pairs(c, black, seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.1, 1.0, size=(6, 64)) * 300.0 / c          # gray up to ~300 + black
    gray = black + c * x + rng.normal(0.0, 0.5, x.shape)
    clipped = np.minimum(gray, 255.0)
    fit = fit_camera_constant(x, clipped, 255.0)
    assert fit.saturated == int(np.sum(gray >= 255.0))
    assert fit.used + fit.saturated == x.size
    assert abs(fit.camera_constant / c - 1.0) < 6 * fit.stderr / c + 1e-9
    assert abs(fit.black_level - black) < 2.0
    assert 0.99 < fit.r2 <= 1.0


def test_readings_at_0_are_left_out_like_saturated_ones():
    x = np.outer([1.0, 2.0, 4.0], np.linspace(1.0, 2.0, 8)) * 1e-15
    gray = np.maximum(2e16 * x - 30.0, 0.0)                       # the dimmest read 0 (clipped)
    fit = fit_camera_constant(x, gray, 255.0)
    assert fit.dark == int(np.sum(gray == 0)) > 0
    assert fit.camera_constant == pytest.approx(2e16) and fit.black_level == pytest.approx(-30.0)


def test_fit_is_none_when_nothing_usable():
    x = np.full((3, 10), 1e-16)
    assert fit_camera_constant(x, np.full(x.shape, 255.0), 255.0) is None       # all saturated
    assert fit_camera_constant(x, np.full(x.shape, 100.0), 255.0) is None       # no spread in P t
    assert fit_camera_constant(x, np.full(x.shape, np.nan), 255.0) is None      # samples off image
    x = np.outer([1.0, 2.0, 3.0], np.linspace(1.0, 2.0, 10)) * 1e-15
    gray = np.vstack([1e17 * x[0], np.full((2, 10), 255.0)])
    assert fit_camera_constant(x, gray, 255.0) is None          # one shot only: no sweep left


# --- the sweep ---------------------------------------------------------------------------------

def test_sweep_spans_dim_to_near_saturation_by_the_model():
    # planned 6 ms gives the brightest sample 120 of 255: G ~ t
    t = shutter_sweep(6e-3, 120.0, 255.0, (1e-5, 0.02), 5)
    assert len(t) == 5 and np.all(np.diff(t) > 0)
    brightest = 120.0 * t / 6e-3
    assert brightest[0] == pytest.approx(0.1 * 255) and brightest[-1] == pytest.approx(0.9 * 255)
    assert np.allclose(t[1:] / t[:-1], t[1] / t[0])             # geometric


def test_sweep_is_clipped_to_the_shutter_range_and_refused_when_none_is_left():
    t = shutter_sweep(6e-3, 120.0, 255.0, (2e-3, 1e-2), 4)
    assert t[0] == 2e-3 and t[-1] == 1e-2 and len(np.unique(t)) == 4
    with pytest.raises(PlanInfeasible, match="no shutter sweep"):
        shutter_sweep(6e-3, 120.0, 255.0, (6e-3, 6e-3), 4)


# --- end to end on the simulated cell ----------------------------------------------------------

def test_cli_calibrates_the_hinge_and_writes_the_fit_and_the_picture(tmp_path, capsys):
    assert main(["calibrate", "reference-part", str(HINGE), "--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "calibration.json").read_text())
    assert (tmp_path / "calibration.png").stat().st_size > 0
    fit = written["fit"]
    assert fit["camera_constant"] == pytest.approx(C_TASK, rel=0.01)      # neutral truth
    assert abs(fit["black_level"]) < 1.0 and fit["r2"] > 0.999 and fit["saturated"] == 0
    assert written["camera_constant_ratio"] == pytest.approx(fit["camera_constant"] / C_TASK)
    assert written["plan"]["feasible"] and written["reason"] == ""
    shots = written["shots"]
    assert len(shots) == 6 == len({s["shutter_s"] for s in shots})
    # dim to near (not at) saturation: the model is right here, so the gray says so directly
    assert shots[0]["gray_max"] < 0.2 * 255 and 0.75 * 255 < shots[-1]["gray_max"] < 255
    out = capsys.readouterr().out
    assert "camera constant c = " in out and "set camera.sensor.camera_constant" in out


@pytest.mark.parametrize("scale", [0.8, 1.4])
def test_fit_finds_the_true_camera_constant(tmp_path, scale):
    cell = calibrate_sim(variant(tmp_path, {"sim.truth.camera_constant_scale": scale}), tmp_path / "c")
    assert cell.error is None
    fit = cell.result.fit
    assert fit.camera_constant == pytest.approx(scale * C_TASK, rel=0.01)
    assert cell.result.camera_constant_ratio == pytest.approx(scale, rel=0.01)
    assert fit.r2 > 0.999
    if scale > 1:       # brighter than the model: the top shots saturate and are left out
        assert fit.saturated > 0 and fit.saturated + fit.used == 6 * 64
    assert cell.stops == ["camera.close"]                       # closed normally, no fault stop


def test_fit_finds_the_black_level(tmp_path):
    effects = ["shadows", "cone_falloff", "black_level", "quantization"]
    cell = calibrate_sim(variant(tmp_path, {"sim.effects": effects,
                                            "sim.truth.camera_constant_scale": 0.8}), tmp_path / "c")
    fit = cell.result.fit
    assert fit.black_level == pytest.approx(round(0.02 * 255), abs=0.5)     # sim.world: 5 gray
    assert fit.camera_constant == pytest.approx(0.8 * C_TASK, rel=0.01)


def test_fit_under_sensor_noise_is_within_its_standard_error(tmp_path):
    effects = ["shadows", "cone_falloff", "noise", "black_level", "quantization"]
    cell = calibrate_sim(variant(tmp_path, {"sim.effects": effects,
                                            "sim.truth.camera_constant_scale": 0.8}), tmp_path / "c")
    fit = cell.result.fit
    c_true = 0.8 * C_TASK
    assert abs(fit.camera_constant - c_true) < 4 * fit.stderr + 0.002 * c_true
    assert fit.camera_constant == pytest.approx(c_true, rel=0.01)
    assert fit.black_level == pytest.approx(5.0, abs=1.0)


# --- what stops it -----------------------------------------------------------------------------

@pytest.mark.parametrize("argv", [["--shots", "2"], ["--shots", "-1"]])
def test_bad_shots_is_bad_input_in_one_line(argv, capsys):
    assert main(["calibrate", "reference-part", str(HINGE), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"cell calibrate: command line: --shots: found {argv[1]}, expected an integer >= 3"]


def test_an_infeasible_plan_exits_1_before_anything_moves(tmp_path, monkeypatch, capsys):
    connected = []
    monkeypatch.setattr(backends, "open_devices", lambda *a, **k: connected.append(a))
    task = variant(tmp_path, {"camera.shutter_range_ms": [0.01, 0.02]})
    assert main(["calibrate", "reference-part", str(task), "--out", str(tmp_path / "c")]) == 1
    assert connected == []
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell calibrate: infeasible: ") and "fails" in last      # in words on the terminal
    written = json.loads((tmp_path / "c" / "calibration.json").read_text())
    assert written["fit"] is None and written["shots"] == [] and " binds: " in written["reason"]    # names in JSON


def test_a_camera_fault_stops_all_motion_and_exits_3(tmp_path):
    cell = calibrate_sim(HINGE, tmp_path, faults={"camera_fail_on_capture": 2})
    assert isinstance(cell.error, DeviceFault) and cell.error.exit_code == 3
    assert cell.error.device == "camera" and "motion stopped" in str(cell.error)
    assert cell.stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    assert len(cell.written["shots"]) == 1 and cell.written["fit"] is None     # what was measured
    assert cell.written["fault"]["device"] == "camera" and not cell.written["fault"]["stop_failures"]


def test_a_servo_fault_turns_its_torque_off(tmp_path):
    cell = calibrate_sim(HINGE, tmp_path, faults={"lamp_fail_on_move": 1})
    assert isinstance(cell.error, DeviceFault) and "Hardware Error Status" in str(cell.error)
    assert cell.stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    assert not any(cell.devices.lamp.torque.values())


def test_the_cli_turns_a_fault_into_exit_3_and_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes:
                        make_sim_devices(task, scene, faults={"camera_fail_on_capture": 1}))
    assert main(["calibrate", "reference-part", str(HINGE), "--out", str(tmp_path)]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell calibrate: camera: capture timed out") and "motion stopped" in last


def test_the_task_backend_is_used_unless_overridden(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes:
                        seen.append(backend) or make_sim_devices(task, scene))
    task = variant(tmp_path, HW)        # the real cell named (never reached: open_devices is patched)
    quick = ["--shots", "3", "--out"]
    assert main(["calibrate", "reference-part", str(task), "--yes", *quick, str(tmp_path / "a")]) == 0
    assert main(["calibrate", "reference-part", str(task), "--backend", "sim", *quick, str(tmp_path / "b")]) == 0
    assert seen == ["hw", "sim"]


def test_on_the_real_cell_the_operator_confirms_the_reference_part_before_anything(tmp_path, monkeypatch,
                                                                                    capsys):
    connected = []
    monkeypatch.setattr(backends, "open_devices", lambda *a, **k: connected.append(a))
    task = variant(tmp_path, HW)
    assert main(["calibrate", "reference-part", str(task), "--out", str(tmp_path / "c")]) == 3    # stdin: no terminal
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "place the reference part" in last and "run with --yes" in last and connected == []
