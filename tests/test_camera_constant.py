"""`cell calibrate camera-constant`: the camera constant from a laser of known power at several
shutter times (sec. 4.1), on the simulated cell with noise, black level and quantization, against
the world's true c (task c * sim.truth.camera_constant_scale, which the routine never reads: it is
handed the task with a neutral truth while the simulated cell renders the true one); untrustworthy
series refused with the reason (exit 1); the camera file written, used by a task and never
replaced without --force; a device fault stops the cell and exits 3."""
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.run import backends

from cell.calibration import camera_constant as routine
from cell.calibration.camera_constant import Frame, fit_series, spot_window
from cell.cli import main
from cell.core.errors import DeviceFault, GoalNotReached
from cell.task.loader import load_task
from cell.devices.operator import Operator
from cell.physics.radiometry import camera_constant_from_datasheet
from cell.task.types import Truth
from sim.cell import make_sim_devices
from sim.laser import SPOT_SIGMA_PX, spot_shares

import simcell

HINGE = Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml"
C_TASK = 1.5e16
EFFECTS = ["noise", "black_level", "quantization"]
POWER_W = 2e-10                 # after the filters: the spot's sum reaches full scale near 0.1 ms


def sim_task(tmp_path, scale=1.3, seed=1, **changes):
    """The hinge task on a simulated cell with noise, black level and quantization and a world
    whose c is `scale` x the task's; its sensor cut to 320 x 240 px (the spot needs a few dozen:
    a quicker test)."""
    small = {"camera.sensor.width_px": 320, "camera.sensor.height_px": 240}
    return simcell.variant(tmp_path, HINGE, {"sim.effects": EFFECTS, "sim.truth.camera_constant_scale": scale,
                                             "sim.seed": seed, **small, **changes})


def calibrate(task_path, out, power_w=POWER_W, faults=None, camera_file=None):
    """routine.run handed the task with a neutral truth; the simulated cell renders the task's
    truth. Returns (result or the error, the cell's safe-stop calls, calibration.json)."""
    true = load_task(task_path)
    believed = replace(true, sim=replace(true.sim, truth=Truth()))
    laser = routine.Laser(power_w, Operator(yes=True))
    stops = []

    def connect():
        return simcell.record_stops(make_sim_devices(true, None, faults=faults, laser=laser), stops)
    try:
        result = routine.run(believed, out, connect, laser, camera_file or Path(out).parent / "camera.yaml")
    except Exception as err:                                    # noqa: BLE001 - returned for the test to judge
        result = err
    return result, stops, json.loads((Path(out) / "calibration.json").read_text())


# --- the sim's spot and the window ----------------------------------------------------------------

def test_the_spot_s_shares_are_the_gaussian_s_integral_over_each_pixel():
    shares = spot_shares((41, 41), (20.3, 19.6), 1.2)
    assert shares.sum() == pytest.approx(1.0, abs=1e-12)
    rows, cols = np.indices(shares.shape)
    assert np.sum(shares * rows) == pytest.approx(20.3, abs=1e-9)          # the centroid is the centre
    assert np.sum(shares * (rows - 20.3) ** 2) == pytest.approx(1.2**2 + 1 / 12, rel=1e-6)   # + a pixel's width


def test_the_window_holds_the_whole_spot_and_its_sum_is_the_power():
    signal = 3000.0 * spot_shares((200, 300), (101.4, 150.8), SPOT_SIGMA_PX)
    signal += np.random.default_rng(0).normal(0.0, 0.4, signal.shape)
    where, (row, col, half) = spot_window(signal, noise_rms=0.4)
    assert (row, col) == (101, 151) and 4 <= half <= 16
    assert signal[where].sum() == pytest.approx(3000.0, abs=3 * 0.4 * (2 * half + 1))
    near_edge = 3000.0 * spot_shares((200, 300), (3.0, 150.0), SPOT_SIGMA_PX)
    assert spot_window(near_edge, noise_rms=0.4)[0] is None


# --- the fit and its refusals ---------------------------------------------------------------------

