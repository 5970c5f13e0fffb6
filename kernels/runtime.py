"""One place that starts Warp: quietly, once, lazily on first use, on the CPU; and the threads a
big launch is split over.

Compiled kernels are cached on disk by Warp (default ~/.cache/warp/<version>, shared by
every process of a CI run); we keep that cache. Kernels are module-level objects, so each
Warp module compiles (or loads from the cache) once per process, on its first launch. A
compile takes seconds (the first use after an install or an update of this package): then,
and only then, one line on stderr says so and how long it took, every kernel module of the
package compiled at once.

Warp runs a CPU launch on one core, one element after another. It calls the kernel through
ctypes, which lets go of the GIL, so launches on several Python threads run at once: a big
launch is cut into contiguous slices of its first dimension (`slices`), one recorded launch each,
run side by side (`in_parallel`). Each element is computed alone, by the same code on the same
inputs, so the result is bitwise the one launch's. (Tile kernels could not be split this way:
Warp's CPU tile storage is one static buffer, not a thread's own; none of ours uses tiles.)
Work of launches the caller need not wait for runs beside it on a thread of its own
(`in_background`: the judge's dense patches while it judges the next feature's samples).
"""
import importlib
import os
import pkgutil
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

import warp as wp

from kernels.cores import available_cores

DEVICE = "cpu"
# Warp launches a CPU kernel with a block of 1 thread (warp.config.enable_cpu_blocks off): the
# variant a launch loads, and so the one whose binary the disk cache must hold
CPU_BLOCK_DIM = 1
COMPILING = "compiling the lighting kernels (first use after install, ~7 s) ..."

_lock = threading.Lock()
_ready = False
_checked: set[str] = set()      # kernel modules found in the disk cache or compiled by this process


def ensure_init(module: str | None = None) -> str:
    """Initialize Warp once per process (no greeting, no CUDA-driver warning), the kernel module
    named `module` (the caller's __name__) loaded or compiled (compile_missing); return the device."""
    global _ready
    if _ready and (module is None or module in _checked):
        return DEVICE
    with _lock:
        if not _ready:
            wp.config.quiet = True              # Warp <= 1.9
            wp.config.log_level = getattr(wp, "LOG_WARNING", 30)   # newer: hides greeting and load times
            with native_output_silenced(2):     # libwarp prints "no CUDA driver" from C++
                wp.init()
            _ready = True
        if module is not None and module not in _checked:
            compile_missing()
    return DEVICE


def compile_missing() -> list[str]:
    """Compile, with a line on stderr saying so and its time, every kernel module of this package
    whose CPU binary the disk cache lacks; returns their names (none: nothing said). The modules
    are imported here by name: each imports this one, and all must be defined before one compile."""
    package = sys.modules[__name__.rpartition(".")[0]]
    for found in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        importlib.import_module(found.name)      # every kernel module defined, so one compile covers all
    ours = sorted(name for name in sys.modules if name.startswith(package.__name__ + ".") and name not in _checked)
    modules = [wp.get_module(name) for name in ours]
    missing = [m for m in modules if m.kernels and not os.path.isdir(
        os.path.join(wp.config.kernel_cache_dir, m.get_module_identifier(block_dim=CPU_BLOCK_DIM)))]
    if missing:
        print(COMPILING, end="", file=sys.stderr, flush=True)
        start = time.perf_counter()
        for m in missing:
            wp.load_module(m, device=DEVICE, block_dim=CPU_BLOCK_DIM)
        print(f" done in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    _checked.update(ours)
    return [m.name for m in missing]


class native_output_silenced:
    """Redirect file descriptor `fd` (2: stderr, 1: stdout) to /dev/null for the duration, for
    native libraries that print from C/C++ whatever their options say (errors still raise)."""

    def __init__(self, fd: int = 2) -> None:
        self.fd = fd

    def __enter__(self):
        self.saved = None
        try:
            (sys.stdout if self.fd == 1 else sys.stderr).flush()
            self.saved = os.dup(self.fd)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self.fd)
            os.close(devnull)
        except (OSError, ValueError, AttributeError):
            self.saved = None
        return self

    def __exit__(self, *exc):
        if self.saved is not None:
            os.dup2(self.saved, self.fd)
            os.close(self.saved)
        return False


MIN_SLICE = 1 << 14     # evaluations (ray casts, shaded points) a slice holds at least: about a
                        # millisecond, against tens of microseconds to hand a launch to a thread

