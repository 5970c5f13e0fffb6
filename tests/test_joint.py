"""Drive levels re-solved over every feature a shot may cover (cell.planning.joint), held to an
independent expectation: on tests/tasks/features/plate_bar.yaml (two patches asking different
bands, a bar light over each) each patch's own shot leaves the other out of its band, a brute
force over a grid of drive levels and exposures finds drives putting both in band from one shot,
and the plan takes that one shot, its predicted gray the sum of each light's share recomputed here."""
import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from cell.core.progress import Progress
from cell.devices import rig
from cell.planning import evaluate
from cell.planning.plan import PlannerSettings
from cell.planning.whole_part import candidate_plans, plan_features
from cell.task import loader

TASK = Path(__file__).parent / "tasks" / "features" / "plate_bar.yaml"


@pytest.fixture(scope="module")
def planned():
    task = loader.load_task(TASK)
    tasks = [task.with_feature(i) for i in range(len(task.features))]
    cands, _, lend, columns = candidate_plans(tasks, PlannerSettings(), Progress.silent())
    return task, tasks, cands, lend, columns


def shares(task, lent_plan, shot):
    """(1 + K, P) each light's gray per exposure at full drive on a feature's samples at the shot
    (the spot at the shot's pose first), and the feature's band: straight from the kernels."""
    from dataclasses import replace
    scene = replace(lent_plan.planned_scene, T_cell_cam=shot.T_cell_cam)
    problem = evaluate.build_problem(task, scene, None, focus_m=shot.exposure.focus_m)
    pos = shot.lamp_position.reshape(1, 3)
    spot = evaluate.unit_gray(problem, pos, rig.lamp_aim(task.lamp.rig.pivot_m, pos))[0]
    return np.vstack([spot, problem.lights.unit_gray]), problem.band, problem.black_level, problem.kappa_open


def margin(v, band, black, drive, gain, delta):
    """The worst sample's distance inside its band [gray], every drive off by +-delta."""
    signal = gain * (np.asarray(drive) @ v)
    return min(float(np.min(black + (1 - delta) * signal - band[0])), float(np.min(band[1] - black - (1 + delta) * signal)))


def test_each_patchs_own_drives_leave_the_other_out_of_band_and_joint_drives_cover_both(planned):
    task, tasks, cands, lend, columns = planned
    delta = tasks[0].requirements.drive_tolerance
    camera = task.camera
    for s, ((f, p), (column, _, joint)) in enumerate(zip(cands, columns)):
        g = 1 - f
        shot = p.shot
        # at its own drives the shot leaves the other patch out of band: the judge and a recount agree
        assert not column[g].covered
        v, band, black, _ = shares(tasks[g], lend[g], shot)
        gain = shot.exposure.shutter_s / shot.exposure.f_number**2
        assert margin(v, band, black, shot.drive, gain, 0.0) < 0
        # a brute force over drives (every 0.1) x exposures (500, log-spaced) on both patches' samples
        own_v, own_band, _, kappa_f = shares(tasks[f], lend[f], shot)
        kappa = max(kappa_f, shares(tasks[g], lend[g], shot)[3])
        gains = np.geomspace(camera.shutter_range_s[0] / camera.lens.f_number_range[1] ** 2,
                             camera.shutter_range_s[1] / kappa**2, 500)
        levels = np.linspace(0.0, 1.0, 11)
        both = np.hstack([own_v, v])
        low = np.r_[np.full(own_v.shape[1], own_band[0]), np.full(v.shape[1], band[0])]
        high = np.r_[np.full(own_v.shape[1], own_band[1]), np.full(v.shape[1], band[1])]
        best = -np.inf
        for drive in itertools.product(levels, repeat=len(both)):
            signal = np.asarray(drive) @ both
            x = gains[:, None] * signal[None]
            best = max(best, float(np.max(np.minimum(black + (1 - delta) * x - low, high - black - (1 + delta) * x)
                                          .min(axis=1))))
        if best > 0:
            # some drives cover both: the joint program finds them, at least as good as the grid
            assert joint is not None and joint.column[g].covered and joint.own.covered
            j = joint.shot
            gain = j.exposure.shutter_s / j.exposure.f_number**2
            found = min(margin(own_v, own_band, black, j.drive, gain, delta), margin(v, band, black, j.drive, gain, delta))
            assert found == pytest.approx(joint.margin_gray, abs=1e-6)
            assert joint.margin_gray >= best - 1e-6
            # the predicted gray of each patch is the sum of each light's share at the joint drives
            assert np.allclose(joint.own.gray, black + gain * (j.drive @ own_v), rtol=1e-6)
            assert np.allclose(joint.column[g].gray, black + gain * (j.drive @ v), rtol=1e-6)
        else:
            assert joint is None
    assert any(joint is not None for _, _, joint in columns), "no shot covers both patches jointly"


