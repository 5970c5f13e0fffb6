"""The planning problem of one shot and what the model predicts for lamp poses on the rig,
vectorized over candidates: gray per sample from the bulk Warp kernel (G = b + u t / kappa^2,
eq. 10, 11, 17, b the sensor's black level), the exposure that centres it in the band (sec. 5.4)
and the lamp moved by its tolerance.
The requirements (cell.planning.requirements) are judged on these values."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry
from kernels.recent import Kept
from cell.physics import projection
from cell.devices import rig
from cell.physics.material import Material
from cell.physics import brdf, depth_of_field as dof
from cell.planning.regions import WANTED_TERM

if TYPE_CHECKING:
    from cell.collision.rays import BallsSeen
    from kernels.gray import GrayInputs, GrayResult
    from cell.planning.plan import Maps
    from cell.planning.scene import Scene
    from cell.task.types import Task


def depth_of_field_limits(task: Task, scene: Scene, focus_m: float | None = None) -> tuple[float, float, float]:
    """(focus [m], depth of field needed [m], f-number) for the camera focused on the feature
    centre, or at focus_m (a shot's, judged on another feature) (sec. 4.3, 5.4): the widest
    f-number within the lens's range whose near and far limits hold the nearest and the farthest
    sample and whose depth of field is at least the task's. The limits are judged where they
    fall: a patch seen at a slant is not centred on the focus."""
    lens = task.camera.lens
    f, sigma = lens.focal_length_m, lens.circle_of_confusion_m
    focus = centre_focus(scene) if focus_m is None else float(focus_m)
    depths = scene.sample_depths()
    nearest, farthest = float(depths.min()), float(depths.max())
    wanted = task.requirements.depth_of_field_m
    # the task's depth: closed form, rounded up by 1e-9 so it holds despite floating-point rounding
    kappa = dof.f_number_for_depth(focus, f, sigma, wanted) * (1 + 1e-9)

    def holds(k):           # with 1e-6 to spare: points on the surface are known to float32
        return (dof.near_limit(focus, f, k, sigma) <= nearest * (1 - 1e-6)
                and dof.far_limit(focus, f, k, sigma) >= farthest * (1 + 1e-6))

    k_lo, k_hi = lens.f_number_range
    if not holds(max(kappa, k_lo)) and holds(k_hi):
        lo, hi = max(kappa, k_lo), k_hi              # bisection: the limits widen with kappa
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if holds(mid) else (mid, hi)
        kappa = hi
    return focus, max(wanted, farthest - nearest), float(np.clip(kappa, k_lo, k_hi))


def centre_focus(scene: Scene) -> float:
    """The focus [m] of the scene's camera focused on the feature centre: their distance."""
    return float(np.linalg.norm(scene.camera_position - scene.center))


def target_gray(band: tuple[float, float]) -> float:
    """The gray the exposure aims the feature at: the band's geometric centre, its low end taken
    as at least a quarter of the high end (a band from 0 would aim at 0, a black image)."""
    low, high = band
    return float(np.sqrt(max(low, 0.25 * high) * high))


@dataclass(frozen=True)
class LightsAtScene:
    """The task's lights besides the spot at a scene (cell.planning.lights.contribution), one row
    per light in the task's order (K, P): gray per exposure at full drive, unlit, dominant term;
    the emitter points each took (K,); and with a light tolerance, each light's gray per exposure
    with its aim turned by it in TOLERANCE_RING directions (K, TOLERANCE_RING, P) at the same
    points (lights.turned; empty (K, 0, P) without one, or for a light at drive 0)."""

    unit_gray: np.ndarray
    unlit: np.ndarray
    dominant: np.ndarray
    points: tuple[int, ...]
    turned: np.ndarray


class KernelInputs:
    """A Problem's Warp inputs (kernels.gray.GrayInputs) and its lights' contributions, shared
    with the Problems `replace` makes of it (a search replaces its maps): built for the task,
    scene and material they were made of, rebuilt where one of those is another object. Pickled
    empty: Warp handles stay in their process."""

    def __init__(self) -> None:
        self.made_of: tuple[Task, Scene, Material] | None = None
        self.gray: GrayInputs | Rows | None = None
        self.lights_of: tuple[Task, Scene, Material, tuple[int, ...]] | None = None
        self.lights: LightsAtScene | None = None
        self.defects: dict[Any, Any] = {}       # cell.planning.defects: a defect's inputs, with what they were made of
        self.fixed: dict[str, tuple[tuple[Task, Scene], Any]] = {}    # Problem.fixed's values, with what they were made of
        self.top: tuple[Task, LightsAtScene, np.ndarray] | None = None  # Problem.full_drive's row, with what it was made of
        self.at_lamps: dict[str, tuple[Task, Scene, bytes, np.ndarray]] = {}  # Problem.at_lamps' last lamps and rows

    def __getstate__(self):
        return {}

    def __setstate__(self, state):
        self.__init__()


@dataclass(frozen=True)
class Problem:
    """Everything a shot's evaluation needs, fixed before the search: the task, the scene, the
    maps, the material as planned (albedo scaled by the loop's measured error), the gray band,
    the sensor's black level b (the task's camera.sensor.black_level, 0 when unknown), the focus,
    the needed depth of field, the widest f-number giving it, how many samples the camera
    cannot see (the part or a fixed light's housing hides them, or they lie outside the image)
    and which it sees (camera_seen: the spot lamp's housing may hide some of those at a lamp
    pose, requirements.camera_view); lights_off: the task's lights (indices into task.lights) it is judged with at
    drive 0, whose contributions it need not compute (a shot's certificate: a light off adds
    nothing, lit_by_all)."""

    task: Task
    scene: Scene
    maps: Maps | None
    material: Material
    band: tuple[float, float]
    black_level: float
    focus_m: float
    depth_needed_m: float
    kappa_open: float
    camera_unseen: int
    lights_off: tuple[int, ...] = ()
    kernels: KernelInputs = field(default_factory=KernelInputs, compare=False, repr=False)
    camera_seen: np.ndarray | None = field(default=None, compare=False, repr=False)  # (P,) the samples counted seen

    @property
    def gray_inputs(self) -> GrayInputs | Rows:
        """The kernel's fixed inputs (kernels.gray.GrayInputs), converted once per plan: a search
        evaluates it hundreds of times, on Problems that differ in their maps alone."""
        task, scene, material = self.task, self.scene, self.material
        made_of, gray = self.kernels.made_of, self.kernels.gray
        if (made_of is None or gray is None or made_of[0] is not task or made_of[1] is not scene
                or made_of[2] is not material):
            gray = gray_inputs(task, scene, material)
            self.kernels.gray, self.kernels.made_of = gray, (task, scene, material)
        return gray

    def fixed(self, name: str, compute: Callable[[], Any]) -> Any:
        """The value `name` of the task's camera and samples alone, no lamp in it (a requirement's
        view angle or resolution, the samples' depths): compute() once per task and scene,
        kept for the Problems `replace` makes of this one (a search's refinement evaluates the
        requirements tens of thousands of times on one camera and one set of samples)."""
        made_of, value = self.kernels.fixed.get(name, (None, None))
        if made_of is None or made_of[0] is not self.task or made_of[1] is not self.scene:
            value = compute()
            self.kernels.fixed[name] = ((self.task, self.scene), value)
        return value

    def given(self, name: str, value: Any) -> None:
        """Keep `value` as fixed's `name` for this task and scene, found elsewhere: its rows of
        the same computation over a shot's samples of several features at once (cell.planning.
        coverage.judge_all; each sample's row its own)."""
        self.kernels.fixed[name] = ((self.task, self.scene), value)

    def at_lamps(self, name: str, positions: np.ndarray, compute: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(C, P) rows `name` of lamps at `positions` (C, 3), a lamp's row its own alone
        (spot_blocked's, requirements.lamp_hides'), read-only: compute(positions) where the last
        lamps asked (or given, keep_at_lamps) do not begin with these, else their first rows (a
        chosen shot's sentences and its lights' shares ask its lamp's row again, the first of the
        poses its Candidates were made of, at_exposure)."""
        key = positions.tobytes()
        kept = self.kernels.at_lamps.get(name)
        if kept is not None and kept[0] is self.task and kept[1] is self.scene and kept[2].startswith(key):
            return kept[3][:len(positions)]
        out = compute(positions)
        self.keep_at_lamps(name, positions, out)
        return out

    def keep_at_lamps(self, name: str, positions: np.ndarray, rows: np.ndarray) -> None:
        """Keep `rows` (C, P) as at_lamps' `name` of lamps at `positions` (C, 3), read-only."""
        rows.flags.writeable = False
        self.kernels.at_lamps[name] = (self.task, self.scene, positions.tobytes(), rows)

    @property
    def lights(self) -> LightsAtScene:
        """The task's lights besides the spot at this scene (LightsAtScene; K = 0 rows without
        any), computed once per task, scene and material, all together (cell.planning.lights.contributions):
        they do not move while the spot is searched. A light in lights_off has a row of 0, unlit,
        its dominant term OCCLUDED and 0 points."""
        from cell.planning.lights import contributions, turned
        task, scene, material = self.task, self.scene, self.material
        made_of, lights = self.kernels.lights_of, self.kernels.lights
        if (made_of is None or lights is None or made_of[3] != self.lights_off
                or made_of[0] is not task or made_of[1] is not scene or made_of[2] is not material):
            on = [k for k in range(len(task.lights)) if k not in self.lights_off]
            found = dict(zip(on, contributions(scene.shadow_mesh, scene.points, scene.normals, scene.T_cell_cam,
                                               [task.lights[k] for k in on], material, task.camera.sensor,
                                               self.band[1])))
            count = len(scene.points)
            tolerance = task.requirements.light_tolerance_rad
            ring = TOLERANCE_RING if tolerance > 0 and found else 0
            lights = LightsAtScene(np.zeros((len(task.lights), count)), np.ones((len(task.lights), count), bool),
                                   np.full((len(task.lights), count), brdf.OCCLUDED, np.int8),
                                   tuple(found[k].points if k in found else 0 for k in range(len(task.lights))),
                                   np.zeros((len(task.lights), ring, count)))
            for k, c in found.items():
                lights.unit_gray[k], lights.unlit[k], lights.dominant[k] = c.unit_gray, c.unlit, c.dominant
                if ring:        # the same emitter points as the nominal aim's: the turn is all that differs
                    lights.turned[k] = [t.unit_gray for t in contributions(
                        scene.casting(but=task.lights[k].name), scene.points, scene.normals, scene.T_cell_cam,
                        turned(task.lights[k], tolerance, ring), material, task.camera.sensor, self.band[1],
                        count=c.points)]
            self.kernels.lights, self.kernels.lights_of = lights, (task, scene, material, self.lights_off)
        return lights

    def full_drive(self, candidates: int) -> np.ndarray:
        """(C, 1 + K) every light at the top of its drive range, the spot first, but the other
        lights that give another reflection than the task's off (wrong_reflection): how the spot
        is searched with the other lights on. The row once per task and lights (a search's
        refinement asks it at every evaluation)."""
        task, lights = self.task, self.lights
        kept = self.kernels.top
        if kept is None or kept[0] is not task or kept[1] is not lights:
            top = np.array([task.lamp.channel.drive_range[1]] + [light.channel.drive_range[1] for light in task.lights])
            top[1:][wrong_reflection(self, lights.unit_gray, lights.dominant)] = 0.0
            top[1:][list(self.lights_off)] = 0.0
            top.flags.writeable = False
            self.kernels.top = kept = (task, lights, top)
        return np.repeat(kept[2][None], candidates, axis=0)     # np.tile's rows, without its checks


def gray_inputs(task: Task, scene: Scene, material: Material, flat: Sequence[tuple[int, int]] = ()) -> GrayInputs:
    """The gray kernel's fixed inputs (kernels.gray.GrayInputs) for the scene's samples and
    camera, the task's lamp and sensor and the material; `flat`: the rows [start, end) of each
    patch among the samples whose rays may share a free cone (GrayInputs' `flat`: a
    certificate's dense patches, cell.planning.certificate.verify_all)."""
    from kernels.gray import GrayInputs
    return GrayInputs(scene.shadow_mesh, scene.points, scene.normals, scene.camera_position,
                      task.lamp.power_w, task.lamp.cone_angle_rad, material.table(),
                      task.camera.sensor.camera_constant, task.camera.sensor.pixel_area_m2,
                      profile=task.lamp.profile, flat=flat)


class SharedLaunches:
    """The gray kernel over the samples of several scenes seen by one camera (kernels.gray.GrayInputs
    of all their points, `counts` of them each, in order), each scene served its rows as by a
    GrayInputs of its own: `rows(k)` answers a call with the result of one launch over every
    scene's samples (made by the first scene that asks for those lamps, kept for the others),
    sliced to scene k's. The same numbers as its own launch: a thread reads one lamp and one
    sample alone (kernels.funcs.shade_point), and the free cones found or not change no result
    (GrayInputs)."""

    def __init__(self, inputs: GrayInputs, counts: list[int]) -> None:
        self.inputs = inputs
        ends = np.cumsum(counts, dtype=int)
        self.bounds = list(zip((ends - np.asarray(counts, dtype=int)).tolist(), ends.tolist()))
        self._launched: dict[tuple[bytes, bytes, bytes | None], GrayResult | Future[GrayResult]] = {}
        self._shadowed: dict[bytes, np.ndarray | Future[np.ndarray]] = {}

    def rows(self, k: int) -> Rows:
        return Rows(self, *self.bounds[k])

    def begin(self, lamp_pos: ArrayLike, lamp_axis: ArrayLike, camera: ArrayLike) -> None:
        """shadowed(camera) and launch(lamp_pos, lamp_axis, None) begun on a thread beside the
        caller's (kernels.runtime.in_background, a lane of their own: never behind the dense
        patches being laid), in that order (a dense Problem asks what its camera sees first),
        each kept for the scenes that ask for it: a certificate's launches run while the caller
        judges the samples (cell.planning.coverage.judge_all)."""
        from kernels.runtime import in_background
        lamp_pos, lamp_axis = Rows.lamps(lamp_pos, lamp_axis)
        seen = np.asarray(camera, dtype=np.float64).reshape(-1, 3)
        self._shadowed[seen.tobytes()] = in_background(self.inputs.shadowed, seen, lane=1)
        self._launched[_launch_key(lamp_pos, lamp_axis, None)] = in_background(self.inputs, lamp_pos, lamp_axis,
                                                                               None, lane=1)

    def launch(self, lamp_pos: np.ndarray, lamp_axis: np.ndarray, power_w: ArrayLike | None) -> GrayResult:
        """The result of one launch over every scene's samples for these lamps (kept by their bytes)."""
        key = _launch_key(lamp_pos, lamp_axis, power_w)
        kept = self._launched.get(key)
        if kept is None:
            kept = self._launched[key] = self.inputs(lamp_pos, lamp_axis, power_w)
        elif isinstance(kept, Future):
            kept = self._launched[key] = kept.result()
        return kept

    def shadowed(self, lamp_pos: np.ndarray) -> np.ndarray:
        """GrayInputs.shadowed over every scene's samples for these lamps (kept by their bytes)."""
        key = np.ascontiguousarray(lamp_pos).tobytes()
        kept = self._shadowed.get(key)
        if kept is None:
            kept = self._shadowed[key] = self.inputs.shadowed(lamp_pos)
        elif isinstance(kept, Future):
            kept = self._shadowed[key] = kept.result()
        return kept


def _launch_key(lamp_pos: np.ndarray, lamp_axis: np.ndarray, power_w: ArrayLike | None) -> tuple[bytes, bytes, bytes | None]:
    """SharedLaunches' key of a launch: its lamps' and powers' bytes."""
    return (np.ascontiguousarray(lamp_pos).tobytes(), np.ascontiguousarray(lamp_axis).tobytes(),
            None if power_w is None else np.asarray(power_w, dtype=np.float64).tobytes())


class Rows:
    """One scene's rows [start, end) of a SharedLaunches, called as its own GrayInputs."""

    def __init__(self, shared: SharedLaunches, start: int, end: int) -> None:
        self.shared, self.start, self.end = shared, start, end

    @staticmethod
    def lamps(lamp_pos: ArrayLike, lamp_axis: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(lamp_pos (C, 3), lamp_axis (C, 3)) as a call reads them (float64)."""
        lamp_pos = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
        return lamp_pos, np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64), lamp_pos.shape)

    def __call__(self, lamp_pos: ArrayLike, lamp_axis: ArrayLike, power_w: ArrayLike | None = None) -> GrayResult:
        from kernels.gray import GrayResult
        lamp_pos, lamp_axis = Rows.lamps(lamp_pos, lamp_axis)
        out = self.shared.launch(lamp_pos, lamp_axis, power_w)
        return GrayResult(*(a[:, self.start:self.end].copy() for a in
                            (out.value, out.shadowed, out.off_axis, out.dominant)))

    def shadowed(self, lamp_pos: ArrayLike) -> np.ndarray:
        """This scene's rows of the shared GrayInputs.shadowed (C, P)."""
        return self.shared.shadowed(np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3))[:, self.start:self.end].copy()


def planning_band(task: Task) -> tuple[float, float]:
    """The gray band planned for: the task's, its top kept half a level below the sensor's full
    scale (a pixel there reads saturated, whatever the band says)."""
    low, high = map(float, task.requirements.gray_band)
    return low, min(high, 2.0 ** task.camera.sensor.bit_depth - 1 - 0.5)


def black_level(task: Task) -> float:
    """b of G = b + c P t [gray]: the task's camera.sensor.black_level, 0 while it is unknown."""
    b = task.camera.sensor.black_level
    return 0.0 if b is None else float(b)


def build_problem(task: Task, scene: Scene, maps: Maps | None, albedo_scale: float = 1.0,
                  focus_m: float | None = None, gray: Rows | None = None,
                  material: Material | None = None, hidden: np.ndarray | None = None,
                  seen: np.ndarray | None = None) -> Problem:
    """The Problem of a task's scene and maps, the camera focused on the feature centre or at
    focus_m (a given shot's), the material the task's scaled by albedo_scale or `material` (a
    search's, which its certificate keeps), its gray kernel the scene's own or `gray`, its rows
    of a launch shared with other scenes (SharedLaunches: a shot judged on several features).
    A sample the camera sees lies inside the image and is not hidden (a lamp at the camera would
    light it): `hidden` (P,) where found before (hidden_from), else by the kernel's shadow flag
    alone here (GrayInputs.shadowed, no shading): the scenes of one shot judged on several
    features ask their SharedLaunches for one launch, not one each. `seen` (P,): the samples the
    camera sees, found before (a shot's samples of several features at once, their rows of one
    Problem's camera_seen: cell.planning.coverage.judge_all)."""
    focus, needed, kappa_open = depth_of_field_limits(task, scene, focus_m)
    p = Problem(task, scene, maps, task.part.material.scaled(albedo_scale) if material is None else material,
                planning_band(task), black_level(task), focus, needed, kappa_open, 0)
    if gray is not None:
        p.kernels.gray, p.kernels.made_of = gray, (task, scene, p.material)
    if seen is not None:
        unseen = ~seen
    else:
        if hidden is None:      # the kernel's flag alone: the arm and camera body shadow the spot, not the view
            hidden = p.gray_inputs.shadowed(scene.camera_position[None])[0]
        unseen = hidden | ~in_image(task, scene)
    return replace(p, camera_unseen=int(np.sum(unseen)), camera_seen=~unseen)


def hidden_from(task: Task, scene: Scene, cameras: ArrayLike) -> np.ndarray:
    """(N, P) the scene's samples hidden from each of N camera positions (N, 3) [m]: the gray
    kernel's shadow flag for a lamp there (build_problem's, GrayInputs.shadowed: no shading),
    which reads the sample, its normal, the mesh and the position alone (kernels.funcs.shadowed_from),
    so one launch serves many cameras."""
    cameras = np.asarray(cameras, dtype=np.float64).reshape(-1, 3)
    if not len(cameras):
        return np.zeros((0, len(scene.points)), bool)
    return gray_inputs(task, scene, task.part.material).shadowed(cameras)


def in_image(task: Task, scene: Scene) -> np.ndarray:
    """(P,) the samples in front of the scene's camera and inside its image (pixel centres
    -0.5 .. size - 0.5, the pinhole's projection)."""
    sensor = task.camera.sensor
    uv, z = projection.project(projection.intrinsics(sensor, task.camera.lens), scene.T_cell_cam, scene.points)
    with np.errstate(invalid="ignore"):
        return ((z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= sensor.width_px - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= sensor.height_px - 0.5))


def unit_gray(problem: Problem, positions: ArrayLike,
              aims: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(gray per exposure u (C, P), shadowed (C, P), off-axis angle (C, P), dominant BRDF term
    (C, P), as brdf.judged_term judges the kernel's) of lamps at `positions` aiming along `aims`,
    from the Warp kernel, the irradiance by the lamp's profile (eq. 11's ideal cone without one)."""
    value, shadowed, off_axis, dominant = spot_rays(problem, positions, aims)
    return value, shadowed, off_axis, judged(problem, positions, dominant)


def spot_rays(problem: Problem, positions: ArrayLike,
              aims: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """unit_gray's (u, shadowed, off-axis, dominant) (C, P) with the kernel's dominant term, not
    yet judged (judged): the Warp kernel's values, the camera body's and the arm's shadows
    (spot_blocked) taken out."""
    out = problem.gray_inputs(positions, aims)
    blocked = spot_blocked(problem, positions)
    return np.where(blocked, 0.0, out.value), out.shadowed | blocked, out.off_axis, out.dominant


def judged(problem: Problem, positions: ArrayLike, dominant: np.ndarray) -> np.ndarray:
    """(C, P) the kernel's dominant term of lamps at `positions` (C, 3) as brdf.judged_term judges
    it (UNKNOWN where an unresolved spike may dominate); the kernel's where the material has no
    unresolved spike. Each row reads its own lamp alone."""
    if problem.material.unresolved is None:               # nothing to judge: the kernel's term
        return dominant
    scene = problem.scene
    s = geometry.unit(np.asarray(positions, float).reshape(-1, 1, 3) - scene.points[None])
    v = geometry.unit(scene.camera_position - scene.points)[None]
    return brdf.judged_term(dominant, scene.normals[None], s, v, problem.material)


def nominal_and_moved(problem: Problem, positions: np.ndarray, drive: np.ndarray,
                      n: int) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """lit_by_all of unit_gray for lamps at `positions` (C, 3) aimed at the rig's pivot, the other
    lights at `drive` (C, 1 + K), in one kernel launch: the first n lamps (the nominal poses) in
    full, (u, shadowed, off-axis, dominant) (n, P), and the rest (the poses the tolerance moves
    them to, whose gray alone is read) their gray per exposure (C - n, P) (lit_gray): the same
    rows as lit_by_all of unit_gray over all, without judging the moved lamps' terms."""
    value, shadowed, off_axis, dominant = spot_rays(problem, positions,
                                                    rig.lamp_aim(problem.task.lamp.rig.pivot_m, positions))
    nominal = lit_by_all(problem, (value[:n], shadowed[:n], off_axis[:n], judged(problem, positions[:n], dominant[:n])),
                         drive[:n])
    return nominal, lit_gray(problem, value[n:], drive[n:])


@dataclass(frozen=True)
class ArmAtShot:
    """The bodies the camera's pose places, which stand still while the spot is searched: the
    camera body (a box, T_cell_box and half sizes) and the UR5e's links (capsules: axes a-b,
    radii) at the joints that reach the pose (none where the arm does not reach it); for the
    prefilters a capsule holding each body (around_a, around_b, around_radius_m: the camera
    body's first, rays.box_capsules, then the links themselves) and balls along each holding it
    widened by rho as seen from m (seen; a long link is held by several, each at most twice the
    capsule's width), m and rho the samples' sphere (middle, rho)."""

    T_cell_box: np.ndarray        # (4, 4)
    half_m: np.ndarray            # (3,)
    a: np.ndarray                 # (K, 3)
    b: np.ndarray                 # (K, 3)
    radius_m: np.ndarray          # (K,)
    around_a: np.ndarray          # (1 + K, 3)
    around_b: np.ndarray          # (1 + K, 3)
    around_radius_m: np.ndarray   # (1 + K,)
    middle: np.ndarray            # (3,)
    rho: float
    seen: BallsSeen               # the balls holding the capsules widened by rho, body by body
    first_ball: np.ndarray        # (1 + K,) each body's first ball in seen


def samples_sphere(problem: Problem) -> tuple[np.ndarray, float]:
    """The sphere holding the problem's samples (geometry.bounding_sphere: middle, radius), once
    per task and scene (the blockers' prefilters read it: spot_blocked, requirements.rig_hides)."""
    return problem.fixed("samples_sphere", lambda: geometry.bounding_sphere(problem.scene.points))


# arm_at_camera's bodies of the last few camera poses, by what makes them (arm_at_camera's key)
_AT_CAMERA: Kept[tuple[np.ndarray, ...]] = Kept(4)


def arm_at_camera(task: Task, T_cell_cam: np.ndarray) -> tuple[np.ndarray, ...]:
    """(T_cell_box, half_m, a, b, radius_m, around_a, around_b, around_radius_m) of ArmAtShot:
    the bodies the camera's pose alone places (the camera body, the links at the joints nearest
    home), read-only, made once per camera pose, robot base, hand-eye and camera body in a
    process (a shot judged on other features, cell.planning.coverage, asks them for each
    feature's samples and dense patch: some 7 Problems on one camera pose)."""
    from cell.collision.rays import box_capsules
    from cell.collision.scene import arm_links, camera_body, reaching_joints
    c, frames = task.cell.collision, task.frames
    key = np.concatenate([np.ravel(x) for x in (T_cell_cam, frames.T_cell_base, frames.T_flange_cam,
                                                c.camera_size_m, [c.camera_offset_m])]).astype(np.float64).tobytes()

    def made() -> tuple[np.ndarray, ...]:
        box = camera_body(frames.T_cell_flange(T_cell_cam), 0.5 * np.asarray(c.camera_size_m, float), c.camera_offset_m)
        q = reaching_joints(frames, T_cell_cam)
        links = () if q is None else arm_links(frames.T_cell_base, q)
        a, b, radius = (np.array([k.a for k in links]).reshape(-1, 3), np.array([k.b for k in links]).reshape(-1, 3),
                        np.array([k.radius_m for k in links]))
        box_a, box_b, box_radius = box_capsules(box.T_cell_box, box.half_m)
        bodies = (box.T_cell_box, box.half_m, a, b, radius, np.vstack([box_a, a]), np.vstack([box_b, b]),
                  np.concatenate([box_radius, radius]))
        for array in bodies:
            array.flags.writeable = False
        return bodies
    return _AT_CAMERA.get(key, made)


def arm_at_shot(task: Task, scene: Scene, sphere: tuple[np.ndarray, float] | None = None) -> ArmAtShot:
    """The camera body and the arm's links at the scene's camera pose (cell.collision.scene:
    camera_body, arm_links, reaching_joints: the joints nearest home, as the shot's clearance;
    arm_at_camera's); sphere the samples' (geometry.bounding_sphere's) where known."""
    from cell.collision.rays import NEAR_MARGIN_M, BallsSeen, capsule_balls
    T_cell_box, half_m, a, b, radius, around_a, around_b, around_radius = arm_at_camera(task, scene.T_cell_cam)
    middle, rho = geometry.bounding_sphere(scene.points) if sphere is None else sphere
    # each capsule widened by rho held by balls along its axis, each at most twice as wide as the capsule
    centres, radii, first = capsule_balls(around_a, around_b, around_radius + rho + NEAR_MARGIN_M)
    return ArmAtShot(T_cell_box, half_m, a, b, radius, around_a, around_b, around_radius, middle, rho,
                     BallsSeen.of(middle, centres, radii), first)


def spot_blocked(problem: Problem, positions: ArrayLike) -> np.ndarray:
    """(C, P) whether the ray from each sample to the spot at each position (C, 3) crosses the
    camera body or a link of the arm (ArmAtShot; cell.collision.rays): a shadow as the part's,
    no spot light there. Only the bodies near the rays are tested, the links in one call: the
    ray sample s -> lamp L at s + t (L - s) lies (1 - t) |s - m| <= rho from m + t (L - m)
    (rho the samples' sphere about their middle m), so a body whose capsule (ArmAtShot.around_*)
    is farther than rho from the segment m -> L blocks none of the lamp's rays; nor one whose
    ball holding that capsule, widened by rho, the segment m -> L cannot meet (ArmAtShot.seen,
    tested first: a few operations for every lamp and body). Read-only, the last lamps' rows kept
    (Problem.at_lamps: requirements.explain_no_shadow and one_shot.light_settings ask a chosen
    shot's lamp again)."""
    return problem.at_lamps("blocked", np.asarray(positions, float).reshape(-1, 3),
                            lambda at: _blocked(problem, at))


def _blocked(problem: Problem, positions: np.ndarray) -> np.ndarray:
    """spot_blocked's rows of lamps at `positions` (C, 3), found."""
    from cell.collision.rays import NEAR_MARGIN_M, segments_cross_boxes, segments_near_segments
    scene = problem.scene
    count = len(scene.points)
    out = np.zeros((len(positions), count), bool)
    arm = problem.fixed("arm_at_shot", lambda: arm_at_shot(problem.task, scene, samples_sphere(problem)))
    near = np.logical_or.reduceat(arm.seen.met_by(positions), arm.first_ball, axis=0)   # (1 + K, C)
    if not near.any():
        return out
    bodies, lamps = np.flatnonzero(near.any(axis=1)), np.flatnonzero(near.any(axis=0))
    near[np.ix_(bodies, lamps)] &= segments_near_segments(
        arm.middle, positions[lamps], arm.around_a[bodies], arm.around_b[bodies],
        arm.around_radius_m[bodies] + arm.rho + NEAR_MARGIN_M)

    def rays(lamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.broadcast_to(scene.points, (len(lamps), count, 3)).reshape(-1, 3),
                np.repeat(positions[lamps], count, axis=0))
    if near[0].any():
        lamps = np.flatnonzero(near[0])
        out[lamps] = segments_cross_boxes(*rays(lamps), arm.T_cell_box[None], arm.half_m)[0].reshape(len(lamps), -1)
    links = np.flatnonzero(near[1:].any(axis=1))
    if len(links):
        lamps = np.flatnonzero(near[1:][links].any(axis=0))
        hit = segments_near_segments(*rays(lamps), arm.a[links], arm.b[links], arm.radius_m[links]).any(axis=0)
        out[lamps] |= hit.reshape(len(lamps), -1)
    return out


def wrong_reflection(problem: Problem, unit_gray: np.ndarray, dominant: np.ndarray) -> np.ndarray:
    """(1 + K,) the lights that give another reflection than the task's at some sample they light
    (dominant term, brdf.judged_term's; none when it asks for `any`): off in the drive program,
    since a light's share of a sample's gray is linear in its drive but which term dominates the
    sum is not, and a light whose own term is the wanted one everywhere keeps the sum's so (a
    light on its own supply cannot be turned off: the caller keeps it on)."""
    reflection = problem.task.requirements.reflection
    if reflection == "any":
        return np.zeros(len(unit_gray), bool)
    wrong = (unit_gray > 0.0) & (dominant != WANTED_TERM[reflection])
    return wrong.any(axis=1)


def lit_by_all(problem: Problem, spot: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
               drive: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The spot's (gray per exposure, shadowed, off-axis, dominant) (C, P) (unit_gray's) with the
    other lights added at drive (C, 1 + K), the spot's drive first: the gray is the drives' sum
    (linear in each light's drive, below saturation); a sample is shadowed where no light with
    some drive reaches it; its off-axis angle is the spot's where the spot alone reaches it (0
    where another light does: the spot's cone need not cover it), and its dominant term the one
    of the light that adds the most there. Without other lights the spot's, scaled by its drive."""
    u, shadowed, off_axis, dominant = spot
    drive = np.asarray(drive, float).reshape(len(u), -1)
    lights = problem.lights
    spot_on = drive[:, :1] > 0.0
    if not len(lights.unit_gray):
        return drive[:, :1] * u, np.logical_or(shadowed, ~spot_on), np.where(spot_on, off_axis, 0.0), dominant
    shares = _shares(lights, u, drive)
    reached = np.concatenate([(~shadowed & spot_on)[:, None],
                              (drive[:, 1:, None] > 0.0) & ~lights.unlit[None]], axis=1)    # (C, 1 + K, P)
    others = reached[:, 1:].any(axis=1)
    terms = np.concatenate([dominant[:, None], np.broadcast_to(lights.dominant[None], shares[:, 1:].shape)], axis=1)
    strongest = np.argmax(shares, axis=1)[:, None]
    return (shares.sum(axis=1), np.logical_not(reached.any(axis=1)), np.where(others | ~spot_on, 0.0, off_axis),
            np.take_along_axis(terms, strongest, axis=1)[:, 0])


def _shares(lights: LightsAtScene, u: np.ndarray, drive: np.ndarray) -> np.ndarray:
    """(C, 1 + K, P) each light's gray per exposure at its drive (C, 1 + K), the spot's (u) first."""
    return np.concatenate([(drive[:, :1] * u)[:, None], drive[:, 1:, None] * lights.unit_gray[None]], axis=1)


def lit_gray(problem: Problem, u: np.ndarray, drive: np.ndarray) -> np.ndarray:
    """lit_by_all's gray per exposure alone (C, P): the spot's u (C, P) and the other lights at
    drive (C, 1 + K), summed in lit_by_all's order (the same bits, row by row)."""
    lights = problem.lights
    if not len(lights.unit_gray):
        return drive[:, :1] * u
    return _shares(lights, u, drive).sum(axis=1)


def drive_moves(problem: Problem, u: np.ndarray) -> list[np.ndarray]:
    """The gray per exposure with every drive off by the task's drive tolerance, low and high
    (each light's share is at least 0, so all low and all high are the extremes at every sample);
    none when the tolerance is 0."""
    delta = problem.task.requirements.drive_tolerance
    return [] if delta <= 0 else [(1.0 - delta) * u, (1.0 + delta) * u]


def light_moves(problem: Problem, u: np.ndarray, drive: np.ndarray) -> list[np.ndarray]:
    """The gray per exposure (C, P) with one light's aim turned by the task's light tolerance, for
    each light and each of TOLERANCE_RING directions (LightsAtScene.turned): u with that light's
    share at drive (C, 1 + K) replaced by its turned one; none without a tolerance."""
    lights = problem.lights
    if not lights.turned.size:
        return []
    drive = np.asarray(drive, float).reshape(len(u), -1)
    return [u + drive[:, 1 + k, None] * (lights.turned[k, m] - lights.unit_gray[k])[None]
            for k in range(lights.turned.shape[0]) for m in range(lights.turned.shape[1])]


def exposure(problem: Problem, unit_gray: np.ndarray,
             moved: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """centring_exposure of the Problem's band, black level, camera and depth of field; with
    `gray_band: any`, top_exposure (`moved`: the tolerance moves' gray per exposure, (M, C, P))."""
    cam = problem.task.camera
    if problem.task.requirements.gray_any:
        return top_exposure(unit_gray, np.zeros((0,) + unit_gray.shape) if moved is None else moved, problem.band,
                            problem.black_level, problem.kappa_open, cam.shutter_range_s, cam.lens.f_number_range)
    return centring_exposure(unit_gray, problem.band, problem.black_level, problem.kappa_open,
                             cam.shutter_range_s, cam.lens.f_number_range)


def centring_exposure(unit_gray: np.ndarray, band: tuple[float, float], black_level: float, kappa_open: float,
                      shutter_range: tuple[float, float],
                      f_number_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(shutter, f-number, shutter needed at kappa_open) putting the geometric mean of the lit
    samples' extremes at the geometric centre of the band the signal must meet: G = b + u t /
    kappa^2 is in [low, high] when u t / kappa^2 is in [low - b, high - b]. The f-number no
    wider than kappa_open (the depth of field's); t_need is inf where no sample is lit."""
    low, high = band
    lit = unit_gray > 0.0
    darkest = np.where(lit, unit_gray, np.inf).min(axis=-1)
    any_lit = lit.any(axis=-1)
    with np.errstate(over="ignore"):       # a lamp of 1e300 W: inf, its t_need 0, "too bright" says it
        u_mid = np.where(any_lit, np.sqrt(np.where(any_lit, darkest, 0.0) * unit_gray.max(axis=-1)), 0.0)
    target = target_gray((low - black_level, high - black_level))
    gain = np.divide(target, u_mid, out=np.full_like(u_mid, np.inf), where=u_mid > 0)
    shutter, kappa = exposure_for_gain(gain, kappa_open, shutter_range, f_number_range)
    return shutter, kappa, kappa_open**2 * gain


def top_exposure(unit_gray: np.ndarray, moved: np.ndarray, band: tuple[float, float], black_level: float,
                 kappa_open: float, shutter_range: tuple[float, float],
                 f_number_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`gray_band: any`'s (shutter, f-number, shutter needed at kappa_open) for gray per exposure
    (C, P) and its tolerance moves' (M, C, P): the brightest sample, moved or not, at the band's
    top (x = (high - b) / max u: a defect's CNR grows with the exposure, cell.planning.drives.raised);
    the shutter needed is the one putting the darkest lit sample at the band's low end (what
    `any` asks: not black), inf where no sample is lit."""
    low, high = band
    lit = unit_gray > 0.0
    brightest = np.max(np.concatenate([unit_gray[None], moved]), axis=(0, 2))
    darkest = np.where(lit, unit_gray, np.inf).min(axis=-1)
    with np.errstate(divide="ignore", over="ignore"):
        gain = np.where(brightest > 0, (high - black_level) / np.where(brightest > 0, brightest, 1.0), np.inf)
        need = np.where(lit.any(axis=-1), max(low - black_level, 0.0) / np.where(lit.any(axis=-1), darkest, 1.0),
                        np.inf)
    shutter, kappa = exposure_for_gain(gain, kappa_open, shutter_range, f_number_range)
    return shutter, kappa, kappa_open**2 * need


def exposure_for_gain(gain: ArrayLike, kappa_open: float, shutter_range: tuple[float, float],
                      f_number_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(shutter [s], f-number) giving the exposure gain x = t / kappa^2 [s] (inf: the longest
    shutter): t = x kappa_open^2 at kappa_open (the depth of field's widest) within the shutter
    range; shorter than the shortest, stopped down at it, kappa = sqrt(t_lo / x) up to the lens's max."""
    gain = np.asarray(gain, float)
    t_lo, t_hi = shutter_range
    t_need = kappa_open**2 * gain
    with np.errstate(divide="ignore"):
        kappa = np.where(t_need < t_lo, np.sqrt(t_lo / gain), kappa_open)
    # np.clip's bounds as two ufuncs (the same values; np.clip's own checks cost more on a few poses)
    return np.minimum(np.maximum(t_need, t_lo), t_hi), np.minimum(np.maximum(kappa, kappa_open), f_number_range[1])


@dataclass(frozen=True)
class Candidates:
    """Lamp poses (C of them) and what the model predicts for each: positions (C, 3), gray
    (C, P) at the chosen exposure, the gray with the lamp moved by its tolerance (M, C, P) at the
    same exposure (M = 0 when not evaluated), shadowed and off-axis angle (C, P), and the
    exposure: shutter, f-number, shutter needed (C,), and each sample's dominant BRDF term (C, P);
    the lights' drives (C, 1 + K), the spot's first (evaluate.lit_by_all)."""

    position: np.ndarray
    gray: np.ndarray
    moved_gray: np.ndarray
    shadowed: np.ndarray
    off_axis: np.ndarray
    dominant: np.ndarray
    shutter: np.ndarray
    kappa: np.ndarray
    t_need: np.ndarray
    drive: np.ndarray

    def pick(self, k: int) -> Candidates:
        """Candidate k alone, as Candidates of one."""
        return Candidates(**{f.name: getattr(self, f.name)[:, k:k + 1] if f.name == "moved_gray"
                             else getattr(self, f.name)[k:k + 1] for f in fields(self)})


def stacked(ones: Sequence[Candidates]) -> Candidates:
    """Candidates of one each (at_exposure's) as one Candidates, in order; their moved grays
    must be as many."""
    return Candidates(**{f.name: np.concatenate([getattr(c, f.name) for c in ones], axis=1 if f.name == "moved_gray"
                                                else 0) for f in fields(Candidates)})


TOLERANCE_RING = 8          # lamp errors of lamp_tolerance in this many directions around the aim
# (TOLERANCE_RING, 2) (cos psi, sin psi) of the ring's directions psi = 2 pi k / TOLERANCE_RING, once
_RING = np.array([(np.cos(a), np.sin(a)) for a in 2.0 * np.pi * np.arange(TOLERANCE_RING) / TOLERANCE_RING])


def tolerance_moves(problem: Problem, tilt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d_pan, d_tilt), each (M, C), moving the lamp direction at each of C tilts by
    lamp_tolerance in M = TOLERANCE_RING directions psi (a ring: an error of that size in any
    direction, not only along the two axes): (tol cos psi / cos tilt, tol sin psi), cos tilt at
    least 1e-3; M = 0 without a tolerance."""
    tol = problem.task.requirements.lamp_tolerance_rad
    if tol <= 0:
        return np.zeros((0, len(tilt))), np.zeros((0, len(tilt)))
    across = np.maximum(np.cos(tilt), 1e-3)
    return (tol * _RING[:, :1]) / across, np.broadcast_to(tol * _RING[:, 1:], (TOLERANCE_RING, len(tilt)))


def candidates(problem: Problem, pan: ArrayLike, tilt: ArrayLike, radius: ArrayLike,
               tolerance: bool = True, drive: ArrayLike | None = None) -> Candidates:
    """Candidates for lamp joints (C,) arrays, the other lights at `drive` (1 + K,) (the spot's
    first; default: every light at the top of its range), the exposure centring their sum. With
    `tolerance` the lamp is also moved by lamp_tolerance in TOLERANCE_RING directions (one bulk
    call for all) and every drive is off by the drive tolerance (drive_moves)."""
    pivot = problem.task.lamp.rig.pivot_m
    pan, tilt, radius = (np.atleast_1d(np.asarray(x, float)) for x in (pan, tilt, radius))
    if not pan.shape == tilt.shape == radius.shape:
        pan, tilt, radius = np.broadcast_arrays(pan, tilt, radius)
    n = len(pan)
    d_pan, d_tilt = tolerance_moves(problem, tilt) if tolerance else (np.zeros((0, n)), np.zeros((0, n)))
    m = len(d_pan)
    all_pos = rig.lamp_position(pivot, np.concatenate([pan, (pan + d_pan).ravel()]),
                                np.concatenate([tilt, (tilt + d_tilt).ravel()]), np.concatenate([radius] * (m + 1)))
    drives = problem.full_drive(n) if drive is None else np.tile(np.asarray(drive, float), (n, 1))
    (u, shadowed, off_axis, dominant), moved = nominal_and_moved(problem, all_pos, np.concatenate([drives] * (m + 1)), n)
    b = problem.black_level
    moved = moved.reshape(m, n, u.shape[1])
    extra = drive_moves(problem, u) + light_moves(problem, u, drives) if tolerance else []
    if extra:
        moved = np.concatenate([moved, np.array(extra).reshape(-1, n, u.shape[1])])
    shutter, kappa, t_need = exposure(problem, u, moved)
    gain = (shutter / kappa**2)[:, None]
    return Candidates(all_pos[:n], b + u * gain, b + moved * gain, shadowed, off_axis, dominant, shutter, kappa,
                      t_need, drives)


# moved_positions' rows of the last few lamps, by their pivot, joints and tolerance
_MOVED: Kept[np.ndarray] = Kept(4)


def moved_positions(problem: Problem, joints: Sequence[float]) -> np.ndarray:
    """(M, 3) the lamp at `joints` (pan, tilt, radius) moved by its tolerance (tolerance_moves:
    each move's position by rig.lamp_position alone, M = 0 without a tolerance), read-only, once
    per pivot, joints and tolerance in a process: a shot judged on several features asks them
    for each feature's samples (cell.planning.coverage), eight positions of the same few numbers."""
    pivot = np.asarray(problem.task.lamp.rig.pivot_m, float)
    key = np.concatenate([pivot.ravel(), np.asarray(joints, float).ravel(),
                          [problem.task.requirements.lamp_tolerance_rad]]).astype(np.float64).tobytes()

    def made() -> np.ndarray:
        d_pan, d_tilt = tolerance_moves(problem, np.array([joints[1]]))
        moved = np.array([rig.lamp_position(pivot, joints[0] + dp, joints[1] + dt, joints[2])
                          for dp, dt in zip(d_pan, d_tilt)]).reshape(-1, 3)
        moved.flags.writeable = False
        return moved
    return _MOVED.get(key, made)


def at_exposure(problem: Problem, position: ArrayLike, shutter_s: float, f_number: float,
                joints: Sequence[float] | None = None, drive: ArrayLike | None = None) -> Candidates:
    """Candidates of one lamp at `position` (aiming at the rig's pivot) at a fixed shutter and
    f-number, the other lights at `drive` (1 + K,) (default: every light at the top of its
    range): a chosen shot, as the certificate checks it. Given its `joints` (pan, tilt, radius),
    the lamp is also moved by its tolerance around them, and every drive by the drive tolerance,
    at the same exposure."""
    pos = np.asarray(position, float).reshape(1, 3)
    moved_pos = np.zeros((0, 3)) if joints is None else moved_positions(problem, joints)
    all_pos = np.vstack([pos, moved_pos])
    drives = problem.full_drive(1) if drive is None else np.asarray(drive, float).reshape(1, -1)
    (u, shadowed, off_axis, dominant), moved = nominal_and_moved(problem, all_pos, np.tile(drives, (len(all_pos), 1)), 1)
    gain = shutter_s / f_number**2
    t_need = exposure(problem, u)[2]
    b = problem.black_level
    moved = moved.reshape(len(moved_pos), 1, u.shape[1])
    if joints is not None:
        moved = np.concatenate([moved, np.array(drive_moves(problem, u) + light_moves(problem, u, drives))
                               .reshape(-1, 1, u.shape[1])])
    return Candidates(pos, b + u * gain, b + moved * gain, shadowed, off_axis, dominant,
                      np.array([float(shutter_s)]), np.array([float(f_number)]), t_need, drives)
