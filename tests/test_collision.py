"""Collision checking (cell.collision): the distance between two bodies against analytic
distances and a dense brute-force sampling that shares no code with it, overlap and containment
giving <= 0, the scene's bodies placed by the kinematics, and the task's `cell.collision` keys."""
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from cell.cli import main
from cell.collision.bodies import SAMPLE_BOUND_M, Box, Capsule, Mesh, distance
from cell.collision.scene import CollisionScene, arm_links
from cell.core import geometry
from cell.core.errors import TaskError
from cell.devices import ur5e
from cell.task.loader import load_task

from simcell import variant

ROOT = Path(__file__).resolve().parent.parent
HINGE, BRACKET = ROOT / "tasks" / "hinge.yaml", ROOT / "tasks" / "bracket.yaml"
h = SAMPLE_BOUND_M


def box(name, center, size, rpy=(0.0, 0.0, 0.0)):
    return Box(name, geometry.from_rpy(np.asarray(rpy, float), center), 0.5 * np.asarray(size, float))


def plate(name, size, center):
    """A closed box mesh (trimesh's primitive), as a part or a table."""
    return Mesh.of(name, trimesh.creation.box(extents=size), geometry.transform(translation=center))


# -- analytic distances: the result lies in [d - h, d] -------------------------------------------

@pytest.mark.parametrize("gap", [0.003, 0.02, 0.1])
def test_two_boxes_side_by_side_are_their_gap_apart(gap):
    a = box("a", (0.0, 0.0, 0.0), (0.04, 0.06, 0.1))
    b = box("b", (0.04 / 2 + gap + 0.01, 0.01, 0.02), (0.02, 0.02, 0.02))
    assert gap - h - 1e-12 <= distance(a, b) <= gap + 1e-12


def test_a_box_turned_45_deg_reaches_with_its_edge():
    """b turned 45 deg about z: its vertical edge is sqrt(2) s / 2 from its centre toward a."""
    s, x = 0.02, 0.06
    a = box("a", (0.0, 0.0, 0.0), (0.04, 0.04, 0.04))
    b = box("b", (x, 0.0, 0.0), (s, s, s), rpy=(0.0, 0.0, np.pi / 4))
    expected = x - np.sqrt(2) * s / 2 - 0.02
    assert expected - h - 1e-12 <= distance(a, b) <= expected + 1e-12


@pytest.mark.parametrize("height", [0.005, 0.05])
def test_a_box_above_a_table_mesh_is_its_height_above(height):
    table = plate("fixture", (0.4, 0.4, 0.02), (0.0, 0.0, -0.01))          # top face at z = 0
    camera = box("camera_body", (0.05, -0.03, height + 0.05), (0.06, 0.06, 0.1), rpy=(0.0, 0.0, 0.3))
    assert height - h - 1e-12 <= distance(camera, table) <= height + 1e-12
    assert distance(table, camera) == distance(camera, table)


def test_capsules_are_their_axes_distance_less_both_radii():
    """Skew axes: x axis at z = 0 and y axis at z = 0.2, 0.2 apart."""
    a = Capsule("a", np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 0.05)
    b = Capsule("b", np.array([0.0, -1.0, 0.2]), np.array([0.0, 1.0, 0.2]), 0.03)
    assert distance(a, b) == pytest.approx(0.12, abs=1e-12)
    c = Capsule("c", np.array([2.0, 0.0, 0.1]), np.array([3.0, 0.0, 0.1]), 0.01)   # end to end
    assert distance(a, c) == pytest.approx(np.hypot(1.0, 0.1) - 0.06, abs=1e-12)


def test_a_capsule_beside_a_box_is_the_gap_to_its_surface():
    a = box("a", (0.0, 0.0, 0.0), (0.1, 0.1, 0.1))
    link = Capsule("link", np.array([0.09, -0.2, 0.0]), np.array([0.09, 0.2, 0.0]), 0.02)   # 0.02 off x = 0.05
    assert 0.02 - h - 1e-12 <= distance(a, link) <= 0.02 + 1e-12
    assert distance(link, a) == distance(a, link)


# -- overlap and containment: never a positive distance ------------------------------------------

def test_overlapping_bodies_give_no_positive_distance():
    a = box("a", (0.0, 0.0, 0.0), (0.1, 0.1, 0.1))
    assert distance(a, box("b", (0.09, 0.0, 0.0), (0.1, 0.1, 0.1))) <= 0.0
    assert distance(a, Capsule("c", np.array([0.0, 0.0, 0.04]), np.array([0.0, 0.0, 0.5]), 0.01)) <= 0.0
    assert distance(plate("part", (0.1, 0.1, 0.1), (0.0, 0.0, 0.0)), box("b", (0.06, 0.0, 0.0), (0.04, 0.04, 0.04))) <= 0.0


