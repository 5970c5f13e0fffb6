"""Registration: where the feature really is in a capture. The model's image
of the part at the read-back camera and lamp poses (kernels.render, the planner's shading: the
task's material, lamp and camera constant), every light of the task shining at the capture's
read-back drives as the simulator renders them (cell.planning.lights.rendered), is aligned with
the capture, and the feature's
samples move by the shift found, so the measured region follows the feature as it appears.

Two steps. The model's whole view at 1/COARSE resolution is rendered, and its window around the
feature matched over the whole capture by its edges (coarse_shift: of the image less its blur,
high_pass, so that the lamp's soft edge does not count), finds any shift that keeps it in the
frame (a 2 deg hand-eye tilt on the hinge is 188 px), to within a coarse pixel. It matches
only windows of the capture with texture (more variation than the sensor's noise explains: the
black background beside a small part, flat to the rounding, scored 1.000 with anything), a
peak must clear what a frame of pure noise reaches against the same template, and the whole
view moved by the shift must agree with the capture better than unmoved; otherwise it starts
from the model's place. cv2.findTransformECC (a translation and
a turn, MOTION_EUCLIDEAN, on intensity) then refines it to a fraction of a pixel in a window
around the feature, the shift being where the warp moves the feature's centre (a part turned
about it, whose edges a translation alone matched 11 px off on the hinge's 3 deg yaw, moves
nothing; the turn is reported, the region is not turned: a disk about its centre stays one): ECC
maximizes the correlation coefficient, which is blind to a gain and an offset of the gray, so a
wrong albedo, camera constant or black level (what the loop corrects after) does not pull it.
Intensity rather than gradient magnitudes there: on the examples' offsets the gradients
correlated less (0.95-0.98 against 0.99-1.0) for the same shift. ECC's move is taken when it gains
more than noise could (significant) and does not take the part's geometric edges (below) away
from where the model puts them: a noiseless capture's light the model lacks (the lamp's soft cone
edge) gains significance for a 0.07 px move that lowers them. The template is the model's image
smoothed as the capture is, with its neighbours (smoothed_template), over the smallest window
that resolves a direction (below), grown where an edge runs along its border (edged_window: the
side beyond it is the edge's other half, which ECC weighs by the little of it inside).

What the window cannot tell is not moved: the template's structure tensor J = sum grad T grad T^T
(its gray per pixel, on the model's noiseless image) resolves a direction when its eigenvalue
is at least EDGE_PX pixels of edge at the window's contrast (a step of height H gives about
H^2 / (2 sqrt(pi) sigma) per pixel of edge length, sigma the smoothing) and at least RATIO of
the other: along the conrod's shank (two parallel edges) only the shift across it is resolved,
the one along it stays the model's. A capture whose feature cannot be registered (no direction
resolved, more than SATURATED_FRACTION of the window saturated, no texture in the capture where
the window lands, ECC not converging, a correlation below what a right alignment
reaches (correlates_as_aligned) with the part's geometric edges not where it puts them (below),
ECC wandering more
than COARSE pixels or TURN_STEP_DEG from a coarse start that matched nothing; from a coarse
match, wandering keeps the match) keeps the model's region and says so in the cell's words (never
OpenCV's text); the loop never reports such a shot in band. Neither the model nor the capture
showing an edge around the feature (a plate filling the frame) is nothing to register: the
model's region, trusted.

A light the model has wrong changes the capture's shading, not where the part is: the hinge's lamp
turned 2-3 deg off its aim moves its soft edge across the feature's window, and ECC's correlation
fell to 0.78-0.43 of its ceiling, the edges' to 0.94-0.82, with the part where the model puts it.
So where both fall short, the part's geometric edges decide (geometric_edges: its silhouette, depth
steps and creases, from kernels.render's hit, depth and normal, which move with the part whatever
the light does): their contrast relative to the shading (geometric_correlation, blind to a light
that multiplies the gray by a slowly varying factor) at least MIN_CORRELATION of its ceiling
trusts the alignment (0.98-0.99 there; 1 px off 0.81-0.84, 2 px 0.43-0.49), moved only along the
directions those edges resolve, and the loop corrects the light; otherwise the feature is not
registered."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from functools import cache
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike

from cell.physics import contrast, projection
from cell.physics.sensor import dark_noise, system_gain
from cell.planning import lights
from kernels.render import render

if TYPE_CHECKING:
    from cell.planning.scene import Scene
    from cell.task.types import Sensor, Task

Window = tuple[int, int, int, int]          # (u0, v0, width, height) of a part of the image [px]
LampPose = tuple[np.ndarray, np.ndarray]    # the lamp's position and aim in the cell frame
Drives = Mapping[int, float] | None         # {channel: level 0..1} read back (None: every light at full)
Edged = tuple[Window, np.ndarray, np.ndarray, np.ndarray, np.ndarray]    # edged_window's answer

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
SMOOTH_PAD_PX = 4           # px: its reach (OpenCV's kernel for a float image: 4 sigma each side)
EDGE_CLEAR_PX = 16          # px: the window grown beyond the first margin that resolves a direction
                            # where an edge runs along its border (edged_window; on the bracket 10 mm along
                            # y, no true shift across its edges: 8 px left web_outer 0.4 px off, 0.988 of
                            # its ceiling; 16 px 0.2 px, 0.993)
EDGE_PX = 20.0              # a resolved direction: this many pixels of edge at the window's contrast
RATIO = 0.01                # ... and at least this fraction of the other direction's eigenvalue
MIN_CORRELATION = 0.95      # a trusted alignment's correlation: this share of what the noise allows
                            # (0.985-0.9998 on the examples' offsets with every effect on; 0.90 on a
                            # saturated hinge), and that ceiling at least this
SHADING_SIGMA_PX = 12.0     # correlates_as_aligned: the window's edges are it less its blur of this (the
                            # lamp's soft edge and the lobe's shading, tens of pixels wide, left out)
GEOMETRY_TURN_DEG = 20.0    # geometric_edges: a normal break, neighbouring pixels' faces turned more than this
DEPTH_STEP_PX = 10.0        # ... a depth break, neighbours' depths apart by more than this many pixel footprints
                            # (a continuous surface up to 84 deg from the view: less)
GEOMETRY_REACH_PX = 3       # ... and the pixels this near one (the smoothed edge's reach)
RELATIVE_FLOOR = 0.05       # shading: the edges divided by it, it by at least this share of its 99th percentile
SIGNIFICANCE = 3.0          # standard errors of the correlation ECC must gain to move the window
TEXTURE = 2.0               # a window with texture varies more than this x what the sensor's noise gives
SATURATED_FRACTION = 0.2    # more of the window's pixels at saturation: its shape is unknown there
ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


@dataclass(frozen=True)
class Registration:
    """The feature's shift in the capture from where the model puts it, (dx, dy) px (image x
    right, y down; 0 in a direction not resolved and in all when not trusted), the pixel's
    footprint at the feature [m], whether it is trusted and why (note), the directions resolved
    (none when trusted: neither the model nor the capture has an edge around the feature),
    ECC's correlation, its ceiling (what a right alignment's reaches through the sensor's noise:
    intensity_correlation; nan where ECC did not run) and the time it took."""

    shift_px: tuple[float, float]
    footprint_m: float
    trusted: bool
    resolved: int
    correlation: float
    note: str
    time_s: float
    rotation_deg: float = 0.0    # the image's turn about the optical axis, ECC's (not applied)
    ceiling: float = np.nan

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
            return f"not registered ({self.note}): the model's region is measured"
        if not self.resolved:
            return f"{self.note}: the model's region is measured"
        dx, dy = self.shift_px
        return (f"feature found {self.offset_px:.1f} px ({1e3 * self.offset_m:.2f} mm) from where the model puts "
                f"it (dx {dx:+.1f}, dy {dy:+.1f} px, turned {self.rotation_deg:+.2f} deg; correlation "
                f"{self.correlation:.3f}"
                + (f"; {self.note}" if self.note else "") + f"; {1e3 * self.time_s:.0f} ms)")

    def to_json(self) -> dict[str, Any]:
        return {"shift_px": list(self.shift_px), "offset_px": self.offset_px, "offset_m": self.offset_m,
                "footprint_m": self.footprint_m, "trusted": self.trusted, "resolved": self.resolved,
                "correlation": self.correlation, "note": self.note, "time_s": self.time_s,
                "rotation_deg": self.rotation_deg, "ceiling": self.ceiling}


def beyond_limit(registration: dict[str, Any], limit_m: float) -> str | None:
    """The stop's reason when a trusted registration (Registration.to_json) puts the feature
    farther than limit_m (cell.run.loop.registration_limit) from where the model puts it, else None."""
    if not registration["trusted"] or registration["offset_m"] <= limit_m:
        return None
    return (f"the feature appears {registration['offset_px']:.0f} px ({1e3 * registration['offset_m']:.1f} mm) from "
            f"where the model puts it, more than the registration limit {1e3 * limit_m:.1f} mm "
            f"(loop.registration_limit_m, else the lamp's distance x tan lamp_tolerance): check the "
            f"hand-eye calibration or the part's fixture")


def not_registered(registration: dict[str, Any]) -> str:
    """The stop's reason when a capture's feature could not be registered (Registration.to_json,
    not trusted) though its gray on the model's region is in band: that region may not be the
    feature, so the shot is not reported in band."""
    return (f"the feature could not be registered ({registration['note']}): its gray on the model's region "
            f"is in band, but that region may not be the feature, so the shot is not reported in band; check the "
            f"lighting of the feature's edges, the hand-eye calibration or the part's fixture")


def expected_image(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, window: Window,
                   scale: int = 1, drives: Drives = None, counts: Sequence[int] | None = None,
                   shadows: bool = True) -> np.ndarray:
    """The model's gray per unit exposure (c A Phi R / 8, eq. 10, 11, 17) over a window
    (u0, v0, width, height) of a grid `scale` times coarser than the sensor's, seen from T_cell_cam
    with the lamp at lamp_pose (position, aim) and every light at its channel's level in drives
    (lights.drive_level; each as counts[k] emitter points, None: lights.emitter_counts at the
    scene): the planner's shading with cast shadows (without: `shadows` False)."""
    sensor, lens = task.camera.sensor, task.camera.lens
    grid = replace(sensor, width_px=round(sensor.width_px / scale), height_px=round(sensor.height_px / scale),
                   pixel_pitch_m=sensor.pixel_pitch_m * scale)
    width, height = window[2:]
    rays = window_rays(projection.intrinsics(grid, lens), T_cell_cam, window)
    position, aim = lamp_pose
    table, origin = task.part.material.table(), T_cell_cam[:3, 3]
    value = lights.drive_level(task.lamp.channel.number, drives) * render(
        scene.shadow_mesh, origin, rays, position, aim, task.lamp.power_w, task.lamp.cone_angle_rad, table,
        sensor.camera_constant, sensor.pixel_area_m2, shadows=shadows, profile=task.lamp.profile,
        part_faces=len(scene.faces)).value
    if task.lights:
        counts = lights.emitter_counts(task, scene, scene.T_cell_cam) if counts is None else counts
        value += lights.rendered(scene.shadow_mesh, origin, rays, T_cell_cam, task.lights, counts,
                                 [lights.drive_level(light.channel.number, drives) for light in task.lights],
                                 table, sensor.camera_constant, sensor.pixel_area_m2, shadows=shadows,
                                 part_faces=len(scene.faces))
    return value.reshape(height, width).astype(np.float32)


