"""The collision scene of a task (`cell.collision` keys, docs/formats.md) and the clearance of
the cell at one pose of the arm, camera and lamp.

Bodies: the part and the optional fixture (meshes, fixed in the cell), the UR5e's links
(capsules along its kinematic chain, placed by cell.devices.ur5e.forward), the camera body (a
box on the flange, centred `offset_m` along the tool axis, its axes the flange's), the lamp
body (a box behind the lamp's front at its position, its z axis the lamp's aim), the pan-tilt's
links that hold it (rig_links: the tilt servo's box behind the lamp, and where the task declares
the rig's reach the arm's tube from the lamp's back to the servo) and each fixed light's housing
(light_body: a ring's annulus round its hole, a dome's shell open at its hole, any other light's
box, each behind its emitting surface). Bodies that may
touch: neighbours on the arm's chain and the next but one (they share a joint housing), the
flange's two wrist links and the camera, the lamp and its links (each meets the next along the
lamp's axis), the robot base and the fixture it may stand on, the part and its fixture. The
clearance is the smallest distance over every other pair, found by
branch and bound on bounding spheres (the exact distance of a pair only where it could be the
smallest), so the result is the minimum, not an estimate of it. `Pairs` keeps each pair's lower
bound (the spheres' gap, or its distance once computed) for the paths' steps (cell.collision.paths).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from cell.collision import bulk
from cell.collision.bodies import (ROUNDING_M, SAMPLE_BOUND_M, Annulus, Body, Box, Capsule, Mesh, Shell, bracket,
                                  distance, surface_samples)
from cell.core import geometry
from cell.devices import ur5e
from cell.devices.rig import RIG_ARM_RADIUS_M, TILT_SERVO_SIZE_M, lamp_frame
from cell.task.types import HOUSING_RIM_M

if TYPE_CHECKING:
    from cell.core.frames import Frames
    from cell.task.types import Light, Task

# The UR5e's envelope (UR's published link dimensions, rounded up): its links as capsules between
# points of the DH chain, the upper arm offset 138 mm and the forearm 7 mm along the joint-2 axis
# from the DH line (the wrist reaches d4 = 133 mm), radii of the link tubes and joint housings.
SHOULDER_OFFSET_M, FOREARM_OFFSET_M = 0.138, 0.007
ARM_LINKS = (("base", 0.076), ("shoulder", 0.062), ("upper_arm", 0.056), ("elbow", 0.050),
             ("forearm", 0.042), ("wrist_1", 0.046), ("wrist_2", 0.046), ("wrist_3", 0.046))
CHAIN = tuple(name for name, _ in ARM_LINKS) + ("camera_body",)
# The lamp and the pan-tilt's links holding it (rig_links), in the order CollisionScene.bodies puts them,
# last; the arm only where the task declares the rig's reach (cell.collision.rig_reach_m).
JOINT_MOVE = "its joint move"            # the second of a Clearance's bodies where the arm cannot make a moveJ
LAMP_BODIES = ("lamp_body", "tilt_servo", "rig_arm")
MAY_TOUCH = frozenset({frozenset(CHAIN[i:i + 2]) for i in range(len(CHAIN) - 1)}
                      | {frozenset((CHAIN[i], CHAIN[i + 2])) for i in range(len(CHAIN) - 2)}
                      | {frozenset(pair) for pair in combinations(LAMP_BODIES, 2)}
                      | {frozenset(("base", "fixture")), frozenset(("part", "fixture"))})
# The last joint (1-6) that moves each body of the chain (arm_links' points: o1 = o0 + d1 z0 never moves,
# o4 = o3 + d4 z3 moves with joint 3, o5 = o4 + d5 z4 with 4, o6 = o5 + d6 z5 with 5, the camera body
# with the flange, 6); the fixed bodies and the lamp: 0, no joint of the arm moves them.
LINK = {"base": 0, "shoulder": 1, "upper_arm": 2, "elbow": 2, "forearm": 3, "wrist_1": 3, "wrist_2": 4,
        "wrist_3": 5, "camera_body": 6}


def arm_links(T_cell_base: np.ndarray, q: ArrayLike) -> tuple[Capsule, ...]:
    """The UR5e's links (Capsule per ARM_LINKS entry, cell frame) at joints q (6,) [rad]."""
    frames = ur5e.chain(T_cell_base, np.asarray(q, float))
    o, z1 = frames[:, :3, 3], frames[1, :3, 2]        # z1: joint 2's axis (2-4 parallel)
    points = [(o[0], o[1]), (o[1], o[1] + SHOULDER_OFFSET_M * z1),
              (o[1] + SHOULDER_OFFSET_M * z1, o[2] + SHOULDER_OFFSET_M * z1),
              (o[2] + SHOULDER_OFFSET_M * z1, o[2] + FOREARM_OFFSET_M * z1),
              (o[2] + FOREARM_OFFSET_M * z1, o[3] + FOREARM_OFFSET_M * z1),
              (o[3] + FOREARM_OFFSET_M * z1, o[4]), (o[4], o[5]), (o[5], o[6])]
    return tuple(Capsule(name, a, b, r) for (name, r), (a, b) in zip(ARM_LINKS, points))


