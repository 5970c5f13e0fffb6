"""The moving bodies as shadow geometry (cell.collision.rays): the slab test against trimesh's
own ray casting, and the spot lamp's housing hiding feature samples from the camera."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import trimesh
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from cell.collision.rays import segments_cross_boxes, segments_near_segments
from cell.core import geometry
from cell.devices import rig
from cell.planning import evaluate, requirements
from cell.planning.one_shot import plan
from cell.planning.scene import build_scene
from cell.task.loader import load_task


def brute_force(T_cell_box, half_m, origins, targets):
    """(N,) whether each segment crosses the box mesh: an end inside it (behind every face's
    plane: the mesh is convex) or a face's plane met by the segment's line (trimesh's
    intersections.planes_lines, as its ray casting does) within the segment, at a point inside
    that triangle (trimesh's barycentric coordinates)."""
    box = trimesh.creation.box(extents=2.0 * half_m, transform=T_cell_box)
    d = targets - origins
    length = np.linalg.norm(d, axis=1)

    def inside(p):
        return np.all(np.einsum("fj,nfj->nf", box.face_normals, p[:, None] - box.triangles[None, :, 0]) < 0, axis=1)
    crossed = inside(origins) | inside(targets)
    for triangle, normal in zip(box.triangles, box.face_normals):
        n = len(origins)
        at, valid = trimesh.intersections.planes_lines(np.tile(triangle[0], (n, 1)), np.tile(normal, (n, 1)),
                                                       origins, d / length[:, None])
        rays = np.flatnonzero(valid)
        along = np.einsum("nj,nj->n", at - origins[rays], d[rays]) / length[rays]
        bary = trimesh.triangles.points_to_barycentric(np.tile(triangle, (len(rays), 1, 1)), at)
        hit = (along > 0) & (along < length[rays]) & np.all(bary >= 0, axis=1)
        crossed[rays[hit]] = True
    return crossed


def test_the_slab_test_agrees_with_trimesh_ray_casting_on_random_boxes_and_segments():
    rng = np.random.default_rng(26)
    agree = crossings = 0
    for _ in range(20):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-0.2, 0.2, 3)
        half = rng.uniform(0.02, 0.3, 3)
        origins, targets = rng.uniform(-0.6, 0.6, (2, 300, 3))
        fast = segments_cross_boxes(origins, targets, T[None], half)[0]
        slow = brute_force(T, half, origins, targets)
        agree += np.sum(fast == slow)
        crossings += slow.sum()
    assert agree == 20 * 300 and 500 < crossings < 5500          # both outcomes well represented


def test_boxes_and_segments_broadcast_and_grazing_or_parallel_segments_do_not_cross():
    T = np.stack([np.eye(4)] * 2)
    T[1, :3, 3] = (5.0, 0.0, 0.0)
    half = np.array([1.0, 1.0, 1.0])
    # along x through both boxes; one along the face y = 1 (grazing); parallel to z inside; one short of the box
    origins = np.array([[-2.0, 0.0, 0.0], [-2.0, 1.0, 0.0], [0.5, 0.5, -3.0], [-3.0, 0.0, 0.0]])
    targets = np.array([[7.0, 0.0, 0.0], [7.0, 1.0, 0.0], [0.5, 0.5, 3.0], [-1.5, 0.0, 0.0]])
    assert segments_cross_boxes(origins, targets, T, half).tolist() == [[True, False, True, False],
                                                                         [True, False, False, False]]
    # one target for every origin
    assert segments_cross_boxes(origins[:1], np.zeros(3), T, half).tolist() == [[True], [False]]


def test_one_origin_gives_the_bits_of_the_origin_repeated_for_every_target():
    """A line of sight's one origin (the camera) is placed in the boxes' frames and offset from the
    capsules once: the same answer, bit for bit, as the origin repeated per target; the sums the
    tests read (rays.dot, rays.in_frames) are the dot product and R^T x to rounding."""
    from cell.collision.rays import dot, in_frames
    rng = np.random.default_rng(28)
    T = np.stack([np.eye(4)] * 5)
    T[:, :3, :3] = Rotation.random(5, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.2, 0.2, (5, 3))
    half = rng.uniform(0.02, 0.2, (5, 3))
    origin, targets = rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, (400, 3))
    a, b = rng.uniform(-0.3, 0.3, (2, 6, 3))
    radius = rng.uniform(0.02, 0.15, 6)
    repeated = np.broadcast_to(origin, targets.shape)
    crossed = segments_cross_boxes(origin, targets, T, half)
    assert np.array_equal(crossed, segments_cross_boxes(repeated, targets, T, half)) and 50 < crossed.sum() < 1900
    assert np.array_equal(segments_cross_boxes(targets, origin, T, half), segments_cross_boxes(targets, repeated, T, half))
    near = segments_near_segments(origin, targets, a, b, radius)
    assert np.array_equal(near, segments_near_segments(repeated, targets, a, b, radius)) and 50 < near.sum() < 2300
    x, y = rng.normal(size=(2, 7, 3))
    np.testing.assert_allclose(dot(list(x.T), list(y.T)), np.sum(x * y, axis=1), rtol=1e-12, atol=1e-15)
    by_hand = np.array([[R.T @ v for v in x] for R in T[:, :3, :3]])
    np.testing.assert_allclose(np.stack(in_frames(T[:, :3, :3], list(x.T)), axis=-1), by_hand, rtol=1e-12, atol=1e-15)


