"""`cell bench --quick` as a smoke test: bench.json's structure, every number finite, one default
setting per task, Pareto flags as defined, finer settings no less accurate on average.
No timing is asserted: the machine running the suite decides those."""
import json
import math
from dataclasses import asdict
from pathlib import Path

import pytest

from cell.bench import QUICK_SWEEP
from cell.cli.bench import summary
from cell.cli import main
from cell.planner import PlannerSettings

TASKS = Path(__file__).resolve().parent.parent / "tasks"
SETTING_KEYS = {"name", "task", "time_s", "gray_error", "gray_error_max", "lamp_error_mm", "lamp_error_deg",
                "feasible", "feasible_agrees", "finite", "pareto", "default"}
KERNEL_KEYS = {"name", "size", "warp_per_s", "reference_per_s", "ratio"}


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "--quick", "--out", str(out), str(TASKS / "hinge.yaml"), str(TASKS / "conrod.yaml")]) == 0
    return json.loads((out / "bench.json").read_text()), out


def leaves(value, key=""):
    """(key, value) of every leaf of a JSON value."""
    if isinstance(value, dict):
        return [leaf for k, v in value.items() for leaf in leaves(v, k)]
    if isinstance(value, list):
        return [leaf for v in value for leaf in leaves(v, key)]
    return [(key, value)]


def test_bench_writes_json_and_plot(bench):
    result, out = bench
    assert (out / "bench.png").stat().st_size > 10_000
    assert {r["task"] for r in result["settings"]} == {"hinge", "conrod"}
    for row in result["settings"]:
        assert SETTING_KEYS <= row.keys()
        assert row["gray_error_max"] == pytest.approx(max(abs(e) for e in row["gray_error"].values()))
    names = {r["name"] for r in result["kernels"]}
    assert {"gray", "visibility", "rays vs trimesh", "rays vs embree"} <= names
    for row in result["kernels"]:
        assert KERNEL_KEYS <= row.keys() and row["size"] > 0 and row["warp_per_s"] > 0
        if row["unavailable"]:          # e.g. trimesh without rtree: said, not failed
            assert row["ratio"] is None and row["reference_per_s"] is None
        else:
            assert row["ratio"] == pytest.approx(row["warp_per_s"] / row["reference_per_s"])


def test_every_number_is_finite(bench):
    """bench.json writes a NaN/inf as null: no null but where null means something."""
    result, _ = bench
    available = [r for r in result["kernels"] if not r["unavailable"]]
    for key, x in leaves(result["settings"] + result["references"] + available):
        if x is None:
            assert key in ("samples", "unavailable")   # PlannerSettings.samples None: the task's
        elif isinstance(x, (int, float)):
            assert math.isfinite(x), key
    assert all(r["finite"] for r in result["settings"])


def test_exactly_one_default_per_task(bench):
    result, _ = bench
    for task in ("hinge", "conrod"):
        defaults = [r for r in result["settings"] if r["task"] == task and r["default"]]
        assert len(defaults) == 1
        assert defaults[0]["settings"] == asdict(PlannerSettings())


def test_pareto_flags_are_the_undominated_settings(bench):
    result, _ = bench
    for task in ("hinge", "conrod"):
        rows = [r for r in result["settings"] if r["task"] == task]
        points = [(r["time_s"], r["gray_error_max"]) for r in rows]
        for row, (t, e) in zip(rows, points):
            dominated = any(t2 <= t and e2 <= e and (t2, e2) != (t, e) for t2, e2 in points)
            assert row["pareto"] == (not dominated), row["name"]


def test_finer_settings_are_not_less_accurate_on_average(bench):
    """QUICK_SWEEP runs coarse to fine; gray error averaged over the tasks does not grow."""
    result, _ = bench
    mean_error = [sum(r["gray_error_max"] for r in result["settings"] if r["name"] == name) / 2
                  for name in QUICK_SWEEP]
    assert mean_error == sorted(mean_error, reverse=True)


def test_summary_names_the_default_and_the_fastest_setting_within_1_gray_level():
    rows = [{"task": "t", "name": n, "time_s": t, "gray_error_max": e, "default": n == "default"}
            for n, t, e in [("coarse", 0.1, 1.8), ("samples 16", 0.2, 0.9), ("default", 0.3, 0.5),
                            ("fine", 1.5, 0.2)]]
    (line,) = summary(rows)
    assert line == ("t: default 0.300 s, gray within 0.50 of the reference; fastest within 1 gray "
                    "level: samples 16, 0.200 s (0.90)")
    (line,) = summary([{**rows[0], "default": True}])
    assert line.endswith("fastest within 1 gray level: none")
