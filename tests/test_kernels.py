"""The Warp kernels against their NumPy references (cell.physics.reference).

Gray values agree to 1e-5 relative with an identical zero pattern; visibility and shadows
agree except for rays that graze an edge, and those must be few and provably ambiguous
(a 1e-4 rad tilt of the reference ray flips its answer)."""
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from cell.core import geometry
from cell.physics import radiometry, reference as ref
from kernels import cone, gray, visibility
from kernels.cone import NO_CONE, free_cone_cosines
from kernels.funcs import SECTORS
from kernels.gray import GrayInputs, gray_per_exposure
from kernels.mesh import WarpMesh
from kernels.proximity import closest_points
from kernels.render import render
from kernels.visibility import combined_map, visibility_maps, visible_from_all

ROOT = Path(__file__).resolve().parents[1]
C_CAMERA = 1.5e16
A_PIXEL = 4.65e-6**2
P_LAMP = 0.23043
GAMMA = math.radians(12.0)
RTOL = 1e-5

# [phase_rad, rho, sigma1, m1, sigma2, m2]: phase-dependent, spike exponents into the thousands
METAL = np.array([
    [0.00, 0.040, 4.0, 20.0, 30.0, 1000.0],
    [0.30, 0.036, 3.0, 60.0, 20.0, 4000.0],
    [0.70, 0.030, 2.0, 150.0, 10.0, 10000.0],
    [1.20, 0.025, 1.0, 400.0, 5.0, 10000.0],
])
# a soft-edged lamp profile [off_axis_rad, relative] for the 12 deg cone: half at the nominal edge
SOFT = np.column_stack([np.radians([0.0, 2.0, 4.0, 5.0, 6.0, 7.0, 8.0]),
                        [1.0, 0.99, 0.93, 0.80, 0.50, 0.15, 0.0]])
ALUMINIUM = np.column_stack([np.radians([0, 10, 20, 30, 40, 60, 80]),
                             [0.0340, 0.0325, 0.0310, 0.02959, 0.0282, 0.0260, 0.0240],
                             np.full(7, 4.0), np.full(7, 6.0), np.full(7, 30.0), np.full(7, 400.0)])


def box(extents, center):
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


@pytest.fixture(scope="module")
def blocks():
    """A slab 100 x 100 x 20 mm (top face z = 10 mm) with a 100 mm tall wall along its +x side."""
    return WarpMesh.from_trimesh(trimesh.util.concatenate([
        box((0.10, 0.10, 0.02), (0.0, 0.0, 0.0)), box((0.02, 0.10, 0.10), (0.06, 0.0, 0.04))]))


@pytest.fixture(scope="module")
def hinge():
    mesh = trimesh.load(ROOT / "tasks" / "parts" / "hinge.stl")
    mesh.apply_scale(1e-3)                         # the task file says mm
    return WarpMesh.from_trimesh(mesh), mesh


def lamps_around(rng, center, count, radius=(0.1, 0.5), min_elevation=-0.3, aim_spread=0.03):
    """Random lamp positions around `center` and aims at points near it (so cones cut)."""
    az = rng.uniform(-np.pi, np.pi, count)
    el = rng.uniform(min_elevation, 1.4, count)
    pos = center + geometry.direction_from_angles(az, el) * rng.uniform(*radius, (count, 1))
    target = center + rng.uniform(-aim_spread, aim_spread, (count, 3))
    return pos, geometry.unit(target - pos)


def ambiguous_rays(mesh, origins, dirs, max_dist, normals, eps=1e-4):
    """Rays whose hit/miss flips when tilted by eps rad (they graze an edge), or that run
    within eps of their point's tangent plane."""
    dirs = geometry.unit(dirs)
    base = ref.ray_hits_any(mesh, origins, dirs, max_dist)
    helper = np.where(np.abs(dirs[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = geometry.unit(np.cross(dirs, helper))
    b = np.cross(dirs, a)
    flips = np.zeros(len(dirs), dtype=bool)
    for tilt in (a, -a, b, -b):
        flips |= ref.ray_hits_any(mesh, origins, geometry.unit(dirs + eps * tilt), max_dist) != base
    return flips | (np.abs(np.sum(dirs * normals, axis=1)) < eps)


def assert_gray_agrees(mesh, points, normals, lamps, warp, numpy, offset_m=1e-5):
    """Identical shadows except ambiguous grazing rays; identical zero pattern, dominant
    terms and off-axis angles; gray within RTOL where the reference is lit."""
    c, p = np.nonzero(warp.shadowed != numpy.shadowed)
    assert len(c) <= max(2, 1e-3 * warp.value.size), f"{len(c)} shadow mismatches"
    if len(c):
        n = geometry.unit(normals[p])
        assert ambiguous_rays(mesh, points[p] + offset_m * n, lamps[c] - points[p],
                              np.linalg.norm(lamps[c] - points[p], axis=1), n).all()
    same = warp.shadowed == numpy.shadowed
    np.testing.assert_array_equal(warp.value[same] > 0.0, numpy.value[same] > 0.0)
    np.testing.assert_array_equal(warp.dominant, numpy.dominant)
    np.testing.assert_allclose(warp.off_axis, numpy.off_axis, rtol=0, atol=1e-9)
    lit = same & (numpy.value > 0.0)
    np.testing.assert_allclose(warp.value[lit], numpy.value[lit], rtol=RTOL, atol=0)


def test_gray_matches_reference_beside_a_wall(blocks):
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(-0.045, 0.045, (40, 2)), np.full(40, 0.01)])
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.01]), 300)
    camera = np.array([-0.03, 0.01, 0.40])
    args = (points, normals, camera, lamps, aims, P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    warp, numpy = gray_per_exposure(blocks, *args), ref.gray_per_exposure(blocks, *args)
    cast = numpy.shadowed & (np.sum((lamps[:, None] - points[None]) * normals[None], axis=-1) > 0)
    assert 0.05 < cast.mean() < 0.5                   # the wall really casts shadows
    assert (numpy.value > 0).mean() > 0.1 and (numpy.off_axis > GAMMA / 2).mean() > 0.1
    assert set(np.unique(numpy.dominant)) == {-1, 0, 1, 2}
    assert_gray_agrees(blocks, points, normals, lamps, warp, numpy)


def test_gray_matches_reference_on_the_hinge(hinge):
    mesh, tm = hinge
    points, face = trimesh.sample.sample_surface(tm, 48, seed=3)
    normals = tm.face_normals[face]
    rng = np.random.default_rng(11)
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.004]), 200, radius=(0.08, 0.6))
    args = (points, normals, np.array([-0.025, 0.0, 0.5]), lamps, aims, P_LAMP, GAMMA, ALUMINIUM,
            C_CAMERA, A_PIXEL)
    warp, numpy = gray_per_exposure(mesh, *args), ref.gray_per_exposure(mesh, *args)
    assert (numpy.value > 0).mean() > 0.05
    assert_gray_agrees(mesh, points, normals, lamps, warp, numpy)
    for switch in ({"shadows": False}, {"cone": False}):
        assert_gray_agrees(mesh, points, normals, lamps, gray_per_exposure(mesh, *args, **switch),
                           ref.gray_per_exposure(mesh, *args, **switch))