def sweep(sums, saturated=(), too_dark=()):
    t = 1e-4 * np.arange(1, len(sums) + 1)
    return [Frame("sweep", ti, f"capture-{i}.png", 100.0, i in saturated, i in too_dark, s)
            for i, (ti, s) in enumerate(zip(t, sums))]


def test_the_fit_is_the_least_squares_line_and_c_its_slope_over_the_power():
    t = 1e-4 * np.arange(1, 9)
    noise = np.array([3.0, -2.0, 1.0, -4.0, 2.0, 0.5, -1.5, 1.0])
    frames = sweep(2.5e16 * POWER_W * t + 4.0 + noise, saturated={8})     # a 9th, saturated, left out
    frames.append(Frame("sweep", 9e-4, "capture-9.png", 255.0, True, False, 9e3))
    fit = fit_series(frames, POWER_W)
    A = np.column_stack([np.ones(8), t])                                   # by hand: normal equations
    (b, slope), *_ = np.linalg.lstsq(A, 2.5e16 * POWER_W * t + 4.0 + noise, rcond=None)
    assert fit.camera_constant == pytest.approx(slope / POWER_W) and fit.offset == pytest.approx(b)
    residual = 2.5e16 * POWER_W * t + 4.0 + noise - A @ (b, slope)
    stderr = np.sqrt(residual @ residual / 6 / np.sum((t - t.mean()) ** 2))
    assert fit.camera_constant_stderr == pytest.approx(stderr / POWER_W)
    assert (fit.frames_used, fit.frames_saturated, fit.frames_too_dark) == (8, 1, 0)


@pytest.mark.parametrize("frames, reason", [
    (sweep([1e3] * 6, saturated=set(range(6))), "saturated at every shutter time"),
    (sweep(np.arange(1, 7) * 100.0, saturated={3, 4, 5}, too_dark={0}), "too few usable frames: 2 of 6 "
                                                                         "(3 saturated, 1 too dark)"),
    (sweep((np.arange(1, 9) * 100.0) ** 2), "poor linearity: r2 0.9"),
])
def test_an_untrustworthy_series_is_refused_with_the_reason(frames, reason):
    with pytest.raises(GoalNotReached, match=reason.replace("(", r"\(").replace(")", r"\)")):
        fit_series(frames, POWER_W)


# --- on the simulated cell ------------------------------------------------------------------------

