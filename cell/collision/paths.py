"""The moves between two stops (the arm's home pose, the shots) checked along their paths, via
points around a collision, and the order of a route whose moves are all checked.

The arm moves first, the lamp parked at the first stop's pose (cell.run.acquisition.move_to), by
moveL: the camera's position on a straight line and its orientation by slerp, the joints by the
inverse kinematics nearest the last step's (as the controller follows a Cartesian path), ending
on the branch the second stop was planned on. Then the lamp moves in its joints (pan, tilt,
radius linear together), the arm at the second stop.
Steps by conservative advancement, pair by pair: a bound on how far one body of a pair travels
relative to the other in a step (on the arm, the body further down the chain seen from the
other's link: sum_i |dq_i| r_i over the joints between them, r_i its reach about joint i's axis,
`body_reach`; the camera body against the still bodies also by its moveL's own travel; the lamp
and each of the pan-tilt's links holding it against the still rest by (|dpan| + |dtilt|) rho +
|dr|, rho its farthest point from the pivot) is kept at most max(padding / 2, L - padding) after
a pose where the pair is at least L apart: between two checked poses every pair stays at least
the padding apart, or (near it) the step bounds its swept distance below half the padding. A
pair far apart (a bounding-sphere gap
well above the padding) or that the step's joints do not move between (the camera and the
wrist as the base turns) does not shorten the step. A direct move closer than
the padding gets via points: back along the camera's axis from the first stop, across at that
standoff, in along the second's axis; retreats of VIA_RETREATS_M are tried in turn. A lamp move
closer than the padding gets via joints (`lamp_route`): up or down to another tilt, across in pan
at it, to the target's tilt, the radius the larger of the two ends'. Where no moveL is clear
(a straight path through a singularity or a change of the arm's configuration), the arm moves by
moveJ (`joint_path`: the joints linear to the second stop's, stepped as a moveL's by the joints'
sweep), directly or across between the via points. `plan_transition` is the move from where the
devices read back to a target of the arm, the lamp or both (cell.run.motion).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from cell.collision.bodies import Body, Box, Capsule
from cell.collision.scene import JOINT_MOVE, LAMP_BODIES, LINK, Clearance, CollisionScene, Pairs
from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.devices import ur5e
from cell.devices.interfaces import check_arm_motion, check_joint_motion, joint_commands, line_commands
from cell.devices.rig import lamp_position

if TYPE_CHECKING:
    from cell.task.device_config import ArmConfig

HOME = "home"                            # a move's end that is the arm's home pose, not a shot
VIA_RETREATS_M = (0.10, 0.20, 0.30)      # back along the camera's axis, tried in turn
MIN_STEP_M = 0.001                       # a padding of 0 still checks every millimetre
LAMP_VIA_TILTS = 7                       # tilts across the rig's range tried for the lamp's via joints
MAX_STEPS = 5000                         # a longer path is refused, not checked for minutes
MAX_JOINT_STEP_RAD = 0.2                 # more in one step of a straight path: it meets a singularity
MIN_STEP_S = 1e-6                        # a step of the path parameter below this: a singularity
SAME_BRANCH_RAD = 1e-3                   # joints arriving this close to the stop's planned ones
CORNERS = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3)).T.reshape(-1, 3)   # a box's, in half sizes
JOINT_ARC_RAD = 0.05                     # a moveJ's corners: the camera every this much of the leading joint's turn
UNCHECKED_M = 1e6                        # the travel a route solver sees of a move that cannot be made

End = int | str                          # a shot's index in the plan, or HOME


@dataclass(frozen=True)
class Move:
    """A move from `start` to `end` (shot indices, or HOME): the smallest clearance along its
    path (via points included), the via camera poses T_cell_cam (empty: direct) and the lamp's
    via joints (pan, tilt, radius; empty: direct), the camera's
    corners in the cell frame [m] (start, via points, end: its path is straight between them;
    along a leg the arm makes by moveJ, `joint_legs`, its joints linear to the leg's end's,
    `via_joints` or `joints_end`, points along the camera's arc), its travel (the camera's path
    plus the lamp's straight line) [m], the poses checked and the time the arm's commands take
    (`duration_s`, arm_duration_s); `clear` when that clearance is at least the padding."""

    start: End
    end: End
    clearance: Clearance
    via: tuple[np.ndarray, ...] = ()
    steps: int = 0
    corners_m: tuple[np.ndarray, ...] = ()
    travel_m: float = np.inf
    joints_end: np.ndarray | None = None   # where the arm arrives (None: it does not)
    lamp_via: tuple[tuple[float, float, float], ...] = ()   # the lamp's via joints (empty: direct)
    lamp_first: bool = False               # the lamp moves before the arm (cell.run.motion's moves only)
    joint_legs: tuple[int, ...] = ()       # the legs made by moveJ (0: from the start to the first via or the end)
    via_joints: tuple[np.ndarray, ...] = ()   # the arm's joints at each via point, where a leg is a moveJ
    duration_s: float = np.inf             # the arm's commands along it (inf: not made)

    @property
    def clear(self) -> bool:
        return self.clearance.ok

    def reason(self) -> str:
        return f"the move from {_name(self.start)} to {_name(self.end)}: {self.clearance.reason()}"

    def to_json(self) -> dict[str, object]:
        return {"from": self.start, "to": self.end, "clearance_m": self.clearance.distance_m,
                "clearance_bodies": list(self.clearance.bodies), "via": [T.tolist() for T in self.via],
                "travel_m": self.travel_m, "steps": self.steps,
                **({"duration_s": self.duration_s} if np.isfinite(self.duration_s) else {}),
                **({} if self.joints_end is None else {"arm_joints_deg": np.degrees(self.joints_end).tolist()}),
                **({"lamp_via": [list(j) for j in self.lamp_via]} if self.lamp_via else {}),
                **({"lamp_first": True} if self.lamp_first else {}),
                **({"joint_legs": list(self.joint_legs),
                    "via_arm_joints_deg": [np.degrees(q).tolist() for q in self.via_joints]}
                   if self.joint_legs else {})}


def _name(end: End) -> str:
    return "the home pose" if end == HOME else f"shot {end}" if isinstance(end, int) else str(end)


def _least(clearances: list[Clearance], padding_m: float) -> Clearance:
    return min(clearances, key=lambda c: c.distance_m, default=Clearance(np.inf, ("", ""), padding_m))


def _allowed(scene: CollisionScene, c: Clearance) -> float:
    """How far a point of one moving body may move in the next step after a pose where its
    pairs' clearance is c (the lamp against the still rest)."""
    return max(0.5 * scene.padding_m, MIN_STEP_M, c.distance_m - scene.padding_m)


def body_reach(scene: CollisionScene, bodies: tuple[Body, ...], q: ArrayLike) -> np.ndarray:
    """(bodies, 6) r_bi [m] at joints q: how far from joint i's axis the farthest point of body b
    lies, for the joints that move it (i < LINK of its name; 0 for the others and for bodies no
    joint moves): a capsule's farther end plus its radius (the distance from a line is convex
    along a segment, so an end is the farthest), a box's farthest corner."""
    frames = ur5e.chain(scene.frames.T_cell_base, np.asarray(q, float))
    origins, axes = frames[:6, :3, 3], frames[:6, :3, 2]
    reach = np.zeros((len(bodies), 6))
    for b, body in enumerate(bodies):
        link = LINK.get(body.name, 0)
        if isinstance(body, Capsule) and link:
            points, thick = np.array([body.a, body.b]), body.radius_m
        elif isinstance(body, Box) and link:
            points, thick = geometry.apply(body.T_cell_box, CORNERS * body.half_m), 0.0
        else:                                   # the part, the fixture, the lights, the lamp
            continue
        rel = points[None] - origins[:link, None]                         # (link, points, 3)
        across = rel - np.einsum("ipk,ik->ip", rel, axes[:link])[..., None] * axes[:link, None]
        reach[b, :link] = np.linalg.norm(across, axis=2).max(axis=1) + thick
    return reach


@lru_cache(maxsize=64)
def _moved_by(names: tuple[str, ...], i: bytes, j: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(the pairs' mover: the body of each pair further down the chain, (pairs, 6) the joints
    that move it relative to the other: those between the two bodies' LINKs, the pairs of the
    camera body and a body no joint moves). Joints nearer the base move both together and
    change no distance between them."""
    a, b = np.frombuffer(i, int), np.frombuffer(j, int)
    link = np.array([LINK.get(name, 0) for name in names])
    mover = np.where(link[a] >= link[b], a, b)
    lo, hi = np.minimum(link[a], link[b]), np.maximum(link[a], link[b])
    joints = (np.arange(6) >= lo[:, None]) & (np.arange(6) < hi[:, None])
    camera = (hi == LINK["camera_body"]) & (lo == 0)
    for out in (mover, joints, camera):
        out.setflags(write=False)
    return mover, joints, camera


def arm_path(scene: CollisionScene, T_from: np.ndarray, q_from: ArrayLike, T_to: np.ndarray,
             lamp: ArrayLike | None) -> tuple[Clearance, np.ndarray, int]:
    """(the smallest Clearance along the moveL from T_from (joints q_from) to T_to, or the first
    below the padding, the joints it ends at, the poses checked); raises ur5e.Unreachable where
    the inverse kinematics fail or jump (a singularity, a change of configuration).
    Steps per pair of bodies: in the frame of the pair's body nearer the base, its other body
    moves by the joints between them (`_moved_by`), its points at most
    sweep = sum_i |dq_i| (r_i + allowed) (r_i its reach about joint i's axis, body_reach, at the
    farther of the step's two ends, widened by the step allowed: no point moves farther out
    than that within the step), kept at most allowed = max(padding / 2, L - padding) after a
    pose where L is a lower bound of the pair's distance (Pairs.bound: the bounding spheres' gap,
    or the distance where that gap allows too short a step): between two checked poses the
    pair stays at least the padding apart, or (near it) the step bounds its swept distance
    below half the padding. The camera body against a body no joint moves: the lesser of that
    and its own path's bound, ds (|p_to - p_from| + angle rho) (geometry.line_path: the moveL's
    position linear in s, its orientation turning angle ds about one axis, rho the body's farthest
    corner from the camera's origin)."""
    pose, angle = geometry.line_path(T_from, T_to)

    def at(s: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return pose(s), ur5e.inverse(scene.frames.T_base_flange(scene.frames.T_base_cam(pose(s))), q)

    box = scene.camera_body(scene.frames.T_cell_flange(T_from))
    rho = float(np.linalg.norm(geometry.apply(box.T_cell_box, CORNERS * box.half_m) - T_from[:3, 3], axis=1).max())
    rate = float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3])) + angle * rho      # the camera body's travel per unit s
    return _advance(scene, T_from, np.asarray(q_from, float), lamp, at, rate, "the straight path")


