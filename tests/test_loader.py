"""The loader: the shipped tasks load in SI units, and every kind of broken input is one
clear line naming the file and the key, with exit code 2."""
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell import cli

from cell.task import loader, schema
from cell.cli import check
from cell.core.errors import TaskError
from cell.task.types import SimConfig

ROOT = Path(__file__).resolve().parents[1]
TASKS = ROOT / "tasks"
HINGE = TASKS / "hinge.yaml"
CONROD = TASKS / "conrod.yaml"
HINGE_TEXT = HINGE.read_text()
MATERIAL = "materials/milled_aluminium.yaml"
HINGE_SENSOR = yaml.safe_load(HINGE_TEXT)["camera"]["sensor"]


# --- helpers that write (broken) variants of the hinge task into a folder ---

def write_task(folder, edit=None):
    """Copy hinge.yaml and what it references into folder, apply edit(task, folder) and write
    the task; an edit returning text writes that text instead. Returns the task's path."""
    shutil.copytree(TASKS / "parts", folder / "parts")
    shutil.copytree(TASKS / "materials", folder / "materials")
    task = schema.read_yaml(HINGE)
    text = edit(task, folder) if edit else None
    path = folder / "task.yaml"
    path.write_text(text if isinstance(text, str) else yaml.safe_dump(task, sort_keys=False))
    return path


def _parent(task, dotted):
    *keys, last = dotted.split(".")
    for key in keys:
        task = task[key]
    return task, last


def put(dotted, value):
    """Edit: set task[dotted] = value."""
    def edit(task, folder):
        parent, last = _parent(task, dotted)
        parent[last] = value
    return edit


def drop(dotted):
    """Edit: delete task[dotted]."""
    def edit(task, folder):
        parent, last = _parent(task, dotted)
        del parent[last]
    return edit


def rename(dotted, new):
    """Edit: move task[dotted] to the sibling key `new`, keeping its value."""
    def edit(task, folder):
        parent, last = _parent(task, dotted)
        parent[new] = parent.pop(last)
    return edit


def both(*edits):
    """Edit: the edits one after the other."""
    def edit(task, folder):
        for e in edits:
            e(task, folder)
    return edit


def text(replace=None, content=None):
    """Edit: the task file's text, either given whole or hinge.yaml with (old, new) replaced."""
    def edit(task, folder):
        if content is not None:
            return content
        assert replace[0] in HINGE_TEXT
        return HINGE_TEXT.replace(*replace)
    return edit


def material(key, value):
    """Edit: set material[key] = value (None deletes) in the task's material file."""
    def edit(task, folder):
        path = folder / MATERIAL
        data = schema.read_yaml(path)
        if value is None:
            del data[key]
        else:
            data[key] = value
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    return edit


def mesh_file(content):
    """Edit: write bytes as parts/bad.stl and point the task at it."""
    def edit(task, folder):
        (folder / "parts" / "bad.stl").write_bytes(content)
        task["part"]["mesh"] = "parts/bad.stl"
    return edit


def hand_eye_file(content, **arm):
    """Edit: write content as hand-eye.yaml beside the task, point cell.arm.hand_eye at it and set
    the other cell.arm keys given."""
    def edit(task, folder):
        (folder / "hand-eye.yaml").write_text(content)
        task.setdefault("cell", {})["arm"] = {"hand_eye": "hand-eye.yaml", **arm}
    return edit


def inverted_mesh(task, folder):
    """Edit: the hinge's mesh with every triangle's winding reversed (normals pointing in)."""
    import trimesh
    mesh = trimesh.load(folder / "parts" / "hinge.stl")
    mesh.invert()
    mesh.export(folder / "parts" / "inside_out.stl")
    task["part"]["mesh"] = "parts/inside_out.stl"


def ascii_stl(*triangles):
    facets = "".join("facet normal 0 0 1\nouter loop\n" + "".join(f"vertex {v}\n" for v in t)
                     + "endloop\nendfacet\n" for t in triangles)
    return f"solid t\n{facets}endsolid t\n".encode()


# --- the shipped tasks ---

def test_hinge_loads_in_si_units():
    task = loader.load_task(HINGE)
    assert task.lamp.power_w == 0.23043                      # power_mw: 230.43
    assert task.camera.shutter_range_s == (1e-5, 0.02)       # shutter_range_ms: [0.01, 20.0]
    assert task.lamp.cone_angle_rad == pytest.approx(math.radians(12.0))
    assert task.lamp.rig.tilt_range_rad == pytest.approx((math.radians(5.0), math.radians(85.0)))
    assert task.camera.sensor.camera_constant == 1.5e16
    assert task.requirements.gray_band == (100.0, 125.0)
    assert task.requirements.depth_of_field_m == 0.021
    assert np.linalg.norm(task.camera.view_direction) == pytest.approx(1.0)
    np.testing.assert_allclose(task.lamp.profile[8], [math.radians(6.0), 0.5])    # half at the nominal edge


