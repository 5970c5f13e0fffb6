"""The contrast-to-noise ratio each declared defect shows in a capture, as cell.physics.contrast
defines it: the defect's pixels against the good surface beside it,
CNR = |G_defect - G_good| / sqrt(sigma(G_good)^2 + sigma(G_defect)^2), G_defect the mean over a
part of the defect, G_good the good neighbours' gray there (a plane in the tangent plane's x, y
fitted to them: the light's gradient across the defect cancels) and sigma the EMVA 1288 temporal
noise of one pixel at that gray (the camera's datasheet keys, as planned: one capture must do).

Where the pixels are: each pixel's ray (moved back by the registration's shift) meets the
feature's tangent plane through the defect's position (position_m, else the feature's centre)
at an offset that contrast.footprint sorts: on the defect, or its good neighbours, the pixels
between GUARD_PX and GUARD_PX + BAND_PX pixel footprints beyond its edge (beside a scratch's
groove, around a disk), within the feature and clear of the other defects; a scratch within
NEAR_PX footprints of its position along it (where the planner's CNR at that point holds: the
light changes along a groove the feature's width long). Per part, as the
planner judges it (cell.planning.defects): a scratch's two walls (the larger CNR), a dent's rim
(its outer RIM_PX footprint: the steepest tilts) at its best azimuth (_rim: its gray a Fourier
series in the azimuth), a coating's disk. A scratch's orientation is not declared, only its
range: it is found as the one whose walls show the largest CNR, every COARSE_PX pixel footprints
at the feature's edge (at most MAX_ORIENTATIONS over the range), then FINE times finer about the
best.

A mean over n pixels has sigma / sqrt(n), so the measured CNR scatters about the true one by
about sqrt(1 / n_defect + 1 / n_good) / sqrt(2) in CNR units (tests/test_defects.py's tolerance).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.core import geometry
from cell.physics import contrast, projection
from cell.planning import defects as planned

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import Defect, Task

GUARD_PX = 1.5          # neighbours start this many pixel footprints beyond the defect's edge
BAND_PX = 4.0           # and span this many
RIM_PX = 1.0            # a dent's rim: its outer pixel footprint (its contrast grows fastest there)
MIN_PIXELS = 4          # a part or neighbourhood with fewer is not measured
RIM_ORDER = 6           # a dent's rim gray: a Fourier series in azimuth to this order
RIM_PIXELS = 4          # with at least this many rim pixels per coefficient
COARSE_PX = 4.0         # a scratch's orientations tried this many pixel footprints apart at the feature's edge,
FINE = 16               # then this many times finer about the best (a quarter footprint)
MAX_ORIENTATIONS = 720
NEAR_PX = 32.0          # a scratch is measured within this many pixel footprints of its position along it


@dataclass(frozen=True)
class MeasuredDefect:
    """One declared defect in one capture: the plan's predicted CNR (the worst over the feature
    and the orientations) and the measured one at the defect's place (None: too few of its
    pixels in view), with the grays and the pixel counts behind it and a scratch's orientation
    as found [rad]."""

    name: str
    kind: str
    min_cnr: float
    predicted_cnr: float | None
    measured_cnr: float | None
    gray_good: float | None = None
    gray_defect: float | None = None
    pixels: int = 0
    neighbours: int = 0
    orientation_rad: float | None = None

    def describe(self) -> str:
        """'4.2 measured, 5.1 predicted' (its measured CNR against the plan's)."""
        measured = "not measured" if self.measured_cnr is None else f"{self.measured_cnr:.1f} measured"
        return measured + ("" if self.predicted_cnr is None else f", {self.predicted_cnr:.1f} predicted")

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "min_cnr": self.min_cnr, "predicted_cnr": self.predicted_cnr,
                "measured_cnr": self.measured_cnr, "gray_good": self.gray_good, "gray_defect": self.gray_defect,
                "pixels": self.pixels, "neighbours": self.neighbours,
                "orientation_deg": None if self.orientation_rad is None else float(np.degrees(self.orientation_rad))}


