"""The lights besides the pan-tilt's spot as the kernels see them: each light's emitting surface
sampled into emitter points (cell-frame position, unit axis, an equal share of its power, its
profile), and each light's gray per exposure at full drive at every feature sample, the sum over
its points, each with its own shadow ray (the bulk kernel of kernels.gray, a point being a lamp).

Extended lights are integrated by a midpoint rule over equal parts of their surface (a ring's
arc, a bar's length, an area's cells, a dome's zones of equal area), and the number of points is
doubled until doubling changes no sample's gray by more than INTEGRATION_GRAY gray levels at any
exposure the plan can choose (contributions): below saturation a light's gray at a sample is at
most the band's top, so a change of INTEGRATION_GRAY / top of the light's brightest sample is at
most INTEGRATION_GRAY levels. The change on doubling bounds the coarser count's error whenever
doubling at least halves the error, which a midpoint rule does on a smooth integrand (it quarters
it); the finer count's value is kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry

if TYPE_CHECKING:
    from kernels.mesh import WarpMesh
    from cell.physics.material import Material
    from cell.planning.scene import Scene
    from cell.task.types import Light, Sensor, Task

INTEGRATION_GRAY = 0.1          # gray levels: the largest integration error of a light's gray
START_POINTS = {"spot": 1, "ring": 16, "bar": 8, "area": 16, "dome": 64, "coaxial": 16}
MAX_POINTS = 4096               # per light: a dome at 4096 points costs as much as a search's 1000 lamps x 4
# a Lambertian emitter's profile, cos(theta), tabulated at 1 deg: linear between the angles, its
# largest relative error (h^2 / 8, h = 1 deg in radians) 4e-5, a hundredth of a gray level at 255
LAMBERTIAN_DEG = np.arange(0.0, 91.0)
LAMBERTIAN = np.column_stack([np.radians(LAMBERTIAN_DEG),
                              np.where(LAMBERTIAN_DEG < 90.0, np.cos(np.radians(LAMBERTIAN_DEG)), 0.0)])
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


@dataclass(frozen=True)
class Emitters:
    """A light as N point emitters: positions and unit axes (N, 3), cell frame, each emitting
    power_w (the light's power over N) by `profile` (M, 2) [off_axis_rad, relative] (None: the
    spot's ideal cone of cone_angle_rad)."""

    position: np.ndarray
    axis: np.ndarray
    power_w: float
    profile: np.ndarray | None
    cone_angle_rad: float


def pose(light: Light, T_cell_cam: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, unit axis, unit `along`) of a light in the cell frame: a fixed light's own, a
    flange light's carried by the camera pose T_cell_cam (its keys are in the camera frame)."""
    if light.mount == "fixed":
        return light.position_m, light.axis, light.along
    T = np.asarray(T_cell_cam, float)
    return geometry.apply(T, light.position_m), geometry.rotate(T, light.axis), geometry.rotate(T, light.along)


def turned(light: Light, angle_rad: float, directions: int) -> list[Light]:
    """The light with its aim turned by angle_rad about its centre in `directions` directions
    evenly around its axis (its pose error: a fixed light's bracket, a flange light's mount), its
    `along` kept perpendicular to the turned axis; its emitting surface turns with it."""
    from dataclasses import replace
    across = np.cross(light.axis, light.along)
    out = []
    for a in 2.0 * np.pi * np.arange(directions) / directions:
        axis = np.cos(angle_rad) * light.axis + np.sin(angle_rad) * (np.cos(a) * light.along + np.sin(a) * across)
        along = geometry.unit(light.along - (light.along @ axis) * axis)
        out.append(replace(light, axis=geometry.unit(axis), along=along))
    return out


def _disk(n: int, radius: float) -> np.ndarray:
    """(n, 2) centres of n equal-area parts of a disk: Vogel's sunflower, r = R sqrt((i + 1/2) / n)."""
    i = np.arange(n)
    r = radius * np.sqrt((i + 0.5) / n)
    return np.column_stack([r * np.cos(i * GOLDEN_ANGLE), r * np.sin(i * GOLDEN_ANGLE)])


def _rectangle(n: int, width: float, height: float) -> np.ndarray:
    """(nx ny, 2) cell centres of an nx x ny grid over a width x height rectangle, cells as near
    square as n allows (nx ny >= n)."""
    nx = max(1, int(round(np.sqrt(n * width / height))))
    ny = max(1, int(np.ceil(n / nx)))
    x = (np.arange(nx) + 0.5) / nx - 0.5
    y = (np.arange(ny) + 0.5) / ny - 0.5
    X, Y = np.meshgrid(width * x, height * y, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


def emitters(light: Light, T_cell_cam: ArrayLike, n: int) -> Emitters:
    """The light as about n point emitters (a spot is one; a rectangle rounds n to its grid):
    - ring: n LEDs evenly on the circle of radius_m about the axis, each tilted by tilt_rad from
      the axis toward it (0: parallel to the axis);
    - bar: n points at the midpoints of equal parts of its length along `along`, all along the axis;
    - area, coaxial: the centres of equal parts of a rectangle (size_m, width along `along`) or a
      disk (radius_m) across the axis at the centre, all along the axis;
    - dome: the hemisphere of radius_m whose pole (the camera's hole, hole_radius_m) is at the
      centre and which opens along the axis, in zones of equal area (cos of the angle from the pole
      evenly spaced, azimuths by the golden angle), each emitting toward the sphere's centre.
    Each point has an equal share of power_w (equal parts of the surface) and the light's profile,
    by default a Lambertian emitter's (a spot's: eq. (11)'s cone)."""
    centre, axis, along = pose(light, T_cell_cam)
    across = np.cross(axis, along)
    profile = light.profile if light.profile is not None or light.type == "spot" else LAMBERTIAN
    cone = light.cone_angle_rad if light.cone_angle_rad is not None else np.pi
    if light.type == "spot":
        positions, axes = centre[None], axis[None]
    elif light.type == "ring":
        phi = 2.0 * np.pi * (np.arange(n) + 0.5) / n
        radial = np.cos(phi)[:, None] * along + np.sin(phi)[:, None] * across
        positions = centre + _required(light.radius_m) * radial
        axes = np.cos(light.tilt_rad) * axis - np.sin(light.tilt_rad) * radial
    elif light.type == "bar":
        s = _required(light.length_m) * ((np.arange(n) + 0.5) / n - 0.5)
        positions, axes = centre + s[:, None] * along, np.broadcast_to(axis, (n, 3))
    elif light.type in ("area", "coaxial"):
        uv = _disk(n, _required(light.radius_m)) if light.size_m is None else _rectangle(n, *light.size_m)
        positions = centre + uv[:, :1] * along + uv[:, 1:] * across
        axes = np.broadcast_to(axis, positions.shape)
    elif light.type == "dome":
        radius = _required(light.radius_m)
        top = 1.0 if light.hole_radius_m is None else np.sqrt(1.0 - (light.hole_radius_m / radius) ** 2)
        cos_polar = top * (1.0 - (np.arange(n) + 0.5) / n)     # from the pole's rim (top) to the rim (0)
        sin_polar = np.sqrt(1.0 - cos_polar**2)
        phi = np.arange(n) * GOLDEN_ANGLE
        sphere = centre + radius * axis
        positions = sphere + radius * (-cos_polar[:, None] * axis + sin_polar[:, None] * (
            np.cos(phi)[:, None] * along + np.sin(phi)[:, None] * across))
        axes = geometry.unit(sphere - positions)
    else:
        raise ValueError(f"unknown light type {light.type!r}")
    count = len(positions)
    return Emitters(np.ascontiguousarray(positions, float), np.ascontiguousarray(axes, float),
                    light.power_w / count, profile, float(cone))


def _required(value: float | None) -> float:
    """A shape key the loader requires for this type (cell.task.loader.SHAPES)."""
    if value is None:
        raise ValueError("the light lacks a shape key its type requires (the loader checks this)")
    return float(value)


@dataclass(frozen=True)
class Contribution:
    """One light's share at every feature sample at full drive: unit_gray (P,), gray per exposure
    [gray / (s / kappa^2)], the sum over its emitter points; unlit (P,): no point reaches the
    sample (behind it, shadowed, or off every point's profile); dominant (P,): the BRDF term of
    the point that adds the most (brdf's DIFFUSE/LOBE/SPIKE; OCCLUDED where the camera or every
    point is behind the surface); points: how many emitter points it took."""

    unit_gray: np.ndarray
    unlit: np.ndarray
    dominant: np.ndarray
    points: int


def contribution(mesh: WarpMesh | None, points: ArrayLike, normals: ArrayLike, T_cell_cam: ArrayLike,
                 light: Light, material: Material, sensor: Sensor, gray_top: float,
                 count: int | None = None) -> Contribution:
    """One light's Contribution at the samples seen from the camera at T_cell_cam, with count
    emitter points, or (None) as many as the module's rule finds for gray_top, the band's top."""
    return contributions(mesh, points, normals, T_cell_cam, (light,), material, sensor, gray_top, count)[0]


BATCH_EVALUATIONS = 1 << 21     # emitter points x samples per kernel call: its outputs about 38 MB


def contributions(mesh: WarpMesh | None, points: ArrayLike, normals: ArrayLike, T_cell_cam: ArrayLike,
                  made: Sequence[Light], material: Material, sensor: Sensor, gray_top: float,
                  count: int | None = None) -> list[Contribution]:
    """Each light's Contribution (as `contribution` finds one's), the lights evaluated together: at
    each doubling the emitter points of every light still doubling go to the kernel in one call per
    profile (up to BATCH_EVALUATIONS each), each point with its own power, on one kernels.gray
    input per profile (the samples' surfaces and free cones found once, not once per light)."""
    from kernels.gray import GrayInputs
    T = np.asarray(T_cell_cam, float)
    points = np.asarray(points, float).reshape(-1, 3)
    inputs: dict[tuple[bytes | None, float], GrayInputs] = {}

    def evaluate(wanted: dict[int, int]) -> dict[int, Contribution]:
        """{light index: its Contribution at n points} of {light index: n}."""
        groups: dict[tuple[bytes | None, float], list[tuple[int, Emitters]]] = {}
        for k, n in wanted.items():
            e = emitters(made[k], T, n)
            key = (None if e.profile is None else np.asarray(e.profile, float).tobytes(), e.cone_angle_rad)
            groups.setdefault(key, []).append((k, e))
        found = {}
        for key, members in groups.items():
            if key not in inputs:
                e = members[0][1]
                inputs[key] = GrayInputs(mesh, points, normals, T[:3, 3], e.power_w, e.cone_angle_rad,
                                         material.table(), sensor.camera_constant, sensor.pixel_area_m2,
                                         profile=e.profile)
            for batch in _batches(members, max(1, BATCH_EVALUATIONS // max(1, len(points)))):
                out = inputs[key](np.vstack([e.position for _, e in batch]), np.vstack([e.axis for _, e in batch]),
                                  np.concatenate([np.full(len(e.position), e.power_w) for _, e in batch]))
                start = 0
                for k, e in batch:
                    rows = slice(start, start + len(e.position))
                    found[k] = _summed(out.value[rows], out.dominant[rows], len(points))
                    start = rows.stop
        return found

    if count is not None:
        fixed = evaluate({k: 1 if light.type == "spot" else int(count or 1) for k, light in enumerate(made)})
        return [fixed[k] for k in range(len(made))]
    start = {k: 1 if light.type == "spot" else START_POINTS[light.type] for k, light in enumerate(made)}
    coarse = evaluate(start)
    final = {k: coarse[k] for k, light in enumerate(made) if light.type == "spot"}
    n = {k: start[k] for k in coarse if k not in final}
    while n:
        for k in [k for k in n if 2 * n[k] > MAX_POINTS]:       # as fine as it may get: the finest kept
            final[k] = coarse[k]
            del n[k]
        n = {k: 2 * m for k, m in n.items()}
        fine = evaluate(n)
        for k in list(n):
            if converged(coarse[k], fine[k], gray_top):
                final[k] = fine[k]
                del n[k]
            else:
                coarse[k] = fine[k]
    return [final[k] for k in range(len(made))]


def _batches(members: list[tuple[int, Emitters]], lamps: int) -> list[list[tuple[int, Emitters]]]:
    """Consecutive lights whose points together stay within `lamps` (a light more alone)."""
    out: list[list[tuple[int, Emitters]]] = [[]]
    size = 0
    for member in members:
        if out[-1] and size + len(member[1].position) > lamps:
            out.append([])
            size = 0
        out[-1].append(member)
        size += len(member[1].position)
    return out


def _summed(value: np.ndarray, dominant: np.ndarray, samples: int) -> Contribution:
    """A light's Contribution from its points' rows (N, P) of the kernel's value and dominant term."""
    lit = value > 0.0
    strongest = np.argmax(value, axis=0) if len(value) else np.zeros(samples, int)
    return Contribution(value.sum(axis=0), np.logical_not(lit.any(axis=0)),
                        np.take_along_axis(dominant, strongest[None], axis=0)[0], len(value))


def converged(coarse: Contribution, fine: Contribution, gray_top: float) -> bool:
    """The module's rule: doubling the points changed no sample by more than INTEGRATION_GRAY /
    gray_top of the finer one's brightest."""
    top = float(fine.unit_gray.max(initial=0.0))
    return bool(np.max(np.abs(fine.unit_gray - coarse.unit_gray), initial=0.0) <= INTEGRATION_GRAY / gray_top * top)


def emitter_counts(task: Task, scene: Scene, T_cell_cam: ArrayLike) -> tuple[int, ...]:
    """How many emitter points image each of task.lights: the module's rule at the scene's
    feature samples seen from T_cell_cam, the band's top the highest feature's, so an image
    integrates each light as finely as the plan did (the simulator's and registration's)."""
    if not task.lights:
        return ()
    top = max(feature.requirements.gray_band[1] for feature in task.features)
    found = contributions(scene.shadow_mesh, scene.points, scene.normals, T_cell_cam, task.lights, task.part.material,
                          task.camera.sensor, top)
    return tuple(c.points for c in found)


def drive_level(channel: int | None, drives: Mapping[int, float] | None) -> float:
    """A light's drive level in an image: its channel's in `drives` ({channel: level 0..1}, the
    controller's read-back; a channel not in them is off), 1 without a channel or without drives."""
    if channel is None or drives is None:
        return 1.0
    return float(drives.get(channel, 0.0))


def rendered(mesh: WarpMesh, origin: ArrayLike, ray_dirs: np.ndarray, T_cell_cam: ArrayLike, made: Sequence[Light],
             counts: Sequence[int], factors: Sequence[float], table: np.ndarray, camera_constant: float,
             pixel_area_m2: float, shadows: bool, shading_normals: np.ndarray | None = None,
             part_faces: int | None = None) -> np.ndarray:
    """(N,) sum_k f_k G_k: the value (c A_pixel Phi R / 8 per ray, kernels.render) of each light k
    as counts[k] emitter points (`emitters`, a flange light carried by T_cell_cam), each with its
    own shadow ray, times factors[k] (its drive, in the simulator times its channel's true power);
    a light at factor 0 is not rendered. The simulator's image and registration's model both;
    shading_normals (N, 3): each hit shaded with its own normal, part_faces: the mesh's faces
    from there on occluders (kernels.render's)."""
    from kernels.render import render
    value = np.zeros(len(ray_dirs))
    for light, n, factor in zip(made, counts, factors):
        if factor > 0.0:
            e = emitters(light, T_cell_cam, n)
            value += factor * render(mesh, origin, ray_dirs, e.position, e.axis, e.power_w, e.cone_angle_rad, table,
                                     camera_constant, pixel_area_m2, shadows=shadows, profile=e.profile,
                                     shading_normals=shading_normals, part_faces=part_faces).value
    return value
