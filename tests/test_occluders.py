"""Fixed lights block the camera's view and the spot's beam (cell.planning.occluders): a ring's
housing is an annulus the camera looks through, a bar's a box, a dome's a shell with its camera
hole. Each checked against the shape's own solid in NumPy (points along each segment, the solid
grown and shrunk by a margin: a segment through the shrunk solid must be blocked, one missing
the grown solid must be free), through the planner's kernel, the planner's verdict (the light
named) and the simulated camera's image."""
from dataclasses import astuple, replace
from pathlib import Path

import numpy as np
import pytest

from cell.core import geometry
from cell.physics.projection import project
from cell.planning import evaluate, occluders
from cell.planning.one_shot import plan
from cell.planning.scene import build_scene
from cell.task.loader import load_task
from cell.task.types import Channel, Light, SimConfig, Truth
from kernels.gray import gray_per_exposure
from kernels.mesh import WarpMesh
from sim.world import Renderer

ROOT = Path(__file__).resolve().parent.parent
RING = ROOT / "tasks" / "ring.yaml"
PLATE_BAR = ROOT / "tests" / "tasks" / "features" / "plate_bar.yaml"
PROUD, DEPTH, RIM = 5e-4, 0.020, 0.005      # the housings' setback, default depth and rim, as docs/formats.md gives them
MARGIN = 5e-4                # grown / shrunk by this: beyond the polygons' 0.1 mm and float32
STEP = 5e-5                  # points along a segment this far apart (< 2 MARGIN: none slips through)
DOWN = np.array([0.0, 0.0, -1.0])


def fixed(name, kind, position, axis=DOWN, along=(1.0, 0.0, 0.0), channel=7, **keys):
    axis = geometry.unit(np.asarray(axis, float))
    along = np.asarray(along, float) - (np.asarray(along, float) @ axis) * axis
    return Light(name, kind, "fixed", 0.5, Channel(channel), np.asarray(position, float), axis,
                 geometry.unit(along), **keys)


def local(light, points):
    """Points in the light's frame (along, across, axis), its emitting centre at 0."""
    R = np.column_stack([light.along, np.cross(light.axis, light.along), light.axis])
    return (np.asarray(points) - light.position_m) @ R


def inside_ring(light, points, grow):
    x, y, z = local(light, points).T
    r = np.hypot(x, y)
    h = light.housing()
    return ((r >= h.aperture_radius_m - grow) & (r <= h.outer_radius_m + grow)
            & (z <= -PROUD + grow) & (z >= -h.depth_m - grow))


def inside_bar(light, points, grow):
    x, y, z = local(light, points).T
    return ((np.abs(x) <= 0.5 * light.length_m + RIM + grow) & (np.abs(y) <= RIM + grow)
            & (z <= -PROUD + grow) & (z >= -light.housing().depth_m - grow))


def inside_dome(light, points, grow):
    x, y, z = local(light, points).T
    R, depth = light.radius_m, light.housing().depth_m
    rho = np.sqrt(x**2 + y**2 + (z - R) ** 2)          # from the sphere's centre, R along the axis
    return ((rho >= R + PROUD - grow) & (rho <= R + depth + grow) & (z <= R + grow)
            & (np.hypot(x, y) >= light.hole_radius_m - grow))


def reference(inside, light, origins, targets):
    """(C, P) +1 where the segment origin p -> target c must be blocked, 0 where it must be free,
    -1 where the margin leaves it open."""
    out = np.full((len(targets), len(origins)), -1)
    for c, target in enumerate(targets):
        for p, origin in enumerate(origins):
            n = int(np.ceil(np.linalg.norm(target - origin) / STEP)) + 1
            points = origin + np.linspace(0.0, 1.0, n)[:, None] * (target - origin)
            if inside(light, points, -MARGIN).any():
                out[c, p] = 1
            elif not inside(light, points, MARGIN).any():
                out[c, p] = 0
    return out


