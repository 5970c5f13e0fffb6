"""Localization: where the part and the camera really are, from the loop's own captures.

The model's image of the whole view (registration.expected_image: the planner's shading at the
read-back camera and lamp poses) and the cell-frame point each of its pixels sees (kernels.render's
depth) are compared with the capture by their edges: both equalized (the logarithm of the gray,
so the lamp's falloff and the shading add a slowly varying term) and band-passed (a Gaussian of
sigma less one of BAND_RATIO sigma). The model's strongest edge pixels (EDGE_QUANTILE) are
samples: a point X on the part and the model's band-passed gray there.

What explains them: the part's pose error E_part in the cell frame (turned by part_rpy about the
feature centre c, then moved by part_offset, as the simulator's truth keys state it) and the
camera's hand-eye turn E_he (in the camera frame, T_true = T_read E_he). X appears in view i,
taken from the read-back pose C_i, at

    u = pi(K, E_he^-1 C_i^-1 E_part X),

and the capture's band-passed gray there (bilinear) times a gain per view must equal the
model's. The 9 parameters are fitted to every view at once by robust least squares
(scipy.optimize.least_squares, soft_l1 at LOSS), coarse to fine over SCALES_PX, from the start
the whole views' shifts give (whole_shift, turned: fit_shifts); the Jacobian is the capture's slope times
each point's image motion. Standard errors: the full covariance's, the sandwich of the
information J^T J / s^2 (s^2 the residuals' variance) and the scores of TILE_PX tiles of edge
samples (_solve), prior residuals (PRIOR_*) keeping it determined where the views tell nothing
(the conrod's shank along its length), plus the model's error: the two finest scales' estimates'
difference, in quadrature (model_error).

Not every edge moves with the part: a shadow's rim lies where the line from the lamp (fixed in the
cell) through its caster meets the receiving face. The edge samples a cast shadow draws (drawn:
the model's image without cast shadows has little of the edge there; cast_shadows finds each
rim's caster by a ray from the lamp) appear where the moved caster's shadow falls on the moved
face (shadow_points, _appear); the others where their point does.

One view cannot tell a part moved across the view by d from the camera turned by d / Z (Z the
feature's distance): both move the feature alike, and only the part's apparent tilt tells them
apart, weakly; with one view the hand-eye turn is held near 0 (PRIOR_ONE_VIEW_RAD). A second
view does (second_views): orbited about the feature and rolled about its own axis, a part's move
(fixed in the cell) turns with the view while the hand-eye turn turns with the camera; turned a
little off the feature, a hand-eye roll moves the feature while a part's turn about it does not.

The fit's standard errors say what its edges determine if they moved with the part; the light
stays in the cell, and a straight shank moved along itself looks the same. How far the views
leave the part's position open (resolution) is judged on the model's images rendered at the
estimate and moved either way of each parameter (rendered_information), each view over its
residual; the loop takes further views (by_resolution) where that exceeds the registration
limit, among them views with the lamp low along the open direction (lamps_along: the light's
edges that move with the part, shadows of what stands up there), starts the fit there from the
earlier estimate moved along it as the rendered images fit best (along_start), and names the
direction (along) where it stays open. A part long along that direction may still be tilted along
it unseen (the first views see that tilt by perspective alone, a lamp-low view's shadow rim ties
it to the offset along the direction): the loop then takes a view from its side (sideways),
keeps the better of the fits from the model's pose and along it (better), refined at the fine
scales (side_refit), and widens the fit's covariance by what the views tell over their residual
(rendered_covariance, PoseError.widened). Two views may tell the position and leave the tilt
open: where the fit's own tilt across the first view is told worse than the plan tolerates
(untold_tilt), the loop takes a view from the side that tilt moves the part's points along the
first view's axis, and refines the first views' estimate at the fine scales (side_refit)."""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cell.core import geometry
from cell.devices.interfaces import Arm
from cell.devices.rig import lamp_frame
from cell.physics import projection
from cell.planning.evaluate import black_level
from cell.run import registration

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.planning.plan import Plan
    from cell.planning.scene import Scene
    from cell.run.registration import Drives, LampPose
    from cell.task.types import Task

SCALES_PX = (6.0, 3.0, 1.5)  # the edge fit's scales, coarse to fine (Gaussian sigma)
TILE_PX = 48                # the standard errors' groups of edge samples that err together (_solve)
BAND_RATIO = 4.0            # band_pass: the blur left out, this many times the scale
EDGE_QUANTILE = 0.8         # the model's edge samples: its part pixels of the strongest gradient
MAX_SAMPLES = 4000          # per view and scale
MAX_NFEV = 30               # least_squares evaluations per scale
FLOOR = 0.03                # equalized: the gray, of the image's 99th percentile, below which it is flat
LOSS = 0.5                  # the robust loss's scale (soft_l1), of the images' unit spread
PRIOR_OFFSET_M = 0.02       # the priors' spreads: what the fit takes where the views tell nothing
PRIOR_TURN_RAD = np.radians(10.0)
PRIOR_HAND_EYE_RAD = np.radians(5.0)
PRIOR_ONE_VIEW_RAD = np.radians(0.2)   # one view: its shift is the part's (significant: a second view)
TILT_LIMIT = 2.0            # significant: a tilt beyond this many lamp tolerances
MAX_OFFSET_M = 0.015         # implausible: beyond these the fit matched the wrong edges
MAX_TURN_RAD = np.radians(7.0)
MAX_HAND_EYE_RAD = np.radians(3.0)
MIN_CONTRAST_GRAY = 10.0    # localize: a capture flatter than this [gray] shows nothing
MIN_SAMPLES = 200           # fewer edge samples in a view: it tells nothing
SHADOWED = 0.5              # cast_shadows: a part pixel below this of its gray without cast shadows is in one
CAST_GAP_M = 1e-4           # cast_shadows: the part meets the lamp's ray this far before the rim: it casts
CAST_EDGE = 0.5             # drawn: an edge whose gradient without cast shadows is below this of its own is cast
REACH = 3.0                 # drawn: a cast edge sample's shadow rim within this many scales (sigma)
GRAZING_RAD = np.radians(5.0)   # drawn: light more nearly along the rim's face than this: its rim is left rigid
ORBITS_DEG = (30.0, 50.0)   # second_views: the orbits about the feature,
ORBITS = 8                  # about this many axes across the view,
ROLL_DEG = 90.0             # the roll about the camera's axis
AIM_OFF_DEG = 1.5           # and the turn off the feature (about 150 px on the examples)
INFORMATION_UNITS = np.array([1e-3] * 3 + [np.radians(0.3)] * 6)   # view_information: the accuracy sought,
VIEW_SCALE = 4              # the candidates' model images this many times coarser than the sensor
VIEW_GRAY = 0.6             # the second view's exposure: its brightest part at this of saturation
SEARCH_TILTS_DEG = (-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0)   # coarse_starts: the part's tilts across the view,
SEARCH_ROLLS_DEG = (-6.0, -3.0, 0.0, 3.0, 6.0)              # its turns about the view axis
SEARCH_SHIFTS = (-1.0, 0.0, 1.0)                            # and its shifts, of registration.COARSE px
STEP_UNITS = 0.5            # rendered_information: its differences half an INFORMATION_UNITS either way
MAX_EXTRA_VIEWS = 2         # the loop's views beyond the second where the part's position stays open
SIDEWAYS = np.sin(np.radians(20.0))    # sideways: a view this far to the side of an open direction, at least
ALONG_COS = np.cos(np.radians(30.0))   # along: a direction within this of a part axis is named by it
COVERAGE = 2.0              # Resolution.unresolved: the registration limit holds with this many uncertainties
TILT_TOLD = 0.5             # untold_tilt: the tilt the plan tolerates, of the lamp tolerance (the mirror turns 2x)
FINE_SCALES_PX = SCALES_PX[1:]   # side_refit: the edge fit's scales without the coarsest
LAMP_TILTS_DEG = (15.0, 25.0)   # lamps_along: the lamp's elevations for a further view along a weak direction
HORIZONTAL = 0.5            # lamps_along: a weak direction less across the cell's xy plane than this has no pan
ALONG_STEP_M = 1e-3         # along_start: its steps along the weak direction
AIM_GRID_DEG = (-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0)   # lamp_turn: the lamp's turns about its x and y,
AIM_FINE_DEG = 0.25         # then about the best in these steps, two either way
SAME_LAMP_M = 1e-3          # lamp_turn: views whose lamp stands within this and aims within SAME_LAMP_RAD
SAME_LAMP_RAD = np.radians(0.2)    # of the first's share its pose (a servo tick is 0.09 deg)
PAN_MARGIN_RAD = np.radians(1.0)   # lamps_along: its pans this far inside the rig's range (a servo rig's pan at
                                   # exactly 180 deg is tick 4096, one beyond its position limit)


@dataclass(frozen=True)
class Shadows:
    """What the lamp's cast shadows draw in a view of the model (cast_shadows): the image without
    them (H, W), and for each pixel of a shadow's rim (in the shadow, beside a lit pixel of the
    part) the point of the part that casts it and the rim's face normal (H, W, 3; cell frame, NaN
    off the rims), each pixel's distance [px] to the nearest rim pixel and that pixel's flat
    index, and the lamp's position (cell frame)."""

    plain: np.ndarray
    casters: np.ndarray
    normals: np.ndarray
    distance: np.ndarray
    nearest: np.ndarray
    lamp_m: np.ndarray


@dataclass(frozen=True)
class ModelView:
    """The model's image of one view: gray per unit exposure (H, W), each pixel's cell-frame
    point (H, W, 3) (NaN where the ray misses the part), from the read-back camera pose; and,
    where asked, what the lamp's cast shadows draw in it (Shadows)."""

    value: np.ndarray
    points: np.ndarray
    T_cell_cam: np.ndarray
    shadows: Shadows | None = None


@dataclass(frozen=True)
class Drawn:
    """The edge samples a cast shadow draws (Samples.drawn): which of them (N,) and, for each of
    those (M,), the point of the part that casts the shadow's rim nearest it, that rim pixel's
    point and face normal (M, 3; cell frame, the model's part pose), and the lamp's position."""

    which: np.ndarray
    casters: np.ndarray
    rims: np.ndarray
    normals: np.ndarray
    lamp_m: np.ndarray


