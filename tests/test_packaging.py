"""What a regular install (`pip install .`) carries. The suite runs on the editable install, which
imports every folder of the tree whether pyproject.toml lists it or not; these checks hold the
hand-written package list and package-data globs to the tree."""
import tomllib
from pathlib import Path

from cell.bench.suite import DEFAULT_TASKS
from cell.task.loader import load_task

ROOT = Path(__file__).resolve().parents[1]
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed():
    found = {".".join(p.parent.relative_to(ROOT).parts)
             for top in ("cell", "kernels", "sim") for p in (ROOT / top).rglob("__init__.py")}
    assert set(SETUPTOOLS["packages"]) == found | {"lightplan_tasks"}


def test_package_data_takes_every_example_file_along():
    tasks = ROOT / SETUPTOOLS["package-dir"]["lightplan_tasks"]
    examples = {p for p in tasks.rglob("*") if p.is_file() and p.suffix not in (".py", ".pyc")}
    taken = {p for pattern in SETUPTOOLS["package-data"]["lightplan_tasks"] for p in tasks.glob(pattern)}
    assert examples == taken


def test_bench_defaults_are_the_installed_example_tasks():
    assert [load_task(p).path.name for p in DEFAULT_TASKS] == ["hinge.yaml", "conrod.yaml"]
