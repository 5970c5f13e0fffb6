"""Where planning's independent jobs run: here, one after another (SERIAL), or on a Dask
distributed cluster (Cluster): a LocalCluster of N worker processes on this machine (`--workers
N`) or a running cluster by its scheduler's address (`--scheduler ADDRESS`). A process splits its
big kernel launches over as many threads as it has cores (kernels.runtime); N workers on this
machine split theirs over their share of the cores (cores / N, at least 1), so that the workers'
threads do not outnumber the cores they share, and a worker of another machine over its own.

A planner hands its jobs to `pool.jobs(say)` and reads their results as they complete, handing
on new jobs as earlier results allow (a feature's lamp searches once its viewpoints are known):
stages overlap instead of waiting for their slowest job. A job takes only values, never another
job's pending result, so the scheduler holds every job in its queue and gives it to the first
worker free, in the planner's order (`first` jobs ahead); each job is the same function on the
same values as the serial run, and the planner places each result by its key: the plan is
bit-identical to the serial one. A job's progress lines are kept where it runs and said when it
completes. Jobs carry their Task and plans by value (the mesh is in the Task and the Scene, the
BVH each process's own): a worker needs no task file, only the same lightplan-cell and libraries
(fingerprint). distributed is imported only here, only when a cluster is asked for.
"""

from __future__ import annotations

import hashlib
import itertools
import sys
import uuid
from collections import deque
from collections.abc import Hashable
from collections.abc import Callable, Iterable, Iterator, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any, Protocol

from cell.core.errors import TaskError

SCHEDULER_TIMEOUT_S = 10.0       # a scheduler that has not answered (or has no worker) by then: exit 2
# The LocalCluster's scheduler and workers, quiet where Dask's defaults take time the plan's jobs
# need (an idle 2-worker LocalCluster kept 5 % of a core busy here, 1 % so):
LOCAL_CONFIG = {
    "distributed.scheduler.worker-saturation": 1.0,   # a worker's next job once it starts one (1.1 rounds
                                                       # up to two in hand, one waiting while the other idles)
    "distributed.scheduler.work-stealing": False,      # jobs wait in the scheduler's queue: none to steal
    "distributed.admin.tick.interval": "1s",           # the event loops' watchdog (20 ms)
    "distributed.admin.system-monitor.interval": "5s", # the dashboard's CPU and memory samples (0.5 s)
    "distributed.worker.profile.enabled": False,       # each worker's sampling profiler (every 10 ms)
}
LIBRARIES = ("numpy", "scipy", "warp-lang", "trimesh")     # whose versions a worker's plan depends on


class Jobs(Protocol):
    """A set of jobs (a Pool's): submit(key, fn, *args, first=False, ahead=None) runs fn(*args,
    say) as a job; iterating yields (key, result) as they complete, jobs submitted meanwhile
    included. `ahead(*args)`: the part of the job a process may begin while it runs the job
    before (work of launches, laid on the thread beside: kernels.runtime.in_background); where a
    pool calls it (SERIAL), the job is called fn(*args, say, begun=what ahead returned), else as
    without (a cluster's jobs run in other processes: each does its whole)."""

    def submit(self, key: Hashable, fn: Callable[..., Any], *args: Any, first: bool = False,
               ahead: Callable[..., Any] | None = None) -> None: ...

    def __iter__(self) -> Iterator[tuple[Any, Any]]: ...


class Pool:
    """jobs(say): a set of jobs to submit and read as they complete; map(fn, jobs, say)."""

    def jobs(self, say: Callable[[str], None]) -> Jobs:
        """A new set of jobs whose progress lines go to say."""
        raise NotImplementedError

    def close(self) -> None:
        """Let go of the pool's workers (the `with` block's end)."""
        raise NotImplementedError

    def map(self, fn: Callable[..., Any], jobs: Sequence[Sequence[Any]], say: Callable[[str], None]) -> list[Any]:
        """fn(*job, say) of every job, in the jobs' order."""
        running = self.jobs(say)
        for k, job in enumerate(jobs):
            running.submit(k, fn, *job)
        done = dict(running)
        return [done[k] for k in range(len(jobs))]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class Serial(Pool):
    """Each job in this process, in the order submitted, when its result is asked for (so that a
    progress bar moves as each job ends), its progress said as it goes."""

    def jobs(self, say: Callable[[str], None]) -> SerialJobs:
        return SerialJobs(say)

    def close(self) -> None:
        pass


