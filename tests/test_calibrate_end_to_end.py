"""Calibration end to end: a hinge task whose world differs from it in the camera constant, the
material and the hand-eye is calibrated with the three routines through the command line
(`cell calibrate hand-eye`, `cell calibrate camera-constant`, `cell measure-brdf`, each with --yes
and --out), the task then names the files they wrote (cell.arm.hand_eye, camera.sensor,
part.material), and `cell run` converges in its first capture; the uncalibrated task does not.

The simulated cell renders the world with the hinge's effects and noise, black_level and
quantization on. Its truth keys are relative to the task's model (true c = task c x
camera_constant_scale, true camera = reported camera composed with camera_offset_m /
camera_rpy_deg), so each calibrated task carries the truth re-expressed against its own model:
the same world (`same_world`), which no routine reads. The world's spike (m2 = 150, half width
2.75 deg in beta) is wider than the 2 deg step, so the goniometer resolves it."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from cell.core import geometry
from cell.cli import main
from cell.task.loader import load_task

TASKS = Path(__file__).resolve().parent.parent / "tasks"
EFFECTS = ["shadows", "cone_falloff", "noise", "black_level", "quantization"]
C_SCALE = 1.25                                   # the world's c over the task's 1.5e16
OFFSET_M, RPY_DEG = [0.0015, -0.002, 0.003], [0.8, -0.6, 1.2]
WORLD = {"rho": 0.04, "sigma1": 3.5, "m1": 7.0, "sigma2": 30.0, "m2": 150.0}  # the task's: 0.031, 4, 6, 30, 400
# half the example sensor's pixels, each twice as large (the same field of view), and a goniometer
# sweep of 80 poses (2 deg steps, ti and te up to 50 deg, at the phase angles about the hinge's plan)
SENSOR = {"width_px": 516, "height_px": 388, "pixel_pitch_m": 9.3e-6}
GONIOMETER = {"phase_deg": [10, 30], "step_deg": 2, "max_angle_deg": 50}
LASER_W = "2e-10"


def hinge(folder):
    """The hinge task as a mapping, its files absolute, on the test's sensor and goniometer, the
    world's truth in its sim section."""
    doc = yaml.safe_load((TASKS / "hinge.yaml").read_text())
    doc["part"] |= {k: str(TASKS / doc["part"][k]) for k in ("mesh", "material")}
    doc["camera"]["sensor"] |= SENSOR
    (folder / "world.yaml").write_text(yaml.safe_dump({"name": "the world's metal", "source": "test truth",
                                                       "phase_deg": [0, 90], **{k: [v, v] for k, v in WORLD.items()}}))
    doc["sim"] = {"seed": 3, "effects": EFFECTS, "truth": {"camera_constant_scale": C_SCALE, "material": "world.yaml",
                                                          "camera_offset_m": OFFSET_M, "camera_rpy_deg": RPY_DEG}}
    doc["calibration"] = {"goniometer": GONIOMETER}
    return doc


def write(folder, name, doc):
    path = folder / name
    path.write_text(yaml.safe_dump(doc))
    return str(path)


class World:
    """The world's camera constant and camera on the flange, from the uncalibrated task's model
    and its truth keys (as sim.world composes them)."""

    def __init__(self, task):
        self.c = task.camera.sensor.camera_constant * C_SCALE
        self.T_flange_cam = task.frames.T_flange_cam @ geometry.from_rpy(np.radians(RPY_DEG), OFFSET_M)

    def same_world(self, folder, name, doc):
        """The task `doc` written with its truth keys re-expressed against its own model, so that
        the simulated cell renders this world: c scale = c / the task's c, the camera error =
        inv(the task's T_flange_cam) @ the world's."""
        doc["sim"]["truth"] |= {"camera_constant_scale": 1.0, "camera_offset_m": [0, 0, 0], "camera_rpy_deg": [0, 0, 0]}
        model = load_task(write(folder, name, doc))
        error = np.linalg.inv(model.frames.T_flange_cam) @ self.T_flange_cam
        doc["sim"]["truth"] |= {"camera_constant_scale": float(self.c / model.camera.sensor.camera_constant),
                                "camera_offset_m": error[:3, 3].tolist(),
                                "camera_rpy_deg": Rotation.from_matrix(error[:3, :3]).as_euler("xyz", degrees=True).tolist()}
        return write(folder, name, doc)