def joint_path(scene: CollisionScene, q_from: ArrayLike, q_to: ArrayLike,
               lamp: ArrayLike | None) -> tuple[Clearance, np.ndarray, int]:
    """(the smallest Clearance along the moveJ from joints q_from to q_to, or the first below the
    padding, the joints it ends at (q_to), the poses checked): the joints linear in s,
    q(s) = q_from + s (q_to - q_from), as a UR controller's moveJ interpolates them (every joint
    starts and stops together), the camera where the forward kinematics put it. Steps as
    arm_path's (conservative advancement per pair of bodies, sweep = sum_i |dq_i| (r_i + allowed)),
    with no bound of the camera's own path: it follows no line."""
    a, b = np.asarray(q_from, float), np.asarray(q_to, float)

    def at(s: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = a + s * (b - a)
        return _camera(scene, q), q

    return _advance(scene, _camera(scene, a), a, lamp, at, np.inf, "the joint move")


def joint_leg(scene: CollisionScene, arm: ArmConfig, q_from: ArrayLike, q_to: ArrayLike,
              lamp: ArrayLike | None) -> tuple[Clearance, np.ndarray, int]:
    """joint_path's (Clearance, joints at the end, poses checked) of the moveJ from q_from to
    q_to, its envelope first (check_joint_motion): where the arm cannot make it, Clearance -inf
    with the arm and JOINT_MOVE named and why, the joints where they were, none checked."""
    try:
        check_joint_motion(arm, scene.frames, q_from, q_to)
        return joint_path(scene, q_from, q_to, lamp)
    except (ur5e.Unreachable, DeviceFault) as err:
        why = err.reason if isinstance(err, DeviceFault) else str(err)
        return Clearance(-np.inf, ("arm", JOINT_MOVE), scene.padding_m, why), np.asarray(q_from, float), 0


def _advance(scene: CollisionScene, T_from: np.ndarray, q_from: np.ndarray, lamp: ArrayLike | None,
             at: Callable[[float, np.ndarray], tuple[np.ndarray, np.ndarray]], rate: float,
             path: str) -> tuple[Clearance, np.ndarray, int]:
    """The conservative advancement of arm_path and joint_path along a path whose pose and
    joints at s in [0, 1] are at(s, the last step's joints); `rate` bounds the camera body's
    travel per unit s against the bodies no joint moves (inf: no bound but the joints'). Returns
    (the smallest Clearance, or the first below the padding, where the camera was; the joints at
    its end; the poses checked)."""
    s, q = 0.0, q_from
    bodies = scene.bodies(T_from, q, lamp)
    pairs, reach = Pairs.of(bodies, len(scene.fixed)), body_reach(scene, bodies, q)
    mover, joints, camera = _moved_by(tuple(body.name for body in bodies), pairs.i.tobytes(), pairs.j.tobytes())
    least = max(0.5 * scene.padding_m, MIN_STEP_M)
    found, where = [pairs.least(scene.padding_m)], [T_from[:3, 3]]
    ds = 1.0
    while s < 1.0 and found[-1].ok:
        while True:
            s_next = min(1.0, s + ds)
            T_next, q_next = at(s_next, q)
            dq = np.abs(q_next - q)
            bodies_next = scene.bodies(T_next, q_next, lamp)
            reach_next = body_reach(scene, bodies_next, q_next)
            r = np.maximum(reach, reach_next)[mover]
            ratio = _worst(pairs, r, joints, dq, np.where(camera, rate * (s_next - s), np.inf), least,
                           scene.padding_m)
            if ratio <= 1.0 and dq.max() <= MAX_JOINT_STEP_RAD:
                break
            ds = (s_next - s) * 0.9 * min(1.0 / max(ratio, 1e-300), MAX_JOINT_STEP_RAD / max(dq.max(), 1e-300))
            if ds < MIN_STEP_S:
                raise ur5e.Unreachable(f"{path} turns a joint {np.degrees(dq.max()):.0f} deg in a "
                                       "vanishing step: a singularity or a change of configuration on the way")
        s, q, reach = s_next, q_next, reach_next
        pairs = Pairs.of(bodies_next, len(scene.fixed))
        found.append(pairs.least(scene.padding_m))
        where.append(T_next[:3, 3])
        if len(found) > MAX_STEPS:
            raise ur5e.Unreachable(f"a path of more than {MAX_STEPS} checked poses")
        ds *= 2.0
    k = int(np.argmin([c.distance_m for c in found]))
    return replace(found[k], where=f"with the camera at {np.round(where[k], 3).tolist()} m (cell frame)"), q, len(found)


def _worst(pairs: Pairs, reach: np.ndarray, joints: np.ndarray, dq: np.ndarray, path: np.ndarray,
           least: float, padding_m: float) -> float:
    """The largest sweep / allowed over the pairs (arm_path) for joint steps dq, each pair's
    sweep at most `path` (the camera body's own path bound; inf for the others); a pair over 1
    on its spheres' gap gets its distance (Pairs.exact) first."""
    def ratios() -> np.ndarray:
        allowed = np.maximum(least, pairs.bound - padding_m)
        sweep = np.einsum("pi,pi,i->p", reach + allowed[:, None], joints, dq)
        return np.minimum(sweep, path) / allowed

    found = ratios()
    over = np.flatnonzero((found > 1.0) & np.isnan(pairs.distances))
    for k in over:
        pairs.exact(int(k))
    if len(over):
        found = ratios()
    return float(found.max(initial=0.0))


def lamp_path(scene: CollisionScene, T_cam: np.ndarray, q: ArrayLike, joints_from: ArrayLike,
              joints_to: ArrayLike) -> tuple[Clearance, int]:
    """The smallest Clearance (or the first below the padding) as the lamp moves in its joints
    (pan, tilt, radius), the arm still, and the poses checked. Each step by the least over the
    lamp and the links holding it (CollisionScene.lamp_bodies) of its pairs' clearance (_allowed)
    over its travel in the whole move, (|dpan| + |dtilt|) rho + |dradius| (rho its farthest point
    from the pivot, CollisionScene.lamp_reach; a change of radius moves each of its points at most
    that far along the aim): no other pair's distance changes."""
    a, b = np.asarray(joints_from, float), np.asarray(joints_to, float)
    reach = scene.lamp_reach(max(a[2], b[2]))
    turn, out = abs(b[0] - a[0]) + abs(b[1] - a[1]), abs(b[2] - a[2])    # a bound over the whole move
    s, at, found = 0.0, [lamp_position(scene.pivot_m, *a)], []
    while True:
        bodies = scene.bodies(T_cam, q, at[-1])
        pairs = Pairs.of(bodies, len(scene.fixed))
        found.append(pairs.least(scene.padding_m))
        if s >= 1.0 or not found[-1].ok:
            break
        step = min(_allowed(scene, pairs.least(scene.padding_m, (pairs.i == k) | (pairs.j == k)))
                   / max(turn * reach[LAMP_BODIES.index(body.name)] + out, 1e-300)
                   for k, body in enumerate(bodies) if body.name in LAMP_BODIES)
        s = min(1.0, s + step)
        at.append(lamp_position(scene.pivot_m, *((1 - s) * a + s * b)))
    k = int(np.argmin([c.distance_m for c in found]))
    return replace(found[k], where=f"with the lamp at {np.round(at[k], 3).tolist()} m (cell frame)"), len(found)


def lamp_route(scene: CollisionScene, T_cam: np.ndarray, q: ArrayLike, joints_from: ArrayLike,
               joints_to: ArrayLike) -> tuple[Clearance, tuple[tuple[float, float, float], ...], int]:
    """(the smallest Clearance along the lamp's route, its via joints, the poses checked): the
    direct joint move (lamp_path) if clear; else through via joints at another tilt: the lamp to
    it at its pan, across in pan at it, down or up to the target's, the radius the larger end's;
    the rig's tilt range in LAMP_VIA_TILTS steps, the nearest to the two ends' first. Neither:
    the direct move's Clearance, not clear, no via joints."""
    a = tuple(float(x) for x in np.asarray(joints_from, float))
    b = tuple(float(x) for x in np.asarray(joints_to, float))
    direct, steps = lamp_path(scene, T_cam, q, a, b)
    if direct.ok:
        return direct, (), steps
    lo, hi = scene.tilt_range_rad
    middle, radius = 0.5 * (a[1] + b[1]), max(a[2], b[2])
    for tilt in sorted(np.linspace(lo, hi, LAMP_VIA_TILTS), key=lambda t: abs(t - middle)):
        via = ((a[0], float(tilt), radius), (b[0], float(tilt), radius))
        found = []
        for j_from, j_to in pairwise((a, *via, b)):
            c, n = lamp_path(scene, T_cam, q, j_from, j_to)
            steps += n
            found.append(c)
            if not c.ok:
                break
        if found[-1].ok and len(found) == 3:
            return _least(found, scene.padding_m), via, steps
    return direct, (), steps


@dataclass(frozen=True)
class Stop:
    """What a move needs of a stop: the camera pose, the arm's joints there (a move's first
    stop: where it starts; its second: as planned, the move arrives where the path leads), the
    lamp's joints (None: not known, e.g. at the home pose before the run reads it)."""

    T_cell_cam: np.ndarray
    arm_joints: np.ndarray
    lamp_joints: tuple[float, float, float] | None


def plan_move(scene: CollisionScene, arm: ArmConfig, start: End, a: Stop, end: End, b: Stop,
              retreats: Sequence[float] = VIA_RETREATS_M, joint: bool = False) -> Move:
    """The Move from stop a to stop b: direct if clear, else through the first via points
    (`retreats`) whose path is clear; neither: the direct move, not clear, with its bodies.
    By moveL, or with `joint` by moveJ where the arm changes configuration: the direct move a
    moveJ to b's joints (the solution of b's pose nearest b.arm_joints), the via points' crossing
    a moveJ to the retreated pose's solution nearest those, their retreat and approach moveLs."""
    lamp_a = None if a.lamp_joints is None else lamp_position(scene.pivot_m, *a.lamp_joints)
    q_b = None
    if joint:
        try:
            q_b = _joints_at(scene, b.T_cell_cam, b.arm_joints)
        except ur5e.Unreachable as err:
            return Move(start, end, Clearance(-np.inf, ("arm", "its reach"), scene.padding_m, str(err)), (), 0,
                        (a.T_cell_cam[:3, 3], b.T_cell_cam[:3, 3]))
    direct, q, steps, _ = _through(scene, arm, [a.T_cell_cam, b.T_cell_cam], a.arm_joints, lamp_a,
                                   None if q_b is None else [q_b])
    if direct.ok:
        return _with_lamp(scene, arm, Move(start, end, direct, (), steps, joints_end=q,
                                           joint_legs=() if q_b is None else (0,)), a, b)
    for retreat in retreats:
        via = (_retreated(a.T_cell_cam, retreat), _retreated(b.T_cell_cam, retreat))
        try:
            for T in via:
                check_arm_motion(arm, scene.frames, T, arm.speed_m_s)
            targets = None if q_b is None else [None, _joints_at(scene, via[1], q_b), None]
        except (DeviceFault, ur5e.Unreachable):
            continue
        found, q, n, reached = _through(scene, arm, [a.T_cell_cam, *via, b.T_cell_cam], a.arm_joints, lamp_a, targets)
        steps += n
        if found.ok:
            legs, at = ((), ()) if q_b is None else ((1,), tuple(reached[:2]))
            return _with_lamp(scene, arm, Move(start, end, found, via, steps, joints_end=q, joint_legs=legs,
                                               via_joints=at), a, b)
    return Move(start, end, direct, (), steps, (a.T_cell_cam[:3, 3], b.T_cell_cam[:3, 3]))


def _joints_at(scene: CollisionScene, T_cell_cam: np.ndarray, q_near: ArrayLike) -> np.ndarray:
    """The arm's joints with the camera at T_cell_cam nearest q_near (ur5e.inverse; raises
    ur5e.Unreachable)."""
    return ur5e.inverse(scene.frames.T_base_flange(scene.frames.T_base_cam(T_cell_cam)), q_near)


def plan_transition(scene: CollisionScene, arm: ArmConfig, a: Stop, b: Stop, start: End = "start",
                    end: End = "the target") -> Move:
    """The Move from where the devices are (a: read back) to b: the arm's path and then the
    lamp's route (plan_move), or where that is not clear the lamp's route first and then the
    arm's path (`lamp_first`: the lamp out of the camera's way), each direct before either
    tries via points; all by moveL, and where none of those is clear, the same by moveJ
    (plan_move's `joint`: a change of the arm's configuration no straight path makes); or, the
    camera staying where it is (b at a's pose), the lamp's route alone (lamp_route, the arm
    still at a's joints); b's lamp joints None: the arm moves, the lamp stays (and is checked
    where it stands). None clear: the arm-first moveL, not clear, or the arm-first moveJ's
    collision where the arm cannot follow the straight path."""
    same = (np.allclose(a.T_cell_cam[:3, 3], b.T_cell_cam[:3, 3], atol=1e-9)
            and np.allclose(a.T_cell_cam[:3, :3], b.T_cell_cam[:3, :3], atol=1e-9))
    if not same:
        line = _arm_transition(scene, arm, start, a, end, b, joint=False)
        if line.clear:
            return line
        joint = _arm_transition(scene, arm, start, a, end, b, joint=True)
        if joint.clear or (line.clearance.distance_m == -np.inf and joint.clearance.distance_m > -np.inf):
            return joint
        return line
    if b.lamp_joints is None or a.lamp_joints is None:
        lamp_at = None if a.lamp_joints is None else lamp_position(scene.pivot_m, *a.lamp_joints)
        return Move(start, end, scene.clearance(a.T_cell_cam, a.arm_joints, lamp_at), (), 1,
                    (a.T_cell_cam[:3, 3],), 0.0, np.asarray(a.arm_joints, float), duration_s=0.0)
    found, lamp_via, steps = lamp_route(scene, a.T_cell_cam, a.arm_joints, a.lamp_joints, b.lamp_joints)
    at = [lamp_position(scene.pivot_m, *j) for j in (a.lamp_joints, *lamp_via, b.lamp_joints)]
    return Move(start, end, found, (), steps, (a.T_cell_cam[:3, 3],),
                float(sum(np.linalg.norm(y - x) for x, y in pairwise(at))), np.asarray(a.arm_joints, float),
                lamp_via if found.ok else (), duration_s=0.0)


def _arm_transition(scene: CollisionScene, arm: ArmConfig, start: End, a: Stop, end: End, b: Stop,
                    joint: bool) -> Move:
    """plan_transition's moves of the arm (by moveJ with `joint`): the arm first, direct; the
    lamp first, direct; the arm first through via points; the lamp first through via points;
    the first clear, else the arm-first move, not clear."""
    first = plan_move(scene, arm, start, a, end, b, retreats=(), joint=joint)
    both = a.lamp_joints is not None and b.lamp_joints is not None
    if first.clear:
        return first
    lamp_first = _lamp_first(scene, arm, start, a, end, b, (), joint) if both else None
    if lamp_first is not None:
        return lamp_first
    move = plan_move(scene, arm, start, a, end, b, joint=joint)
    if move.clear or not both:
        return move
    return _lamp_first(scene, arm, start, a, end, b, VIA_RETREATS_M, joint) or move


def _lamp_first(scene: CollisionScene, arm: ArmConfig, start: End, a: Stop, end: End, b: Stop,
                retreats: Sequence[float], joint: bool = False) -> Move | None:
    """The move with the lamp's route first (the arm still at a), then the arm's path (the lamp
    at b), or None where either is not clear."""
    assert a.lamp_joints is not None and b.lamp_joints is not None
    c, lamp_via, n = lamp_route(scene, a.T_cell_cam, a.arm_joints, a.lamp_joints, b.lamp_joints)
    if not c.ok:
        return None
    then = plan_move(scene, arm, start, replace(a, lamp_joints=b.lamp_joints), end, replace(b, lamp_joints=None),
                     retreats, joint)
    if not then.clear:
        return None
    at = [lamp_position(scene.pivot_m, *j) for j in (a.lamp_joints, *lamp_via, b.lamp_joints)]
    return replace(then, clearance=_least([c, then.clearance], scene.padding_m), lamp_via=lamp_via,
                   lamp_first=True, steps=then.steps + n,
                   travel_m=then.travel_m + float(sum(np.linalg.norm(y - x) for x, y in pairwise(at))))


def _through(scene: CollisionScene, arm: ArmConfig, poses: list[np.ndarray], q: np.ndarray,
             lamp: np.ndarray | None, targets: Sequence[np.ndarray | None] | None = None
             ) -> tuple[Clearance, np.ndarray, int, list[np.ndarray]]:
    """The smallest Clearance of the legs through the poses in turn, each a moveL (arm_path) or,
    where targets[k] gives joints, a moveJ to them (joint_path, its envelope by
    check_joint_motion); -inf, the arm named, where the arm cannot make a leg (where: why,
    ur5e.Unreachable's or the envelope's words). Also the joints it ends at, the poses checked and
    the joints at each pose after the first."""
    found, steps, reached = list[Clearance](), 0, list[np.ndarray]()
    for k, (T_from, T_to) in enumerate(pairwise(poses)):
        target = None if targets is None else targets[k]
        if target is not None:
            c, q, n = joint_leg(scene, arm, q, target, lamp)
        else:
            try:
                c, q, n = arm_path(scene, T_from, q, T_to, lamp)
            except ur5e.Unreachable as err:
                return Clearance(-np.inf, ("arm", "its reach"), scene.padding_m, str(err)), q, steps, reached
        found.append(c)
        reached.append(q)
        steps += n
        if not c.ok:
            return c, q, steps, reached
    return _least(found, scene.padding_m), q, steps, reached


def _with_lamp(scene: CollisionScene, arm: ArmConfig, move: Move, a: Stop, b: Stop) -> Move:
    """The move with the lamp's own move after the arm's (the arm where it arrived at b)
    counted in, its corners (along a moveJ leg the camera every JOINT_ARC_RAD of its leading
    joint's turn), its travel and the arm's time (arm_duration_s). A lamp not known at a (the
    home pose) is checked from b's pose (the run checks it from where it reads it) and counts no
    travel."""
    assert move.joints_end is not None, "a clear arm move arrives somewhere"
    joints = (a.arm_joints, *move.via_joints, move.joints_end)
    corners = (a.T_cell_cam[:3, 3], *(p for k, T in enumerate((*move.via, b.T_cell_cam))
                                      for p in (_arc(scene, joints[k], joints[k + 1]) if k in move.joint_legs
                                                else (T[:3, 3],))))
    travel = float(sum(np.linalg.norm(q - p) for p, q in pairwise(corners)))
    least, n = move.clearance, 0
    if b.lamp_joints is not None:
        start = b.lamp_joints if a.lamp_joints is None else a.lamp_joints
        c, lamp_via, n = lamp_route(scene, b.T_cell_cam, move.joints_end, start, b.lamp_joints)
        least = _least([move.clearance, c], scene.padding_m)
        move = replace(move, lamp_via=lamp_via)
        if a.lamp_joints is not None:
            at = [lamp_position(scene.pivot_m, *j) for j in (a.lamp_joints, *lamp_via, b.lamp_joints)]
            travel += float(sum(np.linalg.norm(y - x) for x, y in pairwise(at)))
    return replace(move, clearance=least, steps=move.steps + n, corners_m=corners, travel_m=travel,
                   duration_s=arm_duration_s(scene, arm, move, a, b))


def arm_duration_s(scene: CollisionScene, arm: ArmConfig, move: Move, a: Stop, b: Stop) -> float:
    """The time [s] the arm's commands take along the clear move from stop a to stop b: each leg
    (to a via pose, to b) a moveL (line_commands) or, in Move.joint_legs, a moveJ to the joints
    planned there (joint_commands), at the arm's speed_m_s and acceleration_m_s2, a leg longer
    than its move_timeout_s made in several commands along the same path (as the run makes it,
    cell.run.motion)."""
    assert move.joints_end is not None, "a clear arm move arrives somewhere"
    poses, joints = (a.T_cell_cam, *move.via, b.T_cell_cam), (a.arm_joints, *move.via_joints, move.joints_end)
    timeout = arm.move_timeout_s
    return float(sum(t for k in range(len(poses) - 1)
                     for _, t in (joint_commands(arm, scene.frames, joints[k], joints[k + 1], timeout)
                                  if k in move.joint_legs else line_commands(arm, poses[k], poses[k + 1], timeout))))


def _arc(scene: CollisionScene, q_from: np.ndarray, q_to: np.ndarray) -> list[np.ndarray]:
    """The camera's positions along the moveJ from q_from to q_to, every JOINT_ARC_RAD of the
    leading joint's turn, q_from's left out."""
    n = max(1, int(np.ceil(float(np.abs(q_to - q_from).max()) / JOINT_ARC_RAD)))
    return [_camera(scene, q_from + s * (q_to - q_from))[:3, 3] for s in np.linspace(0.0, 1.0, n + 1)[1:]]


def _camera(scene: CollisionScene, q: np.ndarray) -> np.ndarray:
    """T_cell_cam with the arm at joints q (the forward kinematics)."""
    return scene.frames.T_cell_cam_from_base(scene.frames.T_base_cam_from_flange(ur5e.forward(q)))


def _retreated(T_cell_cam: np.ndarray, distance_m: float) -> np.ndarray:
    """The camera pose moved back along its optical axis (away from what it looks at)."""
    T = T_cell_cam.copy()
    T[:3, 3] -= distance_m * T[:3, 2]
    return T


def home_stop(scene: CollisionScene, lamp_joints: tuple[float, float, float] | None = None) -> Stop:
    """The arm at its home joints (ur5e.HOME_JOINTS): where a run starts."""
    T_base_cam = scene.frames.T_base_cam_from_flange(ur5e.forward(ur5e.HOME_JOINTS))
    return Stop(scene.frames.T_cell_cam_from_base(T_base_cam), np.array(ur5e.HOME_JOINTS), lamp_joints)


def checked_route(scene: CollisionScene, arm: ArmConfig, stops: Sequence[Stop],
                  shortest_order: Callable[[np.ndarray], tuple[int, ...]],
                  rounds: int = 8) -> tuple[tuple[int, ...], list[Move]]:
    """(the order of stops[1:] (indices from 0) from stops[0], where the arm is (the home pose),
    and the checked Moves along it, each from where the last arrived). Lazy: a route solver
    (`shortest_order` of a travel matrix, index 0 the start) orders the stops by straight-line
    travel, a lower bound of every move's; the moves of that order are checked (plan_transition,
    as the run makes them: the arm first, else the lamp first) and
    their true travel (via points counted; UNCHECKED_M where no path is clear) put in, until
    an order's moves change no entry (then no other order is shorter), or after `rounds`
    orders the shortest checked one. A move that is not clear ends its order's list."""
    n = len(stops)
    D = np.zeros((n, n))
    for i, a in enumerate(stops):
        for j, b in enumerate(stops):
            D[i, j] = np.linalg.norm(b.T_cell_cam[:3, 3] - a.T_cell_cam[:3, 3])
            if a.lamp_joints is not None and b.lamp_joints is not None:
                D[i, j] += np.linalg.norm(lamp_position(scene.pivot_m, *b.lamp_joints)
                                          - lamp_position(scene.pivot_m, *a.lamp_joints))
    checked: dict[tuple[int, int, bytes, bytes], Move] = {}
    tried: list[tuple[float, tuple[int, ...], list[Move]]] = []
    for _ in range(rounds):
        order = tuple(shortest_order(D))
        moves, q, lamp, changed = [], stops[0].arm_joints, stops[0].lamp_joints, False
        for i, j in pairwise([0, *(k + 1 for k in order)]):
            key = (i, j, np.asarray(q, float).tobytes(), np.asarray(lamp, float).tobytes())
            if key not in checked:
                checked[key] = plan_transition(scene, arm, replace(stops[i], arm_joints=q, lamp_joints=lamp), stops[j],
                                               HOME if i == 0 else i - 1, j - 1)
            move = checked[key]
            moves.append(move)
            cost = move.travel_m if move.clear else UNCHECKED_M
            changed |= cost > D[i, j] + 1e-12
            D[i, j] = max(D[i, j], cost)
            if not move.clear or move.joints_end is None:
                break
            q, lamp = move.joints_end, stops[j].lamp_joints
        total = sum(m.travel_m if m.clear else UNCHECKED_M for m in moves)
        tried.append((total + UNCHECKED_M * (len(order) + 1 - len(moves)), order, moves))
        if not changed:
            return order, moves
    _, order, moves = min(tried, key=lambda t: t[0])
    return order, moves