def reaching_joints(frames: Frames, T_cell_cam: np.ndarray,
                    arm_joints: ArrayLike | None = None) -> tuple[float, ...] | None:
    """The UR5e's joints [rad] with the camera at T_cell_cam: arm_joints when the planner chose
    them, else the inverse kinematics nearest the home joints
    (ur5e.HOME_JOINTS); None where the arm does not reach."""
    if arm_joints is not None:
        return tuple(float(q) for q in np.asarray(arm_joints, float))
    try:
        q = ur5e.inverse(frames.T_base_flange(frames.T_base_cam(T_cell_cam)), ur5e.HOME_JOINTS)
    except ur5e.Unreachable:
        return None
    return tuple(float(x) for x in q)


def light_bodies(task: Task) -> tuple[Box | Annulus | Shell, ...]:
    """Each fixed light's housing (named as the light) as its collision body (light_body)."""
    return tuple(light_body(light) for light in task.lights if light.mount == "fixed")


def light_body(light: Light, setback_m: float = 0.0) -> Box | Annulus | Shell:
    """A fixed light's housing (Light.housing gives its sizes), from setback_m to its depth behind
    the emitting surface, in the light's frame (its `along`, across and axis, the emitting centre
    at 0): a ring's Annulus from aperture_radius_m (the hole the camera looks through) to
    outer_radius_m; a dome's Shell outside its emitting hemisphere (radius_m, its centre radius_m
    along the axis), open at its camera hole (hole_radius_m) and at its rim; any other light's
    Box: half its emitting surface's extent across the axis plus HOUSING_RIM_M (a bar's half
    length along and none across, a disk's radius, an area's half width and height, a spot's
    none). The shadows' housings (cell.planning.occluders) are these shapes. A flange light moves
    with the camera and is inside the camera body's reach (not a body)."""
    housing = light.housing()
    T = geometry.transform(np.column_stack([light.along, np.cross(light.axis, light.along), light.axis]),
                           light.position_m)
    if light.type == "ring":
        return Annulus(light.name, T, housing.aperture_radius_m, housing.outer_radius_m,
                       (-housing.depth_m, -setback_m))
    if light.type == "dome":
        radius = float(light.radius_m or 0.0)
        return Shell(light.name, T, radius, radius + setback_m, radius + housing.depth_m,
                     float(light.hole_radius_m or 0.0))
    if light.type == "bar":
        half = (0.5 * float(light.length_m or 0.0) + HOUSING_RIM_M, HOUSING_RIM_M)
    elif light.size_m is not None:
        half = (0.5 * float(light.size_m[0]) + HOUSING_RIM_M, 0.5 * float(light.size_m[1]) + HOUSING_RIM_M)
    else:
        half = (float(light.radius_m or 0.0) + HOUSING_RIM_M,) * 2
    centre = np.asarray(light.position_m, float) - 0.5 * (housing.depth_m + setback_m) * light.axis
    return Box(light.name, geometry.transform(T[:3, :3], centre), np.array([*half, 0.5 * (housing.depth_m - setback_m)]))


def camera_body(T_cell_flange: np.ndarray, half_m: ArrayLike, offset_m: float) -> Box:
    """The camera's box: its axes the flange's, its centre offset_m along the tool axis."""
    T = T_cell_flange @ geometry.transform(translation=(0.0, 0.0, offset_m))
    return Box("camera_body", T, np.asarray(half_m, float))


