"""Planning on Dask (cell.planning.parallel, `cell plan --workers N | --scheduler ADDRESS`): the plans are
the serial ones in every key but timing_s, on a LocalCluster `cell plan` starts and on one this
module starts and names by its address; errors on a worker are the serial run's one line; a
scheduler that does not answer is one line and exit 2 within its timeout. Everything on
127.0.0.1 (LocalCluster's host)."""
import io
import json
import logging
import pickle
import re
import socket
import time
from dataclasses import replace
from pathlib import Path

import pytest

from cell import cli

from cell.core import jsonio
from cell.core.progress import Progress

from cell.planning import parallel
from cell.core.errors import DeviceFault, PlanInfeasible, TaskError
from cell.bench.multi_feature import same_plan, without_timing
from cell.task.loader import load_task
from cell.planning.plan import PlannerSettings
from cell.run.moves import with_moves
from cell.planning.whole_part import own_plan, plan_features

ROOT = Path(__file__).resolve().parent.parent
HINGE = ROOT / "tasks" / "hinge.yaml"
PLANNED = ROOT / "tests" / "tasks" / "features" / "hinge_planned.yaml"


@pytest.fixture(scope="module")
def scheduler():
    """The address of a LocalCluster of 2 worker processes on 127.0.0.1, started here."""
    from distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                      dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        yield cluster.scheduler_address


def document(plan):
    """plan.json as written and read back, without timing_s."""
    return without_timing(json.loads(jsonio.dumps(plan.to_json())))


def written(folder):
    return without_timing(json.loads((folder / "plan.json").read_text()))


def one_line(err):
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.long
def test_serial_workers_2_and_a_cluster_by_address_plan_the_same(scheduler, tmp_path, capsys):
    said = io.StringIO()
    serial = with_moves(load_task(PLANNED), plan_features(load_task(PLANNED), progress=Progress(said)))
    alone = own_plan(load_task(HINGE), PlannerSettings(), None, None, "", lambda msg: None)   # cell plan's job
    assert cli.main(["plan", str(PLANNED), "--workers", "2", "--out", str(tmp_path / "local")]) == 0
    local_err = capsys.readouterr().err
    assert cli.main(["plan", str(PLANNED), str(HINGE), "--scheduler", scheduler, "--out", str(tmp_path / "remote")]) == 0
    remote_err = capsys.readouterr().err
    expected = document(serial)
    assert written(tmp_path / "local") == expected
    assert written(tmp_path / "remote" / "hinge_planned") == expected
    assert written(tmp_path / "remote" / "hinge") == document(alone)
    for k, own in enumerate(serial.plans):                  # each candidate's own plan.json too
        assert written(tmp_path / "local" / f"candidate-{k}") == document(own)
        assert written(tmp_path / "remote" / "hinge_planned" / f"candidate-{k}") == document(own)
    # the workers' progress reached the terminal, each task's lines named when there are several: the
    # kept viewpoints and the cover as the serial plan said them (the stages' quarter lines depend on
    # the order the jobs complete in), each stage's last line
    kept = [line for line in said.getvalue().splitlines() if "camera poses kept" in line or line.startswith("cover:")]
    assert kept and sorted(kept) == sorted(line for line in local_err.splitlines()
                                           if "camera poses kept" in line or line.startswith("cover:"))
    for stage in ("viewpoints", "lamp searches", "judging"):
        assert re.search(rf"^{stage}: (\d+) of \1 in ", local_err, re.M), local_err
    # the bench's comparison: blind to timing_s, not to a candidate's own plan
    assert same_plan(serial, replace(serial, timing_s={}, plans=tuple(replace(p, timing_s={}) for p in serial.plans)))
    assert not same_plan(serial, replace(serial, plans=serial.plans[::-1]))
    assert "hinge_planned: feature end_face: " in remote_err and "hinge: global search:" in remote_err


