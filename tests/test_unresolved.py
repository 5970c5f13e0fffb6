"""A spike the goniometer did not resolve (the material file's `unresolved`, written by `cell
measure-brdf`) is loaded, and the planner keeps the lamp out of where it may be: lamp directions
whose half vector lies within the goniometer's step of a sample's normal. The trial that found
it: a world of m2 800 measured with a 6 deg step (rho, sigma1, m1 within 0.3 %, the spike
unresolved) had its lamp planned near the mirror direction and its first capture saturated."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.planning import certificate, evaluate, one_shot, regions, requirements
from cell.cli import main
from cell.task.loader import load_material, load_task
from cell.physics import brdf
from cell.planning.plan import PlannerSettings
from cell.planning.scene import build_scene

TASKS = Path(__file__).resolve().parent.parent / "tasks"
WORLD = {"rho": 0.04, "sigma1": 3.5, "m1": 7.0, "sigma2": 30.0, "m2": 800.0}
STEP_DEG = 6.0
M_MAX = float(np.log(2) / (2 * np.radians(STEP_DEG) ** 2))         # 31.6: what a 6 deg step resolves
# what `cell measure-brdf` wrote for that world at phase 10 and 30 deg, a 6 deg step, ti and te
# up to 50 deg (23 poses; the trial's run, tests/test_goniometer.py measures the same way)
MEASURED = {"name": "milled aluminium (measured)", "source": "cell measure-brdf, step 6 deg", "phase_deg": [10.0, 30.0],
            "rho": [0.0398727, 0.0398349], "sigma1": [3.50778, 3.48964], "m1": [7.00913, 6.96491],
            "sigma2": [0.0, 0.0], "m2": [31.6037, 31.6037], "sigma2_stderr": [np.inf, np.inf],
            "m2_stderr": [np.inf, np.inf],
            "unresolved": {"terms": {"spike": [10.0, 30.0]}, "step_deg": STEP_DEG, "resolvable_m_max": 31.6037}}


def write_material(path, doc):
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def table(phases, spike_unresolved):
    """A material of constant parameters over `phases`, its spike unresolved at those given."""
    n = len(phases)
    doc = {"name": "t", "source": "test", "phase_deg": phases, "rho": [0.04] * n, "sigma1": [3.5] * n,
           "m1": [7.0] * n, "sigma2": [0.0] * n, "m2": [M_MAX] * n}
    if spike_unresolved:
        doc["unresolved"] = {"terms": {"spike": spike_unresolved}, "step_deg": STEP_DEG, "resolvable_m_max": M_MAX}
    return doc


def test_the_unresolved_section_loads_in_radians(tmp_path):
    m = load_material(write_material(tmp_path / "m.yaml", MEASURED))
    assert m.unresolved.terms == {"spike": tuple(np.radians([10.0, 30.0]))}
    assert m.unresolved.step_rad == pytest.approx(np.radians(6.0)) and m.unresolved.resolvable_m_max == 31.6037
    assert "unresolved" not in m.extra and m.scaled(2.0).unresolved == m.unresolved
    assert load_material(write_material(tmp_path / "n.yaml", table([10.0], None))).unresolved is None


def goniometer_directions(beta_deg, alpha_deg):
    """(n, s, v) of the goniometer's geometry: h at beta from the normal, the lamp at beta +
    alpha / 2, the camera at beta - alpha / 2, in the x-z plane."""
    b, a = np.radians(beta_deg), np.radians(alpha_deg)

    def direction(angle):
        return np.stack([np.sin(angle), np.zeros_like(angle), np.cos(angle)], axis=-1)
    return np.array([0.0, 0.0, 1.0]), direction(b + a / 2), direction(b - a / 2)


def test_the_keep_out_is_the_step_about_the_mirror_direction_at_the_unresolved_rows_phases(tmp_path):
    """Table rows 10, 30, 60 deg, the spike unresolved at 10 only: it shapes the parameters at
    phase angles below 30 deg (clamped below 10), not at 40 or 70; there h within 6 deg of n."""
    material = load_material(write_material(tmp_path / "m.yaml", table([10.0, 30.0, 60.0], [10.0])))
    beta = np.array([0.0, -3.0, 5.9, -5.9, 6.1, 10.0, -20.0])
    for alpha, unresolved_there in ((5.0, True), (20.0, True), (29.0, True), (40.0, False), (70.0, False)):
        n, s, v = goniometer_directions(beta, np.full(beta.shape, alpha))
        expected = unresolved_there & (np.abs(beta) < STEP_DEG)
        np.testing.assert_array_equal(brdf.unresolved_spike(n, s, v, material), expected, err_msg=f"{alpha}")
        dominant = brdf.dominant_term_vectors(n, s, v, material)
        judged = brdf.judged_term(dominant, n, s, v, material)
        np.testing.assert_array_equal(judged, np.where(expected, brdf.UNKNOWN, dominant))


def test_the_region_map_marks_the_cone_unknown_and_no_reflection_wants_it(tmp_path):
    """Camera 3 deg off the normal: the map's UNKNOWN cells are exactly the lamp directions whose
    half vector lies within 6 deg of the normal (brute force), elsewhere the map is unchanged;
    `lobe` and `any` refuse them."""
    measured = load_material(write_material(tmp_path / "m.yaml", MEASURED))
    without = load_material(write_material(tmp_path / "w.yaml", {k: v for k, v in MEASURED.items() if k != "unresolved"}))
    grid, frame, normal = regions.SphereGrid(np.radians(2.0)), np.eye(3), np.array([0.0, 0.0, 1.0])
    view = np.array([np.sin(np.radians(3.0)), 0.0, np.cos(np.radians(3.0))])
    judged = regions.dominant_term_map(grid, frame, normal, view, measured)
    plain = regions.dominant_term_map(grid, frame, normal, view, without)
    s = grid.directions(frame)
    h = (s + view) / np.linalg.norm(s + view, axis=-1, keepdims=True)
    cone = (np.degrees(np.arccos(np.clip(h @ normal, -1, 1))) < STEP_DEG) & (s @ normal > 0)
    assert cone.sum() > 20 and np.array_equal(judged == brdf.UNKNOWN, cone)
    assert np.array_equal(judged[~cone], plain[~cone]) and (plain[cone] == brdf.LOBE).all()
    visible = np.ones(judged.shape, bool)
    for reflection in ("lobe", "any"):
        assert not (regions.wanted_region(judged, visible, reflection) & cone).any()
        assert regions.wanted_region(plain, visible, reflection)[cone].all()


def test_the_region_map_of_the_visible_cells_alone_is_the_whole_maps_there(tmp_path):
    """dominant_term_map's `where` (build_maps passes the visibility map): in those cells the
    terms of the whole map, UNKNOWN cone and all, OCCLUDED elsewhere; the wanted region the same."""
    measured = load_material(write_material(tmp_path / "m.yaml", MEASURED))
    grid, frame, normal = regions.SphereGrid(np.radians(2.0)), np.eye(3), np.array([0.0, 0.0, 1.0])
    view = np.array([np.sin(np.radians(3.0)), 0.0, np.cos(np.radians(3.0))])
    whole = regions.dominant_term_map(grid, frame, normal, view, measured)
    s = grid.directions(frame)
    visible = (s[..., 0] < 0.3) & (s[..., 2] > 0.1)         # a hemisphere less a wall on one side
    part = regions.dominant_term_map(grid, frame, normal, view, measured, where=visible)
    assert (whole[visible] == brdf.UNKNOWN).any() and len(np.unique(whole[visible])) >= 3
    np.testing.assert_array_equal(part[visible], whole[visible])
    assert (part[~visible] == brdf.OCCLUDED).all() and part.dtype == whole.dtype
    for reflection in ("lobe", "any", "diffuse"):
        np.testing.assert_array_equal(regions.wanted_region(part, visible, reflection),
                                      regions.wanted_region(whole, visible, reflection))
    # the visible cells' directions are kept per frame and cells: asked again, and for other cells
    # or another frame of the same cells, each map is its own whole map's there
    np.testing.assert_array_equal(regions.dominant_term_map(grid, frame, normal, view, measured, where=visible), part)
    fewer = visible & (s[..., 1] > 0.0)
    np.testing.assert_array_equal(regions.dominant_term_map(grid, frame, normal, view, measured, where=fewer)[fewer],
                                  whole[fewer])
    turned = frame[[1, 2, 0]]
    np.testing.assert_array_equal(regions.dominant_term_map(grid, turned, normal, view, measured, where=visible)[visible],
                                  regions.dominant_term_map(grid, turned, normal, view, measured)[visible])


def hinge(folder, material_doc, reflection="lobe"):
    """The hinge task on a 516 x 388 px sensor (twice the pitch), the world m2 800 (its other
    parameters the material's), noise, black level, quantization, shadows and cone falloff, the
    cell's own collision check (every move of the run clears it), the task's material `material_doc`."""
    doc = yaml.safe_load((TASKS / "hinge.yaml").read_text())
    doc["part"]["mesh"] = str(TASKS / doc["part"]["mesh"])
    doc["part"]["material"] = str(write_material(folder / "material.yaml", material_doc))
    doc["camera"]["sensor"] |= {"width_px": 516, "height_px": 388, "pixel_pitch_m": 9.3e-6}
    doc["requirements"]["reflection"] = reflection
    write_material(folder / "world.yaml", {"name": "the world's metal", "source": "test truth", "phase_deg": [0, 90],
                                           **{k: [v, v] for k, v in WORLD.items()}})
    doc["sim"] = {"seed": 3, "effects": ["shadows", "cone_falloff", "noise", "black_level", "quantization", "collisions"],
                  "truth": {"material": "world.yaml"}}
    path = folder / "task.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def half_vector_angles_deg(task_path, lamp):
    """Each point's angle between its normal and the half vector of its lamp and camera directions,
    on the patch at the certificate's density (thousands of points: every sample, and between)."""
    task = load_task(task_path)
    scene = build_scene(task, certificate.dense_samples(task, build_scene(task, None)))
    s = np.asarray(lamp) - scene.points
    v = scene.camera_position - scene.points
    h = s / np.linalg.norm(s, axis=1, keepdims=True) + v / np.linalg.norm(v, axis=1, keepdims=True)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(h * scene.normals, axis=1), -1, 1)))