def test_a_lamp_profile_scales_the_gray_as_the_reference_does(blocks):
    """With a soft-edged profile Warp == NumPy, and the gray is the cone-free gray times the
    profile at each point's off-axis angle (0 beyond its last angle, light beyond gamma/2)."""
    rng = np.random.default_rng(8)
    points = np.column_stack([rng.uniform(-0.045, 0.045, (40, 2)), np.full(40, 0.01)])
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.01]), 300)
    args = (points, normals, np.array([-0.03, 0.01, 0.40]), lamps, aims, P_LAMP, GAMMA, METAL,
            C_CAMERA, A_PIXEL)
    warp, numpy = (f(blocks, *args, profile=SOFT) for f in (gray_per_exposure, ref.gray_per_exposure))
    assert_gray_agrees(blocks, points, normals, lamps, warp, numpy)
    spill = (numpy.off_axis > GAMMA / 2) & (numpy.off_axis < SOFT[-1, 0]) & ~numpy.shadowed
    assert spill.sum() > 20 and np.all(warp.value[spill] > 0.0)
    no_cone = gray_per_exposure(blocks, *args, cone=False, profile=SOFT)     # the profile's axis intensity
    relative = np.interp(warp.off_axis, SOFT[:, 0], SOFT[:, 1], right=0.0)
    np.testing.assert_allclose(warp.value, no_cone.value * relative, rtol=1e-12, atol=0)
    np.testing.assert_allclose(no_cone.value, gray_per_exposure(blocks, *args, cone=False).value
                               * radiometry.axis_intensity(P_LAMP, GAMMA, SOFT) / radiometry.axis_intensity(P_LAMP, GAMMA),
                               rtol=1e-12, atol=0)
    hard = gray_per_exposure(blocks, *args, profile=[[0.0, 1.0], [0.02, 1.0], [GAMMA / 2, 1.0]])
    np.testing.assert_allclose(hard.value, gray_per_exposure(blocks, *args).value, rtol=1e-14, atol=0)


def test_spike_exponents_up_to_1e4_agree_in_float64():
    """Near the mirror direction c -> 1, where float32 would lose ~m * 6e-8 relative."""
    rng = np.random.default_rng(5)
    table = np.array([[0.0, 0.03, 4.0, 3000.0, 30.0, 10000.0]])      # one row: clamped everywhere
    camera = np.array([0.0, -0.2, 0.3])
    mirror = np.array([0.0, 0.2, 0.3])
    lamps = mirror + rng.normal(scale=2e-3, size=(400, 3))          # within ~1e-2 rad of the mirror
    points = np.zeros((1, 3))
    normals = np.array([[0.0, 0.0, 1.0]])
    args = (points, normals, camera, lamps, -lamps, P_LAMP, np.pi, table, C_CAMERA, A_PIXEL)
    warp, numpy = gray_per_exposure(None, *args), ref.gray_per_exposure(None, *args)
    assert np.all(np.isfinite(warp.value)) and (numpy.dominant == 2).mean() > 0.3
    np.testing.assert_allclose(warp.value, numpy.value, rtol=RTOL, atol=0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m1=st.floats(1.0, 1e3), m2=st.floats(1e3, 1e5),
       sigma1=st.floats(0.0, 10.0), sigma2=st.floats(0.0, 100.0))
def test_any_valid_parameters_give_finite_gray_equal_to_reference(seed, m1, m2, sigma1, sigma2):
    rng = np.random.default_rng(seed)
    table = np.array([[0.0, 0.05, sigma1, m1, sigma2, m2], [2.0, 0.02, sigma1, 2 * m1, sigma2, 2 * m2]])
    points = rng.normal(scale=0.01, size=(16, 3))
    normals = rng.normal(size=(16, 3))
    lamps = rng.normal(scale=0.3, size=(8, 3))
    args = (points, normals, rng.normal(scale=0.3, size=3), lamps, -lamps, P_LAMP, 2.0, table,
            C_CAMERA, A_PIXEL)
    warp, numpy = gray_per_exposure(None, *args), ref.gray_per_exposure(None, *args)
    assert np.all(np.isfinite(warp.value)) and np.all(warp.value >= 0.0)
    np.testing.assert_allclose(warp.value, numpy.value, rtol=RTOL, atol=0)
    np.testing.assert_array_equal(warp.dominant, numpy.dominant)


def test_lamp_or_camera_behind_the_surface_gives_zero():
    points, normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    lamps = np.array([[0.1, 0.0, -0.3], [0.3, 0.0, 0.0], [0.1, 0.0, 0.3]])
    common = (lamps, -lamps, P_LAMP, np.pi, METAL, C_CAMERA, A_PIXEL)
    front = gray_per_exposure(None, points, normals, np.array([0.0, 0.0, 0.5]), *common)
    np.testing.assert_array_equal(front.value[:2, 0], 0.0)             # below / in the tangent plane
    np.testing.assert_array_equal(front.shadowed[:, 0], [True, True, False])
    np.testing.assert_array_equal(front.dominant[:, 0], [-1, -1, 0])
    assert front.value[2, 0] > 0.0
    behind = gray_per_exposure(None, points, normals, np.array([0.0, 0.0, -0.5]), *common)
    np.testing.assert_array_equal(behind.value, 0.0)
    np.testing.assert_array_equal(behind.dominant, -1)