def cli(capsys, *argv):
    """main(argv): (exit code, stdout)."""
    code = main(list(argv))
    return code, capsys.readouterr().out


def report(folder):
    return json.loads((folder / "report.json").read_text())


def test_a_task_off_in_c_material_and_hand_eye_is_calibrated_and_converges_in_its_first_capture(tmp_path, capsys):
    doc = hinge(tmp_path)
    uncalibrated = write(tmp_path, "uncalibrated.yaml", doc)
    world = World(load_task(uncalibrated))

    # the control: the task as it is does not converge in its first capture
    cli(capsys, "run", uncalibrated, "--out", str(tmp_path / "run-uncalibrated"))
    first = report(tmp_path / "run-uncalibrated")["iterations"][0]
    assert not first["in_band"] and first["measured_gray"]["mean"] > 1.2 * first["predicted_gray"]["mean"]

    # 1. intrinsics and hand-eye
    code, out = cli(capsys, "calibrate", "hand-eye", uncalibrated, "--out", str(tmp_path / "hand-eye"),
                    "--poses", "10", "--yes", "--json")
    assert code == 0 and json.loads(out)["hand_eye_file"] == str(tmp_path / "hand-eye" / "hand-eye.yaml")
    doc["cell"] = {"backend": "sim", "arm": {"hand_eye": "hand-eye/hand-eye.yaml"}}    # in its run folder
    with_hand_eye = world.same_world(tmp_path, "with-hand-eye.yaml", doc)
    T = load_task(with_hand_eye).frames.T_flange_cam
    turn = Rotation.from_matrix(T[:3, :3].T @ world.T_flange_cam[:3, :3]).magnitude()
    assert np.linalg.norm(T[:3, 3] - world.T_flange_cam[:3, 3]) < 1e-3 and np.degrees(turn) < 0.2

    # 2. the camera constant, and the black level of its dark frames
    code, out = cli(capsys, "calibrate", "camera-constant", with_hand_eye, "--laser-power-w", LASER_W,
                    "--out", str(tmp_path / "laser"), "--yes", "--json")
    laser = json.loads(out)
    assert code == 0 and laser["camera_file"] == str(tmp_path / "laser" / "camera.yaml")
    assert laser["camera_constant"] == pytest.approx(world.c, rel=0.02) and laser["black_level"] == 5.0
    doc["camera"]["sensor"] = "laser/camera.yaml"
    with_camera = world.same_world(tmp_path, "with-camera.yaml", doc)

    # 3. the material, with the calibrated c and hand-eye
    code, out = cli(capsys, "measure-brdf", with_camera, "--out", str(tmp_path / "brdf"), "--yes", "--json")
    measured = json.loads(out)
    assert code == 0 and measured["phase_deg"] == GONIOMETER["phase_deg"] and "unresolved" not in measured
    for key in ("rho", "sigma1", "m1"):
        assert np.allclose(measured[key], WORLD[key], rtol=0.05), (key, measured[key])
    doc["part"]["material"] = "brdf/material.yaml"
    calibrated = world.same_world(tmp_path, "calibrated.yaml", doc)

    # the calibrated task: in the band at its first capture, the camera file's black level used
    assert cli(capsys, "run", calibrated, "--out", str(tmp_path / "run"))[0] == 0
    done = report(tmp_path / "run")
    assert done["converged"] and len(done["iterations"]) == 1 and done["iterations"][0]["in_band"]
    assert done["black_level"] == {"value": 5.0, "noise_rms": 0.0, "source": "task"}
    assert not (tmp_path / "run" / "dark.png").exists()               # no dark frame of its own