@dataclass(frozen=True)
class _Pixels:
    """The capture's pixels around the feature: their gray and where their rays meet the
    feature's tangent plane, in the feature frame's (x, y) from its centre [m]."""

    gray: np.ndarray
    xy: np.ndarray
    footprint_m: float
    row: np.ndarray
    col: np.ndarray


def unseen(found: Sequence[MeasuredDefect]) -> str | None:
    """Why a capture whose gray is in band still fails its inspection: the declared defects that
    measure below their min_cnr, each with its measured and planned CNR (None: every measured
    defect shows; one too little in view to measure is not judged)."""
    missed = [d for d in found if d.measured_cnr is not None and d.measured_cnr < d.min_cnr]
    if not missed:
        return None
    said = "; ".join(f"the {d.kind} '{d.name}' shows with CNR {d.measured_cnr:.1f} over the sensor's noise, "
                     f"{d.min_cnr:g} wanted" + ("" if d.predicted_cnr is None else f" ({d.predicted_cnr:.1f} planned)")
                     for d in missed)
    return (f"{said}: the inspection would miss {'it' if len(missed) == 1 else 'them'} though the gray is in "
            f"band; light from across the defect or expose longer (cell plan says which)")


def _pixels(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray,
            shift_px: tuple[float, float]) -> _Pixels:
    centre, frame, radius = scene.center, scene.frame, task.feature.radius_m
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    ring = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    rim = centre + radius * (np.cos(ring)[:, None] * frame[:, 0] + np.sin(ring)[:, None] * frame[:, 1])
    uv, _ = projection.project(K, T_cell_cam, rim)
    uv = uv + np.asarray(shift_px, float)
    h, w = np.shape(image)[:2]
    lo = np.clip(np.floor(np.nanmin(uv, axis=0)) - 2, 0, [w - 1, h - 1]).astype(int)
    hi = np.clip(np.ceil(np.nanmax(uv, axis=0)) + 2, 0, [w - 1, h - 1]).astype(int)
    grid_u, grid_v = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    u, v = grid_u.ravel(), grid_v.ravel()
    model = np.column_stack([u - shift_px[0], v - shift_px[1], np.ones(len(u))])
    rays = geometry.rotate(T_cell_cam, model @ np.linalg.inv(K).T)
    origin = T_cell_cam[:3, 3]
    along = rays @ frame[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((centre - origin) @ frame[:, 2]) / along
    hit = np.isfinite(t) & (t > 0)
    xy = ((origin + t[hit, None] * rays[hit]) - centre) @ frame[:, :2]
    distance = float(np.linalg.norm(centre - origin))
    footprint = task.camera.sensor.pixel_pitch_m * distance / task.camera.lens.focal_length_m
    return _Pixels(np.asarray(image, float)[v[hit], u[hit]], xy, footprint, v[hit], u[hit])


def _position_xy(task: Task, scene: Scene, d: Defect) -> np.ndarray:
    """A defect's position (x, y) in the feature frame from the feature's centre (the planned
    part pose: the registration's shift carries the part's true one)."""
    if d.position_m is None:
        return np.zeros(2)
    position = geometry.apply(task.frames.T_cell_part, np.asarray(d.position_m, float))
    return (position - scene.center) @ scene.frame[:, :2]


def _outside(d: Defect, xy: np.ndarray, theta: float, at: np.ndarray, radius: float,
             near_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """contrast.footprint of the pixels for defect d at `at` (x, y) (a scratch along theta, its
    chord cut to within near_m of its position)."""
    if d.kind == "scratch":
        t0, t1 = contrast.scratch_chord(at, theta, radius)
        return contrast.footprint(xy - at, "scratch", theta, float(d.width_m or 0.0),
                                  chord_m=(max(t0, -near_m), min(t1, near_m)))
    return contrast.footprint(xy - at, d.kind, radius_m=float(d.radius_m or 0.0))


def measure(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray, shift_px: tuple[float, float],
            black_level: float, predicted: Mapping[str, float]) -> tuple[MeasuredDefect, ...]:
    """Each defect of the one-feature task's feature in a capture from T_cell_cam, the feature
    (the planned Scene's) found shift_px (dx, dy) from where the model puts it, with black level
    b [gray]; predicted: the plan's CNR by the defect's name (Shot.defects). The dents
    and coatings are where declared; each scratch is found first, clear of them and of the
    scratches found before it; then each disk, clear of the others and of the scratches found."""
    feature = task.feature
    if not feature.defects:
        return ()
    px = _pixels(image, task, scene, T_cell_cam, shift_px)
    radius, guard = feature.radius_m, GUARD_PX * px.footprint_m
    within = np.hypot(px.xy[:, 0], px.xy[:, 1]) <= radius
    at = {d.name: _position_xy(task, scene, d) for d in feature.defects}
    disks = {d.name: _outside(d, px.xy, 0.0, at[d.name], radius)[1] < guard
             for d in feature.defects if d.kind != "scratch"}
    K, dark, full = planned.noise_of(task.camera.sensor)
    noise = (black_level, K, dark, full)
    strips = np.zeros(len(px.gray), bool)
    found: dict[str, MeasuredDefect] = {}
    for d in sorted(feature.defects, key=lambda d: d.kind != "scratch"):
        usable = within & ~strips
        for name, reach in disks.items():
            if name != d.name:
                usable &= ~reach
        thetas = _orientations(d, radius, px.footprint_m) if d.kind == "scratch" else np.zeros(1)
        best = _best(d, px, usable, thetas, at[d.name], radius, noise)
        if best is not None and len(thetas) > 1:          # then every FINE-th of a step about it
            step = float(thetas[1] - thetas[0])
            lo, hi = d.orientation_rad
            finer = best[5] + step * np.arange(-FINE, FINE + 1) / FINE
            if hi - lo < np.pi:                            # else theta and theta + 180 deg are one groove
                finer = np.clip(finer, lo, hi)
            best = _best(d, px, usable, finer, at[d.name], radius, noise)
        if best is None:
            found[d.name] = MeasuredDefect(d.name, d.kind, d.min_cnr, predicted.get(d.name), None)
            continue
        value, good, bad, n, m, theta = best
        if d.kind == "scratch":
            strips |= _outside(d, px.xy, theta, at[d.name], radius)[1] < guard
        found[d.name] = MeasuredDefect(d.name, d.kind, d.min_cnr, predicted.get(d.name), value, good, bad, n, m,
                                       theta if d.kind == "scratch" else None)
    return tuple(found[d.name] for d in feature.defects)


def on_defects(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray, shift_px: tuple[float, float],
               found: Sequence[MeasuredDefect]) -> np.ndarray:
    """(H, W) the capture's pixels on the feature's declared defects or within GUARD_PX pixel
    footprints of their edges (a scratch along its orientation as found, else its range's first):
    what the gray band does not judge (a defect is meant to differ from the surface: a coating of
    twice the albedo would read as a spread the exposure cannot narrow)."""
    out = np.zeros(np.shape(image)[:2], bool)
    if not task.feature.defects:
        return out
    px = _pixels(image, task, scene, T_cell_cam, shift_px)
    theta = {m.name: m.orientation_rad for m in found}
    for d in task.feature.defects:
        along = theta.get(d.name)
        reach = _outside(d, px.xy, d.orientation_rad[0] if along is None else along, _position_xy(task, scene, d),
                         task.feature.radius_m)[1] < GUARD_PX * px.footprint_m
        out[px.row[reach], px.col[reach]] = True
    return out


def _best(d: Defect, px: _Pixels, usable: np.ndarray, thetas: np.ndarray, at: np.ndarray, radius: float,
          noise: tuple[float, float, float, float]) -> tuple[float, float, float, int, int, float] | None:
    """_cnr's largest over the orientations, with its orientation (None: none measurable)."""
    best: tuple[float, float, float, int, int, float] | None = None
    for theta in thetas:
        seen = _cnr(d, px, usable, float(theta), at, radius, noise)
        if seen is not None and (best is None or seen[0] > best[0]):
            best = seen + (float(theta),)
    return best


def _orientations(d: Defect, radius: float, fp: float) -> np.ndarray:
    """A scratch's candidate orientations over its range, COARSE_PX pixel footprints apart at the
    feature's edge (at most MAX_ORIENTATIONS): a groove turned by that still lies on its pixels
    near its position, so the best of them is next to the true one."""
    lo, hi = d.orientation_rad
    span = min(hi - lo, np.pi)
    n = int(min(MAX_ORIENTATIONS, max(1, np.ceil(span / (COARSE_PX * fp / max(radius, fp))))))
    return lo + span * np.arange(n + (hi - lo < np.pi - 1e-12)) / n


def _cnr(d: Defect, px: _Pixels, usable: np.ndarray, theta: float, at: np.ndarray, radius: float,
         noise: tuple[float, float, float, float]) -> tuple[float, float, float, int, int] | None:
    """(CNR, good gray, defect gray, its pixels, the neighbours) of the defect's best part at
    orientation theta, or None when too few pixels show it or its neighbours."""
    part, outside = _outside(d, px.xy, theta, at, radius, NEAR_PX * px.footprint_m)
    fp = px.footprint_m
    good = usable & (outside >= GUARD_PX * fp) & (outside <= (GUARD_PX + BAND_PX) * fp)
    on = usable & (part > 0)
    if good.sum() < MIN_PIXELS or on.sum() < MIN_PIXELS:
        return None
    plane = np.linalg.lstsq(np.column_stack([np.ones(int(good.sum())), px.xy[good]]), px.gray[good], rcond=None)[0]
    if d.kind == "dent":
        return _rim(px, on & (outside >= -RIM_PX * fp), at, plane, int(good.sum()), noise)
    best = None
    for group in ([on & (part == 1), on & (part == 2)] if d.kind == "scratch" else [on]):
        if group.sum() >= MIN_PIXELS:
            b = float(np.mean(px.gray[group]))
            g = float(plane @ np.concatenate([[1.0], px.xy[group].mean(axis=0)]))
            value = float(contrast.cnr(g, b, *noise))
            if best is None or value > best[0]:
                best = (value, g, b, int(group.sum()), int(good.sum()))
    return best


def _rim(px: _Pixels, rim: np.ndarray, at: np.ndarray, plane: np.ndarray, neighbours: int,
         noise: tuple[float, float, float, float]) -> tuple[float, float, float, int, int] | None:
    """A dent's rim: its gray as a Fourier series in the azimuth psi about its centre, to order
    RIM_ORDER (fewer where the rim has under RIM_PIXELS pixels per coefficient), fitted by least
    squares; the CNR at its best azimuth (every degree) against the neighbours' plane there. Its
    pixels: the rim's over the coefficients (what a mean's would be worth)."""
    n = int(rim.sum())
    order = min(RIM_ORDER, (n // RIM_PIXELS - 1) // 2)
    if order < 1:
        return None
    offset = px.xy[rim] - at
    radius = float(np.mean(np.hypot(offset[:, 0], offset[:, 1])))

    def basis(psi: np.ndarray) -> np.ndarray:
        k = np.arange(1, order + 1)
        return np.column_stack([np.ones(len(psi)), np.cos(np.outer(psi, k)), np.sin(np.outer(psi, k))])

    coef = np.linalg.lstsq(basis(np.arctan2(offset[:, 1], offset[:, 0])), px.gray[rim], rcond=None)[0]
    psi = np.radians(np.arange(360.0))
    gray = basis(psi) @ coef
    where = at + radius * np.column_stack([np.cos(psi), np.sin(psi)])
    good = np.column_stack([np.ones(len(psi)), where]) @ plane
    ratio = contrast.cnr(good, gray, *noise)
    k = int(np.argmax(ratio))
    return float(ratio[k]), float(good[k]), float(gray[k]), n // (2 * order + 1), neighbours
