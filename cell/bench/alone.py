"""A plan measured alone (cell.bench.scaling's rows): a fresh process (`python -m
cell.bench.alone TASK WORKERS`) loads the task, warms up (a plan of its first feature: the
process's first plan loads Warp's kernels; with WORKERS > 0 on a LocalCluster of that many worker
processes, whose first plan does the same), says `ready`, waits for `go` on its stdin, plans the
whole task and says its result: wall time, CPU time of its process tree (itself and, with workers,
the cluster's nannies and workers), the plan's timing_s, and the digest of its plan.json content
without timing_s (plan_digest). Nothing else lives in that process, so the time and memory are the
plan's own, not those of plans made before it in the same heap.

Its peak memory is sampled from the parent (measure), between `go` and the result, so that the
sampler's own work (reading /proc) is not in the process it measures: PeakMemory of the child's
tree. Resident set sizes summed (pages several processes share, the libraries, count in each: an
upper bound) every MEMORY_PERIOD_S; proportional set sizes summed (Linux's
/proc/PID/smaps_rollup `Pss`: a shared page split among the processes mapping it, so the sum is
what they take together; the number the issue's 1 GB is judged on) after the resident sum reached
a new high, at most every PSS_PERIOD_S: the kernel walks every page to sum them (7 ms CPU for a
300 MB process here), while the pages the processes share, the difference, stay as they are once
the libraries are loaded. The tree is listed again every TREE_EVERY-th sample (psutil lists a
process's children by reading every process's /proc/PID/stat on the machine: 2-4 ms CPU at 100
processes, where the resident sizes of 5 processes take 0.1 ms)"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import psutil

if TYPE_CHECKING:
    from cell.planning.plan import Plan

MEMORY_PERIOD_S = 0.05
PSS_PERIOD_S = 0.5                  # the proportional sizes at most this often
TREE_EVERY = 10                     # samples: the tree listed again every 0.5 s
READY, GO = "ready", "go"           # the child's and the parent's lines before the plan
RESULT = "result "                  # the child's result line: RESULT + JSON


class PeakMemory:
    """The largest sums [bytes] of the memory of process `root` (None: this one) and its children
    (recursive), sampled by a thread of this process while the `with` block runs: `peak` of the
    resident set sizes (every `period` s), `peak_proportional` of the proportional set sizes
    (once the resident sum has reached a new high, at most every PSS_PERIOD_S, and at the end);
    `proportional_reads`: how often they were read."""

    def __init__(self, root: int | None = None, period: float = MEMORY_PERIOD_S, sampling: bool = True) -> None:
        self.root, self.period, self.sampling = psutil.Process(root), period, sampling
        self.peak, self.peak_proportional, self.proportional_reads = 0, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._tree: list[psutil.Process] = []

    def processes(self) -> list[psutil.Process]:
        """The root and its children now (none once the root has ended)."""
        try:
            return [self.root, *self.root.children(recursive=True)]
        except psutil.NoSuchProcess:
            return []

    def resident(self, processes: Sequence[psutil.Process] | None = None) -> int:
        """The sum of resident set sizes now [bytes] (of `processes`, default the tree now); a
        process that ends while being read counts 0."""
        total = 0
        for process in self.processes() if processes is None else processes:
            try:
                total += process.memory_info().rss
            except psutil.NoSuchProcess:
                pass
        return total

    def proportional(self, processes: Sequence[psutil.Process] | None = None) -> int:
        """The sum of proportional set sizes now [bytes] (of `processes`, default the tree now;
        proportional_size of each)."""
        return sum(proportional_size(p) for p in (self.processes() if processes is None else processes))

    def _sample(self) -> None:
        count, higher, due = 0, False, 0.0
        while True:
            if count % TREE_EVERY == 0:
                self._tree = self.processes()
            resident = self.resident(self._tree)
            higher |= resident > self.peak
            self.peak = max(self.peak, resident)
            if higher and time.monotonic() >= due:
                self._read_proportional(self._tree)
                higher, due = False, time.monotonic() + PSS_PERIOD_S
            count += 1
            if self._stop.wait(self.period):
                return

    def _read_proportional(self, tree: Sequence[psutil.Process]) -> None:
        self.peak_proportional = max(self.peak_proportional, self.proportional(tree))
        self.proportional_reads += 1

    def __enter__(self) -> PeakMemory:
        if self.sampling:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.sampling:
            self._stop.set()
            self._thread.join()
            tree = self.processes()
            self.peak = max(self.peak, self.resident(tree))
            self._read_proportional(tree)


def proportional_size(process: psutil.Process) -> int:
    """A process's proportional set size [bytes] from /proc/PID/smaps_rollup (one line to read,
    where psutil's memory_full_info parses every mapping's smaps); its resident set where the
    rollup is missing (not Linux, or older than 4.14), 0 once it has ended."""
    try:
        with open(f"/proc/{process.pid}/smaps_rollup") as rollup:
            for line in rollup:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except FileNotFoundError:
        pass
    except (ProcessLookupError, PermissionError):
        return 0
    try:
        return process.memory_info().rss
    except psutil.NoSuchProcess:
        return 0


def digest(documents: Sequence[Any]) -> str:
    """SHA-256 of the JSON documents without their timing_s keys (at any depth), keys sorted,
    floats as Python writes them (shortest round trip: equal digests, equal bits)."""
    from cell.bench.multi_feature import without_timing
    from cell.core import jsonio
    text = json.dumps(jsonio.plain(without_timing(list(documents))), sort_keys=True, allow_nan=False, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def plan_digest(plan: Plan) -> str:
    """digest of a multi-feature plan's plan.json and each candidate shot's own plan.json: what
    multi_feature.same_plan compares, in 64 characters a process can hand back."""
    return digest([plan.to_json(), *(p.to_json() for p in plan.plans)])


def tree_cpu_s(processes: Sequence[psutil.Process]) -> dict[int, float]:
    """{pid: user + system CPU time [s]} of the processes that still run."""
    out = {}
    for process in processes:
        try:
            times = process.cpu_times()
            out[process.pid] = times.user + times.system
        except psutil.NoSuchProcess:
            pass
    return out


def result(plan: Plan, wall_s: float, cpu_s: float) -> dict[str, Any]:
    """The child's result: the plan's counts, times, timing_s and digest."""
    assert plan.cover is not None                      # a multi-feature plan's
    return {"features": len(plan.features), "candidates": plan.cover["candidate_shots"], "shots": len(plan.shots),
            "feasible": plan.feasible, "wall_s": wall_s, "cpu_s": cpu_s, "timing_s": dict(plan.timing_s),
            "judge_share": plan.timing_s["judge"] / plan.timing_s["total"], "digest": plan_digest(plan)}


def child(task_path: str, workers: int) -> None:
    """The child's side (see the module's docstring); its lines go to stdout."""
    from cell.planning import parallel
    from cell.planning.whole_part import plan_features
    from cell.task.loader import load_task
    task = load_task(Path(task_path))
    with parallel.local_cluster(workers) if workers else parallel.SERIAL as pool:
        plan_features(replace(task, features=task.features[:1]), pool=pool)
        print(READY, flush=True)
        if sys.stdin.readline().strip() != GO:
            return
        me = psutil.Process()
        tree = [me, *me.children(recursive=True)]
        before = tree_cpu_s(tree)
        t0 = time.perf_counter()
        plan = plan_features(task, pool=pool)
        wall_s = time.perf_counter() - t0
        after = tree_cpu_s(tree)
        cpu_s = sum(after[pid] - before[pid] for pid in after if pid in before)
        print(RESULT + json.dumps(result(plan, wall_s, cpu_s)), flush=True)


def measure(task_path: Path, workers: int, sampling: bool = True) -> dict[str, Any]:
    """The child's result of planning the task at `task_path` alone (workers: 0 serial, else a
    LocalCluster of that many), with `peak_rss_b` and `peak_pss_b` of its tree (0 without
    `sampling`: the sampler's own cost measured by its absence) and the load (1-minute average)
    at `go` and at the result."""
    with tempfile.TemporaryFile("w+") as errors:
        process = subprocess.Popen([sys.executable, "-m", "cell.bench.alone", str(task_path), str(workers)],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors, text=True)
        assert process.stdin is not None and process.stdout is not None
        try:
            lines = iter(process.stdout.readline, "")
            if next((line for line in lines if line.strip() == READY), None) is None:
                raise RuntimeError(failed(process, errors))
            with PeakMemory(process.pid, sampling=sampling) as memory:
                load = [os.getloadavg()[0]]
                process.stdin.write(GO + "\n")
                process.stdin.flush()
                line = next((line for line in lines if line.startswith(RESULT)), None)
                load.append(os.getloadavg()[0])
            if line is None:
                raise RuntimeError(failed(process, errors))
        finally:
            process.stdin.close()
            process.wait()
    out: dict[str, Any] = json.loads(line[len(RESULT):])
    return {**out, "peak_rss_b": memory.peak, "peak_pss_b": memory.peak_proportional, "load": load}


def failed(process: subprocess.Popen[str], errors: Any) -> str:
    """The child's exit code and the end of its stderr (it ended without its result)."""
    process.kill()
    process.wait()
    errors.seek(0)
    return f"cell.bench.alone ended with {process.returncode} before its result:\n" + errors.read()[-2000:]


if __name__ == "__main__":
    child(sys.argv[1], int(sys.argv[2]))
