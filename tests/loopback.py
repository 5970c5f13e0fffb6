"""Loopback addresses of the tests' own: the UR emulator binds UR's fixed ports (29999, 30003,
30004), and other test sessions on this machine, and the suite's other worker processes, may run
theirs at the same time, so each picks an address in 127.0.0.2..254 where none of those ports is
taken, and starts the emulator there.

A picked address stays reserved until this process ends: its ports are bound here with
SO_REUSEADDR, not listening. Another process's probe (a bind without SO_REUSEADDR) fails on them, so
no other worker or session picks the address, while an emulator (which binds with SO_REUSEADDR
and listens, as sim.ur_controller and socket.create_server do) can still start there, again and
again; a connection to a reserved port where nothing listens is refused."""
import random
import selectors
import socket
import subprocess
import sys

import pytest

UR_PORTS = (29999, 30003, 30004)
# What a busy machine may add to a wait that takes a fraction of a second idle: with the suite's
# workers on both cores and other test runs (a load of 13 seen) a process or thread waits seconds
# for its turn. Upper bounds that say "no hang" (a wait of 300 s, a timeout never noticed) allow it;
# lower bounds (a timeout waited for) do not need it.
BUSY_S = 3.0


_reserved: list[socket.socket] = []      # bound, never listening, held until the process ends


def free_host(ports=UR_PORTS):
    """A loopback address (127.0.0.X, X in 2..254, in random order) where every port binds,
    reserved for this process."""
    for x in random.sample(range(2, 255), 253):
        host = f"127.0.0.{x}"
        held = []
        for port in ports:
            sock = _reserve(host, port)
            if sock is None:
                break
            held.append(sock)
        if len(held) == len(ports):
            _reserved.extend(held)
            return host
        for sock in held:
            sock.close()
    raise RuntimeError(f"no loopback address 127.0.0.2..254 has the ports {ports} free")


def refusing_port(host="127.0.0.1"):
    """A port of host where nothing listens (a connection is refused), reserved for this process."""
    sock = _reserve(host, 0)
    _reserved.append(sock)
    return sock.getsockname()[1]


def _reserve(host, port):
    """A socket bound to (host, port) as a reservation, or None where the port is taken (by a
    reservation too): bound without SO_REUSEADDR, which fails on any socket bound there, and then
    given SO_REUSEADDR, so that an emulator binding with it may listen there."""
    sock = socket.socket()
    try:
        sock.bind((host, port))
    except OSError:
        sock.close()
        return None
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    return sock


def start_emulator(host, options, max_seconds, log, ready_timeout_s=60.0):
    """`python -m sim.ur_controller --host host` with options, its stderr in the file `log`,
    once it printed READY (pytest.fail otherwise). It ends itself after max_seconds even if
    pytest dies; stop_emulator kills it. Its start (a Python process's imports) takes about a
    second idle, several with the suite on both cores and other test runs at a load of 13."""
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
    with socket.create_connection((host, 29999), timeout=10.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()                                         # the welcome line
        sock.sendall(command.encode() + b"\n")
        return reader.readline().decode().strip()
