"""The camera's sensor from an EMVA 1288 datasheet and from a camera file: c = eta lambda K / (h c0)
against the paper's camera (hand-derived), the keys checked at load (both c's given and apart,
a key missing its partners, a broken camera file: one line naming the file and the key, exit 2),
and the simulated sensor (sim.world.SensorModel) against the `emva1288` package's camera model and
against EMVA 1288's formulas: mean = K (eta mu_p) + b, variance = K^2 (sigma_d^2 + eta mu_p) + 1/12."""
import numpy as np
import pytest
import yaml
from emva1288.camera import Camera as EmvaCamera
from emva1288.camera import routines as emva_routines

from cell import cli

from cell.task import loader
from cell.physics.radiometry import camera_constant_from_datasheet
from sim.world import SensorModel

from test_loader import HINGE, HINGE_SENSOR, put, write_task

PAPER_C = 1.5e16                # sec. 4.1's camera [1/(W s)]
DATASHEET = {"quantum_efficiency": 0.5, "wavelength_um": 0.525, "system_gain_dn_per_e": 0.0114}


def test_the_paper_s_camera_constant_is_eta_0_5_at_525_nm_with_k_about_0_0114():
    # by hand: a 525 nm photon carries h c0 / lambda = 6.62607015e-34 * 299792458 / 525e-9 J
    photon_j = 6.62607015e-34 * 299792458.0 / 525e-9
    assert photon_j == pytest.approx(3.7838e-19, rel=1e-4)
    electrons_per_joule = 0.5 / photon_j                       # 1.3214e18 electrons per W s
    k = PAPER_C / electrons_per_joule                          # the gain that makes c = 1.5e16
    assert k == pytest.approx(0.01135, rel=1e-3) and round(k, 4) == 0.0114
    assert camera_constant_from_datasheet(0.5, 525e-9, k) == pytest.approx(PAPER_C, rel=1e-12)
    assert camera_constant_from_datasheet(0.5, 525e-9, 0.0114) == pytest.approx(PAPER_C, rel=0.005)


def sensor_edit(keys, drop=("camera_constant",)):
    """Edit: the hinge's sensor with keys added and `drop` removed."""
    sensor = {k: v for k, v in HINGE_SENSOR.items() if k not in drop} | keys
    return put("camera.sensor", sensor)


def test_the_datasheet_keys_give_c_and_the_noise_model(tmp_path):
    keys = DATASHEET | {"dark_noise_e": 12.0, "saturation_capacity_e": 20000}
    task = loader.load_task(write_task(tmp_path, sensor_edit(keys)))
    sensor = task.camera.sensor
    assert sensor.camera_constant == pytest.approx(camera_constant_from_datasheet(0.5, 525e-9, 0.0114))
    assert sensor.wavelength_m == pytest.approx(525e-9)
    model = SensorModel.of(sensor)
    assert (model.gain_dn_per_e, model.dark_noise_e, model.saturation_capacity_e) == (0.0114, 12.0, 20000.0)


def test_without_the_datasheet_the_sim_keeps_its_assumed_sensor():
    model = SensorModel.of(loader.load_task(HINGE).camera.sensor)
    assert model.gain_dn_per_e == pytest.approx(255 / 10_000) and model.dark_noise_e == 10.0
    assert model.saturation_capacity_e == np.inf and model.black_level == 5.0


def test_both_c_given_within_1_percent_load_as_written(tmp_path):
    task = loader.load_task(write_task(tmp_path, sensor_edit(DATASHEET | {"camera_constant": 1.5e16}, drop=())))
    assert task.camera.sensor.camera_constant == 1.5e16        # 0.4 % from the datasheet's 1.5065e16


