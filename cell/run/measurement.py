"""Gray values of the feature in a captured image: at the projected feature samples, and over
the feature's image region (the convex hull of the projected samples)."""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from cell.physics import projection
from cell.core.errors import DeviceFault, GoalNotReached
from cell.planning.plan import gray_stats

if TYPE_CHECKING:
    from cell.task.types import Task


def sample_pixels(task: Task, T_cell_cam: np.ndarray, points: np.ndarray, shift_px: tuple[float, float] = (0.0, 0.0),
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel (row, col) of each feature sample seen from the actual camera pose, moved
    by shift_px (dx, dy: where registration found the feature), and whether it falls inside the
    image."""
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    uv, _ = projection.project(K, T_cell_cam, points)
    uv = uv + np.asarray(shift_px, float)
    sensor = task.camera.sensor
    col = np.rint(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(int)
    row = np.rint(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(int)
    inside = (col >= 0) & (col < sensor.width_px) & (row >= 0) & (row < sensor.height_px)
    return row, col, inside


def read_samples(image: np.ndarray, task: Task, T_cell_cam: np.ndarray, points: np.ndarray,
                 shift_px: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(row, col, inside, gray) of each feature sample in a frame (moved by shift_px,
    sample_pixels): its pixel, whether it is in
    the image, the gray there (NaN outside). A frame of another size than camera.sensor is a
    camera fault (the projection would read the wrong pixels); no sample in the image means the
    camera does not see the feature."""
    sensor = task.camera.sensor
    if np.shape(image)[:2] != (sensor.height_px, sensor.width_px):
        h, w = np.shape(image)[:2]
        raise DeviceFault("camera", f"frames are {w}x{h} px, camera.sensor says "
                                    f"{sensor.width_px}x{sensor.height_px}: set the camera's resolution")
    row, col, inside = sample_pixels(task, T_cell_cam, points, shift_px)
    if not inside.any():
        raise GoalNotReached("no feature sample projects into the image: check the camera pose "
                             "and the hand-eye calibration (cell.arm.hand_eye_*)")
    gray = np.where(inside, np.asarray(image, float)[np.where(inside, row, 0), np.where(inside, col, 0)], np.nan)
    return row, col, inside, gray


def surface_at_samples(image: np.ndarray, m: Measurement) -> np.ndarray:
    """The surface's gray (local_mean over m's feature region) of another frame from the same
    pose at each of m's sample pixels (NaN where m's sample is off the image): a basis capture
    read where its summed capture was."""
    if m.region is None:
        raise ValueError("a joined Measurement has no region of its own")
    inside = np.isfinite(m.sample_gray)
    surface = local_mean(np.asarray(image, float), m.region)
    return np.where(inside, surface[np.where(inside, m.row, 0), np.where(inside, m.col, 0)], np.nan)


def feature_mask(shape: tuple[int, ...], row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Pixels inside the convex hull of the samples' pixels (the feature's image region)."""
    mask = np.zeros(shape, dtype=np.uint8)
    if len(row):
        hull = cv2.convexHull(np.column_stack([col, row]).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def local_mean(image: np.ndarray, mask: np.ndarray, size: int = 5) -> np.ndarray:
    """Mean of each pixel's size x size neighbourhood within mask (normalized convolution): the
    surface's gray with the sensor's pixel noise averaged down by size (5: 5x), while shading that
    changes over tens of pixels passes unchanged. Outside the mask: 0."""
    m = mask.astype(np.float64)
    total = cv2.boxFilter(np.asarray(image, np.float64) * m, -1, (size, size), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(m, -1, (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return np.where(mask, total / np.maximum(count, 1.0), 0.0)


@dataclass(frozen=True)
class BlackLevel:
    """b of G = b + c P t [gray]: what a pixel reads without light, the dark frame's pixel noise
    (rms; 0 when b is the task's) and where b comes from."""

    value: float
    noise_rms: float
    source: str

    @property
    def ceiling(self) -> float:
        """The highest gray that still reads the black level: b + max(1 level, 4 sigma)."""
        return self.value + max(1.0, 4.0 * self.noise_rms)

    def to_json(self) -> dict[str, Any]:
        return {"value": self.value, "noise_rms": self.noise_rms, "source": self.source}


def black_level_of(dark: np.ndarray) -> BlackLevel:
    """BlackLevel of a dark frame: its median (a few lit or hot pixels do not move it) and its
    noise as 1.4826 x the median absolute deviation (the rms of Gaussian noise)."""
    dark = np.asarray(dark, float)
    b = float(np.median(dark))
    return BlackLevel(b, float(1.4826 * np.median(np.abs(dark - b))), "dark frame")


@dataclass(frozen=True)
class Measurement:
    """Gray of one capture over the feature's image region (the convex hull of the projected
    samples, seen from the arm's read-back pose) and at each sample's pixel (NaN off the image).

    The band is judged on the surface's gray at every pixel, local_mean (5x5 within the region):
    a sensor's pixel noise, whose extremes over ten thousand pixels reach +-4 sigma, is no
    property of the lighting and no lamp pose or exposure could narrow it. Without noise the two
    agree to the rounding; the raw pixels' range and the noise are reported beside it."""

    row: np.ndarray              # (P,) each sample's pixel
    col: np.ndarray
    sample_gray: np.ndarray      # (P,) gray there, NaN off the image
    region: np.ndarray | None    # (H, W) bool: the feature's pixels (None: joined, the regions never merged)
    gray: np.ndarray             # raw gray of the region's pixels
    surface: np.ndarray          # their local mean
    saturated: np.ndarray        # (H, W) bool: region pixels at saturation or above
    saturation: float
    min: float                   # of the surface's gray
    max: float

    def stats(self) -> dict[str, float]:
        """measured_gray of report.json: mean/min/max of the surface's gray over the region,
        `pixels` in it, how many read saturation or more, the raw pixels' range as the camera
        delivered them (a real sensor clips at saturation; the sim without `quantization` does
        not) and the pixel noise (rms of raw minus surface)."""
        return {**gray_stats(self.surface), "pixels": int(self.gray.size),
                "saturated": int(self.saturated.sum()),
                "pixel_min": float(self.gray.min()), "pixel_max": float(self.gray.max()),
                "noise_rms": float(np.sqrt(np.mean((self.gray - self.surface) ** 2)))}

    def black_fraction(self, black: BlackLevel) -> float:
        """The fraction of the region's pixels reading the BlackLevel (at most its ceiling):
        no light reaches them (off the part, or a cast shadow)."""
        return float(np.mean(self.gray <= black.ceiling))

    def in_band(self, band: tuple[float, float]) -> bool:
        return not self.saturated.any() and band[0] <= self.min and self.max <= band[1]


def measure_feature(image: np.ndarray, task: Task, T_cell_cam: np.ndarray, points: np.ndarray, saturation: float,
                    shift_px: tuple[float, float] = (0.0, 0.0), exclude: np.ndarray | None = None) -> Measurement:
    """The Measurement of a frame taken from T_cell_cam (read back) of the feature's samples,
    their pixels moved by shift_px (where registration found the feature); `exclude` (H, W): pixels
    left out of its region (a declared defect's: cell.run.defects.on_defects)."""
    row, col, inside, sample_gray = read_samples(image, task, T_cell_cam, points, shift_px)
    image = np.asarray(image, float)
    region = feature_mask(image.shape, row[inside], col[inside])
    if exclude is not None:
        region &= ~exclude
    surface = local_mean(image, region)[region]
    return Measurement(row, col, sample_gray, region, image[region], surface, region & (image >= saturation),
                       float(saturation), float(surface.min()), float(surface.max()))


def joined(measurements: Iterable[Measurement]) -> Measurement:
    """The Measurements of the features of one capture side by side, for the control law judging
    them together (one exposure serves them all): their samples, pixels and surface gray
    concatenated, each as measured in its own region. It has no region (None): the regions are
    never merged; `saturated` flags its pixels in that order."""
    ms = list(measurements)
    cat = lambda get: np.concatenate([get(m) for m in ms])
    return Measurement(cat(lambda m: m.row), cat(lambda m: m.col), cat(lambda m: m.sample_gray), None,
                       cat(lambda m: m.gray), cat(lambda m: m.surface), cat(lambda m: m.saturated[m.region]),
                       ms[0].saturation, min(m.min for m in ms), max(m.max for m in ms))
