"""Pictures: drawn from several threads at once they come out as if drawn one after the other;
cell.png draws each shot where its numbers put it."""
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as plt_image
from matplotlib.colors import to_rgb

from cell.loader import load_task
from cell.pictures import FEATURE_COLORS, display_mesh, write_bench, write_cell
from cell.planner import plan
from cell.recorder import write_plan

ROOT = Path(__file__).resolve().parent.parent

ROWS = [{"task": "t", "name": n, "time_s": t, "gray_error_max": e, "default": n == "default", "pareto": True}
        for n, t, e in [("coarse", 0.1, 1.8), ("default", 0.3, 0.5), ("fine", 1.5, 0.2)]]


def test_bench_plots_drawn_in_threads_equal_one_drawn_alone(tmp_path):
    """Log axes lay out their tick labels with matplotlib's shared mathtext parser."""
    write_bench(tmp_path / "alone.png", ROWS)
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda k: write_bench(tmp_path / f"{k}.png", ROWS), range(8)))
    alone = (tmp_path / "alone.png").read_bytes()
    assert all((tmp_path / f"{k}.png").read_bytes() == alone for k in range(8))


# --- cell.png: the cell of a plan ---

@pytest.fixture(scope="module")
def hinge():
    task = load_task(ROOT / "tasks" / "hinge.yaml")
    return task, plan(task)


def marker_colours(picture, png):
    """The RGB of the PNG at each drawn shot's camera and lamp marker centre, and the shot's own."""
    image = plt_image.imread(png)[..., :3]
    at = lambda px: image[int(round(px[1])), int(round(px[0]))]          # noqa: E731
    return [(at(s.camera_px), at(s.lamp_px), np.array(to_rgb(s.color))) for s in picture.shots]


def test_cell_png_of_a_one_shot_plan_draws_its_camera_frustum_lamp_and_feature(hinge, tmp_path):
    """The hinge: one shot. Its frustum is the pinhole's rectangle at the focus distance d,
    1032 x 4.65 um x d / 25 mm by 776 x 4.65 um x d / 25 mm, centred on the optical axis; the camera
    and lamp markers lie where the PNG has the shot's colour; write_plan writes cell.png beside
    the maps."""
    task, planned = hinge
    picture = write_cell(tmp_path / "cell.png", planned, task)
    (drawn,) = picture.shots
    shot, d = planned.shot, planned.shot.exposure.focus_m
    c = drawn.frustum_m
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(1032 * 4.65e-6 * d / 0.025, rel=1e-12)
    assert np.linalg.norm(c[2] - c[1]) == pytest.approx(776 * 4.65e-6 * d / 0.025, rel=1e-12)
    np.testing.assert_allclose(c.mean(axis=0), shot.camera_position + d * shot.T_cell_cam[:3, 2], atol=1e-12)
    np.testing.assert_allclose(drawn.camera_m, shot.camera_position)
    np.testing.assert_allclose(drawn.lamp_m, shot.lamp_position)
    np.testing.assert_allclose(drawn.aim_m, task.lamp.rig.pivot_m)
    assert picture.features == (("feature", FEATURE_COLORS[0], 0),)
    for camera, lamp, own in marker_colours(picture, tmp_path / "cell.png"):
        np.testing.assert_allclose(camera, own, atol=2 / 255)
        np.testing.assert_allclose(lamp, own, atol=2 / 255)
    write_plan(planned, task, tmp_path / "plan")
    assert {"cell.png", "visibility_brdf.png", "regions.png", "cost.png"} <= {p.name for p in (tmp_path / "plan").iterdir()}


def test_the_display_mesh_keeps_a_small_part_and_thins_a_dense_one():
    """The hinge (780 facets) is only split, so its surface and bounds stay; the dome (16 536) is
    thinned to about the asked count, its bounds within a clustering cell."""
    import trimesh
    for name, asked in (("hinge", 2000), ("sphere_cap", 1500)):
        mesh = trimesh.load(ROOT / "tasks" / "parts" / f"{name}.stl")
        v, f = display_mesh(mesh.vertices, mesh.faces, asked, split=6)
        shown = trimesh.Trimesh(v, f, process=False)
        if len(mesh.faces) <= asked:
            assert shown.area == pytest.approx(mesh.area, rel=1e-9)
            np.testing.assert_allclose(shown.bounds, mesh.bounds, atol=1e-9)
        else:
            assert 0.5 * asked < len(f) < 2 * asked
            np.testing.assert_allclose(shown.bounds, mesh.bounds, atol=np.sqrt(2 * mesh.area / asked))