def test_c_is_the_world_s_within_2_percent_and_its_stderr_covers_it(tmp_path):
    result, stops, written = calibrate(sim_task(tmp_path), tmp_path / "run")
    c_true = 1.3 * C_TASK
    fit = result.fit
    assert result.success and fit.camera_constant == pytest.approx(c_true, rel=0.02)
    assert abs(fit.camera_constant - c_true) < 3 * fit.camera_constant_stderr
    assert fit.camera_constant_stderr < 0.01 * c_true and fit.r_squared > 0.9999
    assert fit.frames_used == 8 and written["camera_constant"] == fit.camera_constant
    assert stops == ["camera.close"]                              # closed normally, nothing stopped
    kinds = [f["kind"] for f in written["frames"]]
    assert kinds == ["dark"] * 6 + ["probe"] * kinds.count("probe") + ["sweep"] * 8
    assert len(list((tmp_path / "run").glob("capture-*.png"))) == len(kinds)
    assert (tmp_path / "run" / "calibration.png").stat().st_size > 0
    steps = [json.loads(line)["step"] for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert steps[0] == "setup" and steps[-1] == "done" and "move_camera" not in steps and "move_lamp" not in steps


def test_a_world_far_brighter_than_the_task_says_is_found_by_the_probes(tmp_path):
    """The world's c 12x the task's: the first probe (the task's c putting the spot's sum at full
    scale) saturates, a 4x shorter one does not; the sweep follows the probe, not the task."""
    result, _, written = calibrate(sim_task(tmp_path, scale=12.0), tmp_path / "run")
    probes = [f for f in written["frames"] if f["kind"] == "probe"]
    assert [p["saturated"] for p in probes] == [True, False]
    assert probes[1]["shutter_s"] == pytest.approx(probes[0]["shutter_s"] / 4)
    assert result.fit.camera_constant == pytest.approx(12.0 * C_TASK, rel=0.02) and result.fit.frames_used == 8


def test_over_seeds_the_stderr_is_the_scatter_s(tmp_path):
    """z = (c - c_true) / stderr over 6 worlds (seeds: the noise and where the spot lands). With 8
    frames and 2 parameters z is Student's t with 6 degrees of freedom: rms sqrt(6/4) = 1.22,
    |z| < 5.96 with 99.9 %. A stderr half the scatter's would give an rms near 2.5, one twice it
    an rms near 0.6. (Over 30 seeds: rms 1.46, mean error +0.07 %, the largest 0.9 %.)"""
    z = []
    for seed in range(1, 7):
        (tmp_path / str(seed)).mkdir()
        result, _, _ = calibrate(sim_task(tmp_path / str(seed), scale=0.8, seed=seed), tmp_path / str(seed) / "run")
        assert result.fit.camera_constant == pytest.approx(0.8 * C_TASK, rel=0.02)
        z.append((result.fit.camera_constant - 0.8 * C_TASK) / result.fit.camera_constant_stderr)
    z = np.array(z)
    assert np.all(np.abs(z) < 5.96) and 0.6 < np.sqrt(np.mean(z**2)) < 2.5, z


def test_a_spot_at_the_datasheet_s_full_well_is_saturated_though_below_the_adc_s_top(tmp_path):
    """A full well of 15000 e- at K 0.0114 is 171 gray above the dark: a spot clipped there never
    reads 255, yet is saturated; without the datasheet's keys only 255 is."""
    shares = spot_shares((240, 320), (120.0, 160.0), SPOT_SIGMA_PX)
    darks = routine.Darks({1e-5: np.full((3, 240, 320), 5.0), 0.02: np.full((3, 240, 320), 5.0)})
    clipped = 5.0 + np.minimum(4000.0 * shares, 171.0)
    task = load_task(HINGE)
    datasheet = replace(task, camera=replace(task.camera, sensor=replace(
        task.camera.sensor, system_gain_dn_per_e=0.0114, saturation_capacity_e=15000.0)))
    assert routine.Spot(datasheet, darks).judge(clipped, 1e-3)[1]
    assert routine.Spot(datasheet, darks).room(1e-3) == pytest.approx(170.0)
    assert not routine.Spot(task, darks).judge(clipped, 1e-3)[1] and routine.Spot(task, darks).room(1e-3) == 250.0


def test_with_the_datasheet_sensor_c_is_the_world_s(tmp_path):
    """eta 0.5 at 525 nm, K 0.0114, a full well of 15000 e- (171 gray, below the ADC's 255: the
    sweep stays below it). c from the datasheet, the world's 1.2 x that."""
    sensor = {k: v for k, v in yaml.safe_load(HINGE.read_text())["camera"]["sensor"].items()
              if k != "camera_constant"}
    sensor |= {"width_px": 320, "height_px": 240, "quantum_efficiency": 0.5, "wavelength_um": 0.525,
               "system_gain_dn_per_e": 0.0114, "dark_noise_e": 10.0, "saturation_capacity_e": 15000}
    task = sim_task(tmp_path, scale=1.2, **{"camera.sensor": sensor})
    result, _, written = calibrate(task, tmp_path / "run")
    c_true = 1.2 * camera_constant_from_datasheet(0.5, 525e-9, 0.0114)
    assert result.fit.frames_saturated == 0 and max(f["peak"] for f in written["frames"] if f["kind"] != "dark") < 171
    assert result.fit.camera_constant == pytest.approx(c_true, rel=0.02)
    assert abs(result.fit.camera_constant - c_true) < 3 * result.fit.camera_constant_stderr
    document = yaml.safe_load((tmp_path / "camera.yaml").read_text())
    assert "quantum_efficiency" not in document and document["saturation_capacity_e"] == 15000


@pytest.mark.parametrize("power_w, reason", [
    (1e-5, "the spot is saturated at every shutter time down to 0.01 ms"),
    (1e-16, "the spot is too dark at every shutter time up to 20 ms"),
])
def test_a_saturated_or_too_dark_series_is_refused_with_the_reason_and_exit_1(tmp_path, capsys, power_w, reason):
    task = sim_task(tmp_path)
    out = tmp_path / "run"
    argv = ["calibrate", "camera-constant", str(task), "--laser-power-w", str(power_w), "--out", str(out)]
    assert main(argv) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"cell calibrate: {reason}")
    written = json.loads((out / "calibration.json").read_text())
    assert written["fit"] is None and reason in written["reason"] and written["frames"]
    assert not (tmp_path / "camera.yaml").exists()


