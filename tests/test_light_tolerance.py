"""The other lights' pose error in the lamp tolerance (requirements.light_tolerance_deg): each
light's gray with its aim turned by the tolerance, held to the same light turned here by
scipy's rotation and evaluated by the lights' own kernel call, and the moved grays the
requirement judges, recomputed from the shares."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cell.devices import rig
from cell.planning import evaluate, requirements
from cell.planning.lights import contributions
from cell.planning.scene import build_scene
from cell.task import loader

TASK = Path(__file__).parent / "tasks" / "features" / "plate_bar.yaml"
TOLERANCE = np.radians(2.0)


def problem_of(tolerance):
    task = loader.load_task(TASK).with_feature(0)
    feature = task.feature
    feature = replace(feature, requirements=replace(feature.requirements, light_tolerance_rad=tolerance))
    task = replace(task, features=(feature,))
    scene = build_scene(task, 32)
    return task, scene, evaluate.build_problem(task, scene, None)


def test_each_lights_turned_gray_is_that_light_turned_by_a_rotation():
    task, scene, problem = problem_of(TOLERANCE)
    lights = problem.lights
    assert lights.turned.shape == (2, evaluate.TOLERANCE_RING, len(scene.points))
    for k, light in enumerate(task.lights):
        across = np.cross(light.axis, light.along)
        # direction 0 turns the aim toward `along`: a rotation about axis x along by the tolerance
        rot = Rotation.from_rotvec(TOLERANCE * across)
        moved = replace(light, axis=rot.apply(light.axis), along=rot.apply(light.along))
        expected = contributions(scene.warp_mesh, scene.points, scene.normals, scene.T_cell_cam, [moved],
                                 problem.material, task.camera.sensor, problem.band[1], count=lights.points[k])[0]
        assert np.allclose(lights.turned[k, 0], expected.unit_gray, rtol=1e-9, atol=0)
        # a 2 deg turn of a bar 60 mm from the patch changes its light there, by a few percent at most
        change = np.abs(lights.turned[k] - lights.unit_gray[k]).max() / lights.unit_gray[k].max()
        assert 0 < change < 0.2


def test_the_lamp_tolerance_judges_every_light_turned_at_its_drive():
    task, scene, problem = problem_of(TOLERANCE)
    _, _, without = problem_of(0.0)
    drive = np.array([0.2, 0.5, 1.0])
    joints = (0.0, np.radians(50.0), 0.2)
    pos = rig.lamp_position(task.lamp.rig.pivot_m, *joints)
    c = evaluate.at_exposure(problem, pos, 4e-3, 2.8, joints=joints, drive=drive)
    c0 = evaluate.at_exposure(without, pos, 4e-3, 2.8, joints=joints, drive=drive)
    extra = c.moved_gray[len(c0.moved_gray):]
    assert len(extra) == 2 * evaluate.TOLERANCE_RING
    lights, gain, b = problem.lights, 4e-3 / 2.8**2, problem.black_level
    u = (c.gray[0] - b) / gain
    for k in range(2):
        for m in range(evaluate.TOLERANCE_RING):
            expected = b + gain * (u + drive[1 + k] * (lights.turned[k, m] - lights.unit_gray[k]))
            assert np.allclose(extra[k * evaluate.TOLERANCE_RING + m, 0], expected, rtol=1e-9)
    assert np.array_equal(c.moved_gray[:len(c0.moved_gray)], c0.moved_gray)
    value = requirements.lamp_tolerance(problem, c)[0]
    assert value >= requirements.lamp_tolerance(without, c0)[0]
    assert "other lights' aims" in requirements.explain_lamp_tolerance(problem, c, value <= 0)
