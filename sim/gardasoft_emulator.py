"""A Gardasoft RT-series LED lighting controller (RT220 / RT420 / RT820F, Ethernet) on loopback,
so tests can run the real adapter (cell.devices.hw.gardasoft) without a controller.

    python -m sim.gardasoft_emulator --port N [--host 127.0.0.1] [--channels 4]
                                     [--max-seconds S] [--fault silent|drop [--fault-on-command K]]
                                     [--event C,E [--event-on-command K]]

It prints `READY host:port` once it listens (port 0: any free port) and ends itself after
--max-seconds. Written from the RTxxx user manual, not from the adapter:
- 12.1 Ethernet configuration: TCP, port 30313; a command line ends with carriage return.
- 12.3 Command structure: two upper-case letters and comma-separated numbers, spaces ignored,
  several commands on a line separated by `;`; the last character of every reply is `>`.
- 12.3.1 General commands: `VR` reports the firmware (`RT420-20 (HW02) V031` for the 4-channel
  model); `STc` reports channel c's settings, `ST0` the general ones (`TM 1, TP 20.00ms`);
  `GTm` turns the event messages on (1) or off (0); `GR` reads and clears the last event.
- 12.3.2 Lighting channel commands: `RSc,s` puts channel c (1..channels) in continuous mode at
  s percent (0..100).
- 13.3 Error codes: `Err 1` a parameter value is invalid, `Err 2` command not recognised,
  `Err 3` a number in the wrong format, `Err 4` the wrong number of parameters.
- 13.5 Event codes: `Evt<channel>,<event code>;`, sent after `GT1` to the client that sent the
  last command (the manual's "most recent address").
The manual lists the abbreviations of a channel's ST report (rating RA and CS, input trigger IP,
flags FL) but, in the pages found, gives no example of the whole reply; this emulator answers
`STc` in the form of the manual's ST0 example, `KEY value` pairs separated by `, `:
`CH c, MD CONT, S 42.5%` (MD: the channel's mode, CONT after RS, OFF at power-up; S: the RS
setting in percent).

Faults a real controller shows, on request (`inject`, or the command line): `silent` (reads
commands and answers nothing more, the connection stays open), `drop` (the connection closes
without an answer, the controller keeps listening), an error event `Evt c,e` sent at once.
Every line received is kept as bytes (`received`) for exact asserts.
"""
import argparse
import re
import selectors
import socket
import threading
import time
from typing import Self

from sim.addresses import loopback

TCP_PORT = 30313                                   # 12.1: TCP commands go to this port
MODELS = {2: "RT220-20", 4: "RT420-20", 8: "RT820F-20"}
FAULTS = ("silent", "drop")
Fault = str | tuple[int, int]                      # one of FAULTS, or an event (channel, code)
INVALID, UNKNOWN_COMMAND, BAD_NUMBER, PARAMETER_COUNT = 1, 2, 3, 4      # 13.3 error codes
COMMAND = re.compile(r"([A-Z]{2})(.*)")
NUMBER = re.compile(r"\d+(\.\d*)?|\.\d+")


class CommandError(Exception):
    """A command the controller answers with `Err n` (13.3)."""

    def __init__(self, code: int) -> None:
        self.code = code


