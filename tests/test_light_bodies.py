"""Fixed lights as obstacles for the collision check (cell.collision.scene.light_bodies): each
fixed light's housing is a body whose front face holds its emitter points (cell.planning.lights,
an independent construction of the same light), a camera put into a bar's housing is refused
naming the bar; a ring's body is the annulus round its hole and a dome's the shell open at its
hole (closed forms, a dense brute force written out here); the simulator's own check has the
same shapes, lets a camera through a ring's hole and stops one driven into its housing."""
from pathlib import Path

import numpy as np

import pytest
from scipy.spatial import cKDTree

from cell.collision.bodies import BOX_TOLERANCE_M, SAMPLE_BOUND_M, Annulus, Box, Capsule, Shell, distance
from cell.collision.scene import CollisionScene, light_bodies, light_body, reaching_joints
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.planning.lights import emitters
from cell.planning.scene import look_at
from cell.planning.whole_part import plan_features
from cell.run.moves import with_moves
from cell.task import loader
from cell.task.types import HOUSING_DEPTH_M, Channel, Light
from sim.arm import SimArm
from sim.obstacles import CONTACT_M, Obstacles, light_housing, surface_points

from simcell import variant

TASKS = Path(__file__).parent / "tasks" / "features"
RING = Path(__file__).parent.parent / "tasks" / "ring.yaml"


def test_each_fixed_lights_housing_holds_its_emitter_points_on_its_front_face():
    task = loader.load_task(TASKS / "plate_bar.yaml")
    boxes = light_bodies(task)
    assert [b.name for b in boxes] == ["bar_left", "bar_right"]
    for light, box in zip(task.lights, boxes):
        points = emitters(light, np.eye(4), 64).position
        assert np.allclose(box.sdf(points), 0.0, atol=1e-9)           # on the surface
        assert np.all(box.sdf(points - 1e-3 * light.axis) < 0)          # just behind: inside the housing
        assert np.all(box.sdf(points + 1e-3 * light.axis) > 0)          # just in front: outside
        assert np.isclose(box.sdf(light.position_m - HOUSING_DEPTH_M * light.axis - 1e-3 * light.axis), 1e-3)
    scene = CollisionScene.of(task)
    assert [b.name for b in scene.fixed] == ["part", "bar_left", "bar_right"]


def test_a_ring_on_the_flange_is_no_fixed_body_and_a_fixed_ring_is():
    task = loader.load_task(RING)
    assert [b.name for b in light_bodies(task)] == ["dark_field_ring"]


def test_a_camera_inside_a_bars_housing_is_refused_naming_the_bar():
    task = loader.load_task(TASKS / "plate_bar.yaml")
    scene = CollisionScene.of(task)
    bar = task.lights[0]
    # the camera's optical centre 5 mm behind the bar's emitting centre, looking along the bar's axis
    T = np.eye(4)
    T[:3, :3] = geometry.frame_from_normal(-np.asarray(bar.axis))
    T[:3, 3] = np.asarray(bar.position_m) - 0.005 * np.asarray(bar.axis)
    c = scene.clearance(T)
    assert not c.ok and "bar_left" in c.bodies
    far = np.eye(4)
    far[:3, 3] = (0.0, 0.0, 0.4)
    assert scene.clearance(far).ok


# -- a ring's and a dome's bodies are hollow: closed forms and a dense brute force ----------------

T_LIGHT = geometry.from_rpy(np.array([0.3, -0.2, 0.5]), (0.01, 0.02, 0.1))     # any pose
h = SAMPLE_BOUND_M
INNER, OUTER, DEPTH = 0.05, 0.07, 0.02                                        # a ring's housing
R, HOLE, SHELL = 0.1, 0.02, 0.01                                              # a dome's


def ring_body():
    return Annulus("ring", T_LIGHT, INNER, OUTER, (-DEPTH, 0.0))


def dome_body():
    return Shell("dome", T_LIGHT, R, R, R + SHELL, HOLE)


def on_axis(t):
    """The point t along the light's axis from its emitting centre (cell frame)."""
    return geometry.apply(T_LIGHT, np.array([0.0, 0.0, t]))


