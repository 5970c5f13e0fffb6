"""cell measure-brdf on the simulated cell (noise, black level, quantization on): a world whose
material differs from the task's is measured as a goniometer without the routine ever reading
the truth; poses the arm or the rig refuse are skipped with the reason; a spike narrower than the
step is reported unresolved, a wider one measured; --yes answers the prompt; a fault exits 3."""
import io
import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.run import backends

from cell.calibration import goniometer
from cell.physics import brdf_fit
from cell.cli import main
from cell.core.errors import DeviceFault, GoalNotReached, TaskError
from cell.task.loader import load_material, load_task
from cell.devices.operator import Operator
from sim.arm import SimArm
from sim.cell import make_sim_devices

import simcell

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"
EFFECTS = ["noise", "black_level", "quantization"]
WORLD = {"rho": 0.08, "sigma1": 2.5, "m1": 10.0, "sigma2": 20.0, "m2": 800.0}   # the task's: 0.03, 4, 6, 30, 400


def world_material(tmp_path, **changes):
    values = WORLD | changes
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump({"name": "the world's metal", "source": "test truth", "phase_deg": [0, 90],
                                    **{k: [v, v] for k, v in values.items()}}))
    return path


def sim_task(tmp_path, goniometer_keys, **world):
    """The hinge on a simulated cell with noise, black level and quantization, the world's
    material not the task's, the sensor cut to 320 x 240 px (the patch is at its centre)."""
    return simcell.variant(tmp_path, HINGE, {
        "sim.effects": EFFECTS, "sim.truth.material": str(world_material(tmp_path, **world)),
        "camera.sensor.width_px": 320, "camera.sensor.height_px": 240,
        "calibration.goniometer": goniometer_keys})


class Unread:
    """A truth the routine must not read: any attribute is an error."""

    def __getattr__(self, name):
        raise AssertionError(f"the routine read the simulator's truth ({name})")


def measure(task_path, out, faults=None, operator=None):
    """goniometer.run handed the task without its truth; the simulated cell renders the truth.
    Returns (result or the error, the cell's safe-stop calls, measurement.json)."""
    true = load_task(task_path)
    believed = replace(true, sim=replace(true.sim, truth=Unread()))
    staged, cell = goniometer.sample_task(true), simcell.SimpleNamespace(devices=None, stops=[])
    connect = simcell.recording_connect(staged, cell, faults=faults)
    try:
        result = goniometer.run(believed, out, connect, operator or Operator(yes=True, stdout=io.StringIO()))
    except Exception as err:                                    # noqa: BLE001 - returned for the test to judge
        result = err
    return result, cell.stops, json.loads((Path(out) / "measurement.json").read_text())


