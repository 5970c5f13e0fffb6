"""Typed inspection task (docs/formats.md), SI units inside. The loader lives in cell.task.loader."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from cell.task.board import Board
from cell.task.collision import CollisionConfig
from cell.task.device_config import DevicesConfig
from cell.core.frames import Frames
from cell.physics.material import Material


@dataclass(frozen=True)
class Part:
    mesh_path: Path
    mesh: trimesh.Trimesh          # in metres, part frame (its pose: Task.frames.T_cell_part)
    material: Material


@dataclass(frozen=True)
class Requirements:
    gray_band: tuple[float, float]         # (low, high) gray levels
    reflection: str                # diffuse | lobe | spike | any
    region_margin_rad: float
    lamp_tolerance_rad: float
    depth_of_field_m: float = 0.0  # wanted depth of field beyond the feature's own depth range
    resolution_m: float | None = None      # a pixel covers at most this on the feature (None: not asked)
    view_angle_rad: float | None = None    # the camera at most this far from each sample's normal
    drive_tolerance: float = 0.0           # each light channel's true drive within drive x (1 +- this)
    light_tolerance_rad: float = 0.0       # each light's aim (besides the spot) off by up to this: its pose error
    gray_any: bool = False                 # `gray_band: any`: only the defects' contrast matters, gray_band the
                                           # sensor's range (cell.task.loader.any_band)


DEFECT_KINDS = ("scratch", "dent", "coating")


@dataclass(frozen=True)
class Defect:
    """A defect the inspection must see on a feature (`defects`, docs/formats.md), with the
    contrast-to-noise ratio it must show at least (cell.physics.contrast): a `scratch`, a V-groove
    of width_m and depth_m in any orientation of orientation_rad (from, to) in the feature's
    tangent plane from the feature frame's x axis; a `dent`, a spherical dimple of radius_m and
    depth_m (its sagitta); a `coating`, a patch of radius_m of another material. position_m (part
    frame, None: the feature's centre) is where the simulator puts it; the planner asks for it
    at every point of the feature."""

    name: str
    kind: str                      # DEFECT_KINDS
    min_cnr: float
    width_m: float | None = None                   # scratch
    depth_m: float | None = None                   # scratch, dent
    orientation_rad: tuple[float, float] = (0.0, float(np.pi))     # scratch
    radius_m: float | None = None                  # dent, coating
    material: Material | None = None               # coating
    position_m: tuple[float, float, float] | None = None   # part frame
    key: str = "feature.defects[0]"                # where the task file gives it, for errors


@dataclass(frozen=True)
class Feature:
    name: str                      # `feature` for the one-feature form
    center_m: np.ndarray           # part frame, on the surface (snapped to the closest point)
    normal: np.ndarray             # part frame, unit, outward
    radius_m: float
    samples: int
    requirements: Requirements     # the task's, with the feature's own keys replacing them
    key: str = "feature"           # where the task file gives it (`features[2]`), for errors
    defects: tuple[Defect, ...] = ()       # what the inspection must see on it (cell.planning.defects)


@dataclass(frozen=True)
class Sensor:
    width_px: int
    height_px: int
    pixel_pitch_m: float
    bit_depth: int
    camera_constant: float         # c of eq. (10) [1/(W s)], as given or from the datasheet keys
    camera_constant_stderr: float | None = None    # as measured (cell calibrate camera-constant)
    # EMVA 1288 datasheet figures (None: not given); eta and K give c, K and the rest the sim's noise
    quantum_efficiency: float | None = None        # eta at wavelength_m
    wavelength_m: float | None = None              # the light's (the lamp's) wavelength
    system_gain_dn_per_e: float | None = None      # K [gray per electron]
    dark_noise_e: float | None = None              # sigma_d [electrons rms]
    saturation_capacity_e: float | None = None     # mu_e,sat [electrons]
    source: str | None = None                      # where the numbers come from
    file: Path | None = None                       # the camera file they were read from, if any
    black_level: float | None = None               # b of G = b + c P t [gray]; None: measured by `cell run`

    @property
    def pixel_area_m2(self) -> float:
        return self.pixel_pitch_m**2


@dataclass(frozen=True)
class Lens:
    focal_length_m: float
    f_number_range: tuple[float, float]
    circle_of_confusion_m: float


@dataclass(frozen=True)
class Viewpoint:
    """How the camera's pose is chosen (`camera.viewpoint`): `fixed`, the task's rule
    (distance_m along view_direction), or `planned` on view spheres around each feature
    (cell.planning.viewpoints): radii over standoff_range_m in standoff_steps, directions step_rad apart,
    at most per_feature poses of each feature tried with lamps."""

    mode: str = "fixed"
    standoff_range_m: tuple[float, float] | None = None
    standoff_steps: int = 3
    step_rad: float = float(np.radians(15.0))
    per_feature: int = 3


@dataclass(frozen=True)
class CameraModel:
    distance_m: float
    view_direction: np.ndarray     # part frame, unit, from feature to camera
    sensor: Sensor
    lens: Lens
    shutter_range_s: tuple[float, float]
    viewpoint: Viewpoint = Viewpoint()


@dataclass(frozen=True)
class LampRig:
    pivot_m: np.ndarray            # cell frame
    pan_range_rad: tuple[float, float]
    tilt_range_rad: tuple[float, float]
    radius_range_m: tuple[float, float]
    radius_axis: str               # manual | servo


@dataclass(frozen=True)
class Channel:
    """Where a light is driven: its channel on the lighting controller (None: on its own supply,
    always at full drive), the drive levels it may take (fractions of full) and whether it can
    only be switched (off, or at the range's top)."""

    number: int | None = None
    drive_range: tuple[float, float] = (0.0, 1.0)
    switched: bool = False


@dataclass(frozen=True)
class Lamp:
    """The spot on the pan-tilt rig (`lamp`, or a `lights` entry with mount: pan_tilt)."""

    power_w: float
    cone_angle_rad: float          # full opening angle gamma (eq. 11's cone; with a profile its beam angle)
    rig: LampRig
    profile: np.ndarray | None = None# (M, 2) [off_axis_rad, relative]: I(theta)/I(0), linear, 0
                                   # beyond the last angle; None: eq. (11)'s ideal cone
    name: str = "lamp"
    channel: Channel = Channel()
    key: str = "lamp"              # where the task file gives it (`lamp`, or `lights[i]`), for errors

    @property
    def lit_half_angle_rad(self) -> float:
        """The off-axis angle beyond which the lamp lights nothing: the profile's end, where it
        reaches 0 for good (gamma / 2 for eq. (11)'s ideal cone)."""
        if self.profile is None:
            return 0.5 * self.cone_angle_rad
        angles, relative = self.profile[:, 0], self.profile[:, 1]
        lit = np.flatnonzero(relative > 0)
        return float(angles[min(lit[-1] + 1, len(angles) - 1)])


LIGHT_TYPES = ("spot", "ring", "bar", "area", "dome", "coaxial")
MOUNTS = ("fixed", "pan_tilt", "flange")


@dataclass(frozen=True)
class Light:
    """A light that stays where it is mounted while the pan-tilt's spot is searched (`lights`,
    docs/formats.md): fixed in the cell or on the camera's flange. Its pose is its emitting
    surface's centre and the unit axis it emits along; a flange light's is in the camera frame
    (z the optical axis), at offset_m along it, so that it moves with the camera. The shape's
    keys are its type's (cell.planning.lights samples it into emitter points); each point emits
    by `profile` (I(theta)/I(0), None: a Lambertian emitter, cos theta), their powers summing to
    power_w."""

    name: str
    type: str                      # LIGHT_TYPES
    mount: str                     # fixed | flange
    power_w: float                 # radiant, all of it (energy conserved over the profile)
    channel: Channel
    position_m: np.ndarray         # fixed: cell frame; flange: camera frame (0, 0, offset_m)
    axis: np.ndarray               # unit, the frame's as position_m
    along: np.ndarray              # unit, perpendicular to axis: a bar's length, an area's width
    profile: np.ndarray | None = None      # (M, 2) [off_axis_rad, relative]; None: Lambertian
    cone_angle_rad: float | None = None    # spot: eq. (11)'s cone when it has no profile
    radius_m: float | None = None          # ring, dome, a disk area or coaxial source
    tilt_rad: float = 0.0                  # ring: LEDs tilted toward the axis
    length_m: float | None = None          # bar
    size_m: tuple[float, float] | None = None      # area or coaxial rectangle [width, height]
    hole_radius_m: float | None = None     # dome: the camera's hole at its pole
    key: str = "lights[0]"                 # where the task file gives it, for errors
    housing_depth_m: float | None = None   # fixed: its housing this deep behind the emitting surface
    aperture_radius_m: float | None = None     # fixed ring: its housing's hole (the camera looks through)
    outer_radius_m: float | None = None        # fixed ring: its housing's outer edge

    def housing(self) -> HousingSize:
        """A fixed light's housing (`lights[]` housing keys, docs/formats.md), the defaults filled
        in: HOUSING_DEPTH_M deep, a ring's annulus HOUSING_RIM_M either side of its LEDs' circle
        (the hole at least half the radius)."""
        radius = float(self.radius_m or 0.0)
        aperture = self.aperture_radius_m if self.aperture_radius_m is not None else max(
            radius - HOUSING_RIM_M, 0.5 * radius)
        outer = self.outer_radius_m if self.outer_radius_m is not None else radius + HOUSING_RIM_M
        depth = self.housing_depth_m if self.housing_depth_m is not None else HOUSING_DEPTH_M
        return HousingSize(float(depth), float(aperture), float(outer))


# a fixed light's housing where the task gives no size: its emitting surface's extent plus HOUSING_RIM_M
# each side, HOUSING_DEPTH_M deep behind it (an LED bar's or ring's body: some 10-30 mm; datasheets vary)
HOUSING_RIM_M, HOUSING_DEPTH_M = 0.005, 0.020


@dataclass(frozen=True)
class HousingSize:
    """A fixed light's housing behind its emitting surface [m]: its depth, and a ring's annulus
    (aperture_radius_m, the hole the camera looks through, to outer_radius_m)."""

    depth_m: float
    aperture_radius_m: float
    outer_radius_m: float


@dataclass(frozen=True)
class Truth:
    """How the simulated world differs from the model (docs/formats.md, `sim.truth`); vectors as
    tuples, so that truths compare equal."""

    albedo_scale: float = 1.0
    camera_constant_scale: float = 1.0
    lamp_direction_error_rad: float = 0.0
    material: Material | None = None           # the world's BRDF table; None: the task's
    part_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)# cell frame
    part_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)# about the feature centre
    camera_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)# camera frame (hand-eye error)
    camera_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lamp_radius_error_m: float = 0.0           # the lamp this much farther from the pivot
    channel_power_scale: tuple[tuple[int, float], ...] = ()  # (channel, its true power / the model's); 0: dead
    defect_orientation_rad: tuple[tuple[str, float], ...] = ()  # (a scratch's name, its orientation in the world)