def test_cone_cuts_off_exactly_outside_half_the_opening_angle():
    """Lamp 0.3 m above a plane aiming straight down: points at 5.9 and 6.1 deg off axis."""
    off = np.radians([0.0, 3.0, 5.9, 6.1, 10.0])
    points = np.column_stack([0.3 * np.tan(off), np.zeros(5), np.zeros(5)])
    normals = np.tile([0.0, 0.0, 1.0], (5, 1))
    args = (points, normals, np.array([0.0, 0.0, 0.5]), [[0.0, 0.0, 0.3]], [[0.0, 0.0, -1.0]],
            P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    inside = gray_per_exposure(None, *args)
    np.testing.assert_allclose(inside.off_axis[0], off, atol=1e-12)
    assert np.all(inside.value[0, :3] > 0.0)
    np.testing.assert_array_equal(inside.value[0, 3:], 0.0)
    no_cone = gray_per_exposure(None, *args, cone=False)
    np.testing.assert_array_equal(no_cone.value[0, :3], inside.value[0, :3])
    assert np.all(no_cone.value[0, 3:] > 0.0)


def test_the_rods_lamp_at_040_m_with_r_0252_gives_gray_130_at_f62_and_11_7_ms():
    """Physics notes' worked check: Phi(0.40 m) = 41.84 W/m^2, R = 0.252 (diffuse, on axis)."""
    table = np.array([[0.0, 0.252, 0.0, 2.0, 0.0, 3.0]])
    g = gray_per_exposure(None, np.zeros((1, 3)), [[0.0, 0.0, 1.0]], np.array([0.0, 0.0, 0.35]),
                          [[0.0, 0.0, 0.40]], [[0.0, 0.0, -1.0]], P_LAMP, GAMMA, table,
                          C_CAMERA, A_PIXEL)
    assert g.value[0, 0] * 11.7e-3 / 6.2**2 == pytest.approx(130.0, abs=0.5)


def test_visibility_matches_reference_beside_a_wall(blocks):
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-0.045, 0.045, (12, 2)), np.full(12, 0.01)])
    normals = np.tile([0.0, 0.0, 1.0], (12, 1))
    az = np.radians(np.arange(-180.0, 180.0, 5.0))
    el = np.radians(np.arange(-10.0, 90.0, 5.0))                      # includes the tangent plane
    warp = visibility_maps(blocks, points, normals, np.eye(3), az, el)
    numpy = ref.visibility_maps(blocks, points, normals, np.eye(3), az, el)
    assert warp.shape == (12, len(el), len(az)) and warp.dtype == bool
    assert not warp[:, el <= 0].any()                                   # the slab hides these
    assert 0.1 < 1 - warp[:, el > 0].mean() < 0.5                       # the wall hides these
    assert_visibility_agrees(blocks, points, normals, np.eye(3), az, el, warp, numpy)
    np.testing.assert_array_equal(combined_map(warp), warp.all(axis=0))


def near_the_knuckle():
    """(points, normals, frame, azimuths, elevations): 10 samples on the hinge's leaf near the
    knuckle, the feature frame rotated about the normal, a 6 deg grid above the leaf."""
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.026, -0.005, 10), rng.uniform(-0.015, 0.015, 10),
                              np.full(10, 0.004)])
    normals = np.tile([0.0, 0.0, 1.0], (10, 1))
    frame = geometry.frame_from_normal([0.0, 0.0, 1.0], reference=(1.0, 1.0, 0.0))
    return points, normals, frame, np.radians(np.arange(-180.0, 180.0, 6.0)), np.radians(np.arange(3.0, 90.0, 6.0))


def test_visibility_matches_reference_on_the_hinge_in_a_tilted_frame(hinge):
    """Samples on the leaf near the knuckle; the feature frame is rotated about the normal."""
    mesh, _ = hinge
    points, normals, frame, az, el = near_the_knuckle()
    warp = visibility_maps(mesh, points, normals, frame, az, el)
    numpy = ref.visibility_maps(mesh, points, normals, frame, az, el)
    assert 0.05 < 1 - warp.mean() < 0.6
    assert_visibility_agrees(mesh, points, normals, frame, az, el, warp, numpy)


@pytest.mark.parametrize("free_cones", [True, False])
def test_the_directions_every_sample_sees_are_their_maps_combined(hinge, blocks, free_cones):
    """visible_from_all (each direction's samples in turn until one does not see it) is
    combined_map of the samples' own maps, cell for cell: beside the hinge's knuckle in a tilted
    frame (the reference's maps too), beside the wall with samples on the slab and on the
    wall's side; every direction with no samples, none with no directions."""
    mesh, _ = hinge
    points, normals, frame, az, el = near_the_knuckle()
    combined = visible_from_all(mesh, points, normals, frame, az, el, free_cones=free_cones)
    np.testing.assert_array_equal(combined, combined_map(visibility_maps(mesh, points, normals, frame, az, el)))
    assert combined.shape == (len(el), len(az)) and 0.05 < combined.mean() < 0.95
    reference = ref.visibility_maps(mesh, points, normals, frame, az, el).all(axis=0)
    assert np.count_nonzero(combined != reference) <= 2
    rng = np.random.default_rng(6)
    points = np.vstack([np.column_stack([rng.uniform(-0.045, 0.045, (8, 2)), np.full(8, 0.01)]),
                        [[0.03, 0.0, 0.02], [0.03, 0.01, 0.03]]])
    normals = np.vstack([np.tile([0.0, 0.0, 1.0], (8, 1)), np.tile([-1.0, 0.0, 0.0], (2, 1))])
    az, el = np.radians(np.arange(-180.0, 180.0, 4.0)), np.radians(np.arange(-90.0, 90.1, 4.0))
    combined = visible_from_all(blocks, points, normals, np.eye(3), az, el, free_cones=free_cones)
    np.testing.assert_array_equal(combined, combined_map(visibility_maps(blocks, points, normals, np.eye(3), az, el)))
    assert combined.any() and not combined.all()
    assert visible_from_all(blocks, np.zeros((0, 3)), np.zeros((0, 3)), np.eye(3), az, el).all()
    assert visible_from_all(blocks, points, normals, np.eye(3), az, el[:0]).shape == (0, len(az))


def assert_visibility_agrees(mesh, points, normals, frame, az, el, warp, numpy, offset_m=1e-5):
    p, e, a = np.nonzero(warp != numpy)
    assert len(p) <= max(2, 2e-3 * warp.size), f"{len(p)} of {warp.size} cells differ"
    if len(p):
        dirs = ref.feature_directions(frame, az, el)[e, a]
        n = geometry.unit(normals[p])
        assert ambiguous_rays(mesh, points[p] + offset_m * n, dirs, 10.0, n).all()


def test_a_ray_through_the_walls_top_edge_counts_as_ambiguous(blocks):
    """The tolerance above is honest: an exact edge hit flips under a 1e-4 rad tilt, a clear
    ray does not."""
    origin = np.array([[0.0, 0.0, 0.01 + 1e-5]] * 2)
    dirs = geometry.unit(np.array([[0.05, 0.0, 0.08 - 1e-5], [0.0, 0.0, 1.0]]))
    normals = np.array([[0.0, 0.0, 1.0]] * 2)
    np.testing.assert_array_equal(ambiguous_rays(blocks, origin, dirs, 10.0, normals), [True, False])


