"""The lighting controller: a Gardasoft RT-series multi-channel LED controller (RT220, RT420,
RT820F) over Ethernet, standard-library sockets only.

From the RTxxx LED lighting controllers user manual (section numbers are the manual's):
- 12.1 Ethernet configuration: TCP commands to port 30313; a carriage return (ASCII 13) ends a
  command line.
- 12.3 Command structure: the last character of every reply is `>`; the host waits for it
  before sending the next command.
- 12.3.1 General commands: `VR` reports the firmware (`RT420-20 (HW02) V031`: model RT420, whose
  middle digit is its channel count); `STc` reports channel c's settings; `GT1` turns on the
  event messages, sent to the address of the last command.
- 12.3.2 Lighting channel commands: `RSc,s` sets channel c to continuous mode at s percent
  (0..100) of full brightness.
- 13.3 Error codes: a refused command is answered `Err n` (1 invalid parameter, 2 command not
  recognised, 3 a number's format, 4 the number of parameters, 5 a parameter adjusted into range).
- 13.5 Event codes: `Evt<channel>,<event code>;` (channel 0: none); 128 (a light connected and
  working) and 138 (SafePower train-up completed) report no error, the others do (EVENTS).
The reply to `STc` is not given whole in the manual's pages found: it lists the report's
abbreviations (RA and CS the light's rating, IP the input trigger, FL flags) and shows the ST0
reply as `KEY value` pairs separated by commas (`TM 1, TP 20.00ms`). Read here in that form: the
channel's setting is the `S` field in percent (`%` optional) and a `CH` field, if there, must
be the channel asked - the form the loopback emulator (sim/gardasoft_emulator.py, written from
the same manual) answers. A real controller answering otherwise is a DeviceFault saying so,
never a wrong level.
"""
import re
import socket
import time

from cell.core.errors import DeviceFault
from cell.devices.interfaces import LightController
from cell.task.device_config import LightingConfig

PROMPT = b">"
ERROR = re.compile(r"Err\s*(\d+)")
EVENT = re.compile(r"Evt\s*(\d+)\s*,\s*(\d+)\s*;?")
MODEL = re.compile(r"RT(\d)\d0")                  # RT220, RT420, RT820F: the channel count
NO_ERROR_EVENTS = {128, 138}
EVENTS = {129: "a light connected without a current or voltage rating",
          130: "over temperature", 131: "over current",
          132: "an error while autosensing the rating of a light",
          139: "SafePower train-up failed or cancelled",
          140: "switched mode: the light turned off, duty cycle too high"}
ERRORS = {1: "a parameter value is invalid", 2: "command not recognised",
          3: "a number in the wrong format", 4: "wrong number of parameters",
          5: "a parameter out of range, adjusted"}
PERCENT_STEP = 0.1                                # the resolution RS is sent with [%]