@pytest.mark.parametrize("effects, black", [(EFFECTS, 5.0), (["noise", "quantization"], 0.0)])
def test_the_camera_file_carries_the_black_level_of_the_dark_frames(tmp_path, effects, black):
    """The world's black level is sim.world.BLACK_LEVEL x 255 rounded = 5 gray with the effect
    black_level, else 0 (the dark noise of 0.26 gray rms rounds to 0); a task naming the camera
    file then knows it, so cell run takes no dark frame of its own."""
    result, _, written = calibrate(sim_task(tmp_path, **{"sim.effects": effects}), tmp_path / "run")
    assert result.black_level.value == black and written["black_level"]["value"] == black
    assert result.black_level.noise_rms < 0.5 and written["black_level"]["source"] == "dark frame"
    camera = tmp_path / "camera.yaml"
    assert yaml.safe_load(camera.read_text())["black_level"] == black
    user = simcell.variant(tmp_path, sim_task(tmp_path), {"camera.sensor": "camera.yaml"})
    assert load_task(user).camera.sensor.black_level == black


# --- the command line, the camera file ------------------------------------------------------------

def test_json_prints_the_fit_and_the_camera_file_is_used_by_a_task(tmp_path, capsys):
    task = sim_task(tmp_path, scale=0.9)
    argv = ["calibrate", "camera-constant", str(task), "--laser-power-w", str(POWER_W), "--json"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert {"camera_constant", "camera_constant_stderr", "r_squared", "frames_used"} <= printed.keys()
    assert printed["camera_constant"] == pytest.approx(0.9 * C_TASK, rel=0.02) and printed["frames_used"] == 8
    camera = tmp_path / "a" / "camera.yaml"                   # in the run folder: the task's folder as it was
    assert printed["camera_file"] == str(camera) and sorted(p.name for p in tmp_path.glob("*.yaml")) == [task.name]
    document = yaml.safe_load(camera.read_text())
    assert document["camera_constant"] == pytest.approx(printed["camera_constant"], rel=1e-5)
    assert document["source"].startswith("cell calibrate camera-constant")
    assert document["black_level"] == printed["black_level"] == 5.0        # sim.world.BLACK_LEVEL of 255, rounded

    user = simcell.variant(tmp_path, task, {"camera.sensor": "a/camera.yaml"})  # relative to the task file
    assert load_task(user).camera.sensor.camera_constant == document["camera_constant"]
    assert main(["check", str(user)]) == 0
    sensor_line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("sensor"))
    assert f"c = {document['camera_constant']:.5g} +- " in sensor_line and f"from {camera}" in sensor_line

    # beside the task only when asked; a second run over it refused before any work, then --force
    beside = tmp_path / "camera.yaml"
    assert main([*argv, "--out", str(tmp_path / "b"), "--camera-file", str(beside)]) == 0
    assert json.loads(capsys.readouterr().out)["camera_file"] == str(beside) and not (tmp_path / "b" / "camera.yaml").exists()
    before = beside.read_text()
    assert main([*argv, "--out", str(tmp_path / "c"), "--camera-file", str(beside)]) == 2
    assert capsys.readouterr().err == (f"cell calibrate: command line: --camera-file: found {beside}, a file "
                                       "that exists, expected a new file, or --force to replace it\n")
    assert beside.read_text() == before and not (tmp_path / "c").exists()
    assert main([*argv, "--out", str(tmp_path / "d"), "--camera-file", str(beside), "--force"]) == 0
    assert json.loads(capsys.readouterr().out)["camera_file"] == str(beside) and beside.read_text() != before


