"""Registration: where the feature really is in a capture. The model's image
of the part at the read-back camera and lamp poses (kernels.render, the planner's shading: the
task's material, lamp and camera constant), every light of the task shining at the capture's
read-back drives as the simulator renders them (cell.planning.lights.rendered), is aligned with
the capture, and the feature's
samples move by the shift found, so the measured region follows the feature as it appears.

Two steps. The model's window around the feature at 1/COARSE resolution, matched over the whole
capture by its edges (coarse_shift: of the image less its blur, high_pass, so that the lamp's
soft edge does not count), finds any shift that keeps it in the frame (a 2 deg hand-eye
tilt on the hinge is 188 px), to within a coarse pixel. cv2.findTransformECC (a translation and
a turn, MOTION_EUCLIDEAN, on intensity) then refines it to a fraction of a pixel in a window
around the feature, the shift being where the warp moves the feature's centre (a part turned
about it, whose edges a translation alone matched 11 px off on the hinge's 3 deg yaw, moves
nothing; the turn is reported, the region is not turned: a disk about its centre stays one): ECC
maximizes the correlation coefficient, which is blind to a gain and an offset of the gray, so a
wrong albedo, camera constant or black level (what the loop corrects after) does not pull it.
Intensity rather than gradient magnitudes there: on the examples' offsets the gradients
correlated less (0.95-0.98 against 0.99-1.0) for the same shift.

What the window cannot tell is not moved: the template's structure tensor J = sum grad T grad T^T
(its gray per pixel, on the model's noiseless image) resolves a direction when its eigenvalue
is at least EDGE_PX pixels of edge at the window's contrast (a step of height H gives about
H^2 / (2 sqrt(pi) sigma) per pixel of edge length, sigma the smoothing) and at least RATIO of
the other: along the conrod's shank (two parallel edges) only the shift across it is resolved,
the one along it stays the model's. A capture whose registration cannot be trusted (no direction
resolved, more than SATURATED_FRACTION of the window saturated, ECC not converging, a correlation
below MIN_CORRELATION, ECC wandering more than COARSE pixels or TURN_STEP_DEG from the coarse
estimate) keeps the model's region and says so."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from cell.physics import projection
from cell.planning import lights
from kernels.render import render

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import Task

Window = tuple[int, int, int, int]          # (u0, v0, width, height) of a part of the image [px]
LampPose = tuple[np.ndarray, np.ndarray]    # the lamp's position and aim in the cell frame
Drives = Mapping[int, float] | None         # {channel: level 0..1} read back (None: every light at full)

COARSE = 4                  # the coarse step's pixels per model pixel
MARGIN_PX = 24              # the window around the feature's samples: the conrod's shank edges
                            # are 1 mm (15 px) beyond its patch; doubled while it resolves nothing,
MAX_MARGIN_PX = 192         # up to this (the hinge's screw heads are 100-200 px beyond its patch)
COARSE_MARGIN_PX = 96       # the coarse step's window (its search: the whole frame)
COARSE_TURNS_DEG = (-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0)   # the coarse step's turns of it
TURN_STEP_DEG = 2.0         # their step: ECC's turn farther from the coarse one is not trusted
HIGH_PASS_SIGMA = 3.0       # coarse px (12 px): the coarse step matches the edges of the image
                            # less this blur of it (high_pass)
SMOOTH_SIGMA = 1.0          # px, Gaussian before ECC and the structure tensor
EDGE_PX = 20.0              # a resolved direction: this many pixels of edge at the window's contrast
RATIO = 0.01                # ... and at least this fraction of the other direction's eigenvalue
MIN_CORRELATION = 0.95      # ECC's correlation coefficient of a trusted alignment (0.985-0.9998
                            # on the examples' offsets with every effect on; 0.90 on a saturated hinge)
SATURATED_FRACTION = 0.2    # more of the window's pixels at saturation: its shape is unknown there
ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


@dataclass(frozen=True)
class Registration:
    """The feature's shift in the capture from where the model puts it, (dx, dy) px (image x
    right, y down; 0 in a direction not resolved and in all when not trusted), the pixel's
    footprint at the feature [m], whether it is trusted and why (note), the directions resolved,
    ECC's correlation and the time it took."""

    shift_px: tuple[float, float]
    footprint_m: float
    trusted: bool
    resolved: int
    correlation: float
    note: str
    time_s: float
    rotation_deg: float = 0.0    # the image's turn about the optical axis, ECC's (not applied)

    @property
    def offset_px(self) -> float:
        return float(np.hypot(*self.shift_px))

    @property
    def offset_m(self) -> float:
        """The pose error it implies at the feature: offset x the pixel's footprint there."""
        return self.offset_px * self.footprint_m

    def describe(self) -> str:
        """The log's sentence."""
        if not self.trusted:
            return f"not trusted ({self.note}): the model's region is measured"
        dx, dy = self.shift_px
        return (f"feature found {self.offset_px:.1f} px ({1e3 * self.offset_m:.2f} mm) from where the model puts "
                f"it (dx {dx:+.1f}, dy {dy:+.1f} px, turned {self.rotation_deg:+.2f} deg; correlation "
                f"{self.correlation:.3f}"
                + (f"; {self.note}" if self.note else "") + f"; {1e3 * self.time_s:.0f} ms)")

    def to_json(self) -> dict[str, Any]:
        return {"shift_px": list(self.shift_px), "offset_px": self.offset_px, "offset_m": self.offset_m,
                "footprint_m": self.footprint_m, "trusted": self.trusted, "resolved": self.resolved,
                "correlation": self.correlation, "note": self.note, "time_s": self.time_s,
                "rotation_deg": self.rotation_deg}


