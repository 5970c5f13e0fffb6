"""Simulated lighting controller: channels 1..channels each holding the drive level last set
(0..1, all off at power-up), read back as held, as the simulated camera's renderer reads them
(sim.world.Renderer: each light at its channel's level)."""

from __future__ import annotations

from cell.core.errors import DeviceFault
from cell.devices.interfaces import LightController

OVER_CURRENT = 131           # the RT manual's event code (13.5) the injected fault reports


class SimLightController(LightController):
    """Fault injection: set number `fail_on_set` (counting every set_drive from 1, all_off's
    included) is refused with the controller's over-current event, the channel left as it was."""

    def __init__(self, channels: int, fail_on_set: int | None = None) -> None:
        super().__init__(channels, "simulated lighting controller")
        self.levels_set = {c: 0.0 for c in range(1, channels + 1)}
        self.sets = 0
        self.fail_on_set = fail_on_set

    def _set_drive(self, channel: int, level: float) -> float:
        self.sets += 1
        if self.sets == self.fail_on_set:
            raise DeviceFault(self.device, f"{self.name}: channel {channel}: event {OVER_CURRENT}: over current "
                                           f"(set {self.sets}, injected)")
        self.levels_set[channel] = level
        return level

    def _read_drive(self, channel: int) -> float:
        return self.levels_set[channel]

    def describe(self) -> dict:
        return {**super().describe(), "driver": "simulated"}
