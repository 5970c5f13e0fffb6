"""The ranges an inspection cell's physical keys can have, in one table (docs/formats.md says each
beside its key): a value the schema accepts (a positive length) but no cell has (a camera 500 m
from the part, a 20 s shutter, a 230 W LED) is most likely a unit slip, and is refused with the
unit that makes it plausible ("did you mean distance_mm: 500?").

A cell that does exceed a range widens it in the task's `limits:` section, by the row's key:
`limits: {camera.shutter_range_s: [1.0e-6, 60]}` (a position row takes its radius alone).
`attach(TASK)` gives each row's Spec its check and adds the range to its `expected` words; the
loader reads `limits` first and checks the rest under `widened(limits)`.
"""

from __future__ import annotations

import contextlib
import copy
import difflib
from collections.abc import Iterator, Mapping
from contextvars import ContextVar
from dataclasses import dataclass
from os import PathLike
from typing import Any

import numpy as np

from cell.core.errors import TaskError
from cell.task.schema import UNITS, Section, Sections, Spec, ToSI, _unit, schema_keys, show


@dataclass(frozen=True)
class Range:
    """A plausible SI value: a size within [low, high] (each element of a pair), or, for a
    position (low None), a point within `high` of its frame's origin."""

    low: float | None
    high: float
    quantity: str                      # length | time | power

    def holds(self, si: Any) -> bool:
        v = np.asarray(si, float)
        if self.low is None:
            return bool(np.linalg.norm(v) <= self.high)
        return bool(np.all((self.low <= v) & (v <= self.high)))

    def span(self) -> str:
        if self.low is None:
            return f"within {amount(self.high, self.quantity)} of the origin"
        return f"{amount(self.low, self.quantity)} to {amount(self.high, self.quantity)}"

    def words(self) -> str:
        return f"plausible: {self.span()}"


def amount(si: float, quantity: str) -> str:
    """An SI value in the largest unit that keeps it at least 1: `10 mm`, `1 us`, `230 mW`."""
    units = {"length": (("m", 1.0), ("mm", 1e-3), ("um", 1e-6)),
             "time": (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)),
             "power": (("W", 1.0), ("mW", 1e-3))}[quantity]
    for name, scale in units:
        if abs(si) >= scale:
            break
    return f"{si / scale:g} {name}"


L, T, P = "length", "time", "power"


def _size(low: float, high: float, quantity: str = L) -> Range:
    return Range(low, high, quantity)


def _position(radius: float) -> Range:
    return Range(None, radius, L)


