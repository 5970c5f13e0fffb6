"""Gray value per exposure for every (candidate lamp, sample point): the planner's bulk job."""
import threading
from dataclasses import dataclass
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
from numpy.typing import ArrayLike

from . import funcs
from .emission import axis_intensity, hard_cone_profile, profile_solid_angle
from .recent import Kept
from ._arrays import output, profile2d, table2d, unit_rows, vec3d, vec3d_view
from .cone import MARGIN_RAD, NO_CONE, common_cone_cosine, free_cone_cosines, worth_finding
from .runtime import ensure_init, in_parallel, launch_sliced, slices

if TYPE_CHECKING:
    from .mesh import WarpMesh


@dataclass(frozen=True)
class GrayResult:
    """Per (candidate, point), shape (C, P).

    value: c A_pixel Phi R / 8 = G / (t / kappa^2) [gray s^-1]; 0 when shadowed.
    shadowed: lamp behind the point's tangent plane, or (with shadows) the mesh blocks it.
    off_axis: angle between the lamp's axis and the ray lamp -> point [rad] (cone coverage:
        the point is inside the nominal cone iff off_axis <= gamma / 2; the lamp's profile at
        this angle scales the value).
    dominant: 0 diffuse, 1 lobe, 2 spike, -1 camera or lamp behind the surface (BRDF only).
    """

    value: np.ndarray
    shadowed: np.ndarray
    off_axis: np.ndarray
    dominant: np.ndarray


@wp.kernel
def surface_kernel(points: wp.array(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d), camera: wp.vec3d,
                   offset_m: wp.float64, free_cos: wp.array(dtype=wp.float64), sectors: wp.int32,
                   surfaces: wp.array(dtype=funcs.Surface)):
    """One thread per sample point: what the shading needs of it alone (funcs.surface); its
    sectors' cones in row p of the sector table, if `sectors`."""
    p = wp.tid()
    row = -1
    if sectors != 0:
        row = p
    surfaces[p] = funcs.surface(points[p], normals[p], camera, offset_m, free_cos[p], row)


@wp.kernel
def gray_kernel(mesh_id: wp.uint64, shadows: wp.int32, cone: wp.int32,
                surfaces: wp.array(dtype=funcs.Surface), sector_cos: wp.array2d(dtype=wp.float64),
                lamp_pos: wp.array(dtype=wp.vec3d),
                lamp_axis: wp.array(dtype=wp.vec3d), intensity_w_sr: wp.array(dtype=wp.float64),
                profile: wp.array2d(dtype=wp.float64), table: wp.array2d(dtype=wp.float64),
                camera_constant: wp.float64, pixel_area_m2: wp.float64, first_lamp: wp.int32,
                first_point: wp.int32, stop_point: wp.int32,
                value: wp.array2d(dtype=wp.float64), shadowed: wp.array2d(dtype=wp.bool),
                off_axis: wp.array2d(dtype=wp.float64), dominant: wp.array2d(dtype=wp.int8)):
    """One thread per candidate lamp c from first_lamp on (its axis intensity I(0) its own: the
    emitter points of several lights in one call), over the sample points p in [first_point,
    stop_point) (on the CPU a thread is a loop's turn: this way the lamp is read once and no
    thread index is divided; the slices: _Batch)."""
    c = wp.tid() + first_lamp
    lamp = lamp_pos[c]
    axis = lamp_axis[c]
    intensity = intensity_w_sr[c]
    for p in range(first_point, stop_point):
        sh = funcs.shade_point(mesh_id, shadows, cone, surfaces[p], sector_cos, lamp, axis, intensity,
                               profile, table, camera_constant, pixel_area_m2)
        value[c, p] = sh.value
        shadowed[c, p] = sh.shadowed
        off_axis[c, p] = sh.off_axis
        dominant[c, p] = wp.int8(sh.dominant)