def test_a_body_wholly_inside_another_is_caught():
    """The sampled bound alone misses these (every sample of the outer body is outside the inner)."""
    big = box("big", (0.0, 0.0, 0.0), (0.3, 0.3, 0.3))
    assert distance(big, box("small", (0.01, 0.0, 0.0), (0.02, 0.02, 0.02))) < 0.0
    assert distance(big, Capsule("c", np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0]), 0.01)) < 0.0
    part = plate("part", (0.3, 0.3, 0.3), (0.0, 0.0, 0.0))
    assert distance(part, box("small", (0.0, 0.0, 0.0), (0.02, 0.02, 0.02))) < 0.0
    assert distance(part, Capsule("c", np.array([0.0, 0.0, 0.0]), np.array([0.05, 0.0, 0.0]), 0.01)) < 0.0
    assert distance(plate("part", (0.02, 0.02, 0.02), (0.0, 0.0, 0.0)), big) < 0.0   # mesh inside the box


# -- brute force: dense samples of both surfaces, nearest pairs by a k-d tree --------------------

def dense(body, pitch=0.001):
    """Points on a body's surface about `pitch` apart, by trimesh's own primitives."""
    if isinstance(body, Box):
        m = trimesh.creation.box(extents=2 * body.half_m, transform=body.T_cell_box)
    elif isinstance(body, Capsule):
        axis = body.b - body.a
        T = geometry.transform(geometry.frame_from_normal(geometry.unit(axis)), body.center)
        m = trimesh.creation.capsule(height=float(np.linalg.norm(axis)), radius=body.radius_m, count=[64, 64])
        m.apply_transform(T)
    else:
        m = trimesh.Trimesh(body.vertices, body.faces)
    n = int(m.area / pitch ** 2)
    return trimesh.sample.sample_surface_even(m, n, radius=0.5 * pitch, seed=7)[0]


def test_random_poses_agree_with_a_dense_brute_force():
    """Our distance is at most the brute force's (with its own sampling error, pitch / 2 plus a
    capsule's facets) and at most h below it."""
    rng = np.random.default_rng(3)
    part = Mesh.of("part", trimesh.creation.icosphere(subdivisions=2, radius=0.04), np.eye(4))
    bodies = []
    for _ in range(6):
        d = geometry.unit(rng.normal(size=3))
        bodies.append(box("camera_body", d * rng.uniform(0.07, 0.11), rng.uniform(0.02, 0.06, 3), rng.uniform(-3, 3, 3)))
        a = d * rng.uniform(0.07, 0.12)
        bodies.append(Capsule("link", a, a + rng.uniform(-0.1, 0.1, 3), float(rng.uniform(0.01, 0.04))))
    tolerance, tree = 0.001 + 0.0005, cKDTree(dense(part))
    for body in bodies:
        brute = tree.query(dense(body))[0].min()
        ours = distance(part, body)
        assert brute - h - tolerance <= ours <= brute + tolerance, (body, ours, brute)


# -- the scene ------------------------------------------------------------------------------------

def test_the_arm_links_end_at_the_flange_of_the_forward_kinematics():
    q = np.radians([30.0, -70.0, 100.0, -120.0, -90.0, 10.0])
    T_cell_base = geometry.transform(translation=(0.0, -0.4, 0.0))
    links = arm_links(T_cell_base, q)
    assert [c.name for c in links][-1] == "wrist_3" and links[0].a == pytest.approx([0.0, -0.4, 0.0])
    assert links[-1].b == pytest.approx((T_cell_base @ ur5e.forward(q))[:3, 3])
    assert all(np.allclose(a.b, b.a) for a, b in zip(links, links[1:]))                # one chain


def test_a_camera_in_the_part_and_a_lamp_on_the_camera_are_named():
    task = load_task(BRACKET)
    scene = CollisionScene.of(task)
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 0.02)                                                       # camera in the part
    hit = scene.clearance(T)
    assert not hit.ok and hit.distance_m <= 0.0 and set(hit.bodies) == {"camera_body", "part"}
    assert "collision" in hit.reason() and "camera_body" in hit.reason() and "part" in hit.reason()
    T[:3, 3] = (0.0, 0.0, 0.4)                                                        # above, looking up
    assert scene.clearance(T).ok
    lamp = scene.frames.T_cell_flange(T)[:3, 3] + (0.0, 0.0, 0.05)                     # lamp on the camera
    hit = scene.clearance(T, lamp_position=lamp)
    assert set(hit.bodies) == {"camera_body", "lamp_body"} and hit.distance_m <= 0.0


