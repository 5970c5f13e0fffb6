"""Each light channel's real share, measured with the cell: basis captures and the drives
re-solved on them.

Below saturation the gray is linear in each channel's drive, G = b + t / kappa^2 sum_k w_k u_k
(cell.planning.drives), so one capture per channel at a known drive w_k, the others off, measures
its real share s_k = w_k u_k t / kappa^2 at every feature sample, whatever the model got wrong
about it (its power, its pose, the material it lights); the lights on no channel are always on
and share one capture with every channel off. The same linear program the planner solved on
the model's shares is solved again on the measured ones. A channel whose measured share is far
below what the model predicts, while the others' are not, is a channel fault (a dead LED string,
its wiring, the controller), said as such: its own cause, not the material's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from cell.planning import drives as program
from cell.planning.plan import LightSetting

DEAD = 0.1      # a channel giving less than this of its predicted light (relative to the others') is dead
WEAK = 0.5      # ... less than this, far too weak: a fault, not a model error
LIT = 0.05      # a sample counts in a channel's scale where the model gives it this much of its brightest


@dataclass(frozen=True)
class Share:
    """One basis capture: the lights it lit (a channel's, or every light on no channel), at what
    drive, and their gray added at each feature sample (less the black level), predicted by the
    plan's model and measured (NaN where the sample is off the image)."""

    channel: int | None
    names: tuple[str, ...]
    drive: float
    predicted: np.ndarray
    measured: np.ndarray

    @property
    def scale(self) -> float:
        """Measured over predicted, the median over the samples the model lights (LIT); NaN when
        it lights none."""
        lit = (self.predicted > LIT * self.predicted.max(initial=0.0)) & np.isfinite(self.measured)
        return float(np.median(self.measured[lit] / self.predicted[lit])) if lit.any() else float("nan")

    def unit(self, gain: float) -> np.ndarray:
        """Gray per exposure at full drive at every sample, u = s / (w t / kappa^2): measured where
        the capture saw the sample, else the model's times the share's scale."""
        scale = self.scale if np.isfinite(self.scale) else 0.0
        share = np.where(np.isfinite(self.measured), np.maximum(self.measured, 0.0), scale * self.predicted)
        return share / (self.drive * gain)

    def label(self) -> str:
        return (f"channel {self.channel} ({', '.join(self.names)})" if self.channel is not None
                else f"the lights on no channel ({', '.join(self.names)})")


@dataclass(frozen=True)
class Basis:
    """The basis captures of one feature and the drives re-solved on their measured shares
    (cell.planning.drives.Drives, its drive per Share in order)."""

    shares: tuple[Share, ...]
    solved: program.Drives

    def relative(self) -> np.ndarray:
        """Each share's scale over the median of all (its own where it is the only one): a
        channel alone off from the rest is the channel's fault, all off alike the material's."""
        scales = np.array([s.scale for s in self.shares])
        if len(scales) < 2 or not np.isfinite(scales).any():
            return scales
        return scales / max(float(np.nanmedian(scales)), 1e-12)

    def failing(self) -> list[tuple[Share, float, str]]:
        """(share, relative scale, 'dead' | 'far too weak') of the channels that give far less
        light than the others do against the model."""
        out = []
        for share, r in zip(self.shares, self.relative()):
            if share.channel is not None and np.isfinite(r) and r < WEAK:
                out.append((share, float(r), "dead" if r < DEAD else "far too weak"))
        return out

    def describe(self) -> str:
        parts = [f"{s.label()} at {s.drive:.0%}: {s.scale:.0%} of the predicted light" for s in self.shares]
        return "; ".join(parts) + f"; re-solved: {self.solved.message}"

    def to_json(self) -> dict[str, Any]:
        return {"channel_scale": {str(s.channel): s.scale for s in self.shares if s.channel is not None},
                "drives": {str(s.channel): float(w) for s, w in zip(self.shares, self.solved.drive)
                           if s.channel is not None},
                "shutter_s": self.solved.shutter_s, "f_number": self.solved.f_number,
                "margin_gray": self.solved.margin_gray, "feasible": self.solved.feasible,
                "basis_captures": len(self.shares)}

    def fault(self) -> str:
        """A channel fault in a process engineer's words ('' when none)."""
        return "; ".join(f"{share.label()} gives {r:.0%} of the light the model predicts, against the other "
                         f"channels: {kind} (its LEDs, their wiring or the controller's output)"
                         for share, r, kind in self.failing())


def joined(lights: Sequence[Sequence[LightSetting]]) -> list[LightSetting]:
    """The lights of one shot as several features' plans each hold them (the same lights in the
    same order, each with its gray on that feature's samples) as one list over all their samples,
    concatenated in the features' order."""
    first = lights[0]
    if any([x.name for x in other] != [x.name for x in first] for other in lights[1:]):
        raise ValueError("the features' plans hold different lights: not one shot's")
    return [replace(light, gray=np.concatenate([other[i].gray for other in lights])) for i, light in enumerate(first)]


def groups(lights: Sequence[LightSetting], drives: dict[int, float]) -> list[tuple[int | None, list[LightSetting]]]:
    """The basis captures to take: one per channel driven above 0, and one for the lights on no
    channel that light the feature (always on: every channel off)."""
    out: list[tuple[int | None, list[LightSetting]]] = [
        (light.channel, [light]) for light in lights if light.channel is not None and drives.get(light.channel, 0) > 0]
    fixed = [light for light in lights if light.channel is None and light.gray.max(initial=0.0) > 0]
    return out + ([(None, fixed)] if fixed else [])


def measure(lights: Sequence[LightSetting], drives: dict[int, float], gain_ratio: float, black: float,
            capture_with: Callable[[dict[int, float], str], np.ndarray]) -> list[Share]:
    """The Shares of the basis captures: capture_with({channel: level}, name) -> the gray at each
    feature sample of a capture at the aim's exposure; predicted, each light's planned gray (at
    its planned drive and the plan's exposure) scaled to the drive and by gain_ratio, the aim's
    exposure t / kappa^2 over the plan's."""
    shares = []
    for channel, members in groups(lights, drives):
        levels = {c: (level if c == channel else 0.0) for c, level in drives.items()}
        drive = 1.0 if channel is None else drives[channel]
        predicted = gain_ratio * sum((light.gray / max(light.drive, 1e-12) * drive for light in members),
                                     np.zeros_like(members[0].gray))
        name = f"channel-{channel}" if channel is not None else "no-channel"
        measured = capture_with(levels, name) - black
        shares.append(Share(channel, tuple(light.name for light in members), drive, predicted, measured))
    return shares


def resolve(shares: Sequence[Share], gain: float, band: tuple[ArrayLike, ArrayLike], black: float, kappa_open: float,
            shutter_range_s: tuple[float, float], f_number_range: tuple[float, float],
            channel_ranges: dict[int, tuple[float, float]], switched: dict[int, bool],
            drive_error: float) -> Basis:
    """The drive program (cell.planning.drives.solve_drives) on the measured shares: each share's
    gray per exposure at full drive u = s / (w t / kappa^2) over the samples every capture saw,
    its channel's drive range (the lights on no channel fixed at 1); the band (low, high) a number
    each or one per sample (a shot of several features: each sample its own feature's band)."""
    seen = np.all([np.isfinite(s.measured) for s in shares], axis=0)
    low, high = (np.broadcast_to(np.asarray(end, float), seen.shape)[seen] for end in band)
    unit = np.array([s.unit(gain)[seen] for s in shares])
    ranges = [(1.0, 1.0) if s.channel is None else channel_ranges[s.channel] for s in shares]
    on_off = [False if s.channel is None else switched[s.channel] for s in shares]
    solved = program.solve_drives(unit, (low, high), black, kappa_open, shutter_range_s, f_number_range, ranges, on_off,
                                  drive_error)
    return Basis(tuple(shares), solved)