def run(task_path):
    """`cell run`: (the planned lamp position, the first capture's report)."""
    out = task_path.parent / "run"
    assert main(["run", str(task_path), "--out", str(out)]) in (0, 1)
    report = json.loads((out / "report.json").read_text())
    return report["plan"]["lamp"]["position_m"], report["iterations"][0]


def test_the_trial_the_lamp_stays_out_of_the_unresolved_spike_and_the_first_capture_is_in_band(tmp_path):
    for name in ("unresolved", "forgotten"):
        (tmp_path / name).mkdir()
    task = hinge(tmp_path / "unresolved", MEASURED)
    lamp, first = run(task)
    assert half_vector_angles_deg(task, lamp).min() > STEP_DEG
    assert first["in_band"] and first["measured_gray"]["saturated"] == 0, first["measured_gray"]

    # the control: the same file without its `unresolved` section plans the lamp into the cone and saturates
    forgotten = hinge(tmp_path / "forgotten", {k: v for k, v in MEASURED.items() if k != "unresolved"})
    lamp, first = run(forgotten)
    assert half_vector_angles_deg(forgotten, lamp).min() < STEP_DEG
    assert not first["in_band"] and first["measured_gray"]["saturated"] > 0
    assert first["measured_gray"]["mean"] > 1.5 * first["predicted_gray"]["mean"]


