"""Typed inspection task (docs/formats.md), SI units inside. The loader lives in cell.loader."""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from cell.device_config import DevicesConfig
from cell.frames import Frames
from cell.material import Material


@dataclass(frozen=True)
class Part:
    mesh_path: Path
    mesh: trimesh.Trimesh          # in metres, part frame (its pose: Task.frames.T_cell_part)
    material: Material


@dataclass(frozen=True)
class Feature:
    center_m: np.ndarray           # part frame, on the surface (snapped to the closest point)
    normal: np.ndarray             # part frame, unit, outward
    radius_m: float
    samples: int


@dataclass(frozen=True)
class Requirements:
    gray_band: tuple               # (low, high) gray levels
    reflection: str                # diffuse | lobe | spike | any
    region_margin_rad: float
    lamp_tolerance_rad: float
    depth_of_field_m: float = 0.0  # wanted depth of field beyond the feature's own depth range


@dataclass(frozen=True)
class Sensor:
    width_px: int
    height_px: int
    pixel_pitch_m: float
    bit_depth: int
    camera_constant: float         # c of eq. (10) [1/(W s)]

    @property
    def pixel_area_m2(self):
        return self.pixel_pitch_m**2


@dataclass(frozen=True)
class Lens:
    focal_length_m: float
    f_number_range: tuple
    circle_of_confusion_m: float


@dataclass(frozen=True)
class CameraModel:
    distance_m: float
    view_direction: np.ndarray     # part frame, unit, from feature to camera
    sensor: Sensor
    lens: Lens
    shutter_range_s: tuple


@dataclass(frozen=True)
class LampRig:
    pivot_m: np.ndarray            # cell frame
    pan_range_rad: tuple
    tilt_range_rad: tuple
    radius_range_m: tuple
    radius_axis: str               # manual | servo


@dataclass(frozen=True)
class Lamp:
    power_w: float
    cone_angle_rad: float          # full opening angle gamma (eq. 11's normalization)
    rig: LampRig
    profile: np.ndarray = None     # (M, 2) [off_axis_rad, relative]: I(theta)/I(0), linear, 0
                                   # beyond the last angle; None: eq. (11)'s ideal cone

    @property
    def lit_half_angle_rad(self):
        """The off-axis angle beyond which the lamp lights nothing: the profile's end, where it
        reaches 0 for good (gamma / 2 for eq. (11)'s ideal cone)."""
        if self.profile is None:
            return 0.5 * self.cone_angle_rad
        angles, relative = self.profile[:, 0], self.profile[:, 1]
        lit = np.flatnonzero(relative > 0)
        return float(angles[min(lit[-1] + 1, len(angles) - 1)])


@dataclass(frozen=True)
class Truth:
    albedo_scale: float = 1.0
    camera_constant_scale: float = 1.0
    lamp_direction_error_rad: float = 0.0


@dataclass(frozen=True)
class SimConfig:
    seed: int = 1
    effects: tuple = ()
    truth: Truth = Truth()


@dataclass(frozen=True)
class CellConfig:
    backend: str                   # sim | hw
    devices: DevicesConfig         # cell.arm / cell.pan_tilt / cell.camera, defaults filled in


@dataclass(frozen=True)
class Task:
    path: Path
    name: str
    part: Part
    frames: Frames                 # the named transforms: part, robot base, hand-eye
    feature: Feature
    requirements: Requirements
    camera: CameraModel
    lamp: Lamp
    cell: CellConfig
    sim: SimConfig
