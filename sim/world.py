"""The simulated camera's world: the task's scene rendered with the planner's own shading
(kernels.render uses kernels.funcs.shade_point, like the planner's bulk kernel), the world's
"truth" (task `sim.truth`) and only the effects the task lists (`sim.effects`).

gray = value t / kappa^2 with value = c A_pixel Phi R / 8 (eq. 10, 11, 17) per pixel, shaded in
the world the truth (`sim.truth`) declares: the true material (truth `material`, else the task's)
with rho * albedo_scale, the true c (model c * camera_constant_scale), the part at its true pose
(T_cell_part moved by part_offset_m in the cell frame after turning by part_rpy about the feature
centre), the camera where the arm's reported pose composed with the hand-eye error (camera_offset_m,
camera_rpy in the camera frame) puts it, the lamp lamp_radius_error_m farther from the pivot along
its commanded aim and its true axis lamp_direction_error away from that aim (the axis enters only
through the lamp's profile). With no effects and a neutral truth a pixel's gray is the planner's
prediction at the point it sees: the task's lamp profile (`lamp.profile`; without one eq. (11)'s
ideal cone with a hard edge), no cast shadows, float gray, unclipped.

Every light of the task (`lights`) is rendered besides the spot, as the planner sees it: its
emitter points (cell.planning.lights.emitters) through the same kernel, each with its own shadow
ray, so that with `shadows` an extended light casts soft shadows. The number of points is the
planner's own rule (cell.planning.lights.emitter_counts: doubled until doubling moves no feature
sample by INTEGRATION_GRAY gray at the band's top), found once per light at the feature's samples
seen from the scene's camera pose, so the image integrates each light as finely as the plan
did. Each light shines at its channel's drive level as the lighting controller reads it back
(none given: every light at full drive), the spot at its channel's (1 when it has none),
G = sum_k w_k s_k G_k with s_k the truth's channel_power_scale (0: a dead channel): linear in
every drive, as the planner assumes (cell.planning.drives). cone_falloff softens the spot's edge only.

Effects, applied in the physical order light -> lens -> sensor -> ADC, whatever the list's order:
  shadows       cast shadows (the kernel's shadow rays); faces turned from the lamp are dark anyway
  cone_falloff  the world's lamp has a softer edge than the model's: the model's profile (the
                task's, else eq. (11)'s hard cone) blurred in angle by a Gaussian (1 deg for a
                12 deg cone), so the model holds near the axis, the edge falls more gently (the
                hard cone: to half at the nominal edge) and some light spills beyond it
  vignetting    natural vignetting, cos^4 of the ray's angle to the optical axis
  defocus       thin-lens blur, circle of confusion c of depth_of_field.blur_diameter per pixel
  noise         EMVA 1288's sensor (SensorModel): shot noise (Poisson in electrons), dark noise,
                the full well; the datasheet's camera.sensor keys where given, else FULL_WELL_E at
                full scale and READ_NOISE_E
  black_level   a constant offset, BLACK_LEVEL of full scale (5 gray at 8 bits)
  quantization  gray rounded to integers, clipped to [0, 2^bits - 1] (uint8, or uint16 above 8 bits)
  defects       each feature's declared defects (`defects`) on the part, where the task puts them
                (`position_m`, else the feature's centre; moved with the part's true pose), a
                scratch at sim.truth.defect_orientation of its name, else its range's first; on
                cell.physics.contrast.footprint: each pixel whose ray hits the defect is shaded
                again with the defect's normal (a scratch's wall turned by +-atan(2 h / w), a
                dent's normal leaning by asin(rho / R)) or its material (a coating). One ray per
                pixel: a groove narrower than a pixel shows at its walls' full contrast in the
                pixels whose centre it crosses, as the planner assumes (cell.planning.defects)
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import gaussian_filter
from scipy.special import erfc, ndtr

from cell.core import geometry
from cell.physics import contrast
from cell.physics.sensor import (BLACK_LEVEL, FULL_WELL_E, READ_NOISE_E, dark_noise, levels,  # noqa: F401
                                 saturation_level, system_gain)
from cell.physics.depth_of_field import blur_diameter
from cell.physics.projection import intrinsics, pixel_rays
from cell.planning import lights
from cell.planning.scene import Scene, build_scene
from kernels.render import RenderResult, render

if TYPE_CHECKING:
    from cell.task.types import Defect, Sensor, Task

CONE_EDGE = 1.0 / 6.0       # cone edge blur s as a fraction of the half angle gamma/2
DEFOCUS_STEP_PX = 0.5       # defocus depth layers: circle of confusion in these steps
# FULL_WELL_E, READ_NOISE_E, BLACK_LEVEL: cell.physics.sensor's, which the planner's noise reads too


def cone_falloff(off_axis_rad: ArrayLike, cone_angle_rad: float, profile: np.ndarray | None = None) -> np.ndarray:
    """The world's lamp profile: irradiance relative to the model's on the axis (its profile's
    energy-conserving I(0), kernels.emission.axis_intensity) at off-axis angle
    theta, the model's profile blurred in angle by a Gaussian of s = CONE_EDGE gamma/2. Without a
    profile (the hard cone) erfc((theta - gamma/2) / (sqrt 2 s)) / 2; with one, blurred_profile."""
    half = 0.5 * cone_angle_rad
    if profile is not None:
        return blurred_profile(off_axis_rad, profile, CONE_EDGE * half)
    return 0.5 * erfc((np.asarray(off_axis_rad) - half) / (np.sqrt(2.0) * CONE_EDGE * half))


def _normal_pdf(x):
    return np.exp(-0.5 * x * x) / np.sqrt(2.0 * np.pi)


def blurred_profile(off_axis_rad: ArrayLike, profile: ArrayLike, s: float) -> np.ndarray:
    """E[f(|theta + X|)], X ~ N(0, s^2): a profile f (M, 2) [off_axis_rad, relative], linear and 0
    beyond its last angle, blurred in angle across the axis (f(|t|) along a line through it). On a
    segment [a, b], f = f_a + beta (t - a), its integral against N(t; mu, s) is
    (f_a + beta (mu - a)) (Phi(B) - Phi(A)) - beta s (phi(B) - phi(A)), A = (a - mu) / s,
    B = (b - mu) / s; E sums it over the segments at mu = theta and mu = -theta."""
    theta = np.abs(np.asarray(off_axis_rad, dtype=float))
    profile = np.asarray(profile, dtype=float)
    a, b = profile[:-1, 0], profile[1:, 0]
    f_a, beta = profile[:-1, 1], np.diff(profile[:, 1]) / np.diff(profile[:, 0])
    out = np.zeros_like(theta)
    for mu in (theta, -theta):                  # |t| folds the Gaussian about the axis
        for k in range(len(a)):
            A, B = (a[k] - mu) / s, (b[k] - mu) / s
            out += ((f_a[k] + beta[k] * (mu - a[k])) * (ndtr(B) - ndtr(A))
                    - beta[k] * s * (_normal_pdf(B) - _normal_pdf(A)))
    return out


def defocus(gray: np.ndarray, depth_m: np.ndarray, focus_m: float, focal_length_m: float, f_number: float,
            pixel_pitch_m: float) -> np.ndarray:
    """Thin-lens blur: each depth layer (circle of confusion c in DEFOCUS_STEP_PX steps) is spread
    by the Gaussian with its disk's second moment (sigma = c / 4) and the layers are summed, so
    light is conserved (occlusion at depth steps is ignored). depth_m along the optical axis."""
    c_px = blur_diameter(depth_m, focus_m, focal_length_m, f_number) / pixel_pitch_m
    layer = np.rint(c_px / DEFOCUS_STEP_PX)
    out = np.zeros_like(gray)
    for k in np.unique(layer[gray != 0.0]):
        light = np.where(layer == k, gray, 0.0)
        out += gaussian_filter(light, k * DEFOCUS_STEP_PX / 4.0, mode="constant") if k else light
    return out


@dataclass(frozen=True)
class SensorModel:
    """EMVA 1288's linear camera model behind the lens: the noiseless gray G = c P t is
    mu_e = G / K electrons; noise makes them Poisson(mu_e) plus Gaussian dark noise sigma_d, the
    full well mu_e,sat clips them, and the gray is K e + black level, rounded. So mean
    K (eta mu_p) + b and variance K^2 (sigma_d^2 + eta mu_p) + 1/12 (rounding), mu_p photons."""

    gain_dn_per_e: float            # K
    dark_noise_e: float             # sigma_d
    saturation_capacity_e: float    # mu_e,sat (inf: only the ADC clips)
    black_level: float              # b [gray]
    bit_depth: int

    @classmethod
    def of(cls, sensor: Sensor) -> SensorModel:
        """The task's sensor: its datasheet keys (camera.sensor) where given, else FULL_WELL_E
        electrons at full scale, READ_NOISE_E and no full well below the ADC's top."""
        full_scale = float(saturation_level(sensor.bit_depth))
        gain = system_gain(sensor.bit_depth, sensor.system_gain_dn_per_e)
        dark = dark_noise(sensor.dark_noise_e)
        return cls(gain, dark, sensor.saturation_capacity_e or np.inf, float(np.rint(BLACK_LEVEL * full_scale)),
                   sensor.bit_depth)

    def read_out(self, gray: np.ndarray, effects: Collection[str], rng: np.random.Generator) -> np.ndarray:
        """The sensor's image of the noiseless gray, with the effects listed: noise (shot, dark,
        full well), black_level, quantization (integers clipped to the bit depth)."""
        if "noise" in effects:
            electrons = rng.poisson(gray / self.gain_dn_per_e) + rng.normal(0.0, self.dark_noise_e, gray.shape)
            gray = self.gain_dn_per_e * np.minimum(electrons, self.saturation_capacity_e)
        if "black_level" in effects:
            gray = gray + self.black_level
        if "quantization" in effects:
            gray = levels(gray, self.bit_depth)
        return gray