def test_the_certificate_refuses_a_lamp_in_the_cone_at_every_point_the_search_would(tmp_path):
    """The forgotten file's shot (its lamp in the cone) judged with the unresolved material: the
    dense certificate fails on reflection_region alone (the gray is the same model's), counting
    the points whose half vector lies within the step of their normal, and the search's own
    samples see it too (both read brdf.judged_term)."""
    for name in ("unresolved", "forgotten"):
        (tmp_path / name).mkdir()
    forgotten = hinge(tmp_path / "forgotten", {k: v for k, v in MEASURED.items() if k != "unresolved"})
    shot = one_shot.plan(load_task(forgotten)).shot
    task_path = hinge(tmp_path / "unresolved", MEASURED)
    _, problem = one_shot.search(load_task(task_path), PlannerSettings(refine=False), 1.0, np.zeros((0, 3)),
                                lambda message: None)
    verification, _ = certificate.verify(problem, shot)
    (failing,) = verification.failing
    inside = int(np.sum(half_vector_angles_deg(task_path, shot.lamp_position) < STEP_DEG))
    assert failing.name == "reflection_region" and inside > 0
    # the dense points in the cone, and the specular point the certificate adds (nearest the mirror)
    assert f"{inside + 1} of {verification.points} lit samples see the lamp where an unresolved spike may be" \
        in failing.detail, failing.detail
    c = evaluate.at_exposure(problem, shot.lamp_position, shot.exposure.shutter_s, shot.exposure.f_number)
    assert requirements.wrong_reflection(problem, c)[0].any()


def test_a_spike_wanted_of_a_material_whose_spike_is_unresolved_is_infeasible_and_says_re_measure(tmp_path, capsys):
    task = hinge(tmp_path, MEASURED, reflection="spike")
    assert main(["plan", str(task), "--out", str(tmp_path / "plan")]) == 1
    err = capsys.readouterr().err
    assert "cell plan: infeasible: reflection type fails: the spike was not resolved: " in err, err
    assert "step 6 deg" in err and "re-measure the material with a finer calibration.goniometer.step_deg" in err
