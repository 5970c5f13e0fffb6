"""A triangle mesh as a Warp BVH (wp.Mesh), for the ray-casting kernels."""
import hashlib
from functools import cached_property
from typing import Any

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from .recent import Kept
from .runtime import ensure_init


class WarpMesh:
    """wp.Mesh of vertices (V, 3) [m] and faces (F, 3), holding its Warp arrays alive.

    Warp stores float32 vertices; `vertices` is that float32 geometry as float64, so a NumPy
    reference can cast rays against exactly what the kernels see. Building is cheap
    (a BVH over F triangles): rebuild rather than mutate.
    """

    def __init__(self, vertices: ArrayLike, faces: ArrayLike) -> None:
        device = ensure_init()
        points = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
        faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
        if len(faces) == 0:
            raise ValueError("WarpMesh needs at least one triangle")
        if faces.min() < 0 or faces.max() >= len(points):
            raise ValueError("WarpMesh: face index out of range")
        self.vertices = points.astype(np.float64)
        self.faces = faces.astype(np.int64)
        self._points = wp.array(points, dtype=wp.vec3, device=device)
        self._indices = wp.array(faces.ravel(), dtype=wp.int32, device=device)
        self.mesh = wp.Mesh(points=self._points, indices=self._indices)

    @classmethod
    def from_trimesh(cls, mesh: Any) -> "WarpMesh":
        """From anything with .vertices and .faces (a trimesh.Trimesh)."""
        return cls(mesh.vertices, mesh.faces)

    @property
    def id(self) -> Any:
        """The wp.uint64 handle kernels take."""
        return self.mesh.id

    @cached_property
    def digest(self) -> bytes:
        """A digest of the geometry the kernels see (its vertices and faces), found once: a
        WarpMesh is never changed (rebuild rather than mutate), so it names this geometry in a
        cache's key (kernels.cone.common_cone_cosine)."""
        return hashlib.blake2b(self.vertices.tobytes() + self.faces.tobytes(), digest_size=16).digest()

    def __repr__(self):
        return f"WarpMesh({len(self.vertices)} vertices, {len(self.faces)} faces)"


_SHARED: Kept[WarpMesh] = Kept(8)   # this process's meshes by key (the judge lays dense patches on
                                    # runtime.in_background's thread: asked from two threads)


def shared_mesh(key: str, vertices: ArrayLike, faces: ArrayLike) -> WarpMesh:
    """The process's WarpMesh of this geometry, built on first use and kept for the next.

    Warp handles cannot be pickled or sent to another process, so plans and scenes carry plain
    arrays and a `key` naming their geometry (a digest); each process builds its own BVH once.
    The few most recent meshes are kept (a bench or a test suite plans many scenes of one part),
    under a lock: threads of one process ask at once (runtime.in_background).
    """
    return _SHARED.get(key, lambda: WarpMesh(vertices, faces))
