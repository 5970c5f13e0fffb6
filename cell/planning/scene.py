"""The task's geometry in the cell frame: part mesh, feature samples, camera pose.

Shared by the planner, the simulated camera and the closed loop so they all see one scene. A
Scene is plain arrays (it pickles: a plan made in a worker process carries it back); the Warp
BVH of its mesh is the process's own (kernels.mesh.shared_mesh, keyed by the geometry's digest).
Rays that light or see the part (shadow rays, the camera's view, the visibility maps, a
rendered pixel) are cast against its shadow mesh: the part and the fixed lights' housings
(cell.planning.occluders), the part's faces first; what needs the part alone (its samples, the
certificate's closest points) uses the part's mesh.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.core import geometry
from cell.core.errors import TaskError
from kernels.recent import Kept
from cell.planning.occluders import Housing, housings
from kernels.mesh import shared_mesh
from kernels.proximity import closest_points

if TYPE_CHECKING:
    from kernels.mesh import WarpMesh
    from cell.task.types import Task

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
PATCH_ITERATIONS = 6        # pushes of the disk's points out onto a curved patch
PATCH_TOLERANCE = 1e-4      # of the radius: where a sample lands at its distance
PATCH_LEAVES = 0.05         # of the radius: a sample this far from its distance runs off the patch
PATCH_PUSH_MAX = 3.0        # a guess goes at most this many times its distance out


def look_at(position: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """T_cell_cam for a camera at `position` looking at `target` (OpenCV axes: z forward,
    x right, y down in the image): (4, 4), or (N, 4, 4) for rows of positions and targets
    (N, 3), each the very one it gets alone (the planner's view spheres place thousands)."""
    position = np.asarray(position, dtype=float)
    z = geometry.unit(np.asarray(target, dtype=float) - position)
    up = np.broadcast_to(np.asarray(up, dtype=float), z.shape)
    along = (up[..., None, :] @ z[..., :, None])[..., 0, 0]        # each a 1-D np.dot's arithmetic
    up = np.where((np.abs(along) > 0.99)[..., None], np.array([0.0, 1.0, 0.0]), up)
    x = geometry.unit(np.cross(z, up))
    y = np.cross(z, x)
    T = np.zeros(z.shape[:-1] + (4, 4))
    T[..., :3, :3] = np.stack([x, y, z], axis=-1)
    T[..., :3, 3] = position
    T[..., 3, 3] = 1.0
    return T


@lru_cache(maxsize=64)
def feature_disk(n: int, radius: float) -> np.ndarray:
    """n points over a disk, shape (n, 2): round(sqrt(pi n)) evenly on its rim, the rest spread
    over the inside (Vogel's sunflower). The rim is sampled on purpose: gray varies smoothly over
    a patch, so its extremes, which decide "every point in band", lie mostly on the edge.
    Made once per (n, radius) and read-only (a part's scenes ask the same disks again)."""
    rim = int(round(np.sqrt(np.pi * n))) if n >= 8 else 0      # fewer: the sunflower alone
    a = 2.0 * np.pi * np.arange(rim) / rim
    i = np.arange(n - rim)
    r = radius * np.sqrt((i + 0.5) / (n - rim + (rim > 0)))    # inside the rim when there is one
    out = np.vstack([np.column_stack([radius * np.cos(a), radius * np.sin(a)]),
                     np.column_stack([r * np.cos(i * GOLDEN_ANGLE), r * np.sin(i * GOLDEN_ANGLE)])])
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class Scene:
    vertices: np.ndarray         # (V, 3) part mesh in the cell frame [m]
    faces: np.ndarray            # (F, 3) vertex indices
    mesh_key: str                # digest of vertices and faces: names the geometry in caches
    center: np.ndarray           # feature centre, cell frame
    normal: np.ndarray           # feature normal, cell frame
    frame: np.ndarray            # 3x3, columns x, y, z of the feature frame (z = normal)
    points: np.ndarray           # (P, 3) feature samples on the surface
    normals: np.ndarray          # (P, 3) surface normals at the samples
    T_cell_cam: np.ndarray       # the camera pose the planner assumes
    housings: tuple[Housing, ...] = ()     # the fixed lights' housings, cell frame (they do not move)

    def __post_init__(self) -> None:
        """Its arrays read-only, however it was made (built, replaced by the certificate)."""
        _read_only(self.__dict__.values())

    def __getstate__(self):
        """Its fields (not the depths it keeps: sample_depths)."""
        return {k: v for k, v in self.__dict__.items() if k != "_depths"}

    def __setstate__(self, state):
        """Unpickled (a plan from a worker process): its arrays read-only again, as built."""
        self.__dict__.update(state)
        _read_only(state.values())

    @property
    def camera_position(self) -> np.ndarray:
        return self.T_cell_cam[:3, 3]

    @property
    def warp_mesh(self) -> WarpMesh:
        """This process's Warp BVH of the mesh (built on first use)."""
        return shared_mesh(self.mesh_key, self.vertices, self.faces)

    @property
    def shadow_mesh(self) -> WarpMesh:
        """This process's Warp BVH of the part and the housings, the part's faces first (its
        len(faces) are the part's: kernels.render's part_faces); the part's own without housings."""
        return self.casting()

    def casting(self, but: str | None = None) -> WarpMesh:
        """The shadow mesh without the housing of the light named `but`: a light turned by its
        pose error (evaluate's light tolerance) turns its housing with it, which never shadows its
        own emitter points, so its light is cast against the part and the others' housings."""
        kept = [h for h in self.housings if h.name != but]
        if not kept:
            return self.warp_mesh
        offsets = np.cumsum([len(self.vertices)] + [len(h.vertices) for h in kept])
        faces = np.vstack([self.faces] + [h.faces + o for h, o in zip(kept, offsets)])
        vertices = np.vstack([self.vertices] + [h.vertices for h in kept])
        key = hashlib.blake2b(self.mesh_key.encode() + vertices[len(self.vertices):].tobytes()
                              + faces[len(self.faces):].tobytes(), digest_size=16).hexdigest()
        return shared_mesh(key, vertices, faces)

    def sample_depths(self) -> np.ndarray:
        """Distances camera -> samples along the optical axis [m], read-only, computed once (a
        certificate's focus, depth of field, its sentence and its picks each read them)."""
        depths = self.__dict__.get("_depths")
        if depths is None:
            depths = geometry.by_component(np.subtract, self.points, self.camera_position) @ self.T_cell_cam[:3, 2]
            depths.flags.writeable = False
            object.__setattr__(self, "_depths", depths)
        return depths


def build_scene(task: Task, samples: int | None = None, extra: np.ndarray | None = None,
                T_cell_cam: ArrayLike | None = None) -> Scene:
    """Scene of a one-feature task: mesh and feature in the cell frame, `samples` points over the
    feature patch (default: the task's) and the `extra` cell-frame points (the certificate's
    worst), on the surface; the camera at T_cell_cam (a shot's), by default the task's rule: at
    camera.distance_m along view_direction from the feature centre, looking at it.

    The patch is the surface within radius_m of the centre (task-format), so a disk point at
    radius rho must land at 3D distance rho: projected onto a curved surface it falls short (a
    cylinder's R atan(rho / R)), so its guess is pushed out radially until it lands there."""
    T = task.frames.T_cell_part
    vertices, faces, key, face_normals = placed_mesh(task)
    center = geometry.apply(T, task.feature.center_m)
    normal = geometry.unit(geometry.rotate(T, task.feature.normal))
    frame = geometry.frame_from_normal(normal)
    points, hit = feature_patch(task, (vertices, faces, key), center, frame, samples or task.feature.samples)
    reach = 4 * task.feature.radius_m + 0.01
    if extra is not None and len(extra):
        more, more_hit, _ = closest_points(shared_mesh(key, vertices, faces), np.asarray(extra, float), max_dist=reach)
        points, hit = np.vstack([points, more]), np.concatenate([hit, more_hit])
    if np.any(hit < 0):
        raise TaskError(task.path, f"{task.feature.key}.radius_m", f"{task.feature.radius_m:g} m, a patch "
                        f"{int(np.sum(hit < 0))} of whose {len(hit)} samples find no surface within "
                        f"{1e3 * reach:.0f} mm", "a patch on the part's surface")
    normals = face_normals[hit]
    if T_cell_cam is None:
        cam = center + task.camera.distance_m * geometry.unit(geometry.rotate(T, task.camera.view_direction))
        T_cell_cam = look_at(cam, center)
    return Scene(vertices=vertices, faces=faces, mesh_key=key, center=center, normal=normal, frame=frame,
                 points=points, normals=normals, T_cell_cam=np.array(T_cell_cam, float), housings=housings(task))


_PATCHES: Kept[tuple[np.ndarray, np.ndarray]] = Kept(128)


def feature_patch(task: Task, mesh: tuple[np.ndarray, np.ndarray, str], center: np.ndarray, frame: np.ndarray,
                  n: int) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3), faces hit (n,)) of the task's feature patch of n samples on the placed mesh
    (vertices, faces, key: placed_mesh's) about `center` in `frame` (build_scene's pushes), read-only: made once per
    mesh, feature and n in a process, the 128 most recent kept. The judge's certificates ask a
    feature's dense patch again at each shot as far from it as one before (n, dense_samples,
    follows the camera's distance): some 200 of the 504 scenes at 40 features."""
    known = (mesh[2], center.tobytes(), frame.tobytes(), n, float(task.feature.radius_m))

    def made() -> tuple[np.ndarray, np.ndarray]:
        patch = _projected(task, mesh, center, frame, n)
        _read_only(patch)
        return patch
    return _PATCHES.get(known, made)


