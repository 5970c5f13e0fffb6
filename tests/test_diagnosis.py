"""No false "dim": pixels at the black level inside the feature's region (off
the part, a cast shadow) are found before any exposure correction and named in the reason, and a
correction implying an implausible albedo is refused, not acted on. The decision is
cell.run.control.correct's; each cause is checked on its own, on made-up measurements and on the
simulated cell with the world's part or camera moved off the conrod's 14 mm shank."""
import numpy as np
import pytest

from cell.run import control, registration
from cell.core.errors import GoalNotReached
from cell.run.measurement import BlackLevel, Measurement
from simcell import run_loop as run, variant

HINGE, CONROD = "tasks/hinge.yaml", "tasks/conrod.yaml"
LIMITS = control.Limits((110.0, 150.0), (1e-5, 0.02), (6.2, 16.0))
NO_BLACK = BlackLevel(0.0, 0.0, "task")


def measurement(pixels, samples):
    """A Measurement of raw region pixels (their surface gray the pixels themselves) and the
    gray at the samples."""
    pixels, samples = np.asarray(pixels, float), np.asarray(samples, float)
    n = len(samples)
    return Measurement(np.zeros(n, int), np.zeros(n, int), samples, np.ones(pixels.shape, bool), pixels, pixels,
                       np.zeros(pixels.shape, bool), 255.0, float(pixels.min()), float(pixels.max()))


# --- the decision, cause by cause ------------------------------------------------------------

def test_pixels_at_the_black_level_among_lit_ones_stop_before_any_exposure_correction():
    """37 of 100 pixels read b = 5 and the rest 130: without the check the darkest pixel (5)
    would read as a dim feature and the shutter would open 30x (sqrt(110 150) / sqrt(5 130))."""
    pixels = np.r_[np.full(37, 5.0), np.full(63, 130.0)]
    c = control.correct(measurement(pixels, [130.0] * 4 + [5.0]), np.full(5, 130.0), 4e-3, 6.2, LIMITS,
                        BlackLevel(5.0, 0.0, "dark frame"))
    assert c.action == "stop" and c.cause == "black pixels"
    assert c.reason.startswith("37 % of the feature's pixels read the black level 5.0 (off the part or shadowed)")
    assert "fixture / hand-eye" in c.reason


def test_a_few_black_pixels_or_a_uniformly_dim_feature_are_no_such_cause():
    few = np.r_[np.full(1, 0.0), np.full(1999, 120.0)]          # 0.05 %, below BLACK_FRACTION
    c = control.correct(measurement(few, [120.0] * 4), np.full(4, 130.0), 4e-3, 6.2, LIMITS, NO_BLACK)
    assert c.action == "exposure"
    dim = np.r_[np.full(40, 0.0), np.full(60, 3.0)]             # lit at 3 < 8 levels: too dim to tell
    fraction, lit = control.black_pixels(measurement(dim, [3.0] * 4), NO_BLACK)
    assert fraction == pytest.approx(0.4) and not lit


def test_a_correction_implying_an_albedo_outside_the_plausible_range_is_refused():
    """Measured 13 where the model says 130: an albedo x0.1 is the plausible range's edge, x0.05
    (6.5) is beyond it; 4 re-plans at x0.5 before make x0.5 x 0.2 = x0.1 implied again."""
    m = measurement(np.full(50, 13.0), [13.0] * 4)
    assert control.correct(m, np.full(4, 130.0), 4e-3, 6.2, LIMITS, NO_BLACK).action == "exposure"
    m = measurement(np.full(50, 6.5), [6.5] * 4)
    c = control.correct(m, np.full(4, 130.0), 4e-3, 6.2, LIMITS, NO_BLACK)
    assert c.action == "stop" and c.cause == "albedo"
    assert "imply an albedo x0.05 of the material table's, outside the plausible x0.1-x10" in c.reason
    m = measurement(np.full(50, 26.0), [26.0] * 4)               # 0.2x the model's, planned at x0.5
    assert control.correct(m, np.full(4, 130.0), 4e-3, 6.2, LIMITS, NO_BLACK, albedo_scale=0.5).action == "exposure"
    c = control.correct(m, np.full(4, 130.0), 4e-3, 6.2, LIMITS, NO_BLACK, albedo_scale=0.4)
    assert c.cause == "albedo" and "x0.08" in c.reason


