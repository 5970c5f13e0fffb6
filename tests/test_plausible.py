"""Plausibility at load (issue 29, item 1): a unit slip on any physical key of the examples (a value
written in m that was meant in mm, and the reverse) is refused with exit 2 naming the key and,
where a range refuses it, the unit that was meant; the few slips that leave a value a cell may
have still plan only with the fixed camera's reach checked. A fixed camera the arm cannot take
is exit 1 before anything moves."""
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings, strategies as st

from cell import cli
from cell.core.errors import PlanInfeasible, TaskError
from cell.planning.scene import build_scene
from cell.planning.viewpoints import require_reach
from cell.task import plausible
from cell.task.loader import TASK, load_task
from cell.task.schema import UNITS, _unit, schema_keys

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "tasks").glob("*.yaml"))
PHYSICAL = ("length", "time", "power")


def absolute(raw, folder=ROOT / "tasks"):
    """The task's mesh and material by absolute paths, so a variant may lie anywhere."""
    raw["part"] |= {k: str(folder / raw["part"][k]) for k in ("mesh", "material")}
    return raw


def physical_keys(node, path=""):
    """(dotted path as written, value) of every non-zero number or list of numbers under a key
    whose unit suffix is a length, time or power."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        here = f"{path}[{key}]" if isinstance(key, int) else f"{path}.{key}" if path else str(key)
        suffix = _unit(str(key))[1] if isinstance(key, str) else None
        numbers = np.asarray(value, float) if isinstance(value, (int, float, list)) and not isinstance(value, bool) \
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in np.ravel(np.asarray(value, object))) \
            else None
        if suffix and UNITS[suffix][0] in PHYSICAL and numbers is not None and np.any(numbers):
            yield here, value
        elif isinstance(value, (dict, list)):
            yield from physical_keys(value, here)


def at(raw, dotted):
    """(the mapping holding the dotted key, its last part)."""
    parts = re.findall(r"[^.\[\]]+|\[\d+\]", dotted)
    node = raw
    for part in parts[:-1]:
        node = node[int(part[1:-1])] if part.startswith("[") else node[part]
    return node, parts[-1]


SLIPS = [(task.stem, key, factor) for task in EXAMPLES
         for key, _ in physical_keys(yaml.safe_load(task.read_text())) for factor in (1e3, 1e-3)]
SLIPS += [(task.stem, "part.mesh_unit", "m") for task in EXAMPLES]       # their meshes are in mm

# slips that leave a value an inspection may have, so they load and plan (the reach checked): a
# depth of field 1000x smaller is a smaller wish (21 um), not an impossible one; a position 1000x
# nearer its frame's origin lies within a few um of it, and each example's part touches its origin
# (the feature snaps to the surface there, the pivot lies on it): no range tells it from a real one
LOADS = {(name, key, 1e-3) for name in ("hinge", "conrod", "bracket", "ring", "conrod-defects", "hinge-scratch",
                                       "conrod-faint")
         for key in ("requirements.depth_of_field_m", "lamp.rig.pivot_m")}
LOADS |= {(name, "feature.center_m", 1e-3) for name in ("hinge", "conrod", "ring", "conrod-defects")}
# the ring on the lens 60 um in front of it instead of 60 mm: where offset 0 puts it, a ring on the
# lens's front (its emitters at the lens, not at the part)
LOADS |= {("ring", "lights[0].offset_mm", 1e-3)}
LOADS -= {("conrod-defects", "feature.center_m", 1e-3)}
# a slip refused where it shows first: the feature moved, the dent declared on it lies off it
REFUSED_AT = {("conrod-defects", "feature.center_m", 1e-3): "feature.defects[1].position_m",
              ("hinge-scratch", "feature.center_m", 1e-3): "feature.defects[0].position_m",
              ("conrod-faint", "feature.center_m", 1e-3): "feature.defects[0].position_m"}
LOADS |= {("bracket", f"features[{i}].center_mm", 1e-3) for i in range(5)}


def same_key(said, written):
    """The refusal names the key written, an element of it, or the same key in SI units (a check
    after the schema's names the value it checks: `position_m` for a written `position_mm`)."""
    def stem(key):
        head, dot, last = key.rpartition(".")
        return head + dot + _unit(last)[0]
    return said == written or said.startswith(written + "[") or stem(said) == stem(written)


def slipped(tmp_path, name, key, factor):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / f"{name}.yaml").read_text()))
    node, last = at(raw, key)
    if key == "part.mesh_unit":
        node[last] = factor
    else:
        node[last] = (np.asarray(node[last], float) * factor).tolist()
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_every_example_has_physical_keys_to_slip():
    assert {name for name, _, _ in SLIPS} == {task.stem for task in EXAMPLES} >= {"hinge", "conrod", "bracket"}
    assert ("hinge", "lamp.power_mw", 1e3) in SLIPS and ("bracket", "features[3].radius_mm", 1e-3) in SLIPS
    assert len(SLIPS) >= 60