def test_hinge_feature_snaps_to_the_leaf_with_normal_up():
    task = loader.load_task(HINGE)
    np.testing.assert_allclose(task.feature.center_m, [0.006, 0.0, 0.004], atol=1e-12)
    np.testing.assert_allclose(task.feature.normal, [0.0, 0.0, 1.0], atol=1e-9)


def test_hinge_mesh_is_in_metres_and_material_in_radians():
    task = loader.load_task(HINGE)
    np.testing.assert_allclose(task.part.mesh.extents, [0.070, 0.040, 0.012], atol=1e-9)
    np.testing.assert_allclose(task.frames.T_cell_part, np.eye(4))
    assert task.part.material.name == "milled aluminium"
    assert task.part.material.phase_rad[-1] == pytest.approx(math.radians(80.0))


def test_conrod_loads():
    task = loader.load_task(CONROD)
    assert task.requirements.reflection == "diffuse"
    assert task.sim.effects == ("shadows", "cone_falloff", "quantization", "collisions")
    np.testing.assert_allclose(task.feature.normal, [0.0, 0.0, 1.0], atol=1e-9)


def test_every_unit_spelling_gives_the_same_si_value(tmp_path):
    def edit(task, folder):
        rename("camera.distance_m", "distance_mm")(task, folder)
        task["camera"]["distance_mm"] = 500.0
        rename("camera.sensor.pixel_pitch_m", "pixel_pitch_um")(task, folder)
        task["camera"]["sensor"]["pixel_pitch_um"] = 4.65
        rename("lamp.power_mw", "power_w")(task, folder)
        task["lamp"]["power_w"] = 0.23043
        rename("lamp.cone_angle_deg", "cone_angle_rad")(task, folder)
        task["lamp"]["cone_angle_rad"] = math.radians(12.0)
    task = loader.load_task(write_task(tmp_path, edit))
    hinge = loader.load_task(HINGE)
    assert task.camera.distance_m == hinge.camera.distance_m == 0.5
    assert task.camera.sensor.pixel_pitch_m == pytest.approx(4.65e-6, rel=1e-15)
    assert task.lamp.power_w == hinge.lamp.power_w
    assert task.lamp.cone_angle_rad == pytest.approx(hinge.lamp.cone_angle_rad, rel=1e-15)


def test_a_lamp_profile_loads_in_radians_in_either_unit(tmp_path):
    written = {"off_axis_deg": [0.0, 4.0, 6.0, 8.0], "relative": [1.0, 0.9, 0.5, 0.0]}
    task = loader.load_task(write_task(tmp_path / "deg", put("lamp.profile", written)))
    np.testing.assert_array_equal(task.lamp.profile, np.column_stack([np.radians(written["off_axis_deg"]),
                                                                      written["relative"]]))
    in_rad = {"off_axis_rad": np.radians(written["off_axis_deg"]).tolist(), "relative": written["relative"]}
    again = loader.load_task(write_task(tmp_path / "rad", put("lamp.profile", in_rad)))
    np.testing.assert_allclose(again.lamp.profile, task.lamp.profile, rtol=1e-15)
    assert loader.load_task(write_task(tmp_path / "none", put("lamp.profile", None))).lamp.profile is None


def test_optional_sections_take_their_defaults(tmp_path):
    def edit(task, folder):
        del task["sim"], task["cell"], task["requirements"]["depth_of_field_m"]
    task = loader.load_task(write_task(tmp_path, edit))
    assert task.sim == SimConfig()
    assert task.cell.backend == "sim" and task.cell.devices.given == ()
    assert task.cell.devices.arm.host is None and task.cell.devices.pan_tilt.baud == 57600
    assert task.requirements.depth_of_field_m == 0.0


def test_the_worlds_material_loads_beside_the_tasks_and_vectors_in_si(tmp_path):
    """sim.truth.material is read relative to the task file, like part.material, and the task
    keeps its own; the pose errors arrive in metres and radians."""
    def edit(task, folder):
        task["sim"]["truth"].update({"material": "materials/gray_cast_iron.yaml", "part_offset_mm": [0, 2, 0],
                                     "camera_rpy_deg": [0.25, 0, 0], "lamp_radius_error_mm": 20})
    task = loader.load_task(write_task(tmp_path, edit))
    truth = task.sim.truth
    assert truth.material.name == loader.load_material(TASKS / "materials/gray_cast_iron.yaml").name
    assert task.part.material.name == loader.load_material(TASKS / MATERIAL).name != truth.material.name
    assert truth.part_offset_m == (0.0, 0.002, 0.0) and truth.lamp_radius_error_m == pytest.approx(0.02)
    assert truth.camera_rpy_rad == pytest.approx((math.radians(0.25), 0.0, 0.0))
    assert loader.load_task(HINGE).loop.albedo_scale_range == (0.1, 10.0)
    assert loader.load_task(HINGE).loop.registration_limit_m is None