@wp.kernel
def shadow_kernel(mesh_id: wp.uint64, shadows: wp.int32, surfaces: wp.array(dtype=funcs.Surface),
                  sector_cos: wp.array2d(dtype=wp.float64), lamp_pos: wp.array(dtype=wp.vec3d), first: wp.int32,
                  shadowed: wp.array2d(dtype=wp.bool)):
    """One thread per (point from `first` on, lamp) (runtime.launch_sliced: a camera's rays to
    a dense patch's points cut along the points): gray_kernel's shadow flag alone
    (funcs.shadowed_from)."""
    p, c = wp.tid()
    p = p + first
    shadowed[c, p] = funcs.shadowed_from(mesh_id, shadows, surfaces[p], sector_cos, lamp_pos[c])


FLAT_SLACK_M = 1e-6      # a flat patch's cylinder of ray origins widened and lowered by this: float32's rounding
                        # of a coordinate up to some 10 m (what the BVH's rays start from) stays inside
FLAT_SPREAD_RAD = 1e-4  # a patch's normals this far apart at most count as one plane's (a curved patch's do not)
SMALL = 1 << 16         # evaluations: a call this small reuses its launch (a search makes hundreds)
# what a (lamp, point) costs in runtime.slices's evaluations (MIN_SLICE of them about a millisecond,
# some 60 ns each), measured on one thread on the 40-feature part (lightplan_tasks.many_features):
SHADE_WORK = 4.0        # gray_kernel: a shadow ray and the shading, some 270 ns
RAY_WORK = 2.0          # shadow_kernel: the shadow ray alone, some 130 ns