def test_a_bad_task_on_a_worker_is_the_serial_runs_one_line(scheduler, tmp_path, capsys):
    """A patch over the part's edge is found where the scene is built: on the worker."""
    from simcell import variant
    edge = variant(tmp_path, HINGE, {"feature.center_m": [0.030, 0.0, 0.004]})
    assert cli.main(["plan", str(edge), "--out", str(tmp_path / "serial")]) == 2
    serial = one_line(capsys.readouterr().err)
    assert cli.main(["plan", str(edge), "--scheduler", scheduler, "--out", str(tmp_path / "cluster")]) == 2
    assert one_line(capsys.readouterr().err) == serial and "runs over an edge of the part" in serial


def test_a_scheduler_that_does_not_answer_is_one_line_and_exit_2_within_the_timeout(tmp_path, capsys, monkeypatch):
    with socket.socket() as s:                  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(parallel, "SCHEDULER_TIMEOUT_S", 2.0)
    t0 = time.perf_counter()
    assert cli.main(["plan", str(HINGE), "--scheduler", f"tcp://127.0.0.1:{port}", "--out", str(tmp_path / "p")]) == 2
    assert time.perf_counter() - t0 < 2.0 + 8.0
    err = one_line(capsys.readouterr().err)
    assert err.startswith(f"cell plan: command line: --scheduler: found tcp://127.0.0.1:{port}, which did not "
                          "answer within 2 s")
    assert not (tmp_path / "p").exists()


def test_a_scheduler_without_workers_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    from distributed import LocalCluster
    monkeypatch.setattr(parallel, "SCHEDULER_TIMEOUT_S", 1.0)
    with LocalCluster(n_workers=0, host="127.0.0.1", scheduler_port=0, dashboard_address="127.0.0.1:0",
                      silence_logs=logging.ERROR) as empty:
        assert cli.main(["plan", str(HINGE), "--scheduler", empty.scheduler_address]) == 2
    assert "a scheduler with no worker after 1 s" in one_line(capsys.readouterr().err)


@pytest.mark.parametrize("workers", ["0", "-1", "two", "1.5"])
def test_workers_must_be_a_whole_number_at_least_1(workers, tmp_path, capsys):
    assert cli.main(["plan", str(HINGE), "--workers", workers, "--out", str(tmp_path / "p")]) == 2
    assert one_line(capsys.readouterr().err) == (f"cell plan: command line: --workers: found {workers}, expected "
                                                 "a whole number of worker processes, at least 1\n")
    assert not (tmp_path / "p").exists()


def test_workers_and_scheduler_together_are_refused(tmp_path, capsys):
    assert cli.main(["plan", str(HINGE), "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"]) == 2
    err = one_line(capsys.readouterr().err)
    assert "--scheduler tcp://127.0.0.1:8786 with --workers 2" in err and "expected one of them" in err


def test_errors_pickle_whole_so_a_workers_error_reads_as_it_was_raised():
    for error in (TaskError("a.yaml", "feature.radius_m", "-1", "a positive number"), DeviceFault("arm", "stopped"),
                  PlanInfeasible("infeasible: shadow binds")):
        copy = pickle.loads(pickle.dumps(error))
        assert type(copy) is type(error) and str(copy) == str(error) and copy.exit_code == error.exit_code


def test_the_first_worker_whose_code_or_libraries_differ_is_named():
    ours = parallel.fingerprint()
    assert set(ours) == {"python", "lightplan-cell", *parallel.LIBRARIES}
    assert parallel.first_difference(ours, {"tcp://127.0.0.1:1": dict(ours)}) is None
    theirs = {"tcp://127.0.0.1:1": dict(ours), "tcp://127.0.0.1:2": {**ours, "lightplan-cell": "0" * 16}}
    assert parallel.first_difference(ours, theirs) == ("tcp://127.0.0.1:2", "lightplan-cell")
    assert parallel.first_difference(ours, {"w": {}}) == ("w", "python")


