"""Plans against the dense check (tests/dense.py): the feature patch's true surface at 6000 points,
shaded with cell.physics's NumPy equations and brute-force shadow rays, not with the planner's
samples. The examples and the curved parts' tasks (tests/tasks/: a dome, a shaft and a fillet;
matte paint, gray cast iron and milled aluminium; bands 60-250 and 100-125)."""
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from cell.planning import one_shot
from cell.cli import main
from cell.task.loader import load_task
from dense import (CURVED_TASKS, EXAMPLES, acceptance_failures, dense_check, patch_surface,
                   shade)

TASKS = {**EXAMPLES, **CURVED_TASKS}


@cache
def planned(name):
    """(task, plan, dense check) of a task, planned once per session."""
    task = load_task(TASKS[name])
    plan = one_shot.plan(task)
    return task, plan, dense_check(task, plan.shot)


def test_the_curved_tasks_cover_parts_materials_and_bands():
    tasks = [load_task(p) for p in CURVED_TASKS.values()]
    assert {t.part.mesh_path.name for t in tasks} == {"sphere_cap.stl", "lying_cylinder.stl", "filleted_block.stl"}
    assert {t.part.material.name for t in tasks} >= {"matte gray paint", "milled aluminium"}
    assert {t.requirements.gray_band for t in tasks} == {(60, 250), (100, 125)}


@pytest.mark.parametrize("name", sorted(CURVED_TASKS))
def test_cell_check_loads_the_curved_task(name, capsys):
    assert main(["check", str(CURVED_TASKS[name])]) == 0
    assert "feature" in capsys.readouterr().out


def test_the_patch_is_the_surface_within_the_radius_sampled_by_area():
    """Dome (r 30 mm about (0, 0, -5) mm): every point on the sphere within 6 mm of the centre,
    spread evenly by area (mean squared distance r^2 / 2 on a near-flat disk). Hinge: the leaf's
    underside is within 6 mm of the centre too (the leaf is 4 mm thick), but not the patch."""
    task = load_task(CURVED_TASKS["sphere_paint_wide"])
    points, normals = patch_surface(task, 4000)
    center = task.feature.center_m
    r = np.linalg.norm(points - center, axis=1)
    assert r.max() <= 0.006 and r.max() > 0.0059
    np.testing.assert_allclose(np.linalg.norm(points - [0, 0, -0.005], axis=1), 0.030, atol=5e-6)
    assert abs(np.mean(r**2) / 0.006**2 - 0.5) < 0.03
    assert np.all(normals @ task.feature.normal > np.cos(np.radians(15.0)))
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


@pytest.mark.parametrize("name", sorted(CURVED_TASKS))
def test_a_curved_plans_verdict_is_its_requirements(name):
    """Plan-level consistency: feasible exactly when every requirement value is <= 1; a feasible
    plan predicts every sample in band, lit and seen; an infeasible one names what binds."""
    task, plan, _ = planned(name)
    assert plan.feasible == all(r.value <= 1.0 for r in plan.requirements)
    low, high = task.requirements.gray_band
    if plan.feasible:
        assert low <= plan.shot.gray.min() and plan.shot.gray.max() <= high
    else:
        assert plan.binding in {r.name for r in plan.requirements} and plan.hint


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_the_examples_plans_hold_on_the_dense_surface(name):
    """Hinge and connecting rod: every one of 6000 points lit, seen, in focus and in band, within
    0.5 gray of the predicted extremes (flat patches: the samples' rim finds them)."""
    task, plan, check = planned(name)
    assert plan.feasible and acceptance_failures(plan, check) == []
    assert check.gray.min() >= plan.shot.gray.min() - 0.5 and check.gray.max() <= plan.shot.gray.max() + 0.5


@pytest.mark.parametrize("name", sorted(CURVED_TASKS))
def test_a_feasible_curved_plan_stays_in_band_and_in_focus_on_the_dense_surface(name):
    """The issue's acceptance: a plan called feasible keeps every point of the true surface in band,
    lit, seen and in focus (an independent dense check); an infeasible one promises nothing."""
    _, plan, check = planned(name)
    assert acceptance_failures(plan, check) == []


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