@pytest.mark.long
@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(slip=st.sampled_from(SLIPS))
def test_a_unit_slip_on_any_physical_key_is_refused_naming_it_or_plans_with_the_reach_checked(tmp_path, slip):
    name, key, factor = slip
    path = slipped(tmp_path, name, key, factor)
    try:
        task = load_task(path)
    except TaskError as refused:
        assert refused.exit_code == 2 and refused.file == str(path)
        assert same_key(refused.key, REFUSED_AT.get(slip, key)), (slip, str(refused))
        if key == "part.mesh_unit":
            assert "did you mean mesh_unit: mm?" in str(refused)
        elif "as an inspection cell has" in str(refused.expected):     # a range refused it: the unit meant
            base, suffix = _unit(key.rpartition(".")[2].split("[")[0])
            meant = [u for u, (q, _) in UNITS.items() if q == UNITS[suffix][0]
                     and np.isclose(UNITS[u][1](1.0) * factor, UNITS[suffix][1](1.0))]
            if meant:                                                   # (no km, no kW: no unit to name)
                assert f"did you mean {base}_{meant[0]}:" in str(refused), str(refused)
        return
    assert slip in LOADS, f"{slip} loaded silently"
    for i in range(len(task.features)):
        if task.camera.viewpoint.mode == "fixed":
            one = task.with_feature(i)
            try:
                require_reach(one, build_scene(one))
            except PlanInfeasible as unreachable:
                assert str(unreachable).startswith("camera_reach")