def axis_box(half, centre_t):
    """A box on the light's axis, its faces parallel to the light's frame, centred centre_t along it."""
    return Box("camera_body", T_LIGHT @ geometry.transform(translation=(0.0, 0.0, centre_t)), np.asarray(half, float))


def test_a_point_on_a_rings_axis_is_the_holes_rim_away_not_inside():
    ring = ring_body()
    for t in (-0.015, -0.01, -0.001):                        # level with the housing: the hole's wall
        assert ring.sdf(on_axis(t))[0] == pytest.approx(INNER, abs=1e-12)
    for above in (0.003, 0.05):                              # in front of its LEDs, behind its back
        assert ring.sdf(on_axis(above))[0] == pytest.approx(np.hypot(INNER, above), abs=1e-12)
        assert ring.sdf(on_axis(-DEPTH - above))[0] == pytest.approx(np.hypot(INNER, above), abs=1e-12)
    middle = geometry.apply(T_LIGHT, np.array([0.0, 0.5 * (INNER + OUTER), -0.5 * DEPTH]))
    assert ring.sdf(middle)[0] == pytest.approx(-0.5 * min(OUTER - INNER, DEPTH), abs=1e-12)


@pytest.mark.parametrize("centre_t, gap_along", [(-0.01, 0.0), (0.04, 0.02), (-0.07, 0.0)])
def test_a_camera_box_through_a_rings_hole_is_its_corner_to_the_rim(centre_t, gap_along):
    """A 60 x 60 mm box on the axis: its vertical edges sqrt(2) 30 mm from the axis, so it clears the
    hole's wall by INNER - 42.4 mm where it passes the housing, by hypot(that, gap) above it."""
    half = np.array([0.03, 0.03, 0.05]) if gap_along == 0.0 else np.array([0.03, 0.03, 0.02])
    corner = np.hypot(*half[:2])
    expected = np.hypot(INNER - corner, gap_along)
    got = distance(axis_box(half, centre_t), ring_body())
    assert expected - BOX_TOLERANCE_M - 1e-12 <= got <= expected + 1e-12
    assert distance(ring_body(), axis_box(half, centre_t)) == got
    # the old body, a box solid across the hole, overlapped it
    assert distance(axis_box(half, centre_t), Box("old", T_LIGHT @ geometry.transform(translation=(0, 0, -0.5 * DEPTH)),
                                                  np.array([OUTER, OUTER, 0.5 * DEPTH]))) <= (0.0 if gap_along == 0 else 1.0)


def test_a_link_down_the_axis_of_a_ring_or_through_a_domes_hole_is_the_hole_less_its_radius():
    a, b = on_axis(0.3), on_axis(-0.3)
    assert distance(Capsule("wrist_3", a, b, 0.03), ring_body()) == pytest.approx(INNER - 0.03, abs=1e-5)
    assert distance(dome_body(), Capsule("wrist_3", a, b, 0.012)) == pytest.approx(HOLE - 0.012, abs=1e-5)
    across = Capsule("forearm", on_axis(-0.01) + 0.3 * T_LIGHT[:3, 0], on_axis(-0.01) - 0.3 * T_LIGHT[:3, 0], 0.02)
    assert distance(across, ring_body()) <= 0.0                  # across the housing: through its wall


def test_a_domes_shell_is_open_at_its_hole_and_its_rim():
    dome = dome_body()
    assert dome.sdf(on_axis(R))[0] == pytest.approx(R, abs=1e-12)      # its sphere's centre: the inner surface all round
    edge = np.sqrt((R + SHELL) ** 2 - HOLE ** 2)          # the hole's outer edge, this far from the centre along the axis
    for above in (0.0, 0.01, 0.1):                        # at and above the pole: the hole's wall, or its outer edge
        assert dome.sdf(on_axis(-above))[0] == pytest.approx(np.hypot(HOLE, max(0.0, R + above - edge)), abs=1e-12)
    beyond = geometry.apply(T_LIGHT, np.array([R + 0.5 * SHELL, 0.0, R + 0.004]))   # past the rim's plane
    assert dome.sdf(beyond)[0] == pytest.approx(0.004, abs=1e-12)
    wall = geometry.apply(T_LIGHT, np.array([0.0, 0.0, R]) + (R + 0.5 * SHELL) * geometry.unit(np.array([1.0, 0.0, -1.0])))
    assert dome.sdf(wall)[0] == pytest.approx(-0.5 * SHELL, abs=1e-12)