def sectors_of(normal, dirs):
    """The azimuth sector of each unit direction about the normal, as kernels.funcs defines it:
    u = n x (x, or y for n near x), w = n x u; the diamond angle of (<d, u>, <d, w>)."""
    e = [0.0, 1.0, 0.0] if abs(normal[0]) > 0.9 else [1.0, 0.0, 0.0]
    u = geometry.unit(np.cross(normal, e))
    w = np.cross(normal, u)
    x, y = dirs @ u, dirs @ w
    r = np.abs(x) + np.abs(y)
    diamond = np.where(y >= 0, np.where(x >= 0, y / r, 1 - x / r), np.where(x < 0, 2 - y / r, 3 + x / r))
    return np.minimum((diamond * SECTORS / 4).astype(int), SECTORS - 1)


def test_the_free_cone_beside_the_wall_reaches_its_top_edge(blocks):
    """At (0, 0, 10 mm) on the slab the wall's near top edge, 50 mm across and 80 mm up, is the
    nearest to the normal: beta = atan2(x_wall, z_top - z_origin), less the margin (float32
    geometry as the mesh stores it); the sectors facing away from the wall (more than 50 deg
    from +x) see nothing above: 90 deg. On a lone slab every cone is 90 deg. Under the slab the
    axis meets it: no cone."""
    x_wall = blocks.vertices[blocks.vertices[:, 0] > 0.04, 0].min()
    z_top = blocks.vertices[:, 2].max()
    origin = np.array([[0.0, 0.0, 0.01 + 1e-5]])
    up = np.array([[0.0, 0.0, 1.0]])
    beta = math.atan2(x_wall, z_top - origin[0, 2])
    assert math.degrees(beta) == pytest.approx(32.0, abs=0.1)
    free, sectors = free_cone_cosines(blocks, origin, up)
    np.testing.assert_allclose(free, [math.cos(beta - cone.MARGIN_RAD)], rtol=0, atol=1e-12)
    az = np.radians(np.arange(0.0, 360.0, 0.25))
    around = np.column_stack([np.cos(az), np.sin(az), np.zeros_like(az)])
    k = sectors_of(up[0], around)
    facing = np.unique(k[np.abs(np.angle(np.exp(1j * az))) < np.radians(50.0)])
    away = np.setdiff1d(np.arange(SECTORS), facing)
    assert len(away) >= SECTORS // 2 and sectors[0, k[0]] == free[0]          # +x: the wall's edge
    np.testing.assert_allclose(sectors[0, away], math.sin(cone.MARGIN_RAD), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(sectors[0, facing], free[0])        # the wall's faces span them all
    assert np.all(sectors[0] <= free[0])                                # a sector's cone: never narrower
    slab = WarpMesh.from_trimesh(box((0.10, 0.10, 0.02), (0.0, 0.0, 0.0)))
    free, sectors = free_cone_cosines(slab, origin, up)
    np.testing.assert_allclose(np.append(free, sectors), math.sin(cone.MARGIN_RAD), rtol=0, atol=1e-15)
    free, sectors = free_cone_cosines(blocks, [[0.0, 0.0, -0.02]], up)
    assert free[0] == NO_CONE and np.all(sectors == NO_CONE)


def test_no_ray_inside_a_free_cone_hits_the_hinge(hinge):
    """Soundness against the brute-force reference: rays from hinge samples inside their
    sectors' cones never hit; the narrowest cone is tight (some ray 0.02 rad outside it hits; a
    sector's may be narrower than it need be: a triangle counts with its nearest point in each
    sector it reaches)."""
    mesh, _ = hinge
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-0.026, -0.005, 6), rng.uniform(-0.015, 0.015, 6), np.full(6, 0.004)])
    normals = np.tile([0.0, 0.0, 1.0], (6, 1))
    origins = points + 1e-5 * normals
    free, sectors = free_cone_cosines(mesh, origins, normals)
    assert np.all(free < 1.0) and np.all(sectors <= free[:, None])
    az = np.radians(np.arange(0.0, 360.0, 0.5))
    flat = np.column_stack([np.cos(az), np.sin(az), np.zeros_like(az)])
    assert np.mean(sectors < free[:, None]) > 0.25                     # sectors do widen them
    for p in range(len(points)):
        rays = np.repeat(origins[p:p + 1], len(az), 0)
        beta = np.arccos(np.minimum(sectors[p], 1.0))[sectors_of(normals[p], flat)]
        inside = geometry.direction_from_angles(az, np.pi / 2 - beta * rng.uniform(0.0, 1.0, len(az)))
        assert not ref.ray_hits_any(mesh, rays, inside, 10.0).any()
        outside = geometry.direction_from_angles(az, np.pi / 2 - np.arccos(free[p]) - 0.02)
        assert ref.ray_hits_any(mesh, rays, outside, 10.0).any()