def test_the_issue_s_slips_say_the_unit_meant(tmp_path, capsys):
    hinge = (ROOT / "tasks" / "hinge.yaml").read_text()
    for before, after, says in (
            ("distance_m: 0.50", "distance_m: 500", "camera.distance_m: found 500, expected 10 mm to 2 m, as an "
                                                     "inspection cell has; did you mean distance_mm: 500?"),
            ("shutter_range_ms: [0.01, 20.0]", "shutter_range_s: [0.01, 20.0]",
             "camera.shutter_range_s: found [0.01, 20.0], expected 1 us to 10 s, as an inspection cell has; "
             "did you mean shutter_range_ms: [0.01, 20.0]?"),
            ("power_mw: 230.43", "power_w: 230.43", "lamp.power_w: found 230.43, expected 10 mW to 100 W, as an "
                                                    "inspection cell has; did you mean power_mw: 230.43?"),
            ("mesh_unit: mm", "mesh_unit: m", "part.mesh_unit: found m, which makes parts/hinge.stl 70 x 40 x 12 m, "
                                              "expected the unit of the mesh's coordinates, a part's largest side "
                                              "1 mm to 2 m; did you mean mesh_unit: mm?")):
        path = tmp_path / "slip.yaml"
        text = hinge.replace(before, after).replace("parts/", f"{ROOT}/tasks/parts/").replace(
            "materials/", f"{ROOT}/tasks/materials/")
        path.write_text(text)
        assert cli.main(["check", str(path)]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and says.replace("parts/hinge.stl", f"{ROOT}/tasks/parts/hinge.stl") in err, err


def test_a_mesh_in_m_read_as_mm_points_at_mesh_unit(tmp_path):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    import trimesh
    mesh = trimesh.load(raw["part"]["mesh"])
    mesh.apply_scale(1e-3)                                   # the hinge written in metres
    mesh.export(tmp_path / "hinge_m.stl")
    raw["part"]["mesh"] = str(tmp_path / "hinge_m.stl")
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(TaskError) as refused:
        load_task(tmp_path / "t.yaml")
    assert refused.value.key == "part.mesh_unit" and "did you mean mesh_unit: m?" in str(refused.value)


def test_limits_widen_a_range_for_a_cell_beyond_it(tmp_path):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    raw["camera"].pop("shutter_range_ms")
    raw["camera"]["shutter_range_s"] = [1e-5, 30.0]            # a camera exposing up to half a minute
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(TaskError, match="camera.shutter_range_s: found"):
        load_task(tmp_path / "t.yaml")
    raw["limits"] = {"camera.shutter_range_s": [1e-6, 60.0], "part.position_m": 3.0}   # docs/formats.md's
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert load_task(tmp_path / "t.yaml").camera.shutter_range_s == (1e-5, 30.0)
    raw["limits"] = {"camera.shutter_range_s": [1e-6, 20.0]}                           # still too narrow
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(TaskError, match=r"expected 1 us to 20 s"):
        load_task(tmp_path / "t.yaml")


@pytest.mark.parametrize("limits, key, says", [
    ({"camera.distance": [0, 1]}, "limits.camera.distance", "did you mean 'camera.distance_m'?"),
    ({"camera.distance_m": 3}, "limits.camera.distance_m", "an ascending pair [low, high]"),
    ({"camera.distance_m": [3, 1]}, "limits.camera.distance_m", "an ascending pair [low, high]"),
    ({"part.position_m": [0, 3]}, "limits.part.position_m", "a positive radius"),
    ([1, 2], "limits", "a mapping of plausible-range keys"),
])
def test_bad_limits_are_one_line_naming_the_key(tmp_path, capsys, limits, key, says):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    raw["limits"] = limits
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert cli.main(["check", str(tmp_path / "t.yaml")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f": {key}: found" in err and says in err, err


def test_every_range_has_its_key_and_its_words_in_the_schema():
    """One table: each row's Spec says its range in `expected` (docs/formats.md's accepted column)."""
    specs = dict(schema_keys(TASK))
    for key, row in plausible.RANGES.items():
        if key not in plausible.MESHES:
            assert specs[key].expected.endswith(f"({row.words()})") and specs[key].plausible.key == key


def test_a_fixed_camera_the_arm_cannot_take_is_exit_1_before_anything_moves(tmp_path, capsys):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    raw["camera"]["distance_m"] = 0.95            # plausible, inside a wider workspace, out of the UR5e's reach
    raw["cell"]["arm"] = {"workspace_min_m": [-1.5, -1.5, -1.5], "workspace_max_m": [1.5, 1.5, 1.5]}
    (tmp_path / "far.yaml").write_text(yaml.safe_dump(raw))
    assert cli.main(["run", str(tmp_path / "far.yaml"), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "beyond the UR5e's reach: its flange would be 1.080 m from the arm's base" in err, err
    log = (tmp_path / "run" / "log.jsonl").read_text()
    assert '"move_camera"' not in log and '"move_lamp"' not in log
    raw["camera"]["distance_m"] = 0.7             # the default workspace's top is 1 m above the table
    raw["cell"].pop("arm")
    raw["camera"]["view_direction"] = [0.0, 0.0, 1.0]
    raw["part"]["position_m"] = [0.0, 0.0, 0.35]
    raw["lamp"]["rig"]["pivot_m"] = [0.006, 0.0, 0.354]
    (tmp_path / "high.yaml").write_text(yaml.safe_dump(raw))
    assert cli.main(["plan", str(tmp_path / "high.yaml"), "--out", str(tmp_path / "plan")]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "is at [0.006, 0.0, 1.054] m in the cell frame, where the arm cannot take it: camera at " \
           "[0.006, 0.0, 1.054] m is outside the workspace" in err, err


@pytest.mark.parametrize("collision, says", [
    ({"padding_m": 10}, "cell.collision.padding_m: found 10, expected 0 um to 500 mm, as an inspection cell has; "
                        "did you mean padding_mm: 10?"),
    ({"camera_body": {"size_m": [60, 60, 100]}}, "cell.collision.camera_body.size_m: found [60, 60, 100], expected "
                                                 "5 mm to 1 m, as an inspection cell has; did you mean size_mm: "),
    ({"camera_body": {"offset_m": 50}}, "cell.collision.camera_body.offset_m: found 50, expected -500 mm to 500 mm, "
                                        "as an inspection cell has; did you mean offset_mm: 50?"),
    ({"lamp_body": {"size_mm": [0.06, 0.06, 0.08]}}, "did you mean size_m: [0.06, 0.06, 0.08]?"),
])
def test_a_unit_slip_on_a_collision_key_is_refused_naming_it(tmp_path, capsys, collision, says):
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    raw["cell"]["collision"] = collision
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert cli.main(["check", str(tmp_path / "t.yaml")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and says in err, err


@pytest.mark.parametrize("scale, unit, says", [(1.0, "m", "did you mean fixture_mesh_unit: mm?"),
                                               (1e-3, "mm", "did you mean fixture_mesh_unit: m?")])
def test_a_fixture_mesh_in_the_wrong_unit_points_at_fixture_mesh_unit(tmp_path, scale, unit, says):
    import trimesh
    (tmp_path / "table.stl").write_bytes(trimesh.creation.box(extents=(400 * scale, 400 * scale, 20 * scale))
                                         .export(file_type="stl"))                # a table 400 mm square
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    raw["cell"]["collision"] = {"fixture_mesh": str(tmp_path / "table.stl"), "fixture_mesh_unit": unit}
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(TaskError) as refused:
        load_task(tmp_path / "t.yaml")
    assert refused.value.key == "cell.collision.fixture_mesh_unit" and says in str(refused.value), str(refused.value)
    assert "a fixture's largest side 1 mm to 5 m" in str(refused.value)
    raw["cell"]["collision"]["fixture_mesh_unit"] = {"m": "mm", "mm": "m"}[unit]     # as the hint says: loads
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert load_task(tmp_path / "t.yaml").cell.collision.fixture.extents.max() == pytest.approx(0.4)


@pytest.mark.parametrize("position, says", [
    ([0.0, 0.0, 0.008], "lights[1].position_m: found [0.0, 0.0, 0.008] m, 0 mm from the part's surface"),
    ([0.0, 0.0, 2.3e-5], "lights[1].position_m: found [0.0, 0.0, 2.3e-05] m, 0.023 mm from the part's surface"),
    ([0.02, 0.01, 0.0085], "0.5 mm from the part's surface"),
])
def test_a_fixed_light_on_the_part_s_surface_is_refused(tmp_path, capsys, position, says):
    """The ring's dark-field light at the feature, at its own position / 1000 (on the plate's
    underside) or 0.5 mm above the plate: degenerate geometry (no direction from a surface point to
    a light on it), refused at load."""
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "ring.yaml").read_text()))
    raw["lights"][1]["position_m"] = position
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert cli.main(["check", str(tmp_path / "t.yaml")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and says in err and "expected a light off the part, more than 1 mm " \
        "from its surface" in err, err
    raw["lights"][1]["position_m"] = [0.0, 0.0, 0.0095]              # 1.5 mm above the plate: a light may be there
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    assert load_task(tmp_path / "t.yaml").lights[1].position_m[2] == pytest.approx(0.0095)


def written_slip(row, last):
    """A value for the key `last` of `row` as a slip writes it: a plausible one (half the row's top)
    in the next smaller unit's number under the SI key (mm written as m, ms as s, mW as W), shaped as
    the key is (a position or a box size a 3-vector, a range a pair)."""
    value = 0.5 * row.high * 1000
    if row.low is None:
        return [value, 0.0, 0.0]
    if "range" in last:
        return [value, value]
    return [value] * 3 if last == "size_m" else value


@pytest.mark.parametrize("key", [k for k in plausible.RANGES if "[]" not in k and k not in plausible.MESHES])
def test_the_same_slip_on_every_other_physical_key_is_refused_naming_it_and_the_unit_meant(tmp_path, key):
    """Every key of the table outside a list, examples' or not (the cell's devices, the collision
    bodies, calibration, the simulated truth): written in m, s or W with the number of mm, ms or mW
    it was meant in, it exits 2 naming the key and the unit meant."""
    raw = absolute(yaml.safe_load((ROOT / "tasks" / "hinge.yaml").read_text()))
    head, _, last = key.rpartition(".")
    node = raw
    for part in head.split("."):                                       # the section, made where absent
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
    base, _ = _unit(last)
    for written in [k for k in node if _unit(k)[0] == base]:           # the key in the example's own unit
        node.pop(written)
    node[last] = written_slip(plausible.RANGES[key], last)
    (tmp_path / "t.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(TaskError) as refused:
        load_task(tmp_path / "t.yaml")
    meant = {"length": "mm", "time": "ms", "power": "mw"}[plausible.RANGES[key].quantity]
    assert refused.value.exit_code == 2 and same_key(refused.value.key, key), str(refused.value)
    assert f"as an inspection cell has; did you mean {base}_{meant}: " in str(refused.value), str(refused.value)
