"""An independent dense check of a plan's shot: the feature patch's true surface, the mesh within
feature.radius_m of the feature centre (docs/formats.md), sampled by area at thousands of points
(not the planner's feature_disk samples), each point shaded with cell.physics's NumPy equations
and cell.physics.reference's brute-force ray casting (nothing computed by Warp, nothing of the
planner's search).

Per point p with facet normal n, lamp L aiming at the rig's pivot, camera C (eq. 6-7, 10, 11, 17):
  G = c * A_pixel * Phi(|L - p|, off-axis) * R(n, s, v) / (8 kappa^2) * t, clipped at 2^bits - 1,
  0 where the lamp is behind the facet or the ray p -> L hits the part (shadow);
  in focus when near(u) <= (p - C) . z_cam <= far(u), u the shot's focus (sec. 4.3, thin lens).

`python tests/dense.py` plans the example and curved tasks and prints each plan's predicted gray
beside the dense check's.
"""
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cell.core import geometry
from cell.physics import brdf, depth_of_field as dof, radiometry, reference

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = {name: ROOT / "tasks" / f"{name}.yaml" for name in ("hinge", "conrod")}
CURVED_TASKS = {p.stem: p for p in sorted((ROOT / "tests" / "tasks").glob("*.yaml"))}


OFFSET_M = 1e-5             # shadow and view rays leave 10 um above the facet (as the kernels')


@dataclass(frozen=True)
class DenseCheck:
    """A shot evaluated at points of the patch: gray (clipped), and per point whether it is
    saturated, shadowed from the lamp, unseen by the camera, and its depth along the optical axis
    against the depth of field's limits [m]."""

    band: tuple
    points: np.ndarray       # (N, 3) cell frame [m]
    radius_m: np.ndarray     # (N,) distance from the feature centre
    gray: np.ndarray         # (N,) eq. (10) clipped to [0, 2^bits - 1]
    saturated: np.ndarray    # (N,) bool: unclipped gray >= 2^bits - 1
    shadowed: np.ndarray     # (N,) bool: lamp behind the facet or the ray to it blocked
    unseen: np.ndarray       # (N,) bool: camera behind the facet or the ray to it blocked
    depth_m: np.ndarray      # (N,) (p - C) . z_cam
    near_m: float
    far_m: float

    @property
    def in_focus(self):
        return (self.depth_m >= self.near_m) & (self.depth_m <= self.far_m)

    @property
    def in_band(self):
        return (self.gray >= self.band[0]) & (self.gray <= self.band[1])

    def summary(self):
        """Counts and extremes, for reports and failure messages."""
        return {"points": len(self.gray), "min_gray": float(self.gray.min()), "max_gray": float(self.gray.max()),
                "in_band": float(self.in_band.mean()), "out_of_focus": int(np.sum(~self.in_focus)),
                "shadowed": int(self.shadowed.sum()), "unseen": int(self.unseen.sum()),
                "saturated": int(self.saturated.sum()),
                "depth_mm": [1e3 * float(self.depth_m.min()), 1e3 * float(self.depth_m.max())],
                "focus_limits_mm": [1e3 * self.near_m, 1e3 * self.far_m]}


def cell_mesh(task):
    """The part's mesh in the cell frame (metres), as the task loaded it."""
    mesh = task.part.mesh.copy()
    mesh.apply_transform(task.frames.T_cell_part)
    return mesh


