"""Big launches split over threads (kernels.runtime.slices, in_parallel) give bitwise the one
launch's result, on every split kernel: visibility, free cones, the bulk gray (cut along its lamps
and along its points), its shadow flags alone, the closest points and the renderer. The expectation is the one-thread launch, and, at the
split, the NumPy references (cell.physics.reference) as tests/test_kernels holds the one launch to
them. Slices are forced small here (MIN_SLICE 1) so that small inputs split too, over 3 threads:
uneven slices, more threads than the machine's 2 cores."""
import dataclasses
import math
import os

import numpy as np
import pytest
import trimesh

from cell.core import geometry
from cell.physics import reference as ref
from cell import cli
from kernels import cores, runtime
from kernels.cone import free_cone_cosines
from kernels.gray import GrayInputs, gray_per_exposure
from kernels.mesh import WarpMesh
from kernels.proximity import closest_points
from kernels.render import render
from kernels.visibility import visibility_maps, visible_from_all
from test_kernels import (A_PIXEL, ALUMINIUM, C_CAMERA, GAMMA, METAL, P_LAMP, assert_gray_agrees,  # hinge: a fixture
                          assert_visibility_agrees, hinge, lamps_around, near_the_knuckle)

THREADS = 3


@pytest.fixture
def launches(monkeypatch):
    """The number of launches each in_parallel call ran, with slices of any size allowed."""
    counted: list[int] = []
    run = runtime.in_parallel

    def counting(recorded):
        counted.append(len(recorded))
        run(recorded)
    monkeypatch.setattr(runtime, "MIN_SLICE", 1)
    monkeypatch.setattr(runtime, "in_parallel", counting)
    monkeypatch.setattr("kernels.gray.in_parallel", counting)      # imported by name there
    yield counted
    runtime.set_threads(None)


def on(threads, fn, *args, **kwargs):
    """fn(*args, **kwargs) with big launches split over `threads` threads."""
    runtime.set_threads(threads)
    try:
        return fn(*args, **kwargs)
    finally:
        runtime.set_threads(None)


def assert_bitwise(one, split):
    """Every array of the two results (tuples or dataclasses of arrays) equal, element by element
    (NaN where NaN)."""
    if dataclasses.is_dataclass(one):
        one, split = dataclasses.astuple(one), dataclasses.astuple(split)
    assert len(one) == len(split)
    for a, b in zip(one, split):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)


def test_slices_cover_the_range_once_and_evenly(monkeypatch):
    monkeypatch.setattr(runtime, "MIN_SLICE", 10)
    for threads, count, work, expected in ((3, 10, 3.0, [(0, 3), (3, 6), (6, 10)]),
                                           (3, 10, 1.0, [(0, 10)]),        # 10 evaluations: one slice's worth
                                           (2, 7, 100.0, [(0, 3), (3, 7)]),
                                           (8, 3, 100.0, [(0, 1), (1, 2), (2, 3)])):   # at most one item each
        assert on(threads, runtime.slices, count, work) == expected
    assert on(1, runtime.slices, 10_000, 1e6) == [(0, 10_000)]


def test_the_thread_count_defaults_to_the_cores_this_process_may_use(monkeypatch):
    """Its affinity, or fewer where LIGHTPLAN_CORES says so (never more: they are not there)."""
    affinity = len(os.sched_getaffinity(0))
    runtime.set_threads(None)
    monkeypatch.delenv(cores.CORES_VARIABLE, raising=False)
    assert runtime.threads() == affinity
    monkeypatch.setenv(cores.CORES_VARIABLE, "1")
    assert runtime.threads() == 1
    monkeypatch.setenv(cores.CORES_VARIABLE, str(affinity + 3))
    assert runtime.threads() == affinity
    with pytest.raises(ValueError, match="at least 1"):
        runtime.set_threads(0)


@pytest.mark.parametrize("raw", ["0", "-2", "two", "1.5", ""])
def test_a_cores_setting_not_a_whole_number_of_at_least_1_is_bad_input(monkeypatch, capsys, raw):
    monkeypatch.setenv(cores.CORES_VARIABLE, raw)
    with pytest.raises(ValueError) as err:
        cores.available_cores()
    assert str(err.value) == (f"environment: LIGHTPLAN_CORES: found {raw!r}, expected a whole number of cores, "
                              "at least 1 (or unset: every core this process may run on)")
    assert cli.main(["check", "tasks/hinge.yaml"]) == 2            # before any work: one line, exit 2
    out, said = capsys.readouterr()
    assert out == "" and said == f"cell check: {err.value}\n"