# -- the task's keys ------------------------------------------------------------------------------

def test_the_collision_keys_load_in_si_with_defaults(tmp_path):
    assert load_task(HINGE).cell.collision.padding_m == 0.01
    (tmp_path / "table.stl").write_bytes(trimesh.creation.box(extents=(400, 400, 20)).export(file_type="stl"))
    path = variant(tmp_path, HINGE, {"cell.collision": {
        "padding_mm": 15, "camera_body": {"size_mm": [50, 50, 120], "offset_mm": 60},
        "lamp_body": {"size_m": [0.05, 0.05, 0.1]}, "fixture_mesh": str(tmp_path / "table.stl")}})
    c = load_task(path).cell.collision
    assert c.padding_m == pytest.approx(0.015) and c.camera_size_m == pytest.approx((0.05, 0.05, 0.12))
    assert c.camera_offset_m == pytest.approx(0.06) and c.lamp_size_m == pytest.approx((0.05, 0.05, 0.1))
    assert c.fixture.extents == pytest.approx([0.4, 0.4, 0.02])                        # the part's unit, mm


@pytest.mark.parametrize("key, value, expected", [
    ("padding_m", -0.01, "a number >= 0"),
    ("camera_body", {"size_m": [0.05, 0.0, 0.1]}, "positive lengths"),
    ("fixture_mesh", "no-such-table.stl", "cell.collision.fixture_mesh"),
])
def test_bad_collision_keys_are_one_line_naming_file_and_key_and_exit_2(tmp_path, capsys, key, value, expected):
    path = variant(tmp_path, HINGE, {f"cell.collision.{key}": value})
    with pytest.raises(TaskError) as err:
        load_task(path)
    assert str(path) in str(err.value) and f"cell.collision.{key}" in str(err.value) and expected in str(err.value)
    assert main(["check", str(path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "found" in lines[0] and "expected" in lines[0]


# -- moves between two shots (cell.collision.paths) ------------------------------------------------

def wall_task(tmp_path):
    """The hinge with a wall (the fixture) between two camera poses 0.4 m above the cell's floor at
    x = -/+0.15 m, y = 0.15 m: the wall 20 mm thick at x = 0, y 0.05-0.25 m, its top at z = 0.42 m."""
    wall = trimesh.creation.box(extents=(20.0, 200.0, 220.0), transform=geometry.transform(translation=(0, 150, 310)))
    (tmp_path / "wall.stl").write_bytes(wall.export(file_type="stl"))
    return load_task(variant(tmp_path, HINGE, {"cell.collision.fixture_mesh": str(tmp_path / "wall.stl")}))


def stop(task, x, q_near=np.zeros(6)):
    """The camera 0.4 m above (x, 0.15 m) looking down, the arm's joints nearest q_near."""
    from cell.collision.paths import Stop
    from cell.planning.scene import look_at
    T = look_at(np.array([x, 0.15, 0.40]), np.array([x, 0.15, 0.0]))
    q = ur5e.inverse(task.frames.T_base_flange(task.frames.T_base_cam(T)), q_near)
    return Stop(T, q, (np.radians(180.0), np.radians(45.0), 0.2))     # the lamp at x = -0.14 m, clear


def test_a_move_through_a_wall_gets_via_points_over_it_and_each_step_keeps_the_padding(tmp_path):
    from cell.collision.paths import arm_path, plan_move
    task = wall_task(tmp_path)
    scene = CollisionScene.of(task)
    b = stop(task, 0.15)
    a = stop(task, -0.15, b.arm_joints)                          # the same configuration, mirrored
    assert scene.clearance(a.T_cell_cam, a.arm_joints).ok and scene.clearance(b.T_cell_cam, b.arm_joints).ok
    direct, _, _ = arm_path(scene, a.T_cell_cam, a.arm_joints, b.T_cell_cam, None)
    assert not direct.ok and "fixture" in direct.bodies and "with the camera at" in direct.reason()
    move = plan_move(scene, task.cell.devices.arm, 0, a, 1, b)
    assert move.clear and len(move.via) == 2 and move.to_json()["from"] == 0 and move.to_json()["to"] == 1
    assert all(T[2, 3] > 0.42 + 0.05 for T in move.via)          # the camera's bottom over the wall's top
    assert move.clearance.distance_m >= task.cell.collision.padding_m


def test_a_move_beyond_the_arms_reach_is_refused_saying_why_not_as_a_collision(tmp_path):
    """A moveL whose end the UR5e does not reach (1.2 m from its base, which spans 0.82 m): the
    refusal gives the inverse kinematics' own words (ur5e.Unreachable), not two bodies touching."""
    from cell.collision.paths import Stop, plan_move
    from cell.planning.scene import look_at
    task = wall_task(tmp_path)
    start = stop(task, -0.15, stop(task, 0.15).arm_joints)          # clear, as the test above's
    a = Stop(start.T_cell_cam, start.arm_joints, None)
    far = look_at(np.array([0.6, 0.6, 0.4]), np.array([0.6, 0.6, 0.0]))
    with pytest.raises(ur5e.Unreachable) as beyond:
        ur5e.inverse(task.frames.T_base_flange(task.frames.T_base_cam(far)), a.arm_joints)
    move = plan_move(CollisionScene.of(task), task.cell.devices.arm, 0, a, 1, Stop(far, a.arm_joints, None), ())
    said = move.clearance.reason()
    assert not move.clear and move.clearance.distance_m == -np.inf
    assert said == f"the arm cannot follow the straight path ({beyond.value})" and "touch or overlap" not in said


# -- the paths' steps per pair: which joints move a body, how far its points travel -----------------

def bodies_at(scene, q):
    """The scene's bodies with the arm at joints q (the camera where the flange puts it)."""
    T_base_cam = scene.frames.T_base_cam_from_flange(ur5e.forward(q))
    return scene.bodies(scene.frames.T_cell_cam_from_base(T_base_cam), q)


def material_points(body, frame, rng, n=200):
    """Points of the body (its surface, or its box's inside) in `frame`'s coordinates: where they
    sit in the link that carries them, so that they move as the link moves. A capsule's: n
    directions of a Fibonacci sphere about 11 points of its axis, both ends among them."""
    from cell.collision.bodies import Capsule
    if isinstance(body, Capsule):
        k = np.arange(n) + 0.5
        z, phi = 1.0 - 2.0 * k / n, np.pi * (1.0 + 5.0 ** 0.5) * k
        u = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z])
        axis = body.a + np.linspace(0.0, 1.0, 11)[:, None] * (body.b - body.a)
        points = (axis[:, None, :] + body.radius_m * u[None]).reshape(-1, 3)
    else:
        corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3)).T.reshape(-1, 3)
        points = geometry.apply(body.T_cell_box, np.vstack([corners, rng.uniform(-1, 1, (n, 3))]) * body.half_m)
    return geometry.apply(np.linalg.inv(frame), points)