def test_free_cones_change_no_gray_and_no_visibility(hinge, monkeypatch):
    """The cones only spare rays: with them (found once the lamps make them worth it) the gray
    and the visibility maps equal those cast without them, bit for bit."""
    mesh, _ = hinge
    rng = np.random.default_rng(5)
    points = np.column_stack([rng.uniform(-0.026, -0.005, 32), rng.uniform(-0.015, 0.015, 32), np.full(32, 0.004)])
    normals = np.tile([0.0, 0.0, 1.0], (32, 1))
    lamps, aims = lamps_around(rng, np.array([-0.015, 0.0, 0.004]), 2 * len(mesh.faces), min_elevation=0.0)
    args = (mesh, points, normals, np.array([-0.01, 0.02, 0.3]), P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    with_cones = GrayInputs(*args)
    first, rest = with_cones(lamps[:3], aims[:3]), with_cones(lamps[3:], aims[3:])
    assert with_cones.has_free_cones
    az, el = np.radians(np.arange(-180.0, 180.0, 2.0)), np.radians(np.arange(1.0, 90.0, 2.0))
    maps = visibility_maps(mesh, points, normals, np.eye(3), az, el)
    monkeypatch.setattr(gray, "worth_finding", lambda *_: False)
    monkeypatch.setattr(visibility, "worth_finding", lambda *_: False)
    without = GrayInputs(*args)(lamps, aims)
    assert 0.02 < without.shadowed.mean() < 0.5
    for field in ("value", "shadowed", "off_axis", "dominant"):
        np.testing.assert_array_equal(getattr(first, field), getattr(without, field)[:3])
        np.testing.assert_array_equal(getattr(rest, field), getattr(without, field)[3:])
    np.testing.assert_array_equal(maps, visibility_maps(mesh, points, normals, np.eye(3), az, el))


def in_cylinder(rng, count, axis_point, radius, low):
    """Random origins above z = low within `radius` of the vertical axis through axis_point."""
    r, a = radius * np.sqrt(rng.uniform(0.0, 1.0, count)), rng.uniform(-np.pi, np.pi, count)
    return np.column_stack([axis_point[0] + r * np.cos(a), axis_point[1] + r * np.sin(a),
                            low + rng.uniform(0.0, 0.002, count)])


def test_a_cylinders_common_cone_lets_no_ray_hit_and_is_no_wider_than_its_points_own(blocks):
    """cone.cylinder_cone_cosine on the slab beside the wall: rays from random origins in the
    cylinder (5 mm about (20, 0) mm, from 10 um above the slab up) in random directions inside
    its cone meet nothing (the brute-force reference); the cone is no wider than the free cone
    of the cylinder's origin nearest the wall's top edge (free_cone_cosines), and within a
    degree of it; beside nothing but the slab it is the open sky (90 deg less the margin); a
    cylinder reaching the wall, or under the slab, has none."""
    rng = np.random.default_rng(29)
    axis_point, radius, low = np.array([0.02, 0.0, 0.0]), 0.005, 0.01 + 1e-5
    cosine = cone.cylinder_cone_cosine(blocks, axis_point, [0.0, 0.0, 1.0], radius, low)
    beta = math.acos(cosine)
    nearest = np.array([[0.02 + radius, 0.0, low]])
    own = free_cone_cosines(blocks, nearest, [[0.0, 0.0, 1.0]])[0][0]
    assert cosine >= own and math.acos(own) - beta < math.radians(1.0) and 0.3 < beta < 1.2
    origins = in_cylinder(rng, 4000, axis_point, radius, low)
    directions = geometry.direction_from_angles(rng.uniform(-np.pi, np.pi, 4000),
                                                np.pi / 2 - beta * rng.uniform(0.0, 1.0, 4000))
    assert not ref.ray_hits_any(blocks, origins, directions, 10.0).any()
    outside = geometry.direction_from_angles(np.zeros(50), np.pi / 2 - math.acos(own) - 0.02 - np.zeros(50))
    assert ref.ray_hits_any(blocks, np.repeat(nearest, 50, axis=0), outside, 10.0).all()   # the wall is there
    slab = WarpMesh.from_trimesh(box((0.10, 0.10, 0.02), (0.0, 0.0, 0.0)))
    assert cone.cylinder_cone_cosine(slab, axis_point, [0.0, 0.0, 1.0], radius, low) == pytest.approx(
        math.sin(cone.MARGIN_RAD), abs=1e-15)
    assert cone.cylinder_cone_cosine(blocks, axis_point, [0.0, 0.0, 1.0], 0.031, low) == NO_CONE
    assert cone.cylinder_cone_cosine(blocks, axis_point, [0.0, 0.0, 1.0], radius, -0.02) == NO_CONE


def test_flat_patches_common_cones_change_no_gray_and_no_shadow(blocks):
    """GrayInputs told which rows are flat patches (`flat`: a certificate's dense patches) casts
    fewer rays and gives the gray, shadows, off-axis angles, dominant terms and the shadow flags
    of a lamp at the camera of one not told, bit for bit; a patch whose normals differ (curved)
    gets no cone, one beside the wall a narrower one than one in the open."""
    rng = np.random.default_rng(31)
    near, far = (np.column_stack([c + rng.uniform(-0.004, 0.004, (600, 2)), np.full(600, 0.01)])
                 for c in ([0.02, 0.0], [-0.03, 0.02]))
    tilted = geometry.unit(np.column_stack([rng.uniform(-0.1, 0.1, (100, 2)), np.ones(100)]))
    points = np.vstack([near, far, far[:100]])
    normals = np.vstack([np.tile([0.0, 0.0, 1.0], (1200, 1)), tilted])
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.01]), 12)
    args = (blocks, points, normals, np.array([-0.02, 0.01, 0.3]), P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    told = GrayInputs(*args, flat=[(0, 600), (600, 1200), (1200, 1300)])
    cosines = told._flat_cones([(0, 600), (600, 1200), (1200, 1300)])
    assert cosines[0] > cosines[600] > 0.0 and cosines[1200] == NO_CONE
    alone = GrayInputs(*args)
    for mine, own in ((told(lamps, aims), alone(lamps, aims)), (told(lamps[:1], aims[:1]), alone(lamps[:1], aims[:1]))):
        for field in ("value", "shadowed", "off_axis", "dominant"):
            np.testing.assert_array_equal(getattr(mine, field), getattr(own, field))
    camera = np.array([[-0.02, 0.01, 0.3], [0.05, 0.0, 0.05]])
    np.testing.assert_array_equal(told.shadowed(camera), alone.shadowed(camera))
    assert 0.02 < alone(lamps, aims).shadowed.mean() < 0.9 and alone.shadowed(camera)[1].any()


def test_small_calls_reuse_their_launch_but_not_their_results(blocks):
    """Small calls replay one recorded launch, over as many lamps as each has (more, fewer, as
    many as before): each result is its own array, equal to a call of its own."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.045, 0.045, (20, 2)), np.full(20, 0.01)])
    normals = np.tile([0.0, 0.0, 1.0], (20, 1))
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.01]), 40)
    args = (points, normals, np.array([0.0, 0.0, 0.4]), P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    g = GrayInputs(blocks, *args)
    cuts = [(0, 9), (9, 18), (18, 23), (23, 35), (35, 36), (31, 40)]
    got = [g(lamps[a:b], aims[a:b]) for a, b in cuts]
    assert set(g._launches.values()) == {None} and len(g._single.lamp_pos) == 12
    assert not np.array_equal(got[0].value, got[1].value)
    for result, (a, b) in zip(got, cuts):
        want = gray_per_exposure(blocks, *args[:3], lamps[a:b], aims[a:b], *args[3:])
        for field in ("value", "shadowed", "off_axis", "dominant"):
            assert getattr(result, field).shape == (b - a, 20)
            np.testing.assert_array_equal(getattr(result, field), getattr(want, field))


def test_each_lamp_its_own_power_equals_a_call_per_power(blocks):
    """Lamps of several powers in one call (power_w per lamp: the emitter points of several lights)
    give, bit for bit, what a call of each power gives, and the reference's values."""
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.045, 0.045, (30, 2)), np.full(30, 0.01)])
    normals = np.tile([0.0, 0.0, 1.0], (30, 1))
    lamps, aims = lamps_around(rng, np.array([0.0, 0.0, 0.01]), 12)
    powers = np.repeat([0.05, 0.2, 1.3], 4)
    args = (points, normals, np.array([0.0, 0.0, 0.4]))
    together = GrayInputs(blocks, *args, P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)(lamps, aims, powers)
    for k in range(3):
        rows = slice(4 * k, 4 * k + 4)
        alone = gray_per_exposure(blocks, *args, lamps[rows], aims[rows], powers[4 * k], GAMMA, METAL, C_CAMERA,
                                  A_PIXEL)
        for field in ("value", "shadowed", "off_axis", "dominant"):
            np.testing.assert_array_equal(getattr(together, field)[rows], getattr(alone, field))
        want = ref.gray_per_exposure(blocks, *args, lamps[rows], aims[rows], powers[4 * k], GAMMA, METAL, C_CAMERA,
                                     A_PIXEL)
        np.testing.assert_allclose(together.value[rows], want.value, rtol=1e-9, atol=1e-12 * want.value.max())