BROKEN = [
    pytest.param(sensor_edit(DATASHEET | {"camera_constant": 1.6e16}, drop=()), "camera.sensor.camera_constant",
                 "found 1.6e+16, 6.2 % from the 1.506e+16 of quantum_efficiency 0.5, wavelength_m 5.25e-07 and "
                 "system_gain_dn_per_e 0.0114, expected the two within 1 % (or only one of them)", id="disagree"),
    pytest.param(sensor_edit({"quantum_efficiency": 0.5, "system_gain_dn_per_e": 0.0114}),
                 "camera.sensor.wavelength_m", "found nothing, expected a value beside quantum_efficiency",
                 id="no-wavelength"),
    pytest.param(sensor_edit({"quantum_efficiency": 0.5, "wavelength_um": 0.525}),
                 "camera.sensor.system_gain_dn_per_e", "found nothing, expected a value beside quantum_efficiency",
                 id="no-gain"),
    pytest.param(sensor_edit({"wavelength_um": 0.525}, drop=()), "camera.sensor.quantum_efficiency",
                 "found nothing, expected a value beside wavelength_m", id="wavelength-alone"),
    pytest.param(sensor_edit({"system_gain_dn_per_e": 0.0114}), "camera.sensor.camera_constant",
                 "found nothing, expected c in G = c P t [1/(W s)], or quantum_efficiency, wavelength_m and "
                 "system_gain_dn_per_e from an EMVA 1288 datasheet (required key)", id="no-c"),
    pytest.param(sensor_edit({"wavelength_m": 525}, drop=()), "camera.sensor.wavelength_m",
                 "found 525, expected a wavelength of light within [0.2, 2] um", id="nanometres-as-metres"),
    pytest.param(sensor_edit({"quantum_efficiency": 1.2}, drop=()), "camera.sensor.quantum_efficiency",
                 "expected a number in (0, 1]", id="efficiency-above-1"),
    pytest.param(put("camera.sensor", 42), "camera.sensor",
                 "found 42, expected a mapping of keys", id="number-for-sensor"),
]


@pytest.mark.parametrize("edit, key, text", BROKEN)
def test_bad_sensor_keys_are_one_line_naming_the_key(tmp_path, capsys, edit, key, text):
    path = write_task(tmp_path, edit)
    assert cli.main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path}: {key}: " in err and text in err, err


# --- camera files ---------------------------------------------------------------------------------

def with_camera_file(name, content):
    """Edit: write content (a mapping, or text) as the camera file `name` beside the task and
    point camera.sensor at it."""
    def edit(task, folder):
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(content if isinstance(content, str) else yaml.safe_dump(content))
        task["camera"]["sensor"] = name
    return edit


def test_a_camera_file_relative_to_the_task_gives_the_sensor(tmp_path, capsys):
    sensor = {k: v for k, v in HINGE_SENSOR.items() if k != "camera_constant"} | DATASHEET | {
        "source": "datasheet, EMVA 1288 at 525 nm"}
    path = write_task(tmp_path, with_camera_file("cameras/cam.yaml", sensor))
    task = loader.load_task(path)
    assert task.camera.sensor.file == tmp_path / "cameras" / "cam.yaml"
    assert task.camera.sensor.camera_constant == pytest.approx(1.5065e16, rel=1e-4)
    assert cli.main(["check", str(path)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("sensor"))
    assert "c = 1.5065e+16 1/(W s) (EMVA 1288: eta 0.5 at 525 nm, K 0.0114 DN/e-)" in line
    assert f"from {tmp_path / 'cameras' / 'cam.yaml'}: datasheet, EMVA 1288 at 525 nm" in line


CAMERA_BROKEN = [
    pytest.param(dict(HINGE_SENSOR, camera_constant=-1.0), "camera_constant", "found -1.0, expected a positive number",
                 id="negative-c"),
    pytest.param(dict(HINGE_SENSOR, pixel_pich_m=4.65e-6), "pixel_pich_m", "did you mean 'pixel_pitch_m'",
                 id="unknown-key"),
    pytest.param({k: v for k, v in HINGE_SENSOR.items() if k != "camera_constant"}, "camera_constant",
                 "found nothing", id="no-c"),
    pytest.param(dict(HINGE_SENSOR, **DATASHEET, camera_constant=3e16), "camera_constant", "% from the",
                 id="disagree"),
    pytest.param("width_px: [\n", "", "YAML syntax error", id="yaml-syntax"),
]


@pytest.mark.parametrize("content, key, text", CAMERA_BROKEN)
def test_a_broken_camera_file_is_one_line_naming_it_and_its_key(tmp_path, capsys, content, key, text):
    path = write_task(tmp_path, with_camera_file("camera.yaml", content))
    assert cli.main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(tmp_path / "camera.yaml") in err and text in err, err
    assert f"camera.yaml: {key}: found" in err if key else True


def test_a_missing_camera_file_is_one_line_naming_the_task_key(tmp_path, capsys):
    path = write_task(tmp_path, put("camera.sensor", "nowhere.yaml"))
    assert cli.main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path}: camera.sensor: found '{tmp_path / 'nowhere.yaml'}'" in err, err
    assert "relative to the task file" in err