def _projected(task: Task, mesh: tuple[np.ndarray, np.ndarray, str], center: np.ndarray, frame: np.ndarray,
               n: int) -> tuple[np.ndarray, np.ndarray]:
    """feature_patch's points and faces, made: the disk's guesses pushed out until they land at their distance."""
    disk = feature_disk(n, task.feature.radius_m)
    guesses = on_plane(center, frame, disk)
    bvh = shared_mesh(mesh[2], mesh[0], mesh[1])
    reach = 4 * task.feature.radius_m + 0.01
    wanted = np.hypot(disk[:, 0], disk[:, 1])
    away = wanted > 1e-3 * task.feature.radius_m
    for _ in range(PATCH_ITERATIONS):
        points, hit, _ = closest_points(bvh, guesses, max_dist=reach)
        landed = _row_norms(geometry.by_component(np.subtract, points, center))
        push = away & (hit >= 0) & (landed > 0)
        if not np.any(np.abs(landed[push] - wanted[push]) > PATCH_TOLERANCE * task.feature.radius_m):
            break
        offset = geometry.by_component(np.multiply, geometry.by_component(np.subtract, guesses[push], center),
                                       (wanted[push] / landed[push])[:, None])
        reach_out = _row_norms(offset) / (PATCH_PUSH_MAX * wanted[push])     # an edge: no
        guesses[push] = geometry.by_component(np.add, center, geometry.by_component(      # surface out there
            np.divide, offset, np.maximum(reach_out, 1.0)[:, None]))
    # `landed` is of the last query's points: where they land (the loop's break or its last round)
    short = away & (hit >= 0) & (np.abs(landed - wanted) > PATCH_LEAVES * task.feature.radius_m)
    if np.any(short):
        raise TaskError(task.path, f"{task.feature.key}.center_m",
                        f"a patch of radius {1e3 * task.feature.radius_m:g} mm whose"
                        f" {int(short.sum())} of {n} samples cannot lie on the surface at their distance "
                        f"(it runs over an edge of the part)", "a patch on one continuous surface")
    return points, hit