@pytest.mark.long
def test_the_world_s_rho_sigma1_m1_are_recovered_and_the_narrow_spike_is_unresolved(tmp_path):
    task = sim_task(tmp_path, {"phase_deg": [30, 60], "step_deg": 8, "max_angle_deg": 85})
    result, _, written = measure(task, tmp_path / "run")
    assert result.success, result.message
    doc = result.material
    assert doc["phase_deg"] == [30.0, 60.0]
    for key in ("rho", "sigma1", "m1"):
        assert np.allclose(doc[key], WORLD[key], rtol=0.05), (key, doc[key])
        assert all(0 < s < 0.05 * WORLD[key] for s in doc[f"{key}_stderr"]), key
    # m2 800 is narrower than an 8 deg step sees (M = ln 2 / (2 step^2) = 17.8): not invented
    m_max = np.log(2) / (2 * np.radians(8) ** 2)
    assert doc["unresolved"] == {"terms": {"spike": [30.0, 60.0]}, "step_deg": 8.0,
                                 "resolvable_m_max": pytest.approx(m_max, rel=1e-5)}
    assert doc["sigma2"] == [0.0, 0.0] and np.isinf(doc["sigma2_stderr"]).all() and np.isinf(doc["m2_stderr"]).all()
    # refused and counted: the lamp overhead (tilt beyond 85 deg), the camera below the workspace (z < 0.10 m)
    reasons = [r["reason"] for r in written["refused"]]
    assert any(r.startswith("pan-tilt: tilt") for r in reasons)
    assert any(r.startswith("arm: camera at") and "outside the workspace" in r for r in reasons)
    assert len(result.readings) + len(result.refused) + len(result.failed) == result.poses
    # the world is brighter than the task's guess: the clipped first takes were taken again, shorter
    assert any(r.takes > 1 for r in result.readings)
    lines = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    clipped = [line for line in lines if line["step"] == "patch" and line["clipped"]]
    assert clipped and all(r.signal < 255 - 5 for r in result.readings)
    assert any(line["message"].startswith(f"pose 1 of {result.poses}") for line in lines)   # progress
    # the files: the CSV the fitter reads, the material a task loads, the plot, patch crops
    material = load_material(tmp_path / "run" / "material.yaml")
    assert np.allclose(material.rho, doc["rho"]) and "cell measure-brdf" in material.source
    # ... its unresolved spike as the planner reads it (tests/test_unresolved.py: what it does)
    assert material.unresolved.terms == {"spike": tuple(np.radians([30.0, 60.0]))}
    assert material.unresolved.step_rad == np.radians(8.0)
    assert material.unresolved.resolvable_m_max == pytest.approx(m_max, rel=1e-5)
    assert (tmp_path / "run" / "fit.png").stat().st_size > 0 and (tmp_path / "run" / "patch-1.png").exists()
    frames = len(list((tmp_path / "run").glob("capture-*.png"))) + (tmp_path / "run" / "dark.png").exists()
    assert frames == sum(line["step"] == "capture" for line in lines)       # the dark frame's dark.png
    rows = (tmp_path / "run" / "goniometer.csv").read_text().splitlines()
    assert rows[0] == "theta_i_deg,theta_e_deg,phase_deg,reflectance" and len(rows) == 1 + len(result.readings)


@pytest.mark.long
def test_a_spike_wider_than_the_step_is_measured(tmp_path):
    """m2 = 100 has a half width of sqrt(ln 2 / 200) = 3.4 deg in beta; a 1.5 deg step resolves it."""
    task = sim_task(tmp_path, {"phase_deg": [30], "step_deg": 1.5, "max_angle_deg": 40}, m2=100.0)
    result, _, _ = measure(task, tmp_path / "run")
    doc = result.material
    assert "unresolved" not in doc
    for key in ("rho", "sigma1", "m1"):
        assert doc[key][0] == pytest.approx(WORLD[key], rel=0.05), key
    assert doc["sigma2"][0] == pytest.approx(WORLD["sigma2"], rel=0.1)
    assert doc["m2"][0] == pytest.approx(100.0, rel=0.1)


def test_the_poses_keep_the_phase_angle_and_the_mirror_pose_at_beta_0():
    task = load_task(HINGE)
    gonio = task.calibration.goniometer
    wanted = goniometer.poses(task)
    assert {round(np.degrees(p.phase_rad), 9) for p in wanted} == {20.0, 40.0, 60.0}
    for p in wanted:
        l, v, n = np.array(p.to_lamp), np.array(p.to_camera), np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(np.clip(l @ v, -1, 1))) == pytest.approx(np.degrees(p.phase_rad), abs=1e-9)
        assert np.arccos(l @ n) == pytest.approx(p.theta_i_rad) and np.arccos(v @ n) == pytest.approx(p.theta_e_rad)
        assert max(p.theta_i_rad, p.theta_e_rad) <= gonio.max_angle_rad + 1e-12
        # eq. (7)'s mirror cosine is cos 2 beta
        assert 2 * np.cos(p.theta_i_rad) * np.cos(p.theta_e_rad) - np.cos(p.phase_rad) == pytest.approx(
            np.cos(2 * p.beta_rad), abs=1e-12)
    assert sum(p.beta_rad == 0 for p in wanted) == 3


def test_unresolved_terms_are_those_absent_or_narrower_than_the_step():
    doc = {"phase_deg": [20.0, 40.0, 60.0], "m1": [10.0, 10.0, 10.0], "sigma1": [2.0, 2.0, 2.0],
           "sigma2": [5.0, 0.0, 5.0], "m2": [20.0, 25.0, 400.0], "sigma1_stderr": [0.1] * 3,
           "m1_stderr": [0.1] * 3, "sigma2_stderr": [0.5, np.inf, 0.5], "m2_stderr": [1.0, np.inf, 10.0],
           "unidentifiable": {"spike": [40.0]}}
    step = np.radians(6.0)                                  # M = ln 2 / (2 step^2) = 31.6
    assert brdf_fit.unresolved_terms(doc, step) == {"spike": [40.0, 60.0]}
    assert doc["sigma2"] == [5.0, 0.0, 0.0] and doc["m2"][0] == 20.0 and doc["m2"][2] == pytest.approx(31.6, abs=0.1)
    assert doc["sigma2_stderr"][0] == 0.5 and np.isinf(doc["sigma2_stderr"][2])


