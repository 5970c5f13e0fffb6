"""The generated many-feature example (tasks/many_features.py) and cell bench's rows of it
(cell.bench.scaling, each plan measured alone by cell.bench.alone): the features lie on the faces
they are named after, the growth exponent is the log-log slope, the peak memory counts a process
tree's and not the sampler's, the digest tells plans apart by their content but not their timing,
and a short run of the rows."""
import math
import os
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
import trimesh
import yaml

from cell.bench import alone, scaling
from cell.task.loader import load_task
from lightplan_tasks import many_features

# the bracket's faces' outward normals (make_parts.bracket's docstring)
NORMALS = {"base_top": (0, 0, 1), "chamfer": (1, 0, 1), "web_inner": (1, 0, 0), "bevel": (-1, 0, 1),
           "web_outer": (-1, 0, 0)}


def triangles_under(mesh, point, tolerance=1e-6):
    """Indices of the mesh's triangles that contain `point` (in its plane, barycentric inside)."""
    a, b, c = (mesh.triangles[:, k] for k in range(3))
    n = np.cross(b - a, c - a)
    area2 = np.einsum("ij,ij->i", n, n)
    inside = [np.einsum("ij,ij->i", np.cross(q - p, point - p), n) >= -tolerance * area2
              for p, q in ((a, b), (b, c), (c, a))]
    plane = np.abs(np.einsum("ij,ij->i", point - a, n)) <= tolerance * np.sqrt(area2)
    return np.flatnonzero(plane & inside[0] & inside[1] & inside[2])


def test_the_generated_part_has_each_feature_on_the_face_it_is_named_after(tmp_path):
    path = many_features.write(tmp_path, 12)
    task = load_task(path)
    names = [f.name for f in task.features]
    assert len(names) == 12 and len(set(names)) == 12
    assert names[:6] == ["base_top_1", "chamfer_1", "web_inner_1", "bevel_1", "web_outer_1", "base_top_2"]
    mesh = trimesh.load(tmp_path / "many-12.stl", force="mesh")
    raw = yaml.safe_load(path.read_text())["features"]
    centres = np.array([f["center_mm"] for f in raw])
    for f, centre in zip(raw, centres):
        normals = mesh.face_normals[triangles_under(mesh, centre)]      # on the surface: in a triangle
        expected = np.array(NORMALS[f["name"].rsplit("_", 1)[0]], float)
        assert len(normals) and np.allclose(normals, expected / np.linalg.norm(expected), atol=1e-9)
    # three segments 14 mm apart, centred on y = 0; the part reaches 13 mm past the outer ones
    assert sorted({c[1] for c in centres}) == [-14.0, 0.0, 14.0]
    assert mesh.bounds[:, 1].tolist() == [-27.0, 27.0]


def test_the_first_five_features_are_the_brackets_own_moved_along_y(tmp_path):
    bracket = yaml.safe_load((many_features.HERE / "bracket.yaml").read_text())["features"]
    ours = yaml.safe_load(many_features.write(tmp_path, 5).read_text())["features"]
    for a, b in zip(bracket, ours):
        assert b["name"] == a["name"] + "_1" and b["radius_mm"] == a["radius_mm"] and b["samples"] == a["samples"]
        assert b["center_mm"][::2] == a["center_mm"][::2] and b["center_mm"][1] == 0.0


def test_the_growth_exponent_is_the_log_log_slope():
    features = [10, 20, 40, 100]
    for k in (1.0, 1.5, 2.0):
        times = [0.3 * n**k for n in features]
        assert scaling.growth_exponent(features, times, (10, 40)) == pytest.approx(k)
    # a fixed cost on top of linear growth: below 1
    assert scaling.growth_exponent([10, 40], [5.0 + 10, 5.0 + 40], (10, 40)) == pytest.approx(
        math.log(45 / 15) / math.log(4))
    assert math.isnan(scaling.growth_exponent([40], [11.3], (40, 40)))     # one size: no slope (not 0 / 0)


HOLD = ("import time; b = bytearray(300_000_000); b[::4096] = b'x' * len(b[::4096]); time.sleep(1.0); del b; "
        "time.sleep(1.0)")


def test_peak_memory_counts_a_child_process_and_its_peak():
    """A child that holds 300 MB of its own for a moment, then frees it: both peaks (resident and
    proportional: private pages count whole in each) hold it, the end does not."""
    with alone.PeakMemory() as memory:
        before, before_proportional = memory.resident(), memory.proportional()
        child = subprocess.Popen([sys.executable, "-c", HOLD])
        child.wait()
    assert memory.peak - before > 280e6
    assert memory.peak_proportional - before_proportional > 280e6
    assert memory.resident() - before < 100e6 and memory.proportional() - before_proportional < 100e6