@pytest.mark.parametrize("threads", [1, 2])
def test_background_work_runs_on_a_thread_of_its_own_in_order_with_its_exceptions(threads):
    """On one thread (a worker's share of one core) it runs on the caller's, at once."""
    import threading
    ran = []
    runtime.set_threads(threads)
    try:
        first = runtime.in_background(lambda: ran.append(threading.current_thread().name) or len(ran))
        failed = runtime.in_background(math.sqrt, -1.0)
        last = runtime.in_background(lambda: ran.append(threading.current_thread().name) or len(ran))
    finally:
        runtime.set_threads(None)
    assert (first.result(), last.result()) == (1, 2)
    assert ran[0] == ran[1] and (ran[0] == threading.current_thread().name) == (threads == 1)
    # its launches whole beside the caller's thread
    assert runtime.in_background(runtime.slices, 10 ** 6, 1.0).result() == [(0, 10 ** 6)]
    with pytest.raises(ValueError, match="math domain error"):
        failed.result()


def test_a_background_lane_never_waits_behind_another():
    """Work asked in lane 1 runs while lane 0's thread is busy (each lane a thread of its own,
    its launches whole as lane 0's)."""
    import threading
    free = threading.Event()
    runtime.set_threads(2)
    try:
        held = runtime.in_background(free.wait, 10.0)          # lane 0 busy until lane 1 frees it
        freed = runtime.in_background(lambda: free.set() or threading.current_thread().name, lane=1)
        name = freed.result(timeout=10.0)
        assert held.result(timeout=10.0) is True
        assert runtime.in_background(runtime.slices, 10 ** 6, 1.0, lane=1).result() == [(0, 10 ** 6)]
    finally:
        runtime.set_threads(None)
    assert name != threading.current_thread().name


def test_split_visibility_maps_and_free_cones_equal_one_launch(hinge, launches):
    mesh, _ = hinge
    points, normals, frame, az, el = near_the_knuckle()
    args = (mesh, points, normals, frame, az, el)
    one = on(1, visibility_maps, *args)
    assert launches[-1] == 1
    split = on(THREADS, visibility_maps, *args)
    assert launches[-1] == THREADS
    np.testing.assert_array_equal(split, one)
    assert 0.05 < 1 - split.mean() < 0.6
    for threads in (1, THREADS):                     # the combined map's launch split over the directions' rows
        np.testing.assert_array_equal(on(threads, visible_from_all, *args), one.all(axis=0))
        assert launches[-1] == threads
    assert_visibility_agrees(mesh, points, normals, frame, az, el, split, ref.visibility_maps(*args))
    origins = points + 1e-5 * normals                # the shadow rays' start, as the kernels use them
    cones = on(1, free_cone_cosines, mesh, origins, normals), on(THREADS, free_cone_cosines, mesh, origins, normals)
    assert launches[-2:] == [1, THREADS]
    assert_bitwise(*cones)
    assert np.any(cones[0][0] < 1.0)                  # some point has a free cone to compare


@pytest.mark.parametrize("lamps, samples", [(200, 48), (4, 500)], ids=["along-lamps", "along-points"])
def test_split_gray_equals_one_launch_and_the_reference(hinge, launches, lamps, samples):
    """A global search's many lamps on few samples is cut along the lamps; a certificate's few
    lamps on many points along the points."""
    mesh, tm = hinge
    points, face = trimesh.sample.sample_surface(tm, samples, seed=3)
    normals = tm.face_normals[face]
    lamp_pos, aims = lamps_around(np.random.default_rng(11), np.array([0.0, 0.0, 0.004]), lamps, radius=(0.08, 0.6))
    args = (mesh, points, normals, np.array([-0.025, 0.0, 0.5]), lamp_pos, aims, P_LAMP, GAMMA, ALUMINIUM,
            C_CAMERA, A_PIXEL)
    one = on(1, gray_per_exposure, *args)
    split = on(THREADS, gray_per_exposure, *args)
    assert launches == [1, THREADS]
    assert_bitwise(one, split)
    assert (split.value > 0).mean() > 0.05 and split.shadowed.any()
    assert_gray_agrees(mesh, points, normals, lamp_pos, split, ref.gray_per_exposure(*args))