def started(label, wait_s, say):
    """A job: (its label, when it started [s, this machine's clock]) after holding its worker wait_s."""
    start = time.time()
    time.sleep(wait_s)
    return label, start


def ran_in_order(pool):
    """The labels of jobs on `pool` in the order they started: a blocker, then three submitted
    while it runs, the last of them `first`; and a job submitted while the results are read."""
    jobs = pool.jobs(lambda line: None)
    jobs.submit("blocker", started, "blocker", 0.3)
    jobs.submit("late", started, "late", 0.0)
    jobs.submit("later", started, "later", 0.0)
    jobs.submit("early", started, "early", 0.0, first=True)
    done = {}
    for key, (label, start) in jobs:
        done[key] = start
        if key == "blocker":
            jobs.submit("afterwards", started, "afterwards", 0.0)
    return sorted(done, key=done.get)


def test_a_job_first_runs_ahead_and_jobs_submitted_while_reading_are_read_too(scheduler):
    """On one worker the jobs run in the planner's order, `first` ahead (Dask's own order among
    jobs submitted within 100 ms of each other is arbitrary); serially each as it is given."""
    with parallel.remote_cluster(scheduler) as cluster:
        one = cluster.restricted(sorted(cluster.client.nthreads())[:1])
        assert ran_in_order(one) == ["blocker", "early", "late", "later", "afterwards"]
    assert ran_in_order(parallel.SERIAL) == ["blocker", "late", "later", "early", "afterwards"]


def test_serial_jobs_begin_the_next_job_ahead_and_hand_each_its_beginning():
    """SERIAL: a job with `ahead` is begun before the job before it runs (or just before its own
    run where the job before had no beginning to come after), once, and gets what its ahead
    returned as `begun`; a job without runs as given."""
    events = []

    def begin(label):
        events.append(f"begin {label}")
        return f"{label}'s start"

    def job(label, say, begun=None):
        events.append(f"run {label} with {begun}")
        return label

    jobs = parallel.SERIAL.jobs(lambda line: None)
    jobs.submit("a", job, "a", ahead=begin)
    jobs.submit("b", job, "b", ahead=begin)
    jobs.submit("c", job, "c")
    jobs.submit("d", job, "d", ahead=begin)
    assert [key for key, _ in jobs] == ["a", "b", "c", "d"]
    assert events == ["begin a", "begin b", "run a with a's start", "run b with b's start", "begin d",
                      "run c with None", "run d with d's start"]


def test_the_local_cluster_hands_a_worker_one_job_at_a_time_without_stealing():
    with parallel.local_cluster(1) as cluster:
        scheduler = cluster.cluster.scheduler
        assert scheduler.WORKER_SATURATION == 1.0 and "stealing" not in scheduler.extensions
        assert cluster.client.scheduler_info()["workers"] and cluster.cluster.scheduler_address.startswith("tcp://127.0.0.1:")


def kernel_threads(say):
    """A job: the threads its process splits a big kernel launch over."""
    from kernels.runtime import threads
    return threads()


def test_workers_split_their_kernels_over_their_share_of_the_cores(scheduler):
    """--workers N: each worker's launches over cores / N threads (its share: N workers' threads do
    not outnumber the cores), the restricted pool's too; a cluster by address: each worker's own
    cores; serially: this process's cores."""
    from kernels.cores import available_cores
    cores = available_cores()
    with parallel.local_cluster(2) as both:
        share = max(1, cores // 2)
        assert both.map(kernel_threads, [()] * 4, lambda line: None) == [share] * 4
        one = both.restricted(sorted(both.client.nthreads())[:1])
        assert one.map(kernel_threads, [()] * 2, lambda line: None) == [share] * 2
    with parallel.remote_cluster(scheduler) as cluster:
        assert cluster.map(kernel_threads, [()] * 2, lambda line: None) == [cores] * 2
    assert parallel.SERIAL.map(kernel_threads, [()], lambda line: None) == [cores]