class SerialJobs:
    """submit(key, fn, *args, ahead=None) queues fn(*args, say); iterating runs them one by one
    and yields (key, result) in the order submitted, jobs submitted meanwhile included. A job
    with `ahead` is begun (ahead(*args)) just before the job before it runs, after that one's own
    beginning (what it lays beside comes after what that job lays), or, where it was not queued
    yet then, just before its own run."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.queued = deque[tuple[Hashable, Callable[..., Any], tuple[Any, ...], Callable[..., Any] | None]]()
        self.begun: dict[Hashable, Any] = {}

    def submit(self, key: Hashable, fn: Callable[..., Any], *args: Any, first: bool = False,
               ahead: Callable[..., Any] | None = None) -> None:
        self.queued.append((key, fn, args, ahead))

    def __iter__(self):
        while self.queued:
            key, fn, args, ahead = self.queued.popleft()
            if ahead is not None and key not in self.begun:
                self.begun[key] = ahead(*args)
            if self.queued and self.queued[0][3] is not None:
                after, _, after_args, begin = self.queued[0]
                self.begun[after] = begin(*after_args)
            if ahead is None:
                yield key, fn(*args, self.say)
            else:
                yield key, fn(*args, self.say, begun=self.begun.pop(key))


SERIAL = Serial()


def _run(fn, args, kernel_threads):
    """A job on a worker, its kernel launches split over `kernel_threads` threads (None: the
    worker's cores): (its result, its progress lines)."""
    from kernels.runtime import set_threads
    set_threads(kernel_threads)
    lines = []
    return fn(*args, lines.append), lines


class Cluster(Pool):
    """Jobs as Dask futures on a client's cluster (`only`: on those worker addresses alone), each
    job's kernel launches split over `kernel_threads` threads (None: each worker's cores)."""

    def __init__(self, client: Any, cluster: Any = None, only: list[str] | None = None,
                 kernel_threads: int | None = None) -> None:
        self.client, self.cluster, self.only, self.kernel_threads = client, cluster, only, kernel_threads

    def restricted(self, addresses: Iterable[str]) -> Cluster:
        """The same cluster, its jobs on `addresses` only (the bench's one worker of two)."""
        return Cluster(self.client, only=list(addresses), kernel_threads=self.kernel_threads)

    def jobs(self, say: Callable[[str], None]) -> ClusterJobs:
        return ClusterJobs(self, say)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


FIRST = 1 << 40            # a `first` job's priority over every other's
SUBMITTED = itertools.count()   # the order of every job submitted here, whatever its Cluster


class ClusterJobs:
    """submit(key, fn, *args, first=False, ahead=None) a job to the cluster; iterating yields (key, result)
    as each completes (its lines said then), jobs submitted meanwhile included; the first error
    raised (a CellError as it was raised on the worker), the jobs not done cancelled."""

    def __init__(self, pool: Cluster, say: Callable[[str], None]) -> None:
        from distributed import as_completed
        self.pool, self.say = pool, say
        self.named: dict[str, Hashable] = {}
        self.pending = as_completed(loop=pool.client.loop)

    def submit(self, key: Hashable, fn: Callable[..., Any], *args: Any, first: bool = False,
               ahead: Callable[..., Any] | None = None) -> None:
        """A job ahead of every job submitted after it, and `first` ahead of every job not first
        (Dask's own order is arbitrary among jobs submitted within its fifo_timeout of each
        other). Keyed lightplan-<fn>-<id>: the scheduler sees one task group (Dask queues a
        group's jobs once it has more than two per worker thread), the task stream each fn.
        `ahead` is not called: the job runs whole on a worker."""
        pool = self.pool
        where = {} if pool.only is None else {"workers": pool.only, "allow_other_workers": False}
        future = pool.client.submit(_run, fn, args, pool.kernel_threads,
                                    key=f"lightplan-{fn.__name__}-{uuid.uuid4().hex}",
                                    priority=(FIRST if first else 0) - next(SUBMITTED), pure=False, **where)
        self.named[future.key] = key
        self.pending.add(future)

    def __iter__(self):
        try:
            for future in self.pending:
                result, lines = future.result()
                for line in lines:
                    self.say(line)
                yield self.named.pop(future.key), result
        except BaseException:
            self.pool.client.cancel(list(self.pending.futures))
            raise


def local_cluster(workers: int) -> Cluster:
    """A LocalCluster of `workers` processes of one thread each, on 127.0.0.1 only (scheduler,
    workers and the scheduler's HTTP server, on free ports), and its Cluster, with LOCAL_CONFIG
    and no memory limit (a plan's jobs hold a few MB; the nannies' monitor would wake every
    100 ms); each worker's kernels on its share of this process's cores."""
    import logging

    import dask
    from distributed import Client, LocalCluster

    from kernels.cores import available_cores
    with dask.config.set(LOCAL_CONFIG):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               scheduler_port=0, dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR,
                               memory_limit=0)
    return Cluster(Client(cluster, set_as_default=False), cluster,
                   kernel_threads=max(1, available_cores() // workers))


def remote_cluster(address: str, timeout_s: float | None = None) -> Cluster:
    """The Cluster of the running scheduler at `address`, once it has a worker; bad input (exit 2,
    naming --scheduler) when it does not answer or has no worker within the timeout, or when a
    worker's lightplan-cell or libraries differ from ours (its plans would not be ours)."""
    from distributed import Client
    timeout_s = SCHEDULER_TIMEOUT_S if timeout_s is None else timeout_s
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as err:
        raise TaskError("command line", "--scheduler", f"{address}, which did not answer within {timeout_s:g} s "
                        f"({type(err).__name__}: {err})",
                        "the address of a running Dask scheduler, e.g. tcp://127.0.0.1:8786") from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            raise TaskError("command line", "--scheduler", f"{address}, a scheduler with no worker after "
                            f"{timeout_s:g} s", "a scheduler with workers (dask worker ADDRESS)") from None
        try:
            theirs = client.run(fingerprint)
        except Exception as err:            # whatever the worker raised unpickling or running it
            raise TaskError("command line", "--scheduler", f"{address}, whose workers cannot run the planner "
                            f"({type(err).__name__}: {err})",
                            "workers with lightplan-cell installed (pip install lightplan-cell)") from None
        ours = fingerprint()
        differs = first_difference(ours, theirs)
        if differs:
            worker, what = differs
            raise TaskError("command line", "--scheduler", f"worker {worker} with {what} {theirs[worker].get(what)}",
                            f"{what} {ours[what]} as here: a worker runs the same code, or its plans are not "
                            "this planner's")
    except BaseException:
        client.close()
        raise
    return Cluster(client)


def first_difference(ours: dict[str, str], theirs: dict[str, dict[str, str]]) -> tuple[str, str] | None:
    """(worker, what) of the first worker whose fingerprint differs from ours, or None."""
    for worker, found in theirs.items():
        what = next((k for k in ours if found.get(k) != ours[k]), None)
        if what:
            return worker, what
    return None


def fingerprint() -> dict[str, str]:
    """{what: version} a worker's plans depend on: Python, the libraries' versions and a digest of
    lightplan-cell's own code (cell/, kernels/), equal for an editable and a regular install of
    one commit."""
    import cell
    import kernels
    digest = hashlib.blake2b(digest_size=8)
    for package in (cell, kernels):
        root = Path(str(package.__file__)).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(path.relative_to(root.parent).as_posix().encode() + b"\0" + path.read_bytes())
    return {"python": sys.version.split()[0], **{name: metadata.version(name) for name in LIBRARIES},
            "lightplan-cell": digest.hexdigest()}


def pool(workers: int | None = None, scheduler: str | None = None) -> Pool:
    """SERIAL, or the Cluster `--workers` / `--scheduler` ask for (the caller closes it)."""
    if workers is not None:
        return local_cluster(workers)
    if scheduler is not None:
        return remote_cluster(scheduler)
    return SERIAL