class GrayInputs:
    """The inputs that stay fixed while a planner tries lamp poses (the scene, the camera, the
    lamp, the material), converted to Warp arrays once, with what depends on a sample point
    alone (funcs.Surface): a search calls the kernel hundreds of times on a few candidates each.

    mesh: kernels.mesh.WarpMesh or None (no cast shadows); points, normals (P, 3) [m];
    camera_pos (3,); power_w, cone_angle_rad: the lamp (I(0) by kernels.emission.axis_intensity); table (K, 6): Material.table(); shadow
    rays start at point + offset_m * normal; profile (M, 2) [off_axis_rad, relative]: the lamp's
    angular profile (None: eq. (11)'s ideal cone). Call with lamp_pos (C, 3) and lamp_axis
    (C, 3) (the aims, normalized here), and optionally power_w (C,), each lamp's own power (the
    emitter points of several lights of one profile in one call), for a GrayResult of (C, P)
    NumPy arrays.

    The points' free cones (kernels.cone) are found once the lamps evaluated so far make them
    worth it (kernels.cone.worth_finding, each lamp a ray per point): from then on only the rays
    outside them are cast. The result is the same either way. A call of at most SMALL
    evaluations replays its recorded launches (one set per lamp count, split as at its first
    call: kernels.runtime) on its own input and output buffers, under a lock, and returns copies;
    one that is a single launch (runtime.slices: too small to split) replays the one launch kept
    for them all, over as many lamps as it has (Launch.set_dim; its buffers as long as the most
    lamps asked so far): a refinement's rounds ask a few lamps, a different number each round.
    `flat`: the rows [start, end) of each flat patch among the points (a certificate's dense
    patches), whose rays share one free cone from the start (_flat_cones: each point's own
    costs more than the few lamps a certificate asks)."""

    def __init__(self, mesh: "WarpMesh | None", points: ArrayLike, normals: ArrayLike, camera_pos: ArrayLike,
                 power_w: float, cone_angle_rad: float, table: ArrayLike, camera_constant: float,
                 pixel_area_m2: float, shadows: bool = True, cone: bool = True, offset_m: float = 1e-5,
                 profile: ArrayLike | None = None, flat: Sequence[tuple[int, int]] = ()) -> None:
        self.device = ensure_init(__name__)
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        normals = np.ascontiguousarray(unit_rows(normals, "normals"))
        if len(normals) != len(points):
            raise ValueError(f"{len(points)} points but {len(normals)} normals")
        self.count = len(points)
        use_shadows = bool(shadows) and mesh is not None
        self._mesh = mesh if use_shadows else None      # keeps the BVH alive as long as its id is used
        # views of points and normals, which _shadow_rays keeps (and nothing writes)
        self._surface_inputs = [vec3d_view(points, "points"), vec3d_view(normals, "normals"),
                                wp.vec3d(*np.asarray(camera_pos, dtype=np.float64)), float(offset_m)]
        self._shadow_rays = (points, normals, float(offset_m))   # the free cones' ray origins, made if found
        self.surfaces = wp.empty(self.count, dtype=funcs.Surface, device=self.device)
        self._sector_cos, sector_cos_wp = output((max(1, self.count), funcs.SECTORS), np.float64, wp.float64)
        self._set_free_cones(self._flat_cones(flat), None)
        self._lamps_seen = 0
        self.has_free_cones = False
        self._leading = [self._mesh.id if self._mesh is not None else wp.uint64(0), int(use_shadows),
                         int(bool(cone)), self.surfaces, sector_cos_wp]
        # I(0) is linear in the power: P / Omega_p for each lamp's own P (axis_intensity's division)
        self.intensity_w_sr, self._solid_angle_sr, profile_wp, table_wp = lamp_and_material(
            power_w, cone_angle_rad, profile, table)
        self._trailing = [profile_wp, table_wp, float(camera_constant), float(pixel_area_m2)]
        # the kept batches split into slices, by lamp count (None: one launch, the single batch's)
        self._launches: dict[int, _Batch | None] = {}
        self._single: _Batch | None = None           # the kept batch of one launch, for up to its lamps
        self._lock = threading.Lock()

    def shadowed(self, lamp_pos: ArrayLike) -> np.ndarray:
        """(C, P) a call's GrayResult.shadowed for lamps at lamp_pos (C, 3), the same flags
        (funcs.shadowed_from: shade_point's test, which reads no aim, power or BRDF), without
        the shading: whether a camera there sees each point (a launch split along the points,
        runtime.launch_sliced, not recorded; its lamps count toward the free cones as a call's)."""
        lamp_pos = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
        out, out_wp = output((len(lamp_pos), self.count), np.bool_, wp.bool)
        if len(lamp_pos) and self.count:
            with self._lock:
                self._lamps(len(lamp_pos))
                launch_sliced(shadow_kernel, (self.count, len(lamp_pos)),
                              self._leading[:2] + [self.surfaces, self._leading[4], vec3d(lamp_pos, "lamp_pos")],
                              [out_wp], work_per_item=RAY_WORK * len(lamp_pos))
        return out

    def _flat_cones(self, flat: Sequence[tuple[int, int]]) -> np.ndarray:
        """(P,) each point's free cone cosine known before any lamp: of the rows [start, end) of
        each of `flat` whose normals lie within FLAT_SPREAD_RAD of the first's (a flat patch, and
        a point found on it apart), the cone about that normal common to their ray origins
        (kernels.cone.common_cone_cosine about their middle, within their farthest distance
        from the axis and above the lowest, each widened by FLAT_SLACK_M so that their float32
        roundings lie inside too), narrowed by the normals' largest angle from it (a point's
        own normal judges a ray); NO_CONE elsewhere."""
        out = np.full(self.count, NO_CONE)
        points, normals, offset_m = self._shadow_rays
        for start, end in flat:
            if end <= start or self._mesh is None:
                continue
            n = normals[start]
            # a column at a time: (N, 3) arrays against one 3-vector run an inner loop over 3 numbers a point
            other = np.flatnonzero((normals[start:end, 0] != n[0]) | (normals[start:end, 1] != n[1])
                                   | (normals[start:end, 2] != n[2])) + start
            apart = np.sqrt(np.sum((normals[other] - n) ** 2, axis=1, initial=0.0))    # chords: at most the angles
            spread = 2.0 * float(np.arcsin(min(1.0, 0.5 * float(apart.max(initial=0.0)))))
            if spread > FLAT_SPREAD_RAD:
                continue
            o = [points[start:end, k] + offset_m * normals[start:end, k] for k in range(3)]
            middle = np.array([0.5 * (x.min() + x.max()) for x in o])
            d = [x - m for x, m in zip(o, middle)]
            along = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
            across = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - along * along     # |d|^2 less its part along n
            out[start:end] = common_cone_cosine(self._mesh, middle, n,
                                                float(np.sqrt(max(float(across.max()), 0.0))) + FLAT_SLACK_M,
                                                float(along.min() + middle @ n) - FLAT_SLACK_M, MARGIN_RAD + 2.0 * spread)
        return out

    def _lamps(self, count: int) -> None:
        """Count `count` lamps more evaluated, and find the points' free cones once they are worth it."""
        self._lamps_seen += count
        if self._mesh is not None and not self.has_free_cones and self.count and worth_finding(self._lamps_seen, self._mesh):
            points, normals, offset_m = self._shadow_rays
            self._set_free_cones(*free_cone_cosines(self._mesh, points + offset_m * normals, normals))
            self.has_free_cones = True

    def _set_free_cones(self, free_cos, sector_cos):
        """The surfaces with these cones (sector_cos None: none by sector), in place: the
        recorded launches read them."""
        if sector_cos is not None:
            self._sector_cos[:] = sector_cos
        if self.count:
            free_cos = np.ascontiguousarray(free_cos, dtype=np.float64)     # read by the launch, in place
            wp.launch(surface_kernel, dim=self.count, device=self.device,
                      inputs=self._surface_inputs + [wp.array(free_cos, dtype=wp.float64, device=self.device, copy=False),
                                                     int(sector_cos is not None)],
                      outputs=[self.surfaces])

    def __call__(self, lamp_pos: ArrayLike, lamp_axis: ArrayLike, power_w: ArrayLike | None = None) -> GrayResult:
        lamp_pos = np.asarray(lamp_pos, dtype=np.float64).reshape(-1, 3)
        lamp_axis = unit_rows(np.broadcast_to(np.asarray(lamp_axis, dtype=np.float64), lamp_pos.shape),
                              "lamp_axis")
        if power_w is None:
            intensity = np.full(len(lamp_pos), self.intensity_w_sr)
        else:
            intensity = np.broadcast_to(np.asarray(power_w, dtype=np.float64), len(lamp_pos)) / self._solid_angle_sr
        with self._lock:
            self._lamps(len(lamp_pos))
            lamps = len(lamp_pos)
            if lamps * self.count > SMALL:
                return _Batch(self, lamps).run(lamp_pos, lamp_axis, intensity, copy=False)
            if lamps not in self._launches:
                one = lamps > 0 and self.count > 0 and len(_ranges(lamps, self.count)) == 1
                self._launches[lamps] = None if one else _Batch(self, lamps)
            kept = self._launches[lamps]
            if kept is None:
                if self._single is None or len(self._single.lamp_pos) < lamps:
                    self._single = _Batch(self, lamps)
                kept = self._single
            return kept.run(lamp_pos, lamp_axis, intensity, copy=True)


