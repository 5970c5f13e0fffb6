"""Where planning's independent jobs run: here, one after another (SERIAL), or on a Dask
distributed cluster (Cluster): a LocalCluster of N worker processes on this machine (`--workers
N`) or a running cluster by its scheduler's address (`--scheduler ADDRESS`). Warp launches a CPU
kernel on one core, so a second core helps only through a second process.

A map's results come back in the order the jobs were given, whatever order they finish in, and
each job is the same function on the same values as the serial run: the plan is bit-identical to
the serial one. A job's progress lines are kept where it runs and said when it completes. Jobs
carry their Task and plans by value (the mesh is in the Task and the Scene, the BVH each process's
own): a worker needs no task file, only the same lightplan-cell and libraries (fingerprint).
distributed is imported only here, only when a cluster is asked for.
"""
import hashlib
import sys
from importlib import metadata
from pathlib import Path

from cell.errors import TaskError

SCHEDULER_TIMEOUT_S = 10.0       # a scheduler that has not answered (or has no worker) by then: exit 2
LIBRARIES = ("numpy", "scipy", "warp-lang", "trimesh")     # whose versions a worker's plan depends on


class Serial:
    """Each job in this process, in order, its progress said as it goes."""

    def map(self, fn, jobs, say):
        return [fn(*job, say) for job in jobs]

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


SERIAL = Serial()


def _run(fn, job):
    """A job on a worker: (its result, its progress lines)."""
    lines = []
    return fn(*job, lines.append), lines


class Cluster:
    """Jobs as Dask futures on a client's cluster (`only`: on those worker addresses alone)."""

    def __init__(self, client, cluster=None, only=None):
        self.client, self.cluster, self.only = client, cluster, only

    def restricted(self, addresses):
        """The same cluster, its jobs on `addresses` only (the bench's one worker of two)."""
        return Cluster(self.client, only=list(addresses))

    def map(self, fn, jobs, say):
        """fn(*job, say) of every job, in the jobs' order; the first error raised (a CellError as
        it was raised on the worker), the rest cancelled."""
        from distributed import as_completed
        where = {} if self.only is None else {"workers": self.only, "allow_other_workers": False}
        futures = [self.client.submit(_run, fn, job, pure=False, **where) for job in jobs]
        try:
            for future in as_completed(futures, loop=self.client.loop):
                for line in future.result()[1]:
                    say(line)
        except BaseException:
            self.client.cancel(futures)
            raise
        return [future.result()[0] for future in futures]

    def close(self):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def local_cluster(workers):
    """A LocalCluster of `workers` processes of one thread each, on 127.0.0.1 only (scheduler,
    workers and the scheduler's HTTP server, on free ports), and its Cluster."""
    import logging

    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           scheduler_port=0, dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
    return Cluster(Client(cluster, set_as_default=False), cluster)


def remote_cluster(address, timeout_s=None):
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


def first_difference(ours, theirs):
    """(worker, what) of the first worker whose fingerprint differs from ours, or None."""
    for worker, found in theirs.items():
        what = next((k for k in ours if found.get(k) != ours[k]), None)
        if what:
            return worker, what
    return None


def fingerprint():
    """{what: version} a worker's plans depend on: Python, the libraries' versions and a digest of
    lightplan-cell's own code (cell/, kernels/), equal for an editable and a regular install of
    one commit."""
    import cell
    import kernels
    digest = hashlib.blake2b(digest_size=8)
    for package in (cell, kernels):
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(path.relative_to(root.parent).as_posix().encode() + b"\0" + path.read_bytes())
    return {"python": sys.version.split()[0], **{name: metadata.version(name) for name in LIBRARIES},
            "lightplan-cell": digest.hexdigest()}


def pool(workers=None, scheduler=None):
    """SERIAL, or the Cluster `--workers` / `--scheduler` ask for (the caller closes it)."""
    if workers is not None:
        return local_cluster(workers)
    if scheduler is not None:
        return remote_cluster(scheduler)
    return SERIAL