@settings(max_examples=40, deadline=None)
@given(lamp_polar=st.one_of(st.floats(0.0, 1.5707), st.sampled_from([0.0, 1.5707963, 1.5707963267]),
                            st.floats(1.6, 3.14)),
       camera_polar=st.one_of(st.floats(0.0, 1.5707), st.floats(1.58, 3.1)),
       azimuths=st.tuples(st.floats(-np.pi, np.pi), st.floats(-np.pi, np.pi)),
       near_mirror=st.booleans(), m1=st.floats(1.0, 1e3), m2=st.floats(1e3, 1e5), aim_off=st.floats(0.0, 3.1))
@example(lamp_polar=0.0, camera_polar=6.103515625e-05, azimuths=(0.0, 0.0), near_mirror=True, m1=1.0, m2=1000.0,
         aim_off=0.0)                                  # 6e-8 rad from the mirror: acos's phase angle was 4 % off
@example(lamp_polar=0.75, camera_polar=0.75, azimuths=(0.0, 0.0), near_mirror=False, m1=1.0, m2=1000.0,
         aim_off=0.0)                                  # the camera beside the lamp: acos read alpha 1.5e-8, 1e-8 off
def test_gray_equals_the_brdf_written_with_numpy_power(lamp_polar, camera_polar, azimuths, near_mirror, m1, m2,
                                                       aim_off):
    """The kernel's forms (c^m = exp(m ln c) from one log, the off-axis angle as a chord's
    2 asin(|a + s| / 2), interpolation slopes and I(0) computed once) against eq. (6)-(11) written
    directly: numpy.power, the phase and off-axis angles by atan2 (|a x s|, <a, -s>), over grazing
    and back-facing lamps and cameras, a camera at the mirror direction and exponents up to 1e5. Finite, never negative."""
    n = np.array([0.0, 0.0, 1.0])
    s = geometry.direction_from_angles(azimuths[0], np.pi / 2 - lamp_polar)
    v = geometry.direction_from_angles(azimuths[1], np.pi / 2 - camera_polar)
    if near_mirror:                                     # within ~1e-3 rad of the mirror direction
        v = geometry.unit(2 * (s @ n) * n - s + 1e-3 * v)
    d, distance = 0.3 * s, 0.3
    axis = geometry.unit(np.cross(s, [0.3, 0.5, 0.7]))  # aim_off away from the point
    aim = -s * math.cos(aim_off) + axis * math.sin(aim_off)
    table = np.array([[0.0, 0.05, 2.0, m1, 20.0, m2], [2.0, 0.03, 1.0, 2 * m1, 10.0, 2 * m2]])
    g = gray_per_exposure(None, np.zeros((1, 3)), n[None], 0.4 * v, d[None], aim[None], P_LAMP, np.pi, table,
                          C_CAMERA, A_PIXEL)
    assert np.isfinite(g.value).all() and g.value[0, 0] >= 0.0
    off_axis = math.atan2(np.linalg.norm(np.cross(aim, -s)), aim @ -s)
    assume(abs(off_axis - np.pi / 2) > 1e-9)            # the cone's edge: either side is right
    assert g.off_axis[0, 0] == pytest.approx(off_axis, abs=1e-9)
    cos_i, cos_e, cos_a = s @ n, v @ n, float(np.clip(s @ v, -1, 1))
    alpha = math.atan2(np.linalg.norm(np.cross(s, v)), s @ v)   # not acos(cos_a): ill-conditioned near 0
    rho, s1, e1, s2, e2 = (np.interp(alpha, table[:, 0], table[:, k]) for k in range(1, 6))
    c = 2 * cos_e * cos_i - cos_a
    front = cos_i > 0 and cos_e > 0
    lobes = s1 * np.power(min(c, 1.0), e1) + s2 * np.power(min(c, 1.0), e2) if front and c > 0 else 0.0
    reflectance = rho * (cos_i + lobes) if front else 0.0
    lit = off_axis <= np.pi / 2 and cos_i > 0
    intensity = P_LAMP / (2 * np.pi * (1 - math.cos(np.pi / 2)))
    want = C_CAMERA * A_PIXEL * intensity / distance**2 * reflectance / 8 if lit else 0.0
    assert g.value[0, 0] == pytest.approx(want, rel=1e-9, abs=0.0)


def test_bad_tables_and_shapes_are_refused():
    args = (np.zeros((1, 3)), [[0.0, 0.0, 1.0]], np.array([0.0, 0.0, 1.0]), [[0.0, 0.0, 1.0]],
            [[0.0, 0.0, -1.0]], P_LAMP, GAMMA)
    with pytest.raises(ValueError, match="ascending"):
        gray_per_exposure(None, *args, METAL[::-1], C_CAMERA, A_PIXEL)
    with pytest.raises(ValueError, match=r"\(K, 6\)"):
        gray_per_exposure(None, *args, METAL[:, :5], C_CAMERA, A_PIXEL)
    for profile, message in ((SOFT[:, :1], r"\(M >= 2, 2\)"), (SOFT[:1], r"\(M >= 2, 2\)"),
                             (SOFT[::-1], "start at 0"), (SOFT[1:], "start at 0")):
        with pytest.raises(ValueError, match=message):
            gray_per_exposure(None, *args, METAL, C_CAMERA, A_PIXEL, profile=profile)


def test_a_vec3d_view_reads_the_arrays_own_memory_with_vec3ds_values():
    """_arrays.vec3d_view: the values vec3d copies, over the array's own memory (read-only ones
    too); anything but C-contiguous float64 (N, 3) refused."""
    from kernels import _arrays
    a = np.random.default_rng(3).normal(size=(50, 3))
    a.flags.writeable = False
    view = _arrays.vec3d_view(a, "points")
    assert view.ptr == a.ctypes.data and np.array_equal(view.numpy(), _arrays.vec3d(a, "points").numpy())
    for bad in (a[::2], a.T.copy(), a.astype(np.float32), a[:, :2].copy()):
        with pytest.raises(ValueError, match="C-contiguous float64"):
            _arrays.vec3d_view(bad, "points")