def test_each_body_moves_with_the_joints_up_to_its_link_and_no_others():
    from cell.collision.scene import LINK
    rng = np.random.default_rng(5)
    scene = CollisionScene.of(load_task(BRACKET))
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, 6)
        before = {b.name: b for b in bodies_at(scene, q) if b.name in LINK}
        for joint in range(6):
            moved = q + np.eye(6)[joint] * 0.3
            after = {b.name: b for b in bodies_at(scene, moved) if b.name in LINK}
            for name, link in LINK.items():
                a, b = before[name], after[name]
                same = (np.allclose(a.a, b.a, atol=1e-12) and np.allclose(a.b, b.b, atol=1e-12)
                        if hasattr(a, "a") else np.allclose(a.T_cell_box, b.T_cell_box, atol=1e-12))
                assert same == (joint >= link), (name, joint)


def test_a_pairs_distance_does_not_change_with_the_joints_nearer_the_base_than_both():
    from cell.collision.scene import LINK, MAY_TOUCH
    rng = np.random.default_rng(6)
    scene = CollisionScene.of(load_task(BRACKET))
    q = np.radians([-80.0, -100.0, 80.0, -60.0, -90.0, 20.0])
    bodies = {b.name: b for b in bodies_at(scene, q) if b.name in LINK}
    for _ in range(3):
        moved = q.copy()
        for name_a, name_b in [(a, b) for a in LINK for b in LINK if a < b and frozenset((a, b)) not in MAY_TOUCH]:
            lo = min(LINK[name_a], LINK[name_b])
            moved[:lo] = q[:lo] + rng.uniform(-1.0, 1.0, lo)
            turned = {b.name: b for b in bodies_at(scene, moved) if b.name in LINK}
            assert distance(turned[name_a], turned[name_b]) == pytest.approx(
                distance(bodies[name_a], bodies[name_b]), abs=1e-9), (name_a, name_b)
            moved = q.copy()