def test_peak_memory_of_another_process_counts_its_grandchild_and_not_the_sampler():
    """Sampled from here, the tree of a child whose own child holds 300 MB for a moment: the
    peaks hold the 300 MB; 300 MB this process holds meanwhile count in neither."""
    mine = bytearray(300_000_000)
    mine[::4096] = b"x" * len(mine[::4096])
    parent = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys; subprocess.run([sys.executable, "
                               f"'-c', {HOLD!r}])"])
    with alone.PeakMemory(parent.pid) as memory:
        parent.wait()
    assert 280e6 < memory.peak_proportional < 500e6 and 280e6 < memory.peak < 600e6
    assert len(mine) == 300_000_000


def test_the_proportional_sizes_are_read_while_memory_grows_not_while_it_stays():
    """A child that grows by 20 MB every 0.1 s 20 times, then stays: its proportional sizes are
    read about every PSS_PERIOD_S while it grows, once more within PSS_PERIOD_S after (its top), and
    not again while it stays, but at the end."""
    code = ("import time\nblocks = []\nfor _ in range(20):\n    b = bytearray(20_000_000); b[::4096] = b'x' * len(b[::4096]); "
            "blocks.append(b); time.sleep(0.1)\nprint('grown', flush=True)\ntime.sleep(3.0)")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    with alone.PeakMemory(child.pid) as memory:
        t0 = time.monotonic()
        assert child.stdout.readline() == "grown\n"
        growing_s = time.monotonic() - t0
        time.sleep(alone.PSS_PERIOD_S + 0.2)
        grown = memory.proportional_reads
        time.sleep(1.5)
        stayed = memory.proportional_reads
    child.wait()
    assert 2 <= grown <= growing_s / alone.PSS_PERIOD_S + 3
    assert stayed == grown and memory.proportional_reads == grown + 1         # the end's
    assert 400e6 < memory.peak_proportional <= memory.peak < 500e6


def test_the_digest_is_of_the_content_not_the_timing():
    """Two plan.json documents alike but for timing_s (at any depth) and key order: one digest;
    one number changed by a bit of its last place, or a key's value, or the documents' order: another."""
    plan = {"feasible": True, "shots": [{"camera_m": [0.1, 0.2, 0.30000000000000004], "timing_s": {"search": 1.0}}],
            "timing_s": {"total": 3.0, "judge": 0.5}}
    own = {"lamp_deg": [12.5, -3.25], "timing_s": {"total": 1.0}}
    same = {"timing_s": {"judge": 9.0, "total": 99.0}, "feasible": True,
            "shots": [{"timing_s": {"search": 7.0}, "camera_m": [0.1, 0.2, 0.30000000000000004]}]}
    assert alone.digest([plan, own]) == alone.digest([same, {**own, "timing_s": {"total": 2.0}}])
    nudged = {**plan, "shots": [{**plan["shots"][0], "camera_m": [0.1, 0.2, math.nextafter(0.30000000000000004, 1)]}]}
    changed = [alone.digest([nudged, own]), alone.digest([{**plan, "feasible": False}, own]), alone.digest([own, plan]),
               alone.digest([plan, {**own, "lamp_deg": np.array([12.5, -3.25000001])}])]
    assert len({alone.digest([plan, own]), *changed}) == 5


def test_a_child_that_ends_without_its_result_is_an_error_naming_it(tmp_path):
    with pytest.raises(RuntimeError, match="cell.bench.alone ended with 1 before its result"):
        alone.measure(tmp_path / "missing.yaml", 0)


def test_the_proportional_size_splits_pages_a_forked_child_shares():
    """A 200 MB buffer written before a fork and only read after it is shared by parent and child:
    each process's resident set counts it whole, their proportional sizes split it, so their
    sum counts it about once (Linux's smaps_rollup)."""
    if not os.path.exists("/proc/self/smaps_rollup"):
        pytest.skip("no /proc/PID/smaps_rollup on this system")
    shared = bytearray(200_000_000)
    shared[::4096] = b"x" * len(shared[::4096])
    child = os.fork()
    if child == 0:                                          # the child only keeps the pages mapped
        time.sleep(3.0)
        os._exit(0)
    try:
        time.sleep(0.5)
        me, kid = psutil.Process(), psutil.Process(child)
        resident = me.memory_info().rss + kid.memory_info().rss
        proportional = alone.proportional_size(me) + alone.proportional_size(kid)
        assert resident - proportional > 150e6              # the 200 MB counted twice in one, once in the other
    finally:
        os.waitpid(child, 0)