def test_gray_inputs_of_arrays_in_any_layout_equal_those_of_contiguous_copies(blocks):
    """GrayInputs views its points and normals (_arrays.vec3d_view) once made C-contiguous: a
    column-major or strided points and normals array gives the contiguous copies' gray bit for bit."""
    rng = np.random.default_rng(5)
    points = np.asfortranarray(np.column_stack([rng.uniform(-0.05, 0.05, (40, 2)), np.full(40, 0.01)]))
    normals = np.asfortranarray(np.tile([0.0, 0.0, 2.0], (80, 1)))[::2]
    lamps = np.array([[0.1, 0.05, 0.3], [-0.2, 0.1, 0.2]])
    args = (np.array([0.0, 0.0, 0.5]), P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    assert not points.flags.c_contiguous and not normals.flags.c_contiguous
    for shadow_mesh in (None, blocks):
        a = GrayInputs(shadow_mesh, points, normals, *args)(lamps, -lamps)
        b = GrayInputs(shadow_mesh, np.ascontiguousarray(points), np.ascontiguousarray(normals), *args)(lamps, -lamps)
        assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("value", "shadowed", "off_axis", "dominant"))
        assert np.any(a.value > 0)


def test_a_lamps_and_materials_kernel_arrays_are_made_once_and_equal_those_made_anew():
    """gray.lamp_and_material: I(0), the profile's solid angle and the kernels' profile and table
    arrays equal those made for each GrayInputs (emission.axis_intensity, profile_solid_angle,
    _arrays.profile2d, table2d), the same objects for equal values, others for others; a bad
    table still refused, and not kept."""
    from kernels import _arrays, emission
    for profile in (None, SOFT):
        for table in (METAL, ALUMINIUM):
            kept = gray.lamp_and_material(P_LAMP, GAMMA, profile, table)
            assert kept[0] == emission.axis_intensity(P_LAMP, GAMMA, profile)
            assert kept[1] == emission.profile_solid_angle(emission.hard_cone_profile(GAMMA) if profile is None else profile)
            assert np.array_equal(kept[2].numpy(), _arrays.profile2d(profile, GAMMA).numpy())
            assert np.array_equal(kept[3].numpy(), _arrays.table2d(table).numpy())
            again = gray.lamp_and_material(P_LAMP, GAMMA, None if profile is None else profile.copy(), table.copy())
            assert all(a is b for a, b in zip(kept[2:], again[2:])) and kept[:2] == again[:2]
    assert gray.lamp_and_material(2 * P_LAMP, GAMMA, None, METAL)[0] == 2 * gray.lamp_and_material(P_LAMP, GAMMA, None, METAL)[0]
    assert gray.lamp_and_material(P_LAMP, GAMMA, None, METAL)[2] is not gray.lamp_and_material(P_LAMP, GAMMA, SOFT, METAL)[2]
    for _ in range(2):
        with pytest.raises(ValueError, match="ascending"):
            gray.lamp_and_material(P_LAMP, GAMMA, None, METAL[::-1])


@pytest.fixture(scope="module")
def plate_scene():
    """A 200 mm square plate (z = 0, normal +z) with a 20 mm cube on it, camera 0.5 m above."""
    plate = trimesh.Trimesh([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]],
                            [[0, 1, 2], [0, 2, 3]])
    mesh = WarpMesh.from_trimesh(trimesh.util.concatenate([plate, box((0.02,) * 3, (0.0413, 0.0037, 0.01))]))
    u = np.linspace(-0.25, 0.25, 41)                                   # tan of the pixel angles
    X, Y = np.meshgrid(u, u)
    dirs = geometry.unit(np.column_stack([X.ravel(), Y.ravel(), -np.ones(X.size)]))
    lamp = np.array([0.15, 0.02, 0.1])
    light = (mesh, np.array([0.0, 0.0, 0.5]), dirs, lamp, geometry.unit(-lamp), P_LAMP,
             math.radians(40.0), ALUMINIUM, C_CAMERA, A_PIXEL)
    return light


def test_render_equals_the_gray_kernel_at_its_hit_points(plate_scene):
    mesh, origin, dirs, lamp, aim, *rest = plate_scene
    out = render(mesh, origin, dirs, lamp, aim, *rest)
    on_plate = out.hit & (np.abs(out.normal[:, 2] - 1.0) < 1e-12) & (out.depth > 0.49 / np.abs(dirs[:, 2]))
    assert (~out.hit).sum() > 100 and on_plate.sum() > 900
    assert np.all(np.isinf(out.depth[~out.hit])) and np.all(out.value[~out.hit] == 0.0)
    np.testing.assert_allclose(out.depth[on_plate], 0.5 / -dirs[on_plate, 2], rtol=1e-6)
    points = origin + out.depth[out.hit, None] * dirs[out.hit]
    g = gray_per_exposure(mesh, points, out.normal[out.hit], origin, lamp[None], aim[None], *rest)
    np.testing.assert_allclose(out.value[out.hit], g.value[0], rtol=1e-12, atol=0)
    assert g.shadowed[0].sum() > 20 and (g.off_axis[0] > math.radians(20.0)).sum() > 20


@pytest.mark.parametrize("profile", [None, SOFT * [40.0 / 12.0, 1.0]], ids=["hard-cone", "soft-edge"])
def test_render_matches_the_numpy_renderer(plate_scene, profile):
    """Looser than 1e-5: Warp's hit distance is float32 (3e-8 m at 0.5 m), and the spike
    (m = 400) turns that into ~1e-5 relative. The soft edge: the profile above, for the 40 deg cone."""
    warp, numpy = render(*plate_scene, profile=profile), ref.render(*plate_scene, profile=profile)
    np.testing.assert_array_equal(warp.hit, numpy.hit)
    np.testing.assert_allclose(warp.normal, numpy.normal, atol=1e-6)
    np.testing.assert_allclose(warp.depth[warp.hit], numpy.depth[numpy.hit], rtol=1e-6)
    np.testing.assert_array_equal(warp.value > 0.0, numpy.value > 0.0)
    np.testing.assert_allclose(warp.value, numpy.value, rtol=1e-4, atol=0)


def test_render_of_several_point_lamps_is_the_sum_of_each_one_s_and_the_numpy_renderer_s(plate_scene):
    """An extended light's emitter points in one launch: each shaded with its own shadow ray
    (the cube casts a soft shadow), the sum of rendering each alone, and the NumPy reference's."""
    mesh, origin, dirs, lamp, aim, *rest = plate_scene
    lamps = lamp + np.array([[0.0, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.02, -0.01, 0.02]])
    axes = geometry.unit(-lamps)
    out = render(mesh, origin, dirs, lamps, axes, *rest)
    alone = [render(mesh, origin, dirs, p, a, *rest).value for p, a in zip(lamps, axes)]
    np.testing.assert_allclose(out.value, np.sum(alone, axis=0), rtol=1e-12, atol=0)
    partly = (np.array(alone) > 0).sum(axis=0) == 2
    assert partly.sum() > 5                               # the penumbra: some points hidden
    np.testing.assert_allclose(out.value, ref.render(mesh, origin, dirs, lamps, axes, *rest).value, rtol=1e-4, atol=0)