def test_the_arm_refuses_a_pose_its_kinematics_cannot_reach_without_moving():
    task = load_task(HINGE)
    config = replace(task.cell.devices.arm, workspace_min_m=np.full(3, -5.0), workspace_max_m=np.full(3, 5.0))
    arm = SimArm(config, task.frames)
    before = arm.joints.copy()
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.5)
    assert arm.refusal(far).startswith("camera pose unreachable for the UR5e")
    near = arm.camera_pose()
    assert arm.refusal(near) is None and np.array_equal(arm.joints, before)


def test_an_arm_fault_stops_the_cell_exits_3_and_the_log_is_complete(tmp_path):
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})
    result, stops, written = measure(task, tmp_path / "run", faults={"arm_fail_on_move": 3})
    assert isinstance(result, DeviceFault) and result.exit_code == 3 and result.device == "arm"
    assert "motion stopped" in str(result) and stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    assert written["fault"]["device"] == "arm" and written["material"] is None and len(written["readings"]) == 2
    lines = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert lines[-1]["step"] == "fault" and "motion stopped" in lines[-1]["message"]
    assert not (tmp_path / "run" / "material.yaml").exists()


def test_yes_answers_the_prompt_and_without_it_nothing_moves(tmp_path):
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})
    told = io.StringIO()
    result, _, _ = measure(task, tmp_path / "yes", operator=Operator(yes=True, stdout=told))
    assert result.success and "sample: take the part out" in told.getvalue()
    assert "(confirmed automatically: --yes)" in told.getvalue()
    piped = Operator(yes=False, stdin=io.StringIO(""), stdout=io.StringIO())
    result, stops, written = measure(task, tmp_path / "no", operator=piped)
    assert isinstance(result, DeviceFault) and "run with --yes" in str(result)
    assert written["readings"] == [] and not any((tmp_path / "no").glob("capture-*.png"))


def test_the_cli_prints_the_material_as_json_and_a_fault_exits_3(tmp_path, monkeypatch, capsys):
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})
    assert main(["measure-brdf", str(task), "--out", str(tmp_path / "run"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    keys = ["phase_deg", "rho", "sigma1", "m1", "sigma2", "m2"]
    assert set(keys + [f"{k}_stderr" for k in keys[1:]]) <= printed.keys() and printed["phase_deg"] == [40.0]
    assert printed["rho"][0] == pytest.approx(WORLD["rho"], rel=0.05)
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes:
                        make_sim_devices(task, scene, faults={"camera_fail_on_capture": 2}))
    assert main(["measure-brdf", str(task), "--out", str(tmp_path / "fault")]) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell measure-brdf: camera: capture timed out") and "motion stopped" in last


def test_measure_brdf_and_fit_brdf_write_one_material_of_one_csv_and_say_what_is_unresolved_alike(tmp_path, capsys):
    """The run's own goniometer.csv fitted by `cell fit-brdf`: the same table, standard errors and
    unresolved spike (m2 800 at a 10 deg step, M = 11.4) as the material `cell measure-brdf` wrote,
    only its name and source differ; both print the same line for it."""
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})
    assert main(["measure-brdf", str(task), "--out", str(tmp_path / "run")]) == 0
    measured_out = capsys.readouterr().out
    run = tmp_path / "run"
    assert main(["fit-brdf", str(run / "goniometer.csv"), "--out", str(tmp_path / "fit.yaml")]) == 0
    fit_out, fit_err = capsys.readouterr()
    measured = yaml.safe_load((run / "material.yaml").read_text())
    fitted = yaml.safe_load((tmp_path / "fit.yaml").read_text())
    assert {k: v for k, v in measured.items() if k not in ("name", "source")} == \
        {k: v for k, v in fitted.items() if k not in ("name", "source")}
    m_max = np.log(2) / (2 * np.radians(10) ** 2)
    assert measured["unresolved"] == {"terms": {"spike": [40.0]}, "step_deg": 10.0,
                                      "resolvable_m_max": pytest.approx(m_max, rel=1e-5)}
    said = ("spike unresolved at phase 40 deg: the data's step of 10 deg about the mirror direction sees "
            "exponents up to 11.38; a finer step measures it (cell measure-brdf: calibration.goniometer.step_deg)")
    assert f"  {said}\n" in measured_out and f"{said}\n" in fit_err
    # each estimate shown alike: the unresolved spike's sigma2 0 and m2 in words, never '+- inf'
    shown = {k: brdf_fit.shown_estimate(measured, k, 0) for k in ("rho", "sigma1", "m1", "sigma2", "m2")}
    assert shown["sigma2"] == "0 (not resolved)" and shown["m2"] == "- (not resolved)", shown
    assert re.fullmatch(r"[\d.]+ \+- [\d.e+-]+", shown["rho"]), shown
    assert all(f"{k} {text}" in measured_out and text in fit_out for k, text in shown.items()), (measured_out, fit_out)
    assert "inf" not in measured_out + fit_out + fit_err