def test_an_empty_optional_section_takes_its_defaults(tmp_path):
    without_settings = HINGE_TEXT.split("cell:")[0] + "cell:\nsim:\n"
    task = loader.load_task(write_task(tmp_path, text(content=without_settings)))
    assert task.sim == SimConfig() and task.cell.backend == "sim"


def test_device_settings_are_checked_and_typed_at_load(tmp_path):
    arm = {"host": "127.0.0.1", "speed_m_s": 0.1}
    task = loader.load_task(write_task(tmp_path, put("cell.arm", arm)))
    devices = task.cell.devices
    assert devices.given == ("arm",) and devices.arm.host == "127.0.0.1" and devices.arm.speed_m_s == 0.1
    assert devices.pan_tilt.baud == 57600 and devices.camera.source == 0     # the defaults
    assert "backend sim, arm settings" in check.summarize(task)


def test_fitter_output_is_kept_in_material_extra(tmp_path):
    def edit(task, folder):
        material("rho_stderr", [0.001] * 7)(task, folder)
        material("m2_stderr", [float("inf")] * 7)(task, folder)
        material("rms_residual", [0.002] * 7)(task, folder)
        material("unidentifiable", {"spike": [60, 80]})(task, folder)
    m = loader.load_task(write_task(tmp_path, edit)).part.material
    assert set(m.extra) == {"rho_stderr", "m2_stderr", "rms_residual", "unidentifiable"}
    np.testing.assert_allclose(m.extra["rho_stderr"], 0.001)
    assert m.extra["unidentifiable"] == {"spike": [60, 80]}


def test_summary_names_what_a_person_checks():
    summary = check.summarize(loader.load_task(HINGE))
    for text in ("Aluminium hinge", "hinge.stl", "70.0 x 40.0 x 12.0 mm", "780 triangles",
                 "[6.0, 0.0, 4.0] mm", "113.1 mm^2", "milled aluminium", "0.01..20 ms",
                 "230.43 mW", "tilt 5..85 deg", "backend sim", "quantization"):
        assert text in summary


@pytest.mark.parametrize("task", [HINGE, CONROD], ids=["hinge", "conrod"])
def test_cell_check_passes_on_the_shipped_tasks(task, capsys):
    assert cli.main(["check", str(task)]) == 0
    out, err = capsys.readouterr()
    assert loader.load_task(task).name in out and err == ""


