"""Triangles wound against their neighbours (cell.task.winding): found by the direction each
shared edge runs in its two faces, counted and placed by `cell check`, and named by the planner
when the camera cannot see a feature that lies on them. Meshes with triangles flipped by hand."""
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from cell.cli import main
from cell.task.winding import flipped_faces

PARTS = Path("tasks/parts")


def flip(mesh, faces):
    """The mesh with the given faces' vertex order reversed (their normals turned over)."""
    f = np.array(mesh.faces)
    f[faces] = f[faces][:, ::-1]
    return trimesh.Trimesh(mesh.vertices, f, process=False)


def grid(n=10, step=0.005):
    """An open flat sheet z = 0 of n x n squares, each two triangles wound counter-clockwise
    seen from +z; square (i, j) (x from i step, y from j step) holds faces 2 (i n + j) and + 1."""
    x, y = np.meshgrid(np.arange(n + 1) * step, np.arange(n + 1) * step, indexing="ij")
    vertices = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    at = lambda i, j: i * (n + 1) + j
    faces = [[at(i, j), at(i + 1, j), at(i + 1, j + 1)] if k == 0 else [at(i, j), at(i + 1, j + 1), at(i, j + 1)]
             for i in range(n) for j in range(n) for k in range(2)]
    return trimesh.Trimesh(vertices, np.array(faces), process=False)


def test_a_consistent_mesh_has_none_and_scattered_flips_are_each_found():
    sphere = trimesh.creation.icosphere(3)
    assert sphere.is_winding_consistent and len(flipped_faces(sphere)) == 0
    chosen = [5, 100, 400, 700, 1100]
    found = flipped_faces(flip(sphere, chosen))
    assert not flip(sphere, chosen).is_winding_consistent        # trimesh's own verdict agrees
    assert sorted(found.faces.tolist()) == chosen
    assert sorted(found.counts.tolist()) == [1] * 5
    centres = sphere.triangles_center[chosen]
    for place in found.places:                                  # each place is one flipped face's centre
        assert np.min(np.linalg.norm(centres - place, axis=1)) < 1e-12


def test_a_flipped_patch_of_an_open_sheet_is_counted_and_placed_at_its_centre():
    """Squares (3..4, 5..6) of a 10 x 10 sheet of 5 mm squares flipped: 8 triangles, a patch whose
    centre is at x = 20 mm, y = 30 mm by hand. The sheet is open: no volume tells which way is out."""
    sheet = grid()
    chosen = [2 * (i * 10 + j) + k for i in (3, 4) for j in (5, 6) for k in (0, 1)]
    found = flipped_faces(flip(sheet, chosen))
    assert not sheet.is_watertight
    assert sorted(found.faces.tolist()) == chosen and found.counts.tolist() == [8]
    assert found.places[0] == pytest.approx([0.020, 0.030, 0.0], abs=1e-12)
    assert found.where() == "8 around [20.0, 30.0, 0.0] mm (part frame)"


@pytest.mark.parametrize("name", sorted(p.name for p in PARTS.glob("*.stl")))
def test_the_example_parts_have_no_flipped_triangles(name):
    mesh = trimesh.load(PARTS / name, process=True)
    assert len(flipped_faces(mesh)) == 0


@pytest.fixture
def open_hinge_flipped(tmp_path):
    """tasks/hinge.yaml on its mesh with the leaf's bottom removed (an open mesh: the loader's
    inside-out check does not apply) and the leaf's top (60 x 40 mm at z = 4 mm, centred on the
    part's origin; the feature on it) wound the other way: its two triangles."""
    mesh = trimesh.load(PARTS / "hinge.stl", process=True)
    c, n = mesh.triangles_center, mesh.face_normals
    bottom = (np.abs(c[:, 2]) < 1e-9) & (n[:, 2] < -0.99)
    top = (np.abs(c[:, 2] - 4.0) < 1e-9) & (n[:, 2] > 0.99) & (np.abs(c[:, 0]) < 30.0 + 1e-9)
    assert bottom.sum() == 2 and top.sum() == 2
    f = np.array(mesh.faces)
    f[top] = f[top][:, ::-1]
    trimesh.Trimesh(mesh.vertices, f[~bottom], process=False).export(tmp_path / "hinge-open.stl")
    raw = yaml.safe_load(Path("tasks/hinge.yaml").read_text())
    raw["part"]["mesh"] = str(tmp_path / "hinge-open.stl")
    raw["part"]["material"] = str(Path("tasks/materials/milled_aluminium.yaml").resolve())
    path = tmp_path / "hinge-flipped.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_cell_check_warns_of_the_flipped_triangles_with_their_count_and_place(open_hinge_flipped, capsys):
    assert main(["check", str(open_hinge_flipped)]) == 0
    out = capsys.readouterr().out
    assert ("warning      the mesh has 2 triangles wound against their neighbours (flipped): 2 around "
            "[0.0, 0.0, 4.0] mm (part frame); the planner sees them from behind: fix the mesh's winding") in out


def test_the_planner_names_the_meshs_winding_when_the_feature_lies_on_flipped_triangles(open_hinge_flipped, tmp_path,
                                                                                        capsys):
    assert main(["plan", str(open_hinge_flipped), "--out", str(tmp_path / "plan")]) == 1
    err = capsys.readouterr().err
    assert ("the camera cannot see 64 of 64 feature samples: 64 lie on triangles wound against their neighbours "
            "(the mesh's winding is flipped there, 2 around [0.0, 0.0, 4.0] mm (part frame)), so their surface "
            "faces away from the camera; fix the mesh's winding") in err