def lamp_boxes(pivot_m: ArrayLike, lamp_half_m: ArrayLike, lamp_position: ArrayLike,
               R: np.ndarray | None = None) -> np.ndarray:
    """(..., 4, 4) T_cell_box of the lamp's box at each position (..., 3): its front face centred
    at the lamp's position, its axes the lamp's (rig.lamp_frame, or R where given: z the aim at the
    pivot), so its centre lamp_half_m[2] behind the position along the aim."""
    p = np.asarray(lamp_position, float)
    R = lamp_frame(pivot_m, p) if R is None else R
    T = np.zeros((*p.shape[:-1], 4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, p - float(np.asarray(lamp_half_m)[2]) * R[..., 2], 1.0
    return T


def servo_front_m(radius_m: ArrayLike, lamp_depth_m: float, rig_reach_m: float | None) -> np.ndarray:
    """The tilt servo's front face's distance [m] from the pivot, on the lamp's axis behind it,
    with the lamp at radius_m: the rig's declared reach (cell.collision.rig_reach_m), or where
    none is declared the lamp housing's back, radius_m + its depth (a compact head riding with the
    lamp)."""
    radius = np.asarray(radius_m, float)
    return radius + lamp_depth_m if rig_reach_m is None else np.full(radius.shape, float(rig_reach_m))


@dataclass(frozen=True)
class RigLinks:
    """The pan-tilt's links at C lamp positions: the arm (capsules a-b, one radius; a body only
    where `arm`: the rig's reach declared) and the tilt servo (boxes: poses, one half size)."""

    a: np.ndarray                 # (C, 3) the lamp housing's back
    b: np.ndarray                 # (C, 3) the servo's front face (a, where no reach is declared)
    radius_m: float
    T_cell_servo: np.ndarray      # (C, 4, 4)
    servo_half_m: np.ndarray      # (3,)
    arm: bool                     # whether the arm is a body


def rig_links(pivot_m: ArrayLike, lamp_half_m: ArrayLike, rig_reach_m: float | None, lamp_position: ArrayLike,
              R: np.ndarray | None = None) -> RigLinks:
    """The pan-tilt's links with the lamp at each position (C, 3), all behind the lamp along its
    aim z (rig.lamp_frame, or R where given): the tilt servo, its axes the lamp's, its front face
    at servo_front_m from the pivot (the rig's declared reach, or the lamp box's back 2 h_z behind
    its front), and the arm from the lamp box's back out to that face (RIG_ARM_RADIUS_M; no
    length and no body where no reach is declared)."""
    p = np.asarray(lamp_position, float).reshape(-1, 3)
    pivot = np.asarray(pivot_m, float)
    depth = 2.0 * float(np.asarray(lamp_half_m)[2])
    servo_half = 0.5 * np.asarray(TILT_SERVO_SIZE_M)
    R = lamp_frame(pivot, p) if R is None else R
    aim = R[..., 2]
    front = servo_front_m(np.linalg.norm(p - pivot, axis=1), depth, rig_reach_m)
    T = np.zeros((len(p), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, pivot - (front + servo_half[2])[:, None] * aim, 1.0
    return RigLinks(p - depth * aim, pivot - front[:, None] * aim, RIG_ARM_RADIUS_M, T, servo_half,
                    rig_reach_m is not None)


@dataclass(frozen=True)
class Clearance:
    """The smallest distance [m] between two bodies that may not touch, and which two (names);
    `ok` when it is at least the padding."""

    distance_m: float
    bodies: tuple[str, str]
    padding_m: float
    where: str = ""                      # where on a path, e.g. "with the camera at [x, y, z] m"

    @property
    def ok(self) -> bool:
        return self.distance_m >= self.padding_m

    def reason(self) -> str:
        """The refusal's sentence: names both bodies (and where, on a path); a path the arm cannot
        follow (distance -inf, cell.collision.paths) says why instead, no body touching."""
        if self.distance_m == -np.inf:
            path = "the joint move" if self.bodies[1] == JOINT_MOVE else "the straight path"
            return f"the arm cannot follow {path} ({self.where})"
        a, b = self.bodies
        apart = "touch or overlap" if self.distance_m <= 0 else f"only {self.distance_m * 1e3:.1f} mm apart"
        at = f" {self.where}" if self.where else ""
        return f"collision: {a} and {b} {apart}{at}, less than the padding {self.padding_m * 1e3:g} mm"


@dataclass(frozen=True)
class CollisionScene:
    """What the clearance of a pose needs from the task: the fixed meshes, the two boxes' sizes
    and where they sit, the frames, the lamp rig's pivot, declared reach and tilt range and the
    padding."""

    padding_m: float
    fixed: tuple[Body, ...]                # the part first, the fixture, each fixed light's housing
    camera_half_m: np.ndarray
    camera_offset_m: float
    lamp_half_m: np.ndarray
    frames: Frames
    pivot_m: np.ndarray
    rig_reach_m: float | None              # the tilt servo's front from the pivot (rig_links; None: at the lamp)
    tilt_range_rad: tuple[float, float] = (0.0, 0.5 * np.pi)     # the rig's, for the lamp's via points

    @classmethod
    def of(cls, task: Task) -> CollisionScene:
        c = task.cell.collision
        part = _mesh("part", task.part.mesh, task.frames.T_cell_part)
        fixed = (part,) if c.fixture is None else (part, _mesh("fixture", c.fixture, np.eye(4)))
        fixed = (*fixed, *light_bodies(task))
        return cls(c.padding_m, fixed, 0.5 * np.asarray(c.camera_size_m), c.camera_offset_m,
                   0.5 * np.asarray(c.lamp_size_m), task.frames, task.lamp.rig.pivot_m,
                   c.rig_reach_m, task.lamp.rig.tilt_range_rad)

    @property
    def part(self) -> Mesh:
        """The part's body (the first of `fixed`)."""
        part = self.fixed[0]
        if not isinstance(part, Mesh):
            raise TypeError("the collision scene's first fixed body is the part's mesh")
        return part

    def camera_body(self, T_cell_flange: np.ndarray) -> Box:
        return camera_body(T_cell_flange, self.camera_half_m, self.camera_offset_m)

    def lamp_bodies(self, lamp_position: ArrayLike) -> tuple[Body, ...]:
        """The lamp's box (lamp_boxes) and the pan-tilt's links holding it (rig_links: the tilt
        servo's box, the arm's capsule where the rig's reach is declared), named as LAMP_BODIES."""
        p = np.asarray(lamp_position, float)
        R = lamp_frame(self.pivot_m, p)
        links = rig_links(self.pivot_m, self.lamp_half_m, self.rig_reach_m, p, R[None])
        lamp = Box(LAMP_BODIES[0], lamp_boxes(self.pivot_m, self.lamp_half_m, p, R), self.lamp_half_m)
        servo = Box(LAMP_BODIES[1], links.T_cell_servo[0], links.servo_half_m)
        return (lamp, servo, Capsule(LAMP_BODIES[2], links.a[0], links.b[0], links.radius_m)) if links.arm \
            else (lamp, servo)

    def lamp_reach(self, radius_m: float) -> np.ndarray:
        """(3,) the farthest point [m] from the pivot of each of LAMP_BODIES with the lamp at
        radius_m or nearer: the box's back corners within radius_m + 2 |h|; with the servo's front
        face at f (servo_front_m), its corners within f + its half depth + its half diagonal, the
        arm (which ends at that face) within f + its radius. A turn of the rig by (dpan, dtilt)
        moves a point at rho from the pivot by at most (|dpan| + |dtilt|) rho."""
        servo_half = 0.5 * np.asarray(TILT_SERVO_SIZE_M)
        front = float(servo_front_m(radius_m, 2.0 * float(self.lamp_half_m[2]), self.rig_reach_m))
        return np.array([radius_m + 2.0 * float(np.linalg.norm(self.lamp_half_m)),
                         front + float(servo_half[2] + np.linalg.norm(servo_half)), front + RIG_ARM_RADIUS_M])

    def bodies(self, T_cell_cam: np.ndarray, arm_joints: ArrayLike | None = None,
               lamp_position: ArrayLike | None = None) -> tuple[Body, ...]:
        """Every body with the camera at T_cell_cam, the arm's links where joints put them (None:
        no arm, e.g. a pose it does not reach) and the lamp with its links, last (lamp_bodies;
        None: not placed yet)."""
        moving: list[Body] = [self.camera_body(self.frames.T_cell_flange(T_cell_cam))]
        if arm_joints is not None:
            moving += arm_links(self.frames.T_cell_base, arm_joints)
        if lamp_position is not None:
            moving += self.lamp_bodies(lamp_position)
        return (*self.fixed, *moving)

    def clearance(self, T_cell_cam: np.ndarray, arm_joints: ArrayLike | None = None,
                  lamp_position: ArrayLike | None = None) -> Clearance:
        """The Clearance of the cell at this pose (see `bodies`); two fixed bodies (the part, the
        fixture, the fixed lights) are not a pair: neither moves, so no pose changes their distance."""
        return clearance(self.bodies(T_cell_cam, arm_joints, lamp_position), self.padding_m, len(self.fixed))

    def clear(self, T_cell_cam: np.ndarray, arm_joints: ArrayLike | None = None,
              lamp_position: ArrayLike | None = None) -> bool:
        """Whether every pair at this pose (see `clearance`) is at least the padding apart
        (Pairs.clear: the question without the least distance's value)."""
        return Pairs.of(self.bodies(T_cell_cam, arm_joints, lamp_position), len(self.fixed)).clear(self.padding_m)

    def lamp_clear(self, T_cell_cam: np.ndarray, arm_joints: ArrayLike | None,
                   lamp_positions: ArrayLike) -> np.ndarray:
        """(K,) whether the lamp at each of K positions (K, 3) keeps the padding from every body
        it may not touch, the camera at T_cell_cam and the arm at arm_joints (lamp_check)."""
        return self.lamp_check(T_cell_cam, arm_joints)(lamp_positions)

    def lamp_check(self, T_cell_cam: np.ndarray, arm_joints: ArrayLike | None) -> Callable[[ArrayLike], np.ndarray]:
        """lamp_clear with the camera at T_cell_cam and the arm at arm_joints, those bodies placed
        once: a function of the lamp's positions (K, 3). Only the lamp's pairs (every other body
        counted as fixed), so a pose of the arm that itself collides leaves the lamp's answer
        alone (`clearance` names that). Each pair of a lamp's body (lamp_bodies: its box, the
        pan-tilt's links) and another is bounded at all K positions at once (cell.collision.bulk:
        `bounds` where the cheaper Fixed.gaps do not keep the padding): a position whose every pair's
        lower bound keeps the padding is clear, one with a pair's upper bound under it is not,
        and only the others are asked pair by pair (Pairs.clear), so the answer is every pair's
        bodies.distance against the padding."""
        others = self.bodies(T_cell_cam, arm_joints)
        fixed = bulk.Fixed.of(others)

        def clear(lamp_positions: ArrayLike) -> np.ndarray:
            p = np.asarray(lamp_positions, float).reshape(-1, 3)
            R = lamp_frame(self.pivot_m, p)
            links = rig_links(self.pivot_m, self.lamp_half_m, self.rig_reach_m, p, R)
            moving: list[bulk.Moving] = [
                bulk.Boxes(LAMP_BODIES[0], lamp_boxes(self.pivot_m, self.lamp_half_m, p, R), self.lamp_half_m),
                bulk.Boxes(LAMP_BODIES[1], links.T_cell_servo, links.servo_half_m)]
            if links.arm:
                moving.append(bulk.Capsules(LAMP_BODIES[2], links.a, links.b, links.radius_m))
            lower, upper = np.full(len(p), np.inf), np.full(len(p), np.inf)
            for body in moving:
                near = fixed.gaps(body) - SAMPLE_BOUND_M < self.padding_m + ROUNDING_M        # (K, N)
                for n in np.flatnonzero(near.any(axis=0)):
                    at = np.flatnonzero(near[:, n])
                    low, up = bulk.bounds(others[n], body.take(at), self.padding_m)
                    lower[at], upper[at] = np.minimum(lower[at], low), np.minimum(upper[at], up)
            out = lower >= self.padding_m + ROUNDING_M
            for k in np.flatnonzero(~out & (upper >= self.padding_m - ROUNDING_M)):
                out[k] = Pairs.of((*others, *self.lamp_bodies(p[k])), len(others)).clear(self.padding_m)
            return out
        return clear


def clearance(bodies: tuple[Body, ...], padding_m: float, fixed: int = 0) -> Clearance:
    """The smallest distance over the pairs that may not touch (MAY_TOUCH) and are not both among
    the first `fixed` bodies (those that do not move), exactly as bodies.distance gives it
    (Pairs.least)."""
    return Pairs.of(bodies, fixed).least(padding_m)


@dataclass
class Pairs:
    """The pairs of one pose's bodies that may not touch and are not both fixed (body indices i,
    j), their bounding spheres' gaps (bodies.lower_bound) and `bound`, a lower bound of each
    pair's distance: its gap, raised to bodies.distance where `exact` has computed that (both
    lower bounds of the true distance, so their larger one is too)."""

    bodies: tuple[Body, ...]
    i: np.ndarray
    j: np.ndarray
    gap: np.ndarray
    bound: np.ndarray
    distances: np.ndarray                # each pair's bodies.distance where computed, NaN elsewhere

    @classmethod
    def of(cls, bodies: tuple[Body, ...], fixed: int = 0) -> Pairs:
        i, j = _pair_indices(tuple(body.name for body in bodies), fixed)
        centers = np.array([body.center for body in bodies])
        radii = np.array([body.radius for body in bodies])
        gap = np.linalg.norm(centers[i] - centers[j], axis=1) - radii[i] - radii[j]   # bodies.lower_bound
        return cls(bodies, i, j, gap, gap.copy(), np.full(len(gap), np.nan))

    def exact(self, k: int) -> float:
        """Pair k's distance (bodies.distance), computed once; its bound raised to it."""
        if np.isnan(self.distances[k]):
            self.distances[k] = distance(self.bodies[self.i[k]], self.bodies[self.j[k]])
            self.bound[k] = max(self.gap[k], self.distances[k])
        return float(self.distances[k])

    def least(self, padding_m: float, among: np.ndarray | None = None) -> Clearance:
        """The Clearance over all pairs (or those `among` selects): pairs in order of their gap,
        stopping at the first gap no smaller than the least distance found (no pair after it can
        be nearer)."""
        best, names = np.inf, ("", "")
        for k in np.argsort(self.gap, kind="stable"):
            if among is not None and not among[k]:
                continue
            if self.gap[k] >= best:
                break
            d = self.exact(int(k))
            if d < best:
                best, names = d, (self.bodies[self.i[k]].name, self.bodies[self.j[k]].name)
        return Clearance(float(best), names, padding_m)


    def clear(self, padding_m: float) -> bool:
        """Every pair at least padding_m apart (each bodies.distance, the answer the same): the
        pairs whose gap is below it in order of gap, stopping at the first whose distance is
        below it; a pair whose bounding spheres are the padding apart is (its true distance is no
        less), so none after them needs its distance, nor does a pair whose cheaper bounds
        (bodies.bracket) lie on one side of the padding by more than their rounding."""
        for k in np.argsort(self.gap, kind="stable"):
            if self.gap[k] >= padding_m:
                return True
            lower, upper = bracket(self.bodies[self.i[k]], self.bodies[self.j[k]])
            if lower >= padding_m + ROUNDING_M:
                continue
            if upper < padding_m - ROUNDING_M or self.exact(int(k)) < padding_m:
                return False
        return True


@lru_cache(maxsize=64)
def _pair_indices(names: tuple[str, ...], fixed: int) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) of the pairs of bodies so named that may not touch (MAY_TOUCH) and are not both
    among the first `fixed`."""
    pairs = [(i, j) for i, j in combinations(range(len(names)), 2)
             if frozenset((names[i], names[j])) not in MAY_TOUCH and j >= fixed]
    i, j = np.array(pairs, int).reshape(-1, 2).T.copy()
    i.setflags(write=False)
    j.setflags(write=False)
    return i, j


@lru_cache(maxsize=16)
def _cached_mesh(name: str, vertices: bytes, faces: bytes) -> Mesh:
    v = np.frombuffer(vertices).reshape(-1, 3)
    f = np.frombuffer(faces, dtype=np.int64).reshape(-1, 3)
    return Mesh(name, v, f, surface_samples(v, f))


def _mesh(name: str, mesh: trimesh.Trimesh, T_cell_mesh: np.ndarray) -> Mesh:
    """The mesh in the cell frame with its samples, made once per geometry and pose in a process
    (each feature's task of a part shares them)."""
    v = np.ascontiguousarray(geometry.apply(T_cell_mesh, mesh.vertices), float)
    f = np.ascontiguousarray(mesh.faces, np.int64)
    return _cached_mesh(name, v.tobytes(), f.tobytes())