@dataclass(frozen=True)
class Samples:
    """One view's edge samples at a scale: model points X (N, 3, cell frame, the model's part pose),
    the model's band-passed gray there (N,), the capture band-passed alike (H, W), both scaled to
    unit spread, the read-back camera pose T_cell_cam, and those of the samples a cast shadow
    draws (Drawn; None: every sample an edge of the part)."""

    points: np.ndarray
    gray: np.ndarray
    image: np.ndarray
    T_cell_cam: np.ndarray
    drawn: Drawn | None = None


def grid_intrinsics(task: Task, scale: int = 1) -> np.ndarray:
    """K of the sensor's grid `scale` times coarser (registration.expected_image's grid)."""
    sensor = task.camera.sensor
    grid = replace(sensor, width_px=round(sensor.width_px / scale), height_px=round(sensor.height_px / scale),
                   pixel_pitch_m=sensor.pixel_pitch_m * scale)
    return projection.intrinsics(grid, task.camera.lens)


def model_view(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose,
               drives: Drives = None, scale: int = 1, drawn: bool = False) -> ModelView:
    """The model's image over the whole sensor (registration.expected_image, on a grid `scale`
    times coarser) and the point each pixel sees (kernels.render's depth along the pixel's ray);
    with `drawn`, what the lamp's cast shadows draw in it (cast_shadows)."""
    from kernels.render import render
    sensor = task.camera.sensor
    width, height = round(sensor.width_px / scale), round(sensor.height_px / scale)
    value = registration.expected_image(task, scene, T_cell_cam, lamp_pose, (0, 0, width, height), scale, drives)
    K = grid_intrinsics(task, scale)
    rays = projection.pixel_rays(K, T_cell_cam, width, height)
    origin = T_cell_cam[:3, 3]
    hit = render(scene.shadow_mesh, origin, rays, origin, rays[0], 1.0, np.pi, task.part.material.table(),
                 1.0, 1.0, shadows=False, part_faces=len(scene.faces))
    points = np.where(hit.hit[:, None], origin + hit.depth[:, None] * rays, np.nan).reshape(height, width, 3)
    shadows = None
    if drawn:
        plain = registration.expected_image(task, scene, T_cell_cam, lamp_pose, (0, 0, width, height), scale, drives,
                                            shadows=False)
        shadows = cast_shadows(task, scene, value, plain, points, hit.normal.reshape(height, width, 3), lamp_pose)
    return ModelView(value, points, np.array(T_cell_cam, float), shadows)


def cast_shadows(task: Task, scene: Scene, value: np.ndarray, plain: np.ndarray, points: np.ndarray,
                 normals: np.ndarray, lamp_pose: LampPose) -> Shadows:
    """The Shadows of a model's image (value) and the same without cast shadows (plain), its
    pixels' points and face normals (H, W, 3): a part pixel is in a shadow where its gray is less
    than SHADOWED of the plain image's, on its rim where a neighbour (8) of the part is not; the
    part's point casting it is where the ray from the lamp to the rim's point first meets the part
    (kernels.render from the lamp, the part's own mesh: a housing, fixed in the cell, casts none
    here), more than CAST_GAP_M before it."""
    from kernels.render import render
    part = np.isfinite(points[..., 0])
    shaded = part & (value < SHADOWED * plain)
    lit = (part & ~shaded).astype(np.uint8)
    rows, cols = np.nonzero(shaded & (cv2.dilate(lit, np.ones((3, 3), np.uint8)) > 0))
    casters = np.full(points.shape, np.nan)
    lamp = np.asarray(lamp_pose[0], float)
    if len(rows):
        rim = points[rows, cols]
        to_rim = rim - lamp
        length = np.linalg.norm(to_rim, axis=1)
        rays = to_rim / length[:, None]
        hit = render(scene.warp_mesh, lamp, rays, lamp, lamp_pose[1], 1.0, np.pi, task.part.material.table(),
                     1.0, 1.0, shadows=False)
        cast = hit.hit & (hit.depth < length - CAST_GAP_M)
        casters[rows[cast], cols[cast]] = lamp + hit.depth[cast, None] * rays[cast]
    on_rim = np.isfinite(casters[..., 0])
    if on_rim.any():
        distance, (near_rows, near_cols) = distance_transform_edt(~on_rim, return_indices=True)
        nearest = near_rows * on_rim.shape[1] + near_cols
    else:
        distance, nearest = np.full(on_rim.shape, np.inf), np.zeros(on_rim.shape, int)
    return Shadows(plain, casters, np.where(on_rim[..., None], normals, np.nan), distance, nearest, lamp)


def signal(task: Task, image: np.ndarray) -> np.ndarray:
    """A capture's signal, float32: its gray less the sensor's black level b (G = b + c P t; the
    task's camera.sensor.black_level, the loop's measured one), which the model's image (c P per
    unit exposure) does not hold. Left in, b adds to the shading's product and bends the
    logarithm's edges (equalized) where the part is dim: the conrod's tilt came out 1.0 deg off
    with the black level alone (0.3 without it)."""
    return (np.asarray(image, float) - black_level(task)).astype(np.float32)


def equalized(image: np.ndarray) -> np.ndarray:
    """log(image / its 99th percentile + FLOOR), float32, of a signal (the model's image, or a
    capture less its black level: signal): the lamp's falloff and the material's shading
    multiply the gray, so in its logarithm they add a slowly varying term, and an edge of the
    part counts as much in the spot's dim fringe as in its centre (down to FLOOR, where the
    noise begins)."""
    image = np.asarray(image, np.float32)
    top = float(np.percentile(image, 99.0))
    return np.log(np.maximum(image, 0.0) / max(top, 1e-12) + FLOOR).astype(np.float32)


