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