def circles(radii, heights, pitch):
    """Points on circles about the light's axis (its frame), each radius at each height, about
    `pitch` apart along each."""
    out = []
    for r in np.atleast_1d(radii):
        az = np.linspace(0.0, 2 * np.pi, max(8, int(np.ceil(2 * np.pi * r / pitch))), endpoint=False)
        for z in np.atleast_1d(heights):
            out.append(np.column_stack([r * np.cos(az), r * np.sin(az), np.full(len(az), z)]))
    return np.vstack(out)


def dense_ring(pitch):
    """Points on the ring housing's four faces about `pitch` apart, written out: the hole's wall,
    the outer wall, the front and the back."""
    walls = np.linspace(-DEPTH, 0.0, int(np.ceil(DEPTH / pitch)) + 1)
    faces = np.linspace(INNER, OUTER, int(np.ceil((OUTER - INNER) / pitch)) + 1)
    return geometry.apply(T_LIGHT, np.vstack([circles(INNER, walls, pitch), circles(OUTER, walls, pitch),
                                              circles(faces, (-DEPTH, 0.0), pitch)]))


def dense_dome(pitch):
    """Points on the dome housing's surfaces about `pitch` apart, written out: the two spherical
    caps (polar angle up to 90 deg, outside the hole's cylinder), the hole's wall and the rim."""
    out = []
    for rho in (R, R + SHELL):
        polar = np.linspace(np.arcsin(HOLE / rho), 0.5 * np.pi, int(np.ceil(0.5 * np.pi * rho / pitch)) + 1)
        out += [circles(rho * np.sin(p), R - rho * np.cos(p), pitch) for p in polar]
    hole = np.linspace(R - np.sqrt((R + SHELL) ** 2 - HOLE**2), R - np.sqrt(R**2 - HOLE**2), int(SHELL / pitch) + 2)
    out += [circles(HOLE, hole, pitch), circles(np.linspace(R, R + SHELL, int(SHELL / pitch) + 2), R, pitch)]
    return geometry.apply(T_LIGHT, np.vstack(out))


def box_surface(box, pitch):
    """Points on a box's six faces on a grid `pitch` apart, written out."""
    out = []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        U, V = np.meshgrid(*(np.linspace(-box.half_m[k], box.half_m[k], int(np.ceil(2 * box.half_m[k] / pitch)) + 1)
                             for k in (u, v)))
        for side in (-1.0, 1.0):
            face = np.zeros((U.size, 3))
            face[:, axis], face[:, u], face[:, v] = side * box.half_m[axis], U.ravel(), V.ravel()
            out.append(face)
    return geometry.apply(box.T_cell_box, np.vstack(out))


def inside(body, points):
    """The housing's solid, written out in its own frame."""
    x, y, z = ((points - T_LIGHT[:3, 3]) @ T_LIGHT[:3, :3]).T
    r = np.hypot(x, y)
    if isinstance(body, Annulus):
        return (r >= INNER) & (r <= OUTER) & (z >= -DEPTH) & (z <= 0.0)
    rho = np.sqrt(r**2 + (z - R) ** 2)
    return (rho >= R) & (rho <= R + SHELL) & (z <= R) & (r >= HOLE)


def nearest_within(tree, points, bound):
    """The distance from each point to the nearest dense sample, inf where none is within `bound`
    (a k-d tree searching a sphere's samples from near its centre visits them all: the bound
    keeps the brute force fast)."""
    bound = np.broadcast_to(bound, len(points))
    out = np.full(len(points), np.inf)
    for b in np.unique(np.round(bound, 4)):
        pick = np.round(bound, 4) == b
        out[pick] = tree.query(points[pick], distance_upper_bound=b + 1e-4)[0]
    return out


