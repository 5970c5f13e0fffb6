"""Fixed lights as obstacles for the collision check (cell.collision.scene.light_bodies): each
fixed light's housing is a box whose front face holds its emitter points (cell.planning.lights,
an independent construction of the same light), and a camera put into a bar's housing is
refused naming the bar."""
from pathlib import Path

import numpy as np

from cell.collision.scene import CollisionScene, light_bodies
from cell.core import geometry
from cell.planning.lights import emitters
from cell.task import loader
from cell.task.types import HOUSING_DEPTH_M

TASKS = Path(__file__).parent / "tasks" / "features"
RING = Path(__file__).parent.parent / "tasks" / "ring.yaml"


def test_each_fixed_lights_housing_holds_its_emitter_points_on_its_front_face():
    task = loader.load_task(TASKS / "plate_bar.yaml")
    boxes = light_bodies(task)
    assert [b.name for b in boxes] == ["bar_left", "bar_right"]
    for light, box in zip(task.lights, boxes):
        points = emitters(light, np.eye(4), 64).position
        assert np.allclose(box.sdf(points), 0.0, atol=1e-9)           # on the surface
        assert np.all(box.sdf(points - 1e-3 * light.axis) < 0)          # just behind: inside the housing
        assert np.all(box.sdf(points + 1e-3 * light.axis) > 0)          # just in front: outside
        assert np.isclose(box.sdf(light.position_m - HOUSING_DEPTH_M * light.axis - 1e-3 * light.axis), 1e-3)
    scene = CollisionScene.of(task)
    assert [b.name for b in scene.fixed] == ["part", "bar_left", "bar_right"]


def test_a_ring_on_the_flange_is_no_fixed_body_and_a_fixed_ring_is():
    task = loader.load_task(RING)
    assert [b.name for b in light_bodies(task)] == ["dark_field_ring"]


def test_a_camera_inside_a_bars_housing_is_refused_naming_the_bar():
    task = loader.load_task(TASKS / "plate_bar.yaml")
    scene = CollisionScene.of(task)
    bar = task.lights[0]
    # the camera's optical centre 5 mm behind the bar's emitting centre, looking along the bar's axis
    T = np.eye(4)
    T[:3, :3] = geometry.frame_from_normal(-np.asarray(bar.axis))
    T[:3, 3] = np.asarray(bar.position_m) - 0.005 * np.asarray(bar.axis)
    c = scene.clearance(T)
    assert not c.ok and "bar_left" in c.bodies
    far = np.eye(4)
    far[:3, 3] = (0.0, 0.0, 0.4)
    assert scene.clearance(far).ok