def test_split_shadow_flags_equal_one_launch_and_the_gray_kernels(hinge, launches):
    """GrayInputs.shadowed (a camera's rays to a dense patch, cut along the points) on 1 and 3
    threads: the same flags, and the gray kernel's own (shadowed is its test alone)."""
    mesh, tm = hinge
    points, face = trimesh.sample.sample_surface(tm, 500, seed=8)
    inputs = (mesh, points, tm.face_normals[face], np.array([0.0, 0.0, 0.5]), P_LAMP, GAMMA, METAL, C_CAMERA,
              A_PIXEL)
    lamp_pos, aims = lamps_around(np.random.default_rng(6), np.array([0.0, 0.0, 0.004]), 3)
    one = on(1, GrayInputs(*inputs).shadowed, lamp_pos)
    split = on(THREADS, GrayInputs(*inputs).shadowed, lamp_pos)
    assert launches == [1, THREADS]
    np.testing.assert_array_equal(split, one)
    np.testing.assert_array_equal(split, on(1, GrayInputs(*inputs), lamp_pos, aims).shadowed)
    assert 0.05 < split.mean() < 0.95


def test_split_closest_points_equal_one_launch(hinge, launches):
    """Guesses about the hinge, some with no surface within reach (NaN, -1, 0): each query's
    answer the one launch's, bit for bit; tests/test_kernels holds that launch to the surface."""
    mesh, _ = hinge
    guesses = np.random.default_rng(9).uniform([-0.03, -0.02, -0.005], [0.03, 0.02, 0.02], (400, 3))
    one = on(1, closest_points, mesh, guesses, max_dist=0.004)
    split = on(THREADS, closest_points, mesh, guesses, max_dist=0.004)
    assert launches == [1, THREADS]
    assert_bitwise(one, split)
    assert 20 < (split[1] == -1).sum() < 380


def test_a_kept_small_launch_split_equals_one_launch(hinge, launches):
    """The search's recorded launches (a few lamps, called hundreds of times) split as well, and
    give each call's own values."""
    mesh, tm = hinge
    points, face = trimesh.sample.sample_surface(tm, 64, seed=5)
    inputs = (mesh, points, tm.face_normals[face], np.array([0.0, 0.0, 0.5]), P_LAMP, GAMMA, METAL, C_CAMERA,
              A_PIXEL)
    rng = np.random.default_rng(2)
    calls = [lamps_around(rng, np.array([0.0, 0.0, 0.004]), 9) for _ in range(3)]
    one = [on(1, GrayInputs(*inputs), *call) for call in calls]
    runtime.set_threads(THREADS)
    try:
        kept = GrayInputs(*inputs)
        split = [kept(*call) for call in calls]
    finally:
        runtime.set_threads(None)
    assert launches[-3:] == [THREADS] * 3
    for a, b in zip(one, split):
        assert_bitwise(a, b)
    assert not np.array_equal(split[0].value, split[1].value)


def test_split_render_equals_one_launch_and_the_reference(launches):
    """A plate with a cube on it seen from 0.5 m, lit by two point lamps (the cube's shadows)."""
    plate = trimesh.Trimesh([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]],
                            [[0, 1, 2], [0, 2, 3]])
    cube = trimesh.creation.box(extents=(0.02,) * 3,
                                transform=trimesh.transformations.translation_matrix((0.0413, 0.0037, 0.01)))
    mesh = WarpMesh.from_trimesh(trimesh.util.concatenate([plate, cube]))
    u = np.linspace(-0.25, 0.25, 31)
    X, Y = np.meshgrid(u, u)
    dirs = geometry.unit(np.column_stack([X.ravel(), Y.ravel(), -np.ones(X.size)]))
    lamps = np.array([[0.15, 0.02, 0.1], [0.12, -0.03, 0.12]])
    args = (mesh, np.array([0.0, 0.0, 0.5]), dirs, lamps, geometry.unit(-lamps), P_LAMP, math.radians(40.0),
            ALUMINIUM, C_CAMERA, A_PIXEL)
    one = on(1, render, *args)
    split = on(THREADS, render, *args)
    assert launches == [1, THREADS]
    assert_bitwise(one, split)
    assert (~split.hit).sum() > 50 and (split.hit & (split.value == 0.0)).sum() > 5     # misses and shadows
    numpy = ref.render(*args)
    np.testing.assert_array_equal(split.hit, numpy.hit)
    np.testing.assert_allclose(split.value, numpy.value, rtol=1e-4, atol=0)