KEPT_CONSTANTS = 8      # lamps and material tables whose kernel arrays are kept (a plan has one or two)
_CONSTANTS: Kept[tuple[float, float, wp.array, wp.array]] = Kept(KEPT_CONSTANTS)   # GrayInputs are made on
                                                                                      # several threads of a process


def lamp_and_material(power_w: float, cone_angle_rad: float, profile: ArrayLike | None,
                      table: ArrayLike) -> tuple[float, float, wp.array, wp.array]:
    """(I(0) [W/sr] (axis_intensity), the profile's solid angle Omega_p [sr] (profile_solid_angle),
    profile2d's and table2d's arrays) of a lamp and a material table, made once per their values
    in a process (the KEPT_CONSTANTS most recent): every GrayInputs of one task asks the same
    (some 740 at 40 features), and the kernels only read the arrays."""
    shape = np.ascontiguousarray(hard_cone_profile(cone_angle_rad) if profile is None else profile, dtype=np.float64)
    rows = np.ascontiguousarray(table, dtype=np.float64)
    key = b"".join([np.array([power_w, cone_angle_rad, profile is None, *shape.shape, *rows.shape], np.float64).tobytes(),
                    shape.tobytes(), rows.tobytes()])
    return _CONSTANTS.get(key, lambda: (axis_intensity(power_w, cone_angle_rad, profile), profile_solid_angle(shape),
                                        profile2d(profile, cone_angle_rad), table2d(rows)))


