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
from kernels.recent import Kept
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
        return _counts(self.step)[0]

    @property
    def elevation_count(self) -> int:
        return _counts(self.step)[1]

    @property
    def azimuth(self) -> np.ndarray:
        return -np.pi + self.step * np.arange(self.azimuth_count)

    @property
    def elevation(self) -> np.ndarray:
        return -0.5 * np.pi + self.step * np.arange(self.elevation_count)

    def directions(self, frame: ArrayLike = np.eye(3)) -> np.ndarray:
        """(E, A, 3) unit directions of every cell, rotated from the feature frame by `frame`
        (read-only: made once per frame, _rotated_directions)."""
        return _rotated_directions(self.step, np.ascontiguousarray(frame, dtype=float).tobytes())

    def _corners(self, azimuth, elevation):
        """(e0, a0, a1, ta, te): the cells around (azimuth, elevation) and the weights between
        (the grid's sizes by count: sampled at every objective evaluation of a search)."""
        n_az, n_el = _counts(self.step)
        a = (np.asarray(azimuth) + np.pi) / self.step
        # np.clip's values as two ufuncs, without its checks (the row is never -0.0: -pi/2 + pi/2 is +0.0)
        e = np.minimum(np.maximum((np.asarray(elevation) + 0.5 * np.pi) / self.step, 0), n_el - 1)
        a0 = np.floor(a).astype(int)
        e0 = np.minimum(np.floor(e).astype(int), n_el - 2)
        return e0, a0 % n_az, (a0 + 1) % n_az, a - a0, e - e0

    def sample(self, values: np.ndarray, azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
        """Bilinear interpolation of a map at (azimuth, elevation), wrapping across the seam."""
        e0, a0, a1, ta, te = self._corners(azimuth, elevation)
        v = values
        return ((1 - te) * ((1 - ta) * v[e0, a0] + ta * v[e0, a1])
                + te * ((1 - ta) * v[e0 + 1, a0] + ta * v[e0 + 1, a1]))

    def cells_around(self, azimuth: ArrayLike, elevation: ArrayLike, margin: int = 0) -> np.ndarray:
        """Flat indices into an (E, A) map of the cells `sample` reads at these directions, and
        of those up to `margin` rows and columns beyond them (rows clipped at the poles, columns
        wrapping across the seam)."""
        e0, a0, _, _, _ = self._corners(azimuth, elevation)
        steps = np.arange(-margin, margin + 2)
        rows = np.clip(np.ravel(e0)[:, None] + steps, 0, self.elevation_count - 1)
        columns = (np.ravel(a0)[:, None] + steps) % self.azimuth_count
        return np.unique((rows[:, :, None] * self.azimuth_count + columns[:, None, :]).ravel())


@lru_cache(maxsize=8)
def _counts(step: float) -> tuple[int, int]:
    """(azimuth cells 2 pi / step, elevation rows pi / step + 1) of SphereGrid(step), once per step."""
    return int(round(2 * np.pi / step)), int(round(np.pi / step)) + 1


@lru_cache(maxsize=8)
def _cell_directions(step: float) -> np.ndarray:
    """(E, A, 3) unit directions of every cell of SphereGrid(step) in the feature frame, computed
    once per step (read-only): every map of a plan, and of every shot judged, is on one grid."""
    grid = SphereGrid(step)
    el, az = np.meshgrid(grid.elevation, grid.azimuth, indexing="ij")
    out = geometry.direction_from_angles(az, el)
    out.flags.writeable = False
    return out


@lru_cache(maxsize=8)
def _rotated_directions(step: float, frame: bytes) -> np.ndarray:
    """SphereGrid(step).directions of the frame (3x3, C order, its bytes), read-only, the 8 most
    recent kept: a part's features lie on a few faces, so its maps (some 370 dominant-term maps
    of the 40-feature part, its 5 frames) ask the same few rotations again and again."""
    out = _cell_directions(step) @ np.frombuffer(frame).reshape(3, 3).T
    out.flags.writeable = False
    return out


def chord_to_angle(chord: float | np.ndarray) -> np.ndarray:
    """Great-circle angle from the chord between unit vectors: 2 asin(chord / 2)."""
    return 2.0 * np.arcsin(np.clip(0.5 * chord, 0.0, 1.0))


POLE_ROWS = 3       # rows at either pole that on_edge keeps whole: there the grid's neighbours are not its 8


def on_edge(inside: np.ndarray) -> np.ndarray:
    """(E, A) the cells of a map (E, A) with a cell of the other kind among their eight grid
    neighbours (azimuth wrapping across the seam), and every cell of the POLE_ROWS rows at either
    pole. The nearest cell of the other kind from any cell is among them: on the geodesic from a
    cell q to its nearest cell p of the other kind, the point just past p's Voronoi cell (of all
    cells) lies in a neighbour r's (Delaunay: off the poles, one of the eight), no farther from r
    than from p, so r is no farther from q than p (triangle inequality) and, were it of p's kind,
    as near; stepping on along the geodesic ends at a cell of p's kind next to one of the other."""
    count_el, count_az = inside.shape
    # the map with a row repeated beyond each pole and a column wrapped beyond each side of the seam
    around = np.empty((count_el + 2, count_az + 2), bool)
    around[1:-1, 1:-1] = inside
    around[0, 1:-1], around[-1, 1:-1] = inside[0], inside[-1]
    around[:, 0], around[:, -1] = around[:, -2], around[:, 1]
    edge = np.zeros(inside.shape, bool)
    for de in (0, 1, 2):
        for da in (0, 1, 2):
            edge |= around[de:de + count_el, da:da + count_az] != inside
    edge[:POLE_ROWS] = edge[-POLE_ROWS:] = True
    return edge


# a few lamps read cells not found yet (a refinement's steps): the cells NEARBY rows and columns
# around them are found with them, where its next steps are likely to read (each query costs
# ~0.1 ms however few its cells, a cell ~1 us)
FEW_LAMPS = 16
NEARBY = 2
SPLIT_QUERIES = 2048    # cells asked at once from which the k-d tree queries split over the kernels' threads
# cells asked at most, before any k-d tree is built, found by brute force over the edge cells
# (nearest_chord, ~10 us a cell on the 2 deg map) instead (the trees' build ~0.25 ms): a judged
# shot's one lamp reads four
FEW_CELLS = 16


def nearest_chord(queries: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(Q,) the chord from each query (Q, 3) to its nearest target (T, 3), by brute force, summed
    as cKDTree sums it for p = 2, ((0 + dx^2) + dy^2) + dz^2, and its root: the same value bit for
    bit. A component at a time ((Q, 1) against (T,): no (Q, T, 3) array, whose last axis of 3
    NumPy's inner loops would run over)."""
    dx, dy, dz = (queries[:, k:k + 1] - targets[:, k] for k in range(3))
    return np.sqrt(np.min((dx * dx + dy * dy) + dz * dz, axis=1))


class RegionDistance:
    """Exact signed spherical distance transform of a boolean map (E, A) [rad] (eq. 2-3):
    -(distance to the nearest outside cell) inside, +(distance to the nearest inside cell)
    outside, computed only where it is read and kept: a search reads it at the cells around its
    lamps (sample: a few thousand of the map's cells), a judged shot at one lamp's four, a
    picture everywhere (full). Each cell's value is its own, however it was asked.

    Chord length between unit vectors is monotonic in the great-circle angle, so a k-d tree
    on the cells' unit vectors finds the haversine-nearest cell exactly, seam and poles included;
    the trees hold only the cells on_edge, among which the nearest one of the other kind always
    is. Until they are built (the first read of more than FEW_CELLS cells builds them) a few
    cells are found by brute force over those edge cells (nearest_chord: the trees' numbers),
    and only the cells read (no NEARBY ones): a judged shot reads its lamp's four once. An
    empty (or full) region gives +pi (or -pi) everywhere."""

    def __init__(self, grid: SphereGrid, inside: ArrayLike) -> None:
        self.grid = grid
        self.inside = np.array(inside, dtype=bool)
        self.inside.flags.writeable = False
        uniform = np.pi if not self.inside.any() else -np.pi if self.inside.all() else np.nan
        self._values = np.full(self.inside.size, uniform)        # NaN: not asked yet
        self._edge: np.ndarray | None = None                      # (E * A,) the cells on_edge
        self._edges: list[np.ndarray | None] = [None, None]       # the edge cells' directions: outside, inside
        self._trees: tuple[cKDTree, cKDTree] | None = None

    def __getstate__(self) -> dict:
        """Pickled (a plan from a worker process) with the values found so far, not the trees."""
        return {**self.__dict__, "_edge": None, "_edges": [None, None], "_trees": None}

    def at(self, cells: ArrayLike) -> np.ndarray:
        """The transform at the flat indices `cells` of the (E, A) map."""
        cells = np.asarray(cells, dtype=int)
        unknown = np.isnan(self._values[cells])
        if unknown.any():
            missing = np.unique(cells[unknown])
            flat = self.inside.ravel()
            dirs = _cell_directions(self.grid.step).reshape(-1, 3)
            inner, outer = missing[flat[missing]], missing[~flat[missing]]
            if self._trees is None and len(missing) <= FEW_CELLS:
                if len(inner):
                    self._values[inner] = -chord_to_angle(nearest_chord(dirs[inner], self._edge_cells(False)))
                if len(outer):
                    self._values[outer] = chord_to_angle(nearest_chord(dirs[outer], self._edge_cells(True)))
                return self._values[cells]
            if self._trees is None:
                self._trees = cKDTree(self._edge_cells(False)), cKDTree(self._edge_cells(True))
            to_outside, to_inside = self._trees
            workers = threads() if len(missing) >= SPLIT_QUERIES else 1    # each query its own
            if len(inner):
                self._values[inner] = -chord_to_angle(to_outside.query(dirs[inner], workers=workers)[0])
            if len(outer):
                self._values[outer] = chord_to_angle(to_inside.query(dirs[outer], workers=workers)[0])
        return self._values[cells]

    def _edge_cells(self, inside: bool) -> np.ndarray:
        """The directions of the edge cells (on_edge) inside the region, or outside it, found when
        first asked (a judged lamp's few cells inside it ask only for those outside)."""
        kept = self._edges[int(inside)]
        if kept is None:
            if self._edge is None:
                self._edge = on_edge(self.inside).ravel()
            flat = self.inside.ravel()
            kept = _cell_directions(self.grid.step).reshape(-1, 3)[(flat if inside else ~flat) & self._edge]
            self._edges[int(inside)] = kept
        return kept

    def sample(self, azimuth: ArrayLike, elevation: ArrayLike) -> np.ndarray:
        """SphereGrid.sample of the transform at (azimuth, elevation). A value reading a cell not
        found yet is NaN (NaN times any weight is NaN): the cells around those directions are
        found, and they are sampled again (a search's refinement mostly reads cells found before)."""
        values = self._values.reshape(self.inside.shape)
        out = self.grid.sample(values, azimuth, elevation)
        unknown = np.isnan(out)
        if unknown.any():
            azimuth, elevation = np.broadcast_arrays(azimuth, elevation)
            few = np.count_nonzero(unknown) <= FEW_LAMPS and self._trees is not None
            self.at(self.grid.cells_around(azimuth[unknown], elevation[unknown], NEARBY if few else 0))
            out[unknown] = self.grid.sample(values, azimuth[unknown], elevation[unknown])
        return out

    def full(self) -> np.ndarray:
        """(E, A) the transform at every cell."""
        return self.at(np.arange(self.inside.size)).reshape(self.inside.shape)


def dominant_term_map(grid: SphereGrid, frame: np.ndarray, normal: np.ndarray, view: np.ndarray,
                      material: Material, where: np.ndarray | None = None) -> np.ndarray:
    """Sec. 5.2: dominant BRDF term (brdf.DIFFUSE/LOBE/SPIKE, OCCLUDED behind, UNKNOWN where a
    spike the goniometer did not resolve may lie: brdf.judged_term) for a lamp in each grid
    direction, seen by a camera in direction `view` from a surface with `normal`; only in the
    cells `where` (E, A) if given (OCCLUDED elsewhere: the visible cells, all a map reads), each
    cell's term its own."""
    cells = grid.directions(frame) if where is None else _where_directions(grid.step, frame, where)
    terms = brdf.judged_term(brdf.dominant_term_vectors(normal, cells, view, material), normal, cells, view, material)
    if where is None:
        return terms
    out = np.full(where.shape, brdf.OCCLUDED, dtype=terms.dtype)
    out[where] = terms
    return out


_WHERE: Kept[np.ndarray] = Kept(64)


def _where_directions(step: float, frame: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(N, 3) SphereGrid(step).directions(frame)[where], read-only, made once per step, frame and
    cells in a process (the 64 most recent kept): a feature's visibility map does not depend on
    the camera, so the judge's dominant-term maps of one feature at each shot ask its cells again."""
    known = (step, np.ascontiguousarray(frame, dtype=float).tobytes(), np.packbits(where).tobytes())

    def made() -> np.ndarray:
        cells = SphereGrid(step).directions(frame)[where]
        cells.flags.writeable = False
        return cells
    return _WHERE.get(known, made)


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
