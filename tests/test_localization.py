"""Localization (cell.run.localization): the part's pose error in the cell and the camera's
hand-eye turn, estimated from captures of the simulated cell against its truth keys
(sim.truth.part_offset_m, part_rpy_deg, camera_rpy_deg), and the closed loop that follows them.
The expectations are the truth keys themselves and closed forms of the pinhole camera."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from cell.core import geometry
from cell.devices.rig import lamp_aim
from cell.planning.one_shot import plan
from cell.run import localization, measurement, registration
from cell.run.loop import with_black_level
from cell.task.loader import load_task
from sim.arm import SimArm
from sim.world import Renderer
from simcell import run_loop, variant

HINGE, CONROD = "tasks/hinge.yaml", "tasks/conrod.yaml"
EVERY_EFFECT = ["shadows", "cone_falloff", "vignetting", "defocus", "noise", "black_level", "quantization"]


def error(offset_m=(0.0, 0.0, 0.0), part_rpy_deg=(0.0, 0.0, 0.0), hand_eye_rpy_deg=(0.0, 0.0, 0.0),
          center=(0.0, 0.0, 0.0)):
    zero = np.zeros(3)
    return localization.PoseError(np.array(offset_m, float), np.radians(part_rpy_deg), np.radians(hand_eye_rpy_deg),
                                  zero, zero, zero, np.array(center, float), 1, 0, 0.0)


def test_one_view_sees_a_part_offset_and_a_hand_eye_turn_alike():
    """The camera 0.5 m above the feature looking down: the part 3 mm across the view moves the
    feature 3 mm; the camera turned 0.4 deg about its x moves it 0.5 m tan(0.4 deg) = 3.49 mm; a
    move along the view axis or a turn about the feature does not move it."""
    T = geometry.transform(np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, 0.5))      # z down onto the origin
    assert localization.displacement_m(error(offset_m=(0.003, 0.0, 0.0)), T) == pytest.approx(0.003, rel=1e-9)
    assert localization.displacement_m(error(hand_eye_rpy_deg=(0.4, 0.0, 0.0)), T) == pytest.approx(
        0.5 * np.tan(np.radians(0.4)), rel=1e-9)
    assert localization.displacement_m(error(offset_m=(0.0, 0.0, 0.003)), T) == pytest.approx(0.0, abs=1e-12)
    assert localization.displacement_m(error(part_rpy_deg=(3.0, 2.0, 5.0)), T) == pytest.approx(0.0, abs=1e-12)
    limit, tolerance = 0.0039, np.radians(1.0)
    assert localization.significant(error(offset_m=(0.005, 0.0, 0.0)), T, limit, tolerance)
    assert not localization.significant(error(offset_m=(0.003, 0.0, 0.0)), T, limit, tolerance)
    assert localization.significant(error(part_rpy_deg=(0.0, 2.5, 0.0)), T, limit, tolerance)   # a tilt
    assert not localization.significant(error(part_rpy_deg=(1.5, 0.0, 0.0)), T, limit, tolerance)
    assert not localization.significant(error(part_rpy_deg=(0.0, 0.0, 5.0)), T, limit, tolerance)  # about the axis


def test_the_part_error_is_the_simulators():
    """E_part turns about the feature centre, then moves: the centre moves by the offset only."""
    E = error(offset_m=(0.01, -0.002, 0.001), part_rpy_deg=(3.0, -2.0, 5.0), center=(0.006, 0.0, 0.004)).T_part
    assert geometry.apply(E, [0.006, 0.0, 0.004]) == pytest.approx([0.016, -0.002, 0.005])
    assert np.degrees(geometry.rotation_angle(E, np.eye(4))) == pytest.approx(
        np.degrees(np.linalg.norm(__import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation
                                  .from_euler("xyz", np.radians([3.0, -2.0, 5.0])).as_rotvec())))


def test_a_pose_error_found_at_one_feature_is_stated_as_the_simulator_turns_the_part_about_another():
    """The bracket's case: the part 5, -5 mm off and turned 3 deg about y about its first feature's
    centre (base_top, as the simulator's truth keys turn it), localized at the bevel 33 mm beside
    and 30 mm above: stated about base_top, the keys the simulator (sim.world.part_moved) moves
    the part by are the same motion; the offset's standard errors follow the turn's through the
    arm between the centres, as a Monte Carlo of the estimate's covariance spreads them."""
    from types import SimpleNamespace
    from sim.world import part_moved
    base_top, bevel = np.array([0.012, 0.0, 0.006]), np.array([-0.021, 0.0, 0.036])
    truth = SimpleNamespace(part_offset_m=(0.005, -0.005, 0.0), part_rpy_rad=tuple(np.radians([0.0, 3.0, 0.0])))
    E = part_moved(SimpleNamespace(sim=SimpleNamespace(truth=truth)), SimpleNamespace(center=base_top))
    rpy = np.radians([0.0, 3.0, 0.0])
    at_bevel = error(offset_m=geometry.apply(E, bevel) - bevel, part_rpy_deg=[0.0, 3.0, 0.0], center=bevel)
    assert at_bevel.T_part == pytest.approx(E, abs=1e-12)
    assert 1e3 * (at_bevel.part_offset_m - truth.part_offset_m) == pytest.approx([1.62, 0.0, 1.69], abs=0.01)
    stated = at_bevel.about(base_top)
    assert stated.part_offset_m == pytest.approx(truth.part_offset_m, abs=1e-12)
    assert stated.part_rpy_rad == pytest.approx(rpy, abs=1e-12)
    assert stated.T_part == pytest.approx(E, abs=1e-12)
    rng = np.random.default_rng(3)
    spread = rng.normal(size=(9, 9))
    cov = spread @ spread.T * 1e-7
    found = localization.PoseError(*np.split(at_bevel.theta, 3), *np.split(np.sqrt(np.diag(cov)), 3), bevel, 2, 0,
                                   0.0, cov)
    drawn = rng.multivariate_normal(found.theta, cov, 4000)
    moved = np.array([localization.PoseError(*np.split(t, 3), *[np.zeros(3)] * 3, bevel, 2, 0, 0.0).about(base_top)
                      .part_offset_m for t in drawn])
    assert found.about(base_top).part_offset_stderr_m == pytest.approx(np.std(moved, axis=0), rel=0.05)
    sampled = np.cov(moved.T)
    assert found.about(base_top).covariance[:3, :3] == pytest.approx(sampled, abs=0.05 * sampled.diagonal().max())


def test_a_corrected_hand_eye_puts_the_true_camera_where_the_loop_asks(tmp_path):
    """The world's camera is the arm's read-back pose times the truth's hand-eye error; an arm
    corrected by that error moves so that the true camera lands on the commanded pose and reads
    it back there, while the arm itself (what the simulated camera renders from) keeps the task's."""
    task = load_task(variant(tmp_path, HINGE, {}))
    E = geometry.from_rpy(np.radians([2.0, -1.0, 0.5]))
    arm = SimArm(task.cell.devices.arm, task.frames)
    corrected = localization.HandEyeCorrected(arm, E)
    T = plan(task).shot.T_cell_cam
    corrected.move_camera(T)
    assert arm.camera_pose() @ E == pytest.approx(T, abs=1e-9)          # the true camera
    assert corrected.camera_pose() == pytest.approx(T, abs=1e-9)
    assert corrected.refusal(T) is None


def dark_frame_known(task, world, T, lamp, f_number):
    """The task as the loop localizes with it (loop.with_black_level): its sensor's black level
    the one a dark frame of the simulated cell reads (the shortest shutter: measurement.black_level_of),
    as loop.find_black_level finds it."""
    dark = world(T, *lamp, task.camera.shutter_range_s[0], f_number)
    return with_black_level(task, measurement.black_level_of(dark).value)


def captures(tmp_path, task_path, truth, views, seed=None, effects=EVERY_EFFECT):
    """The simulated cell's captures (`effects` on, every one unless given; noise seed `seed`:
    the task's if None) of the task's plan from its camera and the first `views - 1` second
    views, with the lamp at the plan's pose: (task knowing its black level, scene, Views)."""
    keys = {"sim.effects": list(effects)} | {f"sim.truth.{k}": v for k, v in truth.items()}
    keys |= {} if seed is None else {"sim.seed": seed}
    task = load_task(variant(tmp_path, task_path, keys))
    planned = plan(task)
    scene, shot = planned.planned_scene, planned.shot
    lamp = (shot.lamp_position, lamp_aim(task.lamp.rig.pivot_m, shot.lamp_position))
    world = Renderer(task, scene)
    task = dark_frame_known(task, world, scene.T_cell_cam, lamp, shot.exposure.f_number)
    out = []
    for i, T in enumerate([scene.T_cell_cam] + localization.second_views(scene.T_cell_cam, scene.center)[:views - 1]):
        shutter = shot.exposure.shutter_s if i == 0 else localization.view_exposure(
            localization.model_view(task, scene, T, lamp), 255.0, shot.exposure.f_number, task.camera.shutter_range_s)
        out.append(localization.View(world(T, *lamp, shutter, shot.exposure.f_number), T, lamp))
    return task, scene, out


def test_one_view_finds_the_conrod_moved_across_its_shank(tmp_path):
    """5 mm across the shank (the view's y): the case that stopped at the registration limit. One
    view sees the move within 0.3 mm, more than the plan tolerates, and takes it for the part's
    (a hand-eye turn, which one view cannot tell from it, is held near 0: a second view decides)."""
    task, scene, views = captures(tmp_path, CONROD, {"part_offset_m": [0.0, 0.005, 0.0]}, 1)
    found = localization.localize(task, scene, views)
    assert found.part_offset_m[1] == pytest.approx(0.005, abs=3e-4)
    assert localization.displacement_m(found, views[0].T_cell_cam) == pytest.approx(0.005, abs=3e-4)
    assert localization.significant(found, views[0].T_cell_cam, 0.0039, np.radians(1.0))


@pytest.mark.long
def test_the_black_level_is_subtracted_before_the_edges_are_compared(tmp_path):
    """The sensor's black level (5 gray at 8 bits) adds to every pixel, not to the shading's
    product: left in the logarithm it bent the edges where the part is dim (the conrod's tilt
    1.0 deg off with it alone, two views; 0.3 without it). Less the level the dark frame reads,
    one view of the conrod 5 mm across its shank localizes as the same view without a black
    level: every estimate within 1 um and 0.001 deg of it (left in, the level moved its height
    0.5 mm here)."""
    found = []
    for effects in ((), ("black_level",)):
        (tmp_path / f"{len(effects)}").mkdir()
        task, scene, views = captures(tmp_path / f"{len(effects)}", CONROD, {"part_offset_m": [0.0, 0.005, 0.0]}, 1,
                                      effects=effects)
        assert task.camera.sensor.black_level == (5.0 if effects else 0.0)
        found.append(localization.localize(task, scene, views))
    assert found[1].part_offset_m == pytest.approx(found[0].part_offset_m, abs=1e-6)
    assert np.degrees(found[1].part_rpy_rad) == pytest.approx(np.degrees(found[0].part_rpy_rad), abs=1e-3)
    assert np.degrees(found[1].hand_eye_rpy_rad) == pytest.approx(np.degrees(found[0].hand_eye_rpy_rad), abs=1e-3)


@pytest.mark.long
@pytest.mark.parametrize("truth", [
    {"part_offset_m": [0.006, -0.004, 0.0], "camera_rpy_deg": [0.0, 1.5, 0.0]},
    {"part_offset_m": [0.01, 0.0, 0.0]},
    {"camera_rpy_deg": [2.0, 0.0, 0.0]},
    {"part_rpy_deg": [0.0, 5.0, 0.0]},
], ids=["offset-and-hand-eye", "offset-10mm", "hand-eye-2deg", "tilt-5deg"])
def test_two_views_tell_a_part_offset_from_a_camera_turn_on_the_hinge(tmp_path, truth):
    """Within 1 mm and 0.3 deg of the truth keys, tilts and turns about the view's axes; the
    hand-eye's roll and the part's turn about the view axis trade against each other (left out)."""
    task, scene, views = captures(tmp_path, HINGE, truth, 2)
    found = localization.localize(task, scene, views)
    assert found.views == 2
    assert found.part_offset_m == pytest.approx(truth.get("part_offset_m", [0.0] * 3), abs=1e-3)
    assert np.degrees(found.part_rpy_rad[:2]) == pytest.approx(truth.get("part_rpy_deg", [0.0] * 3)[:2], abs=0.3)
    assert np.degrees(found.hand_eye_rpy_rad[:2]) == pytest.approx(truth.get("camera_rpy_deg", [0.0] * 3)[:2],
                                                                   abs=0.3)


@pytest.mark.long
def test_the_loop_follows_a_2_deg_hand_eye_turn_on_the_hinge_and_converges(tmp_path):
    """The camera turned 2 deg about x: registration finds the feature 188 px (17.5 mm) away,
    beyond the 3.9 mm the plan tolerates. The loop takes a second view, finds the turn within
    0.3 deg and the part where the model puts it within 1 mm, corrects the hand-eye, re-plans and
    converges; report.json and the log carry the estimate with its standard errors."""
    cell = run_loop(variant(tmp_path, HINGE, {"sim.truth.camera_rpy_deg": [2.0, 0.0, 0.0],
                                              "sim.effects": EVERY_EFFECT}), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == 2
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx([2.0, 0.0], abs=0.3)
    assert found["part_offset_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert all(len(found[f"{k}_stderr"]) == 3 for k in ("part_offset_m", "part_rpy_deg", "hand_eye_rpy_deg"))
    assert "localize" in cell.steps and len(cell.report["replans"]) == 1
    (line,) = [line for line in cell.log if line["step"] == "localize" and "hand_eye_rpy_deg" in line]
    assert line["hand_eye_rpy_deg"] == found["hand_eye_rpy_deg"]


def plane_view(offset_m, size=240, f=1200.0):
    """A camera 0.3 m above the plane z = 0 looking down on it (K, T_cell_cam) and its Samples:
    the capture of the pattern p(X, Y) = sin(X / 1.5 mm) + cos(Y / 2 mm) on the plane moved by
    offset_m, 1500 points of the plane within 20 mm of the origin and p there (the model's)."""
    K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3], T[2, 3] = np.diag([1.0, -1.0, -1.0]), 0.3
    v, u = np.mgrid[:size, :size].astype(float)
    X, Y = (u - size / 2) * 0.3 / f, -(v - size / 2) * 0.3 / f

    def pattern(x, y):
        return np.sin(x / 1.5e-3) + np.cos(y / 2e-3)

    points = np.column_stack([np.random.default_rng(0).uniform(-0.02, 0.02, (1500, 2)), np.zeros(1500)])
    image = pattern(X - offset_m[0], Y - offset_m[1]).astype(np.float32)
    return K, localization.Samples(points, pattern(points[:, 0], points[:, 1]), image, T)


def test_edge_samples_with_no_image_leave_the_fit_as_it_is_without_them():
    """A sample whose point has no image (NaN: a shadow's rim that a moved caster throws behind the
    camera) has no residual and no image motion: the edge fit of a plane's pattern moved 0.4, -0.3
    mm with 50 such samples added equals the fit without them, estimate, standard errors, residual
    and edge points alike, and finds the move (one view: the priors hold the hand-eye turn)."""
    K, samples = plane_view([4e-4, -3e-4, 0.0])
    without = localization.fit([[samples]], K, np.zeros(3), np.zeros(9))
    unseen = replace(samples, points=np.vstack([samples.points, np.full((50, 3), np.nan)]),
                     gray=np.concatenate([samples.gray, np.ones(50)]))
    found = localization.fit([[unseen]], K, np.zeros(3), np.zeros(9))
    assert without.part_offset_m[:2] == pytest.approx([4e-4, -3e-4], abs=2e-6)
    assert found.theta == pytest.approx(without.theta, rel=1e-6, abs=1e-12)
    assert found.theta_stderr == pytest.approx(without.theta_stderr, rel=1e-5)
    assert found.residual == pytest.approx(without.residual, rel=1e-9)
    assert found.edge_points == without.edge_points == 1500


def test_a_fit_beyond_any_fixture_or_calibration_is_not_followed():
    """15 mm, 7 deg across the view and 3 deg of hand-eye bound what a fixture and a calibration
    can be off; the turns about the view axis, which trade on the conrod, are not judged."""
    T = geometry.transform(np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, 0.5))
    assert localization.implausible(error(offset_m=(0.01, 0.0, 0.0), part_rpy_deg=(0.0, 5.0, 0.0),
                                          hand_eye_rpy_deg=(2.0, 0.0, 0.0)), T) is None
    assert localization.implausible(error(part_rpy_deg=(0.0, 0.0, 8.0), hand_eye_rpy_deg=(0.0, 0.0, 8.0)), T) is None
    assert "28.7 mm off" in localization.implausible(error(offset_m=(0.0287, 0.0, 0.0)), T)
    assert localization.implausible(error(part_rpy_deg=(8.0, 0.0, 0.0)), T) is not None
    assert localization.implausible(error(hand_eye_rpy_deg=(0.0, 3.5, 0.0)), T) is not None


def planned_view(tmp_path, task_path):
    """The task (no truth keys), its plan's scene and lamp pose (position, aim)."""
    task = load_task(variant(tmp_path, task_path, {}))
    planned = plan(task)
    shot = planned.shot
    return task, planned.planned_scene, (shot.lamp_position, lamp_aim(task.lamp.rig.pivot_m, shot.lamp_position))


def test_a_second_view_chosen_by_information_tells_a_part_offset_from_a_camera_turn(tmp_path):
    """Closed form of the pinhole: the part moved by d across the view (its x) and the camera
    turned by d / Z about its y (Z the feature's depth) leave the feature where it was: in one
    view's information that combination weighs under 1 % of the move alone. With the second view
    by_information puts first of second_views (orbited 30 or 50 deg, rolled 90), it weighs as much
    as a quarter of the move, and that view's least eigenvalue is the best of all candidates'."""
    task, scene, lamp = planned_view(tmp_path, HINGE)
    T = scene.T_cell_cam
    depth = float((np.linalg.inv(T) @ np.append(scene.center, 1.0))[2])
    move = np.concatenate([T[:3, 0] * 1e-3, np.zeros(6)])                    # 1 mm across the view
    trade = move + np.concatenate([np.zeros(7), [1e-3 / depth, 0.0]])        # and the camera turned d / Z
    move, trade = move / localization.INFORMATION_UNITS, trade / localization.INFORMATION_UNITS
    one = localization.view_information(task, scene, T, lamp)
    assert trade @ one @ trade < 0.01 * (move @ one @ move)
    candidates = localization.second_views(T, scene.center)
    assert len(candidates) == 32
    infos = [localization.view_information(task, scene, C, lamp) for C in candidates]
    best = localization.best_view(one, infos)
    two = one + infos[best]
    assert trade @ two @ trade > 0.25 * (move @ two @ move)
    assert np.linalg.eigvalsh(two)[0] == max(np.linalg.eigvalsh(one + i)[0] for i in infos)
    first = localization.View(np.zeros((2, 2)), T, lamp)
    assert localization.by_information(task, scene, first, candidates)[0] is candidates[best]


def best_second_view(task, scene, first):
    """The simulated cell's capture from the most informative second view (by_information), the
    lamp where the first view had it, exposed by view_exposure."""
    T = localization.by_information(task, scene, first, localization.second_views(first.T_cell_cam, scene.center))[0]
    f_number = plan(task).shot.exposure.f_number
    shutter = localization.view_exposure(localization.model_view(task, scene, T, first.lamp_pose), 255.0,
                                         f_number, task.camera.shutter_range_s)
    return localization.View(Renderer(task, scene)(T, *first.lamp_pose, shutter, f_number), T, first.lamp_pose)


@pytest.mark.long
def test_the_hinge_tilted_3_deg_with_its_camera_turned_is_not_taken_for_the_other_tilt(tmp_path):
    """The case that converged on the wrong sign of the tilt (the hinge 5 mm off, tilted 3 deg
    about y, the camera turned 1 deg about x): from the most informative second view, the coarse
    starts on either side of each tilt find the truth within 1 mm and 0.3 deg."""
    truth = {"part_offset_m": [0.005, -0.005, 0.0], "part_rpy_deg": [0.0, 3.0, 0.0], "camera_rpy_deg": [1.0, 0.0, 0.0]}
    task, scene, (first,) = captures(tmp_path, HINGE, truth, 1)
    found = localization.localize(task, scene, [first, best_second_view(task, scene, first)])
    assert found.part_offset_m == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert np.degrees(found.part_rpy_rad[:2]) == pytest.approx(truth["part_rpy_deg"][:2], abs=0.3)
    assert np.degrees(found.hand_eye_rpy_rad[:2]) == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)