def test_a_serial_row_is_the_median_of_its_rounds_and_flags_plans_that_differ():
    def measured(wall, judge, digest="d", load=(1.0, 1.5)):
        return {"features": 40, "candidates": 80, "shots": 9, "feasible": True, "wall_s": wall, "cpu_s": wall + 1,
                "timing_s": {"judge": judge, "total": wall}, "judge_share": judge / wall, "peak_rss_b": 5e8 + wall,
                "peak_pss_b": 4e8 + wall, "load": list(load), "digest": digest}
    rounds = [measured(12.0, 3.0, load=(0.5, 0.7)), measured(10.0, 1.5), measured(11.0, 2.0, load=(0.9, 1.2))]
    lines = []
    row = scaling.serial_row(rounds, lines.append)
    assert (row["serial_s"], row["serial_cpu_s"], row["judge_s"]) == (11.0, 12.0, 2.0)
    assert row["judge_share"] == pytest.approx(2.0 / 11.0)          # the median share: 0.15, 0.18, 0.25
    assert row["serial_rounds_s"] == [12.0, 10.0, 11.0] and row["load"] == [0.5, 1.2]
    assert row["peak_memory_serial_b"] == 5e8 + 12.0 and row["digest"] == "d" and "DIFFER" not in lines[0]
    differing = scaling.serial_row(rounds[:2] + [measured(11.0, 2.0, digest="e")], lines.append)
    assert differing["digest"] is None and "the rounds' plans DIFFER" in lines[1]


def test_the_targets_are_the_issues_at_40_features():
    row = {"features": 40, "serial_s": 19.0, "judge_share": 0.25, "peak_pss_2_workers_b": 0.9e9,
           "peak_memory_2_workers_b": 1.3e9}
    summary = {"growth_between": [10, 40], "growth_exponent": 1.2, "workers_features": 40, "speedup": 1.7}
    met = {t["name"]: t["met"] for t in scaling.targets([row], summary)}
    assert met == {"many-40: warm serial plan <= 20 s": True, "many-40: judge <= 20 % of planning": False,
                   "many-40: peak memory with 2 workers <= 1 GB": True,
                   "many: growth exponent 10 -> 40 features <= 1.1": False, "many-40: 2 workers / 1 worker >= 1.6": True}
    assert scaling.targets([{**row, "features": 10}], summary) == []        # --quick: 40 not planned


@pytest.mark.long
def test_a_short_run_plans_each_size_serially_and_on_2_workers_alike():
    lines = []
    result = scaling.run(True, lines.append, sizes=(2, 3))
    rows, summary = result["scaling"], result["scaling_summary"]
    assert [(r["features"], r["candidates"]) for r in rows] == [(2, 4), (3, 6)]
    for row in rows:
        assert row["feasible"] and row["identical"] and 0 < row["judge_share"] < 1
        assert row["speedup"] == pytest.approx(row["serial_s"] / row["workers_2_s"])
        assert row["peak_memory_2_workers_b"] > row["peak_memory_serial_b"] > 50e6     # the workers' too
        assert row["peak_pss_2_workers_b"] > row["peak_pss_serial_b"] > 50e6
        assert 0 < row["serial_cpu_s"] and 0 < row["workers_2_cpu_s"]
    assert summary["growth_exponent"] == pytest.approx(
        math.log(rows[1]["serial_s"] / rows[0]["serial_s"]) / math.log(3 / 2))
    assert summary["workers_features"] == 3 and len(summary["speedups"]) == 1
    assert lines[-1] == scaling.summary_line(summary)


@pytest.mark.long
def test_a_plan_measured_alone_is_the_plan_made_here(tmp_path):
    """The child's plan of a 2-feature part has the digest of the same plan made in this process,
    its judge share is its own timing_s's judge / total, and its times are within its wall time."""
    from dataclasses import replace

    from cell.planning.whole_part import plan_features
    path = many_features.write(tmp_path, 2)
    measured = alone.measure(path, 0)
    task = load_task(path)
    plan_features(replace(task, features=task.features[:1]))
    here = plan_features(task)
    assert measured["digest"] == alone.plan_digest(here)
    assert (measured["features"], measured["candidates"], measured["shots"]) == (2, 4, len(here.shots))
    timing = measured["timing_s"]
    assert measured["judge_share"] == timing["judge"] / timing["total"] and 0 < measured["judge_share"] < 1
    assert timing["total"] <= measured["wall_s"] and measured["peak_pss_b"] > 50e6
    assert measured["peak_rss_b"] >= measured["peak_pss_b"]