# Every plausible range, by the key's dotted SI name (`[]`: each entry of a list). The arm is a
# UR5e (0.85 m reach) in a cell of a few metres: poses within 2 m of the cell's origin, a camera
# within 2 m of its feature; cameras expose between 1 us and 10 s; an LED lamp emits 10 mW to
# 100 W of light; a defect is a scratch 1 um to 10 mm wide, 0.1 um to 5 mm deep, a dent or a coating
# patch 10 um to 100 mm across; the rest what optics and parts of an inspection have.
RANGES: dict[str, Range] = {
    "part.position_m": _position(2.0),
    "feature.center_m": _position(1.0),
    "feature.radius_m": _size(5e-5, 0.5),
    "features[].center_m": _position(1.0),
    "features[].radius_m": _size(5e-5, 0.5),
    "feature.defects[].width_m": _size(1e-6, 0.01),
    "feature.defects[].depth_m": _size(1e-7, 0.005),
    "feature.defects[].radius_m": _size(1e-5, 0.1),
    "feature.defects[].position_m": _position(1.0),
    "features[].defects[].width_m": _size(1e-6, 0.01),
    "features[].defects[].depth_m": _size(1e-7, 0.005),
    "features[].defects[].radius_m": _size(1e-5, 0.1),
    "features[].defects[].position_m": _position(1.0),
    "features[].requirements.depth_of_field_m": _size(0.0, 0.5),
    "features[].requirements.resolution_m": _size(1e-6, 0.01),
    "requirements.depth_of_field_m": _size(0.0, 0.5),
    "requirements.resolution_m": _size(1e-6, 0.01),
    "camera.distance_m": _size(0.01, 2.0),
    "camera.sensor.pixel_pitch_m": _size(5e-7, 5e-5),
    "camera.lens.focal_length_m": _size(1e-3, 1.0),
    "camera.lens.circle_of_confusion_m": _size(5e-7, 5e-4),
    "camera.shutter_range_s": _size(1e-6, 10.0, T),
    "camera.standoff_range_m": _size(0.01, 2.0),
    "lamp.power_w": _size(0.01, 100.0, P),
    "lamp.rig.pivot_m": _position(2.0),
    "lamp.rig.radius_range_m": _size(0.02, 2.0),
    "lights[].power_w": _size(0.01, 100.0, P),
    "lights[].position_m": _position(2.0),
    "lights[].aim_m": _position(2.0),
    "lights[].offset_m": _size(-1.0, 1.0),
    "lights[].radius_m": _size(1e-3, 1.0),
    "lights[].length_m": _size(1e-3, 2.0),
    "lights[].size_m": _size(1e-3, 2.0),
    "lights[].hole_radius_m": _size(5e-4, 1.0),
    "lights[].housing_depth_m": _size(1e-3, 1.0),
    "lights[].aperture_radius_m": _size(5e-4, 1.0),
    "lights[].outer_radius_m": _size(1e-3, 1.0),
    "lights[].rig.pivot_m": _position(2.0),
    "lights[].rig.radius_range_m": _size(0.02, 2.0),
    "cell.arm.connect_timeout_s": _size(0.05, 600.0, T),
    "cell.arm.base_position_m": _position(2.0),
    "cell.arm.hand_eye_position_m": _position(0.5),
    "cell.arm.workspace_min_m": _position(3.0),
    "cell.arm.workspace_max_m": _position(3.0),
    "cell.arm.move_timeout_s": _size(0.05, 600.0, T),
    "cell.pan_tilt.move_timeout_s": _size(0.05, 600.0, T),
    "cell.camera.exposure_unit_s": _size(1e-7, 1.0, T),
    "cell.camera.frame_timeout_s": _size(0.05, 600.0, T),
    "cell.lighting.timeout_s": _size(0.05, 600.0, T),
    "sim.truth.part_offset_m": _position(0.5),
    "sim.truth.camera_offset_m": _position(0.5),
    "sim.truth.lamp_radius_error_m": _size(-0.5, 0.5),
    "calibration.sample.radius_m": _size(1e-3, 0.5),
    "calibration.sample.thickness_m": _size(1e-4, 0.1),
    "calibration.goniometer.lamp_radius_m": _size(0.02, 2.0),
    "calibration.board.square_size_m": _size(1e-3, 0.2),
    "calibration.board.marker_size_m": _size(5e-4, 0.2),
    "calibration.board.position_m": _position(2.0),
    "loop.registration_limit_m": _size(1e-5, 0.1),
    "cell.collision.padding_m": _size(0.0, 0.5),
    "cell.collision.camera_body.size_m": _size(5e-3, 1.0),
    "cell.collision.camera_body.offset_m": _size(-0.5, 0.5),
    "cell.collision.lamp_body.size_m": _size(5e-3, 1.0),
    "cell.collision.rig_reach_m": _size(0.02, 3.0),
}
# a mesh's largest side in the cell's units (a part's; a fixture or a table, a few metres): its
# `_unit` key is blamed when it is not
MESHES = {"part.mesh": _size(1e-3, 2.0), "cell.collision.fixture_mesh": _size(1e-3, 5.0)}
RANGES |= MESHES

_LIMITS: ContextVar[Mapping[str, Range]] = ContextVar("plausible_limits", default=RANGES)


@contextlib.contextmanager
def widened(limits: Mapping[str, Range]) -> Iterator[None]:
    """Check the keys read inside with the task's `limits` in place of the table's rows."""
    token = _LIMITS.set({**RANGES, **limits})
    try:
        yield
    finally:
        _LIMITS.reset(token)


def _hint(written: str, raw: Any, row: Range) -> str:
    """'; did you mean distance_mm: 500?' where another unit of the key's quantity makes the value
    as written plausible, the nearest unit first; else ''."""
    base, suffix = _unit(written)
    if suffix is None:
        return ""
    one = UNITS[suffix][1](1.0)
    others = [u for u, (q, _) in UNITS.items() if q == row.quantity and u != suffix]
    for u in sorted(others, key=lambda u: abs(np.log(UNITS[u][1](1.0) / one))):
        if row.holds(UNITS[u][1](np.asarray(raw, float))):
            return f"; did you mean {base}_{u}: {show(raw)}?"
    return ""