class GardasoftController(LightController):
    """Channels 1..config.channels of the controller at config.host:config.port: each set
    (`RSc,s`) read back (`STc`), event messages on (`GT1`) and every reply's error events and
    `Err n` turned into a DeviceFault naming the controller, its address and the channel. A
    connection refused, dropped or silent past timeout_s is a DeviceFault too; after a lost
    connection every command is refused unsent, except all_off, which connects again first.

    read_only (`cell hw-check`): connected and asked `VR`, nothing sent that changes a setting
    (no `GT1`), so only state() and drive() are meant to be used."""

    def __init__(self, config: LightingConfig, read_only: bool = False) -> None:
        super().__init__(config.channels, f"Gardasoft controller at {config.host}:{config.port}")
        self.config, self.read_only = config, read_only
        self.firmware: str | None = None
        self._sock: socket.socket | None = None
        self._buffer = b""
        self._lost: str | None = None              # why the connection is gone, once it is
        self._connect()

    def _connect(self) -> None:
        """A new connection; messages on (not read-only), the firmware read, the model's channel
        count checked against the configured one (all_off must reach every channel)."""
        self.close()
        self._buffer, self._lost = b"", None
        try:
            self._sock = socket.create_connection((self.config.host, self.config.port),
                                                  timeout=self.config.timeout_s)
        except OSError as err:
            self._sock = None
            raise DeviceFault(self.device, f"{self.name}: cannot connect ({type(err).__name__}: {err})") from None
        try:
            if not self.read_only:
                self.command("GT1")
            self.firmware = self.command("VR").strip()
            mismatch = self.model_mismatch()
            if mismatch and not self.read_only:
                raise DeviceFault(self.device, f"{self.name}: {mismatch}")
        except DeviceFault:
            self.close()
            raise

    def model_mismatch(self) -> str | None:
        """Why the firmware's model contradicts the configured channel count, or None (agrees,
        or the model cannot be read from the firmware text)."""
        model = MODEL.search(self.firmware or "")
        if model and int(model.group(1)) != self.channels:
            return (f"firmware '{self.firmware}' is a {model.group(1)}-channel model, "
                    f"cell.lighting.channels is {self.channels}")
        return None

    def command(self, text: str) -> str:
        """Send one command line and return its reply without the prompt `>` and without event
        messages; an error event or `Err n` in the reply is a DeviceFault, as is no `>` within
        timeout_s or a connection gone."""
        sock = self._sock
        if self._lost or sock is None:
            raise DeviceFault(self.device, f"{self.name}: {self._lost or 'not connected'}: {text} not sent")
        try:
            sock.sendall(text.encode("ascii") + b"\r")
            reply = self._reply(sock, text)
        except OSError as err:                      # refused, reset, broken pipe
            self._lost = f"connection lost ({type(err).__name__}: {err})"
            raise DeviceFault(self.device, f"{self.name}: {self._lost}") from None
        if self._lost:
            raise DeviceFault(self.device, f"{self.name}: {self._lost}")
        self._raise_events(reply)
        error = ERROR.search(reply)
        if error:
            code = int(error.group(1))
            raise DeviceFault(self.device, f"{self.name}: {text} answered Err {code} "
                                           f"({ERRORS.get(code, 'see the manual, 13.3')})")
        return EVENT.sub("", reply).strip()

    def _reply(self, sock: socket.socket, text: str) -> str:
        """The bytes up to the next `>` (what follows stays for the next reply), waited for at
        most timeout_s; sets _lost when the connection closes or the time is up."""
        deadline = time.monotonic() + self.config.timeout_s
        while PROMPT not in self._buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._lost = f"no reply ending in '>' to {text} within {self.config.timeout_s:g} s"
                return ""
            sock.settimeout(remaining)
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            if not data:
                self._lost = f"connection closed by the controller (after {text})"
                return ""
            self._buffer += data
        reply, _, self._buffer = self._buffer.partition(PROMPT)
        return reply.decode("ascii", "replace")

    def _raise_events(self, reply: str) -> None:
        for channel, code in ((int(c), int(e)) for c, e in EVENT.findall(reply)):
            if code in NO_ERROR_EVENTS:
                continue
            meaning = f"error Err {code} ({ERRORS.get(code, 'see the manual, 13.3')})" if code < 128 \
                else EVENTS.get(code, "see the manual, 13.5")
            where = f"channel {channel}" if channel else "no channel"
            raise DeviceFault(self.device, f"{self.name}: {where}: event {code}: {meaning}")

    def _set_drive(self, channel: int, level: float) -> float:
        percent = round(level * 100 / PERCENT_STEP) * PERCENT_STEP
        sent = f"RS{channel},{percent:.1f}".removesuffix(".0")
        self.command(sent)
        read = self._read_drive(channel) * 100
        if abs(read - percent) > PERCENT_STEP / 2:
            raise DeviceFault(self.device, f"{self.name}: channel {channel} reads back {read:g} % "
                                           f"after {sent}")
        return read / 100

    def _read_drive(self, channel: int) -> float:
        reply = self.command(f"ST{channel}")
        fields = dict(part.strip().partition(" ")[::2] for part in re.split(r"[,\r\n]+", reply) if part.strip())
        if fields.get("CH", str(channel)).strip() != str(channel):
            raise DeviceFault(self.device, f"{self.name}: ST{channel} answered for channel {fields['CH']}")
        try:
            return float(fields["S"].strip().removesuffix("%")) / 100
        except (KeyError, ValueError):
            raise DeviceFault(self.device, f"{self.name}: ST{channel} answered {reply!r}, without "
                                           "the setting S in percent") from None

    def all_off(self) -> None:
        """Every channel to 0 %; after a lost connection on a new one first (a dropped
        connection leaves the lights as they were)."""
        if self._lost or self._sock is None:
            self._connect()
        super().all_off()

    def describe(self) -> dict:
        return {**super().describe(), "driver": "gardasoft", "firmware": self.firmware}

    def state(self) -> dict:
        """The firmware and every channel's level read back [0..1]; `problems`: a model whose
        channel count is not the configured one."""
        state = super().state()
        mismatch = self.model_mismatch()
        return {"firmware": self.firmware, **state, "problems": state["problems"] + ([mismatch] if mismatch else [])}

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