def beyond_limit(registration: dict[str, Any], limit_m: float) -> str | None:
    """The stop's reason when a trusted registration (Registration.to_json) puts the feature
    farther than limit_m (cell.run.loop.registration_limit) from where the model puts it, else None."""
    if not registration["trusted"] or registration["offset_m"] <= limit_m:
        return None
    return (f"the feature appears {registration['offset_px']:.0f} px ({1e3 * registration['offset_m']:.1f} mm) from "
            f"where the model puts it, more than the registration limit {1e3 * limit_m:.1f} mm "
            f"(loop.registration_limit_m, else the lamp's distance x tan lamp_tolerance): check the "
            f"hand-eye calibration or the part's fixture")


def expected_image(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, window: Window,
                   scale: int = 1, drives: Drives = None, counts: Sequence[int] | None = None) -> np.ndarray:
    """The model's gray per unit exposure (c A Phi R / 8, eq. 10, 11, 17) over a window
    (u0, v0, width, height) of a grid `scale` times coarser than the sensor's, seen from T_cell_cam
    with the lamp at lamp_pose (position, aim) and every light at its channel's level in drives
    (lights.drive_level; each as counts[k] emitter points, None: lights.emitter_counts at the
    scene): the planner's shading with shadows."""
    sensor, lens = task.camera.sensor, task.camera.lens
    grid = replace(sensor, width_px=round(sensor.width_px / scale), height_px=round(sensor.height_px / scale),
                   pixel_pitch_m=sensor.pixel_pitch_m * scale)
    u0, v0, width, height = window
    K = projection.intrinsics(grid, lens)
    K[:2, 2] -= (u0, v0)
    rays = projection.pixel_rays(K, T_cell_cam, width, height)
    position, aim = lamp_pose
    table, origin = task.part.material.table(), T_cell_cam[:3, 3]
    value = lights.drive_level(task.lamp.channel.number, drives) * render(
        scene.warp_mesh, origin, rays, position, aim, task.lamp.power_w, task.lamp.cone_angle_rad, table,
        sensor.camera_constant, sensor.pixel_area_m2, shadows=True, profile=task.lamp.profile).value
    if task.lights:
        counts = lights.emitter_counts(task, scene, scene.T_cell_cam) if counts is None else counts
        value += lights.rendered(scene.warp_mesh, origin, rays, T_cell_cam, task.lights, counts,
                                 [lights.drive_level(light.channel.number, drives) for light in task.lights],
                                 table, sensor.camera_constant, sensor.pixel_area_m2, shadows=True)
    return value.reshape(height, width).astype(np.float32)


def gradient(image: np.ndarray) -> np.ndarray:
    """|grad image| [gray / px] (Sobel)."""
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, scale=1 / 8)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, scale=1 / 8)
    return cv2.magnitude(gx, gy)