def test_without_json_the_line_to_add_to_the_task_is_printed(tmp_path, capsys):
    task = sim_task(tmp_path)
    assert main(["calibrate", "camera-constant", str(task), "--laser-power-w", str(POWER_W), "--out",
                 str(tmp_path / "runs" / "c1")]) == 0
    out = capsys.readouterr().out
    assert f"  wrote {tmp_path}/runs/c1/camera.yaml: to use it, write camera: {{sensor: runs/c1/camera.yaml, ...}} " \
           f"in {task}\n" in out


@pytest.mark.parametrize("name, found", [("", "a folder"), ("no/such/camera.yaml", "in no existing folder")])
def test_a_camera_file_that_cannot_be_written_is_bad_input_before_any_work(tmp_path, capsys, name, found):
    path = tmp_path / name
    argv = ["calibrate", "camera-constant", str(HINGE), "--laser-power-w", "2e-10", "--camera-file", str(path),
            "--out", str(tmp_path / "run")]
    assert main(argv) == 2
    assert capsys.readouterr().err.startswith(f"cell calibrate: command line: --camera-file: found {path}, {found}")
    assert not (tmp_path / "run").exists()


def test_the_plain_calibrate_names_the_routines_exit_2(capsys):
    with pytest.raises(SystemExit) as exited:
        main(["calibrate", str(HINGE), "--out", "x"])
    assert exited.value.code == 2
    assert capsys.readouterr().err == (f"cell calibrate: command line: ROUTINE: found '{HINGE}', expected "
                                       "camera-constant, reference-part or hand-eye before the task (cell calibrate -h "
                                       "says what each does)\n")


@pytest.mark.parametrize("value", ["0", "-1e-10", "inf", "nan"])
def test_a_laser_power_that_is_no_power_is_bad_input(value, capsys):
    assert main(["calibrate", "camera-constant", str(HINGE), f"--laser-power-w={value}"]) == 2
    assert capsys.readouterr().err == (f"cell calibrate: command line: --laser-power-w: found {float(value)}, "
                                       "expected the laser's power at the sensor, a positive number of watts\n")


def test_on_the_real_cell_the_operator_works_the_laser_before_anything(tmp_path, monkeypatch, capsys):
    connected = []
    monkeypatch.setattr(backends, "open_devices", lambda *a, **k: connected.append(a))
    task = sim_task(tmp_path, **{"cell.backend": "hw", "cell.arm.host": "127.0.0.1", "cell.pan_tilt.port": "/dev/null"})
    argv = ["calibrate", "camera-constant", str(task), "--laser-power-w", str(POWER_W), "--out", str(tmp_path / "r")]
    assert main(argv) == 3                                                  # stdin: no terminal
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell calibrate: laser: ") and "run with --yes" in last and connected == []


def test_the_cli_turns_a_fault_into_exit_3_and_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(backends, "open_devices", lambda task, scene, backend, yes, laser:
                        make_sim_devices(task, scene, faults={"camera_fail_on_capture": 3}, laser=laser))
    argv = ["calibrate", "camera-constant", str(sim_task(tmp_path)), "--laser-power-w", "2e-10", "--out",
            str(tmp_path / "run")]
    assert main(argv) == 3
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("cell calibrate: camera: capture timed out") and "motion stopped" in last
    assert json.loads((tmp_path / "run" / "calibration.json").read_text())["fault"]["device"] == "camera"


def test_a_camera_fault_stops_the_cell_exits_3_and_the_log_is_complete(tmp_path):
    result, stops, written = calibrate(sim_task(tmp_path), tmp_path / "run", faults={"camera_fail_on_capture": 8})
    assert isinstance(result, DeviceFault) and result.exit_code == 3
    assert result.device == "camera" and "motion stopped" in str(result)
    assert stops == ["arm.stop", "pan-tilt.stop", "camera.close"]
    assert written["fault"]["device"] == "camera" and written["fit"] is None and len(written["frames"]) == 7
    lines = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert lines[-1]["step"] == "fault" and "motion stopped" in lines[-1]["message"]
    assert not (tmp_path / "camera.yaml").exists()