@pytest.mark.parametrize("make, dense", [(ring_body, dense_ring), (dome_body, dense_dome)])
def test_the_housings_distance_agrees_with_a_dense_brute_force(make, dense):
    """Random points (SDF), boxes and capsules near the housing: the distance within the dense
    samples' spacing of the nearest sample's, the sign the solid's; a box's and a capsule's
    distance never above the brute force's (tests/test_box_housing.py: a box's within its tolerance)."""
    pitch, body = 5e-4, make()
    samples = dense(pitch)
    tree = cKDTree(samples)
    rng = np.random.default_rng(5)

    def near(n, reach):
        """n points within `reach` of the housing's surface (of a dense sample)."""
        return samples[rng.integers(len(samples), size=n)] + rng.uniform(-reach, reach, (n, 3))
    points = np.vstack([near(4000, 0.03), geometry.apply(T_LIGHT, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, R]]))])
    sdf = body.sdf(points)
    nearest = nearest_within(tree, points, np.abs(sdf) + pitch)
    assert np.all(np.abs(sdf) <= nearest + 1e-12) and np.all(np.isfinite(nearest))
    assert np.array_equal(sdf <= 0.0, inside(body, points))
    for _ in range(16):
        centre = near(1, 0.06)[0]
        cam = Box("camera_body", geometry.from_rpy(rng.uniform(-3, 3, 3), centre), rng.uniform(0.005, 0.03, 3))
        surface = box_surface(cam, pitch)
        got = distance(cam, body)
        if inside(body, surface).any() or cam.sdf(body.point)[0] <= 0.0:
            assert got <= 0.0
        else:
            brute = nearest_within(tree, surface, got + h + 2 * pitch).min()
            assert got <= brute + 1e-12 and np.isfinite(brute)
        a = centre + rng.uniform(-0.1, 0.1, 3)
        link = Capsule("forearm", a, a + rng.uniform(-0.15, 0.15, 3), float(rng.uniform(0.005, 0.03)))
        along = link.a + np.linspace(0.0, 1.0, 4000)[:, None] * (link.b - link.a)
        got = distance(link, body)
        if inside(body, along).any():
            assert got <= 0.0
        else:
            brute = nearest_within(tree, along, got + link.radius_m + 2 * pitch).min() - link.radius_m
            assert got <= brute + 1e-12 and np.isfinite(brute)


# -- the simulator's own check knows the lights' housings, the same shapes ------------------------

RING_LENS = TASKS / "ring_lens.yaml"


def test_the_simulators_housings_are_the_planners_shapes():
    """sim.obstacles.light_housing (trimesh's annulus, its own revolved shell, a box) against the
    planner's bodies: every point the simulator samples on a housing lies on the planner's body's
    surface (within the polygons' 0.01 mm), and its volume is the shape's closed form."""
    ring, dome = fixed_light("ring", radius_m=0.065, aperture_radius_m=0.055, outer_radius_m=0.075), \
        fixed_light("dome", radius_m=R, hole_radius_m=HOLE, housing_depth_m=SHELL)
    bar = loader.load_task(TASKS / "plate_bar.yaml").lights[0]
    ri, ro, d = 0.055, 0.075, HOUSING_DEPTH_M
    volumes = {"ring": np.pi * (ro**2 - ri**2) * d, "bar": (bar.length_m + 0.01) * 0.01 * d,
               "dome": 2 * np.pi / 3 * ((R + SHELL) ** 3 - R**3 - ((R + SHELL) ** 3 - ((R + SHELL) ** 2 - HOLE**2) ** 1.5)
                                        + (R**3 - (R**2 - HOLE**2) ** 1.5))}
    for light in (ring, dome, bar):
        mesh = light_housing(light)
        assert np.abs(light_body(light).sdf(surface_points(mesh))).max() < 1e-5, light.type
        assert mesh.volume == pytest.approx(volumes[light.type], rel=1e-3), light.type


def fixed_light(kind, **keys):
    down = np.array([0.0, 0.0, -1.0])
    return Light(kind, kind, "fixed", 0.5, Channel(7), np.array([0.0, 0.0, 0.2]), down, np.array([1.0, 0.0, 0.0]), **keys)


@pytest.fixture(scope="module")
def ring_lens():
    """ring_lens.yaml and its plan."""
    task = loader.load_task(RING_LENS)
    return task, plan_features(task)


