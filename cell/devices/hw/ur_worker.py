"""ur_rtde in a device worker process, so that no hang of the library can freeze the controller.

ur_rtde's constructors have no read timeout and hold the GIL while they block (checked: one in a
worker thread froze the whole interpreter), and its commands wait up to 300 s for a "done". So
the interfaces live in a process of their own (`python -m cell.devices.hw.ur_worker`, a fresh
interpreter: not multiprocessing's spawn, which re-runs the caller's main script and so fails in
a script without a main guard), and the controller sends it requests over a socket pair, one at
a time, each with a timeout. A worker that does not answer in time is killed (the kernel closes
its sockets) and that is a DeviceFault naming the device, its address and the step. One request
may carry several calls (`Worker.call`), so a watcher polling the receive side pays one round
trip per poll, not one per getter.
"""

from __future__ import annotations

import builtins
import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from cell.core.errors import DeviceFault

START_TIMEOUT_S = 30.0        # a fresh interpreter importing ur_rtde (0.1 s here; a loaded machine)
CLOSE_TIMEOUT_S = 2.0         # a worker asked to end: then it is killed
PR_SET_PDEATHSIG = 1          # linux/prctl.h


class Worker:
    """A process holding ur_rtde objects by name ("receive", "control"). `device` and `address`
    name what a DeviceFault is about, e.g. "arm" and "UR at 192.168.1.10"."""

    def __init__(self, device: str, address: str) -> None:
        self.device, self.address = device, address
        ours, theirs = socket.socketpair()
        env = dict(os.environ)               # the child imports this very `cell`, wherever it lies
        env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(Path(__file__).resolve().parents[3]),
                                                          env.get("PYTHONPATH"))))
        with theirs:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "cell.devices.hw.ur_worker", str(theirs.fileno()), str(os.getpid())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, env=env)
        self._conn = Connection(ours.detach())
        self._dead: str | None = None                     # why the worker is gone, once it is
        self.call([], START_TIMEOUT_S, "start of the ur_rtde worker process")

    def call(self, calls: Sequence[tuple[str, str, tuple[Any, ...]]], timeout_s: float, step: str) -> list[Any]:
        """Run calls [(object, method, args)] in turn in the worker and return their results; method
        "__init__" constructs the object (rtde_receive.RTDEReceiveInterface for "receive",
        rtde_control.RTDEControlInterface for "control"). The first exception a call raises is
        raised here (a builtin type as itself, a library's as RuntimeError); no answer within
        timeout_s kills the worker: DeviceFault naming `step`."""
        if self._dead:
            raise self._fault(f"{step} not sent: {self._dead}")
        try:
            self._conn.send(list(calls))
            answered = self._conn.poll(timeout_s)
            reply = self._conn.recv() if answered else None
        except (OSError, EOFError):                     # the worker died (its socket closed)
            try:
                code = self._process.wait(CLOSE_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                code = None
            self.kill(f"the ur_rtde worker process ended (exit code {code})")
            raise self._fault(f"{step}: {self._dead}") from None
        if reply is None:
            self.kill(f"the ur_rtde worker was stopped after {step} did not answer within {timeout_s} s")
            raise self._fault(f"{step}: no answer within {timeout_s} s (worker stopped)")
        status, *rest = reply
        if status == "ok":
            return rest[0]
        kind, text = rest
        error = getattr(builtins, kind, None)
        if isinstance(error, type) and issubclass(error, Exception):
            raise error(text)
        raise RuntimeError(text)

    def _fault(self, reason):
        return DeviceFault(self.device, f"{self.address}: {reason}")

    def kill(self, why: str = "closed") -> None:
        """End the worker at once (its sockets close with it); later calls are DeviceFaults saying why."""
        if self._dead is None:
            self._dead = why
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait(CLOSE_TIMEOUT_S)
        self._conn.close()

    def close(self, calls: Sequence[tuple[str, str, tuple[Any, ...]]] = (),
              timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Run each of calls (e.g. disconnects; one failing does not skip the next) within
        timeout_s for all, then let the worker end; without calls it is killed at once (the
        objects' destructors would disconnect, which ur_rtde does slowly from a silent host)."""
        deadline = time.monotonic() + timeout_s
        try:
            for call in calls:
                if self._dead:
                    break
                try:
                    self.call([call], max(deadline - time.monotonic(), 0.0), call[1])
                except (DeviceFault, RuntimeError):
                    pass
            if calls and not self._dead:
                self._conn.send(None)                       # end
                self._process.wait(max(deadline - time.monotonic(), 0.0))
        except (OSError, subprocess.TimeoutExpired):
            pass
        finally:
            self.kill()


class Remote:
    """`remote.method(*args)` calls `method` of the worker's object `name`, within `timeout_s`
    (`timeouts` for the methods that need longer, e.g. a stop that brakes first)."""

    def __init__(self, worker: Worker, name: str, timeout_s: float,
                 timeouts: dict[str, float] | None = None) -> None:
        self._worker, self._name, self._timeout_s, self._timeouts = worker, name, timeout_s, timeouts or {}

    def __getattr__(self, method):
        timeout_s = self._timeouts.get(method, self._timeout_s)

        def call(*args):
            return self._worker.call([(self._name, method, args)], timeout_s, method)[0]
        return call


def serve(conn: Connection, parent_pid: int) -> None:
    """The worker's loop: answer each request, a list of calls, ("ok", results) or ("error", type
    name, message) for the first call that raised; None or the socket closing ends it."""
    _die_with_parent(parent_pid)
    import rtde_control
    import rtde_receive
    kinds = {"receive": rtde_receive.RTDEReceiveInterface, "control": rtde_control.RTDEControlInterface}
    objects = {}
    while True:
        try:
            calls = conn.recv()
        except (EOFError, OSError):
            return
        if calls is None:
            return
        results: list[Any] = []
        try:
            for name, method, args in calls:
                if method == "__init__":
                    objects[name] = kinds[name](*args)
                    results.append(None)
                else:
                    results.append(getattr(objects[name], method)(*args))
        except Exception as err:               # the library's errors are the controller's to judge
            conn.send(("error", type(err).__name__, str(err)))
            continue
        conn.send(("ok", results))


def _die_with_parent(parent_pid):
    """The worker is killed with its parent (Linux prctl), so a controller that dies while a
    ur_rtde call blocks here leaves no process behind. (prctl ties it to the thread that started
    the worker: start workers from a thread that outlives them, as the CLI's main thread does.)"""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:             # the parent died before prctl took effect
        os._exit(0)


if __name__ == "__main__":
    serve(Connection(int(sys.argv[1])), int(sys.argv[2]))