def test_render_with_a_profile_equals_the_gray_kernel_with_it(plate_scene):
    mesh, origin, dirs, lamp, aim, *rest = plate_scene
    profile = SOFT * [40.0 / 12.0, 1.0]
    out = render(mesh, origin, dirs, lamp, aim, *rest, profile=profile)
    points = origin + out.depth[out.hit, None] * dirs[out.hit]
    g = gray_per_exposure(mesh, points, out.normal[out.hit], origin, lamp[None], aim[None], *rest,
                          profile=profile)
    np.testing.assert_allclose(out.value[out.hit], g.value[0], rtol=1e-12, atol=0)
    lit_beyond_the_edge = (g.off_axis[0] > math.radians(20.0)) & (g.value[0] > 0.0)
    assert lit_beyond_the_edge.sum() > 20


def test_closest_points_project_onto_the_hinge_leaf(hinge):
    mesh, _ = hinge
    guesses = np.array([[0.006, 0.0, 0.0045], [0.010, 0.005, 0.0035], [0.0, 0.0, 0.5]])
    point, face, normal = closest_points(mesh, guesses, max_dist=0.01)
    np.testing.assert_allclose(point[:2], [[0.006, 0.0, 0.004], [0.010, 0.005, 0.004]], atol=1e-7)
    np.testing.assert_allclose(normal[:2], [[0.0, 0.0, 1.0]] * 2, atol=1e-6)
    assert face[2] == -1 and np.isnan(point[2]).all()


@pytest.mark.parametrize("shadows", [False, True])
def test_a_lamp_or_camera_at_a_sample_point_gives_the_same_finite_gray_in_kernel_and_reference(blocks, shadows):
    """Degenerate geometry (issue 29): the direction to a lamp or a camera at the point itself is 0
    in both (wp.normalize, geometry.direction), not NaN (0/0) in one of them: the lamp at the
    point shadows it, the camera at it sees nothing, every output finite and equal."""
    points = np.array([[0.0, 0.0, 0.01], [0.01, 0.02, 0.01], [0.05, 0.0, 0.05]])    # the slab's top, the wall's face
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    camera = points[2]                                                              # the camera at point 2
    lamps = np.array([points[0], [0.0, 0.1, 0.3], points[1]])                      # lamps 0 and 2 at points 0, 1
    aims = geometry.unit(np.array([[0.0, 0.0, -1.0], -lamps[1], [0.0, 0.3, -1.0]]))
    args = (points, normals, camera, lamps, aims, P_LAMP, np.pi / 2, METAL, C_CAMERA, A_PIXEL, shadows)
    mesh = blocks if shadows else None
    with np.errstate(divide="raise", invalid="raise"):      # no 0/0 or 1/0 on the way either
        numpy = ref.gray_per_exposure(mesh, *args)
    warp = gray_per_exposure(mesh, *args)
    for got in (warp, numpy):
        assert all(np.all(np.isfinite(np.asarray(x, float))) for x in (got.value, got.off_axis))
        assert got.shadowed[0, 0] and got.shadowed[2, 1] and got.value[0, 0] == got.value[2, 1] == 0.0
        np.testing.assert_array_equal(got.value[:, 2], 0.0)                         # the camera's own point
        np.testing.assert_array_equal(got.dominant[:, 2], -1)
        assert got.value[1, 0] > 0.0 and got.value[1, 1] > 0.0                     # the lamp above lights the rest
    # (a shadow ray to a lamp on the surface ends on it: those may differ as grazing rays do)
    assert_gray_agrees(blocks, points, normals, lamps, warp, numpy)
    assert warp.off_axis[0, 0] == numpy.off_axis[0, 0] == pytest.approx(np.pi / 3)   # the chord |a + 0| = 1


def test_the_shadow_flags_alone_are_the_gray_calls_own(hinge):
    """GrayInputs.shadowed (the shadow test alone, no shading) equals a gray call's shadowed for
    the same lamps, bit for bit: lamps all about the hinge (some behind the points' surfaces, one
    at a point), before and after the free cones are found, and without cast shadows."""
    mesh, _ = hinge
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-0.026, -0.005, 40), rng.uniform(-0.015, 0.015, 40), np.full(40, 0.004)])
    normals = geometry.unit(np.tile([0.0, 0.0, 1.0], (40, 1)) + rng.normal(0.0, 0.2, (40, 3)))
    lamps, aims = lamps_around(rng, np.array([-0.015, 0.0, 0.004]), 2 * len(mesh.faces), min_elevation=-0.5)
    lamps[0] = points[3]                        # a lamp at a point: shadowed there
    args = (points, normals, np.array([-0.01, 0.02, 0.3]), P_LAMP, GAMMA, METAL, C_CAMERA, A_PIXEL)
    flags = []
    for inputs in (GrayInputs(mesh, *args), GrayInputs(None, *args)):
        before = inputs.shadowed(lamps[:3])
        assert not inputs.has_free_cones
        first, rest = inputs(lamps[:3], aims[:3]), inputs(lamps[3:], aims[3:])
        assert inputs.has_free_cones == (inputs._mesh is not None)
        after = inputs.shadowed(lamps)
        np.testing.assert_array_equal(before, first.shadowed)
        np.testing.assert_array_equal(after, np.vstack([first.shadowed, rest.shadowed]))
        assert 0.05 < after.mean() < 0.8 and after[0, 3]
        flags.append(after)
    cast, attached = flags
    assert (cast & ~attached).sum() > 20 and not (attached & ~cast).any()    # the hinge casts shadows besides
    assert inputs.shadowed(np.zeros((0, 3))).shape == (0, 40)


def test_unit_rows_are_numpys_bit_for_bit_and_refuse_a_zero_row():
    """kernels._arrays.unit_rows against a / np.linalg.norm(a, axis=1): over many decades, one
    row and many; a zero-length row is refused naming the array."""
    from kernels._arrays import unit_rows
    rng = np.random.default_rng(5)
    for n in (1, 7, 9500):
        a = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-60, 60, size=(n, 3))
        assert np.array_equal(unit_rows(a, "normals"), a / np.linalg.norm(a, axis=1, keepdims=True))
    with pytest.raises(ValueError, match="normals has a zero-length row"):
        unit_rows(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), "normals")
