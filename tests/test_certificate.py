"""The certificates of several features verified together (certificate.verify_all: their
specular points' searches in one launch, one shared gray launch over every dense patch) against
each verified alone (certificate.verify), bit for bit."""
import itertools
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from cell.core import geometry
from cell.planning import certificate, one_shot
from cell.planning.scene import build_scene
from cell.task.loader import load_task
from kernels import runtime
from kernels.proximity import closest_points

TASKS = Path(__file__).resolve().parent.parent / "tasks"
TEST_TASKS = Path(__file__).resolve().parent / "tasks"


def equal(a, b):
    """a == b exactly: arrays element for element (NaN equal to NaN), dataclasses field by field."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b, equal_nan=True)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(equal(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))
    return a == b


@pytest.fixture(scope="module")
def problems_at_one_camera():
    """The bracket's first feature's shot, and each feature's search Problem at that shot's camera
    (a global search, no refinement: the samples, maps and focus a judged feature has)."""
    task = load_task(TASKS / "bracket.yaml")
    settings = replace(one_shot.PlannerSettings(), refine=False)
    say = lambda message: None  # noqa: E731
    plan, _ = one_shot.search(task.with_feature(0), settings, 1.0, np.zeros((0, 3)), say)
    problems = [one_shot.search(task.with_feature(g), settings, 1.0, np.zeros((0, 3)), say, plan.shot.T_cell_cam)[1]
                for g in range(len(task.features))]
    return plan.shot, problems


def test_certificates_verified_together_equal_each_verified_alone(problems_at_one_camera):
    shot, problems = problems_at_one_camera
    together = certificate.verify_all(problems, shot)
    alone = [certificate.verify(p, shot) for p in problems]
    assert len(together) == len(problems) >= 3
    for (v1, worst1), (v2, worst2) in zip(together, alone):
        assert equal(v1, v2) and equal(worst1, worst2)
    counts = [v.points for v, _ in alone]
    assert len(set(counts)) > 1                        # patches of different sizes: the shared rows are sliced
    assert len({v.holds for v, _ in alone}) == 2       # the shot holds on some features, not on others
    assert certificate.verify_all([], shot) == []


def test_dense_patches_laid_in_the_background_give_the_same_certificates(problems_at_one_camera):
    """certificate.verify_all given each dense patch made on the background thread (as
    coverage.judge_all has them made) equals it making them itself, bit for bit."""
    shot, problems = problems_at_one_camera
    made = [runtime.in_background(certificate.dense_scene, p.task, p.scene) for p in problems]
    for (v1, worst1), (v2, worst2) in zip(certificate.verify_all(problems, shot, made),
                                          certificate.verify_all(problems, shot), strict=True):
        assert equal(v1, v2) and equal(worst1, worst2)
    assert all(equal(d.result().points, certificate.dense_scene(p.task, p.scene).points)
               for d, p in zip(made, problems))


def test_the_launches_lit_begins_are_each_patchs_own_and_not_launched_again(problems_at_one_camera):
    """certificate.lit beside begins the gray kernel at the shot's lamp and the camera's shadow
    flags over every dense patch on a thread beside: each patch's rows are its own launch's (a
    GrayInputs of that patch alone), and asking for them launches nothing more; without, it
    begins nothing (verify_all: its launches split when asked)."""
    from cell.devices import rig
    from cell.planning import evaluate
    shot, problems = problems_at_one_camera
    task, material = problems[0].task, problems[0].material
    scenes = [certificate.dense_scene(p.task, p.scene) for p in problems]
    assert not certificate.lit(task, material, shot, scenes)[1]._launched      # verify_all's: launched when asked
    runtime.set_threads(2)
    try:
        patches, shared = certificate.lit(task, material, shot, scenes, beside=True)
    finally:
        runtime.set_threads(None)

    class Refuses:
        def __call__(self, *args):
            raise AssertionError("launched again")

        shadowed = __call__
    shared.inputs = Refuses()
    lamp = np.asarray(shot.lamp_position, float).reshape(1, 3)
    aim = rig.lamp_aim(task.lamp.rig.pivot_m, lamp)
    for k, patch in enumerate(patches):
        own = evaluate.gray_inputs(task, patch, material)
        rows = shared.rows(k)
        assert equal(rows(lamp, aim).value, own(lamp, aim).value)
        assert equal(rows.shadowed(patch.camera_position[None]), own.shadowed(patch.camera_position[None]))


def test_specular_points_searched_together_equal_each_searched_alone(problems_at_one_camera):
    """The dense patches of every feature, their specular points for lamps all round: searched
    together (one launch) and alone, the same points and normals exactly; each on its
    own patch (within its radius of the centre) and at least as well aligned as its best dense point."""
    shot, problems = problems_at_one_camera
    scenes = [build_scene(p.task, certificate.dense_samples(p.task, p.scene), T_cell_cam=p.scene.T_cell_cam)
              for p in problems]
    centre = np.mean([s.center for s in scenes], axis=0)
    for angle in np.radians([0.0, 70.0, 140.0, 210.0, 280.0]):
        lamp = centre + 0.2 * np.array([np.cos(angle), np.sin(angle), 1.0])
        points, normals = certificate.specular_points(scenes, lamp)
        for k, s in enumerate(scenes):
            point, normal = certificate.specular_points([s], lamp)
            assert np.array_equal(point[0], points[k]) and np.array_equal(normal[0], normals[k])
            assert np.linalg.norm(points[k] - s.center) <= np.max(np.linalg.norm(s.points - s.center, axis=1))
            best_dense = certificate.mirror_alignment(s.points, s.normals, lamp, s.camera_position).max()
            found = certificate.mirror_alignment(points[k:k + 1], normals[k:k + 1], lamp, s.camera_position)[0]
            assert found >= best_dense - 1e-6         # the start re-projected onto the surface (float32)


def specular_point_alone(scene, lamp, maxfev=80):
    """A patch's specular point the slow way: scipy's Nelder-Mead from the best dense point, each
    step projected by its own closest_points call and judged by mirror_alignment in NumPy (off
    the patch by its 3-vector's np.linalg.norm), the step back to the start where it ends no better."""
    radius = float(np.max(np.linalg.norm(scene.points - scene.center, axis=1)))
    alignment = certificate.mirror_alignment(scene.points, scene.normals, lamp, scene.camera_position)
    start = scene.points[int(np.argmax(alignment))]

    def at(step):
        query = start + step[0] * scene.frame[:, 0] + step[1] * scene.frame[:, 1]
        point, _, normal = closest_points(scene.warp_mesh, query[None], max_dist=radius)
        if not np.linalg.norm(point[0] - scene.center) <= radius:
            return point[0], normal[0], 2.0
        return point[0], normal[0], -float(certificate.mirror_alignment(point, normal, lamp, scene.camera_position)[0])

    d = 0.02 * radius
    found = minimize(lambda x: at(x)[2], np.zeros(2), method="Nelder-Mead",
                     options={"initial_simplex": [[0.0, 0.0], [d, 0.0], [0.0, d]], "xatol": 1e-7, "fatol": 1e-12,
                              "maxfev": maxfev})
    point, normal, _ = at(found.x if found.fun <= at(np.zeros(2))[2] else np.zeros(2))
    return point, normal


@pytest.fixture(scope="module")
def dense_scenes(problems_at_one_camera):
    """The bracket's dense patches at one camera (flat faces) and the aluminium dome's (curved)."""
    _, problems = problems_at_one_camera
    scenes = [build_scene(p.task, certificate.dense_samples(p.task, p.scene), T_cell_cam=p.scene.T_cell_cam)
              for p in problems]
    dome = load_task(TEST_TASKS / "sphere_aluminium_narrow.yaml")
    return scenes + [build_scene(dome, certificate.dense_samples(dome, build_scene(dome)))]


def test_specular_points_equal_scipys_search_one_point_at_a_time(dense_scenes):
    """specular_points (the searches in one Warp launch, kernels.specular) finds, for
    lamps all round, the very point and normal the one-point-at-a-time scipy search finds."""
    for scenes in (dense_scenes[:-1], dense_scenes[-1:]):
        centre = np.mean([s.center for s in scenes], axis=0)
        for angle in np.radians([0.0, 70.0, 140.0, 210.0, 280.0]):
            lamp = centre + 0.2 * np.array([np.cos(angle), np.sin(angle), 1.0])
            points, normals = certificate.specular_points(scenes, lamp)
            for k, s in enumerate(scenes):
                point, normal = specular_point_alone(s, lamp)
                assert np.array_equal(point, points[k]) and np.array_equal(normal, normals[k])


def test_the_launchs_searches_equal_scipys_for_lamps_anywhere_even_at_a_patch_point(dense_scenes):
    """The specular searches of kernels.specular (all patches in one launch) against the scipy
    search one point at a time, for lamps near and far, above and below the patches, and a lamp
    at a patch's best point (its <v, r> NaN there: np.argmax's NaN first, scipy's NaN ordering)."""
    rng = np.random.default_rng(11)
    scenes = dense_scenes
    centre = np.mean([s.center for s in scenes], axis=0)
    lamps = [centre + rng.normal(size=3) * scale for scale in (0.01, 0.05, 0.3, 2.0) for _ in range(4)]
    s0 = scenes[0]
    lamps.append(s0.points[int(np.argmax(certificate.mirror_alignment(s0.points, s0.normals, lamps[0],
                                                                      s0.camera_position)))])
    with np.errstate(invalid="ignore", divide="ignore"):
        for lamp in lamps:
            points, normals = certificate.specular_points(scenes, lamp)
            for k, s in enumerate(scenes):
                point, normal = specular_point_alone(s, lamp)
                assert np.array_equal(point, points[k], equal_nan=True) and np.array_equal(normal, normals[k])


def test_a_search_cut_short_by_its_evaluations_ends_where_scipys_does(dense_scenes, monkeypatch):
    """maxfev from 3 up: the launch's searches end where scipy's do when an evaluation past maxfev
    ends a step in its reflection, expansion, contraction or shrink (a vertex moved, its value
    kept), whichever step that is: the bracket's flat patches for lamps above, the dome's for
    lamps all round it, near and far (some below its rim, where the search runs into the rim's
    off-patch values and shrinks)."""
    rng = np.random.default_rng(5)
    flat, dome = dense_scenes[:-1], dense_scenes[-1:]
    centre = np.mean([s.center for s in flat], axis=0)
    cases = [(flat, centre + 0.2 * np.array([np.cos(a), np.sin(a), 1.0])) for a in np.radians([0.0, 140.0, 280.0])]
    for _ in range(24):
        direction = rng.normal(size=3)
        cases.append((dome, dome[0].center + direction / np.linalg.norm(direction) * rng.choice([0.02, 0.1, 0.5])))
    with np.errstate(invalid="ignore", divide="ignore"):
        for maxfev in range(3, 41):
            monkeypatch.setattr(certificate, "MAXFEV", maxfev)
            for scenes, lamp in cases:
                points, normals = certificate.specular_points(scenes, lamp)
                for k, s in enumerate(scenes):
                    point, normal = specular_point_alone(s, lamp, maxfev)
                    assert np.array_equal(point, points[k], equal_nan=True) and np.array_equal(normal, normals[k])


def test_a_search_that_meets_the_rim_band_is_searched_again_as_scipy_searches(dense_scenes, monkeypatch):
    """Where a point of a search falls within on_patch's band about the rim (np.linalg.norm's
    rounding decides there), the launch says so and the patch is searched in Python: with the
    band as wide as the patch every search meets it, and the points are still scipy's."""
    from kernels.specular import specular_search
    scenes, lamp = dense_scenes[:3], np.mean([s.center for s in dense_scenes[:3]], axis=0) + [0.05, 0.1, 0.2]
    args = ([s.warp_mesh for s in scenes], [s.points for s in scenes], [s.normals for s in scenes],
            [s.center for s in scenes], [s.frame[:, 0] for s in scenes], [s.frame[:, 1] for s in scenes],
            [s.camera_position for s in scenes], lamp)
    options = (certificate.SIMPLEX_STEP, certificate.XATOL, certificate.FATOL, certificate.MAXFEV)
    assert specular_search(*args, certificate.ON_PATCH_MARGIN, *options)[2].all()
    assert not specular_search(*args, 1.0, *options)[2].any()
    monkeypatch.setattr(certificate, "ON_PATCH_MARGIN", 1.0)
    points, normals = certificate.specular_points(scenes, lamp)
    for k, s in enumerate(scenes):
        point, normal = specular_point_alone(s, lamp)
        assert np.array_equal(point, points[k]) and np.array_equal(normal, normals[k])
    assert [len(x) for x in specular_search([], [], [], [], [], [], [], lamp, 1e-9, *options)] == [0, 0, 0]


def test_numpys_argsort_orders_three_values_as_the_searchs_kernel_does():
    """kernels.specular orders the simplex's three values ascending, NaN last, equal values in
    their order (a stable sort): np.argsort's order, which scipy's search reads, for every
    pattern of ties, signed zeros, infinities and NaN."""
    values = [1.0, 2.0, np.nan, -0.0, 0.0, np.inf, -np.inf]
    for triple in itertools.product(values, repeat=3):
        stable = sorted(range(3), key=lambda k: (np.isnan(triple[k]), 0.0 if np.isnan(triple[k]) else triple[k]))
        assert np.argsort(np.array(triple)).tolist() == stable


def test_alignment_at_one_point_equals_mirror_alignments():
    """alignment_at (Python floats) is mirror_alignment (NumPy) bit for bit, at points from
    millimetres to metres from the lamp and camera, signed zeros and a lamp at the point included."""
    rng = np.random.default_rng(28)
    points = rng.normal(size=(3000, 3)) * rng.choice([1e-3, 0.1, 1.0], size=(3000, 1))
    normals = rng.normal(size=(3000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[:10] = [0.0, -0.0, 1.0]
    lamp, camera = np.array([0.1, -0.2, 0.3]), rng.normal(size=(3000, 3))
    points[0] = lamp
    with np.errstate(invalid="ignore"):
        expected = certificate.mirror_alignment(points, normals, lamp, camera)
        found = [certificate.alignment_at(p, n, lamp.tolist(), c) for p, n, c in
                 zip(points.tolist(), normals.tolist(), camera.tolist())]
    assert np.isnan(expected[0]) and np.array_equal(np.array(found), expected, equal_nan=True)
    assert all(certificate.mirror_alignment(points[k:k + 1], normals[k:k + 1], lamp, camera[k])[0] == expected[k]
               for k in range(1, 200))          # a row alone as in a batch


def test_on_patch_decides_as_the_3_vectors_norm():
    """on_patch is np.linalg.norm(point - center) <= radius, points at the rim to the last ulp included."""
    rng = np.random.default_rng(7)
    center, radius = rng.normal(size=3), 0.006
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distances = radius * (1.0 + rng.choice([-1, 1], 4000) * rng.choice([0.0, 1e-16, 3e-16, 1e-12, 1e-3], 4000))
    points = center + directions * distances[:, None]
    found = [certificate.on_patch(p, center.tolist(), radius) for p in points.tolist()]
    assert found == [bool(np.linalg.norm(p - center) <= radius) for p in points]
    assert 0 < sum(found) < len(found)
    assert not certificate.on_patch([np.nan] * 3, center.tolist(), radius)


def test_mirror_alignment_is_the_form_with_numpys_sums_bit_for_bit():
    """mirror_alignment (geometry.row_sum's sums) equals the form with np.sum and geometry.unit on
    a dense patch's worth of points."""
    rng = np.random.default_rng(3)
    points = rng.normal(size=(20000, 3)) * 0.01
    normals = geometry.unit(rng.normal(size=(20000, 3)))
    lamp, camera = np.array([0.05, -0.2, 0.3]), np.array([0.0, 0.1, 0.5])
    s, v = geometry.unit(lamp - points), geometry.unit(camera - points)
    mirror = 2.0 * np.sum(normals * s, axis=-1, keepdims=True) * normals - s
    assert np.array_equal(certificate.mirror_alignment(points, normals, lamp, camera), np.sum(mirror * v, axis=-1))


def test_a_patchs_row_norms_are_numpys_norms_bit_for_bit():
    """scene._row_norms (the dense patch's landing distances) equals np.linalg.norm along rows,
    for offsets of every size a patch has and rows of zeros and of one component."""
    from cell.planning.scene import _row_norms
    rng = np.random.default_rng(7)
    d = rng.normal(size=(20000, 3)) * 10.0 ** rng.uniform(-9, 1, (20000, 1))
    d[:3] = [[0.0, 0.0, 0.0], [-0.0, 3e-3, 0.0], [1e-300, -2e-300, 0.0]]
    assert np.array_equal(_row_norms(d), np.linalg.norm(d, axis=1))


def test_judge_all_on_one_thread_equals_it_with_the_patches_laid_beside(problems_at_one_camera):
    """coverage.judge_all with a thread beside asks every dense patch there from the start
    (runtime.in_background); on one thread it lays only the met features' patches, each when
    verified: the same coverage of one shot on the bracket's other features, bit for bit."""
    from cell.planning import coverage
    shot, problems = problems_at_one_camera
    settings = replace(one_shot.PlannerSettings(), refine=False)
    tasks = [p.task for p in problems[1:]]
    lent = [coverage.Lent.of(one_shot.search(t, settings, 1.0, np.zeros((0, 3)), lambda message: None)[0])
            for t in tasks]
    judged = []
    for threads in (1, 2):
        runtime.set_threads(threads)
        try:
            judged.append(coverage.judge_all(tasks, lent, shot))
        finally:
            runtime.set_threads(None)
    assert any(c.verification is not None for c in judged[0]) and any(not c.covered for c in judged[0])
    assert equal(judged[0], judged[1])
