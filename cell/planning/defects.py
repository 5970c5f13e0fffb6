"""A feature's declared defects as the planner judges them: the gray a defect would have at each
feature sample under the shot's own lights, drives and exposure, against the good surface's, over
the sensor's noise (cell.physics.contrast), worst over the samples and the scratch's orientations.

A defect is judged as if it lay at each sample, each of its parts shaded where that part lies
(offsets_of, in the sample's tangent plane): a scratch's walls a quarter width to either side of
its line (each wall is half the groove wide), a dent's ring at distance rho from its centre in
each direction as the pixel whose footprint ends there sees it (the area mean over the annulus one
pixel footprint wide inside rho, of tilts asin(r / R): dent_radii, pixel_mean), a coating at the
sample itself. There the part's gray is the shading with its normal (scratch, dent) or material
(coating), and the good surface's gray the same point with the surface's normal and material
(what the run's measurement compares: the part's pixels against its good neighbours' plane at the
part's place): the bulk kernel (kernels.gray.GrayInputs) for the spot, each other light's emitter
points (cell.planning.lights.contribution, as many as the good surface's took) for the rest,
summed at the candidate's drives, G = b + t / kappa^2 sum_k w_k u_k (eq. 10, 17; the planner's
own). A part's cast shadow is the sample's (a defect is far smaller than a shadow's edge).

Per orientation a scratch shows by the larger CNR of its two walls (they lie side by side, each a
half width wide: the groove is seen where either differs from the surface; a groove narrower than
a pixel, averaged with the surface around it, is not modelled); a dent by the largest over its
field of tilts (its parts face every way at once: it has no worst orientation), a coating by its
one gray. The predicted CNR is the smallest of these over the samples and the orientation range.

Orientations are sampled every 5 deg over the range (JUDGED; RANKED's 15 deg and a coarser dent
field while the global search only ranks more than RANKED_ONLY poses; a groove at theta and
theta + 180 deg is the same): between two neighbours the wall normal moves by at most
2 sin(beta) sin(2.5 deg). Where one wall's contrast changes sign the CNR is V-shaped in theta, so
every sample whose grid minimum could dip below the worst between grid points (by the step to its
neighbours) is judged again every FINE_STEP_RAD (0.25 deg) within a grid step, and the best of those
every 0.0125 deg (_refined): the worst orientation to about 0.01 deg.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cell.core import geometry
from cell.devices import rig
from cell.physics import contrast, sensor as sensor_model
from cell.planning.plan import DefectCnr

if TYPE_CHECKING:
    from cell.planning.drives import ContrastRows
    from cell.physics.material import Material
    from cell.planning.evaluate import Candidates, Problem
    from cell.task.types import Defect, Sensor

@dataclass(frozen=True)
class Resolution:
    """How finely a defect is sampled: a scratch's orientations step_rad apart, a dent's tilts at
    rho = a k / rings (k = 1..rings, the last its rim slope) from `azimuths` directions."""

    step_rad: float
    rings: int
    azimuths: int


JUDGED = Resolution(float(np.radians(5.0)), 4, 24)     # a pose judged (at most RANKED_ONLY candidates)
RANKED = Resolution(float(np.radians(15.0)), 2, 8)     # the global search's ranking of many poses
FOOTPRINT_POINTS = 2            # Gauss-Legendre nodes across a dent ring's pixel footprint
RANKED_ONLY = 16                # more candidates than this are only ranked (the global search)
ORIENTATION_STEP_RAD = JUDGED.step_rad
FINE_STEP_RAD = float(np.radians(0.25))
REFINED_SAMPLES = 64
CHUNK = 1 << 16                 # normals per kernel input when judged once (a dense patch)
TINY_CNR = 1e-300               # the ratio's floor: a defect that never shows misses by ln(min_cnr / 1e-300)


def orientations(defect: Defect, step_rad: float = ORIENTATION_STEP_RAD) -> np.ndarray:
    """(O,) a scratch's orientations [rad] at most step_rad apart over its range, both ends
    included; a range of 180 deg or more is every orientation once (theta and theta + 180 deg are
    the same groove). One (0) for a dent or a coating."""
    if defect.kind != "scratch":
        return np.zeros(1)
    lo, hi = defect.orientation_rad
    if hi - lo >= np.pi - 1e-12:
        n = int(np.ceil(np.pi / step_rad - 1e-9))
        return lo + np.pi * np.arange(n) / n
    return np.linspace(lo, hi, max(1, int(np.ceil((hi - lo) / step_rad - 1e-9))) + 1)


def footprint_of(problem: Problem) -> float:
    """A pixel's footprint at the feature's centre [m]: |centre - camera| pitch / f (the pinhole's
    magnification, as cell.run.defects measures in footprints)."""
    scene, camera = problem.scene, problem.task.camera
    return float(np.linalg.norm(scene.center - scene.camera_position) * camera.sensor.pixel_pitch_m
                 / camera.lens.focal_length_m)


def dent_radii(radius_m: float, rings: int, footprint_m: float) -> tuple[np.ndarray, np.ndarray]:
    """((rings, Q) radii [m], (rings, Q) weights summing to 1 per ring): a dent's ring k at
    rho_k = a k / rings as the pixel whose footprint ends there sees it, the mean over the annulus
    [max(rho_k - fp, 0), rho_k] of the gray (its area element r dr): FOOTPRINT_POINTS Gauss-Legendre
    nodes across it, each weighted by its weight times its radius. The run's rim pixels (their
    centres within the outer footprint, one ray each) average exactly that annulus: a pixel at
    the rim alone would claim the rim's full slope (dents measured 6-10 % below their plan)."""
    outer = radius_m * np.arange(1, rings + 1) / rings
    inner = np.maximum(outer - footprint_m, 0.0)
    x, w = np.polynomial.legendre.leggauss(FOOTPRINT_POINTS)
    rho = inner[:, None] + (outer - inner)[:, None] * (0.5 * (x + 1.0))[None]
    weight = w[None] * rho
    return rho, weight / weight.sum(axis=1, keepdims=True)