class Controller:
    """The controller's state: per channel its mode and setting [%], event messages on or off,
    the last event; `answer(line)` is what the controller replies to one command line."""

    def __init__(self, channels: int = 4) -> None:
        if channels not in MODELS:
            raise ValueError(f"an RT controller has 2, 4 or 8 channels, not {channels}")
        self.channels = channels
        self.mode: dict[int, str] = {c: "OFF" for c in range(1, channels + 1)}
        self.setting_pct: dict[int, float] = {c: 0.0 for c in range(1, channels + 1)}
        self.messages = False                       # GT1: events go to the client
        self.last_event: tuple[int, int] | None = None   # (channel, code), read and cleared by GR

    def answer(self, line: str) -> str:
        """The reply to one command line (without its CR): each `;`-separated command's output
        or `Err n`, then the prompt `>`."""
        outputs = []
        for command in line.replace(" ", "").split(";"):
            if not command:
                continue
            try:
                output = self.command(command)
            except CommandError as err:
                output = f"Err {err.code}"
            if output:
                outputs.append(output)
        return "".join(out + "\r\n" for out in outputs) + ">"

    def command(self, text: str) -> str:
        match = COMMAND.fullmatch(text)
        if not match:
            raise CommandError(UNKNOWN_COMMAND)
        name, params = match.group(1), match.group(2).split(",") if match.group(2) else []
        handler = {"RS": self._rs, "ST": self._st, "GT": self._gt, "GR": self._gr, "VR": self._vr}.get(name)
        if handler is None:
            raise CommandError(UNKNOWN_COMMAND)
        return handler([_number(p) for p in params])

    def _channel(self, value: float, allow_zero: bool = False) -> int:
        if value != int(value) or not (0 if allow_zero else 1) <= value <= self.channels:
            raise CommandError(INVALID)
        return int(value)

    def _rs(self, params: list[float]) -> str:
        if len(params) != 2:
            raise CommandError(PARAMETER_COUNT)
        channel = self._channel(params[0])
        if not 0 <= params[1] <= 100:
            raise CommandError(INVALID)
        self.mode[channel], self.setting_pct[channel] = "CONT", params[1]
        return ""

    def _st(self, params: list[float]) -> str:
        if len(params) != 1:
            raise CommandError(PARAMETER_COUNT)
        channel = self._channel(params[0], allow_zero=True)
        if channel == 0:
            return "TM 0, TP 20.00ms"              # the internal trigger off (TT0), its period
        return f"CH {channel}, MD {self.mode[channel]}, S {self.setting_pct[channel]:.1f}%"

    def _gt(self, params: list[float]) -> str:
        if len(params) != 1 or params[0] not in (0, 1):
            raise CommandError(PARAMETER_COUNT if len(params) != 1 else INVALID)
        self.messages = params[0] == 1
        return ""

    def _gr(self, params: list[float]) -> str:
        if params:
            raise CommandError(PARAMETER_COUNT)
        event, self.last_event = self.last_event, None
        return "" if event is None else event_message(*event)

    def _vr(self, params: list[float]) -> str:
        if params:
            raise CommandError(PARAMETER_COUNT)
        return f"{MODELS[self.channels]} (HW02) V031"


def event_message(channel: int, code: int) -> str:
    """13.5: `Evt<channel>,<event code>;`."""
    return f"Evt{channel},{code};"


def _number(text: str) -> float:
    if not NUMBER.fullmatch(text):
        raise CommandError(BAD_NUMBER)
    return float(text)


