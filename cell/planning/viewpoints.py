"""Planned camera viewpoints (camera.viewpoint: planned): camera poses on view spheres around a
feature, pruned coarse to fine before any lamp is tried, so that only a bounded few get a lamp
planned (cell.planning.whole_part).

Directions d in the feature frame (+z the normal) in rings of polar angle theta = 0, step, ...
< 90 deg, each ring round(2 pi sin(theta) / step) evenly; radii r over camera.standoff_range_m.
The camera at C = centre + r d looks at the centre (rolled 0, 90, 180, 270 deg about its axis
until the arm reaches it). Stages, cheapest first, each counted:
  visibility   every sample sees d (the paper's visibility map, all four cells around d)
  view_angle   theta within requirements.view_angle_deg (at the centre; exact per sample below)
  resolution   r pitch / f / cos(theta) within requirements.resolution_m (at the centre)
  workspace    camera and flange (by the frames' hand-eye) inside cell.arm's workspace box
               (cell.devices.interfaces.check_arm_motion's tests, as every move is checked:
               arm_accepts, every roll of every pose at once)
  reach        the UR5e's closed-form inverse kinematics (cell.devices.ur5e) has a solution
               (ur5e.nearest, every roll the box accepts at once)
  collision    the arm's links and the camera body at least cell.collision.padding_m from the part,
               the fixture and each other (cell.collision; the lamp is checked with the shot),
               asked roll by roll until one passes
  seen         a direct ray from every sample to C is free and every sample lies in the image
               (evaluate.build_problem's camera_unseen), the view angle and resolution hold at
               every sample, and the depth of field holds at the lens's narrowest f-number
               (cell.planning.requirements' own values, the cheapest first until one fails)
The survivors are ranked by their largest view angle (the squarest first, then the nearest)
and at most views_per_feature are kept, each at least two steps from those kept before.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import TYPE_CHECKING, cast

import numpy as np

from cell.planning import evaluate, requirements
from cell.core import geometry
from cell.physics import projection
from cell.devices import ur5e
from cell.devices.interfaces import arm_accepts, check_arm_motion
from cell.core.errors import DeviceFault, PlanInfeasible
from cell.collision.scene import Clearance, CollisionScene
from cell.planning.scene import look_at

if TYPE_CHECKING:
    from cell.planning.regions import SphereGrid
    from cell.planning.scene import Scene
    from cell.task.types import Task

STAGES = ("visibility", "view_angle", "resolution", "workspace", "reach", "collision", "seen")
ROLLS = np.radians([0.0, 90.0, 180.0, 270.0])
VIEWPOINT_REQUIREMENTS = ("depth_of_field", "view_angle", "resolution", "camera_view")   # the cheapest first (the
# depth of field without a Problem: viewpoint_values)


@dataclass(frozen=True)
class Viewpoint:
    """A camera pose the arm reaches: T_cell_cam, the UR5e joints reaching it (nearest the
    home joints, ur5e.HOME_JOINTS: the branch the arm's moves start on), its standoff [m] and the largest view angle over the samples [rad]."""

    T_cell_cam: np.ndarray
    arm_joints: np.ndarray
    standoff_m: float
    view_angle_rad: float


@dataclass(frozen=True)
class Viewpoints:
    """The kept viewpoints of one feature, best first, the poses tried, those each stage pruned
    and those that passed every stage (kept or not: the bound), and the visibility map (E, A) of
    the feature's samples they were pruned by: it does not depend on the camera, so the lamp
    search at each kept viewpoint takes it (one_shot.plan's `visible`) instead of casting it again."""

    kept: tuple[Viewpoint, ...]
    poses: int
    pruned: dict[str, int]
    passed: int
    visible: np.ndarray
    time_s: float = 0.0          # the viewpoints' own time (cell.planning.whole_part records it)
    # where no pose survives: the Clearance of the first pose refused by collision, its bodies named
    collided: Clearance | None = None

    def to_json(self) -> dict[str, int | dict[str, int]]:
        return {"poses": self.poses, "pruned": dict(self.pruned), "passed": self.passed, "kept": len(self.kept)}

    def why_none(self) -> str:
        """A sentence for a feature no pose survives, its true cause first: where every pose that
        sees the feature at the view angle and pixel size asked was refused by the arm (workspace,
        reach, collision) and none by its optics (seen), the arm; a collision's example bodies
        (`collided`) after its count."""
        def by(stages: tuple[str, ...]) -> str:
            return ", ".join(f"{self.pruned[s]} by {s.replace('_', ' ')}"
                             + (f": e.g. {self.collided.reason()}" if s == "collision" and self.collided else "")
                             for s in stages if self.pruned[s])
        arm = ("workspace", "reach", "collision")
        seeing = self.poses - sum(self.pruned[s] for s in STAGES[:STAGES.index(arm[0])])
        if seeing and not self.pruned["seen"]:
            return (f"every camera pose on the view spheres that sees the feature ({seeing} of {self.poses}) "
                    f"is refused by the arm ({by(arm)})")
        return f"no camera pose of the {self.poses} on the view spheres survives ({by(STAGES)})"


def sphere_directions(step: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unit directions in the feature frame over the open hemisphere above it and their
    polar angles (N,): rings theta = 0, step, ... < pi / 2 of round(2 pi sin theta / step)."""
    dirs: list[np.ndarray] = []
    polar: list[np.ndarray] = []
    for theta in np.arange(0.0, 0.5 * np.pi - 1e-9, step):
        n = max(1, int(round(2 * np.pi * np.sin(theta) / step)))
        phi = 2 * np.pi * (np.arange(n) + 0.5 * (len(polar) % 2)) / n     # rings staggered
        dirs.append(np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                     np.full(n, np.cos(theta))]))
        polar.append(np.full(n, theta))
    return np.vstack(dirs), np.concatenate(polar)


def roll(angle: float) -> np.ndarray:
    """The turn by `angle` about the z axis: T_cell_cam @ roll(angle) is the camera turned about
    its own optical axis."""
    c, s = np.cos(angle), np.sin(angle)
    return geometry.transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))


def reach_all(task: Task, T_cell_cams: np.ndarray,
              bodies: CollisionScene | None = None) -> list[tuple[np.ndarray, np.ndarray] | str]:
    """For each camera pose (N, 4, 4): (the pose rolled (ROLLS, in turn) so the arm reaches it clear
    of the part and fixture, its joints) or the last stage that refused (collision only with
    `bodies`, the task's collision scene). Every roll's workspace check (arm_accepts) and inverse
    kinematics (ur5e.nearest, nearest the home joints) at once, each the very one a pose gets
    alone; the clearance, the dearest, in turn, only until a roll passes."""
    frames, arm = task.frames, task.cell.devices.arm
    T = np.asarray(T_cell_cams, float).reshape(-1, 1, 4, 4) @ np.array([roll(a) for a in ROLLS])  # (N, rolls)
    flat = T.reshape(-1, 4, 4)
    inside = arm_accepts(arm, frames, flat)
    q = np.full((len(flat), 6), np.nan)
    reached = np.zeros(len(flat), bool)
    q[inside], reached[inside] = ur5e.nearest(frames.T_base_flange(frames.T_base_cam(flat[inside])),
                                              ur5e.HOME_JOINTS)
    out: list[tuple[np.ndarray, np.ndarray] | str] = []
    for n in range(len(T)):
        refused = "workspace"
        for k in range(n * len(ROLLS), (n + 1) * len(ROLLS)):
            if not inside[k]:
                continue
            if not reached[k]:
                refused = "reach" if refused != "collision" else refused
                continue
            if bodies is not None and not bodies.clear(flat[k], q[k]):
                refused = "collision"
                continue
            out.append((flat[k].copy(), q[k].copy()))
            break
        else:
            out.append(refused)
    return out


def require_reach(task: Task, scene: Scene) -> None:
    """A fixed camera pose (camera.viewpoint: fixed, the scene's T_cell_cam) as the arm would be sent
    it, unrolled: inside the workspace box and within the UR5e's reach, else PlanInfeasible (exit
    1) saying which, before any lamp is searched and anything moves."""
    frames, arm, T = task.frames, task.cell.devices.arm, scene.T_cell_cam
    position = np.round(T[:3, 3], 3).tolist()
    feature = "the feature" if task.feature.key == "feature" else f"{task.feature.key} ({task.feature.name})"
    where = (f"{task.name}: the camera {task.camera.distance_m:g} m from {feature} (camera.distance_m along "
             f"camera.view_direction) is at {position} m in the cell frame")
    fix = "a camera.distance_m and view_direction the arm reaches, or camera.viewpoint: planned"
    try:
        check_arm_motion(arm, frames, T, arm.speed_m_s)
    except DeviceFault as refused:
        outside = refused.reason.removesuffix(": refused before moving")
        raise PlanInfeasible(f"camera_reach: {outside}", f"{where}, where the arm cannot take it: {outside} "
                                                         f"(cell.arm.workspace_min_m/max_m); {fix}") from None
    try:
        ur5e.inverse(frames.T_base_flange(frames.T_base_cam(T)), ur5e.HOME_JOINTS)
    except ur5e.Unreachable:
        base = np.round(frames.T_cell_base[:3, 3], 3).tolist()
        far = float(np.linalg.norm(frames.T_cell_flange(T)[:3, 3] - frames.T_cell_base[:3, 3]))
        raise PlanInfeasible(f"camera_reach: camera pose unreachable for the UR5e at {position} m",
                             f"{where}, beyond the UR5e's reach: its flange would be {far:.3f} m from the arm's "
                             f"base at {base} m (cell.arm.base_position_m), or at an angle no joint "
                             f"solution takes; {fix}") from None


def viewpoint_values(task: Task, scene: Scene, hidden: np.ndarray | None = None) -> Iterator[tuple[str, float]]:
    """(name, ln f_i) of each viewpoint requirement the task asks for at the scene's camera (the
    depth of field at the lens's narrowest f-number: whether any f-number gives it), the cheapest
    first, each found when asked for: a pose is pruned at the first that fails, the dearer ones
    (camera_view: the lamp's housing and links) left unasked; `hidden` the samples hidden from the
    camera where found before (evaluate.hidden_from). The depth of field, the first, reads the
    focus on the centre and the samples' depths alone (requirements.depth_of_field_ln, the
    Problem's own value), so a pose it prunes (about half the reached) builds no Problem."""
    kappa = np.array([task.camera.lens.f_number_range[1]])
    yield "depth_of_field", float(np.max(requirements.depth_of_field_ln(task, scene, evaluate.centre_focus(scene),
                                                                        kappa)))
    problem = evaluate.build_problem(task, scene, None, hidden=hidden)
    # the viewpoint requirements read only the f-number, the shutter's shape and the lamp's position
    # of the Candidates, the lamp not placed yet (NaN: its housing hides nothing, requirements.lamp_hides)
    lens_only = cast(evaluate.Candidates, SimpleNamespace(kappa=kappa, shutter=np.zeros(1),
                                                          position=np.full((1, 3), np.nan)))
    by_name = {r.name: r for r in requirements.REGISTRY}
    for r in (by_name[name] for name in VIEWPOINT_REQUIREMENTS[1:]):
        if r.asked is None or r.asked(problem):
            yield r.name, float(np.max(r.ln_value(problem, lens_only)))


def plan_viewpoints(task: Task, scene: Scene, visible: np.ndarray, grid: SphereGrid,
                    collisions: bool = True) -> Viewpoints:
    """Viewpoints of the one-feature task whose samples and visibility map (grid's) are given;
    collisions False: no pose pruned for its clearance (PlannerSettings.collisions, `cell bench` only)."""
    vp, req = task.camera.viewpoint, task.requirements
    sensor, lens = task.camera.sensor, task.camera.lens
    if vp.standoff_range_m is None:
        raise ValueError("planned viewpoints need camera.standoff_range_m (the loader requires it)")
    dirs, polar = sphere_directions(vp.step_rad)
    radii = np.linspace(*vp.standoff_range_m, vp.standoff_steps) if vp.standoff_steps > 1 else \
        np.array([vp.standoff_range_m[0]])
    pruned = dict.fromkeys(STAGES, 0)
    az, el = geometry.angles_from_direction(dirs)
    seen_dir = grid.sample(visible.astype(float), az, el) >= 1.0 - 1e-9
    pruned["visibility"] = int(np.sum(~seen_dir)) * len(radii)
    square = seen_dir & (polar <= (np.inf if req.view_angle_rad is None else req.view_angle_rad) + 1e-12)
    pruned["view_angle"] = int(np.sum(seen_dir & ~square)) * len(radii)
    d = (scene.frame @ dirs[square][:, :, None])[:, None, :, 0]       # each a (3, 3) @ (3,)'s arithmetic
    cameras = (scene.center + radii[:, None] * d).reshape(-1, 3)        # (direction, radius) in turn
    standoffs = np.broadcast_to(radii, (len(d), len(radii))).reshape(-1)
    fine = np.ones(len(cameras), bool)
    if req.resolution_m is not None:
        fine = ~(projection.pixel_footprint(cameras, scene.center, scene.normal, sensor.pixel_pitch_m,
                                            lens.focal_length_m) > req.resolution_m)
    pruned["resolution"] = int(np.sum(~fine))
    bodies = CollisionScene.of(task) if collisions else None
    got = reach_all(task, look_at(cameras[fine], np.broadcast_to(scene.center, cameras[fine].shape)), bodies)
    reached: list[tuple[float, np.ndarray, np.ndarray]] = []         # (standoff, T_cell_cam, joints)
    for r, pose in zip(standoffs[fine], got):
        if isinstance(pose, str):
            pruned[pose] += 1
        else:
            reached.append((float(r), *pose))
    survivors = []
    hidden = evaluate.hidden_from(task, scene, [T[:3, 3] for _, T, _ in reached])     # one launch for all
    for (r, T, q), hid in zip(reached, hidden):
        if any(v > 0.0 for _, v in viewpoint_values(task, replace(scene, T_cell_cam=T), hid)):
            pruned["seen"] += 1
            continue
        angle = projection.view_angles(T[:3, 3], scene.points, scene.normals).max()
        survivors.append(Viewpoint(T, q, r, float(angle)))
    survivors.sort(key=lambda v: (round(v.view_angle_rad, 9), v.standoff_m))
    kept: list[Viewpoint] = []
    for v in survivors:
        axis = v.T_cell_cam[:3, 2]
        if all(np.arccos(np.clip(axis @ k.T_cell_cam[:3, 2], -1, 1)) >= 2 * vp.step_rad - 1e-9 for k in kept):
            kept.append(v)
        if len(kept) == vp.per_feature:
            break
    collided = next((n for n, pose in enumerate(got) if pose == "collision"), None)
    if kept or bodies is None or collided is None:
        return Viewpoints(tuple(kept), len(dirs) * len(radii), pruned, len(survivors), visible)
    unchecked = reach_all(task, look_at(cameras[fine][collided][None], scene.center[None]))[0]   # its first roll reached
    assert not isinstance(unchecked, str)          # a pose refused by collision: some roll is reached
    return Viewpoints((), len(dirs) * len(radii), pruned, 0, visible, collided=bodies.clearance(*unchecked))