@dataclass(frozen=True)
class LoopSettings:
    """The closed loop's limits (`loop`): the albedo scales a correction may imply, how far
    from where the model puts it the feature may be found (registration) [m]."""

    albedo_scale_range: tuple[float, float] = (0.1, 10.0)
    registration_limit_m: float | None = None    # None: the plan's (cell.run.loop.registration_limit)


@dataclass(frozen=True)
class Sample:
    """The goniometer's flat sample (`calibration.sample`): a disc of the material at the lamp
    rig's pivot, its top face there, facing `normal` (cell frame, unit)."""

    material: Material | None = None           # the material it is made of (None: the part's)
    radius_m: float = 0.025
    thickness_m: float = 0.002
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Goniometer:
    """How `cell measure-brdf` samples the BRDF (`calibration.goniometer`)."""

    phase_rad: tuple[float, ...] = tuple(np.radians([20.0, 40.0, 60.0]))
    step_rad: float = float(np.radians(2.0))   # of the half-angle's tilt, in the plane of incidence
    max_angle_rad: float = float(np.radians(80.0))   # ti and te at most
    # the lamp's distance from the pivot: the loader's (calibration.goniometer.lamp_radius_m, by
    # default the middle of lamp.rig.radius_range_m, which only the task knows: no default here)
    lamp_radius_m: float = field(kw_only=True)