class GardasoftEmulator:
    """The controller listening on host:port (port 0: a free one, `address` says which), served
    by one thread; a context manager. `received`: every command line, as bytes up to and
    including its CR."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, channels: int = 4) -> None:
        self.controller = Controller(channels)
        self.received: list[bytes] = []
        self.lock = threading.Lock()
        self._listener = socket.create_server((loopback(host, "gardasoft_emulator"), port))
        self._listener.setblocking(False)
        self.address = self._listener.getsockname()[:2]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self._clients: dict[socket.socket, bytes] = {}      # socket -> bytes not yet a whole line
        self._last_client: socket.socket | None = None      # where event messages go (13.5)
        self._silent = False
        self._armed: dict[int, Fault] = {}          # command number -> fault or event to fire then
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self.serve, name="gardasoft-emulator", daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def inject(self, fault: Fault, on_command: int | None = None) -> None:
        """Fault "silent" or "drop", or an error event (channel, code): now, or when the
        on_command-th command line (counting from 1 since the start) arrives."""
        if fault not in FAULTS and not (isinstance(fault, tuple) and len(fault) == 2):
            raise ValueError(f"fault {fault!r}: expected one of {FAULTS} or (channel, event code)")
        with self.lock:
            if on_command is None:
                self._fire(fault)
            else:
                self._armed[on_command] = fault

    def _fire(self, fault: Fault) -> None:
        if fault == "silent":
            self._silent = True
        elif fault == "drop":
            for sock in list(self._clients):
                self._drop(sock)
        elif isinstance(fault, tuple):
            self.controller.last_event = fault
            if self.controller.messages and self._last_client in self._clients:
                self._send(self._last_client, event_message(*fault))

    def serve(self, max_seconds: float | None = None) -> None:
        """Accept clients and answer their command lines until close() (or max_seconds)."""
        deadline = None if max_seconds is None else time.monotonic() + max_seconds
        while not self._stop.is_set() and (deadline is None or time.monotonic() < deadline):
            for key, _ in self._selector.select(0.05):
                with self.lock:
                    if key.fileobj is self._listener:
                        self._accept()
                    elif key.fileobj in self._clients:
                        self._read(key.fileobj)
        self._close_sockets()

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        self._clients[sock] = b""
        self._selector.register(sock, selectors.EVENT_READ)

    def _read(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(4096)
        except OSError:
            data = b""
        if not data:
            return self._drop(sock)
        buffer = self._clients[sock] + data
        while b"\r" in buffer:
            line, _, buffer = buffer.partition(b"\r")
            self._clients[sock] = buffer
            self._line(sock, line)
            if sock not in self._clients:           # dropped by a fault
                return
        self._clients[sock] = buffer

    def _line(self, sock: socket.socket, line: bytes) -> None:
        self.received.append(line + b"\r")
        self._last_client = sock
        fault = self._armed.pop(len(self.received), None)
        if fault is not None:
            self._fire(fault)
        if self._silent or sock not in self._clients:
            return
        self._send(sock, self.controller.answer(line.decode("ascii", "replace").strip("\n")))

    def _send(self, sock: socket.socket, text: str) -> None:
        try:
            sock.sendall(text.encode("ascii"))
        except OSError:
            self._drop(sock)

    def _drop(self, sock: socket.socket) -> None:
        self._clients.pop(sock, None)
        self._selector.unregister(sock)
        sock.close()

    def _close_sockets(self) -> None:
        with self.lock:
            for sock in list(self._clients):
                self._drop(sock)
            self._selector.unregister(self._listener)
            self._listener.close()
            self._selector.close()

    def close(self) -> None:
        """Stop serving and close every socket (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        elif self._listener.fileno() >= 0:
            self._close_sockets()


def _event(text: str) -> tuple[int, int]:
    channel, _, code = text.partition(",")
    return int(channel), int(code)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sim.gardasoft_emulator", description=__doc__.split("\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to listen on")
    parser.add_argument("--port", type=int, default=TCP_PORT, help="TCP port (0: any free port)")
    parser.add_argument("--channels", type=int, choices=sorted(MODELS), default=4, help="the model's channels")
    parser.add_argument("--max-seconds", type=float, default=600.0, help="end after this long")
    parser.add_argument("--fault", choices=FAULTS, help="go silent or drop the connection")
    parser.add_argument("--fault-on-command", type=int, default=1, help="at this command line (1 = first)")
    parser.add_argument("--event", type=_event, help="send the error event C,E (channel, code)")
    parser.add_argument("--event-on-command", type=int, default=1, help="at this command line (1 = first)")
    args = parser.parse_args(argv)
    emulator = GardasoftEmulator(args.host, args.port, args.channels)
    if args.fault:
        emulator.inject(args.fault, on_command=args.fault_on_command)
    if args.event:
        emulator.inject(args.event, on_command=args.event_on_command)
    host, port = emulator.address
    print(f"READY {host}:{port}", flush=True)
    try:
        emulator.serve(args.max_seconds)
    except KeyboardInterrupt:
        emulator.close()


if __name__ == "__main__":
    main()