def part_moved(task: Task, scene: Scene) -> np.ndarray:
    """4x4, cell frame: how the truth moves the part from its model pose, its part_offset_m (cell
    frame) after turning by part_rpy about the feature centre (the identity when neutral)."""
    truth = task.sim.truth
    about = geometry.transform(translation=scene.center)
    return (geometry.transform(translation=truth.part_offset_m) @ about @ geometry.from_rpy(truth.part_rpy_rad)
            @ np.linalg.inv(about))


def true_part_scene(task: Task, scene: Scene) -> Scene:
    """The scene with the part at its true pose (part_moved); `scene` itself when neutral."""
    truth = task.sim.truth
    if not (np.any(truth.part_offset_m) or np.any(truth.part_rpy_rad)):
        return scene
    T_cell_part = part_moved(task, scene) @ task.frames.T_cell_part
    return build_scene(replace(task, frames=task.frames.with_transform("T_cell_part", T_cell_part)))


@dataclass(frozen=True)
class PlacedDefect:
    """A declared defect where the world has it (cell frame): its position, the feature frame
    there (columns x, y, n), the offset (x, y) of its position from the feature's centre, the
    feature's radius, a scratch's orientation [rad] and a coating's BRDF table."""

    defect: Defect
    position: np.ndarray
    frame: np.ndarray
    from_centre: np.ndarray
    feature_radius_m: float
    theta_rad: float
    table: np.ndarray | None

    def parts(self, points: np.ndarray) -> np.ndarray:
        """(P,) which part of the defect each cell-frame point is on (contrast.footprint)."""
        d, offsets = self.defect, (points - self.position) @ self.frame[:, :2]
        if d.kind == "scratch":
            chord = contrast.scratch_chord(self.from_centre, self.theta_rad, self.feature_radius_m)
            return contrast.footprint(offsets, "scratch", self.theta_rad, float(d.width_m or 0.0), chord_m=chord)[0]
        return contrast.footprint(offsets, d.kind, radius_m=float(d.radius_m or 0.0))[0]

    def normals(self, points: np.ndarray, normals: np.ndarray, parts: np.ndarray) -> np.ndarray:
        """(P, 3) the surface's normals at points on the defect (a coating keeps them)."""
        d, x_axis = self.defect, self.frame[:, 0]
        if d.kind == "scratch":
            tilt = contrast.wall_tilt(float(d.width_m or 0.0), float(d.depth_m or 0.0))
            return contrast.wall_normals(normals, x_axis, self.theta_rad, tilt, parts)
        if d.kind == "dent":
            offsets = (points - self.position) @ self.frame[:, :2]
            return contrast.dimple_normals(normals, x_axis, offsets, float(d.radius_m or 0.0), float(d.depth_m or 0.0))
        return normals