def window_rays(K: np.ndarray, T_cell_cam: np.ndarray, window: Window) -> np.ndarray:
    """Each pixel's ray (cell frame, row by row) of a window (u0, v0, width, height) of the image
    whose intrinsics are K: the principal point moved to the window's corner."""
    u0, v0, width, height = window
    K = K.copy()
    K[:2, 2] -= (u0, v0)
    return projection.pixel_rays(K, T_cell_cam, width, height)


def sobel(image: np.ndarray, depth: int = cv2.CV_64F) -> tuple[np.ndarray, np.ndarray]:
    """(d image / dx, d image / dy) [gray / px] (Sobel's 3 x 3, divided by its weight 8), of OpenCV
    depth `depth`."""
    return cv2.Sobel(image, depth, 1, 0, scale=1 / 8), cv2.Sobel(image, depth, 0, 1, scale=1 / 8)


def gradient(image: np.ndarray) -> np.ndarray:
    """|grad image| [gray / px] (sobel)."""
    return cv2.magnitude(*sobel(image, cv2.CV_32F))


def high_pass(image: np.ndarray) -> np.ndarray:
    """image less its Gaussian blur of HIGH_PASS_SIGMA px: the part's edges, not the lamp's soft
    edge (tens of pixels wide), which a lamp off its aim puts elsewhere than the model does (the
    hinge's lamp 4-5 deg off: matched 70-107 px away without it)."""
    return image - cv2.GaussianBlur(image, (0, 0), HIGH_PASS_SIGMA)