def high_pass(image: np.ndarray) -> np.ndarray:
    """image less its Gaussian blur of HIGH_PASS_SIGMA px: the part's edges, not the lamp's soft
    edge (tens of pixels wide), which a lamp off its aim puts elsewhere than the model does (the
    hinge's lamp 4-5 deg off: matched 70-107 px away without it)."""
    return image - cv2.GaussianBlur(image, (0, 0), HIGH_PASS_SIGMA)


def structure(template: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvalues ascending, eigenvectors as columns) of the structure tensor of a template
    (smoothed by SMOOTH_SIGMA), its gradient in gray per pixel."""
    gx = cv2.Sobel(template, cv2.CV_64F, 1, 0, scale=1 / 8)
    gy = cv2.Sobel(template, cv2.CV_64F, 0, 1, scale=1 / 8)
    J = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
    return np.linalg.eigh(J)


def feature_window(row: np.ndarray, col: np.ndarray, shape: tuple[int, ...], margin: int) -> Window:
    """(u0, v0, width, height): the samples' pixels' bounding box and a margin, inside the image."""
    u0, v0 = max(int(col.min()) - margin, 0), max(int(row.min()) - margin, 0)
    u1, v1 = min(int(col.max()) + margin + 1, shape[1]), min(int(row.max()) + margin + 1, shape[0])
    return u0, v0, u1 - u0, v1 - v0


def edged_window(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, row: np.ndarray,
                 col: np.ndarray, shape: tuple[int, ...], drives: Drives = None, counts: Sequence[int] | None = None,
                 ) -> tuple[Window, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(window, smoothed template, eigenvalues, eigenvectors, resolved directions) of the smallest
    window around the feature (margin MARGIN_PX, doubled up to MAX_MARGIN_PX) whose model image
    resolves a direction (module docstring)."""
    margin = MARGIN_PX
    while True:
        window = feature_window(row, col, shape, margin)
        template = cv2.GaussianBlur(expected_image(task, scene, T_cell_cam, lamp_pose, window, 1, drives, counts),
                                    (0, 0), SMOOTH_SIGMA)
        contrast = float(np.percentile(template, 99) - np.percentile(template, 1))
        values, vectors = structure(template)
        edge = EDGE_PX * contrast**2 / (2.0 * np.sqrt(np.pi) * SMOOTH_SIGMA)
        resolved = (values >= edge) & (values >= RATIO * values[-1])
        if resolved.any() or margin >= MAX_MARGIN_PX:
            return window, template, values, vectors, resolved
        margin *= 2


