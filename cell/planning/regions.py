"""The paper's spherical maps (sec. 2.2, 5.2): an azimuth/elevation grid in the feature frame,
the region-of-similar-brightness map and its signed haversine distance transform (eq. 2-3)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from cell.core import geometry
from cell.physics import brdf

if TYPE_CHECKING:
    from cell.physics.material import Material


@dataclass(frozen=True)
class SphereGrid:
    """Cell centres: azimuth phi_i = -pi + i*step (i < 2pi/step), elevation theta_j = -pi/2 + j*step
    (latitude, poles included). Maps are arrays of shape (E, A)."""

    step: float

    @property
    def azimuth(self) -> np.ndarray:
        return -np.pi + self.step * np.arange(int(round(2 * np.pi / self.step)))

    @property
    def elevation(self) -> np.ndarray:
        return -0.5 * np.pi + self.step * np.arange(int(round(np.pi / self.step)) + 1)

    def directions(self, frame: ArrayLike = np.eye(3)) -> np.ndarray:
        """(E, A, 3) unit directions of every cell, rotated from the feature frame by `frame`."""
        el, az = np.meshgrid(self.elevation, self.azimuth, indexing="ij")
        return geometry.direction_from_angles(az, el) @ np.asarray(frame).T

    def _corners(self, azimuth, elevation):
        """(e0, a0, a1, ta, te): the cells around (azimuth, elevation) and the weights between."""
        a = (np.asarray(azimuth) + np.pi) / self.step
        e = np.clip((np.asarray(elevation) + 0.5 * np.pi) / self.step, 0, len(self.elevation) - 1)
        n_az = len(self.azimuth)
        a0 = np.floor(a).astype(int)
        e0 = np.minimum(np.floor(e).astype(int), len(self.elevation) - 2)
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
        n_az = len(self.azimuth)
        return np.unique(np.concatenate([np.ravel(e * n_az + a) for e in (e0, e0 + 1) for a in (a0, a1)]))


def chord_to_angle(chord: float | np.ndarray) -> np.ndarray:
    """Great-circle angle from the chord between unit vectors: 2 asin(chord / 2)."""
    return 2.0 * np.arcsin(np.clip(0.5 * chord, 0.0, 1.0))


def signed_distance(grid: SphereGrid, inside: ArrayLike, cells: np.ndarray | None = None) -> np.ndarray:
    """Exact signed spherical distance transform of a boolean map (E, A) [rad]:
    -(distance to the nearest outside cell) inside, +(distance to the nearest inside cell) outside;
    only at the flat indices `cells` if given (NaN elsewhere: one lamp's value needs the four
    cells around it, not the whole map).

    Chord length between unit vectors is monotonic in the great-circle angle, so a k-d tree
    on the cells' unit vectors finds the haversine-nearest cell exactly, seam and poles included.
    An empty (or full) region gives +pi (or -pi) everywhere.
    """
    inside = np.asarray(inside, dtype=bool)
    if not inside.any():
        return np.full(inside.shape, np.pi)
    if inside.all():
        return np.full(inside.shape, -np.pi)
    dirs = grid.directions().reshape(-1, 3)
    flat = inside.ravel()
    wanted = np.ones(flat.shape, bool) if cells is None else np.isin(np.arange(flat.size), cells)
    out = np.full(flat.shape, np.nan)
    chord_out, _ = cKDTree(dirs[~flat]).query(dirs[flat & wanted])
    chord_in, _ = cKDTree(dirs[flat]).query(dirs[~flat & wanted])
    out[flat & wanted] = -chord_to_angle(chord_out)
    out[~flat & wanted] = chord_to_angle(chord_in)
    return out.reshape(inside.shape)


def dominant_term_map(grid: SphereGrid, frame: np.ndarray, normal: np.ndarray, view: np.ndarray,
                      material: Material) -> np.ndarray:
    """Sec. 5.2: dominant BRDF term (brdf.DIFFUSE/LOBE/SPIKE, OCCLUDED behind, UNKNOWN where a
    spike the goniometer did not resolve may lie: brdf.judged_term) for a lamp in each grid
    direction, seen by a camera in direction `view` from a surface with `normal`."""
    s = grid.directions(frame)
    return brdf.judged_term(brdf.dominant_term_vectors(normal, s, view, material), normal, s, view, material)


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