def test_cell_check_runs_as_a_program_without_warp():
    done = subprocess.run([sys.executable, "-m", "cell", "check", "tasks/hinge.yaml"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "Aluminium hinge" in done.stdout
    code = "import sys, cell.task.loader; print('warp' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip() == "False"


# --- broken input: (edit, file the error names, key path it names, optional text) ---

BROKEN = [
    pytest.param(text(content=""), "task.yaml", "", "empty file", id="empty-file"),
    pytest.param(text(content="- a\n- b\n"), "task.yaml", "", "mapping", id="top-level-list"),
    pytest.param(text(("  distance_m: 0.50", "  distance_m: [0.50")), "task.yaml:", "", "YAML",
                 id="yaml-syntax-error"),
    pytest.param(text(("  samples: 64", "  samples: 64\n  samples: 32")), "task.yaml:", "",
                 "duplicate key", id="yaml-duplicate-key"),
    pytest.param(drop("lamp.power_mw"), "task.yaml", "lamp.power_w", "required", id="missing-key"),
    pytest.param(drop("camera"), "task.yaml", "camera", "required", id="missing-section"),
    pytest.param(rename("camera.distance_m", "distanse_m"), "task.yaml", "camera.distanse_m",
                 "did you mean 'distance_m'", id="unknown-key"),
    pytest.param(put("cell.robot", {"host": "127.0.0.1"}), "task.yaml", "cell.robot", "unknown",
                 id="unknown-cell-key"),
    pytest.param(put("camera.distance_m", "far"), "task.yaml", "camera.distance_m", "'far'",
                 id="string-for-number"),
    pytest.param(put("camera.distance_m", True), "task.yaml", "camera.distance_m", "True",
                 id="bool-for-number"),
    pytest.param(put("camera.lens.f_number_range", 2.8), "task.yaml", "camera.lens.f_number_range",
                 "pair", id="scalar-for-list"),
    pytest.param(put("camera.view_direction", [0.0, 1.0]), "task.yaml", "camera.view_direction",
                 "3-vector", id="list-length"),
    pytest.param(put("lamp.rig.pivot_m", [0.0, "x", 0.0]), "task.yaml", "lamp.rig.pivot_m[1]",
                 "a number", id="string-in-list"),
    pytest.param(put("feature.radius_m", float("nan")), "task.yaml", "feature.radius_m", "nan", id="nan"),
    pytest.param(put("camera.sensor.camera_constant", float("inf")), "task.yaml",
                 "camera.sensor.camera_constant", "finite", id="inf"),
    pytest.param(put("camera.distance_m", 10**400), "task.yaml", "camera.distance_m", "finite",
                 id="huge-integer"),
    pytest.param(put("part.position_m", [0.0, float("nan"), 0.0]), "task.yaml", "part.position_m[1]",
                 "finite", id="nan-in-list"),
    pytest.param(put("camera.lens.f_number_range", [16.0, 1.4]), "task.yaml", "camera.lens.f_number_range",
                 "found [16.0, 1.4], expected an ascending pair of f-numbers of at least 0.5", id="reversed-range"),
    pytest.param(put("camera.shutter_range_ms", [20.0, 0.01]), "task.yaml", "camera.shutter_range_ms",
                 "ascending", id="reversed-shutter-ms"),
    pytest.param(put("lamp.power_mw", -230.43), "task.yaml", "lamp.power_mw", "positive",
                 id="negative-power"),
    pytest.param(put("lamp.cone_angle_deg", 0.0), "task.yaml", "lamp.cone_angle_deg", "(0, 180)",
                 id="zero-cone-angle"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0]}), "task.yaml", "lamp.profile.relative",
                 "found nothing, expected a list with one value per off-axis angle (required in a profile)",
                 id="profile-without-relative"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0], "relative": [1.0, 0.5, 0.0]}), "task.yaml",
                 "lamp.profile.relative", "found 3 values, expected 2, one per off_axis_deg entry",
                 id="profile-unequal-lengths"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0, 5.0], "relative": [1.0, 0.5, 0.0]}),
                 "task.yaml", "lamp.profile.off_axis_deg", "strictly ascending off-axis angles from 0",
                 id="profile-not-ascending"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [1.0, 6.0], "relative": [1.0, 0.0]}), "task.yaml",
                 "lamp.profile.off_axis_deg", "found [1.0, 6.0], expected strictly ascending off-axis angles from 0",
                 id="profile-not-from-0"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0], "relative": [1.0]}), "task.yaml",
                 "lamp.profile.off_axis_deg", "at least two off-axis angles", id="profile-one-angle"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0], "relative": [1.0, 1.5]}), "task.yaml",
                 "lamp.profile.relative[1]", "found 1.5, expected a number in [0, 1]", id="profile-above-1"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0], "relative": [0.9, 0.5]}), "task.yaml",
                 "lamp.profile.relative[0]", "found 0.9, expected 1 (the profile is relative to the axis)",
                 id="profile-not-1-on-the-axis"),
    pytest.param(put("lamp.cone_angle_deg", 1.0), "task.yaml", "lamp.cone_angle_deg",
                 "found 1 deg, expected 12 deg, twice the angle where lamp.profile falls to half its axis intensity",
                 id="cone-far-narrower-than-its-profile"),
    pytest.param(put("lamp.cone_angle_deg", 18.0), "task.yaml", "lamp.cone_angle_deg",
                 "found 18 deg, expected 12 deg", id="cone-far-wider-than-its-profile"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 2.0], "relative": [1.0, 1.0]}), "task.yaml",
                 "lamp.cone_angle_deg", "found 12 deg, expected 4 deg", id="profile-ends-well-inside-the-cone"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 200.0], "relative": [1.0, 0.0]}), "task.yaml",
                 "lamp.profile.off_axis_deg[1]", "within [0, 180] deg", id="profile-beyond-180"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0], "relativ": [1.0, 0.0]}), "task.yaml",
                 "lamp.profile.relativ", "did you mean 'relative'", id="profile-unknown-key"),
    pytest.param(put("lamp.profile", {"off_axis_deg": [0.0, 6.0], "relative": [1.0, float("nan")]}),
                 "task.yaml", "lamp.profile.relative[1]", "finite", id="profile-nan"),
    pytest.param(put("lamp.rig.tilt_range_deg", [5.0, 95.0]), "task.yaml", "lamp.rig.tilt_range_deg",
                 "[-90, 90]", id="tilt-beyond-90"),
    pytest.param(put("lamp.rig.radius_range_m", [0.0, 0.6]), "task.yaml", "lamp.rig.radius_range_m",
                 "positive", id="zero-radius"),
    pytest.param(put("camera.distance_mm", 500.0), "task.yaml", "camera.distance_mm", "one unit",
                 id="two-units"),
    pytest.param(rename("camera.distance_m", "distance_cm"), "task.yaml", "camera.distance_cm",
                 "length unit", id="unknown-unit"),
    pytest.param(rename("lamp.power_mw", "power_ms"), "task.yaml", "lamp.power_ms", "power unit",
                 id="unit-of-wrong-quantity"),
    pytest.param(put("requirements.reflection", "glossy"), "task.yaml", "requirements.reflection",
                 "diffuse | lobe | spike | any", id="bad-reflection"),
    pytest.param(put("cell.backend", "robot"), "task.yaml", "cell.backend", "sim | hw", id="bad-backend"),
    pytest.param(put("cell.arm", "127.0.0.1"), "task.yaml", "cell.arm", "mapping", id="device-not-mapping"),
    pytest.param(put("cell.arm", {"sped_m_s": 0.1}), "task.yaml", "cell.arm.sped_m_s",
                 "an unknown key, expected one of host,", id="device-unknown-key"),
    pytest.param(put("cell.arm", {"speed_m_s": float("nan")}), "task.yaml", "cell.arm.speed_m_s",
                 "found nan, expected a finite number", id="device-nan"),
    pytest.param(put("cell.arm", {"speed_m_s": 5}), "task.yaml", "cell.arm.speed_m_s",
                 "found 5, expected a speed in (0, 0.25] m/s", id="device-speed-over-limit"),
    pytest.param(put("cell.arm", {"workspace_min_m": [0.7, 0.6, 0.1]}), "task.yaml", "cell.arm.workspace_max_m",
                 "found [0.6, 0.6, 1.0], expected above workspace_min_m [0.7, 0.6, 0.1] on every axis",
                 id="device-workspace-min-above-max"),
    pytest.param(put("cell.arm", {"hand_eye_position_mm": [0, 0, 50], "hand_eye_position_m": [0, 0, 0.05]}),
                 "task.yaml", "cell.arm.hand_eye_position_m", "one unit", id="device-two-units"),
    pytest.param(hand_eye_file("cell: {arm: {hand_eye_position_m: [0, 0, 0.05]}}\n"), "hand-eye.yaml",
                 "cell.arm.hand_eye_rpy_deg", "found nothing, expected a 3-vector [x, y, z] (required key)",
                 id="hand-eye-file-without-its-rotation"),
    pytest.param(hand_eye_file("cell: {arm: {hand_eye_position_m: [0, 0, 0.05], hand_eye_rpy_deg: [0, 0, 0], "
                               "host: 10.0.0.1}}\n"), "hand-eye.yaml", "cell.arm.host",
                 "an unknown key, expected one of hand_eye_position_m, hand_eye_rpy_deg", id="hand-eye-file-other-key"),
    pytest.param(hand_eye_file("hand_eye_position_m: [0, 0, 0.05]\n"), "hand-eye.yaml", "hand_eye_position_m",
                 "an unknown key, expected one of cell", id="hand-eye-file-keys-not-in-their-place"),
    pytest.param(hand_eye_file(""), "hand-eye.yaml", "", "an empty file", id="hand-eye-file-empty"),
    pytest.param(hand_eye_file("cell: {arm: {hand_eye_position_m: [0, 0, 0.05], hand_eye_rpy_deg: [0, 0, 0]}}\n",
                               hand_eye_rpy_deg=[0, 0, 1]), "task.yaml", "cell.arm.hand_eye_rpy_deg",
                 "found a value beside hand_eye 'hand-eye.yaml', expected the hand-eye in one place",
                 id="hand-eye-file-and-keys"),
    pytest.param(put("cell.arm", {"hand_eye": "nowhere.yaml"}), "task.yaml", "cell.arm.hand_eye",
                 "an unreadable file (no such file or directory), expected an existing, readable YAML file, "
                 "relative to the task file", id="hand-eye-file-missing"),
    pytest.param(put("cell.arm", {"hand_eye": [0, 0, 0.05]}), "task.yaml", "cell.arm.hand_eye",
                 "expected the name of a hand-eye file", id="hand-eye-file-not-a-name"),
    pytest.param(put("cell.pan_tilt", {"baud": 12345}), "task.yaml", "cell.pan_tilt.baud",
                 "one of the SDK's rates", id="device-baud"),
    pytest.param(put("cell.pan_tilt", {"pan_id": 2}), "task.yaml", "cell.pan_tilt.tilt_id",
                 "distinct pan, tilt and radius ids", id="device-ids-not-distinct"),
    pytest.param(put("cell.pan_tilt", {"radius_ticks": [4000, 100]}), "task.yaml", "cell.pan_tilt.radius_ticks",
                 "ascending pair of ticks", id="device-radius-ticks"),
    pytest.param(put("cell.camera", {"source": -1}), "task.yaml", "cell.camera.source", "a camera index",
                 id="device-camera-source"),
    pytest.param(put("part.mesh_unit", "inch"), "task.yaml", "part.mesh_unit", "m | mm", id="bad-mesh-unit"),
    pytest.param(put("lamp.rig.radius_axis", "motor"), "task.yaml", "lamp.rig.radius_axis", "manual | servo",
                 id="bad-radius-axis"),
    pytest.param(put("sim.effects", ["shadows", "interreflection"]), "task.yaml", "sim.effects[1]",
                 "not modelled", id="interreflection"),
    pytest.param(put("sim.effects", ["shadows", "bloom"]), "task.yaml", "sim.effects[1]", "cone_falloff",
                 id="unknown-effect"),
    pytest.param(put("sim.effects", ["noise", "noise"]), "task.yaml", "sim.effects[1]", "once",
                 id="duplicate-effect"),
    pytest.param(put("sim.truth.albedo_scale", 0.0), "task.yaml", "sim.truth.albedo_scale", "positive",
                 id="zero-albedo-scale"),
    pytest.param(put("sim.truth.lamp_direction_error_deg", -1.0), "task.yaml",
                 "sim.truth.lamp_direction_error_deg", "within [0, 90] deg", id="negative-lamp-error"),
    pytest.param(put("sim.seed", 1.5), "task.yaml", "sim.seed", "integer", id="float-seed"),
    pytest.param(put("sim.truth.material", "materials/missing.yaml"), "task.yaml", "sim.truth.material",
                 "missing.yaml", id="truth-material-missing"),
    pytest.param(both(material("m2", [5.0] * 7), put("sim.truth.material", MATERIAL)), MATERIAL, "m2[0]",
                 "m2 > m1", id="truth-material-checked-like-the-tasks"),
    pytest.param(put("sim.truth.part_offset_m", [0.0, 0.001]), "task.yaml", "sim.truth.part_offset_m",
                 "a 3-vector", id="truth-part-offset-two-numbers"),
    pytest.param(put("sim.truth.part_rpy_deg", [0.0, "x", 0.0]), "task.yaml", "sim.truth.part_rpy_deg[1]",
                 "a number", id="truth-part-rpy-text"),
    pytest.param(put("sim.truth.camera_offset_m", [0.0, float("inf"), 0.0]), "task.yaml",
                 "sim.truth.camera_offset_m[1]", "finite", id="truth-camera-offset-inf"),
    pytest.param(put("sim.truth.camera_rpy_deg", 0.25), "task.yaml", "sim.truth.camera_rpy_deg", "a 3-vector",
                 id="truth-camera-rpy-scalar"),
    pytest.param(put("sim.truth.lamp_radius_error_m", -0.2), "task.yaml", "sim.truth.lamp_radius_error_m",
                 "more than -0.15 m", id="truth-lamp-behind-the-pivot"),
    pytest.param(put("camera.sensor.black_level", -1), "task.yaml", "camera.sensor.black_level", ">= 0",
                 id="negative-black-level"),
    pytest.param(put("camera.sensor.black_level", 125), "task.yaml", "camera.sensor.black_level",
                 "below the band's top 125", id="black-level-at-the-band-top"),
    pytest.param(put("loop", {"albedo_scale_range": [2.0, 10.0]}), "task.yaml", "loop.albedo_scale_range",
                 "holding 1", id="albedo-range-without-1"),
    pytest.param(put("loop", {"albedo_scale_range": [0.0, 10.0]}), "task.yaml", "loop.albedo_scale_range",
                 "positive scales", id="albedo-range-from-0"),
    pytest.param(put("loop", {"registration_limit_m": 0.0}), "task.yaml", "loop.registration_limit_m",
                 "a positive distance", id="registration-limit-0"),
    pytest.param(put("loop", {"registration_limit_mm": "far"}), "task.yaml", "loop.registration_limit_mm",
                 "a positive distance", id="registration-limit-text"),
    pytest.param(put("requirements.gray_band", [100, 300]), "task.yaml", "requirements.gray_band[1]",
                 "[0, 255]", id="gray-band-beyond-bit-depth"),
    pytest.param(put("requirements.gray_band", [125, 100]), "task.yaml", "requirements.gray_band",
                 "ascending", id="reversed-gray-band"),
    pytest.param(put("camera.sensor.bit_depth", 0), "task.yaml", "camera.sensor.bit_depth", "1..16",
                 id="bit-depth-0"),
    pytest.param(put("feature.samples", 0), "task.yaml", "feature.samples", "integer", id="zero-samples"),
    pytest.param(put("camera.view_direction", [0.0, 0.0, 0.0]), "task.yaml", "camera.view_direction",
                 "non-zero", id="zero-view-direction"),
    pytest.param(put("requirements.depth_of_field_m", -0.01), "task.yaml", "requirements.depth_of_field_m",
                 ">= 0", id="negative-depth-of-field"),
    pytest.param(put("part.mesh", "parts/missing.stl"), "task.yaml", "part.mesh", "no such file",
                 id="missing-mesh"),
    pytest.param(mesh_file(bytes(range(256)) * 3), "task.yaml", "part.mesh", "cannot read",
                 id="garbage-mesh"),
    pytest.param(mesh_file(b"solid empty\nendsolid empty\n"), "task.yaml", "part.mesh", "0 triangles",
                 id="empty-mesh"),
    pytest.param(mesh_file(ascii_stl(("0 0 0", "1 0 0", "nan 1 0"), ("0 0 0", "1 0 0", "0 1 0"))),
                 "task.yaml", "part.mesh", "NaN", id="nan-vertex-mesh"),
    pytest.param(put("feature.center_m", [0.006, 0.0, 0.009]), "task.yaml", "feature.center_m",
                 "5.0 mm from the surface", id="feature-off-surface"),
    pytest.param(put("part.material", "materials/missing.yaml"), "task.yaml", "part.material",
                 "no such file", id="missing-material"),
    pytest.param(material("rho", [0.03] * 6), MATERIAL, "rho", "6 values", id="material-unequal-lengths"),
    pytest.param(material("m2", [400.0] * 6 + [5.0]), MATERIAL, "m2[6]", "m1", id="material-m2-below-m1"),
    pytest.param(material("rho", [0.03] * 6 + [0.0]), MATERIAL, "rho[6]", "positive", id="material-rho-zero"),
    pytest.param(material("phase_deg", [0, 10, 30, 20, 40, 60, 80]), MATERIAL, "phase_deg", "ascending",
                 id="material-phase-not-ascending"),
    pytest.param(material("phase_deg", [0, 10, 20, 30, 40, 60, 190]), MATERIAL, "phase_deg[6]", "180",
                 id="material-phase-beyond-180"),
    pytest.param(material("sigma2", None), MATERIAL, "sigma2", "required", id="material-missing-key"),
    pytest.param(material("sigma_1", [4.0] * 7), MATERIAL, "sigma_1", "did you mean 'sigma1'",
                 id="material-unknown-key"),
    pytest.param(material("sigma1", [4.0] * 6 + [float("nan")]), MATERIAL, "sigma1[6]", "finite",
                 id="material-nan"),
    pytest.param(material("unresolved", {"terms": {"glint": [10]}, "step_deg": 6.0, "resolvable_m_max": 31.6}),
                 MATERIAL, "unresolved.terms.glint", "one of lobe, spike", id="unresolved-unknown-term"),
    pytest.param(material("unresolved", {"terms": {"spike": [10, 15]}, "step_deg": 6.0, "resolvable_m_max": 31.6}),
                 MATERIAL, "unresolved.terms.spike[1]", "one of the table's phase_deg [0, 10, 20",
                 id="unresolved-phase-not-in-the-table"),
    pytest.param(material("unresolved", {"terms": {"spike": [10]}, "step_deg": 0, "resolvable_m_max": 31.6}),
                 MATERIAL, "unresolved.step_deg", "a positive angle", id="unresolved-step-zero"),
    pytest.param(material("unresolved", {"terms": {"spike": [10]}, "resolvable_m_max": 31.6}),
                 MATERIAL, "unresolved.step_deg", "required", id="unresolved-step-missing"),
    pytest.param(material("unresolved", {"terms": {}, "step_deg": 6.0, "resolvable_m_max": 31.6}),
                 MATERIAL, "unresolved.terms", "lobe: [phase angles] and/or spike", id="unresolved-no-term"),
    pytest.param(material("unresolved", "spike"), MATERIAL, "unresolved", "a mapping of keys",
                 id="unresolved-not-a-mapping"),
    # physically implausible, though every number is valid on its own
    pytest.param(put("camera.lens.f_number_range", [0.1, 0.4]), "task.yaml", "camera.lens.f_number_range",
                 "at least 0.5", id="f-number-below-0.5"),
    pytest.param(put("sim.truth.lamp_direction_error_deg", 1000), "task.yaml",
                 "sim.truth.lamp_direction_error_deg", "within [0, 90] deg", id="lamp-error-1000-deg"),
    pytest.param(put("lamp.rig.pivot_m", [0.0, 0.0, 0.002]), "task.yaml", "lamp.rig.pivot_m",
                 "inside the part", id="pivot-inside-the-part"),
    pytest.param(both(put("camera.view_direction", [-1.0, 0.0, -0.05]), put("camera.distance_m", 0.03)),
                 "task.yaml", "camera.distance_m", "inside the part", id="camera-inside-the-part"),
    pytest.param(put("camera.sensor.width_px", 100_000), "task.yaml", "camera.sensor.width_px",
                 "1..65536", id="sensor-side-too-large"),
    pytest.param(put("camera.sensor", {**HINGE_SENSOR, "width_px": 60_000, "height_px": 60_000}), "task.yaml",
                 "camera.sensor", "at most 160 Mpx", id="sensor-frame-too-large"),
    pytest.param(put("camera.distance_m", 0.02), "task.yaml", "camera.distance_m", "more than the focal length",
                 id="camera-within-focal-length"),
    pytest.param(put("camera.lens.focal_length_m", 1e308), "task.yaml", "camera.lens.focal_length_m",
                 "1 mm to 1 m, as an inspection cell has", id="1e308-is-a-finite-number-no-lens-has"),
    pytest.param(mesh_file(ascii_stl(["0 0 0", "1 0 0", "2 0 0"], ["2 0 0", "3 0 0", "4 0 0"])), "task.yaml",
                 "part.mesh", "zero area", id="mesh-on-a-line"),
    pytest.param(put("part.mesh", "parts"), "task.yaml", "part.mesh", "a folder", id="mesh-is-a-folder"),
    pytest.param(inverted_mesh, "task.yaml", "part.mesh", "triangles face inward", id="mesh-inside-out"),
    pytest.param(put("part.material", "materials"), "task.yaml", "part.material", "a folder",
                 id="material-is-a-folder"),
    # YAML tricks
    pytest.param(text(content="a: &a [1, 2, 3, 4, 5, 6, 7, 8, 9]\n" + "".join(
        f"{k}: &{k} [{', '.join(['*' + p] * 9)}]\n" for p, k in zip("abcdefgh", "bcdefghi"))), "task.yaml:", "",
        "aliases expanded", id="alias-bomb"),
    pytest.param(text(content="name: " + "[" * 50 + "]" * 50 + "\n"), "task.yaml:", "",
                 "nesting deeper than 32 levels", id="nested-50-deep"),
    pytest.param(text(content="name: " + "[" * 10_000 + "]" * 10_000 + "\n"), "task.yaml:", "",
                 "nesting depth", id="nested-10000-deep"),
    pytest.param(text(content="name: !!python/object/apply:os.system ['true']\n"), "task.yaml:", "",
                 "no tags", id="unsupported-yaml-tag"),
    pytest.param(text(content="name: '" + "x" * 100_000 + "\n"), "task.yaml", "", "YAML syntax error",
                 id="unterminated-quote"),
]


