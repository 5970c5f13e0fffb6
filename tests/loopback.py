"""Loopback addresses of the tests' own: the UR emulator binds UR's fixed ports (29999, 30003,
30004), and other test sessions on this machine may run theirs at the same time, so each picks
an address in 127.0.0.2..254 where none of those ports is taken, and starts the emulator there."""
import random
import selectors
import socket
import subprocess
import sys

import pytest

UR_PORTS = (29999, 30003, 30004)


def free_host(ports=UR_PORTS):
    """A loopback address (127.0.0.X, X in 2..254, in random order) where every port binds."""
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        if all(_binds(host, port) for port in ports):
            return host
    raise RuntimeError(f"no loopback address 127.0.0.2..254 has the ports {ports} free")


def _binds(host, port):
    with socket.socket() as sock:
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False


def start_emulator(host, options, max_seconds, log, ready_timeout_s=15.0):
    """`python -m sim.ur_controller --host host` with options, its stderr in the file `log`,
    once it printed READY (pytest.fail otherwise). It ends itself after max_seconds even if
    pytest dies; stop_emulator kills it."""
    with open(log, "w") as stderr:
        process = subprocess.Popen(
            [sys.executable, "-m", "sim.ur_controller", "--host", host, "--max-seconds", str(max_seconds),
             *options], stdout=subprocess.PIPE, stderr=stderr, text=True)
    process.log, process.log_seen = log, 0
    with selectors.DefaultSelector() as selector:
        selector.register(process.stdout, selectors.EVENT_READ)
        line = process.stdout.readline().strip() if selector.select(ready_timeout_s) else ""
    if line != "READY":
        stop_emulator(process)
        pytest.fail(f"UR emulator not READY within {ready_timeout_s} s: {log.read_text().strip()}")
    return process


def stop_emulator(process):
    if process is not None:
        process.kill()
        process.wait(timeout=10)
        process.stdout.close()


def dashboard(host, command):
    """One line to the emulator's dashboard server (29999) and its answer line."""
    with socket.create_connection((host, 29999), timeout=2.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()                                         # the welcome line
        sock.sendall(command.encode() + b"\n")
        return reader.readline().decode().strip()