@pytest.mark.long
def test_a_capture_off_the_part_is_localized_not_stopped_at_its_black_pixels(tmp_path):
    """The hinge 8 mm off across y, yawed 5 deg, its camera turned 2 deg about y: the first
    capture's feature is not registered and part of its region reads the black level, which
    stopped the loop (cause black pixels) before it localized. Now it localizes (two views) and
    converges where the part is, the estimate within 1 mm and 0.3 deg of the truth keys."""
    truth = {"part_offset_m": [0.0, 0.008, 0.0], "part_rpy_deg": [0.0, 0.0, 5.0], "camera_rpy_deg": [0.0, 2.0, 0.0]}
    keys = {"sim.effects": EVERY_EFFECT} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cell = run_loop(variant(tmp_path, HINGE, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    assert not cell.report["iterations"][0]["registration"]["trusted"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == 2
    assert found["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx(truth["part_rpy_deg"], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)


@pytest.mark.long
def test_a_spread_read_on_an_unregistered_region_is_localized_before_it_stops(tmp_path):
    """The hinge turned 3 deg about y, its camera 1 deg about x, its lamp mounted 2 deg off its aim
    (the mismatch matrix's `lamp and pose`, seed 2): the first capture's feature is not registered
    (the light the model lacks and the part elsewhere), and the model's region, not the feature,
    reads a spread (max/min) of 1.80, which stopped the loop with `lamp aim` before it localized;
    at the correct model's plan the feature's is 1.20, within the band's 1.25 (aim_solvable). Now the stop on an unregistered region
    localizes first (two views, the lamp's aim found beyond its 1 deg tolerance, so a third from
    the side: docs/closed-loop.md), and the loop converges where the part is, the estimate within
    1 mm and 0.3 deg of the truth keys."""
    truth = {"part_rpy_deg": [0.0, 3.0, 0.0], "camera_rpy_deg": [1.0, 0.0, 0.0], "lamp_direction_error_deg": 2.0}
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 2} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cell = run_loop(variant(tmp_path, HINGE, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    first = cell.report["iterations"][0]
    assert not first["registration"]["trusted"] and not first["in_band"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == 3 and found["iteration"] == 1
    turns = [line["lamp_aim_deg"] for line in cell.log if line["step"] == "localize" and "lamp_aim_deg" in line]
    assert max(turns) > np.degrees(load_task(HINGE).requirements.lamp_tolerance_rad), turns
    # about the feature's centre, as the simulator turns the part: no offset
    assert found["part_offset_m"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx(truth["part_rpy_deg"], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)


def converged_located(tmp_path, task_path, truth, tilt_deg=0.3, views=2):
    """The loop on the simulated cell (every effect on, seed 1) with the truth keys: it must
    converge having followed an estimate from `views` views within 1 mm of the part's offset,
    tilt_deg of its tilts and 0.3 deg of its yaw and of the hand-eye's tilts; its report."""
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 1} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cell = run_loop(variant(tmp_path, task_path, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == views
    assert found["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert found["part_rpy_deg"][:2] == pytest.approx(truth["part_rpy_deg"][:2], abs=tilt_deg)
    assert found["part_rpy_deg"][2] == pytest.approx(truth["part_rpy_deg"][2], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)
    return cell.report


@pytest.mark.long
def test_the_hinge_10_mm_off_tilted_with_its_camera_turned_is_registered_where_it_is_and_converges(tmp_path):
    """The mismatch matrix's hinge 10 mm off in x, tilted 2 deg about x, its camera turned -1, 1 deg
    (seed 1): localized within 1 mm and 0.3 deg of the truth keys, re-planned; at the re-planned
    poses the model's lamp lobe is brighter than the world's soft-edged spot (the correct model's
    too): ECC's correlation was 0.937 with a template blurred over the window alone, below
    MIN_CORRELATION, which stopped it with cause `registration`; with the template smoothed with
    its neighbours it is 0.953 of the 0.997 the noise allows, and the window is not moved: it is
    registered where the model puts it (within 1 px), and converges."""
    truth = {"part_offset_m": [0.01, 0.0, 0.0], "part_rpy_deg": [2.0, 0.0, 0.0], "camera_rpy_deg": [-1.0, 1.0, 0.0]}
    last = converged_located(tmp_path, HINGE, truth)["iterations"][-1]["registration"]
    assert last["trusted"] and last["offset_px"] < 1.0


def test_the_whole_shift_of_a_turned_bar_across_the_view_is_its_centres():
    """A bar across the whole view (the conrod's shank), turned 4 deg about the feature's pixel and
    moved by (-52, -88) px in the capture: whole_shift finds the move of that pixel to within
    registration.COARSE px (the turned template; unturned, only the bar's one end matched)."""
    v, u = np.mgrid[:400, :600].astype(np.float32)
    model = np.where(np.abs(v - 200.0) < 40.0, 100.0, 2.0).astype(np.float32)
    model[(np.abs(v - 200.0) < 40.0) & (np.abs(u - 300.0) < 10.0)] = 60.0      # a mark on the bar
    about, shift = (300.0, 200.0), (-52.0, -88.0)
    M = cv2.getRotationMatrix2D(about, 4.0, 1.0)
    M[:, 2] += shift
    capture = cv2.warpAffine(model, M, (600, 400), borderValue=2.0)
    capture += np.random.default_rng(1).normal(0.0, 0.5, capture.shape).astype(np.float32)
    assert localization.whole_shift(model, capture, about) == pytest.approx(shift, abs=registration.COARSE)


@pytest.mark.long
def test_the_conrod_8_mm_off_yawed_with_its_camera_turned_along_the_shank_is_localized_and_converges(tmp_path):
    """The mismatch matrix's conrod 8 mm across its shank, yawed 5 deg, its camera turned 2 deg
    about y (seed 1): the camera's turn moves the image along the shank, where the first view has
    no edge; the whole view's shift, matched unturned, started the fit 480 px off and it landed
    10-25 mm off (stopped, cause `pose`). With the turned match it starts across the shank where
    registration finds it, and the two views put the part within 1 mm and its yaw and the
    hand-eye within 0.3 deg of the truth keys; its tilt about y, which the two views leave open
    (0.30 deg off from them), is told by a third view from the side (untold_tilt, side_refit:
    docs/closed-loop.md), within 0.3 deg. Followed, re-planned, it converges."""
    truth = {"part_offset_m": [0.0, 0.008, 0.0], "part_rpy_deg": [0.0, 0.0, 5.0], "camera_rpy_deg": [0.0, 2.0, 0.0]}
    converged_located(tmp_path, CONROD, truth, views=3)


def told(diagonal, residual):
    """A view's Told whose information per pixel is diagonal (INFORMATION_UNITS)."""
    return localization.Told(np.diag(np.asarray(diagonal, float)), residual)


@pytest.mark.long
def test_the_conrod_with_its_camera_turned_1_5_deg_about_x_and_minus_y_is_localized_from_the_side(tmp_path):
    """The mismatch matrix's worst conrod (seed 2, every effect): its camera turned 1.5 deg about x
    and -y. From the first, the second and a lamp-low view it was found 2.24 mm off along its shank
    and tilted 2.65 deg off about y (standard errors 0.01-0.1 deg): along the shank the tilt and
    the offset trade. With the view from the side (sideways) it is localized within 1 mm and 0.3
    deg of the truth keys (the hand-eye's roll, which trades with the part's yaw, left out), each
    estimate within 3 of its stated standard errors, and the loop converges."""
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 2, "sim.truth.camera_rpy_deg": [1.5, -1.5, 0.0]}
    cell = run_loop(variant(tmp_path, CONROD, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == 4
    assert any("from the side" in line["message"] for line in cell.log if line["step"] == "move_camera")
    truth = {"part_offset_m": [0.0] * 3, "part_rpy_deg": [0.0] * 3, "hand_eye_rpy_deg": [1.5, -1.5, 0.0]}
    assert found["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx(truth["part_rpy_deg"], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["hand_eye_rpy_deg"][:2], abs=0.3)
    for key, values in truth.items():
        assert np.all(np.abs(np.subtract(found[key], values)) <= 3.0 * np.asarray(found[f"{key}_stderr"])), key


@pytest.mark.long
def test_the_yawed_conrod_whose_tilt_two_views_leave_open_is_localized_from_the_side(tmp_path):
    """The conrod 8 mm across its shank, yawed 5 deg, its camera turned 2 deg about y (seed 2,
    every effect): two views tell its position within the registration limit, but the edge
    fit's own tilt about y is uncertain by 0.8 deg, more than the half degree the plan tolerates
    (untold_tilt), and it was found 0.35 deg off. With the view from the side of that tilt, the
    first views' estimate refined at the fine scales (side_refit), it is within 1 mm and 0.3 deg
    of the truth keys in three views, and the loop converges."""
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 2, "sim.truth.part_offset_m": [0.0, 0.008, 0.0],
            "sim.truth.part_rpy_deg": [0.0, 0.0, 5.0], "sim.truth.camera_rpy_deg": [0.0, 2.0, 0.0]}
    cell = run_loop(variant(tmp_path, CONROD, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] == 3
    assert any("the plan tolerates: a view from the side" in line["message"] for line in cell.log
               if line["step"] == "localize")
    assert np.array(found["part_offset_m"]) == pytest.approx([0.0, 0.008, 0.0], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx([0.0, 0.0, 5.0], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx([0.0, 2.0], abs=0.3)


def test_the_weakest_direction_is_where_the_views_tell_least_over_their_residual(tmp_path):
    """Closed form: views that each tell the 9 parameters independently (diagonal information i_v
    per pixel, residual r_v) leave the part's offset along axis j open by
    1 mm / sqrt(sum_v i_vj / r_v^2 + (1 mm / PRIOR_OFFSET_M)^2); the worst axis is the one told
    least. A view's information counts over its residual squared, one not captured takes the
    worst residual of the others, and a view added never opens the position further. It is open
    where COVERAGE uncertainties exceed the limit."""
    task, scene, _ = planned_view(tmp_path, CONROD)
    strong = [100.0, 100.0, 100.0] + [50.0] * 6
    first, second = told([0.0, 4.0, 9.0] + [50.0] * 6, 0.2), told([2.0, 400.0, 1.0] + [50.0] * 6, 0.5)
    found = localization.resolution(task, scene, [first, second], 2)
    prior = (1e-3 / localization.PRIOR_OFFSET_M) ** 2
    assert found.uncertainty_m == pytest.approx(1e-3 / np.sqrt(2.0 / 0.25 + prior), rel=1e-9)
    assert np.abs(found.direction) == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)
    assert found.residuals == (0.2, 0.5)
    alone = localization.resolution(task, scene, [first], 1)
    assert alone.uncertainty_m == pytest.approx(localization.PRIOR_OFFSET_M, rel=1e-9)   # x: the prior only
    assert alone.uncertainty_m > found.uncertainty_m
    unseen = localization.resolution(task, scene, [first, told(strong, None)], 2)
    assert unseen.uncertainty_m == pytest.approx(1e-3 / np.sqrt(100.0 / 0.04 + prior), rel=1e-9)
    assert "length (the part's x" in alone.along and "20.0 mm" in alone.unresolved(0.0039)
    coverage = localization.COVERAGE
    assert found.unresolved(coverage * found.uncertainty_m) is None
    assert found.unresolved(0.99 * coverage * found.uncertainty_m) is not None


def test_the_views_covariance_is_each_parameter_told_over_the_residual_and_widens_the_fit_s():
    """Closed form: views that tell the 9 parameters independently (diagonal information i_v per
    pixel, residual r_v) leave parameter j uncertain by u_j / sqrt(sum_v i_vj / r_v^2 + p_j^2),
    u_j its INFORMATION_UNITS (1 mm, 0.3 deg) and p_j the prior's u_j / spread (PRIOR_*); a view
    not captured counts over the worst residual of the others. Widened by it, an estimate's
    standard errors are both sources' in quadrature, its value unchanged."""
    first, second = told([0.0, 4.0, 9.0] + [50.0] * 6, 0.2), told([2.0, 400.0, 1.0] + [25.0] * 6, 0.5)
    units = localization.INFORMATION_UNITS
    spreads = np.array([localization.PRIOR_OFFSET_M] * 3 + [localization.PRIOR_TURN_RAD] * 3
                       + [localization.PRIOR_HAND_EYE_RAD] * 3)
    told_sum = np.array([0.0, 4.0, 9.0] + [50.0] * 6) / 0.04 + np.array([2.0, 400.0, 1.0] + [25.0] * 6) / 0.25
    expected = units / np.sqrt(told_sum + (units / spreads) ** 2)
    covariance = localization.rendered_covariance([first, second], 2)
    assert np.sqrt(np.diag(covariance)) == pytest.approx(expected, rel=1e-9)
    assert covariance - np.diag(np.diag(covariance)) == pytest.approx(np.zeros((9, 9)), abs=1e-18)
    unseen = localization.rendered_covariance([first, told([2.0, 400.0, 1.0] + [25.0] * 6, None)], 2)
    assert np.sqrt(unseen[0, 0]) == pytest.approx(1e-3 / np.sqrt(2.0 / 0.04 + (1e-3 / spreads[0]) ** 2), rel=1e-9)
    found = error([0.001, 0.002, 0.0], [0.5, -1.0, 0.0], [0.1, 0.0, 0.0])
    found = replace(found, part_offset_stderr_m=np.array([3e-5, 4e-5, 0.0]),
                                 part_rpy_stderr_rad=np.radians([0.1, 0.2, 0.0]), covariance=None)
    widened = found.widened(covariance)
    own = np.concatenate([[3e-5, 4e-5, 0.0], np.radians([0.1, 0.2, 0.0]), [0.0] * 3])
    assert widened.theta_stderr == pytest.approx(np.sqrt(own**2 + expected**2), rel=1e-9)
    assert widened.theta == pytest.approx(found.theta, abs=0.0)
    assert widened.covariance == pytest.approx(np.diag(own**2) + covariance, rel=1e-12)


def looking_at(center, direction, distance_m=0.3):
    """A camera pose (cell frame) distance_m from center along direction, its z axis onto center."""
    z = -geometry.unit(np.asarray(direction, float))
    x = geometry.unit(np.cross([0.3, 0.5, 0.8], z))
    return geometry.transform(np.column_stack([x, np.cross(z, x), z]), center - distance_m * z)


def tilt_told(T_cell_cam, center, length, across, axis):
    """Brute force: what a bar's two long edges (along `length` through center, 80 mm long, 6 mm
    apart across it) tell of the bar's tilt about `axis` in a view from T_cell_cam, with its
    offset free: each edge point's image motion per tilt and per offset (pinhole, numeric
    differences), of it only the part across the edge's image (an edge tells nothing along
    itself), the tilt's information less what the offset explains (its Schur complement)."""
    def image(points):
        local = geometry.apply(np.linalg.inv(T_cell_cam), points)
        return local[:, :2] / local[:, 2:]

    s = np.linspace(-0.04, 0.04, 41)
    rows = []
    for side in (-0.003, 0.003):
        points = center + s[:, None] * length + side * across
        tangent = image(points + 1e-6 * length) - image(points - 1e-6 * length)
        normal = np.column_stack([-tangent[:, 1], tangent[:, 0]]) / np.linalg.norm(tangent, axis=1)[:, None]
        moves = [np.cross(axis, points - center)] + [np.tile(e, (len(s), 1)) for e in np.eye(3)]
        motions = [(image(points + 1e-6 * m) - image(points - 1e-6 * m)) / 2e-6 for m in moves]
        rows.append(np.column_stack([np.sum(normal * motion, axis=1) for motion in motions]))
    J = np.vstack(rows)
    info = J.T @ J
    return float(info[0, 0] - info[0, 1:] @ np.linalg.pinv(info[1:, 1:]) @ info[1:, 0])


def test_a_tilt_told_worse_than_the_plan_tolerates_is_viewed_from_where_its_edges_tell_it_most():
    """The first camera 0.3 m from the feature centre c along b (slanted 10 deg), the estimate's
    tilt about a (across b) uncertain by s: untold_tilt names it where s exceeds TILT_TOLD lamp
    tolerances (1 deg: 0.5 deg), with s, and not below, nor for a turn about the view axis
    however uncertain. Of the views orbited 50 deg from b in 12 directions, sideways puts first
    (the lamp toward +a: from the side away from it) the one whose edges, of a bar along the direction
    a tilt about a moves along b only (b x a), tell that tilt most with the bar's offset free (a
    brute force over the views, tilt_told: the first view's by perspective alone, less than a
    tenth of it)."""
    c = np.array([0.01, 0.02, 0.0])
    b = geometry.unit([0.0, np.sin(np.radians(10.0)), 1.0])
    a = geometry.unit(np.cross(b, [1.0, 0.3, 0.0]))
    T_first, tolerance = looking_at(c, b), np.radians(1.0)
    limit = localization.TILT_TOLD * tolerance

    def uncertain(axis, stderr_rad):
        cov = np.zeros((9, 9))
        cov[3:6, 3:6] = stderr_rad**2 * np.outer(axis, axis) + np.radians(0.01) ** 2 * np.eye(3)
        return localization.untold_tilt(replace(error(center=c), covariance=cov), T_first, tolerance)

    direction, stderr = uncertain(a, 1.5 * limit)
    assert stderr == pytest.approx(1.5 * limit, rel=1e-3)
    assert uncertain(a, 0.9 * limit) is None and uncertain(b, 10 * limit) is None
    length = np.cross(b, a)
    assert abs(direction @ length) == pytest.approx(1.0, abs=1e-6)
    across = np.cross(length, b)
    poses = [looking_at(c, np.cos(np.radians(50.0)) * b + np.sin(np.radians(50.0))
                        * (np.cos(phi) * a + np.sin(phi) * length))
             for phi in np.radians(np.arange(0.0, 360.0, 30.0))]
    told = np.array([tilt_told(T, c, length, across, a) for T in poses])
    order = localization.sideways(poses, T_first, c, direction, c + 0.5 * b + 0.2 * a)
    assert told[order[0]] == pytest.approx(told.max(), rel=1e-3), (order, told.round(1))
    assert all(poses[i][:3, 3] @ a < c @ a for i in order)
    assert tilt_told(T_first, c, length, across, a) < 0.1 * told.max()


def test_a_view_from_the_side_of_an_open_direction_is_one_orbited_about_it_away_from_the_lamp(tmp_path):
    """The conrod's first view looks down its shank's top face; the second views orbit the camera
    by theta about axes at angle phi to the view's x (second_views). Orbited about x (the shank, the
    direction left open), the camera moves across the shank, to its side by sin(theta) |cos(phi)|
    of its unit vector from the feature (within the first view's 0.05 slant and the 1.5 deg aim
    off); about the view's y it moves along the shank, not to its side at all. sideways puts the
    50 deg orbits about x on the side away from the lamp (the plan's, at +y) first, and leaves out
    those less than SIDEWAYS to the side and every one on the lamp's side."""
    task, scene, (lamp_m, _) = planned_view(tmp_path, CONROD)
    poses = localization.second_views(scene.T_cell_cam, scene.center)
    order = localization.sideways(poses, scene.T_cell_cam, scene.center, np.array([1.0, 0.0, 0.0]), lamp_m)
    closed = np.array([np.sin(np.radians(orbit)) * abs(np.cos(2.0 * np.pi * k / localization.ORBITS))
                       for orbit in localization.ORBITS_DEG for _ in (1, -1) for k in range(localization.ORBITS)])
    lamp_side = np.sign(lamp_m[1] - scene.center[1])
    away = [i for i in range(len(poses)) if np.sign(poses[i][1, 3] - scene.center[1]) == -lamp_side]
    assert lamp_side > 0 and closed[order[0]] == pytest.approx(np.sin(np.radians(50.0)), abs=1e-9)
    assert set(order) <= set(away)
    assert {i for i in away if closed[i] >= localization.SIDEWAYS + 0.03} <= set(order)
    assert not {i for i in range(len(poses)) if closed[i] < localization.SIDEWAYS - 0.03} & set(order)
    assert all(closed[a] >= closed[b] - 0.03 for a, b in zip(order, order[1:]))


def test_a_direction_is_named_by_the_part_s_axes(tmp_path):
    """The conrod is 167 mm long (x), 50 mm wide (y), 16 mm high (z): its axes by their extents;
    a direction between them (45 deg) by its cell-frame vector only."""
    task, scene, _ = planned_view(tmp_path, CONROD)
    assert localization.along(task, scene, np.array([-1.0, 0.0, 0.0])).startswith("along its length (the part's x")
    assert localization.along(task, scene, np.array([0.0, 1.0, 0.0])).startswith("along its width (the part's y")
    assert localization.along(task, scene, np.array([0.1, 0.0, 1.0]) / np.hypot(0.1, 1.0)).startswith(
        "along its height (the part's z")
    assert localization.along(task, scene, np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)) == \
        "along [+0.71, +0.71, +0.00] in the cell"


def test_a_straight_shank_tells_nothing_of_a_move_along_itself(tmp_path):
    """The conrod's first view sees only its shank, a prism along x: moved along x it renders the
    same image (the light stays in the cell), so rendered_information tells nothing along x, and
    the part's position there is open by the prior's spread exactly, named as along its length;
    across the shank (y) and along the view the same view tells it within 1 mm. The edges' motion
    (view_information) claims x is told: every edge point moves in the image."""
    task, scene, (view,) = captures(tmp_path, CONROD, {}, 1)
    (seen,) = localization.rendered_information(task, scene, error(center=scene.center),
                                                [(view.T_cell_cam, view.lamp_pose, None)], [view.image])
    assert seen.information[0, 0] < 1e-9 * seen.information[1, 1] and seen.residual < 1.0
    found = localization.resolution(task, scene, [seen], 1)
    assert found.uncertainty_m == pytest.approx(localization.PRIOR_OFFSET_M, rel=1e-6)
    assert np.abs(found.direction) == pytest.approx([1.0, 0.0, 0.0], abs=1e-6)
    assert "cannot be told from these 1 view" in found.unresolved(0.0039)
    covariance = np.linalg.inv(seen.information / seen.residual**2 + np.diag(localization._priors(
        localization.INFORMATION_UNITS, 1) ** 2))
    assert np.sqrt(covariance[1, 1]) * 1e-3 < 1e-3
    motion = localization.view_information(task, scene, view.T_cell_cam, view.lamp_pose)
    assert motion[0, 0] > 0.0


def test_a_re_plan_after_localization_whose_move_collides_is_refused_naming_the_pose_first(tmp_path):
    """The move to the shot planned where the localization puts the part runs into the wall
    (test_motion's: no path clears it): where_located refuses it, moving nothing, and the stop's
    words (there) name the pose found first, then the collision; a clear stop passes."""
    from types import SimpleNamespace
    from cell.report.recorder import Recorder
    from cell.run import motion
    from cell.run.context import RunContext
    from cell.run.loop import there, where_located
    from test_collision import stop
    from test_motion import walled_in
    task, a, b, devices = walled_in(tmp_path)
    shot = SimpleNamespace(T_cell_cam=b.T_cell_cam, joints=b.lamp_joints)
    found = error(offset_m=(0.01, 0.0, 0.0))
    with Recorder(tmp_path / "run") as recorder:
        move = where_located(RunContext(task, devices, recorder, 6), task, shot, found)
    assert not move.clear
    said = there(found, f"the move there is refused: {motion.refusal(move)}")
    assert said.startswith("the part is off by [+10.00, +0.00, +0.00] mm") and "collision: " in said
    assert "fixture and " in said and "before anything moved" in said
    assert devices.arm.moves == 0 and devices.lamp.moves == 0
    clear = stop(task, -0.15, b.arm_joints)
    with Recorder(tmp_path / "run2") as recorder:
        assert where_located(RunContext(task, devices, recorder, 6), task,
                             SimpleNamespace(T_cell_cam=clear.T_cell_cam, joints=clear.lamp_joints), error()).clear


@pytest.mark.long
@pytest.mark.parametrize("seed", [1, 2])
def test_the_conrod_10_mm_along_its_shank_converges_or_stops_naming_the_direction(tmp_path, seed):
    """The mismatch matrix's conrod 10 mm along its shank, tilted 2 deg about x, its camera turned
    -1, 1 deg: the first view has no edge along the shank; the two-view fit put the part 2.7 mm
    off, and the re-plan for there was refused by the collision check (cause `collision`). Now
    the weakest-direction guard takes further views where the part's position along the shank is
    open beyond the registration limit, and the run converges (within 1 mm of the truth keys) or
    stops with `pose` naming that direction; never `collision`."""
    truth = {"part_offset_m": [0.01, 0.0, 0.0], "part_rpy_deg": [2.0, 0.0, 0.0], "camera_rpy_deg": [-1.0, 1.0, 0.0]}
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": seed} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cell = run_loop(variant(tmp_path, CONROD, keys), tmp_path / "run")
    report = cell.report
    assert report.get("cause") != "collision", report["reason"]
    if report["converged"]:
        assert report["localization"]["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    else:
        assert cell.error.exit_code == 1 and report["cause"] == "pose", report["reason"]
        assert "along its length (the part's x" in report["reason"] and "cannot be told" in report["reason"]


@pytest.mark.long
def test_the_bracket_localized_at_its_bevel_reports_the_pose_as_the_simulator_turns_the_part(tmp_path):
    """The bracket 5, -5 mm off, turned 3 deg about y, its camera turned 1 deg about x (seed 1,
    every effect): the first shot the route visits localizes the part at its own feature, 33 mm
    beside and 30 mm above base_top, about whose centre the simulator turns the part. report.json
    states the pose error about base_top, within 1 mm and 0.3 deg of the truth keys (about the
    bevel it read 1.7 mm off in x and z), and the run converges."""
    import json
    from cell import cli
    truth = {"part_offset_m": [0.005, -0.005, 0.0], "part_rpy_deg": [0.0, 3.0, 0.0], "camera_rpy_deg": [1.0, 0.0, 0.0]}
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 1} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cli.main(["run", str(variant(tmp_path, "tasks/bracket.yaml", keys)), "--out", str(tmp_path / "run")])
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["converged"], report["reason"]
    found = report["localization"]
    assert found["followed"] and found["views"] == 2
    assert found["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx(truth["part_rpy_deg"], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)


@pytest.mark.long
def test_the_standard_errors_cover_the_estimates_spread_over_seeds(tmp_path):
    """The hinge 5, -5 mm off, tilted 3 deg about y, its camera turned 1 deg about x, from the
    first and the most informative second view, every effect on, three noise seeds: each of the
    9 estimates is within 3 of its reported standard errors of the truth key in at least 25 of
    the 27 (the sandwich over image tiles: the fit's s^2 (J^T J)^-1 alone counted every edge
    pixel as independent, 2.5-4 times smaller on the conrod), and the standard errors are no
    wider than the truth needs: the largest error at least 0.5 of its standard error."""
    truth = {"part_offset_m": [0.005, -0.005, 0.0], "part_rpy_deg": [0.0, 3.0, 0.0], "camera_rpy_deg": [1.0, 0.0, 0.0]}
    expected = np.concatenate([truth["part_offset_m"], np.radians(truth["part_rpy_deg"]),
                               np.radians(truth["camera_rpy_deg"])])
    z = []
    for seed in (1, 2, 3):
        (tmp_path / f"{seed}").mkdir()
        task, scene, (first,) = captures(tmp_path / f"{seed}", HINGE, truth, 1, seed)
        found = localization.localize(task, scene, [first, best_second_view(task, scene, first)])
        z.append((found.theta - expected) / found.theta_stderr)
    z = np.abs(np.array(z))
    assert np.sum(z <= 3.0) >= 25, np.round(z, 1)
    assert z.max() >= 0.5, np.round(z, 1)


def test_the_lamp_low_along_a_direction_stands_in_the_vertical_plane_through_it(tmp_path):
    """lamps_along on the conrod's rig (pivot at the feature, pan -180..180, tilt 5..85 deg): for
    its length (x) the lamp stands on either side along x, in the vertical plane through the pivot
    and x, at elevations 15 and 25 deg (rig.lamp_position's, against the closed form atan of height
    over distance), and the pans stay inside the rig's range (no pan at 180 deg exactly). The same
    four for -x; none for a nearly vertical direction; a rig that tilts no lower than 20 deg keeps
    only the 25 deg ones."""
    from dataclasses import replace
    from cell.devices.rig import lamp_position
    task = load_task(variant(tmp_path, CONROD, {}))
    rig, pivot = task.lamp.rig, np.asarray(task.lamp.rig.pivot_m)
    joints = localization.lamps_along(task, np.array([1.0, 0.0, 0.0]), 0.22)
    assert len(joints) == 4
    offsets = np.array([lamp_position(pivot, *j) - pivot for j in joints])
    assert np.abs(offsets[:, 1]) == pytest.approx(0.0, abs=0.22 * np.radians(1.01))    # in the x-z plane
    assert sorted(np.sign(offsets[:, 0])) == [-1.0, -1.0, 1.0, 1.0]
    elevations = np.degrees(np.arctan2(offsets[:, 2], np.hypot(offsets[:, 0], offsets[:, 1])))
    assert sorted(elevations) == pytest.approx([15.0, 15.0, 25.0, 25.0], abs=1e-9)
    assert np.linalg.norm(offsets, axis=1) == pytest.approx(0.22, abs=1e-12)
    assert all(rig.pan_range_rad[0] < j[0] < rig.pan_range_rad[1] for j in joints)
    backwards = localization.lamps_along(task, np.array([-1.0, 0.0, 0.0]), 0.22)
    assert np.array(sorted(backwards)) == pytest.approx(np.array(sorted(joints)))
    assert localization.lamps_along(task, np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0), 0.22) == []
    high = replace(task, lamp=replace(task.lamp, rig=replace(rig, tilt_range_rad=(np.radians(20.0), rig.tilt_range_rad[1]))))
    assert [np.degrees(j[1]) for j in localization.lamps_along(high, np.array([1.0, 0.0, 0.0]), 0.22)] == \
        pytest.approx([25.0, 25.0])


def test_the_lamp_low_along_the_shank_tells_where_the_part_is_along_it(tmp_path):
    """The conrod's first view with the planned lamp tells nothing along the shank (x: the test
    above); from the same camera, the lamp low along the shank (lamps_along: the big boss's shadow
    falls across the shank in view) tells it: rendered_information's x per pixel is a fair part
    of the across-the-shank y's. Then along_start, from an estimate with the part where the model
    has it, moves it along x to within 1 mm of the truth key's 10 mm (the rendered residual of
    both views; the edges' cost of the first view falls toward the model's pose)."""
    from cell.devices.rig import lamp_position
    task, scene, (first,) = captures(tmp_path, CONROD, {"part_offset_m": [0.01, 0.0, 0.0]}, 1)
    pivot = np.asarray(task.lamp.rig.pivot_m)
    radius = float(np.linalg.norm(first.lamp_pose[0] - pivot))
    low = [j for j in localization.lamps_along(task, np.array([1.0, 0.0, 0.0]), radius) if j[0] < 0][0]
    position = lamp_position(pivot, *low)
    lamp = (position, lamp_aim(pivot, position))
    planned, lit = localization.rendered_information(task, scene, error(center=scene.center),
                                                     [(first.T_cell_cam, first.lamp_pose, None),
                                                      (first.T_cell_cam, lamp, None)])
    assert planned.information[0, 0] < 1e-9 * planned.information[1, 1]
    assert lit.information[0, 0] > 0.05 * lit.information[1, 1]
    world = Renderer(task, scene)
    model = localization.model_view(task, scene, first.T_cell_cam, lamp)
    shutter = localization.view_exposure(model, 255.0, 6.2, task.camera.shutter_range_s)
    second = localization.View(world(first.T_cell_cam, *lamp, shutter, 6.2), first.T_cell_cam, lamp)
    moved = localization.along_start(task, scene, [first, second], error(center=scene.center),
                                     np.array([1.0, 0.0, 0.0]))
    assert moved.part_offset_m == pytest.approx([0.01, 0.0, 0.0], abs=1e-3)
    assert moved.part_rpy_rad == pytest.approx(np.zeros(3)) and moved.hand_eye_rpy_rad == pytest.approx(np.zeros(3))


@pytest.mark.long
@pytest.mark.parametrize("seed", [1, 2])
def test_the_conrod_s_turns_are_within_0_3_deg_and_their_standard_errors(tmp_path, seed):
    """The conrod 8 mm across its shank, yawed 5 deg, its camera turned 2 deg about y, from the
    first and the most informative second view, every effect on: its tilt about y came out
    0.58 deg off while the black level was left in the logarithm, 5-16 of its standard errors.
    Now each of the part's turns is within 0.3 deg of the truth keys and within 3 of its standard
    errors (which hold the two finest scales' difference in quadrature: the world's softer lamp
    edge, vignetting and defocus, which the model's image lacks, bias every seed alike), its
    offset within 1 mm. Not asserted, as it does not hold: the offset's and the hand-eye's
    standard errors covering theirs (seed 2: x, y and the hand-eye's tilts 4-5 of them out)."""
    truth = {"part_offset_m": [0.0, 0.008, 0.0], "part_rpy_deg": [0.0, 0.0, 5.0], "camera_rpy_deg": [0.0, 2.0, 0.0]}
    task, scene, (first,) = captures(tmp_path, CONROD, truth, 1, seed)
    found = localization.localize(task, scene, [first, best_second_view(task, scene, first)])
    turn = found.part_rpy_rad - np.radians(truth["part_rpy_deg"])
    assert np.all(np.degrees(np.abs(turn)) <= 0.3), np.degrees(turn)
    assert np.all(np.abs(turn) <= 3.0 * found.part_rpy_stderr_rad), (turn / found.part_rpy_stderr_rad)
    assert found.part_offset_m == pytest.approx(truth["part_offset_m"], abs=1e-3)


def test_a_shadow_s_rim_moves_as_its_caster_and_its_receiver_do_under_a_fixed_lamp():
    """Closed form: the lamp L 100 mm above a floor (z = 0) and 200 mm to the side, a caster point
    Q 10 mm above it, its shadow's rim B on the floor where the ray from L through Q meets it.
    The part (floor and caster) moved by dx along the floor moves the rim by dx H / (H - h)
    (similar triangles, H the lamp's height, h the caster's), raised by dz moves it to
    x_L + (x_Q - x_L) (H - dz) / (H - h - dz); a part's edge moves by dx and 0. Turned and moved
    anyhow, the rim lies on the line from L through the moved caster and on the moved floor."""
    lamp, caster, normal = np.array([-0.2, 0.0, 0.1]), np.array([0.0, 0.0, 0.01]), np.array([0.0, 0.0, 1.0])
    rim = lamp + (caster - lamp) * 0.1 / 0.09
    assert rim[2] == pytest.approx(0.0, abs=1e-15)
    drawn = localization.Drawn(np.ones(1, bool), caster[None], rim[None], normal[None], lamp)
    assert localization.shadow_points(np.eye(4), drawn)[0] == pytest.approx(rim, abs=1e-15)
    moved = localization.shadow_points(geometry.transform(translation=(0.003, 0.0, 0.0)), drawn)[0]
    assert moved == pytest.approx(rim + [0.003 * 0.1 / 0.09, 0.0, 0.0], abs=1e-12)
    raised = localization.shadow_points(geometry.transform(translation=(0.0, 0.0, 0.002)), drawn)[0]
    assert raised == pytest.approx([-0.2 + 0.2 * 0.098 / 0.088, 0.0, 0.002], abs=1e-12)
    E = localization.part_error(np.array([0.004, -0.002, 0.001]), np.radians([2.0, 3.0, -4.0]),
                                np.array([0.01, 0.0, 0.0]))
    turned = localization.shadow_points(E, drawn)[0]
    along = geometry.apply(E, caster) - lamp
    assert np.linalg.norm(np.cross(turned - lamp, along)) == pytest.approx(0.0, abs=1e-15)
    assert geometry.rotate(E, normal) @ (turned - geometry.apply(E, rim)) == pytest.approx(0.0, abs=1e-15)


def test_the_edges_a_low_lamp_s_shadow_draws_appear_where_the_world_renders_them(tmp_path):
    """The conrod tilted 3 deg about its width (y), seen from its plan's camera with the lamp 15 deg
    low along its shank (lamps_along): the big boss's shadow falls along the shank. The simulated
    world, shadows its only effect, renders it at the truth. Of the model's edge samples, those
    its cast shadows draw (Samples.drawn, at every scale) appear under the true pose where the
    world's band-passed edges match the model's within half the residual they have moved with the
    part, as the fit moved every edge before (_project); the edges of the part alike either way."""
    from cell.devices.rig import lamp_position
    truth = {"part_rpy_deg": [0.0, 3.0, 0.0]}
    task, scene, (first,) = captures(tmp_path, CONROD, truth, 1, effects=["shadows"])
    pivot = np.asarray(task.lamp.rig.pivot_m)
    radius = float(np.linalg.norm(first.lamp_pose[0] - pivot))
    low = [j for j in localization.lamps_along(task, np.array([1.0, 0.0, 0.0]), radius) if j[0] < 0][0]
    position = lamp_position(pivot, *low)
    lamp = (position, lamp_aim(pivot, position))
    model = localization.model_view(task, scene, first.T_cell_cam, lamp, drawn=True)
    shutter = localization.view_exposure(model, 255.0, 6.2, task.camera.shutter_range_s)
    image = localization.signal(task, Renderer(task, scene)(first.T_cell_cam, *lamp, shutter, 6.2))
    theta = np.concatenate([np.zeros(3), np.radians(truth["part_rpy_deg"]), np.zeros(3)])
    K = localization.projection.intrinsics(task.camera.sensor, task.camera.lens)

    def rms(samples, uv, which):
        seen = localization.sampled(samples.image, uv)
        gain = float(seen @ samples.gray) / float(seen @ seen)
        return float(np.sqrt(np.mean((gain * seen - samples.gray)[which] ** 2)))

    for sigma in localization.SCALES_PX:
        samples = localization.edge_samples(model, image, sigma)
        cast = samples.drawn.which
        assert cast.sum() > 100
        modelled = localization._appear(K, theta, scene.center, samples)
        rigid = localization._project(K, theta, scene.center, samples.T_cell_cam, samples.points)
        assert rms(samples, modelled, cast) < 0.5 * rms(samples, rigid, cast)
        assert modelled[~cast] == pytest.approx(rigid[~cast], abs=1e-9)


@pytest.mark.long
def test_the_conrod_5_mm_off_tilted_3_deg_with_its_camera_turned_is_localized_within_0_3_deg(tmp_path):
    """The mismatch matrix's conrod 5, -5 mm off, tilted 3 deg about y, its camera turned 1 deg
    about x (seed 1, every effect): its position along the shank open after two views, the loop
    takes further ones, the last with the lamp 15 deg low along the shank, whose boss casts its
    shadow along it. With every edge moved with the part the estimate came out tilted 1.25 deg
    short (the world's shadows alone 1.62 deg; none 0.04); with the shadows' rims moved as the
    fixed lamp draws them, it is within 1 mm and 0.3 deg of the truth keys (its yaw, which trades
    with the hand-eye's roll, too), and the run converges. Then a view from the side: from there
    the move to the re-planned shot is refused (the camera body 9.8 mm from the forearm), so the
    arm goes back to where the part was found first, the way checked before the side view was
    taken."""
    truth = {"part_offset_m": [0.005, -0.005, 0.0], "part_rpy_deg": [0.0, 3.0, 0.0], "camera_rpy_deg": [1.0, 0.0, 0.0]}
    keys = {"sim.effects": EVERY_EFFECT, "sim.seed": 1} | {f"sim.truth.{k}": v for k, v in truth.items()}
    cell = run_loop(variant(tmp_path, CONROD, keys), tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    moves = [line["message"] for line in cell.log if line["step"] == "move_camera"]
    side = next(i for i, m in enumerate(moves) if "from the side" in m)
    assert "back where the part was found, the move on from the side view refused" in moves[side + 1]
    found = cell.report["localization"]
    assert found["followed"] and found["views"] >= 3
    assert found["part_offset_m"] == pytest.approx(truth["part_offset_m"], abs=1e-3)
    assert found["part_rpy_deg"] == pytest.approx(truth["part_rpy_deg"], abs=0.3)
    assert found["hand_eye_rpy_deg"][:2] == pytest.approx(truth["camera_rpy_deg"][:2], abs=0.3)


def test_a_lamp_turn_models_the_views_at_its_lamp_pose_and_leaves_the_others():
    """Closed form: a lamp 0.2 m above the pivot, its aim straight down, its axis found turned by
    atan(0.03) = 1.72 deg toward x: LampTurn's angle is that, and its true axis replaces the aim
    of a view whose lamp stands within a servo tick of that pose (0.3 mm, 0.05 deg off), never of
    one at another pose (5 mm away, or aimed 1 deg otherwise: a lamp-low view), the position kept."""
    position, aim = np.array([0.0, 0.0, 0.2]), np.array([0.0, 0.0, -1.0])
    axis = geometry.unit(np.array([0.03, 0.0, -1.0]))
    turn = localization.LampTurn((position, aim), axis, 0.1, 0.5)
    assert np.degrees(turn.angle_rad) == pytest.approx(np.degrees(np.arctan(0.03)), rel=1e-9)
    assert turn.to_json()["lamp_aim_deg"] == pytest.approx(np.degrees(np.arctan(0.03)), rel=1e-9)
    tick = geometry.unit(np.array([np.tan(np.radians(0.05)), 0.0, -1.0]))
    near = localization.View(np.zeros((2, 2)), np.eye(4), (position + [3e-4, 0.0, 0.0], tick))
    assert localization.same_lamp(near.lamp_pose, turn.lamp_pose)
    turned = turn.applied(near)
    assert turned.lamp_pose[1] == pytest.approx(axis) and turned.lamp_pose[0] == pytest.approx(position + [3e-4, 0, 0])
    away = localization.View(np.zeros((2, 2)), np.eye(4), (position + [5e-3, 0.0, 0.0], aim))
    aside = localization.View(np.zeros((2, 2)), np.eye(4),
                              (position, geometry.unit(np.array([0.0, np.tan(np.radians(1.0)), -1.0]))))
    assert turn.applied(away) is away and turn.applied(aside) is aside


@pytest.mark.long
@pytest.mark.parametrize("aim_error_deg", [2.0, 0.0])
def test_a_lamp_off_its_aim_is_found_and_the_conrod_located_again_under_it(tmp_path, aim_error_deg):
    """The conrod 5 mm across its shank, its lamp mounted 2 deg off its aim (the simulator's truth
    axis, sim.world.Renderer.lamp_axis), first and most informative second view, every effect on:
    the lamp's fade along the shank, moved by the aim, was read as the part 12.7 mm along it.
    lamp_turn at that estimate finds the true axis within 0.5 deg, beyond the 1 deg lamp
    tolerance, and localized again with both views under it the part is within 1 mm of the truth
    key. With the lamp on its aim the turn found stays within the tolerance (the loop applies none)."""
    truth = {"part_offset_m": [0.0, 0.005, 0.0], "lamp_direction_error_deg": aim_error_deg}
    task, scene, (first,) = captures(tmp_path, CONROD, truth, 1)
    views = [first, best_second_view(task, scene, first)]
    found = localization.lamp_turn(task, scene, views, localization.localize(task, scene, views))
    tolerance = task.requirements.lamp_tolerance_rad
    if aim_error_deg == 0.0:
        assert found.angle_rad <= tolerance, np.degrees(found.angle_rad)
        return
    true_axis = Renderer(task, scene).lamp_axis(first.lamp_pose[1])
    assert np.degrees(np.arccos(np.clip(found.axis @ true_axis, -1.0, 1.0))) <= 0.5
    assert found.angle_rad > tolerance
    located = localization.localize(task, scene, [found.applied(v) for v in views])
    assert located.part_offset_m == pytest.approx(truth["part_offset_m"], abs=1e-3)
