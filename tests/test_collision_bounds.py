"""The collision check's cheap paths (cell.collision.bodies SampleCells, bracket, Mesh.contains'
box test; scene.Pairs.clear) held to the full evaluation they stand in for: a mesh's least SDF
over every sample, bit for bit; the bounds around bodies.distance; clear's yes/no against every
pair's distance; on random poses of boxes and capsules about several meshes, touching, inside,
grazing and far, and on degenerate capsules (zero length, along an axis)."""
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cell.collision.bodies import (SAMPLE_BOUND_M, Box, Capsule, Mesh, SampleCells, bracket, distance,
                                   segment_to_box)
from cell.collision.scene import CollisionScene, Pairs, arm_links
from cell.core import geometry
from cell.task.loader import load_task

ROOT = Path(__file__).resolve().parent.parent
BRACKET = ROOT / "tasks" / "bracket.yaml"


def meshes():
    """A sphere, a thin plate, a long bar turned, and the bracket's part in the cell."""
    yield Mesh.of("part", trimesh.creation.icosphere(subdivisions=2, radius=0.04), np.eye(4))
    yield Mesh.of("part", trimesh.creation.box(extents=(0.12, 0.08, 0.004)), geometry.transform(translation=(0.01, 0, 0)))
    yield Mesh.of("part", trimesh.creation.box(extents=(0.2, 0.02, 0.03)),
                  geometry.from_rpy(np.array([0.3, -0.2, 0.7]), np.array([0.0, 0.02, -0.01])))
    yield CollisionScene.of(load_task(BRACKET)).part