def placed_defects(task: Task, scene: Scene) -> tuple[PlacedDefect, ...]:
    """Every feature's declared defects where the world has them: position_m (else the feature's
    centre) and the feature frame (geometry.frame_from_normal, as the planner's scene) moved with
    the part's true pose (part_moved); a scratch at the truth's defect_orientation of its name,
    else its range's first."""
    T_model, moved = task.frames.T_cell_part, part_moved(task, scene)
    T_true = moved @ T_model
    orientation = dict(task.sim.truth.defect_orientation_rad)
    out = []
    for f in task.features:
        centre = (T_true @ np.append(f.center_m, 1.0))[:3]
        frame = moved[:3, :3] @ geometry.frame_from_normal(T_model[:3, :3] @ f.normal)
        for d in f.defects:
            position = centre if d.position_m is None else (T_true @ np.append(d.position_m, 1.0))[:3]
            table = d.material.table() if d.kind == "coating" and d.material is not None else None
            out.append(PlacedDefect(d, position, frame, (position - centre) @ frame[:, :2], f.radius_m,
                                    orientation.get(d.name, d.orientation_rad[0]), table))
    return tuple(out)


class Lit(NamedTuple):
    """How a capture is lit: the true camera pose (a flange light rides on it), the lamp's
    position and true axis, the channels' drives (None: all at full)."""

    T_cell_cam: np.ndarray
    lamp_pos: np.ndarray
    lamp_axis: np.ndarray
    drives: Mapping[int, float] | None