class Check:
    """The plausibility check one row gives its Spec (schema.Spec.read calls it on each value read)."""

    def __init__(self, key: str) -> None:
        self.key = key

    def __call__(self, file: str | PathLike[str], path: str, raw: Any, si: Any) -> None:
        row = _LIMITS.get()[self.key]
        if row.holds(si):
            return
        written = path.rpartition(".")[2]
        widen = "radius" if row.low is None else "[low, high]"
        raise TaskError(file, path, show(raw),
                        f"{row.span()}, as an inspection cell has{_hint(written, raw, row)} "
                        f"(a cell beyond it: `limits: {{{self.key}: {widen}}}` in the task)")


def attach(schema: Mapping[str, Spec]) -> None:
    """Give each Spec of `schema` that has a row its Check and its range in its `expected` words.
    A Spec shared by two keys must be given one of them (copied first): each row its own."""
    seen = set()
    for key, spec in schema_keys(schema):
        if key not in RANGES or key in MESHES:
            continue
        if getattr(spec, "plausible", None) is not None or id(spec) in seen:
            raise ValueError(f"{key}: its Spec serves another key too; give it a copy")
        seen.add(id(spec))
        spec.plausible = Check(key)
        spec.expected = f"{spec.expected} ({RANGES[key].words()})"
    missing = set(RANGES) - {key for key, _ in schema_keys(schema)} - set(MESHES)
    if missing:
        raise ValueError(f"rows of no key: {sorted(missing)}")


def copied(fields: Mapping[str, Spec]) -> dict[str, Spec]:
    """A schema's keys with Specs of their own (a section's keys too), so that attach can give
    each its row; defaults (schema.REQUIRED above all) stay the same objects."""
    def own(spec):
        mine = copy.copy(spec)
        if isinstance(mine, (Section, Sections)):
            mine.fields = copied(spec.fields)
        return mine
    return {key: own(spec) for key, spec in fields.items()}


class Limits(Spec):
    """The task's `limits`: {a row's key: its range widened}, [low, high] in the key's SI unit, or
    a radius for a position row."""

    expected = "a mapping of plausible-range keys to [low, high] (a position's: its radius)"
    default: dict[str, Range] = {}

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> dict[str, Range]:
        if not isinstance(raw, dict):
            raise TaskError(file, path, show(raw), self.expected)
        out = {}
        for key, value in raw.items():
            row, where = RANGES.get(str(key)), f"{path}.{key}"
            if row is None:
                hint = difflib.get_close_matches(str(key), list(RANGES), n=1)
                raise TaskError(file, where, "an unknown key", "a key of the plausible ranges (docs/formats.md), "
                                "such as camera.distance_m" + (f"; did you mean '{hint[0]}'?" if hint else ""))
            number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)  # noqa: E731
            if row.low is None:
                if not (number(value) and value > 0):
                    raise TaskError(file, where, show(value), "a positive radius [m] (a position's range)")
                out[str(key)] = Range(None, float(value), row.quantity)
            else:
                if not (isinstance(value, list) and len(value) == 2 and all(map(number, value))
                        and value[0] <= value[1]):
                    raise TaskError(file, where, show(value), "an ascending pair [low, high] in the key's SI unit")
                out[str(key)] = Range(float(value[0]), float(value[1]), row.quantity)
        return out

    def convert(self, raw: Any, to_si: ToSI) -> dict[str, Range]:
        raise NotImplementedError            # read() checks the mapping itself


def check_mesh(file: str | PathLike[str], key: str, unit: str, extents_m: np.ndarray, name: str) -> None:
    """The mesh at `key` (`part.mesh`, `cell.collision.fixture_mesh`) plausible in size in the
    cell's units, else its unit key (`key`_unit) is refused with the other unit when that one is
    plausible."""
    row = _LIMITS.get()[key]
    if row.holds(float(np.max(extents_m))):
        return
    other = {"m": ("mm", 1e-3), "mm": ("m", 1e3)}[unit]
    size = " x ".join(f"{e:.4g}" for e in extents_m)
    written = key.rpartition(".")[2] + "_unit"
    hint = f"; did you mean {written}: {other[0]}?" if row.holds(float(np.max(extents_m)) * other[1]) else ""
    whose = "a part" if key == "part.mesh" else "a fixture"
    raise TaskError(file, f"{key}_unit", f"{unit}, which makes {name} {size} m",
                    f"the unit of the mesh's coordinates, {whose}'s largest side "
                    f"{row.span()}{hint} "
                    f"(a {whose[2:]} beyond it: `limits: {{{key}: [low, high]}}` in the task)")