def slabs_at_once(origins, targets, T_cell_box, half_m):
    """The slab test on (B, N, 3) arrays at once, as segments_cross_boxes computed it before it
    took a component at a time: R^T x by np.einsum, the bounds by max / min over the last axis."""
    T = np.asarray(T_cell_box, float).reshape(-1, 4, 4)
    half = np.broadcast_to(np.asarray(half_m, float), (len(T), 3))[:, None]
    o, q = np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3)
    R, c = T[:, :3, :3], T[:, :3, 3]
    local = np.einsum("bji,bnj->bni", R, np.broadcast_to(o[None] - c[:, None], (len(T), len(o), 3)))
    d = np.einsum("bji,bnj->bni", R, np.broadcast_to(q - o, (len(T), max(len(o), len(q)), 3)))
    inside = np.abs(local) < half
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - local) / d, (half - local) / d
    near = np.where(d == 0.0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    far = np.where(d == 0.0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    return np.maximum(near.max(axis=-1), 0.0) < np.minimum(far.min(axis=-1), 1.0)


def test_the_slab_test_a_component_at_a_time_answers_as_on_whole_arrays():
    """segments_cross_boxes against the slab test on (B, N, 3) arrays at once: turned and
    axis-aligned boxes, segments parallel to their faces (inside and outside a slab), ends on a
    face, one origin for every target and one target for every origin."""
    rng = np.random.default_rng(41)
    T = np.stack([np.eye(4)] * 6)
    T[:4, :3, :3] = Rotation.random(4, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.2, 0.2, (6, 3))
    half = rng.uniform(0.02, 0.3, (6, 3))
    origins, targets = rng.uniform(-0.6, 0.6, (2, 2000, 3))
    targets[:500, 1:] = origins[:500, 1:]                       # along x: parallel to the upright boxes' faces
    targets[500:700, 2] = origins[500:700, 2] = T[4, 2, 3] + half[4, 2]    # in the plane of a face
    crossed = segments_cross_boxes(origins, targets, T, half)
    assert np.array_equal(crossed, slabs_at_once(origins, targets, T, half)) and 500 < crossed.sum() < 11000
    for origin, target in ((origins[0], targets), (origins, targets[0])):
        assert np.array_equal(segments_cross_boxes(origin, target, T, half), slabs_at_once(origin, target, T, half))


def near_at_once(origins, targets, a, b, radius_m):
    """segments_near_segments on (K, N, 3) arrays at once, as it computed them before it took a
    component at a time: the dot products summed x0 y0 + x2 y2 + x1 y1."""
    def dot(x, y):
        return x[..., 0] * y[..., 0] + x[..., 2] * y[..., 2] + x[..., 1] * y[..., 1]
    a, b = np.asarray(a, float).reshape(-1, 3), np.asarray(b, float).reshape(-1, 3)
    p, q = np.asarray(origins, float).reshape(-1, 3), np.asarray(targets, float).reshape(-1, 3)
    d1, d2 = q - p, b - a
    r = p[None] - a[:, None]
    A, E = dot(d1, d1)[None], dot(d2, d2)[:, None]
    B, C, F = dot(d1[None], d2[:, None]), dot(d1[None], r), dot(d2[:, None], r)
    denom = A * E - B * B
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-18 * A * E, np.clip((B * F - C * E) / denom, 0.0, 1.0), 0.0)
        t = (B * s + F) / E
        s = np.where(t < 0.0, np.clip(-C / A, 0.0, 1.0), np.where(t > 1.0, np.clip((B - C) / A, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    gap = r + s[..., None] * d1[None] - t[..., None] * d2[:, None]
    return dot(gap, gap) < np.asarray(radius_m, float).reshape(-1, 1) ** 2


def test_segments_near_segments_a_component_at_a_time_answers_as_on_whole_arrays():
    """segments_near_segments against the same test on (K, N, 3) arrays at once: random capsules
    and segments, segments parallel to an axis, zero-length segments, one origin for every target
    and one target for every origin."""
    rng = np.random.default_rng(43)
    a, b = rng.uniform(-0.3, 0.3, (2, 7, 3))
    b[0] = a[0] + (0.2, 0.0, 0.0)
    radius = rng.uniform(0.02, 0.15, 7)
    origins, targets = rng.uniform(-0.5, 0.5, (2, 3000, 3))
    targets[:300] = origins[:300] + (0.4, 0.0, 0.0)             # parallel to capsule 0's axis
    targets[300:350] = origins[300:350]                         # points
    near = segments_near_segments(origins, targets, a, b, radius)
    assert np.array_equal(near, near_at_once(origins, targets, a, b, radius)) and 500 < near.sum() < 18000
    for origin, target in ((origins[0], targets), (origins, targets[0])):
        assert np.array_equal(segments_near_segments(origin, target, a, b, radius),
                              near_at_once(origin, target, a, b, radius))


RING = Path(__file__).resolve().parent.parent / "tasks" / "ring.yaml"


def lamp_box_by_hand(task, lamp):
    """The lamp's box as docs/formats.md describes lamp_body: its front face centred at the lamp,
    its z axis the aim at the rig's pivot, its x horizontal."""
    z = geometry.unit(task.lamp.rig.pivot_m - lamp)
    x = geometry.unit(np.cross((0.0, 0.0, 1.0), z))
    half = 0.5 * np.asarray(task.cell.collision.lamp_size_m)
    return geometry.transform(np.column_stack([x, np.cross(z, x), z]), lamp - half[2] * z), half


def test_the_lamp_housing_hides_the_samples_whose_line_of_sight_it_crosses_as_trimesh_finds():
    task = load_task(RING)
    scene = build_scene(task)
    problem = evaluate.build_problem(task, scene, None)
    assert problem.camera_seen.all()
    camera, centre = scene.camera_position, scene.center
    rng = np.random.default_rng(5)
    # lamps about the camera's line of sight to the feature (some hide part of it), and elsewhere on the rig
    along = centre + rng.uniform(0.3, 0.7, (40, 1)) * (camera - centre) + rng.normal(0.0, 0.03, (40, 3))
    pan, tilt = rng.uniform(-np.pi, np.pi, 20), rng.uniform(*task.lamp.rig.tilt_range_rad, 20)
    elsewhere = rig.lamp_position(task.lamp.rig.pivot_m, pan, tilt, 0.3)
    lamps = np.vstack([along, elsewhere])
    hides = requirements.lamp_hides(problem, lamps)
    expected = np.array([brute_force(*lamp_box_by_hand(task, lamp), np.broadcast_to(camera, scene.points.shape),
                                     scene.points) for lamp in lamps])
    assert np.array_equal(hides, expected)
    partly = (expected.any(axis=1) & ~expected.all(axis=1)).sum()
    assert expected[:40].all(axis=1).sum() > 5 and partly > 3 and not expected[40:].any()
    # the requirement counts them as unseen, per lamp pose, and names the lamp
    candidates = SimpleNamespace(position=lamps, shutter=np.zeros(len(lamps)))
    assert np.allclose(requirements.camera_view(problem, candidates), np.log(0.5 + expected.sum(axis=1)))
    k = int(np.argmax(expected.sum(axis=1)))
    sentence = requirements.explain_camera_view(problem, SimpleNamespace(position=lamps[k:k + 1]), False)
    assert f"cannot see {expected[k].sum()} of {len(scene.points)}" in sentence and "lamp_body" in sentence


def test_a_rig_that_puts_the_lamp_on_the_cameras_line_of_sight_is_refused_naming_the_lamp():
    task = load_task(RING)
    # every pose of this rig holds the lamp within 16 mm of the axis the camera looks down, 0.15 m
    # above the feature: its 50 mm housing sits across every line of sight
    low = replace(task.lamp.rig, tilt_range_rad=(np.radians(84.0), np.radians(85.0)), radius_range_m=(0.15, 0.15))
    task = replace(task, lamp=replace(task.lamp, rig=low))
    p = plan(task)
    assert not p.feasible and p.binding == "camera_view"
    assert "lamp_body" in p.hint and "move the lamp" in p.hint


def least_distance(p, q, a, b):
    """The least distance between segments p-q and a-b: |p + s (q - p) - a - t (b - a)|^2 is
    convex in (s, t), so scipy's bounded minimiser over [0, 1]^2 finds its minimum."""
    def squared(x):
        gap = p + x[0] * (q - p) - a - x[1] * (b - a)
        return gap @ gap, 2.0 * np.array([gap @ (q - p), -gap @ (b - a)])
    found = minimize(squared, (0.5, 0.5), jac=True, bounds=((0.0, 1.0), (0.0, 1.0)), method="L-BFGS-B",
                     options={"ftol": 1e-15, "gtol": 1e-12})
    return np.sqrt(found.fun)


def test_segments_near_a_capsule_agree_with_a_minimiser_of_the_segments_distance():
    rng = np.random.default_rng(27)
    a, b = rng.uniform(-0.3, 0.3, (2, 6, 3))
    radius = rng.uniform(0.02, 0.15, 6)
    origins, targets = rng.uniform(-0.5, 0.5, (2, 80, 3))
    near = segments_near_segments(origins, targets, a, b, radius)
    d = np.array([[least_distance(origins[n], targets[n], a[k], b[k]) for n in range(80)] for k in range(6)])
    sure = np.abs(d - radius[:, None]) > 1e-6
    assert sure.sum() > 470 and np.array_equal(near[sure], (d < radius[:, None])[sure])
    assert 30 < near.sum() < 450


def test_spokes_near_a_segment_agree_with_a_minimiser_of_the_segments_distance():
    """SpokesNear (pieces of rays from one point against one segment, the closest points' squared
    distance expanded) against scipy's bounded minimiser: random spokes, spokes parallel to the
    segment, spokes of length 0 (start = end), a segment of length 0, spokes through the origin's
    own point (start 0), grazing ones (the radius 1e-9 off their distance either way)."""
    from cell.collision.rays import SpokesNear
    rng = np.random.default_rng(28)
    for trial in range(12):
        origin, p = rng.uniform(-0.3, 0.3, (2, 3))
        q = p if trial == 11 else p + rng.uniform(-0.4, 0.4, 3)
        unit = rng.normal(size=(40, 3))
        if trial < 11:
            unit[:6] = (q - p) + (0.0 if trial % 2 else rng.normal(0.0, 1e-9, (6, 3)))   # parallel
        unit /= np.linalg.norm(unit, axis=1)[:, None]
        start = rng.uniform(0.0, 0.3, 40)
        end = 0.45
        start[6:9], start[9] = end, 0.0                                                   # of length 0; from o
        d = np.array([least_distance(origin + s * u, origin + end * u, p, q) for s, u in zip(start, unit)])
        spokes = SpokesNear.of(origin, p, q)
        for radius in (0.05, 0.15, 0.3):
            near = spokes.near(unit, start, end, radius)
            sure = np.abs(d - radius) > 1e-6
            assert sure.sum() > 30 and np.array_equal(near[sure], (d < radius)[sure]), (trial, radius)
        # grazing: the radius a hair beyond each spoke's distance finds it, a hair short does not
        assert np.all([spokes.near(unit[k:k + 1], start[k], end, d[k] + 1e-6)[0] for k in range(40)])
        assert not np.any([spokes.near(unit[k:k + 1], start[k], end, d[k] - 1e-6)[0] for k in range(40)])
        assert not spokes.near(np.full((1, 3), np.nan), 0.1, end, 1.0).any()


def test_a_capsule_s_balls_hold_the_capsule():
    from cell.collision.rays import capsule_balls
    rng = np.random.default_rng(29)
    a = rng.uniform(-0.3, 0.3, (5, 3))
    b = a + rng.uniform(-0.5, 0.5, (5, 3)) * np.array([[1.0], [1.0], [1.0], [0.01], [0.0]])   # short, and of length 0
    radius = rng.uniform(0.01, 0.05, 5)
    centres, radii, first = capsule_balls(a, b, radius)
    assert np.array_equal(first, np.searchsorted(np.arange(len(centres)), first)) and first[0] == 0
    assert np.all(radii <= 2.0 * np.repeat(radius, np.diff(np.append(first, len(centres)))) + 1e-12)
    for k in range(5):
        direction = rng.normal(size=(3000, 3))
        points = (a[k] + rng.uniform(0, 1, (3000, 1)) * (b[k] - a[k])
                  + radius[k] * rng.uniform(0, 1, (3000, 1)) * direction / np.linalg.norm(direction, axis=1)[:, None])
        mine = slice(first[k], first[k + 1] if k + 1 < 5 else len(centres))
        held = np.linalg.norm(points[:, None] - centres[None, mine], axis=-1) <= radii[None, mine] * (1 + 1e-12)
        assert held.any(axis=1).all()


def crosses_by_points(bodies, origins, targets, step=2e-4):
    """(N,) whether points every `step` along each segment fall inside one of the bodies (their
    signed distance functions, cell.collision.bodies), and (N,) whether the segment passes at
    least 2 steps clear of them all (sure either way when one of the two holds)."""
    t = np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(targets - origins, axis=1).max() / step)) + 1)
    points = origins[:, None] + t[None, :, None] * (targets - origins)[:, None]
    least = np.min([body.sdf(points.reshape(-1, 3)).reshape(len(origins), -1).min(axis=1) for body in bodies], axis=0)
    return least < 0.0, least > 2 * step


def test_the_camera_body_and_the_arm_shadow_the_spot_where_its_rays_cross_them():
    from cell.collision.scene import CollisionScene, reaching_joints
    task = load_task(RING)
    scene = build_scene(task)
    problem = evaluate.build_problem(task, scene, None)
    assert problem.camera_unseen == 0                          # the view is the kernel's: no body hides it
    cs = CollisionScene.of(task)
    q = reaching_joints(task.frames, scene.T_cell_cam)
    bodies = cs.bodies(scene.T_cell_cam, q)[len(cs.fixed):]    # the camera body and the arm's links
    rng = np.random.default_rng(8)
    # lamps above the camera (its body and the wrist in the way), beside it, and around the rig
    above = scene.camera_position + np.array([0.0, 0.0, 0.12]) + rng.normal(0.0, 0.03, (6, 3))
    pan, tilt = rng.uniform(-np.pi, np.pi, 10), rng.uniform(*task.lamp.rig.tilt_range_rad, 10)
    lamps = np.vstack([above, rig.lamp_position(task.lamp.rig.pivot_m, pan, tilt, rng.uniform(0.2, 0.5, 10))])
    u, shadowed, _, _ = evaluate.unit_gray(problem, lamps, rig.lamp_aim(task.lamp.rig.pivot_m, lamps))
    blocked = evaluate.spot_blocked(problem, lamps)
    for k, lamp in enumerate(lamps):
        inside, clear = crosses_by_points(bodies, scene.points, np.broadcast_to(lamp, scene.points.shape))
        assert np.all(blocked[k][inside]) and not np.any(blocked[k][clear])
    assert blocked[:6].sum() > 100 and np.all(u[blocked] == 0.0) and np.all(shadowed[blocked])
    # the part's own flags stand where no body is in the way
    kernel = problem.gray_inputs(lamps, rig.lamp_aim(task.lamp.rig.pivot_m, lamps))
    assert np.array_equal(shadowed[~blocked], kernel.shadowed[~blocked]) and np.array_equal(u[~blocked], kernel.value[~blocked])
    # the sentence names them where they shadow the chosen lamp
    k = int(np.argmax(blocked.sum(axis=1)))
    one = SimpleNamespace(shadowed=shadowed[k:k + 1], position=lamps[k:k + 1])
    assert f"camera body or the arm stands in the lamp's beam at {blocked[k].sum()}" in requirements.explain_no_shadow(
        replace(problem, maps=SimpleNamespace(visible=np.ones(1))), one, False)


def test_the_bodies_at_a_pose_are_the_collision_scene_s_made_once_per_pose():
    """evaluate.arm_at_camera: the camera body and the arm's links as the collision scene places
    them at the shot, kept per camera pose and what places them (the judge asks a shot's pose again
    for each feature), read-only; equal frames give equal bodies."""
    from cell.collision.scene import CollisionScene, reaching_joints
    task = load_task(RING)
    scene = build_scene(task)
    cs = CollisionScene.of(task)
    body, *links = cs.bodies(scene.T_cell_cam, reaching_joints(task.frames, scene.T_cell_cam))[len(cs.fixed):]
    kept = evaluate.arm_at_camera(task, scene.T_cell_cam)
    T_cell_box, half_m, a, b, radius = kept[:5]
    assert np.allclose(T_cell_box, body.T_cell_box) and np.allclose(half_m, body.half_m)
    assert np.allclose(a, [k.a for k in links]) and np.allclose(b, [k.b for k in links])
    assert np.allclose(radius, [k.radius_m for k in links])
    assert evaluate.arm_at_camera(task, scene.T_cell_cam.copy()) is kept and not any(x.flags.writeable for x in kept)
    other = replace(task, frames=replace(task.frames))
    again = evaluate.arm_at_camera(other, scene.T_cell_cam)
    assert all(np.array_equal(x, y) for x, y in zip(again, kept))
    moved = scene.T_cell_cam.copy()
    moved[:3, 3] += (0.01, 0.0, 0.0)
    assert not np.allclose(evaluate.arm_at_camera(task, moved)[0], T_cell_box)


def test_a_box_s_capsule_holds_the_box():
    from cell.collision.rays import box_capsules
    rng = np.random.default_rng(31)
    T = np.stack([np.eye(4)] * 12)
    T[:, :3, :3] = Rotation.random(12, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-0.3, 0.3, (12, 3))
    half = rng.uniform(0.01, 0.2, (12, 3))
    a, b, radius = box_capsules(T, half)
    corners = np.array(np.meshgrid(*[(-1.0, 1.0)] * 3, indexing="ij")).reshape(3, -1).T
    for k in range(12):
        inside = np.vstack([rng.uniform(-1.0, 1.0, (500, 3)), corners]) * half[k]     # the box's own frame
        points = geometry.apply(T[k], inside)
        s = np.clip((points - a[k]) @ (b[k] - a[k]) / np.sum((b[k] - a[k]) ** 2), 0.0, 1.0)
        gap = np.linalg.norm(points - a[k] - s[:, None] * (b[k] - a[k]), axis=1)
        assert gap.max() <= radius[k] * (1 + 1e-12)
        # no wider than the box: the corners lie on its surface (the axis is the box's longest)
        assert gap.max() == pytest.approx(radius[k]) and np.linalg.norm(b[k] - a[k]) == pytest.approx(2 * half[k].max())


def distance_to_segments(point, origin, ends):
    """(C,) the least distance from a point to each segment origin -> end, by 4001 points along it."""
    t = np.linspace(0.0, 1.0, 4001)
    along = origin + t[None, :, None] * (ends - origin)[:, None]
    return np.linalg.norm(along - point, axis=-1).min(axis=1)


def test_balls_seen_from_a_point_keep_every_segment_that_meets_them():
    from cell.collision.rays import BallsSeen
    rng = np.random.default_rng(32)
    origin = rng.normal(size=3) * 0.1
    centres, radii = rng.uniform(-0.4, 0.4, (6, 3)), rng.uniform(0.05, 0.15, 6)
    centres[0], radii[0] = origin + 0.01, 0.05                        # one ball about the origin
    ends = rng.uniform(-0.6, 0.6, (300, 3))
    met = BallsSeen.of(origin, centres, radii).met_by(ends)
    meets = np.array([distance_to_segments(c, origin, ends) <= r - 1e-3 for c, r in zip(centres, radii)])
    assert not np.any(meets & ~met)                                   # never skips a segment that meets
    assert met[0].all() and meets[1:].sum() > 20 and (met[1:] & ~meets[1:]).sum() < meets[1:].sum()  # and filters
    assert not BallsSeen.of(origin, centres, radii).met_by(np.full(3, np.nan)).any()


def test_the_sight_cone_keeps_every_ball_a_line_of_sight_meets():
    from cell.collision.rays import SightCone
    rng = np.random.default_rng(33)
    apex, middle, rho = np.array([0.0, 0.0, 0.4]), np.array([0.01, -0.02, 0.0]), 0.03
    direction = rng.normal(size=(4000, 3))
    samples = middle + rho * rng.uniform(0, 1, (4000, 1)) ** (1 / 3) * direction / np.linalg.norm(direction, axis=1)[:, None]
    centres = np.vstack([apex + rng.uniform(0.0, 1.2, (150, 1)) * (middle - apex) + rng.normal(0.0, 0.05, (150, 3)),
                         rng.uniform(-0.5, 0.5, (150, 3))])
    radius = 0.04
    meets = np.array([distance_to_segments(c, apex, samples[::10]).min() <= radius - 2e-3 for c in centres])
    found = SightCone.of(apex, middle, rho).meets(centres, radius)
    assert not np.any(meets & ~found) and meets.sum() > 30 and (found & ~meets).sum() < 0.5 * meets.sum()
    assert SightCone.of(middle, middle, rho).meets(centres, radius).all()          # the apex inside: every ball


def with_reach(task, reach_m):
    """The task with cell.collision.rig_reach_m set (None: the servo at the lamp's back)."""
    return replace(task, cell=replace(task.cell, collision=replace(task.cell.collision, rig_reach_m=reach_m)))


@pytest.mark.parametrize("pivot_aside_m, reach_m", [(0.0, None), (0.12, None), (0.12, 0.69)])
def test_the_prefilters_skip_no_crossing_of_the_arm_the_camera_body_the_lamp_or_its_links(pivot_aside_m, reach_m):
    """spot_blocked and lamp_hides equal the exact tests of every body against every ray, their
    prefilters left out, for lamps about the bodies, the lines of sight and the rig (its pivot at
    the feature, and beside it, where the pan-tilt's links hide samples the housing does not; the
    servo at the lamp's back, and at a declared reach with the rig's arm out to it)."""
    task = with_reach(load_task(RING), reach_m)
    task = replace(task, lamp=replace(task.lamp, rig=replace(task.lamp.rig,
                                                             pivot_m=task.lamp.rig.pivot_m + (pivot_aside_m, 0.0, 0.0))))
    scene = build_scene(task)
    problem = evaluate.build_problem(task, scene, None)
    arm = evaluate.arm_at_shot(task, scene)
    rng = np.random.default_rng(34)
    camera, centre, P = scene.camera_position, scene.center, len(scene.points)
    pan, tilt = rng.uniform(-np.pi, np.pi, 60), rng.uniform(*task.lamp.rig.tilt_range_rad, 60)
    # lamps whose pan-tilt arm runs out through the lines of sight 0.1-0.3 m beyond them
    out = centre + rng.uniform(0.4, 0.9, (30, 1)) * (camera - centre) + rng.normal(0.0, 0.01, (30, 3)) - task.lamp.rig.pivot_m
    radius = np.clip(np.linalg.norm(out, axis=1)[:, None] - rng.uniform(0.1, 0.3, (30, 1)), *task.lamp.rig.radius_range_m)
    lamps = np.vstack([centre + rng.uniform(0.2, 1.2, (60, 1)) * (camera - centre) + rng.normal(0.0, 0.04, (60, 3)),
                       arm.a + rng.uniform(0, 1, (len(arm.a), 1)) * (arm.b - arm.a) + rng.normal(0.0, 0.06, arm.a.shape),
                       rig.lamp_position(task.lamp.rig.pivot_m, pan, tilt, rng.uniform(0.15, 0.6, 60)),
                       task.lamp.rig.pivot_m + radius * out / np.linalg.norm(out, axis=1)[:, None]])
    spot, hidden = exact_blockers(problem, lamps)
    kept = evaluate.spot_blocked(problem, lamps)
    assert np.array_equal(kept, spot) and 10 < spot.any(axis=1).sum() < len(lamps) - 10
    assert np.array_equal(requirements.lamp_hides(problem, lamps), hidden) and 10 < hidden.any(axis=1).sum() < len(lamps) - 10
    # the last lamps asked are kept: their first rows answered from them (read-only), others found
    for first in (1, 7, len(lamps)):
        again = evaluate.spot_blocked(problem, lamps[:first])
        assert np.array_equal(again, spot[:first]) and np.shares_memory(again, kept) and not again.flags.writeable
    other = evaluate.spot_blocked(problem, lamps[3:9])
    assert np.array_equal(other, spot[3:9]) and not np.shares_memory(other, kept)


def exact_blockers(problem, lamps):
    """(spot_blocked, lamp_hides) as the exact tests of every body against every ray find them,
    no prefilter: the camera body and the arm's links across the rays sample -> lamp, the lamp's
    housing, the tilt servo and the arm across the lines of sight camera -> sample it sees."""
    from cell.collision.scene import lamp_boxes, rig_links
    task, scene = problem.task, problem.scene
    arm = evaluate.arm_at_shot(task, scene)
    P, camera = len(scene.points), scene.camera_position
    origins = np.broadcast_to(scene.points, (len(lamps), P, 3)).reshape(-1, 3)
    targets = np.repeat(lamps, P, axis=0)
    spot = (segments_cross_boxes(origins, targets, arm.T_cell_box[None], arm.half_m)[0]
            | segments_near_segments(origins, targets, arm.a, arm.b, arm.radius_m).any(axis=0)).reshape(len(lamps), P)
    half = 0.5 * np.asarray(task.cell.collision.lamp_size_m)
    links = rig_links(task.lamp.rig.pivot_m, half, task.cell.collision.rig_reach_m, lamps)
    hidden = (segments_cross_boxes(camera, scene.points, lamp_boxes(task.lamp.rig.pivot_m, half, lamps), half)
              | segments_cross_boxes(camera, scene.points, links.T_cell_servo, links.servo_half_m))
    if links.arm:
        hidden |= segments_near_segments(camera, scene.points, links.a, links.b, links.radius_m)
    seen = np.zeros(P, bool) if problem.camera_seen is None else problem.camera_seen
    return spot, hidden & seen


@pytest.mark.long
def test_the_prefilters_skip_no_crossing_on_the_calls_of_a_plan(monkeypatch):
    """Every call spot_blocked and lamp_hides answer while the bracket is planned (its searches,
    certificates and explanations) equals the exact tests without prefilters."""
    calls = []
    for module, name in ((evaluate, "spot_blocked"), (requirements, "lamp_hides")):
        def recorded(problem, positions, _f=getattr(module, name), _name=name):
            out = _f(problem, positions)
            calls.append((_name, problem, np.array(positions, float).reshape(-1, 3), out))
            return out
        monkeypatch.setattr(module, name, recorded)
    from cell.planning.whole_part import plan_features
    plan_features(load_task(RING.parent / "bracket.yaml"))
    monkeypatch.undo()
    names = [name for name, *_ in calls]
    assert names.count("spot_blocked") > 100 and names.count("lamp_hides") > 100
    rng = np.random.default_rng(37)
    hiding = 0
    for k in rng.permutation(len(calls))[:400]:
        name, problem, positions, out = calls[k]
        spot, hidden = exact_blockers(problem, positions)
        assert np.array_equal(out, spot if name == "spot_blocked" else hidden), (name, k)
        hiding += int(out.any())
    assert hiding > 0


def links_by_hand(task, lamp):
    """The pan-tilt's links as docs/formats.md (cell.collision.rig_reach_m) describes them: the
    tilt servo a 34 x 46.5 x 28.5 mm box (x horizontal, y, z along the aim) whose front face is at
    the lamp box's back, or rig_reach_m from the pivot where the task declares it; the arm a 10 mm
    radius tube from the lamp box's back to the servo's front face (None where no reach is
    declared)."""
    (T, half) = lamp_box_by_hand(task, lamp)
    z = T[:3, 2]
    pivot = task.lamp.rig.pivot_m
    back = lamp - 2 * half[2] * z
    reach = task.cell.collision.rig_reach_m
    front = back if reach is None else pivot - reach * z
    servo_half = np.array([0.034, 0.0465, 0.0285]) / 2
    T_servo = T.copy()
    T_servo[:3, 3] = front - servo_half[2] * z
    return None if reach is None else (back, front, 0.010), T_servo, servo_half


@pytest.mark.parametrize("reach_m", [None, 0.69])
def test_the_pan_tilt_links_hide_the_samples_whose_line_of_sight_they_cross_as_trimesh_finds(reach_m):
    task = with_reach(load_task(RING), reach_m)
    # the rig's pivot 0.12 m beside the feature: an arm can cross the camera's lines of sight where its lamp does not
    task = replace(task, lamp=replace(task.lamp, rig=replace(task.lamp.rig, pivot_m=task.lamp.rig.pivot_m + (0.12, 0.0, 0.0))))
    scene = build_scene(task)
    problem = evaluate.build_problem(task, scene, None)
    camera, centre, pivot = scene.camera_position, scene.center, task.lamp.rig.pivot_m
    rng = np.random.default_rng(35)
    # lamps whose links run out through the camera's line of sight to the feature (the arm 0.1-0.3 m
    # beyond the lamp; the servo at the lamp's back, its 28.5 mm depth across it), and lamps
    # elsewhere on the rig
    crossing = centre + rng.uniform(0.4, 0.9, (30, 1)) * (camera - centre) + rng.normal(0.0, 0.005, (30, 3))
    out = crossing - pivot
    behind = rng.uniform(0.1, 0.3, (30, 1)) if reach_m is not None else 0.08 + rng.uniform(0.0, 0.0285, (30, 1))
    radius = np.linalg.norm(out, axis=1)[:, None] - behind
    lamps = np.vstack([pivot + np.clip(radius, *task.lamp.rig.radius_range_m) * out / np.linalg.norm(out, axis=1)[:, None],
                       rig.lamp_position(pivot, rng.uniform(-np.pi, np.pi, 20), rng.uniform(0.1, 0.5, 20), 0.3)])
    housing, links = requirements.rig_hides(problem, lamps)
    P = len(scene.points)
    sight = np.broadcast_to(camera, scene.points.shape)
    t = np.linspace(0.0, 1.0, 3001)
    along = camera + t[None, :, None] * (scene.points - camera)[:, None]              # (P, 3001, 3)
    for k, lamp in enumerate(lamps):
        assert np.array_equal(housing[k], brute_force(*lamp_box_by_hand(task, lamp), sight, scene.points))
        arm, T_servo, servo_half = links_by_hand(task, lamp)
        servo = brute_force(T_servo, servo_half, sight, scene.points)
        if arm is None:
            assert np.array_equal(links[k], servo)
            continue
        a, b, radius = arm
        s = np.clip(np.einsum("pnj,j->pn", along - a, b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        gap = np.linalg.norm(along - a - s[..., None] * (b - a), axis=-1).min(axis=1)   # the arm's axis, densely
        step = np.linalg.norm(scene.points - camera, axis=1).max() / 3000
        sure = servo | (gap < radius - step) | (gap > radius + step)
        assert np.array_equal(links[k][sure], (servo | (gap < radius))[sure]) and sure.sum() > 0.8 * P
    assert links[:30].any(axis=1).sum() > 10 and not links[30:].any()
    if reach_m is None:          # the servo right behind the housing, narrower: in its shadow on these lines
        return
    assert (links & ~housing).any()
    # the requirement counts them as unseen; the sentence names the links
    k = int(np.argmax((links & ~housing).sum(axis=1)))
    candidates = SimpleNamespace(position=lamps, shutter=np.zeros(len(lamps)))
    assert np.allclose(requirements.camera_view(problem, candidates), np.log(0.5 + (housing | links).sum(axis=1)))
    sentence = requirements.explain_camera_view(problem, SimpleNamespace(position=lamps[k:k + 1]), False)
    assert f"cannot see {(housing | links)[k].sum()} of {P}" in sentence and "pan-tilt's links behind the lamp" in sentence


@pytest.mark.parametrize("reach_m", [None, 0.69])
def test_the_pan_tilt_links_lie_behind_the_lamp_out_of_its_beam(reach_m):
    """Every point of the arm and the servo lies behind the plane of the lamp's front across its
    aim, where no ray to a sample the lamp lights (under 90 deg off its aim) goes."""
    from cell.collision.bodies import Box, Capsule
    from cell.collision.scene import rig_links
    task = with_reach(load_task(RING), reach_m)
    pivot, half = task.lamp.rig.pivot_m, 0.5 * np.asarray(task.cell.collision.lamp_size_m)
    rng = np.random.default_rng(36)
    lamps = rig.lamp_position(pivot, rng.uniform(-np.pi, np.pi, 40), rng.uniform(*task.lamp.rig.tilt_range_rad, 40),
                              rng.uniform(*task.lamp.rig.radius_range_m, 40))
    held = rig_links(pivot, half, reach_m, lamps)
    for k, lamp in enumerate(lamps):
        aim = rig.lamp_aim(pivot, lamp)
        arm = Capsule("arm", held.a[k], held.b[k], held.radius_m)
        servo = Box("servo", held.T_cell_servo[k], held.servo_half_m)
        direction = rng.normal(size=(4000, 3))
        points = lamp + rng.uniform(0.0, 0.8, (4000, 1)) * direction / np.linalg.norm(direction, axis=1)[:, None]
        ahead = points[(points - lamp) @ aim >= 0.0]                 # the half-space the beam's rays run in
        assert arm.sdf(ahead).min() > 0.05 and servo.sdf(ahead).min() > 0.05
        front = np.linalg.norm(lamp - pivot) + 2 * half[2] if reach_m is None else reach_m
        assert np.isclose(np.linalg.norm(held.b[k] - pivot), front) and held.arm is (reach_m is not None)
        assert np.isclose(np.linalg.norm(servo.center - pivot), front + 0.01425)