def patch_surface(task, count=6000, seed=0, radius_m=None):
    """(points (count, 3), facet normals (count, 3)) uniform by area over the surface within
    radius_m (default the feature's) of the feature centre, cell frame: the facets reaching into
    that ball and connected to the centre's facet through such facets (a thin wall's far side,
    also within the ball, is not the patch), sampled by area, points outside the ball rejected."""
    mesh = cell_mesh(task)
    radius = task.feature.radius_m if radius_m is None else radius_m
    center = geometry.apply(task.frames.T_cell_part, task.feature.center_m)
    tri = mesh.triangles
    gap = np.linalg.norm(trimesh.triangles.closest_point(tri, np.broadcast_to(center, (len(tri), 3))) - center, axis=1)
    near = gap <= radius
    pairs = mesh.face_adjacency[near[mesh.face_adjacency].all(axis=1)]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(tri),) * 2)
    _, label = connected_components(graph, directed=False)
    faces = np.flatnonzero(near & (label == label[np.argmin(gap)]))
    area = mesh.area_faces[faces]
    rng = np.random.default_rng(seed)
    points, face_of = np.zeros((0, 3)), np.zeros(0, dtype=int)
    draws = 4 * count
    while len(points) < count:
        f = faces[rng.choice(len(faces), size=draws, p=area / area.sum())]
        r1, r2 = np.sqrt(rng.random(draws)), rng.random(draws)
        t = tri[f]
        p = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
        keep = np.linalg.norm(p - center, axis=1) <= radius
        points, face_of = np.vstack([points, p[keep]]), np.concatenate([face_of, f[keep]])
        draws = int(min(4e6, 2 * (count - len(points)) * draws / max(keep.sum(), 1)) + 1)
    return points[:count], mesh.face_normals[face_of[:count]]