def _ranges(lamps: int, points: int) -> list[tuple[int, int, int, int]]:
    """(first lamp, stop lamp, first point, stop point) of each launch of lamps x points: cut
    along the longer of the two into runtime.slices, each (lamp, point) SHADE_WORK evaluations."""
    if lamps >= points:
        return [(a, b, 0, points) for a, b in slices(lamps, SHADE_WORK * points)]
    return [(0, lamps, a, b) for a, b in slices(points, SHADE_WORK * lamps)]


class _Batch:
    """Buffers and the recorded launches of one lamp count: run copies the lamps in, launches,
    and returns the outputs (copies where the batch is kept for the next call). The lamps x
    points are cut along the longer of the two into runtime.slices (_ranges), a launch each, run
    side by side (runtime.in_parallel): a global search's thousands of lamps, a certificate's few
    lamps on thousands of points. A batch of one launch runs on fewer lamps than it holds as
    well: its launch set to their count (each thread a lamp of its own, over every point, as in
    a batch of their count), the rows beyond left as they were and not returned."""

    def __init__(self, inputs: GrayInputs, lamps: int) -> None:
        shape = (lamps, inputs.count)
        (self.lamp_pos, pos_wp), (self.lamp_axis, axis_wp) = (output((lamps, 3), np.float64, wp.vec3d)
                                                              for _ in range(2))
        self.intensity, intensity_wp = output(lamps, np.float64, wp.float64)
        self.outputs = [output(shape, np.float64, wp.float64), output(shape, np.bool_, wp.bool),
                        output(shape, np.float64, wp.float64), output(shape, np.int8, wp.int8)]
        self.launches = [wp.launch(gray_kernel, dim=stop_lamp - first_lamp, device=inputs.device, record_cmd=True,
                                   inputs=inputs._leading + [pos_wp, axis_wp, intensity_wp] + inputs._trailing
                                   + [first_lamp, first_point, stop_point],
                                   outputs=[out_wp for _, out_wp in self.outputs])
                         for first_lamp, stop_lamp, first_point, stop_point in _ranges(lamps, inputs.count)
                         if lamps and inputs.count]
        self._inputs_wp = (pos_wp, axis_wp, intensity_wp)       # the launches hold their addresses
        self._dim = lamps                   # the lamps a single launch runs over now

    def run(self, lamp_pos: np.ndarray, lamp_axis: np.ndarray, intensity: np.ndarray, copy: bool) -> GrayResult:
        """The outputs of the first len(lamp_pos) lamps (all of them unless the batch is one launch)."""
        lamps = len(lamp_pos)
        self.lamp_pos[:lamps] = lamp_pos
        self.lamp_axis[:lamps] = lamp_axis
        self.intensity[:lamps] = intensity
        if lamps != self._dim:
            self.launches[0].set_dim(lamps)
            self._dim = lamps
        if self.launches:
            in_parallel(self.launches)
        if lamps == len(self.lamp_pos):
            return GrayResult(*(out.copy() if copy else out for out, _ in self.outputs))
        return GrayResult(*(out[:lamps].copy() for out, _ in self.outputs))


def gray_per_exposure(mesh: "WarpMesh | None", points: ArrayLike, normals: ArrayLike, camera_pos: ArrayLike,
                      lamp_pos: ArrayLike, lamp_axis: ArrayLike, power_w: float, cone_angle_rad: float,
                      table: ArrayLike, camera_constant: float, pixel_area_m2: float, shadows: bool = True,
                      cone: bool = True, offset_m: float = 1e-5, profile: ArrayLike | None = None) -> GrayResult:
    """Gray per exposure c A_pixel Phi R / 8 for C candidate lamps x P sample points, in one
    call (GrayInputs, which keeps the fixed inputs, has the arguments' meaning). Returns
    GrayResult of (C, P) NumPy arrays."""
    return GrayInputs(mesh, points, normals, camera_pos, power_w, cone_angle_rad, table, camera_constant,
                      pixel_area_m2, shadows, cone, offset_m, profile)(lamp_pos, lamp_axis)