def test_body_reach_is_the_farthest_point_of_each_body_from_each_axis_that_moves_it():
    from cell.collision.paths import body_reach
    from cell.collision.scene import LINK
    rng = np.random.default_rng(7)
    scene = CollisionScene.of(load_task(BRACKET))
    q = rng.uniform(-np.pi, np.pi, 6)
    bodies = bodies_at(scene, q)
    reach = body_reach(scene, bodies, q)
    frames = ur5e.chain(scene.frames.T_cell_base, q)
    for b, body in enumerate(bodies):
        link = LINK.get(body.name, 0)
        assert np.all(reach[b, link:] == 0.0)
        if link == 0:
            continue
        points = geometry.apply(frames[link], material_points(body, frames[link], rng, 2000))
        for i in range(link):
            o, z = frames[i, :3, 3], frames[i, :3, 2]
            rel = points - o
            far = np.linalg.norm(rel - np.outer(rel @ z, z), axis=1).max()
            assert far - 1e-12 <= reach[b, i] <= far + 1e-4, (body.name, i)   # sampled: within 0.1 mm below


def test_a_step_moves_each_pairs_body_no_farther_than_its_sweep_bound():
    """Dense joint-linear motion over a step: each point of the body further down the chain,
    seen from the frame of the other's link, travels at most sum over the joints between of
    |dq_i| (r_i + X), r_i body_reach's larger at the two ends, X the widening the bound allows
    (X = B / (1 - sum |dq_i|), B the bound unwidened)."""
    from cell.collision.paths import body_reach
    from cell.collision.scene import LINK
    rng = np.random.default_rng(8)
    scene = CollisionScene.of(load_task(BRACKET))
    for trial in range(6):
        q0 = rng.uniform(-np.pi, np.pi, 6)
        one = trial % 2 == 1                              # a step of one joint: the bound is nearly met
        q1 = q0 + (np.eye(6)[rng.integers(6)] * 0.1 if one else rng.uniform(-0.1, 0.1, 6))
        b0, b1 = bodies_at(scene, q0), bodies_at(scene, q1)
        reach = np.maximum(body_reach(scene, b0, q0), body_reach(scene, b1, q1))
        frames0 = ur5e.chain(scene.frames.T_cell_base, q0)
        path = [ur5e.chain(scene.frames.T_cell_base, (1 - t) * q0 + t * q1) for t in np.linspace(0, 1, 101)]
        for b, body in enumerate(b0):
            hi = LINK.get(body.name, 0)
            if hi == 0:
                continue
            local = material_points(body, frames0[hi], rng)
            for lo in range(hi):
                seen = [geometry.apply(np.linalg.inv(F[lo]) @ F[hi], local) for F in path]
                travel = max(np.linalg.norm(p - seen[0], axis=1).max() for p in seen)
                dq = np.abs(q1 - q0)[lo:hi]
                bound = dq @ reach[b, lo:hi]
                assert travel <= dq @ (reach[b, lo:hi] + bound / (1 - dq.sum())) + 1e-12, (body.name, lo)
                if one:                                   # the farthest point's arc: r dq, its chord nearly
                    assert travel >= 0.95 * bound, (body.name, lo)


def test_clear_answers_as_the_least_distance_does_but_trusts_bounding_spheres_the_padding_apart():
    """Pairs.clear against Pairs.least at random arm poses and paddings: the same answer, but
    where the sampled distance errs below the padding for a pair whose spheres alone prove it
    farther (then clear says yes, least no)."""
    from cell.collision.scene import Pairs
    rng = np.random.default_rng(9)
    scene = CollisionScene.of(load_task(BRACKET))
    answers = set()
    for _ in range(60):
        q = rng.uniform(-np.pi, np.pi, 6)
        bodies = bodies_at(scene, q)
        for padding in (0.0, 0.01, 0.05, 0.2):
            least = Pairs.of(bodies, len(scene.fixed)).least(padding)
            pairs = Pairs.of(bodies, len(scene.fixed))
            clear = pairs.clear(padding)
            if clear != least.ok:
                k = [n for n in range(len(pairs.gap)) if {bodies[pairs.i[n]].name, bodies[pairs.j[n]].name}
                     == set(least.bodies)][0]
                assert clear and pairs.gap[k] >= padding and least.distance_m >= padding - h
            answers.add(clear)
    assert answers == {True, False}
