"""Triangles wound against their neighbours: a mesh's faces whose order of vertices (and so whose
normal) is flipped relative to the faces around them. Two faces sharing an edge are wound
consistently when they run that edge in opposite directions; the same direction in both means
one of them is flipped. On a closed mesh a wholly inside-out shell shows as a negative volume
(the loader refuses it), but a few flipped triangles, or any on an open mesh, do not: the planner
then sees those faces from behind (their normals point into the part) and cannot see the feature.

Each connected part of the mesh (faces joined by edges two faces share) is split into the two
classes of a consistent winding (brute force over the adjacency: a face's class is its
neighbour's when they run the shared edge oppositely, the other when alike); the class of fewer
triangles (then of smaller area) in each part is the flipped one: locally flipped triangles are a
few among many, and an open mesh has no inside to tell which way is out."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class Flipped:
    """The faces wound against their neighbours (indices into the mesh's faces), grouped by
    connected patches of them, each patch's area-weighted centroid in the mesh's frame [m]."""

    faces: np.ndarray            # (K,) face indices
    places: np.ndarray           # (G, 3) each patch's centroid
    counts: np.ndarray           # (G,) its triangles

    def __len__(self) -> int:
        return len(self.faces)

    def where(self, frame: str = "part frame", limit: int = 3) -> str:
        """'12 triangles in 2 places: around [x, y, z] mm, ... (part frame)' for a person."""
        around = ", ".join(f"{n} around {np.round(1e3 * p, 1).tolist()} mm"
                           for n, p in zip(self.counts[:limit], self.places[:limit]))
        more = f" and {len(self.places) - limit} more places" if len(self.places) > limit else ""
        return f"{around}{more} ({frame})"


def runs_forward(faces: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Whether each face runs its edge u -> v in its vertex order (v follows u cyclically)."""
    iu = np.argmax(faces == u[:, None], axis=1)
    iv = np.argmax(faces == v[:, None], axis=1)
    return (iv - iu) % 3 == 1


def flipped_faces(mesh: trimesh.Trimesh) -> Flipped:
    """The Flipped faces of a mesh (vertices merged, as the loader's mesh is): per connected part,
    the winding class of fewer triangles, found from the signed adjacency graph (module docstring). A
    part no consistent winding exists for (a Moebius strip) is left alone."""
    faces = np.asarray(mesh.faces)
    n = len(faces)
    pairs, edges = np.asarray(mesh.face_adjacency), np.asarray(mesh.face_adjacency_edges)
    if n == 0 or len(pairs) == 0:
        return Flipped(np.zeros(0, int), np.zeros((0, 3)), np.zeros(0, int))
    alike = runs_forward(faces[pairs[:, 0]], edges[:, 0], edges[:, 1]) == runs_forward(
        faces[pairs[:, 1]], edges[:, 0], edges[:, 1])
    # the doubled graph: face f in class 0 is node f, in class 1 node f + n; an edge run oppositely
    # joins the same classes, an edge run alike the other class
    a, b = pairs[:, 0], pairs[:, 1]
    rows = np.concatenate([a, a + n])
    cols = np.concatenate([np.where(alike, b + n, b), np.where(alike, b, b + n)])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n, 2 * n))
    _, label = connected_components(graph, directed=False)
    _, part = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    area = np.asarray(mesh.area_faces)
    flipped = np.zeros(n, bool)
    for p in np.unique(part):
        members = np.flatnonzero(part == p)
        same = label[members] == label[members[0]]       # the first face's class
        if label[members[0]] == label[members[0] + n]:   # both classes joined: not orientable
            continue
        fewer = (same.sum(), area[members[same]].sum()) < ((~same).sum(), area[members[~same]].sum())
        flipped[members[same if fewer else ~same]] = True
    index = np.flatnonzero(flipped)
    if len(index) == 0:
        return Flipped(index, np.zeros((0, 3)), np.zeros(0, int))
    keep = flipped[a] & flipped[b]                       # patches: flipped faces joined by an edge
    _, patch = connected_components(coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(n, n)),
                                    directed=False)
    groups = [index[patch[index] == g] for g in np.unique(patch[index])]
    groups.sort(key=len, reverse=True)
    centroids = np.asarray(mesh.triangles_center)
    places = np.array([np.average(centroids[g], axis=0, weights=area[g]) for g in groups])
    return Flipped(index, places, np.array([len(g) for g in groups]))
