"""The suite on every core this process may use (pytest-xdist), yet a single test file in this
process alone; Warp's kernels compiled once before the workers start; no test timed by Hypothesis.

Workers: `pytest -q` (the whole suite, or several files) runs one worker process per core of
this process's affinity (os.sched_getaffinity: a container's or `taskset`'s share), tests of one
module or class on the same worker (--dist loadscope: the module-scoped fixtures, a planned task
or a started emulator, are made once). One file (or tests of one file) runs here, serially: a
worker's start (its own imports of Warp, NumPy, SciPy, a second or two) would cost more than it
saves. `-n N` or `-n 0` on the command line decides instead; `-p no:xdist` runs serially too.

Cores: each worker splits its big kernel launches over its share of the cores only, cores //
workers (LIGHTPLAN_CORES, which kernels.cores.available_cores reads), as do its BLAS threads, so
that the workers' threads do not outnumber the cores.
"""
import os
from pathlib import Path

import pytest
from hypothesis import settings

from kernels.cores import CORES_VARIABLE, available_cores

# Hypothesis's default deadline (200 ms per example) fails a property test when the machine is
# busy (other workers, other test runs): the time an example takes is not what the tests check.
settings.register_profile("suite", deadline=None)
settings.load_profile("suite")

BLAS_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _one_file(config):
    """Whether the command line names tests of a single file (paths, or node ids path::test)."""
    files = {Path(str(arg).split("::")[0]) for arg in config.args}
    return len(files) == 1 and next(iter(files)).is_file()


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """Workers by default (-n auto, --dist loadscope) unless -n was given or xdist is not loaded;
    before xdist's own pytest_cmdline_main (this conftest registers later: called first)."""
    if not config.pluginmanager.hasplugin("xdist") or hasattr(config, "workerinput"):
        return
    if config.option.numprocesses is None:
        config.option.numprocesses = "auto"
        if config.option.dist == "no":
            config.option.dist = "loadscope"


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """-n auto: a worker per core this process may use; none for tests of a single file."""
    return 0 if _one_file(config) else available_cores()


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_setupnodes(config, specs):
    """Before the workers start: their share of the cores in their environment (inherited at
    start), and every kernel module compiled here once into Warp's disk cache, which the
    workers then load, instead of each compiling it at the same time (~7 s each, first run only)."""
    share = str(max(1, available_cores() // max(1, len(specs))))
    os.environ[CORES_VARIABLE] = share
    for name in BLAS_VARIABLES:
        os.environ.setdefault(name, share)
    from kernels import runtime
    runtime.ensure_init()
    runtime.compile_missing()
