"""The black level b in the model, G = b + c P t: the planner centres the signal
G - b in the band less b, `cell run` takes b from the task or measures it from a dark frame,
logs it, and its first capture then measures the model's signal; b = 0 leaves every plan as it was."""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from cell.run import loop, measurement
from cell.planning.evaluate import target_gray
from cell.task.loader import load_task
from cell.planning.one_shot import plan
from simcell import recording_connect, run_loop as run, variant

HINGE = "tasks/hinge.yaml"
B_WORLD = 5.0                   # sim.world.BLACK_LEVEL of 255, rounded
WITH_BLACK = {"sim.effects": ["shadows", "cone_falloff", "black_level", "quantization"]}


def with_black_level(task, b):
    return replace(task, camera=replace(task.camera, sensor=replace(task.camera.sensor, black_level=b)))


@pytest.fixture(scope="module")
def hinge():
    return load_task(HINGE)


@pytest.fixture(scope="module")
def plans(hinge):
    return {b: plan(with_black_level(hinge, b)) for b in (None, B_WORLD)}


def test_the_planner_centres_the_signal_above_the_black_level_in_the_band_less_it(plans):
    """The closed form puts sqrt((G_min - b)(G_max - b)) at the geometric centre of [low - b,
    high - b]: sqrt(95 x 120) for b = 5 on the hinge's 100-125, sqrt(100 x 125) without one."""
    for b, p in plans.items():
        b = b or 0.0
        g = p.shot.gray
        assert p.feasible and 100 <= g.min() and g.max() <= 125
        assert np.sqrt((g.min() - b) * (g.max() - b)) == pytest.approx(np.sqrt((100 - b) * (125 - b)), rel=1e-9)


def test_the_loop_re_exposes_the_plan_for_a_black_level_it_did_not_know(hinge, plans):
    """Model.exposure is the planner's closed form: with the plan's own b it gives the plan's
    exposure back, with b = 5 the shutter for the signal target sqrt(95 x 120)."""
    p = plans[None]
    lens_range = (p.shot.exposure.f_number, hinge.camera.lens.f_number_range[1])
    model = loop.Model(p, hinge)
    assert model.exposure(0.0, lens_range) == pytest.approx((p.shot.exposure.shutter_s, p.shot.exposure.f_number),
                                                            rel=1e-12)
    shutter, kappa = model.exposure(B_WORLD, lens_range)
    assert kappa == p.shot.exposure.f_number
    assert shutter / p.shot.exposure.shutter_s == pytest.approx(target_gray((95, 120)) / target_gray((100, 125)),
                                                                rel=1e-9)
    # and the model predicts b plus the plan's signal scaled by t
    predicted = model.predicted(B_WORLD, 2 * p.shot.exposure.shutter_s, p.shot.exposure.f_number)
    np.testing.assert_allclose(predicted, B_WORLD + 2 * p.shot.gray, rtol=1e-12)


def test_a_dark_frame_gives_its_median_and_noise():
    rng = np.random.default_rng(2)
    dark = 5.0 + rng.normal(0.0, 0.8, (200, 300))
    dark[:10, :10] = 200.0                                   # a lit corner does not move b
    black = measurement.black_level_of(dark)
    assert black.value == pytest.approx(5.0, abs=0.02) and black.noise_rms == pytest.approx(0.8, rel=0.03)
    assert black.ceiling == pytest.approx(5.0 + 4 * 0.8, abs=0.2)
    assert measurement.BlackLevel(5.0, 0.0, "task").ceiling == 6.0         # at least one level above b


def test_a_run_measures_the_black_level_from_a_dark_frame_and_converges_in_its_first_capture(tmp_path):
    """The world's sensor adds 5 gray: the dark frame (shortest shutter, planned f-number) reads
    it, the first exposure is the plan's for the signal target sqrt(95 x 120) and the capture's
    signal is the model's (without b in the model it would read (112 + 5) / 112 = 1.045x)."""
    cell = run(variant(tmp_path, HINGE, WITH_BLACK), tmp_path / "run")
    assert cell.error is None and cell.report["converged"]
    assert cell.report["black_level"] == {"value": B_WORLD, "noise_rms": 0.0, "source": "dark frame"}
    dark, = [line for line in cell.log if line["step"] == "black_level"]
    exposures = [line for line in cell.log if line["step"] == "set_exposure"]
    assert exposures[0]["shutter_s"] == load_task(HINGE).camera.shutter_range_s[0]
    assert exposures[0]["f_number"] == cell.report["plan"]["camera"]["f_number"]
    # the model's brightest sample there: 119.4 x 0.01 ms / 5.558 ms
    assert dark["iteration"] == 0 and dark["feature_light"] == pytest.approx(
        cell.report["plan"]["predicted_gray"]["max"] * 1e-5 / cell.report["plan"]["camera"]["shutter_s"], rel=0.01)
    first, = cell.report["iterations"]
    planned = cell.report["plan"]["camera"]["shutter_s"]
    assert first["shutter_s"] / planned == pytest.approx(target_gray((95, 120)) / target_gray((100, 125)), rel=1e-6)
    assert first["model_error"] == pytest.approx(1.0, abs=0.01)
    assert first["predicted_gray"]["mean"] == pytest.approx(first["measured_gray"]["mean"], abs=1.0)


def test_a_black_level_the_task_gives_is_planned_with_and_no_dark_frame_taken(tmp_path):
    cell = run(variant(tmp_path, HINGE, {**WITH_BLACK, "camera.sensor.black_level": B_WORLD}), tmp_path / "run")
    assert cell.error is None and cell.report["converged"]
    assert cell.report["black_level"] == {"value": B_WORLD, "noise_rms": 0.0, "source": "task"}
    assert [line["step"] for line in cell.log][:5] == ["plan", "move_camera", "move_lamp", "black_level",
                                                       "set_exposure"]
    first, = cell.report["iterations"]
    assert first["shutter_s"] == cell.report["plan"]["camera"]["shutter_s"]
    assert first["model_error"] == pytest.approx(1.0, abs=0.01)
    g = cell.report["plan"]["predicted_gray"]
    assert np.sqrt((g["min"] - 5) * (g["max"] - 5)) == pytest.approx(np.sqrt(95 * 120), rel=0.01)


def test_calibrate_fits_c_against_the_plans_signal_when_the_task_knows_b(tmp_path):
    """With camera.sensor.black_level in the task the plan's gray holds b; the sweep pairs the
    measured G with the model's P t of the signal alone, so c and b come out as the world's."""
    from cell.calibration import reference_part
    path = variant(tmp_path, HINGE, {**WITH_BLACK, "camera.sensor.black_level": B_WORLD,
                                     "sim.truth.camera_constant_scale": 0.8})
    task = load_task(path)
    cell = SimpleNamespace(devices=None, stops=[])
    result = reference_part.run(task, tmp_path / "c", recording_connect(task, cell), shots=4)
    assert result.camera_constant_ratio == pytest.approx(0.8, rel=0.01)
    assert result.fit.black_level == pytest.approx(B_WORLD, abs=0.5)
