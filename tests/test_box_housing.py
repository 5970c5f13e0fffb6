"""A box (the camera's body, the lamp's) against a ring's or a dome's housing
(cell.collision.bodies.box_to_revolved): a lower bound within BOX_TOLERANCE_M of the true
distance. The reference is written out here, apart from the planner's code: the housing's
surfaces sampled densely by their own parameters (angle about the axis, place along the
cross-section's edge), the box's exact distance at each, then the best few samples polished by a
local search over those parameters; the true distance is the least over the housing's surface of
the distance to the box, as the box is convex. Random poses, a box inside the hole, one at the
rim, grazing a wall, flat over the ring's front and under the dome's rim."""
import numpy as np

import pytest
from scipy.optimize import minimize

from cell.collision.bodies import BOX_TOLERANCE_M, Annulus, Box, Shell, distance
from cell.core import geometry

T_LIGHT = geometry.from_rpy(np.array([-0.4, 0.25, 1.1]), (-0.02, 0.01, 0.15))     # any pose
INNER, OUTER, FRONT, BACK = 0.055, 0.075, 0.0, -0.02                             # a ring's housing
R, SHELL, HOLE = 0.1, 0.012, 0.03                                                # a dome's


def ring():
    return Annulus("ring", T_LIGHT, INNER, OUTER, (BACK, FRONT))


def dome():
    return Shell("dome", T_LIGHT, R, R, R + SHELL, HOLE)


def edges(body):
    """The housing's cross-section's edges in (r, z) (its own frame) as functions of s in [0, 1]:
    a ring's four sides; a dome's two arcs about (0, R) from its hole to its rim, the hole's wall
    and the rim."""
    if isinstance(body, Annulus):
        return [lambda s: (INNER, BACK + s * (FRONT - BACK)), lambda s: (OUTER, BACK + s * (FRONT - BACK)),
                lambda s: (INNER + s * (OUTER - INNER), FRONT), lambda s: (INNER + s * (OUTER - INNER), BACK)]

    def arc(rho):
        start = np.arcsin(HOLE / rho)
        return lambda s: (rho * np.sin(start + s * (0.5 * np.pi - start)), R - rho * np.cos(start + s * (0.5 * np.pi - start)))
    top, bottom = R - np.sqrt((R + SHELL) ** 2 - HOLE**2), R - np.sqrt(R**2 - HOLE**2)
    return [arc(R), arc(R + SHELL), lambda s: (HOLE, top + s * (bottom - top)), lambda s: (R + s * SHELL, R)]


def surface_point(edge, theta, s):
    r, z = edge(np.clip(s, 0.0, 1.0))
    return geometry.apply(T_LIGHT, np.column_stack([r * np.cos(theta), r * np.sin(theta), z * np.ones_like(theta)]))


def inside(body, point):
    """The point in the housing's solid (written out in its own frame)."""
    x, y, z = geometry.apply(np.linalg.inv(T_LIGHT), point)
    r = np.hypot(x, y)
    if isinstance(body, Annulus):
        return INNER <= r <= OUTER and BACK <= z <= FRONT
    return R <= np.hypot(r, z - R) <= R + SHELL and z <= R and r >= HOLE


def brute_distance(box, body, pitch=1e-3, polish=6):
    """The least of box.sdf over the housing's surface: dense samples `pitch` apart, then the
    `polish` best of them searched locally (Nelder-Mead over angle and place)."""
    starts = []
    for edge in edges(body):
        s = np.linspace(0.0, 1.0, 60)
        r_max = max(edge(x)[0] for x in s)
        theta = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * r_max / pitch), endpoint=False)
        S, TH = np.meshgrid(s, theta)
        d = box.sdf(surface_point(edge, TH.ravel(), S.ravel()))
        for k in np.argsort(d)[:polish]:
            starts.append((d[k], edge, TH.ravel()[k], S.ravel()[k]))
    starts.sort(key=lambda x: x[0])
    best = starts[0][0]
    for _, edge, theta, s in starts[:polish]:
        res = minimize(lambda x: box.sdf(surface_point(edge, np.array([x[0]]), np.array([x[1]])))[0],
                       [theta, s], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 2000})
        best = min(best, float(res.fun))
    return best


def check(box, body):
    """distance(box, body) within [true - BOX_TOLERANCE_M, true], either way round; <= 0 where they meet."""
    got = distance(box, body)
    assert distance(body, box) == got
    true = -1.0 if inside(body, box.center) else brute_distance(box, body)
    if true <= 0.0:
        assert got <= 0.0
    else:
        assert true - BOX_TOLERANCE_M - 1e-9 <= got <= true + 1e-9, (got, true)
    return got, true


def local_box(centre, half, rpy=(0.0, 0.0, 0.0)):
    """A box with its centre and axes given in the light's frame."""
    return Box("camera_body", T_LIGHT @ geometry.from_rpy(np.asarray(rpy, float), centre), np.asarray(half, float))