@dataclass(frozen=True)
class Calibration:
    sample: Sample = Sample()
    goniometer: Goniometer = field(kw_only=True)    # no default: its lamp radius is the task's


@dataclass(frozen=True)
class SimConfig:
    seed: int = 1
    effects: tuple[str, ...] = ()
    truth: Truth = Truth()


@dataclass(frozen=True)
class CellConfig:
    backend: str                   # sim | hw
    devices: DevicesConfig         # cell.arm / cell.pan_tilt / cell.camera, defaults filled in
    collision: CollisionConfig = CollisionConfig()   # cell.collision, defaults filled in


@dataclass(frozen=True)
class Task:
    path: Path
    name: str
    part: Part
    frames: Frames                 # the named transforms: part, robot base, hand-eye
    features: tuple[Feature, ...]  # Feature, one or more
    camera: CameraModel
    lamp: Lamp
    cell: CellConfig
    sim: SimConfig
    board: Board                   # the ChArUco board (calibration.board)
    loop: LoopSettings = LoopSettings()
    lights: tuple[Light, ...] = ()             # the lights besides the pan-tilt's spot
    calibration: Calibration = field(kw_only=True)   # no default: its goniometer's lamp radius is the task's

    @property
    def feature(self) -> Feature:
        """The task's only feature (what one-shot planning, the loop and calibration work on)."""
        if len(self.features) != 1:
            raise ValueError(f"the task has {len(self.features)} features; plan them with "
                             f"cell.planning.whole_part.plan_features, or take one with task.with_feature(i)")
        return self.features[0]

    @property
    def whole_part(self) -> bool:
        """Whether the task is planned and run as a whole part, shot by shot (several features or
        a planned viewpoint: cell.planning.whole_part, cell.run.inspection), not as one shot."""
        return len(self.features) != 1 or self.camera.viewpoint.mode != "fixed"

    @property
    def channels(self) -> dict[int, str]:
        """The lighting controller's channels the task's lights are on, {channel: the key of the
        light's channel in the task file}, the spot's first; empty when no light is on a channel."""
        spot = self.lamp.channel.number
        return ({} if spot is None else {spot: f"{self.lamp.key}.channel"}) | {
            light.channel.number: f"{light.key}.channel" for light in self.lights if light.channel.number is not None}

    @property
    def requirements(self) -> Requirements:
        """The only feature's requirements."""
        return self.feature.requirements

    def with_feature(self, i: int) -> Task:
        """The one-feature task of feature i (the rest of the task shared)."""
        return replace(self, features=(self.features[i],))