def test_bounds_are_judged_as_bounds():
    """Every sample saturated: the error is a lower bound (>=), implausible only above the range;
    every sample at the black level: an upper bound (<=), implausible only below it."""
    assert not control.implausible_albedo(0.05, ">=", (0.1, 10.0))
    assert control.implausible_albedo(11.0, ">=", (0.1, 10.0))
    assert not control.implausible_albedo(11.0, "<=", (0.1, 10.0))
    assert control.implausible_albedo(0.05, "<=", (0.1, 10.0))


# --- the simulated cell ----------------------------------------------------------------------

ALL_BUT_DEFOCUS = ["shadows", "cone_falloff", "vignetting", "noise", "black_level", "quantization"]


@pytest.mark.parametrize("truth, percent", [
    ({"sim.truth.part_offset_m": [0.0, 0.003, 0.0], "sim.effects": ALL_BUT_DEFOCUS}, (6, 16)),
    ({"sim.truth.camera_rpy_deg": [0.25, 0.0, 0.0], "sim.effects": ALL_BUT_DEFOCUS}, (0.1, 1.5)),
], ids=["fixture-3mm-all-effects", "hand-eye-tilt-0.25deg-all-effects"])
def test_a_feature_moved_off_the_conrods_shank_stops_with_the_black_pixels_named(tmp_path, monkeypatch, truth,
                                                                               percent):
    """Registration made untrustworthy (no correlation reaches 1.01), so the model's region is
    measured, as the log says (registration itself: tests/test_register.py). The part 3 mm across the 14 mm shank puts a 1 mm-deep segment of the 12 mm patch's region beside
    the part (36 acos(4/6) - 4 sqrt(20) = 12.4 of 113 mm^2, 11 %), where nothing is lit; a 0.25 deg
    tilt about the camera's x (1.5 mm at 0.35 m) at most a 0.5 mm-deep one (1.5 %), of which the
    tilted camera sees part as the shank's side face. Either way the run stops after its first
    capture, no exposure brightened, no re-plan, with the cause, instead of brightening into
    saturation ("infeasible, shutter_max", or 6 captures swinging between 20 ms and 7 ms)."""
    monkeypatch.setattr(registration, "MIN_CORRELATION", 1.01)
    cell = run(variant(tmp_path, CONROD, truth), tmp_path / "run")
    assert isinstance(cell.error, GoalNotReached) and cell.error.exit_code == 1
    (located,) = [line for line in cell.log if line["step"] == "register"]
    assert not located["trusted"] and located["shift_px"] == [0.0, 0.0]
    assert located["message"].endswith("below 1.01): the model's region is measured")
    reason = str(cell.error)
    fraction = float(reason.split(" %")[0])
    assert percent[0] <= fraction <= percent[1]
    assert "of the feature's pixels read the black level" in reason and "fixture / hand-eye" in reason
    assert len(cell.report["iterations"]) == 1 and cell.report["replans"] == [] and "correct" not in cell.steps
    assert "shutter_max" not in reason and cell.report["reason"] == reason
    assert cell.report["iterations"][0]["correction"] == {"action": "stop", "albedo_scale": 1.0,
                                                         "reason": reason, "cause": "black pixels"}


def test_a_feature_far_too_dark_for_its_model_is_refused_not_re_planned(tmp_path):
    """Albedo x0.001: every pixel reads 0, so the model error is at most 0.5 / 120; a correction
    would imply an albedo far below x0.1: the run stops at its first capture and says so."""
    cell = run(variant(tmp_path, HINGE, {"sim.truth.albedo_scale": 0.001}), tmp_path / "run")
    assert isinstance(cell.error, GoalNotReached)
    reason = str(cell.error)
    assert reason.startswith("measured gray is at most 0.00")
    assert "every pixel of the feature reads the black level" in reason and "outside the plausible x0.1-x10" in reason
    assert len(cell.report["iterations"]) == 1 and cell.report["replans"] == []
    assert cell.report["iterations"][0]["correction"]["cause"] == "albedo"
