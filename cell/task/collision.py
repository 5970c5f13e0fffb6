"""The task's collision settings, `cell.collision` (docs/formats.md): its schema, read by load_task
with the rest of the task, and the typed, SI values cell.collision builds its scene from."""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Callable
from os import PathLike
from typing import Any

import numpy as np
import trimesh

from cell.core.errors import TaskError
from cell.task.schema import NON_NEGATIVE, Choice, Invalid, Number, Section, Text, ToSI, Vector, show

DEFAULT_CAMERA_SIZE_M = (0.06, 0.06, 0.10)     # a 29 mm machine-vision camera and its lens, rounded up
DEFAULT_CAMERA_OFFSET_M = 0.05                 # so the box runs from the flange to 10 cm past it
DEFAULT_LAMP_SIZE_M = (0.06, 0.06, 0.08)       # an LED spot's housing


@dataclass(frozen=True)
class CollisionConfig:
    """Padding [m] every two bodies that may not touch keep between them; the camera body's box
    (size [m], its centre offset_m along the tool axis from the flange); the lamp's box; the
    fixture's mesh (cell frame, metres) or None; the pan-tilt's reach, the tilt servo's front
    face from the pivot along the lamp's axis behind it [m] (None: the servo rides at the lamp's
    back, cell.collision.scene.rig_links)."""

    padding_m: float = 0.01
    camera_size_m: tuple[float, float, float] = DEFAULT_CAMERA_SIZE_M
    camera_offset_m: float = DEFAULT_CAMERA_OFFSET_M
    lamp_size_m: tuple[float, float, float] = DEFAULT_LAMP_SIZE_M
    fixture: trimesh.Trimesh | None = None
    rig_reach_m: float | None = None


class _Size(Vector):
    """A box's size [x, y, z], each positive."""

    def __init__(self, default: tuple[float, float, float]) -> None:
        super().__init__(default=default)
        self.expected = "a 3-vector [x, y, z] of positive lengths"

    def convert(self, raw: Any, to_si: ToSI) -> np.ndarray:
        v = super().convert(raw, to_si)
        if not np.all(v > 0):
            raise Invalid(raw, self.expected)
        return v


COLLISION = Section({
    "padding_m": Number(**NON_NEGATIVE, default=0.01),
    "camera_body": Section({
        "size_m": _Size(DEFAULT_CAMERA_SIZE_M),
        "offset_m": Number(lambda v: True, "a number", default=DEFAULT_CAMERA_OFFSET_M),
    }, required=False),
    "lamp_body": Section({
        "size_m": _Size(DEFAULT_LAMP_SIZE_M),
    }, required=False),
    "fixture_mesh": Text(default=None),
    "fixture_mesh_unit": Choice("m", "mm", default=None),
    "rig_reach_m": Number(lambda v: v > 0, "a positive number", default=None),
}, required=False)


def collision_config(file: str | PathLike[str], c: dict[str, Any], part_unit: str,
                     load_mesh: Callable[[str, str, str], trimesh.Trimesh], radius_max_m: float) -> CollisionConfig:
    """The parsed `cell.collision` -> CollisionConfig; the fixture's mesh read by `load_mesh(key,
    name, unit)` (the part's reader), its unit the part's unless fixture_mesh_unit says; a rig's
    reach no shorter than the spot's rig's largest radius (radius_max_m) plus the lamp's depth
    (the servo behind the lamp there)."""
    lamp_size = _triple(c["lamp_body"]["size_m"])
    reach, least = c["rig_reach_m"], radius_max_m + lamp_size[2]
    if reach is not None and reach < least - 1e-12:
        raise TaskError(file, "cell.collision.rig_reach_m", f"{reach:g} m ({1e3 * reach:g} mm)",
                        f"at least {least:g} m ({1e3 * least:g} mm), the rig's largest radius {radius_max_m:g} m "
                        f"plus the lamp's depth {lamp_size[2]:g} m (cell.collision.lamp_body.size_m): the tilt "
                        "servo stands behind the lamp")
    if c["fixture_mesh"] is None and c["fixture_mesh_unit"] is not None:
        raise TaskError(file, "cell.collision.fixture_mesh_unit", show(c["fixture_mesh_unit"]),
                        "nothing without cell.collision.fixture_mesh")
    fixture = None if c["fixture_mesh"] is None else load_mesh(
        "cell.collision.fixture_mesh", c["fixture_mesh"], c["fixture_mesh_unit"] or part_unit)
    return CollisionConfig(c["padding_m"], _triple(c["camera_body"]["size_m"]), c["camera_body"]["offset_m"],
                           lamp_size, fixture, reach)


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])
