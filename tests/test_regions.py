"""Signed spherical distance transform against brute force with the haversine of eq. (2)-(3)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from cell.core import geometry
from cell.planning.regions import (FEW_CELLS, NEARBY, POLE_ROWS, RegionDistance, SphereGrid, chord_to_angle,
                                  nearest_chord, on_edge)


def signed_distance(grid, inside):
    """The whole transform (what a picture reads)."""
    return RegionDistance(grid, inside).full()


def brute_force(grid, inside):
    el, az = np.meshgrid(grid.elevation, grid.azimuth, indexing="ij")
    az, el, flat = az.ravel(), el.ravel(), inside.ravel()
    out = np.empty(flat.shape)
    for k in range(flat.size):
        other = flat != flat[k]
        d = geometry.haversine_distance(az[k], el[k], az[other], el[other]).min()
        out[k] = -d if flat[k] else d
    return out.reshape(inside.shape)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_brute_force_haversine_on_random_blobs(seed):
    grid = SphereGrid(np.radians(10.0))
    rng = np.random.default_rng(seed)
    centre = geometry.unit(rng.normal(size=3))
    inside = grid.directions() @ centre > np.cos(np.radians(rng.uniform(20, 70)))
    assert np.allclose(signed_distance(grid, inside), brute_force(grid, inside), atol=1e-12)


def test_region_across_the_azimuth_seam():
    grid = SphereGrid(np.radians(5.0))
    el, az = np.meshgrid(grid.elevation, grid.azimuth, indexing="ij")
    inside = (np.abs(az) > np.radians(160)) & (np.abs(el) < np.radians(30))   # straddles +-180 deg
    d = signed_distance(grid, inside)
    assert np.allclose(d, brute_force(grid, inside), atol=1e-12)
    # the cell at az = -180 deg, el = 0 is 20 deg from the region border on either side,
    # not 160 deg as a seam-blind transform would say
    j = np.argmin(np.abs(grid.elevation))
    assert d[j, 0] == pytest.approx(-np.radians(20.0), abs=1e-9)


def test_cap_around_the_pole_is_a_band_of_constant_distance():
    grid = SphereGrid(np.radians(5.0))
    el, _ = np.meshgrid(grid.elevation, grid.azimuth, indexing="ij")
    inside = el >= np.radians(60)
    d = signed_distance(grid, inside)
    assert np.allclose(d, brute_force(grid, inside), atol=1e-12)
    pole = d[-1]            # every azimuth at the pole is 35 deg inside (from 90 to the outside row at 55)
    assert np.allclose(pole, -np.radians(35.0), atol=1e-9)


def test_empty_region_is_far_everywhere():
    grid = SphereGrid(np.radians(10.0))
    inside = np.zeros((len(grid.elevation), len(grid.azimuth)), bool)
    assert np.all(signed_distance(grid, inside) == np.pi)


def test_interpolation_wraps_the_seam():
    grid = SphereGrid(np.radians(10.0))
    values = np.tile(np.cos(grid.azimuth), (len(grid.elevation), 1))
    near_seam = np.pi - np.radians(5.0)     # halfway between az=170 deg and az=-180 deg
    got = grid.sample(values, near_seam, 0.3)
    assert got == pytest.approx(0.5 * (np.cos(np.radians(170.0)) + np.cos(-np.pi)), abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_distance_at_the_cells_around_a_lamp_is_the_whole_maps_there(seed):
    """A judged shot reads the transform only at the cells `sample` reads around its lamp: on a
    fresh map only those are found (by brute force, no tree built), there it equals brute force
    (and the whole map), and sampling gives the same value as sampling the whole map; once the
    trees are built, a few lamps find the cells around them too."""
    grid = SphereGrid(np.radians(10.0))
    rng = np.random.default_rng(seed)
    inside = grid.directions() @ geometry.unit(rng.normal(size=3)) > np.cos(np.radians(40))
    az, el = rng.uniform(-np.pi, np.pi, 3), rng.uniform(-1.5, 1.5, 3)
    cells = grid.cells_around(az, el)
    assert 4 <= len(cells) <= 12
    lazy = RegionDistance(grid, inside)
    got = lazy.sample(az, el)
    found = ~np.isnan(lazy._values)
    assert np.array_equal(np.flatnonzero(found), cells) and lazy._trees is None
    assert np.allclose(lazy._values[cells], brute_force(grid, inside).ravel()[cells], atol=1e-12)
    np.testing.assert_array_equal(got, grid.sample(signed_distance(grid, inside), az, el))
    lazy.at(np.arange(FEW_CELLS + 1))                   # more than a few: the trees
    assert lazy._trees is not None
    az2, el2 = az + 0.7, -el
    lazy.sample(az2, el2)
    nearby = grid.cells_around(az2, el2, NEARBY)        # a few lamps: the cells around them too
    assert np.isin(nearby, np.flatnonzero(~np.isnan(lazy._values))).all()


@pytest.mark.parametrize("seed", range(4))
def test_a_few_cells_by_brute_force_are_the_trees_numbers_bit_for_bit(seed):
    """Before its trees are built, RegionDistance finds a few cells by brute force over the edge
    cells (nearest_chord, summed as cKDTree sums): on the planner's 2 deg grid, cells inside and
    outside, at the seam and the poles, the same numbers exactly as the trees give."""
    grid = SphereGrid(np.radians(2.0))
    rng = np.random.default_rng(seed)
    directions = grid.directions()
    inside = np.zeros(directions.shape[:2], bool)
    for _ in range(rng.integers(1, 4)):
        inside ^= directions @ geometry.unit(rng.normal(size=3)) > np.cos(np.radians(rng.uniform(10, 80)))
    whole = signed_distance(grid, inside).ravel()
    n_az = len(grid.azimuth)
    for _ in range(40):
        cells = rng.choice(inside.size, rng.integers(2, FEW_CELLS + 1), replace=False)
        cells[:2] = [rng.integers(n_az), inside.size - 1 - rng.integers(2 * n_az)]    # a pole's rows, the seam
        lazy = RegionDistance(grid, inside)
        np.testing.assert_array_equal(lazy.at(cells), whole[cells])
        assert lazy._trees is None
    queries, targets = rng.normal(size=(30, 3)), rng.normal(size=(500, 3))
    np.testing.assert_array_equal(nearest_chord(queries, targets), cKDTree(targets).query(queries)[0])


def rolled_edge(inside):
    """on_edge by np.roll of the map padded at the poles: each of the eight neighbours compared."""
    rows = np.pad(inside, ((1, 1), (0, 0)), mode="edge")
    edge = np.zeros(inside.shape, bool)
    for de in (-1, 0, 1):
        for da in (-1, 0, 1):
            edge |= np.roll(rows[1 + de:1 + de + len(inside)], da, axis=1) != inside
    edge[:POLE_ROWS] = edge[-POLE_ROWS:] = True
    return edge


@pytest.mark.parametrize("seed", range(4))
def test_on_edge_compares_each_cell_with_its_eight_neighbours(seed):
    """on_edge (shifted views of the map wrapped at the seam, a row repeated beyond each pole)
    is the comparison with each rolled neighbour, on random maps and single cells at the seam."""
    rng = np.random.default_rng(seed)
    inside = rng.random((91, 180)) < [0.01, 0.3, 0.5, 0.97][seed]
    inside[40, 0] = inside[50, -1] = seed % 2 == 0
    np.testing.assert_array_equal(on_edge(inside), rolled_edge(inside))


@pytest.mark.parametrize("margin", [0, 1, 2])
def test_cells_around_are_the_cells_sample_reads_and_their_neighbours(margin):
    """cells_around: at margin 0 exactly the cells SphereGrid.sample reads (a map NaN elsewhere
    samples finite, and NaN with any one of them taken away), at the seam and beside a pole too;
    at a margin, those and every cell up to `margin` rows and columns from them, no other."""
    grid = SphereGrid(np.radians(2.0))
    rng = np.random.default_rng(margin)
    az = np.concatenate([rng.uniform(-np.pi, np.pi, 5), [np.pi - 1e-3, -np.pi, 0.3]])
    el = np.concatenate([rng.uniform(-1.5, 1.5, 5), [0.1, 0.5 * np.pi - 1e-3, -0.5 * np.pi]])
    n_el, n_az = len(grid.elevation), len(grid.azimuth)
    for a, e in zip(az, el):
        read = grid.cells_around(a, e)
        values = np.full(n_el * n_az, np.nan)
        values[read] = 1.0
        assert np.isfinite(grid.sample(values.reshape(n_el, n_az), a, e))
        for k in read:
            values[k] = np.nan
            assert np.isnan(grid.sample(values.reshape(n_el, n_az), a, e))
            values[k] = 1.0
        around = grid.cells_around(a, e, margin)
        rows, columns = np.divmod(around, n_az)
        r0, c0 = np.divmod(read, n_az)
        row_gap = np.abs(rows[:, None] - r0[None]).min(axis=1)
        column_gap = np.abs((columns[:, None] - c0[None] + n_az // 2) % n_az - n_az // 2).min(axis=1)
        assert np.isin(read, around).all() and row_gap.max() <= margin and column_gap.max() <= margin
        every = {(r, c) for r in range(n_el) for c in range(n_az)
                 if np.abs(r - r0).min() <= margin and np.abs((c - c0 + n_az // 2) % n_az - n_az // 2).min() <= margin}
        assert len(around) == len(every)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cells_found_batch_by_batch_equal_the_whole_map_bit_for_bit(seed):
    """A search asks the transform a few cells at a time (its lamps' as it goes), in batches
    small and large, cells inside and outside the region, some asked again: each cell's value the
    whole map's exactly, on the planner's 2 deg grid, at the seam and the poles too."""
    grid = SphereGrid(np.radians(2.0))
    rng = np.random.default_rng(seed)
    inside = grid.directions() @ geometry.unit(rng.normal(size=3)) > np.cos(np.radians(rng.uniform(15, 60)))
    whole = signed_distance(grid, inside)
    lazy = RegionDistance(grid, inside)
    for count in (1, 7, 40, 3000, 40):
        az = rng.uniform(-np.pi, np.pi, count)
        el = rng.uniform(-0.5 * np.pi, 0.5 * np.pi, count)
        az[:1], el[-1:] = np.pi - 1e-3, 0.5 * np.pi - 1e-3        # beside the seam and a pole
        np.testing.assert_array_equal(lazy.sample(az, el), grid.sample(whole, az, el))
    cells = rng.choice(inside.size, 500, replace=False)
    np.testing.assert_array_equal(lazy.at(cells), whole.ravel()[cells])
    np.testing.assert_array_equal(lazy.full(), whole)


def test_a_pickled_distance_keeps_its_cells_and_finds_the_rest():
    """A plan made in a worker process comes back pickled: the cells found so far travel with it
    (not its trees), and the rest are found after as before."""
    import pickle
    grid = SphereGrid(np.radians(5.0))
    inside = grid.directions() @ geometry.unit([1.0, 0.2, 0.3]) > np.cos(np.radians(35))
    lazy = RegionDistance(grid, inside)
    lazy.sample(np.array([0.1, 2.0]), np.array([0.2, -0.4]))
    back = pickle.loads(pickle.dumps(lazy))
    assert back._trees is None
    np.testing.assert_array_equal(back._values, lazy._values)
    np.testing.assert_array_equal(back.full(), signed_distance(grid, inside))


def nearest_over_all_cells(grid, inside):
    """The transform with k-d trees over every cell of the other kind (none left out)."""
    dirs, flat = grid.directions().reshape(-1, 3), inside.ravel()
    out = np.empty(flat.shape)
    out[flat] = -chord_to_angle(cKDTree(dirs[~flat]).query(dirs[flat])[0])
    out[~flat] = chord_to_angle(cKDTree(dirs[flat]).query(dirs[~flat])[0])
    return out.reshape(inside.shape)


@pytest.mark.parametrize("seed", range(6))
def test_the_edge_cells_alone_give_the_transform_over_all_cells_bit_for_bit(seed):
    """RegionDistance searches only the cells on_edge: the same numbers exactly as trees over
    every cell, on regions of several caps (holes, regions over a pole, across the seam) and
    scattered single cells."""
    rng = np.random.default_rng(seed)
    grid = SphereGrid(np.radians([2.0, 3.0, 5.0][seed % 3]))
    directions = grid.directions()
    inside = np.zeros(directions.shape[:2], bool)
    for _ in range(rng.integers(2, 5)):
        inside ^= directions @ geometry.unit(rng.normal(size=3)) > np.cos(np.radians(rng.uniform(5, 100)))
    inside ^= rng.random(inside.shape) < 0.01 * (seed % 2)
    edge = on_edge(inside)
    assert 0 < edge.sum() < edge.size / 2
    np.testing.assert_array_equal(signed_distance(grid, inside), nearest_over_all_cells(grid, inside))


def test_the_queries_split_over_two_threads_give_the_same_transform():
    """RegionDistance's k-d tree queries on the kernels' threads (kernels.runtime.threads): on
    2 threads the numbers of trees over every cell queried on one, exactly."""
    from kernels import runtime
    grid = SphereGrid(np.radians(2.0))
    directions = grid.directions()
    rng = np.random.default_rng(7)
    inside = np.zeros(directions.shape[:2], bool)
    for _ in range(3):
        inside ^= directions @ geometry.unit(rng.normal(size=3)) > np.cos(np.radians(rng.uniform(10, 80)))
    runtime.set_threads(2)
    try:
        split = signed_distance(grid, inside)
    finally:
        runtime.set_threads(None)
    np.testing.assert_array_equal(split, nearest_over_all_cells(grid, inside))


def test_directions_rotated_once_per_frame_are_the_products():
    """SphereGrid.directions(frame) is the feature-frame directions times frame.T exactly, read-only
    and made once per frame (asked again: the same array)."""
    grid = SphereGrid(np.radians(2.0))
    frame = geometry.frame_from_normal(geometry.unit([0.3, -0.5, 0.8]))
    found = grid.directions(frame)
    assert np.array_equal(found, grid.directions(np.eye(3)) @ frame.T)
    assert not found.flags.writeable and grid.directions(frame.copy()) is found
    assert np.allclose(np.linalg.norm(found, axis=-1), 1.0)