def structure(template: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvalues ascending, eigenvectors as columns) of the structure tensor of a template
    (smoothed by SMOOTH_SIGMA), its gradient in gray per pixel, summed over the mask's pixels
    (None: all)."""
    gx, gy = sobel(template)
    if mask is not None:
        gx, gy = gx[mask], gy[mask]
    J = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
    return np.linalg.eigh(J)


def feature_window(row: np.ndarray, col: np.ndarray, shape: tuple[int, ...], margin: int) -> Window:
    """(u0, v0, width, height): the samples' pixels' bounding box and a margin, inside the image."""
    u0, v0 = max(int(col.min()) - margin, 0), max(int(row.min()) - margin, 0)
    u1, v1 = min(int(col.max()) + margin + 1, shape[1]), min(int(row.max()) + margin + 1, shape[0])
    return u0, v0, u1 - u0, v1 - v0


def edged_window(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, row: np.ndarray,
                 col: np.ndarray, shape: tuple[int, ...], drives: Drives = None, counts: Sequence[int] | None = None,
                 ) -> Edged:
    """(window, smoothed template, eigenvalues, eigenvectors, resolved directions) of the window
    around the feature whose model image resolves a direction: the smallest margin (MARGIN_PX,
    doubled up to MAX_MARGIN_PX) that does, EDGE_CLEAR_PX more where an edge runs along its border
    (edge_on_border). The first margin to resolve a direction is often the first whose window
    reaches an edge, which then lies on its border with the side beyond it left out, and ECC
    weighs it by the little of that side inside: web_inner's window ended on the chamfer's edge
    (correlation 0.945 of the 0.990 the noise allows with the model right; 0.9995 grown), and on
    the bracket 10 mm along y (no true shift across its edges) web_outer's and the chamfer's, whose
    shading the model has wrong there, moved 4.3 and 2.2 px (0.2 and 0.8 grown)."""
    margin = MARGIN_PX
    while True:
        found = window_structure(task, scene, T_cell_cam, lamp_pose, row, col, shape, margin, drives, counts)
        if found[4].any() or margin >= MAX_MARGIN_PX:
            if not edge_on_border(found[1]):
                return found
            return window_structure(task, scene, T_cell_cam, lamp_pose, row, col, shape, margin + EDGE_CLEAR_PX,
                                    drives, counts)
        margin *= 2


def edge_threshold(template: np.ndarray) -> float:
    """EDGE_PX pixels of edge at the template's contrast (its 99th less its 1st percentile H), in
    the structure tensor's units: a step of height H, smoothed by SMOOTH_SIGMA, gives
    H^2 / (2 sqrt(pi) SMOOTH_SIGMA) per pixel of its length."""
    contrast = float(np.percentile(template, 99) - np.percentile(template, 1))
    return EDGE_PX * contrast**2 / (2.0 * np.sqrt(np.pi) * SMOOTH_SIGMA)


def window_structure(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, row: np.ndarray,
                     col: np.ndarray, shape: tuple[int, ...], margin: int, drives: Drives = None,
                     counts: Sequence[int] | None = None) -> Edged:
    """(window, smoothed template, eigenvalues, eigenvectors, resolved directions) of the window
    around the feature with `margin` (feature_window): its template (smoothed_template), its
    structure tensor and the directions it resolves (at least edge_threshold and RATIO of the other)."""
    window = feature_window(row, col, shape, margin)
    template = smoothed_template(task, scene, T_cell_cam, lamp_pose, window, drives, counts)
    values, vectors = structure(template)
    return window, template, values, vectors, (values >= edge_threshold(template)) & (values >= RATIO * values[-1])


def edge_on_border(template: np.ndarray) -> bool:
    """Whether an edge runs along a side of the template: its gradient across that side, squared
    and summed over the SMOOTH_PAD_PX + 1 columns (rows) along it, at least edge_threshold (in
    pixels of edge at the window's contrast, EDGE_PX: the bracket's windows 41-874 where an edge
    lies there, 0-10 where none does; the far dome's 7, not grown, whose window grown took in more
    of the lamp cone's hard edge, which the model has and the world lacks, and was refused)."""
    band = SMOOTH_PAD_PX + 1
    gx, gy = sobel(template)
    across = (gx[:, :band], gx[:, -band:], gy[:band], gy[-band:])
    return bool(max(float(np.sum(np.square(g))) for g in across) >= edge_threshold(template))


def smoothed_template(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose, window: Window,
                      drives: Drives = None, counts: Sequence[int] | None = None) -> np.ndarray:
    """The model's image over a window (expected_image) smoothed by SMOOTH_SIGMA as the capture is,
    with its neighbours: rendered SMOOTH_PAD_PX beyond the window, blurred, then cut to it (blurred
    alone, its border would be reflected where the capture has what lies beyond)."""
    u0, v0, width, height = window
    pad = SMOOTH_PAD_PX
    wide = expected_image(task, scene, T_cell_cam, lamp_pose, (u0 - pad, v0 - pad, width + 2 * pad, height + 2 * pad),
                          1, drives, counts)
    return np.ascontiguousarray(cv2.GaussianBlur(wide, (0, 0), SMOOTH_SIGMA)[pad:pad + height, pad:pad + width])


@dataclass(frozen=True)
class Coarse:
    """The coarse step's answer: the feature centre's shift (dx, dy) [px] and the image's turn
    [deg] it starts ECC from, the best peak among textured windows, the best a frame of pure
    noise reaches against the same template (the ceiling a match must clear), and why it did not
    move (empty when it did, or had no reason to). `flat`: True when neither the model nor the
    capture shows an edge around the feature (nothing to register, and nothing an offset would
    change there), False when the capture shows edges the model has none of, None otherwise."""

    shift_px: np.ndarray
    turn_deg: float
    score: float
    noise_ceiling: float
    note: str = ""
    flat: bool | None = None


def noise_rms(gray: ArrayLike, sensor: Sensor) -> np.ndarray:
    """The sensor's temporal noise and quantisation at a gray [gray rms] (EMVA 1288,
    cell.physics.contrast.temporal_noise; the black level 0 when the task gives none, which
    counts a little more shot noise)."""
    return contrast.temporal_noise(gray, sensor.black_level or 0.0, system_gain(sensor.bit_depth,
                                   sensor.system_gain_dn_per_e), dark_noise(sensor.dark_noise_e))


def edge_noise_gain() -> float:
    """The rms of gradient(high_pass(n)) per unit rms of white noise n: the magnitude of two
    uncorrelated Gaussian components of variance s^2 sum(k_x^2) (k_x the impulse response of
    Sobel x after high_pass) is Rayleigh, whose own rms about its mean is s sqrt((4 - pi) / 2)."""
    delta = np.zeros((65, 65), np.float32)
    delta[32, 32] = 1.0
    k_x = cv2.Sobel(high_pass(delta), cv2.CV_32F, 1, 0, scale=1 / 8)
    return float(np.sqrt((4.0 - np.pi) / 2.0 * np.sum(np.square(k_x, dtype=np.float64))))


def window_sums(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The sum of image over every (width, height) window, indexed by its top-left pixel as
    cv2.matchTemplate's score is."""
    w, h = size
    total = cv2.integral(image.astype(np.float64))
    return total[h:, w:] - total[:-h, w:] - total[h:, :-w] + total[:-h, :-w]


def textured(small: np.ndarray, target: np.ndarray, size: tuple[int, int], sensor: Sensor) -> np.ndarray:
    """Per window of `size` (top-left indexed): whether target (the coarse capture's edges) varies
    over it more than TEXTURE x what the sensor's noise alone gives there (noise_rms at the
    window's mean gray, averaged down by COARSE^2 pixels, through edge_noise_gain). Normalised
    correlation divides by that variation, so a window without it (the black background:
    rounding noise of 3e-7 gray) scores anything, 1.000 included."""
    n = size[0] * size[1]
    mean = window_sums(small, size) / n
    spread = np.sqrt(np.maximum(window_sums(np.square(target), size) / n - (window_sums(target, size) / n) ** 2, 0.0))
    noise = noise_rms(mean, sensor) / COARSE * edge_noise_gain()
    return spread > TEXTURE * noise


def agreement(target: np.ndarray, view_edges: np.ndarray, shift_px: np.ndarray) -> float:
    """The correlation coefficient of the coarse capture's edges with the whole view's expected
    edges moved by shift_px (full-resolution pixels)."""
    M = np.array([[1, 0, shift_px[0] / COARSE], [0, 1, shift_px[1] / COARSE]], np.float32)
    return correlation_coefficient(target, cv2.warpAffine(view_edges, M, (view_edges.shape[1], view_edges.shape[0])))


def correlation_coefficient(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson's r of two images of one shape over their pixels (0 when either is flat)."""
    a, b = a - a.mean(dtype=np.float64), b - b.mean(dtype=np.float64)
    norm = float(np.sqrt(np.sum(a * a, dtype=np.float64) * np.sum(b * b, dtype=np.float64)))
    return float(np.sum(a * b, dtype=np.float64) / norm) if norm > 0.0 else 0.0


def turned_if_significant(peaks: Mapping[float, tuple[float, Any]], pixels: int) -> float:
    """The turn whose peak is highest, if it beats the unturned one's by more than noise could
    (significant), else 0: a window that tells turns apart poorly (a filleted block's) does not
    start ECC 2 deg off."""
    turn = max(peaks, key=lambda t: peaks[t][0])
    return turn if 0.0 not in peaks or significant(peaks[turn][0], peaks[0.0][0], pixels) else 0.0


def coarse_shift(image: np.ndarray, task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose,
                 row: np.ndarray, col: np.ndarray, drives: Drives = None,
                 counts: Sequence[int] | None = None) -> Coarse:
    """Coarse: the feature centre's shift to within COARSE px and the image's turn about it to
    within half a COARSE_TURNS_DEG step. The model's whole view at 1/COARSE resolution is
    rendered; its window around the feature (COARSE_MARGIN_PX), turned by each of
    COARSE_TURNS_DEG about the feature's centre, is matched over the capture averaged down alike,
    by the normalized correlation coefficient (cv2.matchTemplate, TM_CCOEFF_NORMED: blind to gain
    and offset) of their edges (gradient of high_pass): the lamp's soft edge and the lobe's
    shading stay where the lamp is when the part moves, and in intensity they outweighed the
    hinge's edges (its part 2 mm off was matched 67 px away). Not phase correlation: its whitened
    spectrum, on images flat but for a few edges, put its peak 5 px off on the noiseless conrod.

    What it may match: only windows of the capture with texture (textured); a peak no higher
    than the best a frame of pure noise reaches against the same turned templates (seeded, so
    the same each time; the ceiling is scale-free, noise of any rms scores alike) is no match;
    and a move is taken only when the whole view's edges, moved by it, agree with the capture's
    better than unmoved (agreement), by more than noise could (significant). Otherwise the
    model's place (no shift; the turn that scores best there when only the whole view refused
    the move), and why."""
    h, w = image.shape
    size = (round(w / COARSE), round(h / COARSE))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    expected = expected_image(task, scene, T_cell_cam, lamp_pose, (0, 0, *size), COARSE, drives, counts)
    view = gradient(high_pass(expected))
    u0, v0, width, height = feature_window(row // COARSE, col // COARSE, small.shape, COARSE_MARGIN_PX // COARSE)
    edges = view[v0:v0 + height, u0:u0 + width]
    centre = (float(np.mean(col) / COARSE - u0), float(np.mean(row) / COARSE - v0))
    target = gradient(high_pass(small))
    noise = gradient(high_pass(np.asarray(np.random.default_rng(0).standard_normal(small.shape), np.float32)))
    valid = textured(small, target, (width, height), task.camera.sensor)
    seen, modelled = small[v0:v0 + height, u0:u0 + width], expected[v0:v0 + height, u0:u0 + width]
    gain = float(np.sum(seen * modelled, dtype=np.float64) / max(np.sum(np.square(modelled, dtype=np.float64)), 1e-300))
    if gain * float(edges.std()) <= TEXTURE * float(noise_rms(seen.mean(), task.camera.sensor)) / COARSE \
            * edge_noise_gain():            # the model, in the capture's gray, has no edge there
        if valid[v0, u0]:
            return Coarse(np.zeros(2), 0.0, -np.inf, -np.inf,
                          "the capture shows edges around the feature where the model has none", flat=False)
        return Coarse(np.zeros(2), 0.0, -np.inf, -np.inf, "neither the model nor the capture shows an edge around "
                      "the feature: nothing to register, and an offset would change nothing there", flat=True)
    best: dict[float, tuple[float, tuple[int, int]]] = {}   # per turn: its peak and where
    in_place: dict[float, float] = {}                        # per turn: its score at the model's place
    ceiling = -np.inf
    for turn in COARSE_TURNS_DEG:               # the turned window's corners have no edge: 0
        turned = cv2.warpAffine(edges, cv2.getRotationMatrix2D(centre, turn, 1.0), (width, height))
        if not turned.any():
            continue
        scores = np.nan_to_num(cv2.matchTemplate(target, turned, cv2.TM_CCOEFF_NORMED), nan=-1.0)
        in_place[turn] = float(scores[v0, u0])
        scores = np.where(valid, scores, -1.0)
        ceiling = max(ceiling, float(np.nanmax(cv2.matchTemplate(noise, turned, cv2.TM_CCOEFF_NORMED))))
        v, u = np.unravel_index(int(np.argmax(scores)), scores.shape)
        best[turn] = (float(scores[v, u]), (int(u) - u0, int(v) - v0))
    turn = turned_if_significant(best, edges.size)
    score, shift = best[turn][0], COARSE * np.array(best[turn][1], float)
    if score <= ceiling:
        return Coarse(np.zeros(2), 0.0, score, ceiling,
                      f"the capture's edges match the model's nowhere better than pure noise would "
                      f"({score:.2f}, noise reaches {ceiling:.2f})")
    if shift.any() and not significant(agreement(target, view, shift), agreement(target, view, np.zeros(2)),
                                       target.size):
        return Coarse(np.zeros(2), turned_if_significant({t: (v, (0, 0)) for t, v in in_place.items()}, edges.size),
                      score, ceiling,
                      f"the whole view does not agree with moving the feature {np.hypot(*shift):.0f} px")
    return Coarse(shift, turn, score, ceiling)


def warped(image: np.ndarray, warp: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The image sampled (bilinear) where warp (template -> image, ECC's convention) puts each
    pixel of a template of `shape`."""
    return cv2.warpAffine(image, warp, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def warped_correlation(template: np.ndarray, image: np.ndarray, warp: np.ndarray) -> float:
    """The correlation coefficient of the template with the image where warp puts each template
    pixel (warped): what findTransformECC maximizes."""
    return correlation_coefficient(template, warped(image, warp, template.shape))


def significant(correlation: float, start: float, pixels: int) -> bool:
    """Whether a move's correlation beats the one without it by more than SIGNIFICANCE standard
    errors of a correlation coefficient r over N independent pixels, (1 - r^2) / sqrt(N) (N: the
    pixels over the 4 pi sigma^2 a Gaussian of SMOOTH_SIGMA correlates; Sobel's 3 x 3 correlates
    about as many): a smaller gain noise could give, and a move for it is no finding (a lamp
    cone's soft edge the model lacks pulled a dome's ECC window 1.1 px and 1.9 deg for a gain of
    0.001; a shaft's whole view agreed 0.0008 better with a coarse move along its axis)."""
    n = pixels / (4.0 * np.pi * SMOOTH_SIGMA**2)
    return correlation - start > SIGNIFICANCE * (1.0 - start * start) / np.sqrt(n)


def shading_removed(image: np.ndarray) -> np.ndarray:
    """The image less its Gaussian blur of SHADING_SIGMA_PX: its edges, without the slowly varying
    shading (the lamp's soft edge, the lobe) that the loop's exposure and re-plan correct."""
    return image - cv2.GaussianBlur(image, (0, 0), SHADING_SIGMA_PX)


def smoothed_noise_rms(edges: bool = False) -> float:
    """The rms of smoothed white noise n (and shading_removed, with edges) per unit rms of n:
    sqrt(sum k^2), k the impulse response of the Gaussian of SMOOTH_SIGMA (the capture's smoothing
    before ECC), then shading_removed with edges."""
    size = 8 * int(SHADING_SIGMA_PX) + 1
    delta = np.zeros((size, size), np.float32)
    delta[size // 2, size // 2] = 1.0
    k = cv2.GaussianBlur(delta, (0, 0), SMOOTH_SIGMA)
    k = shading_removed(k) if edges else k
    return float(np.sqrt(np.sum(np.square(k, dtype=np.float64))))


class Correlation(NamedTuple):
    """A correlation coefficient r of the template with the capture where ECC's warp puts it, and
    the ceiling: the most a right alignment's reaches through the sensor's noise."""

    r: float
    ceiling: float


def with_ceiling(r: float, template: np.ndarray, seen: np.ndarray, sigma: float) -> Correlation:
    """r with its ceiling for a template and the capture (seen) filtered alike, sigma the rms the
    filter leaves of the sensor's noise. The capture is C = g T + n (n independent of T), whose
    correlation with T is

        ceiling = g s / sqrt(g^2 s^2 + sigma^2),   s = std(T),

    g the least-squares gain <T, C> / <T, T> (means removed)."""
    a = template - template.mean(dtype=np.float64)
    power = float(np.sum(a * a, dtype=np.float64))
    if power <= 0.0:
        return Correlation(r, 0.0)
    signal = abs(float(np.sum(a * seen, dtype=np.float64)) / power) * float(np.sqrt(power / a.size))
    return Correlation(r, signal / float(np.hypot(signal, sigma)) if signal > 0.0 else 0.0)


def intensity_correlation(correlation: float, template: np.ndarray, seen: np.ndarray, noise: float) -> Correlation:
    """ECC's correlation of the template with the capture where its warp puts them (seen, smoothed
    alike) and its ceiling through the sensor's noise of rms `noise` (with_ceiling)."""
    return with_ceiling(correlation, template, seen, noise * smoothed_noise_rms())


def edge_correlation(template: np.ndarray, seen: np.ndarray, noise: float) -> Correlation:
    """The correlation of the template's edges with those of the capture where ECC's warp puts
    them (seen, smoothed alike; shading_removed both) and its ceiling through the sensor's noise of
    rms `noise`: the capture C = g T + S + n, S a slowly varying shading the model has wrong, has
    edges H C = g H T + H n (H S about 0), so with_ceiling of H T and H C."""
    a, b = shading_removed(template), shading_removed(seen)
    return with_ceiling(correlation_coefficient(a, b), a, b, noise * smoothed_noise_rms(edges=True))


def geometric_edges(task: Task, scene: Scene, T_cell_cam: np.ndarray, window: Window) -> np.ndarray:
    """The pixels of a window (u0, v0, width, height) within GEOMETRY_REACH_PX of an edge of the
    part's geometry, which moves with the part whatever the light does: neighbours (4) of which one
    sees the part and the other not (its silhouette), whose depths differ by more than
    DEPTH_STEP_PX pixel footprints (depth / f_px each: a step) or whose faces turn by more than
    GEOMETRY_TURN_DEG (a crease); kernels.render's hit, depth and normal along each pixel's ray,
    the part's own mesh."""
    width, height = window[2:]
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    step = DEPTH_STEP_PX / float(K[0, 0])
    rays = window_rays(K, T_cell_cam, window)
    origin = T_cell_cam[:3, 3]
    hit = render(scene.warp_mesh, origin, rays, origin, rays[0], 1.0, np.pi, task.part.material.table(), 1.0, 1.0,
                 shadows=False)
    seen = hit.hit.reshape(height, width)
    depth = np.where(seen, hit.depth.reshape(height, width), 0.0)
    normal = hit.normal.reshape(height, width, 3)
    edge = np.zeros((height, width), bool)
    crease = np.cos(np.radians(GEOMETRY_TURN_DEG))
    for a, b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),      # across columns
                 ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):     # across rows
        stepped = np.abs(depth[a] - depth[b]) > step * np.minimum(depth[a], depth[b])
        turned = np.sum(normal[a] * normal[b], axis=-1) < crease
        broken = (seen[a] != seen[b]) | (seen[a] & seen[b] & (stepped | turned))
        edge[a] |= broken
        edge[b] |= broken
    size = 2 * GEOMETRY_REACH_PX + 1
    return cv2.dilate(edge.astype(np.uint8), np.ones((size, size), np.uint8)) > 0


def shading(image: np.ndarray) -> np.ndarray:
    """The image's slowly varying part, its Gaussian blur of SHADING_SIGMA_PX, at least
    RELATIVE_FLOOR of its 99th percentile (where the light fades out, the noise takes over)."""
    blur = cv2.GaussianBlur(image, (0, 0), SHADING_SIGMA_PX)
    return np.maximum(blur, RELATIVE_FLOOR * max(float(np.percentile(blur, 99)), 1e-30))


def geometric_correlation(template: np.ndarray, seen: np.ndarray, mask: np.ndarray, noise: np.ndarray,
                          black: float) -> Correlation:
    """The correlation of the template's edges relative to its shading with the capture's (seen,
    where ECC's warp puts it, smoothed alike, less the black level) over the mask (geometric_edges)
    and its ceiling through the sensor's noise (rms `noise` per pixel of seen): a light the model
    has wrong multiplies the signal by a slowly varying S, C = g S T + n, whose edges relative to
    its shading, shading_removed(C) / shading(C) = shading_removed(T) / shading(T) + n', are the
    model's whatever S is (a lamp turned off its aim moved its soft edge across the hinge's
    window: intensity 0.43 of 0.998, edges 0.78 of 0.955; these 0.98 of 0.999). n' has the rms of the
    noise through the smoothing and shading_removed over the shading, per pixel; with_ceiling
    takes the rms of that over the mask."""
    if not mask.any():
        return Correlation(0.0, 0.0)
    signal = seen - black
    a = (shading_removed(template) / shading(template))[mask]
    b = (shading_removed(signal) / shading(signal))[mask]
    sigma = float(np.sqrt(np.mean(np.square(noise / shading(signal))[mask]))) * smoothed_noise_rms(edges=True)
    return with_ceiling(correlation_coefficient(a, b), a, b, sigma)


def as_aligned(c: Correlation) -> bool:
    """A correlation at least MIN_CORRELATION of its ceiling, that ceiling itself at least
    MIN_CORRELATION (correlates_as_aligned)."""
    return c.ceiling >= MIN_CORRELATION and c.r >= MIN_CORRELATION * c.ceiling


def correlates_as_aligned(intensity: Correlation, edges: Correlation) -> bool:
    """Whether ECC's alignment correlates as a right one does, judged against what the noise
    allows: its correlation at least MIN_CORRELATION of its ceiling, or, where the window's slowly
    varying shading (the model's lamp lobe and soft edge, which the loop's exposure and re-plan
    correct) costs more than that (the hinge 10 mm off at its re-planned poses: 0.937 with the
    correct model, every edge in place), its edges' (edge_correlation) at least MIN_CORRELATION of
    theirs; either ceiling itself at least MIN_CORRELATION (a window whose texture stands clear of
    the noise: there the edges' 0.991-0.994 of 0.997, and 1 px off costs 0.03, 2 px 0.13). The
    noise scales a correlation by its ceiling, to first order, so the share is what the alignment
    would score on a noiseless capture: a right one near 1, whatever the noise."""
    return as_aligned(intensity) or as_aligned(edges)


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
               rotation: float = 0.0, ceiling: float = np.nan) -> Registration:
        return Registration((float(shift[0]), float(shift[1])), footprint, trusted, resolved, float(correlation), note,
                            time.perf_counter() - start, rotation, float(ceiling))

    counts = lights.emitter_counts(task, scene, scene.T_cell_cam)
    found = coarse_shift(image, task, scene, T_cell_cam, lamp_pose, row, col, drives, counts)
    if found.flat is not None:      # no edge around the feature in the model: registered as is, or not at all
        return result((0.0, 0.0), found.flat, 0, np.nan, found.note)
    coarse, turn = found.shift_px, found.turn_deg
    (u0, v0, width, height), template, values, vectors, resolved = edged_window(
        task, scene, T_cell_cam, lamp_pose, row, col, image.shape, drives, counts)
    saturated = float(np.mean(image[v0:v0 + height, u0:u0 + width] >= saturation))
    if saturated > SATURATED_FRACTION:
        return result((0.0, 0.0), False, int(resolved.sum()), np.nan,
                      f"{100 * saturated:.0f} % of the window around the feature saturated")
    if not resolved.any():
        return result((0.0, 0.0), False, 0, np.nan, "the window around the feature has too little edge to align on")
    smoothed = cv2.GaussianBlur(image, (0, 0), SMOOTH_SIGMA)
    a0, b0 = int(u0 + coarse[0]), int(v0 + coarse[1])
    seen = smoothed[max(b0, 0):b0 + height, max(a0, 0):a0 + width]
    if seen.size == 0 or float(seen.std()) <= TEXTURE * float(noise_rms(seen.mean(), task.camera.sensor)):
        return result((0.0, 0.0), False, int(resolved.sum()), np.nan,
                      "the capture shows no edge where the feature should be"
                      + (f" ({found.note})" if found.note else ""))
    centre = np.array([np.mean(col) - u0, np.mean(row) - v0])      # the feature's, in the window
    M = cv2.getRotationMatrix2D(tuple(centre), turn, 1.0)           # window -> image: turned about it,
    warp = np.column_stack([M[:, :2], M[:, 2] + (u0, v0) + coarse]).astype(np.float32)   # then shifted
    initial = warp.copy()
    try:
        correlation, warp = cv2.findTransformECC(  # type: ignore[call-overload]  # OpenCV's stubs: no mask None
            template, smoothed, warp, cv2.MOTION_EUCLIDEAN, ECC_CRITERIA, None, 1)
    except cv2.error:       # its text names OpenCV's source file, not the part: said in the cell's words
        return result((0.0, 0.0), False, int(resolved.sum()), np.nan,
                      "registration did not converge on the feature's edges"
                      + (f" ({found.note})" if found.note else ""))
    at_start = warped_correlation(template, smoothed, initial)
    kept = vectors[:, resolved]                     # project onto the resolved directions
    wandered = float(np.max(np.abs(kept.T @ (warp[:, :2] @ centre + warp[:, 2] - centre - (u0, v0) - coarse))))
    kept_coarse = wandered > COARSE and not found.note
    black = task.camera.sensor.black_level or 0.0

    @cache
    def mask() -> np.ndarray:                          # geometric_edges, rendered when first asked for
        return geometric_edges(task, scene, T_cell_cam, (u0, v0, width, height))

    geometry: dict[bytes, Correlation] = {}

    def geometry_at(w: np.ndarray) -> Correlation:     # the part's geometric edges where warp w puts them,
        key = w.tobytes()                              # each warp's once: ECC's guard asks for the warp
        if key not in geometry:                        # by_geometry judges, when ECC's move is kept or not
            seen = warped(smoothed, w, template.shape)
            geometry[key] = geometric_correlation(template, seen, mask(), noise_rms(seen, task.camera.sensor), black)
        return geometry[key]

    if kept_coarse or not significant(correlation, at_start, template.size) \
            or geometry_at(warp).r < geometry_at(initial).r:
        warp, correlation = initial, at_start         # ECC's move gains what noise could, or it left a
                                                      # coarse match that cleared noise and the whole view,
                                                      # or it took the part's own edges away from the model's
    fine = warp[:, :2] @ centre + warp[:, 2] - centre - (u0, v0)    # where the warp moves it
    rotation = float(np.degrees(np.arctan2(warp[1, 0], warp[0, 0])))
    seen_at = warped(smoothed, warp, template.shape)
    noise = float(noise_rms(seen_at.mean(), task.camera.sensor))
    intensity = intensity_correlation(correlation, template, seen_at, noise)
    edges = edge_correlation(template, seen_at, noise)
    judged = (f"correlation {correlation:.3f} of the {intensity.ceiling:.3f} the noise allows, its edges' "
              f"{edges.r:.3f} of the {edges.ceiling:.3f}")
    by_geometry = not correlates_as_aligned(intensity, edges)
    if by_geometry:             # the shading differs from the model's: do the part's own edges agree?
        shape = geometry_at(warp)
        judged += f", its geometric edges' {shape.r:.3f} of the {shape.ceiling:.3f}"
        if not as_aligned(shape):
            return result((0.0, 0.0), False, int(resolved.sum()), correlation,
                          f"{judged}: a share below {MIN_CORRELATION}", ceiling=intensity.ceiling)
        told, along = structure(template, mask())       # move only where those edges tell
        if np.sum(told >= RATIO * told[-1]) < resolved.sum():
            resolved, vectors = told >= RATIO * told[-1], along
            kept = vectors[:, resolved]
    shift, from_coarse = kept @ (kept.T @ fine), kept.T @ (fine - coarse)
    if np.max(np.abs(from_coarse)) > COARSE:
        return result((0.0, 0.0), False, int(resolved.sum()), correlation, f"ECC ended "
                      f"{np.max(np.abs(from_coarse)):.1f} px from the coarse estimate", ceiling=intensity.ceiling)
    if abs(rotation + turn) > TURN_STEP_DEG:        # the coarse turn of the window is -rotation's
        return result((0.0, 0.0), False, int(resolved.sum()), correlation,
                      f"ECC turned {rotation:+.1f} deg, the coarse estimate {-turn:+.0f} deg",
                      ceiling=intensity.ceiling)
    notes = [judged + (": the shading differs from the model's (the light, which the loop corrects), the part's "
                       "geometric edges are where the alignment puts them") * by_geometry
             ] * (correlation < MIN_CORRELATION or by_geometry)
    notes += [f"ECC wandered {wandered:.0f} px off the coarse match, which is kept (to within {COARSE // 2} px)"
             ] * kept_coarse
    if not resolved.all():
        notes.append(f"resolved across the window's edges only (along "
                     f"{np.degrees(np.arctan2(*vectors[::-1, 0])) % 180:.0f} deg in the image it has none: that "
                     f"component is the model's)")
    return result(shift, True, int(resolved.sum()), correlation, "; ".join(notes), rotation, intensity.ceiling)
