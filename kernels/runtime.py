"""One place that starts Warp: quietly, once, lazily on first use, on the CPU.

Compiled kernels are cached on disk by Warp (default ~/.cache/warp/<version>, shared by
every process of a CI run); we keep that cache. Kernels are module-level objects, so each
Warp module compiles (or loads from the cache) once per process, on its first launch.
"""
import os
import sys
import threading

import warp as wp

DEVICE = "cpu"

_lock = threading.Lock()
_ready = False


def ensure_init() -> str:
    """Initialize Warp once per process (no greeting, no CUDA-driver warning); return the device."""
    global _ready
    if _ready:
        return DEVICE
    with _lock:
        if not _ready:
            wp.config.quiet = True              # Warp <= 1.9
            wp.config.log_level = getattr(wp, "LOG_WARNING", 30)   # newer: hides greeting and load times
            with _native_stderr_silenced():     # libwarp prints "no CUDA driver" from C++
                wp.init()
            _ready = True
    return DEVICE


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