def normals_of(defect: Defect, normals: np.ndarray, x_axis: np.ndarray, thetas: np.ndarray,
               resolution: Resolution = JUDGED, footprint_m: float = 0.0) -> np.ndarray:
    """(P, O, W, 3) the defect's normals at each sample: per orientation (O) a scratch's two walls,
    a dent's field of rings x nodes x azimuths tilts (resolution's, dent_radii's nodes across
    each ring's pixel footprint; pixel_mean averages them), a coating's own normal (W = 1)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    if defect.kind == "scratch":
        return contrast.scratch_normals(n, x_axis, thetas, contrast.wall_tilt(_given(defect.width_m),
                                                                              _given(defect.depth_m)))
    if defect.kind == "dent":
        a = _given(defect.radius_m)
        count = resolution.azimuths
        tilts = contrast.dent_tilt(dent_radii(a, resolution.rings, footprint_m)[0].ravel(), a, _given(defect.depth_m))
        azimuths = 2.0 * np.pi * np.arange(count) / count
        return contrast.dent_normals(n, x_axis, tilts, azimuths)[:, None]
    return n[:, None, None]


def offsets_of(defect: Defect, normals: np.ndarray, x_axis: np.ndarray, thetas: np.ndarray,
               resolution: Resolution = JUDGED, footprint_m: float = 0.0) -> np.ndarray:
    """(P, O, W, 3) [m] where each of normals_of's parts lies from the sample, in its tangent
    plane: a scratch's wall turned by +beta (normals_of's first; it faces away from +s, footprint's
    part 1) at s = +w / 4 along n x d(theta), the other at -w / 4; a dent's node at rho
    (dent_radii's) in direction u (its normal leans toward the centre, -u); a coating at the
    sample (zeros)."""
    n = np.asarray(normals, float).reshape(-1, 3)
    x, y = contrast.tangent_axes(n, x_axis)
    if defect.kind == "scratch":
        theta = np.asarray(thetas, float)[None, :, None]
        across = np.cos(theta) * y[:, None] - np.sin(theta) * x[:, None]            # n x d, (P, O, 3)
        quarter = 0.25 * _given(defect.width_m)
        return np.stack([quarter * across, -quarter * across], axis=2)
    if defect.kind == "dent":
        rho = dent_radii(_given(defect.radius_m), resolution.rings, footprint_m)[0].ravel()
        psi = 2.0 * np.pi * np.arange(resolution.azimuths) / resolution.azimuths
        u = np.cos(psi)[None, :, None] * x[:, None] + np.sin(psi)[None, :, None] * y[:, None]    # (P, A, 3)
        return (rho[None, :, None, None] * u[:, None]).reshape(len(n), 1, -1, 3)
    return np.zeros((len(n), 1, 1, 3))


def pixel_mean(defect: Defect, gray: np.ndarray, resolution: Resolution = JUDGED,
               footprint_m: float = 0.0) -> np.ndarray:
    """(..., W) grays of normals_of's parts (..., W') with a dent's nodes across each ring's pixel
    footprint averaged by dent_radii's weights (W = rings x azimuths); other kinds as they are."""
    if defect.kind != "dent":
        return gray
    weight = dent_radii(_given(defect.radius_m), resolution.rings, footprint_m)[1]
    nodes = gray.reshape(gray.shape[:-1] + weight.shape + (resolution.azimuths,))
    return np.einsum("...tqa,tq->...ta", nodes, weight).reshape(gray.shape[:-1] + (-1,))


