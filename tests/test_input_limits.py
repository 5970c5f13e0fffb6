"""Input that could hang, fill memory or crash the loader: each is one line and exit 2 within
seconds, run as the user runs it (a fresh `cell` process) under a memory limit; and a property
test: random YAML structures, alone or grafted into a real task, never raise anything but the
product's own TaskError."""
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings, strategies as st

from cell.task import loader, schema
from cell.core.errors import TaskError

ROOT = Path(__file__).resolve().parents[1]
HINGE = ROOT / "tasks" / "hinge.yaml"
MEMORY_LIMIT = 3 * 2**30          # address space of the whole process, interpreter and libraries included


def limited():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def cell_check(path, env=None, timeout=30):
    """`cell check path` in its own process under MEMORY_LIMIT; (exit code, stderr)."""
    done = subprocess.run([sys.executable, "-m", "cell", "check", str(path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, preexec_fn=limited, env={**os.environ, **(env or {})})
    return done.returncode, done.stderr


def assert_one_line(code, err, *texts):
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for text in texts:
        assert text in err, err


def test_a_device_is_refused_without_reading_it():
    assert_one_line(*cell_check("/dev/zero"), "/dev/zero", "found a device, expected a regular YAML file")


def test_a_named_pipe_with_no_writer_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "task.yaml"
    os.mkfifo(fifo)
    assert_one_line(*cell_check(fifo), "found a named pipe (FIFO)")


def test_a_50_mb_mesh_given_as_the_task_is_refused_by_its_size(tmp_path):
    big = tmp_path / "part.stl"
    with open(big, "wb") as f:
        f.truncate(50 * 2**20)                       # sparse: 50 MB by its size, nothing on disk
    assert_one_line(*cell_check(big), "found 50 MB", "at most 1 MB", "CELL_MAX_YAML_MB")


def big_task(tmp_path, megabytes):
    """hinge.yaml, its files referenced absolutely, with a comment making it `megabytes` large."""
    raw = yaml.safe_load(HINGE.read_text())
    for key in ("mesh", "material"):
        raw["part"][key] = str((HINGE.parent / raw["part"][key]).resolve())
    text = yaml.safe_dump(raw) + "# " + "x" * int(megabytes * 2**20) + "\n"
    path = tmp_path / "big.yaml"
    path.write_text(text)
    return path


def test_the_size_limit_is_a_setting(tmp_path):
    path = big_task(tmp_path, 1.5)
    assert_one_line(*cell_check(path), "big.yaml", "1.5 MB", "at most 1 MB")
    code, err = cell_check(path, env={"CELL_MAX_YAML_MB": "2"})
    assert code == 0, err
    assert_one_line(*cell_check(path, env={"CELL_MAX_YAML_MB": "lots"}), "CELL_MAX_YAML_MB", "a size in MB")


def test_a_billion_laughs_is_refused_before_anything_is_expanded(tmp_path):
    lines = ["a: &a ['lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol']"]
    for parent, name in zip("abcdefghi", "bcdefghij"):
        lines.append(f"{name}: &{name} [{', '.join(['*' + parent] * 9)}]")
    path = tmp_path / "laughs.yaml"
    path.write_text("\n".join(lines) + "\n")         # 9 levels: 9^10 = 3.5e9 values expanded
    assert_one_line(*cell_check(path), "laughs.yaml:", "aliases expanded")


def test_an_alias_or_two_are_fine(tmp_path):
    raw = HINGE.read_text().replace("pivot_m: [0.006, 0.0, 0.004]", "pivot_m: *centre")
    raw = raw.replace("center_m: [0.006, 0.0, 0.004]", "center_m: &centre [0.006, 0.0, 0.004]")
    path = tmp_path / "alias.yaml"
    path.write_text(raw.replace("parts/", f"{HINGE.parent}/parts/").replace("materials/",
                                                                         f"{HINGE.parent}/materials/"))
    assert loader.load_task(path).lamp.rig.pivot_m.tolist() == [0.006, 0.0, 0.004]


# --- random structures ---------------------------------------------------------------------

SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(allow_nan=True),
                    st.text(max_size=12), st.sampled_from(["m", "mm", "lobe", "sim", "hw", "manual", "shadows"]))
KEYS = st.one_of(st.text(max_size=10), st.sampled_from(
    ["name", "part", "mesh", "feature", "center_m", "radius_mm", "samples", "requirements", "gray_band",
     "camera", "sensor", "lens", "lamp", "rig", "cell", "arm", "pan_tilt", "sim", "truth", "effects"]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(KEYS, inner, max_size=5)), max_leaves=25)


def load(tmp_path, document):
    path = tmp_path / "random.yaml"
    path.write_text(yaml.safe_dump(document, allow_unicode=True))
    try:
        loader.load_task(path)
    except TaskError as err:
        assert "\n" not in str(err) and len(str(err)) < 1000
    return path


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(document=VALUES)
def test_any_yaml_document_is_a_task_or_a_task_error(tmp_path, document):
    load(tmp_path, document)


@pytest.fixture(scope="module")
def hinge_raw(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hinge")
    shutil.copytree(HINGE.parent / "parts", folder / "parts")
    shutil.copytree(HINGE.parent / "materials", folder / "materials")
    return folder, schema.read_yaml(HINGE)


def paths(document, prefix=()):
    """Every key path of a nested mapping."""
    for key, value in document.items():
        yield prefix + (key,)
        if isinstance(value, dict):
            yield from paths(value, prefix + (key,))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), value=VALUES)
def test_any_value_at_any_key_of_a_real_task_is_a_task_or_a_task_error(hinge_raw, data, value):
    folder, raw = hinge_raw
    document = yaml.safe_load(yaml.safe_dump(raw))
    *parents, last = data.draw(st.sampled_from(sorted(paths(document))))
    node = document
    for key in parents:
        node = node[key]
    node[last] = value
    load(folder, document)
