"""docs/formats.md is the loader's schemas in words: every key the loader accepts has a row (and no
row names a key it refuses), each row says what the loader accepts, the other units it takes and
its default, and the examples load."""
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.physics.brdf_fit import COLUMNS, PhaseFit, material_document, read_goniometer
from cell.task.loader import MATERIAL, TASK, load_material, load_task
from cell.task.schema import REQUIRED, UNITS, Section, Sections, _unit, schema_keys

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "formats.md"
TASKS = ROOT / "tasks"


def section(title):
    """The text of the `## title...` section, up to the next `## ` heading."""
    text = DOC.read_text()
    start = text.index("\n## " + title)
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def rows(text):
    """{key: its table row's cells} of every table row whose first cell is a `key`, in order."""
    found = {}
    for line in text.splitlines():
        if line.startswith("| `"):
            cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)[1:-1]]
            key = cells[0].strip("`")
            assert key not in found, f"{key} has two rows"
            found[key] = cells
    return found


def blocks(text, language):
    return re.findall(rf"```{language}\n(.*?)```", text, re.S)


def other_units(key):
    """The suffixes the loader also accepts for this key (cell.task.schema's rule)."""
    suffix = _unit(key.rpartition(".")[2])[1]
    return {f"_{u}" for u, (quantity, _) in UNITS.items()
            if suffix and u != suffix and quantity == UNITS[suffix][0]}


def documented_default(key, cell):
    """'required', 'optional' (a section), or the first `value` in the cell, in SI units."""
    if cell in ("required", "optional"):
        return cell
    value = yaml.safe_load(re.search(r"`([^`]*)`", cell).group(1))
    suffix = _unit(key.rpartition(".")[2])[1]
    if isinstance(value, dict):                 # a mapping of names to values in that unit
        return {k: UNITS[suffix][1](float(v)) for k, v in value.items()} if suffix else value
    return UNITS[suffix][1](np.asarray(value, float)) if suffix and value is not None else value


def schema_default(spec):
    if isinstance(spec, Section):
        return "required" if spec.required else "optional"
    if isinstance(spec, Sections):
        return "optional"                   # the alternative to one section (`features`, `feature`)
    return "required" if spec.default is REQUIRED else spec.default


def same(a, b):
    if a is None or b is None or isinstance(a, (str, dict)) or isinstance(b, (str, dict)):
        return a == b
    return np.shape(a) == np.shape(b) and np.allclose(a, b)


SCHEMAS = {"Task": TASK, "Material": MATERIAL}


@pytest.mark.parametrize("title", SCHEMAS)
def test_every_key_the_loader_accepts_has_a_row_and_every_row_is_a_key(title):
    documented, schema = rows(section(title)), dict(schema_keys(SCHEMAS[title]))
    undocumented = sorted(schema.keys() - documented.keys())      # accepted, no row in docs/formats.md
    refused = sorted(documented.keys() - schema.keys())           # a row, but the loader refuses it
    assert undocumented == [] and refused == []


@pytest.mark.parametrize("title", SCHEMAS)
def test_each_row_says_what_the_loader_accepts_its_other_units_and_its_default(title):
    documented = rows(section(title))
    for key, spec in schema_keys(SCHEMAS[title]):
        _, accepted, units, default, _ = documented[key]
        assert accepted == spec.expected, key
        assert set(re.findall(r"`(_\w+)`", units)) == other_units(key), key
        assert same(documented_default(key, default), schema_default(spec)), key


def test_the_device_keys_are_in_the_task_table():
    """cell.arm, cell.pan_tilt and cell.camera come from cell.task.device_config, through cell's section."""
    documented = rows(section("Task"))
    assert {"cell.arm.host", "cell.pan_tilt.radius_ticks", "cell.camera.exposure_unit_s"} <= documented.keys()


def test_the_task_examples_load(tmp_path):
    """The example task, and the same with the features example in place of its `feature:`."""
    example, several = blocks(section("Task"), "yaml")
    example = example.replace("parts/", f"{TASKS}/parts/").replace("materials/", f"{TASKS}/materials/")
    path = tmp_path / "example.yaml"
    path.write_text(example)
    task = load_task(path)
    assert task.name == "Aluminium hinge, leaf surface" and task.lamp.power_w == pytest.approx(0.23043)
    assert task.cell.devices.arm.host == "192.168.1.10" and task.sim.effects == ("shadows", "cone_falloff",
                                                                                    "quantization", "collisions")
    start = example.index("feature:")
    path.write_text(example[:start] + several + example[example.index("requirements:"):])
    leaf, screw = load_task(path).features
    assert (leaf.name, screw.name) == ("leaf", "near_screw") and leaf.requirements == task.requirements
    assert screw.requirements.gray_band == (90, 140) and screw.requirements.lamp_tolerance_rad == pytest.approx(
        np.radians(0.5)) and screw.requirements.reflection == task.requirements.reflection


def test_the_material_examples_load_and_the_fitter_writes_the_documented_keys_in_order(tmp_path):
    table, fitted = blocks(section("Material"), "yaml")
    for i, text in enumerate((table, fitted)):
        (tmp_path / f"m{i}.yaml").write_text(text)
    assert load_material(tmp_path / "m0.yaml").name == "milled aluminium"
    material = load_material(tmp_path / "m1.yaml")
    assert np.isinf(material.extra["sigma2_stderr"]).all() and material.extra["unidentifiable"] == {"spike": [20.0]}
    fit = PhaseFit(20.0, 6, np.array([0.05, 3.0, 8.0, 0.0, 16.0]), np.array([2e-4, 0.01, 0.05, np.inf, np.inf]),
                   1e-4, (0.0, 0.5), ("spike",))
    written = [k for k in rows(section("Material")) if k.partition(".")[0] != "unresolved"]   # measure-brdf's own keys
    assert list(material_document([fit], "brushed steel", "a fit")) == written


def test_the_goniometer_columns_are_the_fitter_s_and_the_example_reads(tmp_path):
    text = section("Goniometer")
    assert list(rows(text)) == list(COLUMNS)
    (csv,) = re.findall(r"```\n(.*?)```", text, re.S)
    (tmp_path / "g.csv").write_text(csv)
    (group,) = read_goniometer(tmp_path / "g.csv")
    assert group.phase_deg == 20 and len(group.reflectance) == 6


def test_readme_and_devices_point_at_formats():
    for doc in (ROOT / "README.md", ROOT / "docs" / "devices.md"):
        text = doc.read_text()
        assert "formats.md" in text and "task-format.md" not in text, doc.name


def test_the_hand_eye_file_example_loads_as_a_task_s_hand_eye(tmp_path):
    """The documented hand-eye file, named by cell.arm.hand_eye, gives T_flange_cam its keys."""
    (example,) = blocks(section("Hand-eye file"), "yaml")
    (tmp_path / "hand-eye.yaml").write_text(example)
    task = yaml.safe_load((TASKS / "hinge.yaml").read_text())
    task["part"] |= {k: str(TASKS / task["part"][k]) for k in ("mesh", "material")}
    task["cell"] = {"arm": {"hand_eye": "hand-eye.yaml"}}
    (tmp_path / "task.yaml").write_text(yaml.safe_dump(task))
    T = load_task(tmp_path / "task.yaml").frames.T_flange_cam
    assert T[:3, 3] == pytest.approx([0.001499, -0.002001, 0.052993])
    assert np.degrees(np.arctan2(T[2, 1], T[2, 2])) == pytest.approx(0.8)   # roll of extrinsic x-y-z