@pytest.mark.parametrize("make", [ring, dome])
def test_random_boxes_near_a_housing_are_within_the_tolerance_of_the_brute_force(make):
    body, rng = make(), np.random.default_rng(26)
    outcomes = []
    middle = np.array([0.0, 0.0, 0.5 * (BACK + FRONT) if isinstance(body, Annulus) else R])
    for _ in range(12):
        centre = middle + geometry.unit(rng.normal(size=3)) * rng.uniform(0.0, 0.16)
        got, true = check(local_box(centre, rng.uniform(0.005, 0.03, 3), rng.uniform(-3, 3, 3)), body)
        outcomes.append(true > 0.0)
    assert any(outcomes) and not all(outcomes)             # both kinds: clear and meeting


@pytest.mark.parametrize("make", [ring, dome])
def test_a_box_inside_the_hole_is_its_corners_to_the_wall(make):
    """A 36 x 36 mm box down the hole, turned about the axis and tilted a little: clear of the
    wall, where the sampled bound it replaces was up to 2 mm low."""
    body, rng = make(), np.random.default_rng(3)
    level = 0.5 * (BACK + FRONT) if isinstance(body, Annulus) else R - np.sqrt(R**2 - HOLE**2) - 0.004
    for _ in range(6):
        half = (0.018 if isinstance(body, Annulus) else 0.012,) * 2 + (0.04,)
        got, true = check(local_box((*rng.uniform(-0.003, 0.003, 2), level),
                                    half, (*rng.uniform(-0.05, 0.05, 2), rng.uniform(-3, 3))), body)
        assert true > 0.0


def test_an_upright_box_in_a_rings_hole_is_exact_to_its_closed_form():
    """Its vertical edges hypot(18, 18) mm from the axis: INNER less that, over the wall's depth."""
    got = distance(local_box((0.0, 0.0, -0.01), (0.018, 0.018, 0.05)), ring())
    assert INNER - np.hypot(0.018, 0.018) - BOX_TOLERANCE_M <= got <= INNER - np.hypot(0.018, 0.018) + 1e-12


@pytest.mark.parametrize("make", [ring, dome])
def test_a_box_at_the_rim_touching_and_just_clear(make):
    """A box's corner put at the cross-section's outer corner (ring: its front's outer edge; dome:
    its rim's outer edge), moved out along the bisector by 0, 0.05, 0.3 and 3 mm."""
    body = make()
    edge = np.array([OUTER, 0.0, FRONT]) if isinstance(body, Annulus) else np.array([R + SHELL, 0.0, R])
    out = geometry.unit(np.array([1.0, 0.0, 1.0]))
    half = np.array([0.01, 0.015, 0.02])
    R_box = geometry.frame_from_normal(out)
    for gap in (0.0, 5e-5, 3e-4, 3e-3):
        corner = edge + gap * out
        T = np.eye(4)
        T[:3, :3] = R_box
        T[:3, 3] = corner + R_box @ half                       # the box's (-,-,-) corner at `corner`
        box = Box("camera_body", T_LIGHT @ T, half)
        got, true = check(box, body)
        assert true == pytest.approx(gap, abs=1e-7)


@pytest.mark.parametrize("make", [ring, dome])
def test_a_box_grazing_the_outer_wall(make):
    """A box's face parallel to the wall's tangent plane, 0, 0.02 and 0.5 mm out."""
    body = make()
    for gap in (0.0, 2e-5, 5e-4):
        if isinstance(body, Annulus):
            centre = (OUTER + gap + 0.01, 0.0, 0.5 * (BACK + FRONT))
        else:
            centre = R * np.array([0.0, 0.0, 1.0]) + (R + SHELL + gap + 0.01) * geometry.unit(np.array([1.0, 0.0, -1.0]))
        rpy = (0.0, 0.0, 0.0) if isinstance(body, Annulus) else (0.0, 0.25 * np.pi, 0.0)   # its x along the normal
        got, true = check(local_box(centre, (0.01, 0.02, 0.005), rpy), body)
        assert true == pytest.approx(gap, abs=1e-7)


def test_a_box_flat_over_the_rings_front_and_under_the_domes_rim():
    """A flat box over the ring's front, wider than the ring (the contact a whole face): its gap;
    a box under the dome's rim plane across the rim: its gap."""
    for gap in (2e-5, 1e-4, 0.004):
        assert distance(local_box((0.003, -0.002, FRONT + gap + 0.005), (0.09, 0.09, 0.005)), ring()) \
            == pytest.approx(gap, abs=1e-12)
        assert distance(local_box((0.0, 0.0, R + gap + 0.005), (0.13, 0.13, 0.005)), dome()) \
            == pytest.approx(gap, abs=1e-12)