_threads: int | None = None
_pool: tuple[int, ThreadPoolExecutor] | None = None       # its thread count, the pool
_pool_lock = threading.Lock()
_background: dict[int, ThreadPoolExecutor] = {}     # in_background's threads, by lane
_beside = threading.local()     # caller: True on in_background's thread
T = TypeVar("T")


def threads() -> int:
    """How many threads a big launch is split over: set_threads's count, else the cores this
    process may use (kernels.cores.available_cores)."""
    return _threads if _threads is not None else available_cores()


def set_threads(count: int | None) -> None:
    """Split big launches over `count` threads from now on in this process (None: available_cores();
    a Dask worker of several on one machine takes its share, cell.planning.parallel)."""
    global _threads
    if count is not None and count < 1:
        raise ValueError(f"kernel threads must be at least 1, got {count}")
    _threads = count


def slices(count: int, work_per_item: float = 1.0) -> list[tuple[int, int]]:
    """range(count) as contiguous (start, stop) slices of near-equal length, as many as threads()
    but none with less than MIN_SLICE evaluations (work_per_item each): one slice when splitting
    does not pay, and on in_background's thread."""
    if getattr(_beside, "caller", False):       # in_background's thread: the caller holds the other core
        return [(0, count)]
    n = max(1, min(threads(), count, int(count * work_per_item // MIN_SLICE)))
    edges = [count * k // n for k in range(n + 1)]
    return list(zip(edges[:-1], edges[1:]))


def in_parallel(launches: Sequence[Any]) -> None:
    """Run recorded launches (wp.launch(..., record_cmd=True)) at once, each on a thread of its own
    (the last on the caller's), and return when all are done; one runs where it is called."""
    if not launches:
        return
    running = [_executor().submit(launch.launch) for launch in launches[:-1]]
    launches[-1].launch()
    for done in running:
        done.result()


def launch_sliced(kernel: Any, dim: int | tuple[int, ...], inputs: list[Any], outputs: list[Any],
                  work_per_item: float = 1.0) -> None:
    """wp.launch of a kernel whose last input is the first index of its launch's first dimension
    (`first`: the kernel adds it to that wp.tid()), split over slices() of that dimension, each
    element of it worth work_per_item evaluations."""
    dims = (dim,) if isinstance(dim, int) else tuple(dim)
    in_parallel([wp.launch(kernel, dim=(stop - start, *dims[1:]), inputs=[*inputs, start], outputs=outputs,
                           device=DEVICE, record_cmd=True)
                 for start, stop in slices(dims[0], work_per_item)])


def _executor() -> ThreadPoolExecutor:
    """The process's threads for in_parallel: threads() - 1 besides the caller's, made on first use."""
    global _pool
    size = max(1, threads() - 1)
    with _pool_lock:
        if _pool is None or _pool[0] != size:
            if _pool is not None:
                _pool[1].shutdown(wait=False)
            _pool = size, ThreadPoolExecutor(max_workers=size, thread_name_prefix="warp-slice")
        return _pool[1]


def in_background(fn: Callable[..., T], *args: Any, lane: int = 0) -> "Future[T]":
    """fn(*args) on a thread of its own beside the caller's, one call after another in the order
    asked; its result (or exception) in the Future. For work mostly of launches (Warp lets go of
    the GIL in them) that the caller's Python need not wait for: its launches run while the caller
    works on. Not the slices' pool (in_parallel): a slice never waits behind it; and its own
    launches are whole (slices: one), the caller's thread running on the other core. `lane`: a
    thread for each, so that work asked in one never waits behind another's queue. With one
    thread (threads(): a Dask worker's share of one core) fn runs here, now."""
    if threads() == 1:
        done: Future[T] = Future()
        try:
            done.set_result(fn(*args))
        except Exception as error:
            done.set_exception(error)
        return done
    with _pool_lock:
        if lane not in _background:
            _background[lane] = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"warp-background-{lane}",
                                                   initializer=_mark_beside)
        return _background[lane].submit(fn, *args)


def _mark_beside() -> None:
    _beside.caller = True


def _forget_pool() -> None:
    """A forked child has none of its parent's threads: it makes its own pool."""
    global _pool, _background
    _pool, _background = None, {}


os.register_at_fork(after_in_child=_forget_pool)