class Renderer:
    """What the simulated camera sees of a task's scene (cell.planning.scene.build_scene), called by
    sim.camera.SimCamera. `scale` < 1 samples a coarser pixel grid over the same sensor (gray per
    real pixel unchanged), for fast tests; K is the grid's camera matrix."""

    def __init__(self, task: Task, scene: Scene, scale: float = 1.0) -> None:
        sensor, lens = task.camera.sensor, task.camera.lens
        self.task, self.scene, self.effects = task, scene, frozenset(task.sim.effects)
        grid = replace(sensor, width_px=round(sensor.width_px * scale),
                       height_px=round(sensor.height_px * scale),
                       pixel_pitch_m=sensor.pixel_pitch_m / scale)
        self.shape, self.pixel_pitch_m = (grid.height_px, grid.width_px), grid.pixel_pitch_m
        self.K = intrinsics(grid, lens)
        self.rays_cam = pixel_rays(self.K, np.eye(4), grid.width_px, grid.height_px)
        truth = task.sim.truth
        self.table = (truth.material or task.part.material).scaled(truth.albedo_scale).table()
        self.camera_constant = sensor.camera_constant * truth.camera_constant_scale
        self.sensor = SensorModel.of(sensor)
        self.world = true_part_scene(task, scene)
        self.T_cam_true = geometry.from_rpy(truth.camera_rpy_rad, truth.camera_offset_m)
        self.rng = np.random.default_rng(task.sim.seed)
        self.error_direction_rad = self.rng.uniform(0.0, 2.0 * np.pi)
        self.power_scale = dict(truth.channel_power_scale)
        self.points = lights.emitter_counts(task, self.world, scene.T_cell_cam)
        self.defects = placed_defects(task, scene) if "defects" in self.effects else ()

    def light_factor(self, channel: int | None, drives: Mapping[int, float] | None) -> float:
        """A light's share of its full power in the world: its channel's drive level (1 without a
        channel or without drives given) times the truth's channel_power_scale of that channel."""
        return lights.drive_level(channel, drives) * (1.0 if channel is None else self.power_scale.get(channel, 1.0))

    def lamp_axis(self, lamp_aim: ArrayLike) -> np.ndarray:
        """The lamp's true axis: the commanded aim turned by lamp_direction_error toward a direction
        drawn once from the seed (a mis-mounted lamp errs the same way at every pose)."""
        aim = geometry.unit(lamp_aim)
        x, y = geometry.frame_from_normal(aim)[:, :2].T
        error, psi = self.task.sim.truth.lamp_direction_error_rad, self.error_direction_rad
        return np.cos(error) * aim + np.sin(error) * (np.cos(psi) * x + np.sin(psi) * y)

    def shade(self, origin: np.ndarray, dirs: np.ndarray, lit: Lit, table: np.ndarray,
              normals: np.ndarray | None = None) -> tuple[np.ndarray, RenderResult]:
        """(value per ray (N,), the spot's kernels.render.RenderResult): the spot (cone_falloff
        applied) and every light at its drive, shaded with the world's table, and with `normals`
        (N, 3) instead of the faces' where given."""
        T_cell_cam, lamp_pos, axis, drives = lit
        effects, lamp, sensor = self.effects, self.task.lamp, self.task.camera.sensor
        soft_cone = "cone_falloff" in effects            # then rendered on-axis, scaled here
        mesh, part_faces = self.world.shadow_mesh, len(self.world.faces)      # the lights' housings after the part
        r = render(mesh, origin, dirs, lamp_pos, axis, lamp.power_w,
                   lamp.cone_angle_rad, table, self.camera_constant, sensor.pixel_area_m2,
                   shadows="shadows" in effects, cone=not soft_cone, profile=lamp.profile, shading_normals=normals,
                   part_faces=part_faces)
        if soft_cone:
            lamp_to_point = origin + r.depth[r.hit, None] * dirs[r.hit] - lamp_pos
            cos_off_axis = np.clip(np.einsum("nj,j->n", geometry.unit(lamp_to_point), axis), -1.0, 1.0)
            r.value[r.hit] *= cone_falloff(np.arccos(cos_off_axis), lamp.cone_angle_rad, lamp.profile)
        value = self.light_factor(lamp.channel.number, drives) * r.value
        value += lights.rendered(mesh, origin, dirs, T_cell_cam, self.task.lights, self.points,
                                 [self.light_factor(light.channel.number, drives) for light in self.task.lights],
                                 table, self.camera_constant, sensor.pixel_area_m2,
                                 shadows="shadows" in effects, shading_normals=normals, part_faces=part_faces)
        return value, r

    def __call__(self, T_cell_cam: np.ndarray, lamp_pos: np.ndarray, lamp_aim: ArrayLike, shutter_s: float,
                 f_number: float, focus_m: float | None = None,
                 drives: Mapping[int, float] | None = None) -> np.ndarray:
        """Gray image (H, W): float, or integers with quantization, seen from the camera pose the
        arm reports (T_cell_cam; the true one is T_cell_cam T_cam_true) with the lamp at its
        read-back pose and each channel at its drive level (drives {channel: level 0..1}, the
        controller's read-back; a channel not in it is off; None: every light at full drive).
        focus_m is the lens's focus distance along the optical axis (None: the feature centre's,
        as planned, sec. 5.4)."""
        task, effects = self.task, self.effects
        T_cell_cam = T_cell_cam @ self.T_cam_true
        origin, optical_axis = T_cell_cam[:3, 3], T_cell_cam[:3, 2]
        lamp_pos = lamp_pos - task.sim.truth.lamp_radius_error_m * geometry.unit(lamp_aim)
        # einsum, not BLAS: OpenBLAS threads left spinning after a matmul slow the Warp kernel 4x
        dirs = np.einsum("ij,nj->ni", T_cell_cam[:3, :3], self.rays_cam)
        lit = Lit(T_cell_cam, lamp_pos, self.lamp_axis(lamp_aim), drives)
        value, r = self.shade(origin, dirs, lit, self.table)
        hit = np.flatnonzero(r.hit)
        points = origin + r.depth[hit, None] * dirs[hit]
        for placed in self.defects:
            parts = placed.parts(points)
            on = parts > 0
            if on.any():
                rays = hit[on]
                value[rays] = self.shade(origin, dirs[rays], lit, self.table if placed.table is None else placed.table,
                                         placed.normals(points[on], r.normal[rays], parts[on]))[0]
        gray = (value * shutter_s / f_number**2).reshape(self.shape)
        cos_field = self.rays_cam[:, 2].reshape(self.shape)
        if "vignetting" in effects:
            gray = gray * cos_field**4
        if "defocus" in effects:
            if focus_m is None:
                focus_m = (self.scene.center - origin) @ optical_axis
            gray = defocus(gray, r.depth.reshape(self.shape) * cos_field, focus_m,
                           task.camera.lens.focal_length_m, f_number, self.pixel_pitch_m)
        return self.sensor.read_out(gray, effects, self.rng)