@pytest.mark.parametrize("edit, file, key, text", BROKEN)
def test_broken_input_is_one_line_naming_file_and_key(tmp_path, capsys, edit, file, key, text):
    path = write_task(tmp_path, edit)
    assert cli.main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert str(tmp_path / file) in err
    assert f": {key}: found" in err if key else ": found" in err
    assert text in err
    assert "np." not in err and "array(" not in err          # values as the user wrote them
    assert len(err) < 600                                     # no value is written out whole


def test_values_in_errors_are_plain_numbers_never_numpy_reprs():
    assert schema.show(np.float64(0.6)) == "0.6"
    assert schema.show(np.array([0.6, 0.6, 0.1])) == "[0.6, 0.6, 0.1]"
    assert schema.show([np.float64(0.6), np.int64(3)]) == "[0.6, 3]"
    assert schema.show("far") == "'far'" and schema.show(None) == "null"


def test_loader_raises_task_error_with_the_key_path(tmp_path):
    with pytest.raises(TaskError) as caught:
        loader.load_task(write_task(tmp_path, put("requirements.gray_band", [100, 300])))
    assert caught.value.key == "requirements.gray_band[1]"
    assert caught.value.file == str(tmp_path / "task.yaml")


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = write_task(tmp_path, text(("  distance_m: 0.50", "  distance_m: [0.50")))
    with pytest.raises(TaskError) as caught:
        loader.load_task(path)
    line = HINGE_TEXT.splitlines().index("  distance_m: 0.50") + 1
    assert caught.value.file.startswith(f"{path}:")
    assert int(caught.value.file.rsplit(":", 1)[1]) >= line


def test_a_missing_task_file_is_one_line(tmp_path, capsys):
    assert cli.main(["check", str(tmp_path / "nope.yaml")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "nope.yaml" in err and "Traceback" not in err


def test_rate_keys_are_not_unit_variants(tmp_path):
    """`speed_m_ms` is not `speed_m` in milliseconds: a rate key is only accepted as written."""
    with pytest.raises(TaskError) as err:
        loader.load_task(write_task(tmp_path / "ms", put("cell.arm", {"speed_m_ms": 0.1})))
    assert "speed_m_ms" in str(err.value) and "speed_m_s" in str(err.value)
    task = loader.load_task(write_task(tmp_path / "s", put("cell.arm", {"speed_m_s": 0.1})))
    assert task.cell.devices.arm.speed_m_s == 0.1
