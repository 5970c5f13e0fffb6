"""The simulated cell's own collision check: what the simulated arm and pan-tilt would hit as they
move, independent of the planner's cell.collision (other geometry, other distances): the part,
the fixture and each fixed light's housing (`light_housing`: a ring's annulus, a dome's shell open
at its hole, a bar's box) as points on a grid over each triangle (`surface_points`) in a k-d tree, the camera and lamp housings as
sampled boxes of the task's `cell.collision` sizes, the UR5e's links as the segments between its
joint origins (cell.devices.ur5e's chain, which the planner's bodies and the real controller share; the lamp's
axes cell.devices.rig.lamp_frame's) with the tube
radii of UR's drawings, the pan-tilt's links behind the lamp (`rig_links`: the tilt servo as a
sampled box, its front at the lamp housing's back or at the task's `cell.collision.rig_reach_m`
from the pivot, and then the rig's arm as its axis with its tube's radius from the housing's back
to the servo; the sizes of cell.devices.rig). A moving body touches another where a sample of one lies within
CONTACT_M of the other's (a surface sample's spacing: penetrating surfaces cross within it), or a
link's axis within its radius plus CONTACT_M. The arm's links among themselves are the
controller's own business (its self-collision limits), not checked here.

A move is checked by conservative advancement (no point of a moving body travels farther between
two checked poses than the gap at the first, less CONTACT_M); the first pose in contact stops it
(`Contact`), nothing moved beyond the last clear one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from cell.devices import ur5e
from cell.devices.rig import RIG_ARM_RADIUS_M, TILT_SERVO_SIZE_M, lamp_frame

from cell.task.types import HOUSING_RIM_M

if TYPE_CHECKING:
    from cell.task.types import Light, Task

CONTACT_M = 0.004           # closer than this: touching (the surface samples' spacing; the
                            # planner keeps 10 mm of padding)
STEP_M = 0.004              # the least step of conservative advancement
FAR_M = 0.1                 # gaps are looked for up to this far (a k-d tree's search stops there)
REACH_M = 1.3               # the UR5e's farthest point from any of its axes, a camera on its flange
# the UR5e's tubes (UR's drawings): base and shoulder 75 mm, upper arm 55, elbow and forearm 45,
# wrists 45 mm in radius; the upper arm runs 138 mm off the DH line along joint 2's axis
LINK_RADII_M = (0.075, 0.055, 0.045, 0.045, 0.045, 0.045)
UPPER_ARM_OFFSET_M = 0.138
CIRCLE_SECTIONS = 256       # a ring's or dome's circles as polygons: within 0.01 mm of a 130 mm circle


@dataclass(frozen=True)
class Contact:
    """Two bodies that would touch, and where (the moving body's point) [m]."""

    moving: str
    other: str
    where_m: np.ndarray

    def __str__(self) -> str:
        return (f"the {self.moving} would hit the {self.other} at {np.round(self.where_m, 3).tolist()} m "
                "(cell frame): protective stop, nothing moved beyond the last clear pose")


def surface_points(mesh: trimesh.Trimesh, spacing: float = CONTACT_M) -> np.ndarray:
    """Points on every triangle of the mesh on a barycentric grid of n steps a side, n = its
    longest edge / spacing rounded up: a triangle's every point lies within `spacing` of one."""
    out = []
    tri = mesh.triangles
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(int)
    for n in np.unique(steps):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        w = np.column_stack([i[keep], j[keep]]) / n                   # barycentric weights of vertices 1, 2
        t = tri[steps == n]
        out.append((t[:, None, 0] + w[None, :, :1] * (t[:, None, 1] - t[:, None, 0])
                    + w[None, :, 1:] * (t[:, None, 2] - t[:, None, 0])).reshape(-1, 3))
    return np.vstack(out)


def light_housing(light: Light) -> trimesh.Trimesh:
    """A fixed light's housing (Light.housing's sizes) as a closed mesh in the cell frame, behind
    its emitting surface in the light's frame (x its `along`, z its axis, its emitting centre at
    0): a ring's annulus (trimesh's) from aperture_radius_m to outer_radius_m; a dome's shell,
    the band between its sphere (radius_m about the point radius_m along z) and one housing_depth_m
    larger, from the camera's hole (hole_radius_m) to the rim (z = radius_m), revolved about z;
    any other light's box of its emitting extent plus HOUSING_RIM_M across, housing_depth_m deep."""
    h = light.housing()
    if light.type == "ring":
        mesh = trimesh.creation.annulus(r_min=h.aperture_radius_m, r_max=h.outer_radius_m, height=h.depth_m,
                                        sections=CIRCLE_SECTIONS)
        mesh.apply_translation((0.0, 0.0, -0.5 * h.depth_m))
    elif light.type == "dome":
        r, hole = float(light.radius_m or 0.0), float(light.hole_radius_m or 0.0)
        arcs = []
        for rho in (r + h.depth_m, r):
            polar = np.linspace(np.arcsin(min(hole / rho, 1.0)), 0.5 * np.pi, CIRCLE_SECTIONS // 4)
            arcs.append(np.column_stack([rho * np.sin(polar), r - rho * np.cos(polar)]))
        mesh = trimesh.creation.revolve(np.vstack([arcs[0], arcs[1][::-1], arcs[0][:1]]), sections=CIRCLE_SECTIONS)
    else:
        if light.type == "bar":
            across = (float(light.length_m or 0.0), 0.0)
        elif light.size_m is not None:
            across = (float(light.size_m[0]), float(light.size_m[1]))
        else:
            across = (2.0 * float(light.radius_m or 0.0),) * 2
        mesh = trimesh.creation.box(extents=(across[0] + 2 * HOUSING_RIM_M, across[1] + 2 * HOUSING_RIM_M, h.depth_m))
        mesh.apply_translation((0.0, 0.0, -0.5 * h.depth_m))
    T = np.eye(4)
    T[:3, :3] = np.column_stack([light.along, np.cross(light.axis, light.along), light.axis])
    T[:3, 3] = light.position_m
    return mesh.apply_transform(T)


def _stacked(bodies: list[tuple[str, np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(points, each one's radius, each one's body name) of bodies given as (name, points, radius)."""
    points = np.vstack([p for _, p, _ in bodies])
    radii = np.concatenate([np.full(len(p), r) for _, p, r in bodies])
    names = [name for name, p, _ in bodies for _ in range(len(p))]
    return points, radii, names


def _box_samples(size: np.ndarray) -> np.ndarray:
    """Points on the surface of a box of `size` centred at 0 (trimesh's box, `surface_points`)."""
    return surface_points(trimesh.creation.box(extents=size))


class Obstacles:
    """The bodies of the simulated cell, where the arm and the lamp are now, and the check of a
    move of either against the rest."""

    def __init__(self, task: Task) -> None:
        c = task.cell.collision
        self.frames = task.frames
        fixed = [("part", task.part.mesh.copy().apply_transform(task.frames.T_cell_part))]
        if c.fixture is not None:
            fixed.append(("fixture", c.fixture))
        fixed += [(light.name, light_housing(light)) for light in task.lights if light.mount == "fixed"]
        points, names = [], []
        for name, mesh in fixed:
            p = surface_points(mesh)
            points.append(p)
            names += [name] * len(p)
        self.fixed = cKDTree(np.vstack(points))
        self.fixed_names = np.array(names)
        self.camera_local = _box_samples(np.asarray(c.camera_size_m)) + (0.0, 0.0, c.camera_offset_m)
        self.lamp_size = np.asarray(c.lamp_size_m, float)
        self.lamp_local = _box_samples(self.lamp_size)
        self.servo_local = _box_samples(np.asarray(TILT_SERVO_SIZE_M))
        self.pivot = np.asarray(task.lamp.rig.pivot_m, float)
        self.reach = c.rig_reach_m                      # the tilt servo's front from the pivot (None: at the lamp)
        self.arm_joints: np.ndarray | None = None       # set by the arm as it moves
        self.lamp_position: np.ndarray | None = None    # set by the lamp as it moves
        self._cache_key: tuple[object, ...] | None = None
        self._cache_tree: cKDTree | None = None

    # -- the bodies at a pose -----------------------------------------------------------------

    def links(self, q: np.ndarray) -> list[tuple[str, np.ndarray, float]]:
        """(name, points along its axis every CONTACT_M, radius) of each link at joints q."""
        frames = ur5e.chain(self.frames.T_cell_base, q)
        o, z = frames[:, :3, 3], frames[:, :3, 2]
        off = UPPER_ARM_OFFSET_M * z[1]
        ends = [(o[0], o[1]), (o[1] + off, o[2] + off), (o[2], o[3]), (o[3], o[4]), (o[4], o[5]), (o[5], o[6])]
        out = []
        for k, ((a, b), r) in enumerate(zip(ends, LINK_RADII_M)):
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / CONTACT_M)) + 1)
            out.append((f"arm link {k + 1}", a + np.linspace(0.0, 1.0, n)[:, None] * (b - a), r))
        return out

    def camera(self, q: np.ndarray) -> np.ndarray:
        T = self.frames.T_cell_base @ ur5e.forward(q)
        return self.camera_local @ T[:3, :3].T + T[:3, 3]

    def lamp(self, position: np.ndarray) -> np.ndarray:
        """The lamp housing's samples: its front face at `position`, its axis to the pivot."""
        R = lamp_frame(self.pivot, position)
        return self.lamp_local @ R.T + position - 0.5 * self.lamp_size[2] * R[:, 2]

    def rig_links(self, position: np.ndarray) -> list[tuple[str, np.ndarray, float]]:
        """(name, points, radius) of the pan-tilt's links holding the lamp at `position`: the tilt
        servo's box samples, its axes the lamp's, its front face on the lamp's axis at the housing's
        back or, with the rig's reach declared, that far from the pivot; then the rig's arm, its
        axis every CONTACT_M from the housing's back to the servo's front."""
        R = lamp_frame(self.pivot, position)
        back = position - self.lamp_size[2] * R[:, 2]
        front = back if self.reach is None else self.pivot - self.reach * R[:, 2]
        servo = [("tilt servo", self.servo_local @ R.T + front - 0.5 * TILT_SERVO_SIZE_M[2] * R[:, 2], 0.0)]
        if self.reach is None:
            return servo
        n = max(2, int(np.ceil(np.linalg.norm(front - back) / CONTACT_M)) + 1)
        return [*servo, ("rig arm", back + np.linspace(0.0, 1.0, n)[:, None] * (front - back), RIG_ARM_RADIUS_M)]

    def lamp_points(self, position: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """(points, each one's radius, each one's body name) of the lamp at `position`: its
        housing's samples (radius 0) and its rig's links."""
        return _stacked([("lamp housing", self.lamp(position), 0.0), *self.rig_links(position)])

    # -- the checks -------------------------------------------------------------------------------

    def _tree(self, key: tuple[object, ...], points: np.ndarray) -> cKDTree:
        """A k-d tree of a body that stands still while the other moves, kept while it does."""
        if self._cache_key != key or self._cache_tree is None:
            self._cache_key, self._cache_tree = key, cKDTree(points)
        return self._cache_tree

    def arm_points(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """(points, each one's radius, each one's body name) of the arm at joints q: the camera
        housing's samples (radius 0) and the links' axes."""
        return _stacked([("camera housing", self.camera(q), 0.0), *self.links(q)])

    def gap(self, q: np.ndarray | None, lamp: np.ndarray | None, lamp_moves: bool = False) -> tuple[float, Contact]:
        """The smallest gap [m] between a moving body (the arm at joints q, the lamp at `lamp`;
        either None: absent) and another, and those two (a Contact where it is); FAR_M when none
        is nearer. Only the pairs the move changes: the arm's with the fixed bodies and the lamp,
        or (`lamp_moves`) the lamp's with the fixed bodies and the arm, in a k-d tree of the one
        standing still."""
        best = (FAR_M, Contact("", "", np.zeros(3)))

        def nearer(points: np.ndarray, radii: np.ndarray, names: list[str], tree: cKDTree,
                   tree_radii: np.ndarray, tree_names: Callable[[int], str]) -> None:
            """The moving body's points against another's tree: the gaps less both radii."""
            nonlocal best
            d, k = tree.query(points, distance_upper_bound=radii.max() + tree_radii.max() + FAR_M)
            found = np.isfinite(d)
            d[found] -= radii[found] + tree_radii[k[found]]
            i = int(np.argmin(d))
            if d[i] < best[0]:
                best = (float(d[i]), Contact(names[i], tree_names(int(k[i])), points[i]))

        def fixed_names(k: int) -> str:
            return str(self.fixed_names[k])

        fixed_radii = np.zeros(len(self.fixed_names))
        lamp_bodies = None if lamp is None else self.lamp_points(lamp)
        if q is not None:
            arm = self.arm_points(q)
            if not lamp_moves:
                nearer(*arm, self.fixed, fixed_radii, fixed_names)
            if lamp_bodies is not None and not lamp_moves:
                tree = self._tree(("lamp", *np.round(lamp_bodies[0][0], 12)), lamp_bodies[0])
                nearer(*arm, tree, lamp_bodies[1], lamp_bodies[2].__getitem__)
            elif lamp_bodies is not None:
                tree = self._tree(("arm", *np.round(q, 12)), arm[0])
                nearer(*lamp_bodies, tree, arm[1], arm[2].__getitem__)
        if lamp_bodies is not None and (lamp_moves or q is None):
            nearer(*lamp_bodies, self.fixed, fixed_radii, fixed_names)
        return best

    def arm_move(self, path: list[np.ndarray]) -> Contact | None:
        """The first contact along the arm's joints `path` (the lamp where it is), linear in the
        joints between its entries. Steps by conservative advancement: after a pose with gap d no
        point of the arm (REACH_M from any of its axes at most) travels more than
        max(STEP_M, d - CONTACT_M) to the next, so no contact falls between two poses checked."""
        for q0, q1 in zip(path, path[1:]):
            sweep, s = float(np.abs(q1 - q0).sum()) * REACH_M, 0.0
            while True:
                q = (1 - s) * q0 + s * q1
                d, contact = self.gap(q, self.lamp_position)
                if d < CONTACT_M:
                    return contact
                if s >= 1.0:
                    break
                s = min(1.0, s + max(STEP_M, d - CONTACT_M) / max(sweep, 1e-300))
        return None

    def lamp_move(self, a: np.ndarray, b: np.ndarray,
                  lamp_at: Callable[[np.ndarray], np.ndarray]) -> Contact | None:
        """The first contact as the lamp's joints go linearly from a to b (the arm where it is);
        lamp_at(joints) -> its position. The points of the lamp and its rig's links move at most
        (|dpan| + |dtilt|) rho + |dradius|, rho the farthest of them from the pivot (at the larger
        radius, where none lies nearer: the housing moves out, the servo with it or standing at
        the rig's reach): conservative advancement as arm_move."""
        points, radii, _ = self.lamp_points(lamp_at(np.array([a[0], a[1], max(a[2], b[2])])))
        rho = float((np.linalg.norm(points - self.pivot, axis=1) + radii).max())
        sweep = (abs(b[0] - a[0]) + abs(b[1] - a[1])) * rho + abs(b[2] - a[2])
        s = 0.0
        while True:
            d, contact = self.gap(self.arm_joints, lamp_at((1 - s) * a + s * b), lamp_moves=True)
            if d < CONTACT_M:
                return contact
            if s >= 1.0:
                return None
            s = min(1.0, s + max(STEP_M, d - CONTACT_M) / max(sweep, 1e-300))