def near(mesh, rng, n):
    """Boxes and capsules about the mesh: far, grazing (their nearest sample just off the
    surface), touching, inside; capsules of zero length and along the cell's axes too."""
    centre, radius = mesh.center, mesh.radius
    out = []
    for k in range(n):
        kind = k % 4
        d = geometry.unit(rng.normal(size=3))
        reach = {0: rng.uniform(1.2, 3.0) * radius, 1: radius, 2: 0.5 * radius, 3: 0.0}[kind]
        at = centre + d * reach
        size = rng.uniform(0.005, 0.06, 3)
        out.append(Box("camera_body", geometry.from_rpy(rng.uniform(-3, 3, 3), at), 0.5 * size))
        axis = {0: rng.uniform(-0.15, 0.15, 3), 1: np.zeros(3), 2: np.array([0.0, 0.0, 0.1]),
                3: rng.uniform(-0.05, 0.05, 3)}[int(rng.integers(4))]
        out.append(Capsule("link", at, at + axis, float(rng.uniform(0.0, 0.03))))
    # grazing: a capsule whose surface passes a sample's distance exactly
    for _ in range(n // 2):
        p = mesh.points[rng.integers(len(mesh.points))]
        d = geometry.unit(rng.normal(size=3))
        r = float(rng.uniform(0.001, 0.02))
        a = p + d * (r + rng.uniform(0.0, 0.004))
        out.append(Capsule("link", a, a + np.cross(d, geometry.unit(rng.normal(size=3))) * 0.1, r))
    return out


def full_distance(mesh, body):
    """bodies.distance of a mesh and a body as written before the cells: the body's SDF at every
    sample, less the sampling bound, or the containment test's depth."""
    least = float(body.sdf(mesh.points).min()) - SAMPLE_BOUND_M
    point = body.a if isinstance(body, Capsule) else body.center
    inside = geometry.winding_number(mesh.vertices, mesh.faces, point) > 0.5
    return min(least, -float(np.linalg.norm(mesh.points - point, axis=1).min()) if inside else np.inf)


def test_the_cells_least_is_the_least_over_every_sample_bit_for_bit():
    rng = np.random.default_rng(11)
    for mesh in meshes():
        cells = mesh.cells
        assert sorted(map(tuple, cells.points)) == sorted(map(tuple, mesh.points))
        for body in near(mesh, rng, 24):
            assert cells.least(body.sdf) == float(body.sdf(mesh.points).min()), body
            lower, upper = cells.bounds(body.sdf)
            assert lower <= float(body.sdf(mesh.points).min()) <= upper


def test_every_sample_lies_in_its_cells_spheres():
    """SampleCells' radii hold each fine and coarse cell's samples (the bounds' premise)."""
    for mesh in meshes():
        c = mesh.cells
        fine = np.repeat(np.arange(len(c.radius)), np.diff(c.start))
        assert np.all(np.linalg.norm(c.points - c.centre[fine], axis=1) <= c.radius[fine] + 1e-15)
        coarse = np.repeat(np.arange(len(c.coarse_radius)), np.diff(c.start[c.coarse_start]))
        assert np.all(np.linalg.norm(c.points - c.coarse_centre[coarse], axis=1) <= c.coarse_radius[coarse] + 1e-15)


def test_a_mesh_and_a_body_are_the_distance_of_the_full_evaluation_bit_for_bit():
    rng = np.random.default_rng(12)
    for mesh in meshes():
        for body in near(mesh, rng, 16):
            assert distance(mesh, body) == full_distance(mesh, body), body
            assert distance(body, mesh) == distance(mesh, body)


def test_the_box_test_for_inside_answers_as_the_winding_number():
    rng = np.random.default_rng(13)
    for mesh in meshes():
        low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        points = rng.uniform(low - 0.02, high + 0.02, (200, 3))
        for p in points:
            assert mesh.contains(p) == (geometry.winding_number(mesh.vertices, mesh.faces, p) > 0.5)


def test_the_bracket_holds_the_distance_of_a_mesh_and_a_body():
    rng = np.random.default_rng(14)
    for mesh in meshes():
        for body in near(mesh, rng, 16):
            lower, upper = bracket(mesh, body)
            d = distance(mesh, body)
            assert lower <= d + 1e-15 and d <= upper + 1e-15, (body, lower, d, upper)
            assert bracket(body, mesh) == (lower, upper)


def capsules_about(box, rng, n):
    """Segments about a box: far, grazing a face, an edge or a corner, crossing it, inside it,
    of zero length, along its axes."""
    T, half = box.T_cell_box, box.half_m
    out = []
    for k in range(n):
        kind = k % 5
        local = rng.uniform(-1, 1, 3) * half
        if kind == 0:                                        # far
            local = geometry.unit(rng.normal(size=3)) * rng.uniform(1.5, 4.0) * np.linalg.norm(half)
        elif kind == 1:                                      # on a face, an edge or a corner
            axes = rng.choice(3, int(rng.integers(1, 4)), replace=False)
            local[axes] = np.sign(rng.normal(size=len(axes))) * half[axes] * (1 + rng.uniform(0, 0.05))
        direction = {0: rng.normal(size=3), 1: rng.normal(size=3), 2: np.eye(3)[rng.integers(3)],
                     3: np.zeros(3), 4: rng.normal(size=3)}[kind]
        a = geometry.apply(T, local)
        b = a + geometry.rotate(T, direction) * rng.uniform(0.0, 0.3)
        out.append(Capsule("link", a, b, float(rng.uniform(0.0, 0.03))))
    return out


def test_the_bracket_holds_a_capsule_and_a_box():
    """Its lower bound below segment_to_box's answer and its upper bound above, on random boxes and
    segments; the lower bound within the box's half diagonal of a dense evaluation along the
    segment (not vacuous)."""
    rng = np.random.default_rng(15)
    for _ in range(60):
        box = Box("camera_body", geometry.from_rpy(rng.uniform(-3, 3, 3), rng.uniform(-0.1, 0.1, 3)),
                  0.5 * rng.uniform(0.005, 0.12, 3))
        for link in capsules_about(box, rng, 10):
            lower, upper = bracket(box, link)
            d = distance(box, link)
            assert d == segment_to_box(box, link.a, link.b) - link.radius_m
            assert lower <= d + 1e-15 <= upper + 2e-15, (lower, d, upper)
            t = np.linspace(0.0, 1.0, 2001)
            dense = float(box.sdf(link.a + t[:, None] * (link.b - link.a)).min()) - link.radius_m
            assert dense - lower <= 2 * box.radius + 1e-12
            assert bracket(link, box) == (lower, upper)


def reference_clear(bodies, fixed, padding):
    """clear by every pair's distance: a pair whose bounding spheres are the padding apart is
    clear (Pairs.clear's own premise), any other by bodies.distance."""
    pairs = Pairs.of(bodies, fixed)
    return all(pairs.gap[k] >= padding or distance(bodies[pairs.i[k]], bodies[pairs.j[k]]) >= padding
               for k in range(len(pairs.gap)))


def test_clear_answers_as_every_pairs_distance_does_at_random_and_grazing_paddings():
    """Random arm poses, camera poses and lamps about the bracket, at fixed paddings and at
    paddings equal to a pair's distance and a hair either side of it (the bounds' rounding)."""
    rng = np.random.default_rng(16)
    scene = CollisionScene.of(load_task(BRACKET))
    fixed = len(scene.fixed)
    answers = set()
    for _ in range(40):
        q = rng.uniform(-np.pi, np.pi, 6)
        bodies = (*scene.fixed, *arm_links(scene.frames.T_cell_base, q))
        T = geometry.from_rpy(rng.uniform(-3, 3, 3), scene.part.center + geometry.unit(rng.normal(size=3)) * 0.1)
        bodies = (*bodies, scene.camera_body(T), *scene.lamp_bodies(scene.part.center + rng.normal(size=3) * 0.15))
        pairs = Pairs.of(bodies, fixed)
        k = int(rng.integers(len(pairs.gap)))
        d = distance(bodies[pairs.i[k]], bodies[pairs.j[k]])
        for padding in (0.0, 0.01, 0.05, 0.2, d, np.nextafter(d, np.inf), d + 1e-10, d - 1e-10):
            clear = Pairs.of(bodies, fixed).clear(float(padding))
            assert clear == reference_clear(bodies, fixed, float(padding)), (q, padding)
            answers.add(clear)
    assert answers == {True, False}


def test_segment_to_box_spaces_its_points_as_numpy_linspace_bit_for_bit():
    """segment_to_box writes np.linspace's arithmetic out (start + k (stop - start) / (n - 1), the
    last point the stop); its answer against the same search with np.linspace itself."""
    rng = np.random.default_rng(17)
    steps = np.arange(17.0)
    for _ in range(20000):
        lo, hi = np.sort(rng.uniform(0.0, 1.0, 2))
        lo, hi = (0.0 if rng.uniform() < 0.2 else float(lo)), (1.0 if rng.uniform() < 0.2 else float(hi))
        t = steps * ((hi - lo) / 16) + lo
        t[-1] = hi
        assert np.array_equal(t, np.linspace(lo, hi, 17))

    def by_linspace(box, a, b):
        lo, hi, ab = 0.0, 1.0, b - a
        for _ in range(4):
            t = np.linspace(lo, hi, 17)
            d = np.linalg.norm(np.maximum(np.abs((a + t[:, None] * ab - box.center) @ box.T_cell_box[:3, :3])
                                          - box.half_m, 0.0), axis=1) + np.minimum(
                (np.abs((a + t[:, None] * ab - box.center) @ box.T_cell_box[:3, :3]) - box.half_m).max(axis=1), 0.0)
            k = int(np.argmin(d))
            lo, hi = t[max(k - 1, 0)], t[min(k + 1, 16)]
        return float(d[k] - (t[1] - t[0]) * np.linalg.norm(ab))

    for _ in range(200):
        box = Box("camera_body", geometry.from_rpy(rng.uniform(-3, 3, 3), rng.uniform(-0.1, 0.1, 3)),
                  0.5 * rng.uniform(0.005, 0.12, 3))
        for link in capsules_about(box, rng, 5):
            assert segment_to_box(box, link.a, link.b) == by_linspace(box, link.a, link.b)