def kernel_blocked(light, origins, targets):
    """(C, P) the planner's gray kernel's shadow flag for lamps at the targets and samples at the
    origins facing up (every target above them), cast against the light's housing alone."""
    h = occluders.housing(light)
    out = gray_per_exposure(WarpMesh(h.vertices, h.faces), origins, np.tile([0.0, 0.0, 1.0], (len(origins), 1)),
                            np.array([0.0, 0.0, 1.0]), targets, np.tile(DOWN, (len(targets), 1)), 1.0, np.pi,
                            np.array([[0.0, 0.5, 0.0, 1.0, 0.0, 1.0]]), 1.0, 1.0)
    return out.shadowed


def check(inside, light, origins, targets):
    expected = reference(inside, light, origins, targets)
    blocked = kernel_blocked(light, origins, targets)
    sure = expected >= 0
    assert sure.mean() > 0.9 and 0.1 < expected[sure].mean() < 0.9      # both kinds, few left open
    assert np.array_equal(blocked[sure], expected[sure] == 1)
    named = occluders.blockers((occluders.housing(light),), np.repeat(origins[None], len(targets), 0).reshape(-1, 3),
                               np.repeat(targets, len(origins), 0))[0].reshape(len(targets), -1)
    assert np.array_equal(named[sure], expected[sure] == 1)             # the NumPy namer agrees


def below_and_above(rng, n, reach, low, high):
    """n points in a disk of radius 0.02 m 5-25 mm below the light, n in a disk of `reach` from
    `low` to `high` above it."""
    def disk(k, r, z0, z1):
        a, rr = rng.uniform(0, 2 * np.pi, k), r * np.sqrt(rng.uniform(0, 1, k))
        return np.column_stack([rr * np.cos(a), rr * np.sin(a), rng.uniform(z0, z1, k)])
    return disk(n, 0.02, -0.025, -0.005), disk(n, reach, low, high)


def test_a_rings_housing_blocks_its_annulus_and_not_its_aperture():
    ring = fixed("ring", "ring", (0.0, 0.0, 0.0), radius_m=0.05, tilt_rad=np.radians(60.0))
    origins, targets = below_and_above(np.random.default_rng(1), 24, 0.15, 0.03, 0.25)
    check(inside_ring, ring, origins, targets)
    straight_up = kernel_blocked(ring, origins, origins * [1, 1, 0] + [0, 0, 0.3])
    assert not np.diag(straight_up).any()            # every view up through the 45 mm hole is free


def test_a_bars_housing_is_its_box():
    bar = fixed("bar", "bar", (0.0, 0.0, 0.0), along=(0.3, 1.0, 0.0), length_m=0.06)
    origins, targets = below_and_above(np.random.default_rng(2), 24, 0.06, 0.03, 0.2)
    check(inside_bar, bar, origins, targets)


def test_a_domes_shell_blocks_all_but_its_camera_hole():
    dome = fixed("dome", "dome", (0.0, 0.0, 0.1), radius_m=0.1, hole_radius_m=0.015, housing_depth_m=0.01)
    rng = np.random.default_rng(3)
    origins = np.column_stack([rng.uniform(-0.02, 0.02, (24, 2)), rng.uniform(0.001, 0.01, 24)])
    a, r = rng.uniform(0, 2 * np.pi, 24), 0.06 * np.sqrt(rng.uniform(0, 1, 24))
    targets = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.12, 0.4, 24)])
    check(inside_dome, dome, origins, targets)
    assert not kernel_blocked(dome, np.array([[0.0, 0.0, 0.005]]), np.array([[0.0, 0.0, 0.5]])).any()