def _blocked(mesh, points, normals, target):
    """bool (N,): the ray from each point (lifted OFFSET_M along its normal) to `target` hits the
    mesh before it. Only facets whose bounding sphere comes within the points' spread of the
    segment from their mean to the target are cast against: every ray lies that close to it."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    reach = np.linalg.norm(points - points.mean(axis=0), axis=1).max() + 2 * OFFSET_M
    tri = mesh.triangles
    mid = tri.mean(axis=1)
    size = np.linalg.norm(tri - mid[:, None], axis=2).max(axis=1)
    center = points.mean(axis=0)
    ab = target - center
    t = np.clip((mid - center) @ ab / (ab @ ab), 0.0, 1.0)
    keep = np.linalg.norm(mid - (center + t[:, None] * ab), axis=1) <= reach + size
    if not keep.any():
        return np.zeros(len(points), dtype=bool)
    origins = points + OFFSET_M * normals
    to = target - origins
    dist = np.linalg.norm(to, axis=1)
    culled = SimpleNamespace(vertices=mesh.vertices, faces=mesh.faces[keep])
    return reference.ray_hits_any(culled, origins, to / dist[:, None], dist)


def shade(task, shot, points, normals, center=None):
    """DenseCheck of a shot (cell.planning.plan.Shot: lamp position, camera pose, exposure) at the given
    surface points and unit normals, cell frame; center (default the feature's) for radius_m."""
    points, normals = np.asarray(points, float), geometry.unit(np.asarray(normals, float))
    mesh = cell_mesh(task)
    if center is None:
        center = geometry.apply(task.frames.T_cell_part, task.feature.center_m)
    sensor, lens, lamp = task.camera.sensor, task.camera.lens, task.lamp
    e = shot.exposure
    camera = shot.T_cell_cam[:3, 3]
    to_lamp = shot.lamp_position - points
    d = np.linalg.norm(to_lamp, axis=1)
    s, v = to_lamp / d[:, None], geometry.unit(camera - points)
    shadowed = np.sum(normals * s, axis=1) <= 0.0
    shadowed[~shadowed] = _blocked(mesh, points[~shadowed], normals[~shadowed], shot.lamp_position)
    unseen = np.sum(normals * v, axis=1) <= 0.0
    unseen[~unseen] = _blocked(mesh, points[~unseen], normals[~unseen], camera)
    aim = geometry.unit(lamp.rig.pivot_m - shot.lamp_position)         # the rig aims at its pivot
    off_axis = np.arccos(np.clip(-s @ aim, -1.0, 1.0))
    irradiance = radiometry.cone_irradiance(lamp.power_w, lamp.cone_angle_rad, d, off_axis, lamp.profile)
    R = brdf.reflectance_vectors(normals, s, v, task.part.material)
    power = radiometry.pixel_power(sensor.pixel_area_m2, np.where(shadowed, 0.0, irradiance), R, e.f_number)
    raw = radiometry.gray_value(sensor.camera_constant, power, e.shutter_s)
    top = 2.0**sensor.bit_depth - 1.0
    f, coc = lens.focal_length_m, lens.circle_of_confusion_m
    return DenseCheck(band=tuple(map(float, task.requirements.gray_band)), points=points,
                      radius_m=np.linalg.norm(points - center, axis=1), gray=np.minimum(raw, top),
                      saturated=raw >= top, shadowed=shadowed, unseen=unseen,
                      depth_m=(points - camera) @ shot.T_cell_cam[:3, 2],
                      near_m=float(dof.near_limit(e.focus_m, f, e.f_number, coc)),
                      far_m=float(dof.far_limit(e.focus_m, f, e.f_number, coc)))


def dense_check(task, shot, count=6000, seed=0, radius_m=None):
    """shade() at `count` points spread by area over the patch's true surface (patch_surface)."""
    return shade(task, shot, *patch_surface(task, count, seed, radius_m))


def acceptance_failures(plan, check):
    """What breaks "a plan reported feasible stays in band on the dense check, every point of the
    patch lit, seen and in focus": [] when it holds (an infeasible plan promises nothing)."""
    if not plan.feasible:
        return []
    s, low, high = check.summary(), *check.band
    failures = []
    if s["in_band"] < 1.0:
        failures.append(f"gray {s['min_gray']:.1f}-{s['max_gray']:.1f} leaves the band {low:g}-{high:g} at "
                        f"{int(np.sum(~check.in_band))} of {s['points']} points ({s['saturated']} saturated)")
    if s["out_of_focus"]:
        failures.append(f"{s['out_of_focus']} of {s['points']} points out of focus (depth "
                        f"{s['depth_mm'][0]:.2f}-{s['depth_mm'][1]:.2f} mm, limits {1e3 * check.near_m:.2f}-"
                        f"{1e3 * check.far_m:.2f} mm)")
    for key in ("shadowed", "unseen"):
        if s[key]:
            failures.append(f"{s[key]} of {s['points']} points {key}")
    return failures


def disk_footprint(task, points, normals):
    """bool (N,): the points a tangent disk of feature.radius_m, projected onto the surface along
    the normals, reaches: p's normal line meets the feature's tangent plane within the radius.
    On a convex patch that is less than the surface within the radius (the planner's samples are
    such a projection); for the report only, not for the acceptance."""
    c = geometry.apply(task.frames.T_cell_part, task.feature.center_m)
    n0 = geometry.unit(geometry.rotate(task.frames.T_cell_part, task.feature.normal))
    t = ((c - points) @ n0) / (normals @ n0)
    return np.linalg.norm(points + t[:, None] * normals - c, axis=1) <= task.feature.radius_m * (1 + 1e-9)


def main():
    """Plan every example and curved task; print predicted and dense gray, focus and the verdict."""
    import time

    from cell.planning import one_shot
    from cell.task.loader import load_task
    print("beyond: dense points beyond the projected tangent disk the planner samples; inside: their gray")
    print(f"{'task':24} {'feasible':8} {'predicted':>13} {'dense':>13} {'beyond':>6} {'inside':>13} "
          f"{'in band':>8} {'unfocused':>9} {'shadow':>6} {'sat':>4}  acceptance")
    for name, path in {**EXAMPLES, **CURVED_TASKS}.items():
        task = load_task(path)
        t0 = time.perf_counter()
        plan = one_shot.plan(task)
        t1 = time.perf_counter()
        check = dense_check(task, plan.shot)
        t2 = time.perf_counter()
        s, g = check.summary(), plan.shot.gray
        points, normals = patch_surface(task)
        inside = disk_footprint(task, points, normals)
        inner = check.gray[inside]
        failures = acceptance_failures(plan, check)
        print(f"{name:24} {str(plan.feasible):8} {g.min():6.1f}-{g.max():6.1f} {s['min_gray']:6.1f}-"
              f"{s['max_gray']:6.1f} {np.sum(~inside):6d} {inner.min():6.1f}-{inner.max():6.1f} {s['in_band']:8.2%} "
              f"{s['out_of_focus']:9d} {s['shadowed']:6d} {s['saturated']:4d}  {'; '.join(failures) or 'holds'}  "
              f"[plan {t1 - t0:.1f} s, dense {t2 - t1:.1f} s]")
        if not plan.feasible:
            print(f"{'':24} {plan.message}")


if __name__ == "__main__":
    main()
