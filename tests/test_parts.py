"""The part meshes tasks/make_parts.py writes: the examples' unchanged, the curved ones closed,
outward, small and smooth enough that a few-millimetre patch has no visible facets."""
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

PARTS = Path(__file__).resolve().parent.parent / "tasks" / "parts"
sys.path.insert(0, str(PARTS.parent))
import make_parts  # noqa: E402  (tasks/ is a folder of data with its script, not a package on the path)

CURVED = ("sphere_cap", "lying_cylinder", "filleted_block")


@pytest.mark.parametrize("name", sorted(make_parts.PARTS))
def test_the_files_are_what_make_parts_writes(name):
    """hinge.stl and conrod.stl byte for byte as committed before the curved parts came."""
    assert make_parts.PARTS[name]().export(file_type="stl") == (PARTS / f"{name}.stl").read_bytes()


@pytest.mark.parametrize("name", CURVED)
def test_curved_parts_are_closed_outward_and_small(name):
    path = PARTS / f"{name}.stl"
    assert path.stat().st_size < 1_000_000
    mesh = trimesh.load(path)
    for shell in mesh.split(only_watertight=False):
        assert shell.is_watertight and shell.is_winding_consistent and shell.volume > 0
    # facets of the curved surfaces (neighbours less than 10 deg apart) turn by under 2 deg
    angles = np.degrees(mesh.face_adjacency_angles)
    assert 0.5 < angles[angles < 10.0].max() < 2.0


def test_the_curved_surfaces_are_where_the_docstrings_say():
    """Dome r 30 mm about (0, 0, -5); shaft r 20 mm about the line y = 0, z = 22; fillet r 10 mm
    about y's parallel through x = z = 20 (mm): vertices off the flat faces lie on them."""
    dome = make_parts.sphere_cap()
    v = dome.vertices[dome.vertices[:, 2] > 10.0 + 1e-9]
    np.testing.assert_allclose(np.linalg.norm(v - [0, 0, -5], axis=1), 30.0, rtol=1e-12)
    shaft = make_parts.lying_cylinder()
    v = shaft.vertices[(shaft.vertices[:, 2] > 5.0 + 1e-9) & (np.abs(shaft.vertices[:, 0]) < 40.0 - 1e-9)]
    np.testing.assert_allclose(np.hypot(v[:, 1], v[:, 2] - 22.0), 20.0, rtol=1e-12)
    block = make_parts.filleted_block()
    v = block.vertices[:-2]                   # extrude() appends the ends' two fan centres
    v = v[(v[:, 0] > 20.0 + 1e-9) & (v[:, 2] > 20.0 + 1e-9)]
    assert len(v) > 100
    np.testing.assert_allclose(np.hypot(v[:, 0] - 20.0, v[:, 2] - 20.0), 10.0, rtol=1e-12)


BRACKET_FACES = {        # bracket()'s docstring: each feature's face, its outward normal (part frame)
    "base_top": (0.0, 0.0, 1.0), "chamfer": (np.sqrt(0.5), 0.0, np.sqrt(0.5)), "web_inner": (1.0, 0.0, 0.0),
    "bevel": (-np.sqrt(0.5), 0.0, np.sqrt(0.5)), "web_outer": (-1.0, 0.0, 0.0)}


def test_the_brackets_shells_are_closed_and_outward_and_each_feature_sits_on_an_outer_face():
    """Each shell closed with consistent outward winding; each feature of tasks/bracket.yaml on the
    face its docstring names (the loader's normal there is that face's), and that face the
    outermost surface: a ray cast from 50 mm out along the normal at every point of the patch's
    rim and centre meets the part first at that point (no overlapping solid covers it)."""
    from cell.task.loader import load_task
    from cell.physics.reference import ray_first_hit
    mesh = trimesh.load(PARTS / "bracket.stl")
    for shell in mesh.split(only_watertight=False):
        assert shell.is_watertight and shell.is_winding_consistent and shell.volume > 0
    task = load_task(PARTS.parent / "bracket.yaml")
    assert [f.name for f in task.features] == list(BRACKET_FACES)
    for f in task.features:
        normal = np.array(BRACKET_FACES[f.name])
        np.testing.assert_allclose(f.normal, normal, atol=1e-12)
        a = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
        frame = np.linalg.svd(np.eye(3) - np.outer(normal, normal))[0][:, :2]      # the face's plane
        points = 1e3 * np.vstack([f.center_m, f.center_m + f.radius_m * (np.cos(a)[:, None] * frame[:, 0]
                                                                         + np.sin(a)[:, None] * frame[:, 1])])
        first, face = ray_first_hit(mesh, points + 50.0 * normal, np.tile(-normal, (len(points), 1)))
        np.testing.assert_allclose(first, 50.0, atol=1e-9, err_msg=f.name)
        np.testing.assert_allclose(mesh.face_normals[face], np.tile(normal, (len(points), 1)), atol=1e-12)