def test_no_light_shadows_its_own_emitter_points():
    """A ray from a sample in front of a light to each of its emitter points meets no housing."""
    from cell.planning.lights import emitters
    lights = (fixed("ring", "ring", (0.0, 0.0, 0.05), radius_m=0.04, tilt_rad=np.radians(75.0)),
              fixed("bar", "bar", (0.0, 0.0, 0.05), length_m=0.1),
              fixed("area", "area", (0.0, 0.0, 0.05), size_m=(0.05, 0.03)),
              fixed("dome", "dome", (0.0, 0.0, 0.15), radius_m=0.1, hole_radius_m=0.01))   # the samples inside its sphere
    samples = np.array([[0.0, 0.0, 0.0], [0.01, -0.005, 0.001], [-0.008, 0.01, 0.0]])
    for light in lights:
        e = emitters(light, np.eye(4), 64)
        h = occluders.housing(light)
        out = gray_per_exposure(WarpMesh(h.vertices, h.faces), samples, np.tile([0.0, 0.0, 1.0], (3, 1)),
                                np.array([0.0, 0.0, 1.0]), e.position, e.axis, 1.0, np.pi,
                                np.array([[0.0, 0.5, 0.0, 1.0, 0.0, 1.0]]), 1.0, 1.0)
        assert not out.shadowed.any(), light.type


def over_the_plate(*lights, effects=()):
    """tasks/ring.yaml (the plate, the camera 0.3 m above the feature) with these fixed lights."""
    task = load_task(RING)
    return replace(task, lights=lights, sim=SimConfig(1, tuple(effects), Truth()))


BAR_OVER = fixed("bar_over", "bar", (0.0, 0.0, 0.15), length_m=0.1, along=(0.0, 1.0, 0.0), channel=2)


def test_a_bar_across_the_cameras_view_is_named_when_the_plan_is_refused():
    task = over_the_plate(BAR_OVER)
    scene = build_scene(task)
    through = reference(inside_bar, BAR_OVER, scene.points, scene.camera_position[None])[0]
    assert np.all(through == 1)                       # the box hides every sample from the camera
    p = plan(task)
    assert not p.feasible and p.binding == "camera_view"
    assert f"cannot see {len(scene.points)} of {len(scene.points)}" in p.hint and "bar_over" in p.hint
    aside = replace(BAR_OVER, position_m=np.array([0.06, 0.0, 0.15]))      # 6 cm aside: out of the view
    task = over_the_plate(aside)
    assert evaluate.build_problem(task, build_scene(task), None).camera_unseen == 0


def test_the_camera_looks_through_a_rings_aperture_and_a_smaller_hole_hides_the_outer_samples():
    task = load_task(RING)
    ring = next(light for light in task.lights if light.mount == "fixed")
    scene = build_scene(task)
    assert evaluate.build_problem(task, scene, None).camera_unseen == 0
    narrow = replace(ring, aperture_radius_m=0.005)
    task = replace(task, lights=(narrow,))
    scene = build_scene(task)
    # closed form: the line sample -> camera (on the axis above) shrinks toward the axis as it
    # rises; it meets the annulus iff at the housing's front face it is still beyond the hole
    rise = scene.camera_position[2] - scene.points[:, 2]
    front = narrow.position_m[2] + PROUD
    radius_at_front = np.hypot(*scene.points[:, :2].T) * (1.0 - (front - scene.points[:, 2]) / rise)
    hidden = radius_at_front > narrow.aperture_radius_m
    sure = np.abs(radius_at_front - narrow.aperture_radius_m) > 0.15e-3     # the polygon's 0.1 mm aside
    assert sure.mean() > 0.9 and 0 < hidden[sure].sum() < sure.sum()
    problem = evaluate.build_problem(task, scene, None)
    unseen = problem.gray_inputs(scene.camera_position[None], -scene.normal[None]).shadowed[0]   # the kernel's flag
    assert np.array_equal(unseen[sure], hidden[sure]) and problem.camera_unseen == unseen.sum()
    from cell.planning.requirements import explain_camera_view
    assert f"dark_field_ring ({unseen.sum()} samples)" in explain_camera_view(problem, None, False)


def spot_behind(light, centre, distance):
    """A spot on the line from the feature centre through the light's housing, `distance` away."""
    behind = light.position_m - 0.5 * light.housing().depth_m * light.axis
    return centre + distance * geometry.unit(behind - centre)


@pytest.fixture(scope="module")
def left_patch():
    """plate_bar's left patch with its bars; a spot 0.3 m away behind bar_left's housing."""
    task = load_task(PLATE_BAR).with_feature(0)
    scene = build_scene(task)
    bar = task.lights[0]
    return task, scene, bar, spot_behind(bar, scene.center, 0.3)