def band_pass(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """The equalized image's edges at scale sigma: its Gaussian blur of sigma less that of
    BAND_RATIO sigma (the lamp's soft edge and the lobe's shading, tens of pixels wide and fixed
    in the cell while the part moves, are left out), float32."""
    image = equalized(image)
    return cv2.GaussianBlur(image, (0, 0), sigma_px) - cv2.GaussianBlur(image, (0, 0), BAND_RATIO * sigma_px)


def whole_shift(model: np.ndarray, capture: np.ndarray, about: tuple[float, float]) -> tuple[float, float]:
    """The shift (dx, dy) [px] of the image point `about` (the feature centre's pixel) from the
    model's image to the capture, to within registration.COARSE px: their equalized edges
    (registration.gradient of registration.high_pass) at 1/COARSE resolution, the model's turned
    about that point by each of registration.COARSE_TURNS_DEG, its part's bounding box matched over
    the capture by normalized correlation, the best turn's peak if it beats the unturned one's by
more than noise could (registration.turned_if_significant), else the unturned one's (turned
hinges' windows scored alike, and a turned start put one 1 mm low). The turns: a long straight edge
    turned a few degrees (the conrod's shank, yawed 5 deg, across the whole view) matches no
    unturned template but at its one end (the shank's edge 480 px off, against -123 px found
    with the turn)."""
    step = registration.COARSE
    size = (round(model.shape[1] / step), round(model.shape[0] / step))
    small_m = cv2.resize(equalized(model), size, interpolation=cv2.INTER_AREA)
    small_c = cv2.resize(equalized(capture), size, interpolation=cv2.INTER_AREA)
    edges_m = registration.gradient(registration.high_pass(small_m))
    edges_c = registration.gradient(registration.high_pass(small_c))
    centre = (about[0] / step, about[1] / step)
    peaks: dict[float, tuple[float, Any]] = {}        # per turn: its peak and the shift there
    for turn in registration.COARSE_TURNS_DEG:
        turned = cv2.warpAffine(edges_m, cv2.getRotationMatrix2D(centre, turn, 1.0), size)
        rows, cols = np.nonzero(turned > 0.05 * turned.max()) if turned.any() else ((), ())
        if len(rows) == 0:
            continue
        v0, v1, u0, u1 = min(rows), max(rows) + 1, min(cols), max(cols) + 1
        template = turned[v0:v1, u0:u1]
        ph, pw = template.shape
        padded = cv2.copyMakeBorder(edges_c, ph, ph, pw, pw, cv2.BORDER_CONSTANT, value=0)
        score = cv2.matchTemplate(padded, template, cv2.TM_CCORR_NORMED)
        _, peak, _, (u, v) = cv2.minMaxLoc(np.nan_to_num(score, nan=-1.0))
        peaks[turn] = (peak, (float(step * (u - pw - u0)), float(step * (v - ph - v0))))
    if not peaks:
        return 0.0, 0.0
    shift: tuple[float, float] = peaks[registration.turned_if_significant(peaks, edges_m.size)][1]
    return shift


def edge_samples(view: ModelView, capture: np.ndarray, sigma_px: float) -> Samples:
    """The view's Samples at scale sigma: the model's part pixels whose band-passed gray changes
    most (the EDGE_QUANTILE of its gradient), their points and band-passed gray, both images
    scaled to unit spread over the part; with the view's Shadows, those a shadow draws (drawn)."""
    seen = np.isfinite(view.points[..., 0])
    model = band_pass(view.value, sigma_px)
    grad = registration.gradient(model)
    candidates = seen & (grad > 0)
    if not candidates.any():
        return Samples(np.zeros((0, 3)), np.zeros(0), np.zeros((2, 2), np.float32), view.T_cell_cam)
    threshold = np.quantile(grad[candidates], EDGE_QUANTILE)
    rows, cols = np.nonzero(candidates & (grad >= threshold))
    pick = np.linspace(0, len(rows) - 1, min(len(rows), MAX_SAMPLES)).astype(int)
    rows, cols = rows[pick], cols[pick]
    points = view.points[rows, cols]
    gray = model[rows, cols]
    image = band_pass(capture, sigma_px)
    cast = None if view.shadows is None else drawn(view.shadows, view.points, grad, rows, cols, sigma_px)
    return Samples(points, gray / max(float(np.std(gray)), 1e-12), image / max(float(np.std(image[seen])), 1e-12),
                   view.T_cell_cam, cast)


def drawn(shadows: Shadows, points: np.ndarray, grad: np.ndarray, rows: np.ndarray, cols: np.ndarray,
          sigma_px: float) -> Drawn | None:
    """Of the edge samples at pixels (rows, cols) of a view (its Shadows, its pixels' points
    (H, W, 3), its band-passed gradient grad), those a cast shadow draws (None: none): the
    band-passed gradient of the image without cast shadows less than CAST_EDGE of grad there, a
    shadow's rim within REACH sigma, the lamp's light not grazing the rim's face (more than
    GRAZING_RAD to it); each with the rim pixel nearest it."""
    plain = registration.gradient(band_pass(shadows.plain, sigma_px))[rows, cols]
    which = (plain < CAST_EDGE * grad[rows, cols]) & (shadows.distance[rows, cols] <= REACH * sigma_px)
    near = shadows.nearest[rows, cols][which]
    casters, normals = shadows.casters.reshape(-1, 3)[near], shadows.normals.reshape(-1, 3)[near]
    steep = np.abs(np.einsum("nj,nj->n", geometry.unit(casters - shadows.lamp_m), normals)) > np.sin(GRAZING_RAD)
    which[which] = steep
    if not which.any():
        return None
    return Drawn(which, casters[steep], points.reshape(-1, 3)[near[steep]], normals[steep], shadows.lamp_m)


@dataclass(frozen=True)
class PoseError:
    """The fitted pose errors: E_part, the part's in the cell frame (turned by part_rpy about the
    feature centre, then moved by part_offset), and E_he, the camera's hand-eye turn (in the
    camera frame), each with its standard error; the views and edge points it rests on and the
    residuals' rms (of the images' unit spread)."""

    part_offset_m: np.ndarray
    part_rpy_rad: np.ndarray
    hand_eye_rpy_rad: np.ndarray
    part_offset_stderr_m: np.ndarray
    part_rpy_stderr_rad: np.ndarray
    hand_eye_rpy_stderr_rad: np.ndarray
    center: np.ndarray                  # the feature centre the part turns about (cell frame)
    views: int
    edge_points: int
    residual: float
    covariance: np.ndarray | None = None  # 9 x 9, of theta (the standard errors its diagonal's roots)

    @property
    def theta(self) -> np.ndarray:
        """The 9 pose parameters (part offset [m], part rpy [rad], hand-eye rpy [rad])."""
        return np.concatenate([self.part_offset_m, self.part_rpy_rad, self.hand_eye_rpy_rad])

    @property
    def T_part(self) -> np.ndarray:
        """E_part: the model's part pose to the true one, in the cell frame."""
        return part_error(self.part_offset_m, self.part_rpy_rad, self.center)

    @property
    def T_hand_eye(self) -> np.ndarray:
        """E_he: the read-back camera pose to the true one (T_true = T_read @ E_he)."""
        return geometry.from_rpy(self.hand_eye_rpy_rad)

    def about(self, center: np.ndarray) -> PoseError:
        """The same pose error stated about another centre c (cell frame): E_part unchanged, its
        turn too, its offset E_part c - c = offset + (R(rpy) - 1)(c - centre); the covariance
        through that offset's derivative in the turn, d/d rpy R(rpy)(c - centre) (central
        differences), the turns' and the hand-eye's as they were."""
        center = np.asarray(center, float)
        arm = center - self.center

        def offset(rpy: np.ndarray) -> np.ndarray:
            return self.part_offset_m + Rotation.from_euler("xyz", rpy).apply(arm) - arm

        A = np.eye(9)
        for j in range(3):
            step = np.zeros(3)
            step[j] = 1e-6
            A[:3, 3 + j] = (offset(self.part_rpy_rad + step) - offset(self.part_rpy_rad - step)) / 2e-6
        cov = self.covariance if self.covariance is not None else np.diag(np.square(self.theta_stderr))
        stated = A @ cov @ A.T
        return replace(self, part_offset_m=offset(self.part_rpy_rad), center=center, covariance=stated,
                       part_offset_stderr_m=np.sqrt(np.maximum(np.diag(stated)[:3], 0.0)))

    def widened(self, covariance: np.ndarray) -> PoseError:
        """The same estimate, another covariance (9 x 9, theta's units) added to its own (errors
        of two sources, in quadrature): its standard errors the sum's diagonal's roots."""
        own = self.covariance if self.covariance is not None else np.diag(np.square(self.theta_stderr))
        total = own + np.asarray(covariance, float)
        stderr = np.sqrt(np.maximum(np.diag(total), 0.0))
        return replace(self, part_offset_stderr_m=stderr[:3], part_rpy_stderr_rad=stderr[3:6],
                       hand_eye_rpy_stderr_rad=stderr[6:9], covariance=total)

    @property
    def theta_stderr(self) -> np.ndarray:
        """The 9 standard errors, in theta's order."""
        return np.concatenate([self.part_offset_stderr_m, self.part_rpy_stderr_rad, self.hand_eye_rpy_stderr_rad])

    def to_json(self) -> dict[str, Any]:
        """report.json's `localization` (docs/formats.md)."""
        return {"part_offset_m": self.part_offset_m.tolist(),
                "part_offset_m_stderr": self.part_offset_stderr_m.tolist(),
                "part_rpy_deg": np.degrees(self.part_rpy_rad).tolist(),
                "part_rpy_deg_stderr": np.degrees(self.part_rpy_stderr_rad).tolist(),
                "hand_eye_rpy_deg": np.degrees(self.hand_eye_rpy_rad).tolist(),
                "hand_eye_rpy_deg_stderr": np.degrees(self.hand_eye_rpy_stderr_rad).tolist(),
                "views": self.views, "edge_points": self.edge_points, "residual": self.residual}


def part_error(offset_m: np.ndarray, rpy_rad: np.ndarray, center: np.ndarray) -> np.ndarray:
    """E_part = move(offset) turn(rpy) about the centre, as sim.world.true_part_scene applies it."""
    about = geometry.transform(translation=center)
    return geometry.transform(translation=offset_m) @ about @ geometry.from_rpy(rpy_rad) @ np.linalg.inv(about)


def _params(theta: np.ndarray, center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E_part, E_he^-1) of the 9 pose parameters."""
    return part_error(theta[:3], theta[3:6], center), np.linalg.inv(geometry.from_rpy(theta[6:9]))


def _project(K: np.ndarray, theta: np.ndarray, center: np.ndarray, T_cell_cam: np.ndarray,
             points: np.ndarray) -> np.ndarray:
    """Where model points appear in a view taken from read-back pose T_cell_cam under the pose
    errors theta: pi(K, E_he^-1 C^-1 E_part X) (module docstring) [px]."""
    E_part, he_inv = _params(theta, center)
    uv, _ = projection.project(K, np.linalg.inv(he_inv @ np.linalg.inv(T_cell_cam) @ E_part), points)
    return uv


def shadow_points(E_part: np.ndarray, drawn: Drawn) -> np.ndarray:
    """Where the rims of the cast shadows that drawn samples show lie with the part moved by
    E_part, the lamp fixed in the cell (M, 3; cell frame): the ray from the lamp L through the
    moved caster E Q meets the moved rim's face (through E B, normal R n) at
    L + t (E Q - L), t = (R n . (E B - L)) / (R n . (E Q - L)); at E = 1, B itself (Q lies on the
    ray from L to B). The part's edges move as E does; a shadow's rim as its caster and its
    receiver move against the fixed lamp (under a lamp 15 deg low, the conrod tilted 3 deg about
    its width lengthens its big boss's shadow along the shank by a fifth)."""
    L = drawn.lamp_m
    to_caster = geometry.apply(E_part, drawn.casters) - L
    normal = geometry.rotate(E_part, drawn.normals)
    t = (np.einsum("nj,nj->n", normal, geometry.apply(E_part, drawn.rims) - L)
         / np.einsum("nj,nj->n", normal, to_caster))
    return L + t[:, None] * to_caster


def _appear(K: np.ndarray, theta: np.ndarray, center: np.ndarray, samples: Samples) -> np.ndarray:
    """Where a view's edge samples appear under the pose errors theta [px]: an edge of the part
    where its point does (_project), an edge a cast shadow draws moved as its rim moves
    (shadow_points), seen from the true camera C E_he."""
    uv = _project(K, theta, center, samples.T_cell_cam, samples.points)
    drawn = samples.drawn
    if drawn is None:
        return uv
    E_part, he_inv = _params(theta, center)
    moved = samples.points[drawn.which] + shadow_points(E_part, drawn) - drawn.rims
    uv[drawn.which] = projection.project(K, samples.T_cell_cam @ np.linalg.inv(he_inv), moved)[0]
    return uv


def _priors(theta: np.ndarray, views: int) -> np.ndarray:
    """The prior residuals that keep the fit determined where the views tell nothing: each
    parameter over its spread (PRIOR_*), the hand-eye turn's tighter with one view."""
    hand_eye = PRIOR_HAND_EYE_RAD if views > 1 else PRIOR_ONE_VIEW_RAD
    return np.concatenate([theta[:3] / PRIOR_OFFSET_M, theta[3:6] / PRIOR_TURN_RAD, theta[6:9] / hand_eye])


def _solve(residuals: Any, theta0: np.ndarray, n_data: int, loss: str, jacobian: Any = "2-point",
           groups: Any = None) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(parameters, covariance, residual rms, inliers) of least_squares from theta0. The
    covariance over the inlying data residuals and the priors: s^2 (J^T J)^-1 with s^2 the
    residuals' variance, or, given groups(x) -> (n_data,) labels of residuals that may err
    together (edge samples in one image tile: neighbours share the band-pass and the model's
    shading error there), the clustered sandwich H^-1 (sum_c g_c g_c^T G / (G - 1) + P) H^-1, with
    H = J_d^T J_d / s^2 + P the information, g_c = J_c^T r_c / s^2 each group's score and P the
    priors' information: where the residuals of a group are correlated, or a group's shading is
    off, its samples count as the few independent ones they are. A label NaN marks a residual
    that does not count (an edge sample with no image where x puts it: fit's), left out of s^2,
    the inliers and the rms as if it were not there."""
    scale = np.concatenate([[1e-3] * 3, [1e-2] * 6, [0.1] * (len(theta0) - 9)])
    solved = least_squares(residuals, theta0, jac=jacobian, loss=loss, f_scale=LOSS, x_scale=scale, max_nfev=MAX_NFEV)
    r = solved.fun[:n_data]
    labels = np.asarray(groups(solved.x), float) if groups is not None else np.zeros(n_data)
    inliers = (np.abs(r) < 3.0 * LOSS if loss != "linear" else np.ones(n_data, bool)) & np.isfinite(labels)
    s2 = max(float(np.sum(r[inliers] ** 2) / max(int(inliers.sum()) - len(theta0), 1)), 1e-12)
    J = solved.jac.copy()
    J[:n_data][~inliers] = 0.0
    data, prior = J[:n_data] / np.sqrt(s2), J[n_data:]       # data weighted by 1 / s, the priors by their spread
    information = np.linalg.pinv(data.T @ data + prior.T @ prior)
    cov = information
    if groups is not None:
        _, index = np.unique(labels[inliers], return_inverse=True)
        scores = np.zeros((index.max() + 1 if len(index) else 0, len(theta0)))
        np.add.at(scores, index, data[inliers] * (r[inliers, None] / np.sqrt(s2)))
        count = len(scores)
        meat = scores.T @ scores * count / max(count - 1, 1) + prior.T @ prior
        cov = information @ meat @ information
    rms = float(np.sqrt(np.mean(r[inliers] ** 2))) if inliers.any() else float("nan")
    return solved.x, cov, rms, int(inliers.sum())


def fit_shifts(K: np.ndarray, center: np.ndarray, poses: Sequence[np.ndarray],
               shifts: Sequence[tuple[float, float]]) -> np.ndarray:
    """The 9 pose parameters that move the feature centre by each view's whole shift (the start
    of the edge fit, from its coarse pixels)."""
    centre = np.asarray(center, float)[None]

    def residuals(theta: np.ndarray) -> np.ndarray:
        out = [(_project(K, theta, centre[0], T, centre) - _project(K, np.zeros(9), centre[0], T, centre)
                - np.asarray(s))[0] / registration.COARSE for T, s in zip(poses, shifts)]
        return np.concatenate(out + [_priors(theta, len(poses))])

    return _solve(residuals, np.zeros(9), 2 * len(poses), "linear")[0]


def sampled(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The image at points uv (N, 2) [px], bilinear, 0 outside (float64)."""
    uv = uv.astype(np.float32)
    return cv2.remap(image, uv[:, :1], uv[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0).ravel().astype(float)


def fit(levels: Sequence[Sequence[Samples]], K: np.ndarray, center: np.ndarray, theta0: np.ndarray) -> PoseError:
    """The PoseError that best explains every view's edges (module docstring): per scale (coarse
    to fine, levels[s][i] view i's Samples at scale s), robust least squares of the capture's
    band-passed gray where each model edge point appears (bilinear) against the model's, a gain
    per view, from theta0 (9 parameters: part offset [m], part rpy [rad], hand-eye rpy [rad]).
    The covariance: the finest scale's (_solve) plus, with two scales or more, model_error of the
    two finest scales' estimates."""
    theta = np.concatenate([theta0, np.ones(len(levels[0]))])
    scales: list[np.ndarray] = []          # the estimate before each scale's fit: the one of the scale before
    for views in levels:
        n_data = sum(len(v.points) for v in views)
        slopes = [(cv2.Sobel(v.image, cv2.CV_32F, 1, 0, scale=1 / 8), cv2.Sobel(v.image, cv2.CV_32F, 0, 1, scale=1 / 8))
                  for v in views]

        def residuals(x: np.ndarray, views: Sequence[Samples] = views) -> np.ndarray:
            out = []
            for i, view in enumerate(views):
                uv = _appear(K, x[:9], center, view)
                out.append(np.where(np.isfinite(uv).all(axis=1), x[9 + i] * sampled(view.image, uv) - view.gray, 0.0))
            return np.concatenate(out + [_priors(x[:9], len(views))])

        def jacobian(x: np.ndarray, views: Sequence[Samples] = views, slopes: Any = slopes) -> np.ndarray:
            """d residual / d parameters: the capture's slope at each point times the point's
            image motion per parameter (central differences of _appear, float64); 0 where the
            point or its motion has no image (a shadow's rim that the moved caster throws behind
            the camera: the conrod's boss turned 11 deg on a coarse start), as its residual is."""
            blocks = []
            for i, (view, (gx, gy)) in enumerate(zip(views, slopes)):
                uv = _appear(K, x[:9], center, view)
                block = np.zeros((len(uv), len(x)))
                slope = np.column_stack([sampled(gx, uv), sampled(gy, uv)])
                for j, h in enumerate([1e-6] * 3 + [1e-5] * 6):
                    step = np.zeros(9)
                    step[j] = h
                    motion = (_appear(K, x[:9] + step, center, view)
                              - _appear(K, x[:9] - step, center, view)) / (2 * h)
                    block[:, j] = x[9 + i] * np.sum(slope * motion, axis=1)
                block[:, 9 + i] = sampled(view.image, uv)
                block[~np.isfinite(block).all(axis=1) | ~np.isfinite(uv).all(axis=1)] = 0.0
                blocks.append(block)
            prior = np.zeros((9, len(x)))
            prior[:9, :9] = np.diag(_priors(np.ones(9), len(views)))
            return np.vstack(blocks + [prior])

        def groups(x: np.ndarray, views: Sequence[Samples] = views) -> np.ndarray:
            """Each sample's tile: its view and its pixel's TILE_PX square where x puts it; NaN
            where it has no image there (it does not count: _solve)."""
            tiles = [np.floor(_appear(K, x[:9], center, view) / TILE_PX) for view in views]
            return np.concatenate([i * 1_000_000 + t[:, 1] * 1000 + t[:, 0] for i, t in enumerate(tiles)])

        scales.append(theta[:9].copy())
        theta, cov, rms, inliers = _solve(residuals, theta, n_data, "soft_l1", jacobian, groups)
    cov = cov[:9, :9] + model_error(scales[-1], theta[:9]) if len(levels) > 1 else cov[:9, :9]
    stderr = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return PoseError(theta[:3], theta[3:6], theta[6:9], stderr[:3], stderr[3:6], stderr[6:9],
                     np.asarray(center, float), len(levels[0]), inliers, rms, cov)


def model_error(coarser: np.ndarray, finest: np.ndarray) -> np.ndarray:
    """The covariance (9 x 9) of what the model's image lacks, from the fit at the two finest
    scales (SCALES_PX[-2:]): d d^T, d their estimates' difference. Where the capture differs from
    the model's image by more than its noise (the world's lamp softer-edged than the model's, a
    lens's vignetting the model has no calibration of, the highlight's rims), the difference
    does not average out over the edge samples, and it weighs differently at the two scales: the
    sandwich over tiles (_solve) covers the noise, this the model's error, added in quadrature
    (each standard error sqrt(s^2 + d^2); the conrod's 3 px and 1.5 px fits were 0.4-0.6 deg
    apart in its tilt about y, 5-10 of the tiles' standard errors, the estimate 0.1-0.15 deg off)."""
    d = np.asarray(finest, float) - np.asarray(coarser, float)
    return np.outer(d, d)


def cost(levels: Sequence[Samples], K: np.ndarray, center: np.ndarray, theta: np.ndarray) -> float:
    """The edge fit's robust cost (soft_l1 at LOSS, fit's) of the 9 pose parameters theta over
    every view's Samples, each view's gain at its least-squares value (<s, m> / <s, s> of the
    capture's samples s and the model's m, not below 0)."""
    total = 0.0
    for view in levels:
        seen = sampled(view.image, _appear(K, theta, center, view))
        gain = max(float(seen @ view.gray) / max(float(seen @ seen), 1e-12), 0.0)
        z = ((gain * seen - view.gray) / LOSS) ** 2
        total += float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))
    return total


def coarse_starts(levels: Sequence[Samples], K: np.ndarray, center: np.ndarray, theta0: np.ndarray) -> list[np.ndarray]:
    """The fit's starts: theta0 (the whole shifts') with the part turned and shifted as the
    coarsest scale's edges fit best (cost) over a grid, one start per side the part tilts to, so
    that a tilt of the other sign, which moves the edges almost alike (made up for by a turn about
    the view axis and a move along it: the hinge 3 deg about y, seen from 50 deg), is a start of
    its own and not only a minimum the fit passes by. The grid: tilts about the first view's x
    and y axes (SEARCH_TILTS_DEG) and turns about its axis (SEARCH_ROLLS_DEG) about the feature
    centre; the best turn of each side (tilted either way about either axis) then shifted across
    the view (SEARCH_SHIFTS x registration.COARSE px at the feature's distance) as fits best;
    the starts distinct, best first."""
    T = levels[0].T_cell_cam
    axes = T[:3, :3].T                                  # the view's x, y, z in the cell frame (rows)
    pixel_m = registration.COARSE * float(np.linalg.norm(center - T[:3, 3])) / K[0, 0]
    start = Rotation.from_euler("xyz", theta0[3:6])
    best: dict[tuple[int, float], tuple[float, np.ndarray]] = {}
    for tilt in ((a, b) for a in SEARCH_TILTS_DEG for b in SEARCH_TILTS_DEG):
        for c in SEARCH_ROLLS_DEG:
            turn = Rotation.from_rotvec(np.radians(tilt[0]) * axes[0] + np.radians(tilt[1]) * axes[1]
                                        + np.radians(c) * axes[2])
            theta = np.concatenate([theta0[:3], (turn * start).as_euler("xyz"), theta0[6:9]])
            value = cost(levels, K, center, theta)
            for side in ((axis, np.sign(tilt[axis])) for axis in (0, 1) if tilt[axis]):
                if side not in best or value < best[side][0]:
                    best[side] = (value, theta)
    starts: list[tuple[float, np.ndarray]] = []
    for _, theta in best.values():
        moved = [theta[:3] + pixel_m * (du * axes[0] + dv * axes[1]) for du in SEARCH_SHIFTS for dv in SEARCH_SHIFTS]
        shifted = [np.concatenate([m, theta[3:]]) for m in moved]
        value, theta = min(((cost(levels, K, center, t), t) for t in shifted), key=lambda t: t[0])
        if not any(np.array_equal(theta, other) for _, other in starts):
            starts.append((value, theta))
    return [theta for _, theta in sorted(starts, key=lambda t: t[0])]


@dataclass(frozen=True)
class View:
    """A capture localization reads: the image, the read-back camera pose (with the hand-eye the
    loop believes), the lamp's read-back pose and the light channels' drives."""

    image: np.ndarray
    T_cell_cam: np.ndarray
    lamp_pose: LampPose
    drives: Drives = None


def localize(task: Task, scene: Scene, views: Sequence[View],
             along: tuple[PoseError, np.ndarray] | None = None) -> PoseError | None:
    """The PoseError of the part and the camera that explains the views' captures against the
    model's images (model_view): each view's whole shift (whole_shift, fit_shifts) turned and
    shifted as a grid's best starts (coarse_starts), and given an earlier estimate and the
    direction its views left open (`along`: Resolution.direction), that estimate moved along it as
    fits best (along_start), each fitted at the coarsest scale, the one
    of least cost starts the edge fit coarse to fine (fit over SCALES_PX); then once more against
    the model's images where the first fit puts the part and the cameras (refine), so that the
    light the part moved into is the model's too. None when a capture is flat (its brightest
    part less than MIN_CONTRAST_GRAY above its median: nothing lit to see) or no view shows edges
    enough to fit (fewer than MIN_SAMPLES)."""
    if any(np.percentile(v.image, 99.5) - np.median(v.image) < MIN_CONTRAST_GRAY for v in views):
        return None
    if along is not None:
        start = along_start(task, scene, views, *along)
        there = localize(task, moved_scene(scene, start.T_part),
                         [replace(v, T_cell_cam=v.T_cell_cam @ start.T_hand_eye) for v in views])
        return None if there is None else composed(start, there)
    models = [model_view(task, scene, v.T_cell_cam, v.lamp_pose, v.drives, drawn=True) for v in views]
    images = [signal(task, v.image) for v in views]
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    shifts = [whole_shift(m.value, image, tuple(projection.project(K, m.T_cell_cam, scene.center[None])[0][0]))
              for m, image in zip(models, images)]
    theta0 = fit_shifts(K, scene.center, [m.T_cell_cam for m in models], shifts)
    levels = [[edge_samples(m, image, s) for m, image in zip(models, images)] for s in SCALES_PX]
    if min(len(s.points) for s in levels[-1]) < MIN_SAMPLES:
        return None
    coarse = [fit(levels[:1], K, scene.center, start) for start in coarse_starts(levels[0], K, scene.center, theta0)]
    best = min(coarse, key=lambda e: cost(levels[0], K, scene.center, e.theta))
    return refine(task, scene, views, fit(levels, K, scene.center, best.theta))


def along_start(task: Task, scene: Scene, views: Sequence[View], error: PoseError,
                direction: np.ndarray) -> PoseError:
    """An earlier estimate moved along a direction its views left open (cell frame, unit) to where
    the model's images rendered with the part there fit the captures best: the sum over the views
    of the squared rendered_residual (the model's image on the grid VIEW_SCALE times coarser, the
    part and the cameras where the estimate moved by s puts them), over s in steps of
    ALONG_STEP_M up to MAX_OFFSET_M either way, then in quarter steps about the best. Rendered,
    not the edges' cost: what the light draws stays in the cell when the part moves (the end of
    the spot on the conrod's shank), and the edge fit, which moves every edge with the part, is
    held by those near where it starts (the conrod 10 mm off along its shank was fitted 9.3 mm
    short from four views; its edges' cost fell toward the model's pose in the views that tell
    nothing along it)."""
    direction = np.asarray(direction, float)
    images = [signal(task, v.image) for v in views]

    def residual(step: float) -> float:
        moved = replace(error, part_offset_m=error.part_offset_m + step * direction)
        scene_there = moved_scene(scene, moved.T_part)
        total = 0.0
        for v, image in zip(views, images):
            model = model_view(task, scene_there, v.T_cell_cam @ moved.T_hand_eye, v.lamp_pose, v.drives,
                               VIEW_SCALE)
            part = np.isfinite(model.points[..., 0])
            if part.any():
                rendered = band_pass(model.value, SCALES_PX[0] / VIEW_SCALE)
                total += rendered_residual(image, rendered, part) ** 2
        return total

    steps = np.arange(-MAX_OFFSET_M, MAX_OFFSET_M + 0.5 * ALONG_STEP_M, ALONG_STEP_M)
    best = min(steps, key=residual)
    best = min(best + 0.25 * ALONG_STEP_M * np.arange(-3, 4), key=residual)
    return replace(error, part_offset_m=error.part_offset_m + best * direction)


def lamps_along(task: Task, direction: np.ndarray, radius_m: float) -> list[tuple[float, float, float]]:
    """The lamp's joints (pan, tilt, radius) [rad, rad, m] for further views that tell the part's
    position along a weak direction (cell frame): panned to either side along it (PAN_MARGIN_RAD
    inside the rig's pan range), at each of LAMP_TILTS_DEG the rig's tilt range allows, at the (manual) radius the lamp stands at. The rig
    turns the lamp about its pivot, so the spot stays there; low, the spot stretches along the
    direction by 1 / sin(tilt), and what stands up there (the conrod's bosses, 6 and 8 mm above
    its shank) casts shadows across the part whose edges move with it. The planned lamp, high
    above, lights the conrod's shank only (its spot ends 15 mm short of either boss), which looks
    the same moved along itself; lit from 15 deg along it, the big boss's shadow ends 16 mm from
    the feature. None where the direction is nearly vertical (less than HORIZONTAL across the
    cell's xy plane: no pan follows it)."""
    flat = np.asarray(direction, float)[:2]
    if np.linalg.norm(flat) < HORIZONTAL:
        return []
    rig, toward = task.lamp.rig, float(np.arctan2(flat[1], flat[0]))
    joints = []
    for side in (0.0, np.pi):
        pans = [p for p in (toward + side + turn for turn in (-2.0 * np.pi, 0.0, 2.0 * np.pi))
                if rig.pan_range_rad[0] <= p <= rig.pan_range_rad[1]]
        if not pans:
            continue
        pan = float(np.clip(pans[0], rig.pan_range_rad[0] + PAN_MARGIN_RAD, rig.pan_range_rad[1] - PAN_MARGIN_RAD))
        joints += [(pan, float(tilt), float(radius_m)) for tilt in np.radians(LAMP_TILTS_DEG)
                   if rig.tilt_range_rad[0] <= tilt <= rig.tilt_range_rad[1]]
    return joints


@dataclass(frozen=True)
class LampTurn:
    """The lamp's aim error lamp_turn found: the lamp pose (position, read-back aim; cell frame)
    of the views it was found in, the true axis (unit, cell frame), and the edge fit's cost per
    edge sample (cost) at the estimate under that axis and under the read-back aim."""

    lamp_pose: LampPose
    axis: np.ndarray
    cost: float
    unturned_cost: float

    @property
    def angle_rad(self) -> float:
        """The angle between the true axis and the read-back aim [rad]."""
        return float(np.arccos(np.clip(geometry.unit(self.lamp_pose[1]) @ self.axis, -1.0, 1.0)))

    def applied(self, view: View) -> View:
        """The view with its lamp's aim the true axis where its lamp pose is the one the turn was
        found at (same_lamp: a mount's error, the same there at every camera pose); another lamp
        pose (the rig turned, a lamp-low view) as it was."""
        if not same_lamp(view.lamp_pose, self.lamp_pose):
            return view
        return replace(view, lamp_pose=(view.lamp_pose[0], self.axis))

    def to_json(self) -> dict[str, Any]:
        """report.json's `localization` keys of the lamp's aim (docs/formats.md)."""
        return {"lamp_aim_deg": float(np.degrees(self.angle_rad)), "lamp_axis": self.axis.tolist()}


def same_lamp(a: LampPose, b: LampPose) -> bool:
    """Whether two read-back lamp poses are one: positions within SAME_LAMP_M, aims within
    SAME_LAMP_RAD."""
    aims = float(np.clip(geometry.unit(a[1]) @ geometry.unit(b[1]), -1.0, 1.0))
    return bool(np.linalg.norm(np.asarray(a[0]) - np.asarray(b[0])) <= SAME_LAMP_M and np.arccos(aims) <= SAME_LAMP_RAD)


def lamp_turn(task: Task, scene: Scene, views: Sequence[View], error: PoseError) -> LampTurn:
    """The lamp's aim error: the turn of its axis that, at the estimate (the part moved by
    `error`, each camera turned by its hand-eye), lets the model's images explain the captures'
    edges best, searched jointly over the views that share the first view's lamp pose (same_lamp:
    a lamp mounted off its aim errs alike at every camera pose while the rig stands still). The
    turns: about the lamp's horizontal x and its y (rig.lamp_frame, both across the aim) over
    AIM_GRID_DEG, then AIM_FINE_DEG steps about the best, two either way; each scored by the
    edge fit's cost per edge sample at the coarsest scale (edge_samples of the model rendered
    under the turned lamp, cost at theta = 0). Why: the lamp's profile fades the light along the
    part, and the edge fit weighs each edge by the model's rendered contrast there; a spot lit off
    its aim moves that fade, which the fit, moving every edge with the part, reads as the part
    moved (the conrod's shank, lit by the spot alone: the lamp 2 deg off read as 12.7 mm along
    it). Rendered at the estimate, the part's light is the cell's, so the fade tells the lamp's
    turn (the conrod: 2 deg found within 0.25 deg), which the part, moved along a shank that looks
    alike, does not."""
    shared = [v for v in views if same_lamp(v.lamp_pose, views[0].lamp_pose)]
    position, aim = np.asarray(views[0].lamp_pose[0], float), geometry.unit(views[0].lamp_pose[1])
    frame = lamp_frame(task.lamp.rig.pivot_m, position)
    x, y = frame[:, 0], frame[:, 1]
    moved = moved_scene(scene, error.T_part)
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    sensor = task.camera.sensor
    models = [model_view(task, moved, v.T_cell_cam @ error.T_hand_eye, v.lamp_pose, v.drives) for v in shared]
    images = [signal(task, v.image) for v in shared]

    def axis(turn: tuple[float, float]) -> np.ndarray:
        return Rotation.from_rotvec(np.radians(turn[0]) * x + np.radians(turn[1]) * y).apply(aim)

    def score(turn: tuple[float, float]) -> float:
        lamp = (position, axis(turn))
        levels = [edge_samples(replace(m, value=registration.expected_image(
            task, moved, m.T_cell_cam, lamp, (0, 0, sensor.width_px, sensor.height_px), 1, v.drives)), image,
            SCALES_PX[0]) for m, v, image in zip(models, shared, images)]
        return cost(levels, K, moved.center, np.zeros(9)) / max(sum(len(s.points) for s in levels), 1)

    scores = {(a, b): score((a, b)) for a in AIM_GRID_DEG for b in AIM_GRID_DEG}
    best = min(scores, key=lambda t: scores[t])
    steps = AIM_FINE_DEG * np.arange(-2, 3)
    for turn in ((best[0] + da, best[1] + db) for da in steps for db in steps):
        if turn not in scores:
            scores[turn] = score(turn)
    best = min(scores, key=lambda t: scores[t])
    return LampTurn((position, aim), axis(best), scores[best], scores[(0.0, 0.0)])


def refine(task: Task, scene: Scene, views: Sequence[View], first: PoseError,
           scales: Sequence[float] = SCALES_PX) -> PoseError:
    """The first fit's PoseError corrected by a fit coarse to fine (scales: SCALES_PX) against the model's
    images with the part moved by it (moved_scene) and each camera turned by its hand-eye turn: the
    part's moves and turns compose (offsets add about the moved centre, turns multiply), the
    hand-eye turns too; the standard errors and residual are the second fit's. Coarse to fine, not
    at the finest scale alone: the edges' 1.5 px band leaves a local minimum wherever a turn moves
    them more than that (the conrod 0.8 deg off about y sat in one, between two barriers along the
    line to the truth; the highlight's rims shift with the turn), the coarse scales' wider basins
    reach the truth's."""
    moved = moved_scene(scene, first.T_part)
    E_he = first.T_hand_eye
    K = projection.intrinsics(task.camera.sensor, task.camera.lens)
    models = [model_view(task, moved, v.T_cell_cam @ E_he, v.lamp_pose, v.drives, drawn=True) for v in views]
    levels = [[edge_samples(m, signal(task, v.image), s) for m, v in zip(models, views)] for s in scales]
    if min(len(s.points) for s in levels[-1]) < MIN_SAMPLES:
        return first
    return composed(first, fit(levels, K, moved.center, np.zeros(9)))


def composed(first: PoseError, second: PoseError) -> PoseError:
    """A PoseError found against the model moved by `first` (second: about the moved centre,
    the cameras turned by first's hand-eye) composed with it: the part's moves and turns compose
    (offsets add about the moved centre, turns multiply), the hand-eye turns too; the standard
    errors, views and residual are second's."""
    turn = Rotation.from_euler("xyz", second.part_rpy_rad) * Rotation.from_euler("xyz", first.part_rpy_rad)
    hand_eye = Rotation.from_euler("xyz", first.hand_eye_rpy_rad) * Rotation.from_euler("xyz", second.hand_eye_rpy_rad)
    return replace(second, part_offset_m=first.part_offset_m + second.part_offset_m,
                   part_rpy_rad=turn.as_euler("xyz"), hand_eye_rpy_rad=hand_eye.as_euler("xyz"),
                   center=first.center)


def tilt_rad(error: PoseError, T_cell_cam: np.ndarray) -> float:
    """The part's turn across the view from T_cell_cam [rad]: its turn less the part about the
    view axis (which changes neither the light nor where the feature appears)."""
    view_axis = T_cell_cam[:3, 2]
    turn = Rotation.from_euler("xyz", error.part_rpy_rad).as_rotvec()
    return float(np.linalg.norm(turn - (turn @ view_axis) * view_axis))


def implausible(error: PoseError, T_cell_cam: np.ndarray) -> str | None:
    """Why a fit cannot be the cell's pose error, or None: its part offset beyond MAX_OFFSET_M,
    its tilt across the view from T_cell_cam beyond MAX_TURN_RAD or the hand-eye's turn across
    the view beyond MAX_HAND_EYE_RAD (a fixture and a calibration are never that far off: the fit
    matched the wrong edges). The turns about the view axis are not judged: the part's and the
    hand-eye's trade against each other where the view has few edges (the conrod's shank)."""
    offset = float(np.linalg.norm(error.part_offset_m))
    tilt = tilt_rad(error, T_cell_cam)
    hand_eye = float(np.linalg.norm(Rotation.from_euler("xyz", error.hand_eye_rpy_rad).as_rotvec()[:2]))
    if offset > MAX_OFFSET_M or tilt > MAX_TURN_RAD or hand_eye > MAX_HAND_EYE_RAD:
        return (f"the fit puts the part {1e3 * offset:.1f} mm off and tilted {np.degrees(tilt):.1f} deg and the "
                f"camera turned {np.degrees(hand_eye):.1f} deg, beyond any fixture ({1e3 * MAX_OFFSET_M:g} mm, "
                f"{np.degrees(MAX_TURN_RAD):g} deg) or hand-eye calibration ({np.degrees(MAX_HAND_EYE_RAD):g} deg): "
                f"the part could not be localized in these views")
    return None


def displacement_m(error: PoseError, T_cell_cam: np.ndarray) -> float:
    """How far the feature centre appears from where the model puts it in a view from T_cell_cam,
    across the view [m at the feature]: what one view sees of a part offset and a hand-eye turn
    alike."""
    T_true = T_cell_cam @ error.T_hand_eye
    moved = geometry.apply(np.linalg.inv(T_true), geometry.apply(error.T_part, error.center))
    model = geometry.apply(np.linalg.inv(T_cell_cam), error.center)
    return float(np.linalg.norm(moved[:2] / moved[2] - model[:2] / model[2]) * model[2])


def significant(error: PoseError, T_cell_cam: np.ndarray, limit_m: float, lamp_tolerance_rad: float) -> bool:
    """Whether the pose error is more than the plan tolerates, so that the model must follow it:
    the feature displaced by more than the registration limit (cell.run.loop.registration_limit:
    a fixture error d turns the lamp's direction to the feature by d / r; within it the loop
    measures where registration finds the feature), or the part tilted by more than TILT_LIMIT
    lamp tolerances (a tilt of the surface by a turns its mirror direction by 2 a; below it the
    loop's exposure, refit and re-plan have held the band, and one view's tilt is uncertain by
    half a degree: 0.6 deg on the conrod from a 1 mm hand-eye offset). A turn about the view axis
    changes neither."""
    return displacement_m(error, T_cell_cam) > limit_m or tilt_rad(error, T_cell_cam) > TILT_LIMIT * lamp_tolerance_rad


def second_views(T_cell_cam: np.ndarray, center: np.ndarray) -> list[np.ndarray]:
    """Candidate camera poses for a second view: the camera orbited by each of ORBITS_DEG about
    the feature centre (about each of ORBITS axes across the view), rolled +-ROLL_DEG about its
    own axis (a part's move across the view turns with the view, a hand-eye turn with the camera)
    and turned AIM_OFF_DEG off the feature (a hand-eye roll moves an off-centre feature, a part's
    turn about it does not). The loop takes the most informative it can reach (by_information)."""
    about = geometry.transform(translation=center)
    poses = []
    for orbit_deg in ORBITS_DEG:
        for roll in (ROLL_DEG, -ROLL_DEG):
            for k in range(ORBITS):
                angle = 2.0 * np.pi * k / ORBITS
                axis = T_cell_cam[:3, :3] @ np.array([np.cos(angle), np.sin(angle), 0.0])
                orbit = geometry.transform(Rotation.from_rotvec(np.radians(orbit_deg) * axis).as_matrix())
                poses.append(about @ orbit @ np.linalg.inv(about) @ T_cell_cam
                             @ geometry.from_rpy(np.radians([AIM_OFF_DEG, 0.0, roll])))
    return poses


def motion(K: np.ndarray, center: np.ndarray, T_cell_cam: np.ndarray, points: np.ndarray) -> np.ndarray:
    """d uv / d theta (N, 2, 9) of model points seen from T_cell_cam at theta = 0, per unit of
    INFORMATION_UNITS (1 mm, 0.3 deg) [px] (central differences of _project)."""
    out = np.zeros((len(points), 2, 9))
    for j in range(9):
        step = np.zeros(9)
        step[j] = 1e-2 * INFORMATION_UNITS[j]
        out[:, :, j] = (_project(K, step, center, T_cell_cam, points)
                        - _project(K, -step, center, T_cell_cam, points)) / 2e-2
    return out


def view_information(task: Task, scene: Scene, T_cell_cam: np.ndarray, lamp_pose: LampPose,
                     drives: Drives = None) -> np.ndarray:
    """The 9 x 9 information (J^T J, parameters in INFORMATION_UNITS) a view from T_cell_cam gives
    the edge fit at its coarsest scale: the model's image there (model_view on a grid VIEW_SCALE
    times coarser), band-passed at SCALES_PX[0] and scaled to unit spread as fit's samples are,
    J = the image's slope at each edge sample (EDGE_QUANTILE) times the sample's image motion
    (motion): what the view's edges, as lit and seen from there, tell of each parameter."""
    view = model_view(task, scene, T_cell_cam, lamp_pose, drives, VIEW_SCALE)
    seen = np.isfinite(view.points[..., 0])
    model = band_pass(view.value, SCALES_PX[0] / VIEW_SCALE)
    if not seen.any():
        return np.zeros((9, 9))
    model = model / max(float(np.std(model[seen])), 1e-12)
    gx = cv2.Sobel(model, cv2.CV_32F, 1, 0, scale=1 / 8)
    gy = cv2.Sobel(model, cv2.CV_32F, 0, 1, scale=1 / 8)
    grad = cv2.magnitude(gx, gy)
    candidates = seen & (grad > 0)
    if not candidates.any():
        return np.zeros((9, 9))
    rows, cols = np.nonzero(candidates & (grad >= np.quantile(grad[candidates], EDGE_QUANTILE)))
    slope = np.column_stack([gx[rows, cols], gy[rows, cols]]).astype(float)
    J = np.einsum("nu,nuj->nj", slope, motion(grid_intrinsics(task, VIEW_SCALE), scene.center, T_cell_cam,
                                                view.points[rows, cols]))
    return J.T @ J


def view_order(first: np.ndarray, candidates: Sequence[np.ndarray]) -> list[int]:
    """The indices of the candidate second views' information (view_information), best first:
    the one that, added to the first view's, is best conditioned, the largest least eigenvalue
    (the combination of the 9 parameters the two views tell worst, told best); ties in order."""
    least = np.array([np.linalg.eigvalsh(first + other)[0] for other in candidates])
    return [int(i) for i in np.argsort(-least, kind="stable")]


def best_view(first: np.ndarray, candidates: Sequence[np.ndarray]) -> int | None:
    """The index of the best candidate second view (view_order's first); None without candidates."""
    order = view_order(first, candidates)
    return order[0] if order else None


def by_information(task: Task, scene: Scene, first: View, candidates: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The candidate second views (camera poses) in view_order of their view_information, the
    lamp where the first view had it: the most informative first, each view's information
    computed once."""
    one = view_information(task, scene, first.T_cell_cam, first.lamp_pose, first.drives)
    infos = [view_information(task, scene, T, first.lamp_pose, first.drives) for T in candidates]
    return [candidates[i] for i in view_order(one, infos)]


def view_exposure(model: ModelView, saturation: float, f_number: float,
                  shutter_range_s: tuple[float, float]) -> float:
    """The shutter [s] that puts the model's brightest part (its 99th percentile) at VIEW_GRAY of
    saturation at this f-number (G = value t / kappa^2), within the camera's range."""
    seen = np.isfinite(model.points[..., 0])
    top = float(np.percentile(model.value[seen], 99.0)) if seen.any() else 0.0
    if top <= 0:
        return shutter_range_s[1]
    return float(np.clip(VIEW_GRAY * saturation * f_number**2 / top, *shutter_range_s))


class HandEyeCorrected(Arm):
    """An arm whose hand-eye the loop has corrected by E_he (PoseError.T_hand_eye): a camera pose
    T is commanded as T E_he^-1 and read back as T_read E_he, so the camera stands where the loop
    asks; the device itself, and what the simulated camera renders from, keep the task's hand-eye."""

    def __init__(self, arm: Arm, T_hand_eye: np.ndarray) -> None:
        super().__init__(arm.config, arm.frames.with_transform("T_flange_cam", arm.frames.T_flange_cam @ T_hand_eye))
        self.arm, self.T_hand_eye = arm, np.asarray(T_hand_eye, float)
        self.device = arm.device

    def _move_tcp(self, T_base_cam: np.ndarray, speed_m_s: float) -> None:
        self.arm._move_tcp(T_base_cam @ np.linalg.inv(self.T_hand_eye), speed_m_s)

    def _move_joints(self, q: np.ndarray, speed_rad_s: float, acceleration_rad_s2: float) -> None:
        self.arm._move_joints(q, speed_rad_s, acceleration_rad_s2)

    @property
    def move_timeout_s(self) -> float | None:
        return self.arm.move_timeout_s

    def _unreachable(self, T_base_cam: np.ndarray) -> str | None:
        return self.arm._unreachable(T_base_cam @ np.linalg.inv(self.T_hand_eye))

    def _joint_angles(self) -> np.ndarray | None:
        return self.arm._joint_angles()

    def _tcp_pose(self) -> np.ndarray:
        return self.arm._tcp_pose() @ self.T_hand_eye

    def stop(self) -> None:
        self.arm.stop()

    def state(self) -> dict[str, Any]:
        return self.arm.state() | {"camera_pose": self.camera_pose().tolist()}

    def close(self) -> None:
        self.arm.close()


def corrected(devices: Devices, error: PoseError | None) -> Devices:
    """The devices with the arm's hand-eye corrected by the pose error's (HandEyeCorrected);
    the devices themselves without one."""
    if error is None:
        return devices
    return replace(devices, arm=HandEyeCorrected(devices.arm, error.T_hand_eye))


def located_task(task: Task, error: PoseError) -> Task:
    """The task with the part where the pose error puts it (T_cell_part <- E_part T_cell_part)
    and the hand-eye corrected (T_flange_cam <- T_flange_cam E_he)."""
    frames = task.frames.with_transform("T_cell_part", error.T_part @ task.frames.T_cell_part)
    frames = frames.with_transform("T_flange_cam", frames.T_flange_cam @ error.T_hand_eye)
    return replace(task, frames=frames)


def moved_scene(scene: Scene, T: np.ndarray) -> Scene:
    """The scene with the part, its feature and the camera moved by T (cell frame)."""
    vertices = np.ascontiguousarray(geometry.apply(T, scene.vertices))
    key = hashlib.blake2b(vertices.tobytes() + np.asarray(scene.faces).tobytes(), digest_size=16).hexdigest()
    return replace(scene, vertices=vertices, mesh_key=key, center=geometry.apply(T, scene.center),
                   normal=geometry.rotate(T, scene.normal), frame=T[:3, :3] @ scene.frame,
                   points=geometry.apply(T, scene.points), normals=geometry.rotate(T, scene.normals),
                   T_cell_cam=T @ scene.T_cell_cam)


def moved_plan(plan: Plan, T: np.ndarray) -> Plan:
    """A one-shot plan carried along with the part moved by T: its scene and its camera (the view
    of the part kept); the lamp stays (the rig turns it about its fixed pivot), the loop corrects
    the exposure for the light it then gives."""
    return replace(plan, scene=moved_scene(plan.planned_scene, T),
                   shots=(replace(plan.shot, T_cell_cam=T @ plan.shot.T_cell_cam),))


def describe(error: PoseError, views: int) -> str:
    """The log's sentence of a pose error found in `views` views."""
    def vector(values: np.ndarray, stderr: np.ndarray, scale: float, unit: str) -> str:
        return (f"[{', '.join(f'{scale * v:+.2f}' for v in values)}] {unit} "
                f"(+- {', '.join(f'{scale * s:.2f}' for s in stderr)})")
    return (f"the part is off by {vector(error.part_offset_m, error.part_offset_stderr_m, 1e3, 'mm')} in the cell "
            f"and turned by {vector(error.part_rpy_rad, error.part_rpy_stderr_rad, 180 / np.pi, 'deg')}; the "
            f"camera's hand-eye turned by "
            f"{vector(error.hand_eye_rpy_rad, error.hand_eye_rpy_stderr_rad, 180 / np.pi, 'deg')} "
            f"({views} view{'s' * (views > 1)}, {error.edge_points} edge points, residual {error.residual:.2f})")


@dataclass(frozen=True)
class Told:
    """What one view tells of the 9 pose parameters where an estimate puts the part and camera
    (rendered_information): the information per pixel J^T J / N (9 x 9, parameters in
    INFORMATION_UNITS) and the rms residual of its capture against the image rendered there
    (of the unit spread; None for a view not yet captured)."""

    information: np.ndarray
    residual: float | None


def rendered_information(task: Task, scene: Scene, error: PoseError,
                         poses: Sequence[tuple[np.ndarray, LampPose, Drives]],
                         images: Sequence[np.ndarray] = ()) -> list[Told]:
    """Told of views from read-back camera poses (T_cell_cam, lamp pose, drives), the first
    len(images) of them captured: the model's image (VIEW_SCALE times coarser) with the part and
    the camera where the estimate puts them and STEP_UNITS either way of each parameter,
    band-passed at SCALES_PX[0] and scaled to unit spread over the part as the fit's are;
    J = the central differences over every part pixel. Rendered, not the edges' motion
    (view_information): the light stays in the cell when the part moves, and a part that looks
    alike after a move (a straight shank moved along itself, its lit spot fixed) tells nothing of
    it. The residual: the capture's signal on the same grid, band-passed alike, times its least-squares
    gain less the estimate's image, rms over the part pixels."""
    theta, sigma = error.theta, SCALES_PX[0] / VIEW_SCALE
    steps = [np.zeros(9)] + [sign * STEP_UNITS * INFORMATION_UNITS[j] * np.eye(9)[j]
                             for j in range(9) for sign in (1.0, -1.0)]
    bands: list[list[np.ndarray]] = [[] for _ in poses]
    seen: list[np.ndarray] = []
    moved = scene
    for n, step in enumerate(steps):         # each moved part's mesh built once for every view
        E_part, he_inv = _params(theta + step, error.center)
        if n == 0 or np.any(step[:6]):
            moved = moved_scene(scene, E_part)
        for i, (T, lamp_pose, drives) in enumerate(poses):
            T_true = T @ np.linalg.inv(he_inv)
            if n == 0:
                view = model_view(task, moved, T_true, lamp_pose, drives, VIEW_SCALE)
                seen.append(np.isfinite(view.points[..., 0]))
                value = view.value
            else:
                height, width = seen[i].shape
                value = registration.expected_image(task, moved, T_true, lamp_pose, (0, 0, width, height),
                                                    VIEW_SCALE, drives)
            bands[i].append(band_pass(value, sigma))
    told = []
    for i, band in enumerate(bands):
        part = seen[i]
        if not part.any():
            told.append(Told(np.zeros((9, 9)), None if i >= len(images) else float("inf")))
            continue
        spread = max(float(np.std(band[0][part])), 1e-12)
        J = np.column_stack([(band[1 + 2 * j] - band[2 + 2 * j])[part] / (2.0 * STEP_UNITS * spread)
                             for j in range(9)]).astype(float)
        residual = rendered_residual(signal(task, images[i]), band[0], part) if i < len(images) else None
        told.append(Told(J.T @ J / int(part.sum()), residual))
    return told


def rendered_residual(image: np.ndarray, model: np.ndarray, part: np.ndarray) -> float:
    """The rms residual of a capture against the model's image band-passed on the grid
    VIEW_SCALE times coarser (`model`, rendered_information's), over the model's part pixels:
    the capture on that grid, band-passed alike, both scaled to unit spread there, the capture
    times its least-squares gain less the model."""
    small = cv2.resize(np.asarray(image, np.float32), part.shape[::-1], interpolation=cv2.INTER_AREA)
    captured = band_pass(small, SCALES_PX[0] / VIEW_SCALE)[part].astype(float)
    captured /= max(float(np.std(captured)), 1e-12)
    rendered = model[part] / max(float(np.std(model[part])), 1e-12)
    gain = max(float(captured @ rendered) / max(float(captured @ captured), 1e-12), 0.0)
    return float(np.sqrt(np.mean((gain * captured - rendered) ** 2)))


@dataclass(frozen=True)
class Resolution:
    """How far the views leave the part's position open where an estimate puts it: along
    `direction` (cell frame, unit) it is told worst, to within uncertainty_m; `along` names that
    direction by the part's axes; the views' residuals (Told) and the covariance of all nine
    parameters by what the views tell (rendered_covariance)."""

    direction: np.ndarray
    uncertainty_m: float
    along: str
    residuals: tuple[float, ...]
    covariance: np.ndarray      # 9 x 9, of theta (rendered_covariance)

    def unresolved(self, limit_m: float) -> str | None:
        """The stop's sentence where the part's position may be off by more than limit_m (the
        registration limit: what the plan tolerates) along its weakest direction, COVERAGE times
        its uncertainty (the fit's edges can miss what the rendered images tell: the conrod 10 mm
        along its shank was fitted 8.4 mm off where three views told it to 2.7 mm, the conrod 5 mm
        4.5 mm off where two told it to 3.0 mm), else None."""
        if COVERAGE * self.uncertainty_m <= limit_m:
            return None
        views = len(self.residuals)
        return (f"the part's position {self.along} cannot be told from these {views} view{'s' * (views > 1)} "
                f"to within the {1e3 * limit_m:.1f} mm the plan tolerates (the registration limit): moving it "
                f"{1e3 * self.uncertainty_m:.1f} mm that way changes the model's images no more than they differ "
                f"from the captures (residual {', '.join(f'{r:.2f}' for r in self.residuals)} of the edges' "
                f"spread), and the limit must hold with {COVERAGE:g} times that")

    def to_json(self) -> dict[str, Any]:
        return {"weakest_direction": self.direction.tolist(), "weakest_uncertainty_m": self.uncertainty_m,
                "weakest_along": self.along}


def rendered_covariance(told: Sequence[Told], views: int) -> np.ndarray:
    """The covariance (9 x 9, theta's units) of the pose parameters by what the views tell where
    an estimate puts the part (rendered_information): the information of every view, each over
    its residual squared (the model's differences from the capture, its shading and lobe, do not
    average out over a view's pixels, so a view counts once: a move is told where its image
    changes by more than the residual), plus the fit's priors (_priors), inverted. A view without
    a residual takes the worst of the others'."""
    worst = max((t.residual for t in told if t.residual is not None), default=1.0)
    residuals = [worst if t.residual is None else t.residual for t in told]
    information = sum((t.information / max(r, 1e-6) ** 2 for t, r in zip(told, residuals)), np.zeros((9, 9)))
    information = information + np.diag(_priors(INFORMATION_UNITS, views) ** 2)
    units = np.diag(INFORMATION_UNITS)
    return units @ np.linalg.inv(information) @ units


def resolution(task: Task, scene: Scene, told: Sequence[Told], views: int) -> Resolution:
    """The part's position where it is told worst: rendered_covariance's part-offset block (every
    other parameter free), its largest eigenvalue and vector."""
    covariance = rendered_covariance(told, views)
    values, vectors = np.linalg.eigh(covariance[:3, :3])
    direction = vectors[:, -1] * (1.0 if vectors[np.argmax(np.abs(vectors[:, -1])), -1] > 0 else -1.0)
    return Resolution(direction, float(np.sqrt(max(values[-1], 0.0))), along(task, scene, direction),
                      tuple(t.residual for t in told if t.residual is not None), covariance)


def untold_tilt(error: PoseError, T_first: np.ndarray, lamp_tolerance_rad: float) -> tuple[np.ndarray, float] | None:
    """Where the part's tilt across the first view (T_first) is told worse than the plan
    tolerates, the direction d (cell frame, unit) to give sideways for a view that tells it, and
    the tilt's standard error [rad]; else None. The tilt: the edge fit's covariance's turn block
    (small turns: rpy as a rotation vector) less its part about b, the unit vector from the feature
    centre c to the first camera (a turn about the view axis changes neither the light nor where
    the feature appears), its largest eigenvalue s^2 and axis a (across b). The edge fit's own,
    not the views' (rendered_covariance): it holds the two finest scales' difference
    (model_error), which a tilt the edges do not fix moves (the conrod 8 mm across its shank,
    yawed 5 deg, its camera turned 2 deg, from two views: 0.81-0.92 deg, the estimate 0.30-0.35 deg off
    about y; the hinge's pose rows 0.06-0.11 deg), while the views' counts each view's whole
    residual as one move and does not tell the two apart. Told worse: s beyond TILT_TOLD lamp
    tolerances (a surface tilted by t turns its mirror direction by 2 t, and the plan holds the
    band under the lamp tolerance). The direction d = b x a: a tilt about a moves a point X by
    a x (X - c), along b where X - c lies along b x a (a x (b x a) = b, a across b), which the
    first view sees by perspective alone; sideways orbits the view to the side of d, along d x b,
    and (b x a) x b = a: the camera looks from the tilt's own axis, where those points spread
    across the image and their motion along b turns them in it."""
    cov = error.covariance if error.covariance is not None else np.diag(np.square(error.theta_stderr))
    b = geometry.unit(T_first[:3, 3] - error.center)
    across = np.eye(3) - np.outer(b, b)
    values, vectors = np.linalg.eigh(across @ cov[3:6, 3:6] @ across)
    stderr = float(np.sqrt(max(values[-1], 0.0)))
    if stderr <= TILT_TOLD * lamp_tolerance_rad:
        return None
    return geometry.unit(np.cross(b, vectors[:, -1])), stderr


def along(task: Task, scene: Scene, direction: np.ndarray) -> str:
    """A cell-frame direction in a process engineer's words: the part's axis (T_cell_part) it is
    nearest, by the part's extent along it (length, width, height), where within 30 deg, and its
    cell-frame vector."""
    R = task.frames.T_cell_part[:3, :3]
    extents = np.ptp(scene.vertices @ R, axis=0)
    local = R.T @ direction
    axis = int(np.argmax(np.abs(local)))
    vector = f"[{', '.join(f'{v:+.2f}' for v in direction)}] in the cell"
    if abs(local[axis]) < ALONG_COS:
        return f"along {vector}"
    name = ("height", "width", "length")[int(np.argsort(np.argsort(extents))[axis])]
    return f"along its {name} (the part's {'xyz'[axis]}: {vector})"


def by_resolution(task: Task, scene: Scene, told: Sequence[Told], candidates: Sequence[Told]) -> list[int]:
    """The indices of candidate further views (their Told, not captured) by the uncertainty of the
    part's position (resolution) with each added to the views', least first; ties in order."""
    views = len(told) + 1
    open_m = [resolution(task, scene, [*told, c], views).uncertainty_m for c in candidates]
    return [int(i) for i in np.argsort(open_m, kind="stable")]


def sideways(poses: Sequence[np.ndarray], T_first: np.ndarray, center: np.ndarray, direction: np.ndarray,
             lamp_m: np.ndarray) -> list[int]:
    """The indices of camera poses (cell frame) by how far they look at the feature from the side
    of a direction the views left open (cell frame, unit), most first: the component of each one's
    unit vector from the feature centre c along d x b, b the first view's (T_first) unit vector
    from c, d the direction; those less than SIDEWAYS to the side left out, and those on the lamp's
    side (lamp_m, cell frame): from there the way back to the shot passes the lamp (the conrod's
    re-planned shot refused, its camera 8.3 mm from the lamp's body). A part long along d (the
    conrod's shank) tilted about d x b moves its points along the first view's axis only, which
    that view sees by perspective alone and a view orbited about d x b (the second view the edges'
    information picks, along the shank) hardly better: the long edges lie in planes through d that
    pass near that camera. Seen from the side, 50 deg about d, the same tilt turns them in the
    image (the conrod 5 mm across its shank: its tilt about y 1.24 deg off from the first, the
    second and a lamp-low view, 0.05 deg with this one added)."""
    c = np.asarray(center, float)
    b = geometry.unit(T_first[:3, 3] - c)
    across = geometry.unit(np.cross(np.asarray(direction, float), b))
    lamp_side = float(np.sign(geometry.unit(np.asarray(lamp_m, float) - c) @ across))
    side = np.array([float(geometry.unit(T[:3, 3] - c) @ across) for T in poses])
    away = -side * lamp_side if lamp_side else np.abs(side)
    return [int(i) for i in np.argsort(-away, kind="stable") if away[i] >= SIDEWAYS]


def better(first: PoseError, other: PoseError) -> PoseError:
    """Of two fits of the same views from different starts, the one whose last fit (refine's,
    against the model's images where its first fit put the part) leaves the smaller residual."""
    return other if other.residual < first.residual else first


def side_refit(task: Task, scene: Scene, views: Sequence[View], earlier: PoseError) -> PoseError:
    """The estimate of the views with the side view last, from `earlier` (the views before it
    told the part's position to within the registration limit, or every view's fit from the
    model's pose and along the open direction, the better): refine at FINE_SCALES_PX, against the
    model rendered where `earlier` puts the part, not the coarsest scale nor a fit from the
    model's pose (the better fit's own last pass was rendered where its coarse fit put the part:
    the conrod 10 mm along its shank, its roll 0.30 -> 0.26 deg). The side view tells the tilt; the fine
    edges keep the position the earlier views told, where it lies in a flat valley of theirs (a
    straight shank along itself), while the coarsest scale's wide band, and with it a fit from
    scratch, slides along that valley (the conrod 8 mm across its shank, yawed 5 deg, with the
    side view: from scratch 1.23 mm off along the shank, and one 6 px pass from there 1.60 mm;
    from the two views' estimate, 0.61 mm off, at 3 and 1.5 px 0.77 mm, its tilt 0.30 -> 0.07
    deg). The earlier estimate lies within the fine scales' basin across the valley: the views
    before told it (the conrod's offset across the shank to 0.24 mm)."""
    return refine(task, scene, views, earlier, FINE_SCALES_PX)