def test_a_camera_through_a_rings_hole_plans_and_the_simulators_check_stops_it_going_into_the_housing(ring_lens):
    """ring_lens.yaml: the camera body reaches through the lens ring's 55 mm hole, 12.6 mm from
    its rim (corner 42.4 mm off the axis): the plan is feasible with that clearance (within the
    box's BOX_TOLERANCE_M); the simulated arm at the shot finds the ring that far by its own
    check, and a move 40 mm to the side, into the housing, stops naming the ring."""
    task, plan = ring_lens
    shot, true = plan.shots[0], 0.055 - np.hypot(0.03, 0.03)
    assert plan.feasible and shot.clearance.bodies == ("lens_ring", "camera_body")
    assert true - BOX_TOLERANCE_M - 1e-9 <= shot.clearance.distance_m <= true + 1e-9
    arm = SimArm(task.cell.devices.arm, task.frames, joints=reaching_joints(task.frames, shot.T_cell_cam),
                 obstacles=Obstacles(task))
    gap, contact = arm.obstacles.gap(arm.joints, None)
    assert contact.other == "lens_ring" and true - 1e-4 <= gap <= true + CONTACT_M
    with pytest.raises(DeviceFault) as fault:
        arm.move_camera(shot.T_cell_cam @ geometry.transform(translation=(0.04, 0.0, 0.0)))
    assert "protective stop" in fault.value.reason and "lens_ring" in fault.value.reason


@pytest.mark.long          # 10-30 s: the simulated arm's own check steps finely near the ring
def test_the_simulated_arm_takes_the_planned_way_down_through_the_rings_hole(ring_lens):
    """The run's move from the home pose: over the ring and down its axis (two via points), which
    the simulator's own check lets through."""
    task, plan = ring_lens
    move = with_moves(task, plan).moves[0]
    assert move.clear and len(move.via) == 2
    ring = next(light for light in task.lights if light.name == "lens_ring")
    assert np.allclose(move.via[-1][:2, 3], ring.position_m[:2], atol=1e-9)     # the last via point on its axis
    arm = SimArm(task.cell.devices.arm, task.frames, obstacles=Obstacles(task))
    for T in (*move.via, plan.shots[0].T_cell_cam):
        arm.move_camera(T)
    assert np.allclose(arm.camera_pose(), plan.shots[0].T_cell_cam, atol=1e-9)


def test_a_dome_over_the_part_is_a_body_the_camera_looks_in_through_its_hole(tmp_path):
    """ring.yaml with a dome (radius 100 mm, its centre at the plate's top, a 15 mm camera hole at
    its pole 108 mm up) instead of its rings: the camera 300 mm over the feature clears the dome by
    its box's lower corners to the hole's outer edge (closed form); lowered to 120 mm its box
    meets the shell round the hole, refused naming the dome; the simulator's check finds it too."""
    dome = {"name": "dome", "type": "dome", "mount": "fixed", "position_m": [0.0, 0.0, 0.108],
            "aim_m": [0.0, 0.0, 0.0], "radius_mm": 100, "hole_radius_mm": 15, "power_w": 2.0, "channel": 1}
    task = loader.load_task(variant(tmp_path, RING, {"lights": [dome]}))
    scene = CollisionScene.of(task)
    assert [b.name for b in scene.fixed] == ["part", "dome"] and isinstance(scene.fixed[1], Shell)
    top = np.array([0.0, 0.0, 0.008])
    for height, clear in ((0.300, True), (0.120, False)):
        T = look_at(top + (0.0, 0.0, height), top)
        c = scene.clearance(T)
        assert c.ok == clear and (clear or "dome" in c.bodies)
        camera = scene.camera_body(task.frames.T_cell_flange(T))
        bottom = camera.center[2] - camera.half_m[2]               # its lower face, level
        edge = 0.008 + np.sqrt(0.12**2 - 0.015**2)     # the hole's outer edge, the shell's top: under the box
        got = distance(camera, scene.fixed[1])
        if clear:
            assert bottom - edge - BOX_TOLERANCE_M - 1e-9 <= got <= bottom - edge + 1e-9
        arm = SimArm(task.cell.devices.arm, task.frames, joints=reaching_joints(task.frames, T), obstacles=Obstacles(task))
        gap, contact = arm.obstacles.gap(arm.joints, None)
        assert (gap >= CONTACT_M) == clear and (clear or contact.other == "dome")