def test_a_bar_between_the_spot_and_the_feature_shadows_it_in_the_planner(left_patch):
    task, scene, bar, lamp = left_patch
    assert np.all(reference(inside_bar, bar, scene.points, lamp[None])[0] == 1)
    problem = evaluate.build_problem(task, scene, None)
    aim = geometry.unit(scene.center - lamp)
    spot = evaluate.unit_gray(problem, lamp[None], aim[None])
    assert spot[1].all() and not spot[0].any()          # shadowed, no gray
    # the gray with every light on is the other lights' alone: the ambient
    gray = evaluate.lit_by_all(problem, spot, np.array([[1.0, 1.0, 1.0]]))[0]
    assert np.allclose(gray[0], problem.lights.unit_gray.sum(axis=0))
    # 3 cm higher the beam passes over the housing and the spot adds to every sample
    free = lamp + [0.0, 0.0, 0.05]
    assert np.all(reference(inside_bar, bar, scene.points, free[None])[0] == 0)
    u_free, shadowed_free, _, _ = evaluate.unit_gray(problem, free[None], geometry.unit(scene.center - free)[None])
    assert not shadowed_free.any() and np.all(u_free > 0)
    from cell.planning.one_shot import build_maps
    from cell.planning.plan import PlannerSettings
    from cell.planning.requirements import explain_no_shadow
    problem = replace(problem, maps=build_maps(task, scene, PlannerSettings()))
    spot_alone = evaluate.at_exposure(problem, lamp, 5e-3, 4.0, drive=[1.0, 0.0, 0.0])
    assert f"bar_left ({len(scene.points)} samples)" in explain_no_shadow(problem, spot_alone, False)


def feature_pixels(renderer, T_cell_cam, points):
    uv, _ = project(renderer.K, T_cell_cam, points)
    return np.rint(uv).astype(int)


@pytest.mark.parametrize("effects", [("shadows",), ()])
def test_a_bar_between_the_spot_and_the_feature_shadows_it_in_the_simulators_image(left_patch, effects):
    """With `shadows` the spot adds nothing where bar_left's housing stands in its beam (the image
    with the spot on is the one with only the other lights: the ambient); without it, the spot lights."""
    task, scene, bar, lamp = left_patch
    task = replace(task, sim=SimConfig(1, effects, Truth()))
    renderer = Renderer(task, scene, scale=0.25)
    aim = scene.center - lamp
    exposure = (5e-3, 4.0)
    with_spot = renderer(scene.T_cell_cam, lamp, aim, *exposure, drives={1: 0.0, 2: 1.0, 3: 1.0})
    ambient = renderer(scene.T_cell_cam, lamp, aim, *exposure, drives={1: 0.0, 2: 1.0, 3: 0.0})
    u, v = feature_pixels(renderer, scene.T_cell_cam, scene.points).T
    assert np.all(ambient[v, u] > 0)
    if effects:
        assert np.allclose(with_spot[v, u], ambient[v, u], rtol=1e-12)
    else:
        assert np.all(with_spot[v, u] > ambient[v, u])


def test_the_simulated_camera_sees_a_bar_across_its_view_dark():
    """Without any effect the housing hides the plate: the feature's pixels read 0 (the housing
    is dark), where the same bar 6 cm aside leaves them lit."""
    scenes = {}
    for name, bar in (("across", BAR_OVER), ("aside", replace(BAR_OVER, position_m=np.array([0.06, 0.0, 0.15])))):
        task = over_the_plate(bar)
        scene = build_scene(task)
        renderer = Renderer(task, scene, scale=0.25)
        lamp = scene.center + np.array([0.0, 0.15, 0.1])
        image = renderer(scene.T_cell_cam, lamp, scene.center - lamp, 5e-3, 4.0, drives={2: 0.0, 3: 1.0})
        u, v = feature_pixels(renderer, scene.T_cell_cam, scene.points).T
        scenes[name] = image[v, u]
    assert np.all(scenes["across"] == 0.0) and np.all(scenes["aside"] > 0.0)


