"""Plans against the dense check (tests/dense.py): the feature patch's true surface at 6000 points,
shaded with cell.physics's NumPy equations and brute-force shadow rays, not with the planner's
samples."""
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from cell import planner
from cell.loader import load_task
from dense import EXAMPLES, acceptance_failures, dense_check, patch_surface, shade

TASKS = EXAMPLES


@cache
def planned(name):
    """(task, plan, dense check) of a task, planned once per session."""
    task = load_task(TASKS[name])
    plan = planner.plan(task)
    return task, plan, dense_check(task, plan.shot)


def test_the_patch_is_the_surface_within_the_radius_sampled_by_area():
    """Hinge: every point within 6 mm of the centre, spread evenly by area (mean squared distance
    r^2 / 2 on a disk); the leaf's underside is within 6 mm too (the leaf is 4 mm thick), but not
    the patch."""
    hinge = load_task(EXAMPLES["hinge"])
    points, normals = patch_surface(hinge, 2000)
    r = np.linalg.norm(points - hinge.feature.center_m, axis=1)
    assert 0.0059 < r.max() <= 0.006 and abs(np.mean(r**2) / 0.006**2 - 0.5) < 0.03
    np.testing.assert_allclose(points[:, 2], 0.004)
    np.testing.assert_allclose(normals, np.broadcast_to([0.0, 0.0, 1.0], normals.shape), atol=1e-12)


@pytest.mark.parametrize("name", sorted(TASKS))
def test_the_dense_physics_is_the_planners_at_its_own_samples(name):
    """The NumPy shading reproduces the Warp prediction at the plan's 64 samples (gray, shadows),
    so any difference on the dense set is where the points are, not the model."""
    task, plan, _ = planned(name)
    at_samples = shade(task, plan.shot, plan.scene.points, plan.scene.normals)
    top = 2.0**task.camera.sensor.bit_depth - 1
    np.testing.assert_allclose(at_samples.gray, np.minimum(plan.shot.gray, top), rtol=1e-4, atol=1e-3)
    assert not at_samples.shadowed.any() and not at_samples.unseen.any()


@pytest.mark.parametrize("name", sorted(TASKS))
def test_the_dense_set_spans_at_least_the_predicted_gray(name):
    """The patch holds every sample, so its gray range holds theirs (to its sampling's spacing)."""
    task, plan, check = planned(name)
    g = np.minimum(plan.shot.gray, 2.0**task.camera.sensor.bit_depth - 1)
    assert check.gray.min() <= g.min() + 0.5 and check.gray.max() >= g.max() - 0.5


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_the_examples_plans_hold_on_the_dense_surface(name):
    """Hinge and connecting rod: every one of 6000 points lit, seen, in focus and in band, within
    0.5 gray of the predicted extremes (flat patches: the samples' rim finds them)."""
    task, plan, check = planned(name)
    assert plan.feasible and acceptance_failures(plan, check) == []
    assert check.gray.min() >= plan.shot.gray.min() - 0.5 and check.gray.max() <= plan.shot.gray.max() + 0.5


def test_the_dense_check_sees_overexposure_defocus_and_shadow():
    """The hinge's plan made wrong three ways, each caught: shutter x 1.5 (out of the narrow band),
    focus 30 mm short (every point beyond the far limit), lamp under the leaf (all shadowed)."""
    task, plan, check = planned("hinge")
    shot, e = plan.shot, plan.shot.exposure
    bright = dense_check(task, replace(shot, exposure=replace(e, shutter_s=1.5 * e.shutter_s)), 500)
    assert bright.in_band.mean() < 0.5 and acceptance_failures(plan, bright)
    blurred = dense_check(task, replace(shot, exposure=replace(e, focus_m=e.focus_m - 0.03)), 500)
    assert not blurred.in_focus.any() and blurred.depth_m.min() > blurred.far_m
    below = replace(shot, lamp_position=shot.lamp_position * [1.0, 1.0, -1.0])
    assert dense_check(task, below, 500).shadowed.all()