def on_plane(center: np.ndarray, frame: np.ndarray, disk: np.ndarray) -> np.ndarray:
    """(N, 3) the disk's points (N, 2) in the plane through `center` spanned by the frame's first
    two columns: center + x frame_x + y frame_y, a component at a time (NumPy's operations on the
    disk's (N, 1) columns times the 3-vectors, in their order: the same bits, without an inner
    loop over 3 numbers a point, a quarter of the time on a dense patch's 10 000)."""
    out = np.empty((len(disk), 3))
    for k in range(3):
        out[:, k] = (center[k] + disk[:, 0] * frame[k, 0]) + disk[:, 1] * frame[k, 1]
    return out


def _row_norms(d: np.ndarray) -> np.ndarray:
    """np.linalg.norm(d, axis=1) of rows (N, 3), bit for bit: the root of their squares' row_sum
    (add.reduce's order), without a reduction over an axis of 3 (a dense patch has ~9000 rows)."""
    return np.sqrt(geometry.row_sum(d * d))


_PLACED: Kept[tuple[np.ndarray, np.ndarray, str, np.ndarray]] = Kept(8)


def placed_mesh(task: Task) -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
    """(vertices (V, 3), faces (F, 3), the digest naming them, face normals (F, 3)) of the task's
    part mesh in the cell frame (T_cell_part), read-only: made once per geometry and pose in a
    process (a part's scenes, some 500 at 40 features, share them; the few most recent kept)."""
    mesh, T = task.part.mesh, task.frames.T_cell_part
    known = (np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes(),
             np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes(),
             np.ascontiguousarray(T, dtype=np.float64).tobytes())

    def made() -> tuple[np.ndarray, np.ndarray, str, np.ndarray]:
        moved = mesh.copy()
        moved.apply_transform(T)
        vertices = np.ascontiguousarray(moved.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(moved.faces, dtype=np.int64)
        key = hashlib.blake2b(vertices.tobytes() + faces.tobytes(), digest_size=16).hexdigest()
        placed = vertices, faces, key, np.array(moved.face_normals)
        _read_only(placed)
        return placed
    return _PLACED.get(known, made)


def _read_only(values):
    """The arrays among values made read-only: mesh_key names this geometry, so it must not
    change under the key (nor a plan's samples under its predictions)."""
    for value in values:
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