@pytest.fixture(scope="module")
def plan(planned):
    return plan_features(planned[0])


def test_the_plan_takes_one_shot_for_both_patches_at_the_joint_drives(planned, plan):
    task = planned[0]
    assert plan.feasible and len(plan.shots) == 1
    shot = plan.shots[0]
    assert {c.feature for c in shot.covers} == {"left", "right"}
    k = plan.cover["chosen"][0]
    own = plan.plans[k]
    # the chosen candidate's own plan reads the joint drives (a run of it drives those)
    assert np.array_equal(own.shot.drive, shot.drive) and own.shot.exposure == shot.exposure
    assert any("solved over the features left, right together" in n for n in own.notes)
    for c in shot.covers:
        low, high = next(t for t in task.features if t.name == c.feature).requirements.gray_band
        assert low <= c.gray.min() and c.gray.max() <= high


def test_cell_png_draws_the_fixed_lights(planned, plan, tmp_path):
    """The bars' emitter points in their colour on cell.png's view of the cell (its left half,
    above the legend), and none of it without the lights."""
    from dataclasses import replace

    from matplotlib.colors import to_rgb

    from cell.report.pictures import FIXED_LIGHT_COLOR, write_cell
    task = planned[0]
    gold = np.round(255 * np.array(to_rgb(FIXED_LIGHT_COLOR)))

    def gold_pixels(path):
        image = cv2.imread(str(path))[..., ::-1].astype(float)
        cell = image[:int(0.8 * image.shape[0]), :image.shape[1] // 2]
        return int(np.sum(np.all(np.abs(cell - gold) < 30, axis=-1)))

    write_cell(tmp_path / "with.png", plan, task)
    write_cell(tmp_path / "without.png", plan, replace(task, lights=()))
    assert gold_pixels(tmp_path / "without.png") == 0
    assert gold_pixels(tmp_path / "with.png") > 20


def test_a_shot_with_lights_is_judged_at_its_own_shutter_on_every_feature(planned):
    """coverage.judge with lights: the shutter the band needs is the shot's (the drive program's,
    at the feature's widest f-number), f = exp(t_need / t_max - 1), not the one centring the judged
    feature alone."""
    from dataclasses import replace

    from cell.planning import coverage
    task, tasks, cands, lend, columns = planned
    t_max = task.camera.shutter_range_s[1]
    for (f, p), (_, _, joint) in zip(cands, columns):
        if joint is None:
            continue
        shot, e = joint.shot, joint.shot.exposure
        for g, c in enumerate(joint.column):
            if c is None:
                c = joint.own
            scene = replace(lend[g].planned_scene, T_cell_cam=shot.T_cell_cam)
            kappa_open = evaluate.build_problem(tasks[g], scene, None, focus_m=e.focus_m).kappa_open
            need = e.shutter_s * (kappa_open / e.f_number) ** 2
            value = next(r.value for r in c.requirements if r.name == "shutter_max")
            assert value == pytest.approx(np.exp(need / t_max - 1.0), rel=1e-9)
            assert coverage.judge(tasks[g], coverage.Lent.of(lend[g]), shot).covered == c.covered