# --- the simulated sensor against EMVA 1288 -------------------------------------------------------

K, SIGMA_D, CAPACITY, ETA, BLACK = 0.0114, 10.0, 20_000.0, 0.5, 5.0
SHAPE = (200, 200)
# photons per pixel where the noise exceeds half a gray level (0.65-2.4 gray rms), EMVA 1288's
# condition for rounding to add sigma_q^2 = 1/12: below it, the rounding's share depends on where
# the mean falls between two levels
LEVELS = [5_000.0, 10_000.0, 20_000.0, 35_000.0]


def ours(mu_p, seed=1):
    """Our sensor's frame of mu_p photons per pixel: the noiseless gray is K eta mu_p (= c P t)."""
    model = SensorModel(K, SIGMA_D, CAPACITY, BLACK, 8)
    gray = np.full(SHAPE, K * ETA * mu_p)
    return model.read_out(gray, {"noise", "black_level", "quantization"}, np.random.default_rng(seed)).astype(float)


def emva(mu_p, seed=1):
    """emva1288's camera (camera.py grab) at mu_p photons per pixel: one wavelength at quantum
    efficiency ETA, no dark current, dark noise SIGMA_D, full well CAPACITY, offset BLACK."""
    wavelength = np.array([525.0])
    qe = emva_routines.Qe(qe=np.full((*SHAPE, 1), ETA), wavelength=wavelength, width=SHAPE[1], height=SHAPE[0])
    camera = EmvaCamera(bit_depth=8, width=SHAPE[1], height=SHAPE[0], qe=qe, K=K, K_min=K, K_max=K, K_steps=1,
                        blackoffset=BLACK, blackoffset_min=BLACK, blackoffset_max=BLACK, blackoffset_steps=1,
                        dark_current_ref=0.0, dark_signal_0=0.0, sigma2_dark_0=SIGMA_D**2, u_esat=CAPACITY,
                        seed=seed)
    radiance = emva_routines.get_radiance(camera.exposure, mu_p, camera.pixel_area,
                                          camera.environment["f_number"], wavelength)
    assert camera.get_photons(radiance)[0] == pytest.approx(mu_p)
    return camera.grab(radiance).astype(float)


@pytest.mark.parametrize("mu_p", LEVELS)
def test_the_simulated_sensor_matches_emva1288_s_camera_model(mu_p):
    """Means agree; variances agree once emva1288's dither is counted (grab adds U(-1/2, 1/2)
    before rounding: 1/12 more than a plain ADC's rounding)."""
    a, b = ours(mu_p), emva(mu_p)
    assert a.mean() == pytest.approx(b.mean(), abs=0.02)
    assert a.var() == pytest.approx(b.var() - 1.0 / 12.0, rel=0.03)


@pytest.mark.parametrize("mu_p", LEVELS)
def test_the_simulated_sensor_follows_emva1288_s_formulas(mu_p):
    frame = ours(mu_p)
    assert frame.mean() == pytest.approx(K * ETA * mu_p + BLACK, abs=0.02)
    assert frame.var() == pytest.approx(K**2 * (SIGMA_D**2 + ETA * mu_p) + 1.0 / 12.0, rel=0.03)


def test_the_full_well_clips_below_the_adc_as_in_emva1288():
    """mu_e,sat = 20000 e- is 228 gray at K 0.0114: far beyond it, both read K mu_e,sat + b."""
    full = K * CAPACITY + BLACK
    for frame in (ours(1e6), emva(1e6)):
        assert frame.mean() == pytest.approx(full, abs=0.5) and frame.max() < 255