def test_the_goniometer_keys_are_checked_at_load(tmp_path):
    assert load_task(HINGE).calibration.goniometer.lamp_radius_m == pytest.approx(0.375)   # the rig's middle
    bad = simcell.variant(tmp_path, HINGE, {"calibration.goniometer.lamp_radius_m": 0.9})
    with pytest.raises(TaskError, match=r"calibration.goniometer.lamp_radius_m: found 0.9, expected a radius "
                                        r"within lamp.rig.radius_range_m \[0.15, 0.6\] m"):
        load_task(bad)
    bad = simcell.variant(tmp_path, HINGE, {"calibration.goniometer": {"phase_deg": [20, 100], "max_angle_deg": 45}})
    with pytest.raises(TaskError, match="calibration.goniometer.phase_deg: found 100 deg, expected phase angles "
                                        "below twice max_angle_deg"):
        load_task(bad)
    bad = simcell.variant(tmp_path, HINGE, {"calibration.sample.radius_mm": -3})
    with pytest.raises(TaskError, match="calibration.sample.radius_mm"):
        load_task(bad)


def test_a_phase_angle_with_too_few_readings_is_refused_with_the_reason(tmp_path):
    """ti, te up to 25 deg at phase 40 deg leave beta within +-5 deg: 1 pose at a 10 deg step, of 6 needed."""
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10, "max_angle_deg": 25})
    result, _, written = measure(task, tmp_path / "run")
    assert isinstance(result, GoalNotReached) and result.exit_code == 1
    assert str(result).startswith("fewer than 6 readings at phase 40 deg (0 of 1 poses refused")
    assert written["material"] is None and len(written["readings"]) == 1


def test_the_confirmation_line_names_yes_only_when_given():
    for operator, said, unsaid in [
            (Operator(yes=True, stdout=io.StringIO()), "(confirmed automatically: --yes)", "simulated"),
            (Operator(simulated=True, stdout=io.StringIO()), "(simulated: nothing to confirm)", "--yes"),
            (Operator(yes=True, simulated=True, stdout=io.StringIO()), "(confirmed automatically: --yes)",
             "simulated")]:
        operator.confirm("sample", "take the part out")
        told = operator.stdout.getvalue()
        assert said in told and unsaid not in told and "press Enter" not in told


@pytest.mark.parametrize("yes, said", [(False, "(simulated: nothing to confirm)"),
                                       (True, "(confirmed automatically: --yes)")])
def test_the_simulated_cells_lamp_radius_prompt_names_yes_only_when_given(yes, said, capsys):
    """`cell run` on the simulated cell: the manual lamp radius is confirmed for the operator, and
    the line says --yes only when it was given."""
    devices = backends.open_devices(load_task(HINGE), None, "sim", yes=yes, board=True)   # no scene to render
    try:
        devices.lamp.operator.confirm("pan-tilt", "set the lamp radius")
    finally:
        devices.safe_stop()
    out = capsys.readouterr().out
    assert said in out and "press Enter" not in out
    assert ("--yes" in out) == yes