def _given(value: float | None) -> float:
    if value is None:
        raise ValueError("the defect lacks a key its kind requires (the loader checks this)")
    return float(value)


def material_of(problem: Problem, defect: Defect) -> Material:
    """A coating's own material (as its file gives it: the loop's albedo scale is the part's);
    for a scratch or a dent the part's, as planned."""
    return defect.material if defect.kind == "coating" and defect.material is not None else problem.material


class _Inputs:
    """The kernel's inputs of some surface points with their normals and material: the spot's
    GrayInputs and the other lights' gray per exposure at full drive (K, N); `sample` (N,) the
    Problem's sample each point belongs to (its cast shadow), `shape` how the N points are laid
    out ((S, O, W))."""

    def __init__(self, problem: Problem, material: Material, points: np.ndarray, normals: np.ndarray,
                 sample: np.ndarray, shape: tuple[int, ...]) -> None:
        from kernels.gray import GrayInputs
        from cell.planning.lights import contribution
        task, scene = problem.task, problem.scene
        self.spot = GrayInputs(None, points, normals, scene.camera_position, task.lamp.power_w,
                               task.lamp.cone_angle_rad, material.table(), task.camera.sensor.camera_constant,
                               task.camera.sensor.pixel_area_m2, profile=task.lamp.profile)
        self.sample, self.shape = sample, shape
        counts = problem.lights.points
        self.lights = np.array([contribution(scene.shadow_mesh, points, normals, scene.T_cell_cam, light, material,
                                             task.camera.sensor, problem.band[1], count=counts[k]).unit_gray
                                for k, light in enumerate(task.lights)]).reshape(len(task.lights), len(points))

    def gray(self, problem: Problem, c: Candidates, cast: np.ndarray) -> np.ndarray:
        """(C, N) the gray at each candidate's lamp, drives and exposure; cast (C, P): the spot's
        light blocked by the part at the Problem's samples."""
        pivot = problem.task.lamp.rig.pivot_m
        u = c.drive[:, :1] * self.spot(c.position, rig.lamp_aim(pivot, c.position)).value * ~cast[:, self.sample]
        if len(self.lights):
            u = u + c.drive[:, 1:] @ self.lights
        return problem.black_level + (c.shutter / c.kappa**2)[:, None] * u


