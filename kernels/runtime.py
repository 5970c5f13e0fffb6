"""One place that starts Warp: quietly, once, lazily on first use, on the CPU.

Compiled kernels are cached on disk by Warp (default ~/.cache/warp/<version>, shared by
every process of a CI run); we keep that cache. Kernels are module-level objects, so each
Warp module compiles (or loads from the cache) once per process, on its first launch. A
compile takes seconds (the first use after an install or an update of this package): then,
and only then, one line on stderr says so and how long it took, every kernel module of the
package compiled at once.
"""
import importlib
import os
import pkgutil
import sys
import threading
import time

import warp as wp

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
            with _native_stderr_silenced():     # libwarp prints "no CUDA driver" from C++
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


class _native_stderr_silenced:
    """Redirect file descriptor 2 to /dev/null for the duration (init errors still raise)."""

    def __enter__(self):
        self.saved = None
        try:
            sys.stderr.flush()
            self.saved = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
        except (OSError, ValueError, AttributeError):
            self.saved = None
        return self

    def __exit__(self, *exc):
        if self.saved is not None:
            os.dup2(self.saved, 2)
            os.close(self.saved)
        return False