def coarse_shift(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose,
                 row: np.ndarray, col: np.ndarray, drives: Drives = None,
                 counts: Sequence[int] | None = None) -> tuple[np.ndarray, float]:
    """(the feature centre's shift (dx, dy) [px] to within COARSE px, the image's turn about it
    [deg] to within half a COARSE_TURNS_DEG step): the model's window around it
    (COARSE_MARGIN_PX) at 1/COARSE resolution, turned by each of COARSE_TURNS_DEG about the
    feature's centre, matched over the capture averaged down alike, by
    the normalized correlation coefficient (cv2.matchTemplate, TM_CCOEFF_NORMED: blind to gain and
    offset) of their gradient magnitudes: the lamp's soft edge and the lobe's shading stay where
    the lamp is when the part moves, and in intensity they outweighed the hinge's edges (its part
    2 mm off was matched 67 px away). Not phase correlation: its whitened spectrum, on images flat
    but for a few edges, put its peak 5 px off on the noiseless conrod and anywhere once the lamp's
    edge differed."""
    h, w = image.shape
    size = (round(w / COARSE), round(h / COARSE))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    u0, v0, width, height = feature_window(row // COARSE, col // COARSE, small.shape, COARSE_MARGIN_PX // COARSE)
    edges = gradient(high_pass(expected_image(task, scene, T_cell_cam, lamp_pose, (u0, v0, width, height), COARSE,
                                              drives, counts)))
    centre = (float(np.mean(col) / COARSE - u0), float(np.mean(row) / COARSE - v0))
    target = gradient(high_pass(small))
    best: tuple[float, tuple[int, int] | None, float] = (-np.inf, None, 0.0)
    for turn in COARSE_TURNS_DEG:               # the turned window's corners have no edge: 0
        M = cv2.getRotationMatrix2D(centre, turn, 1.0)
        score = cv2.matchTemplate(target, cv2.warpAffine(edges, M, (width, height)), cv2.TM_CCOEFF_NORMED)
        _, peak, _, (u, v) = cv2.minMaxLoc(np.nan_to_num(score, nan=-1.0))
        if peak > best[0]:
            best = (peak, (u - u0, v - v0), turn)
    return COARSE * np.array(best[1], float), best[2]


def locate(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose,
           row: np.ndarray, col: np.ndarray, saturation: float = np.inf, drives: Drives = None) -> Registration:
    """The Registration of a capture taken from T_cell_cam (read back) with the lamp at
    lamp_pose and the light channels at `drives` (read back; None: every light at full), the
    feature's samples at pixels (row, col) by the model (those inside the image), pixels at
    `saturation` or above clipped by the sensor."""
    start = time.perf_counter()
    image = np.asarray(image, np.float32)
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    (_,), (depth,) = projection.project(K, T_cell_cam, scene.center[None])
    footprint = float(depth / K[0, 0])

    def result(shift: Any, trusted: bool, resolved: int, correlation: float, note: str,
               rotation: float = 0.0) -> Registration:
        return Registration((float(shift[0]), float(shift[1])), footprint, trusted, resolved, float(correlation), note,
                            time.perf_counter() - start, rotation)

    counts = lights.emitter_counts(task, scene, scene.T_cell_cam)
    coarse, turn = coarse_shift(image, task, scene, T_cell_cam, lamp_pose, row, col, drives, counts)
    (u0, v0, width, height), template, values, vectors, resolved = edged_window(
        task, scene, T_cell_cam, lamp_pose, row, col, image.shape, drives, counts)
    saturated = float(np.mean(image[v0:v0 + height, u0:u0 + width] >= saturation))
    if saturated > SATURATED_FRACTION:
        return result((0.0, 0.0), False, int(resolved.sum()), np.nan,
                      f"{100 * saturated:.0f} % of the window around the feature saturated")
    if not resolved.any():
        return result((0.0, 0.0), False, 0, np.nan, "the window around the feature has too little edge to align on")
    centre = np.array([np.mean(col) - u0, np.mean(row) - v0])      # the feature's, in the window
    M = cv2.getRotationMatrix2D(tuple(centre), turn, 1.0)           # window -> image: turned about it,
    warp = np.column_stack([M[:, :2], M[:, 2] + (u0, v0) + coarse]).astype(np.float32)   # then shifted
    try:
        correlation, warp = cv2.findTransformECC(  # type: ignore[call-overload]  # OpenCV's stubs: no mask None
            template, cv2.GaussianBlur(image, (0, 0), SMOOTH_SIGMA), warp, cv2.MOTION_EUCLIDEAN, ECC_CRITERIA, None, 1)
    except cv2.error:                   # OpenCV's own text (its source path, "NaN encountered") is no reason
        return result((0.0, 0.0), False, int(resolved.sum()), np.nan,   # a person can act on
                      "the fine alignment (ECC) did not converge on this capture")
    fine = warp[:, :2] @ centre + warp[:, 2] - centre - (u0, v0)    # where the warp moves it
    rotation = float(np.degrees(np.arctan2(warp[1, 0], warp[0, 0])))
    kept = vectors[:, resolved]                     # project onto the resolved directions
    shift, from_coarse = kept @ (kept.T @ fine), kept.T @ (fine - coarse)
    if correlation < MIN_CORRELATION:
        return result((0.0, 0.0), False, int(resolved.sum()), correlation,
                      f"correlation {correlation:.3f} below {MIN_CORRELATION}")
    if np.max(np.abs(from_coarse)) > COARSE:
        return result((0.0, 0.0), False, int(resolved.sum()), correlation,
                      f"ECC ended {np.max(np.abs(from_coarse)):.1f} px from the coarse estimate")
    if abs(rotation + turn) > TURN_STEP_DEG:        # the coarse turn of the window is -rotation's
        return result((0.0, 0.0), False, int(resolved.sum()), correlation,
                      f"ECC turned {rotation:+.1f} deg, the coarse estimate {-turn:+.0f} deg")
    note = "" if resolved.all() else (
        f"resolved across the window's edges only (along {np.degrees(np.arctan2(*vectors[::-1, 0])) % 180:.0f} deg "
        f"in the image it has none: that component is the model's)")
    return result(shift, True, int(resolved.sum()), correlation, note, rotation)
