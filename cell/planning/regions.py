"""The paper's spherical maps (sec. 2.2, 5.2): an azimuth/elevation grid in the feature frame,
the region-of-similar-brightness map and its signed haversine distance transform (eq. 2-3)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from cell.core import geometry
from cell.physics import brdf
from kernels.runtime import threads

if TYPE_CHECKING:
    from cell.physics.material import Material


@dataclass(frozen=True)
class SphereGrid:
    """Cell centres: azimuth phi_i = -pi + i*step (i < 2pi/step), elevation theta_j = -pi/2 + j*step
    (latitude, poles included). Maps are arrays of shape (E, A)."""

    step: float

    @property
    def azimuth_count(self) -> int:
        return int(round(2 * np.pi / self.step))

    @property
    def elevation_count(self) -> int:
        return int(round(np.pi / self.step)) + 1

    @property
    def azimuth(self) -> np.ndarray:
        return -np.pi + self.step * np.arange(self.azimuth_count)

    @property
    def elevation(self) -> np.ndarray:
        return -0.5 * np.pi + self.step * np.arange(self.elevation_count)

    def directions(self, frame: ArrayLike = np.eye(3)) -> np.ndarray:
        """(E, A, 3) unit directions of every cell, rotated from the feature frame by `frame`."""
        return _cell_directions(self.step) @ np.asarray(frame).T

    def _corners(self, azimuth, elevation):
        """(e0, a0, a1, ta, te): the cells around (azimuth, elevation) and the weights between
        (the grid's sizes by count: sampled at every objective evaluation of a search)."""
        n_az, n_el = self.azimuth_count, self.elevation_count
        a = (np.asarray(azimuth) + np.pi) / self.step
        e = np.clip((np.asarray(elevation) + 0.5 * np.pi) / self.step, 0, n_el - 1)
        a0 = np.floor(a).astype(int)
        e0 = np.minimum(np.floor(e).astype(int), n_el - 2)
        return e0, a0 % n_az, (a0 + 1) % n_az, a - a0, e - e0

    def sample(self, values: np.ndarray, azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
        """Bilinear interpolation of a map at (azimuth, elevation), wrapping across the seam."""
        e0, a0, a1, ta, te = self._corners(azimuth, elevation)
        v = values
        return ((1 - te) * ((1 - ta) * v[e0, a0] + ta * v[e0, a1])
                + te * ((1 - ta) * v[e0 + 1, a0] + ta * v[e0 + 1, a1]))

    def cells_around(self, azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
        """Flat indices into an (E, A) map of the cells `sample` reads at these directions."""
        e0, a0, a1, _, _ = self._corners(azimuth, elevation)
        n_az = self.azimuth_count
        return np.unique(np.concatenate([np.ravel(e * n_az + a) for e in (e0, e0 + 1) for a in (a0, a1)]))


@lru_cache(maxsize=8)
def _cell_directions(step: float) -> np.ndarray:
    """(E, A, 3) unit directions of every cell of SphereGrid(step) in the feature frame, computed
    once per step (read-only): every map of a plan, and of every shot judged, is on one grid."""
    grid = SphereGrid(step)
    el, az = np.meshgrid(grid.elevation, grid.azimuth, indexing="ij")
    out = geometry.direction_from_angles(az, el)
    out.flags.writeable = False
    return out


def nearest_chord(queries: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(Q,) the chord from each query (Q, 3) to its nearest target (T, 3), by brute force: for
    the few cells a judged lamp reads, cheaper than a k-d tree's build over the whole map. Summed
    as cKDTree sums it, (dx^2 + dy^2) + dz^2, so the same value bit for bit."""
    d = queries[:, None, :] - targets[None]
    return np.sqrt(np.min((d[..., 0] ** 2 + d[..., 1] ** 2) + d[..., 2] ** 2, axis=1))


def chord_to_angle(chord: float | np.ndarray) -> np.ndarray:
    """Great-circle angle from the chord between unit vectors: 2 asin(chord / 2)."""
    return 2.0 * np.arcsin(np.clip(0.5 * chord, 0.0, 1.0))


FEW_CELLS = 64      # cells asked for at most: brute force (nearest_chord), not k-d trees


POLE_ROWS = 3       # rows at either pole that on_edge keeps whole: there the grid's neighbours are not its 8


def on_edge(inside: np.ndarray) -> np.ndarray:
    """(E, A) the cells of a map (E, A) with a cell of the other kind among their eight grid
    neighbours (azimuth wrapping across the seam), and every cell of the POLE_ROWS rows at either
    pole. The nearest cell of the other kind from any cell is among them: on the geodesic from a
    cell q to its nearest cell p of the other kind, the point just past p's Voronoi cell (of all
    cells) lies in a neighbour r's (Delaunay: off the poles, one of the eight), no farther from r
    than from p, so r is no farther from q than p (triangle inequality) and, were it of p's kind,
    as near; stepping on along the geodesic ends at a cell of p's kind next to one of the other."""
    rows = np.pad(inside, ((1, 1), (0, 0)), mode="edge")
    edge = np.zeros(inside.shape, bool)
    for de in (-1, 0, 1):
        for da in (-1, 0, 1):
            edge |= np.roll(rows[1 + de:1 + de + len(inside)], da, axis=1) != inside
    edge[:POLE_ROWS] = edge[-POLE_ROWS:] = True
    return edge


def signed_distance(grid: SphereGrid, inside: ArrayLike, cells: np.ndarray | None = None) -> np.ndarray:
    """Exact signed spherical distance transform of a boolean map (E, A) [rad]:
    -(distance to the nearest outside cell) inside, +(distance to the nearest inside cell) outside;
    only at the flat indices `cells` if given (NaN elsewhere: one lamp's value needs the four
    cells around it, not the whole map).

    Chord length between unit vectors is monotonic in the great-circle angle, so a k-d tree
    on the cells' unit vectors finds the haversine-nearest cell exactly, seam and poles included
    (at a few `cells`: brute force, nearest_chord, the same values); the trees hold only the
    cells on_edge, among which the nearest one of the other kind always is.
    An empty (or full) region gives +pi (or -pi) everywhere.
    """
    inside = np.asarray(inside, dtype=bool)
    if not inside.any():
        return np.full(inside.shape, np.pi)
    if inside.all():
        return np.full(inside.shape, -np.pi)
    dirs = _cell_directions(grid.step).reshape(-1, 3)
    flat = inside.ravel()
    out = np.full(flat.shape, np.nan)
    if cells is not None and len(cells) <= FEW_CELLS:
        cells = np.unique(np.asarray(cells, dtype=int))
        outside = ~flat[cells]
        out[cells[~outside]] = -chord_to_angle(nearest_chord(dirs[cells[~outside]], dirs[~flat]))
        out[cells[outside]] = chord_to_angle(nearest_chord(dirs[cells[outside]], dirs[flat]))
        return out.reshape(inside.shape)
    wanted = np.ones(flat.shape, bool) if cells is None else np.isin(np.arange(flat.size), cells)
    edge = on_edge(inside).ravel()
    workers = threads()             # the queries split over the kernels' threads: each query its own
    chord_out, _ = cKDTree(dirs[~flat & edge]).query(dirs[flat & wanted], workers=workers)
    chord_in, _ = cKDTree(dirs[flat & edge]).query(dirs[~flat & wanted], workers=workers)
    out[flat & wanted] = -chord_to_angle(chord_out)
    out[~flat & wanted] = chord_to_angle(chord_in)
    return out.reshape(inside.shape)


def dominant_term_map(grid: SphereGrid, frame: np.ndarray, normal: np.ndarray, view: np.ndarray,
                      material: Material, where: np.ndarray | None = None) -> np.ndarray:
    """Sec. 5.2: dominant BRDF term (brdf.DIFFUSE/LOBE/SPIKE, OCCLUDED behind, UNKNOWN where a
    spike the goniometer did not resolve may lie: brdf.judged_term) for a lamp in each grid
    direction, seen by a camera in direction `view` from a surface with `normal`; only in the
    cells `where` (E, A) if given (OCCLUDED elsewhere: the visible cells, all a map reads), each
    cell's term its own."""
    s = grid.directions(frame)
    cells = s if where is None else s[where]
    terms = brdf.judged_term(brdf.dominant_term_vectors(normal, cells, view, material), normal, cells, view, material)
    if where is None:
        return terms
    out = np.full(where.shape, brdf.OCCLUDED, dtype=terms.dtype)
    out[where] = terms
    return out


def reflectance_map(grid: SphereGrid, frame: np.ndarray, normal: np.ndarray, view: np.ndarray,
                    material: Material) -> np.ndarray:
    """R of eq. (7) for a lamp in each grid direction (the paper's 'BRDF mapped on the visibility map')."""
    return brdf.reflectance_vectors(normal, grid.directions(frame), view, material)


WANTED_TERM = {"diffuse": brdf.DIFFUSE, "lobe": brdf.LOBE, "spike": brdf.SPIKE}


def wanted_region(dominant: np.ndarray, visible: np.ndarray, reflection: str) -> np.ndarray:
    """Cells where a lamp gives the wanted reflection type and every sample sees it; `any` is
    any known term (not where an unresolved spike may be: its brightness is unknown)."""
    if reflection == "any":
        return visible & (dominant != brdf.OCCLUDED) & (dominant != brdf.UNKNOWN)
    return visible & (dominant == WANTED_TERM[reflection])