FIXED_RING = {"name": "ring", "type": "ring", "mount": "fixed", "power_w": 0.5, "channel": 1,
              "position_m": [0.0, 0.0, 0.1], "aim_m": [0.0, 0.0, 0.0], "radius_mm": 30}
BAR = {"name": "bar", "type": "bar", "mount": "fixed", "power_w": 0.8, "channel": 2, "position_m": [0.1, 0.0, 0.1],
       "aim_m": [0.006, 0.0, 0.004], "length_mm": 100, "along": [0, 1, 0]}


def with_lights(tmp_path, *entries):
    from test_loader import write_task

    def edit(task, folder):
        task["lights"] = [dict(e) for e in entries]
    return load_task(write_task(tmp_path, edit))


def test_a_rings_housing_keys_load_in_si_and_default_to_a_rim_either_side(tmp_path):
    ring, bar = with_lights(tmp_path, FIXED_RING | {"aperture_radius_mm": 20, "outer_radius_mm": 40,
                                                    "housing_depth_mm": 10}, BAR).lights
    assert astuple(ring.housing()) == pytest.approx((0.010, 0.020, 0.040))
    assert bar.housing().depth_m == pytest.approx(DEPTH)
    (tmp_path / "defaults").mkdir()
    ring = with_lights(tmp_path / "defaults", FIXED_RING).lights[0]
    assert astuple(ring.housing()) == pytest.approx((DEPTH, 0.030 - RIM, 0.030 + RIM))


@pytest.mark.parametrize("entry, key, words", [
    (FIXED_RING | {"aperture_radius_mm": 30}, "lights[0].aperture_radius_m", "less than the ring's radius_m"),
    (FIXED_RING | {"outer_radius_mm": 25}, "lights[0].outer_radius_m", "more than the ring's radius_m"),
    (FIXED_RING | {"housing_depth_mm": -5}, "lights[0].housing_depth_mm", "positive"),
    (BAR | {"aperture_radius_mm": 5}, "lights[0].aperture_radius_m", "a key of ring lights"),
    (FIXED_RING | {"mount": "flange", "position_m": None, "aim_m": None, "offset_mm": 20, "housing_depth_mm": 10},
     "lights[0].housing_depth_m", "a key of fixed lights"),
])
def test_bad_housing_keys_are_one_clear_error(tmp_path, entry, key, words):
    from cell.core.errors import TaskError
    with pytest.raises(TaskError) as caught:
        with_lights(tmp_path, {k: v for k, v in entry.items() if v is not None})
    assert caught.value.key == key and words in str(caught.value), str(caught.value)


def test_planned_viewpoints_a_bar_hides_are_pruned_and_others_kept():
    """bracket-bars' web_outer: every view the planner keeps sees all its samples past both bars
    (the NumPy box), and the views it kept without the bars that a bar hides are gone."""
    from cell.planning.plan import PlannerSettings
    from cell.planning.whole_part import viewpoints_of
    task = load_task(ROOT / "tasks" / "bracket-bars.yaml").with_feature(4)
    assert task.feature.name == "web_outer"
    scene = build_scene(task)

    def hidden_by(camera):
        return [bar.name for bar in task.lights if np.any(reference(inside_bar, bar, scene.points, camera[None]) == 1)]
    with_bars = viewpoints_of(task, PlannerSettings(), lambda _: None)
    without = viewpoints_of(replace(task, lights=()), PlannerSettings(), lambda _: None)
    assert with_bars.kept and all(not hidden_by(v.T_cell_cam[:3, 3]) for v in with_bars.kept)
    hidden = [v for v in without.kept if hidden_by(v.T_cell_cam[:3, 3])]
    assert hidden, "the bars hide none of the views kept without them: the test shows nothing"
    kept = [v.T_cell_cam[:3, 3] for v in with_bars.kept]
    assert not any(np.allclose(v.T_cell_cam[:3, 3], c) for v in hidden for c in kept)