class _Parts:
    """A defect's parts at some samples: the defect's inputs (its normals and material where each
    part lies) and, where the parts lie off the samples (offsets_of), the good surface's there."""

    def __init__(self, problem: Problem, defect: Defect, index: np.ndarray, normals: np.ndarray,
                 offsets: np.ndarray) -> None:
        scene = problem.scene
        shape = normals.shape[:-1]
        points = (scene.points[index][:, None, None] + offsets).reshape(-1, 3)
        of_sample = np.broadcast_to(index[:, None, None], shape).reshape(-1)
        self.shape = shape
        self.defect = _Inputs(problem, material_of(problem, defect), points, normals.reshape(-1, 3), of_sample, shape)
        self.good = None if not np.any(offsets) else _Inputs(
            problem, problem.material, points,
            np.broadcast_to(scene.normals[index][:, None, None], normals.shape).reshape(-1, 3), of_sample, shape)

    def grays(self, problem: Problem, c: Candidates, cast: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """((C, N) the defect's gray, (C, N) the good surface's where the parts lie, None: at the
        samples themselves, the candidates' own gray)."""
        return (self.defect.gray(problem, c, cast),
                None if self.good is None else self.good.gray(problem, c, cast))


def defect_gray(problem: Problem, c: Candidates, defect: Defect, sample: np.ndarray | None = None,
                resolution: Resolution = JUDGED, thetas: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((C, S, O, W) the defect's gray at the samples `sample` (indices; None: all of the
    Problem's) for each orientation (O: `thetas`, (O,) or one row per sample (S, O), else the
    resolution's over the range) and wall or tilt (W), each part where it lies (offsets_of);
    (C, S, O, W) the good surface's gray at the same places; the orientations), a dent's rings each
    the mean over its pixel footprint (pixel_mean). The kernel inputs
    of all the samples are kept with the Problem; a large or partial set is evaluated in chunks of
    CHUNK normals and let go."""
    scene = problem.scene
    index = np.arange(len(scene.points)) if sample is None else np.asarray(sample, int)
    given = thetas is not None
    thetas = orientations(defect, resolution.step_rad) if thetas is None else np.asarray(thetas, float)
    cast = cast_shadows(problem, c)
    keep = sample is None and not given
    cache_key = (defect.key, resolution)
    made_of, kept = problem.kernels.defects.get(cache_key, (None, None)) if keep else (None, None)
    made = (problem.task, scene, problem.material)
    fp = footprint_of(problem)
    if kept is None or made_of is None or not all(a is b for a, b in zip(made_of, made)):
        x_axis = scene.frame[:, 0]
        if thetas.ndim == 2:                    # each sample its own orientations
            normals = np.concatenate([normals_of(defect, scene.normals[i:i + 1], x_axis, row, resolution, fp)
                                      for i, row in zip(index, thetas)])
            offsets = np.concatenate([offsets_of(defect, scene.normals[i:i + 1], x_axis, row, resolution, fp)
                                      for i, row in zip(index, thetas)])
        else:
            normals = normals_of(defect, scene.normals[index], x_axis, thetas, resolution, fp)
            offsets = np.broadcast_to(offsets_of(defect, scene.normals[index], x_axis, thetas, resolution, fp),
                                      normals.shape)
        shape = normals.shape[:-1]
        if not (keep and np.prod(shape) <= CHUNK):
            on, beside = _chunked(problem, c, defect, cast, index, normals, offsets)
            return (pixel_mean(defect, on, resolution, fp), pixel_mean(defect, beside, resolution, fp), thetas)
        kept = _Parts(problem, defect, index, normals, offsets)
        problem.kernels.defects[cache_key] = (made, kept)
    gray, good = kept.grays(problem, c, cast)
    full = (len(c.shutter),) + kept.shape
    return (pixel_mean(defect, gray.reshape(full), resolution, fp),
            pixel_mean(defect, _good_gray(c, index, good, full), resolution, fp), thetas)


def _chunked(problem: Problem, c: Candidates, defect: Defect, cast: np.ndarray, index: np.ndarray,
             normals: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """defect_gray's two grays over samples a few at a time (at most about CHUNK parts each),
    their kernel inputs let go after each."""
    per_sample = max(1, CHUNK // max(1, int(np.prod(normals.shape[1:-1]))))
    gray, good = [], []
    for i in range(0, len(index), per_sample):
        part = slice(i, i + per_sample)
        g, ok = _Parts(problem, defect, index[part], normals[part], offsets[part]).grays(problem, c, cast)
        shape = (len(c.shutter),) + normals[part].shape[:-1]
        gray.append(g.reshape(shape))
        good.append(_good_gray(c, index[part], ok, shape))
    return np.concatenate(gray, axis=1), np.concatenate(good, axis=1)


def _good_gray(c: Candidates, index: np.ndarray, good: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """The good surface's gray beside a defect's parts, shaped (C, S, O, W): `good` (_Parts.grays)
    where the parts lie off the samples, else the candidates' own gray at the samples."""
    return c.gray[:, index][:, :, None, None] + np.zeros(shape) if good is None else good.reshape(shape)


def cast_shadows(problem: Problem, c: Candidates) -> np.ndarray:
    """(C, P) whether the part blocks the spot's light at each sample (shadowed with the sample
    facing the spot): the defect's point is the sample's, so its shadow ray is too."""
    scene = problem.scene
    pivot = problem.task.lamp.rig.pivot_m
    shadowed = problem.gray_inputs(c.position, rig.lamp_aim(pivot, c.position)).shadowed
    facing = np.einsum("cpk,pk->cp", c.position[:, None] - scene.points[None], scene.normals) > 0.0
    return shadowed & facing


def noise_figures(problem: Problem) -> tuple[float, float, float]:
    """noise_of the Problem's task's sensor."""
    return noise_of(problem.task.camera.sensor)


def noise_of(s: Sensor) -> tuple[float, float, float]:
    """(K [gray/e-], sigma_d [e-], full scale [gray]) of a sensor: its datasheet keys, else the
    defaults the simulator assumes too (cell.physics.sensor); the run's measured CNR reads them too."""
    return (sensor_model.system_gain(s.bit_depth, s.system_gain_dn_per_e), sensor_model.dark_noise(s.dark_noise_e),
            float(sensor_model.saturation_level(s.bit_depth)))


def cnr_field(problem: Problem, c: Candidates, defect: Defect, sample: np.ndarray | None = None,
              resolution: Resolution = JUDGED, thetas: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """((C, S, O) the defect's CNR per sample and orientation, the best wall or tilt's; (C, S, O)
    the defect's gray there and the good surface's where that part lies; the orientations (O,))
    (defect_gray's arguments)."""
    index = np.arange(len(problem.scene.points)) if sample is None else np.asarray(sample, int)
    gray, good, thetas = defect_gray(problem, c, defect, None if sample is None else index, resolution, thetas)
    K, dark, full = noise_figures(problem)
    ratio = contrast.cnr(good, gray, problem.black_level, K, dark, full)
    best = np.argmax(ratio, axis=-1)[..., None]
    return (np.take_along_axis(ratio, best, axis=-1)[..., 0], np.take_along_axis(gray, best, axis=-1)[..., 0],
            np.take_along_axis(good, best, axis=-1)[..., 0], thetas)


def predicted_cnr(problem: Problem, c: Candidates) -> np.ndarray:
    """(C, D) each defect's predicted CNR at each candidate; a chosen shot's (C = 1) refined
    (judge)."""
    defects = problem.task.feature.defects
    if len(c.shutter) <= RANKED_ONLY:
        return np.array([[d.predicted_cnr for d in judge(problem, c.pick(k))]
                         for k in range(len(c.shutter))]).reshape(len(c.shutter), len(defects))
    out = [cnr_field(problem, c, d, resolution=RANKED)[0].reshape(len(c.shutter), -1).min(axis=-1) for d in defects]
    return np.array(out).reshape(len(defects), len(c.shutter)).T


def judge(problem: Problem, candidate: Candidates) -> tuple[DefectCnr, ...]:
    """Each defect of the Problem's feature on one candidate (Candidates of one): the worst CNR
    over the samples every ORIENTATION_STEP_RAD, then at the REFINED_SAMPLES worst samples every
    FINE_STEP_RAD (a scratch), the smaller kept, with where and at which orientation it is."""
    key = (candidate.position.tobytes(), candidate.shutter.tobytes(), candidate.kappa.tobytes(),
           candidate.drive.tobytes(), hash(candidate.gray.tobytes()))
    memo = problem.kernels.defects.setdefault("judged", {})
    if key not in memo:
        if len(memo) > 64:
            memo.clear()
        memo[key] = _judged(problem, candidate)
    return memo[key]


def _judged(problem: Problem, candidate: Candidates) -> tuple[DefectCnr, ...]:
    out = []
    for d in problem.task.feature.defects:
        ratio, gray, good, thetas = cnr_field(problem, candidate, d)
        s0, o0 = np.unravel_index(int(np.argmin(ratio[0])), ratio[0].shape)
        best = (float(ratio[0, s0, o0]), int(s0), float(thetas[o0]), float(gray[0, s0, o0]), float(good[0, s0, o0]))
        if d.kind == "scratch" and len(thetas) > 1:
            best = _refined(problem, candidate, d, ratio[0], thetas, best)
        value, at, theta, g, ok = best
        out.append(DefectCnr(d.name, d.kind, d.min_cnr, value, theta if d.kind == "scratch" else None,
                             np.array(problem.scene.points[at], float), ok, g))
    return tuple(out)


def _refined(problem: Problem, candidate: Candidates, d: Defect, ratio: np.ndarray, thetas: np.ndarray,
             best: tuple[float, int, float, float, float]) -> tuple[float, int, float, float, float]:
    """The worst (CNR, sample, orientation, defect gray, good gray) with the coarse grid's minima refined.
    Between grid orientations a sample's CNR can fall below its smallest grid value by at most the
    larger step to that value's neighbours (the CNR is V-shaped where a wall's contrast changes
    sign, else smooth): every sample whose bound so reaches below the best grid value (at most
    REFINED_SAMPLES, lowest bounds first) is judged every FINE_STEP_RAD within one grid step of its
    grid minimum, then the best few every FINE_STEP_RAD / 20 within one fine step."""
    lo, hi = d.orientation_rad
    wrap = hi - lo >= np.pi - 1e-12
    o = np.argmin(ratio, axis=-1)
    rows = np.arange(len(ratio))
    step_up = np.abs(np.take(ratio, o + 1, axis=-1, mode="wrap" if wrap else "clip")[rows, rows] - ratio[rows, o])
    step_down = np.abs(np.take(ratio, o - 1, axis=-1, mode="wrap" if wrap else "clip")[rows, rows] - ratio[rows, o])
    bound = ratio[rows, o] - np.maximum(step_up, step_down)
    order = np.argsort(bound)
    worst = order[bound[order] < best[0]][:REFINED_SAMPLES]
    if not len(worst):
        return best
    centre = thetas[o[worst]]
    grid_step = float(np.max(np.diff(thetas))) if len(thetas) > 1 else FINE_STEP_RAD
    for span, step in ((grid_step, FINE_STEP_RAD), (FINE_STEP_RAD, FINE_STEP_RAD / 20.0)):
        around = centre[:, None] + step * np.arange(-round(span / step), round(span / step) + 1)
        if not wrap:
            around = np.clip(around, lo, hi)
        fine, fine_gray, fine_good, _ = cnr_field(problem, candidate, d, worst, thetas=around)
        k = np.argmin(fine[0], axis=-1)
        if fine[0].min() < best[0]:
            fs, fo = np.unravel_index(int(np.argmin(fine[0])), fine[0].shape)
            best = (float(fine[0, fs, fo]), int(worst[fs]), float(around[fs, fo]), float(fine_gray[0, fs, fo]),
                    float(fine_good[0, fs, fo]))
        keep = np.argsort(fine[0].min(axis=-1))[:max(1, REFINED_SAMPLES // 4)]
        worst, centre = worst[keep], around[keep, k[keep]]
    return best


def contrast_rows(problem: Problem, position: np.ndarray, unit_gray: np.ndarray) -> ContrastRows:
    """The drive program's rows of the feature's defects (cell.planning.drives.ContrastRows) with
    the spot at `position` (3,) and unit_gray (1 + K, P) each channel's gray per exposure at full
    drive at the samples (the spot's first): per defect, sample and grid orientation (JUDGED) the
    part the spot alone shows best (the largest |contrast| over the root of the pixels' signal),
    its per-channel contrast and signal sum, its sign the spot's. The per-channel grays are
    defect_gray's at unit drives and exposure (the gray is linear in both)."""
    from cell.planning.drives import ContrastRows
    from cell.planning.evaluate import Candidates
    channels, samples = unit_gray.shape
    b = problem.black_level
    ones, none = np.ones(channels), np.zeros((channels, samples))
    unit = Candidates(np.tile(np.asarray(position, float).reshape(1, 3), (channels, 1)), b + unit_gray,
                      np.zeros((0, channels, samples)), none.astype(bool), none, none.astype(np.int8), ones, ones,
                      ones, np.eye(channels))
    K, dark, _ = noise_figures(problem)
    difference, total, sign, wanted = [], [], [], []
    for d in problem.task.feature.defects:
        gray, good, _ = defect_gray(problem, unit, d)
        diff = (gray - good).reshape(channels, -1, gray.shape[-1])          # (1 + K, S O, W)
        both = (gray + good - 2.0 * b).reshape(diff.shape)
        part = np.argmax(np.abs(diff[0]) / np.sqrt(np.maximum(both[0], 1e-300)), axis=-1)
        rows = np.arange(diff.shape[1])
        difference.append(diff[:, rows, part])
        total.append(both[:, rows, part])
        sign.append(np.where(diff[0, rows, part] < 0.0, -1.0, 1.0))
        wanted.append(np.full(len(rows), d.min_cnr))
    return ContrastRows(np.hstack(difference), np.hstack(total), np.concatenate(sign), np.concatenate(wanted), K, dark)


def place_of(problem: Problem, defect: Defect) -> int:
    """The Problem's sample nearest where the defect lies: its position_m (part frame), else the
    feature's centre (where the simulator renders it)."""
    scene = problem.scene
    at = scene.center if defect.position_m is None else geometry.apply(problem.task.frames.T_cell_part,
                                                                        np.asarray(defect.position_m, float))
    return int(np.argmin(np.linalg.norm(scene.points - at, axis=1)))


def direction_map(problem: Problem, candidate: Candidates, directions: np.ndarray) -> np.ndarray:
    """(D, V) each defect's signed CNR with the spot toward each of `directions` (V, 3) (cell-frame
    unit vectors from the feature's centre: a map's cells) at the candidate's distance from the
    centre, aimed at the rig's pivot, at the candidate's (Candidates of one) exposure and drives,
    where the defect lies (place_of): its CNR (cnr_field's, the best part's) at its worst grid
    orientation (what the plan certifies), signed as G_defect - G_good at the orientation where it
    shows best (+: the defect shows bright on the surface, as dark-field light shows a groove's
    wall; -: dark, as under bright-field light; a scratch at its worst orientation, its walls
    turned across the light, is a little darker under either). All directions in one bulk
    evaluation (the defects' kernel inputs at one sample, V candidates)."""
    from cell.planning.evaluate import Candidates, lit_by_all, unit_gray
    d = np.asarray(directions, float).reshape(-1, 3)
    centre, pivot = problem.scene.center, problem.task.lamp.rig.pivot_m
    positions = centre + float(np.linalg.norm(candidate.position[0] - centre)) * d
    drive = np.tile(candidate.drive[:1], (len(d), 1))
    u, shadowed, off_axis, dominant = lit_by_all(problem, unit_gray(problem, positions, rig.lamp_aim(pivot, positions)),
                                                 drive)
    gain = candidate.shutter[0] / candidate.kappa[0] ** 2
    c = Candidates(positions, problem.black_level + gain * u, np.zeros((0,) + u.shape), shadowed, off_axis, dominant,
                   np.full(len(d), candidate.shutter[0]), np.full(len(d), candidate.kappa[0]),
                   np.full(len(d), candidate.t_need[0]), drive)
    out = []
    for defect in problem.task.feature.defects:
        ratio, gray, good, _ = cnr_field(problem, c, defect, np.array([place_of(problem, defect)]))
        best = np.argmax(ratio[:, 0], axis=-1)[:, None]
        darker = np.take_along_axis(gray[:, 0] - good[:, 0], best, axis=-1)[:, 0] < 0.0
        out.append(np.where(darker, -1.0, 1.0) * ratio[:, 0].min(axis=-1))
    return np.array(out).reshape(len(problem.task.feature.defects), len(d))


def worse_of(a: tuple[DefectCnr, ...], b: tuple[DefectCnr, ...]) -> tuple[DefectCnr, ...]:
    """Per defect the lower CNR of two judgements (the search's samples, the dense patch)."""
    if not b:
        return a
    by_name = {d.name: d for d in b}
    return tuple(by_name[d.name] if d.name in by_name and by_name[d.name].predicted_cnr < d.predicted_cnr else d
                 for d in a)
