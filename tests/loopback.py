"""Loopback addresses of the tests' own: the UR emulator binds UR's fixed ports (29999, 30003,
30004), and other test sessions on this machine may run theirs at the same time, so each picks
an address in 127.0.0.2..254 where none of those ports is taken."""
import random
import socket

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
