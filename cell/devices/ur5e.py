"""UR5e kinematics from the standard DH table: forward, and the closed-form inverse
(8 solutions: shoulder left/right x wrist up/down x elbow up/down).

Frames are UR's own: 0 is the controller's base frame (the one `getActualTCPPose` uses), 6 the
tool flange. The inverse follows the usual derivation for UR arms (joints 2-4 parallel): the
wrist centre fixes q1, the tool z axis fixes q5 and q6, and a planar two-link arm gives q2-q4.
Shared by the planner (a planned camera viewpoint must be reachable, cell.planning.viewpoints) and the
simulated arm and UR controller (sim/).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])     # d_i [m]
A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])          # a_i [m]
ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
JOINT_LIMITS = np.array([2 * np.pi, 2 * np.pi, np.pi, 2 * np.pi, 2 * np.pi, 2 * np.pi])  # +- [rad]
SINGULAR = 1e-9
# elbow up, wrist down, the flange pointing at the table in front of the base: where the arm
# starts (the simulated arm and controller power up here) and the configuration the planner seeks,
# so that the moves between shots stay on one branch of the inverse kinematics
HOME_JOINTS = np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0])


class Unreachable(ValueError):
    """No joint solution for a flange pose; the message says why."""


def dh(i: int, theta: ArrayLike) -> np.ndarray:
    """A_i = Rz(theta) Tz(d_i) Tx(a_i) Rx(alpha_i): (4, 4), or (..., 4, 4) for an array of theta."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(ALPHA[i]), np.sin(ALPHA[i])
    top = [[ct, -st * ca, st * sa, A[i] * ct], [st, ct * ca, -ct * sa, A[i] * st]]
    if np.ndim(theta) == 0:
        return np.array(top + [[0.0, sa, ca, D[i]], [0.0, 0.0, 0.0, 1.0]])
    o = np.zeros_like(ct)               # the constant cells shaped as theta (0 + c is c, bit for bit)
    return np.moveaxis(np.array(top + [[o, o + sa, o + ca, o + D[i]], [o, o, o, o + 1.0]]), (0, 1), (-2, -1))


def forward(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """T_base_flange for joint angles q (6,) [rad]."""
    T = np.eye(4)
    for i, theta in enumerate(q):
        T = T @ dh(i, theta)
    return T


def chain(T_frame_base: np.ndarray, q: Sequence[float] | np.ndarray) -> np.ndarray:
    """(7, 4, 4) the DH frames 0..6 in the frame T_frame_base places the base in: frame i's
    origin and z axis are joint i+1's point and axis (frame 6 the flange), T_i = T_frame_base
    A_1 ... A_i. The one chain the planner's collision bodies, its sweep bounds and the
    simulated cell's own check place the links by."""
    frames = [np.asarray(T_frame_base, float)]
    for i, theta in enumerate(q):
        frames.append(frames[-1] @ dh(i, theta))
    return np.array(frames)


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a . b over the last axis of 3-vectors, each as a (1, 3) @ (3, 1) product: the very
    arithmetic of a 1-D `a @ b` (a sum over axis -1 rounds otherwise), so that poses solved
    together get the joints each would get alone."""
    return (a[..., None, :] @ b[..., :, None])[..., 0, 0]


@dataclass(frozen=True)
class Branches:
    """The closed-form inverse of N flange poses: q (N, 8, 6) angles in [-pi, pi), shoulder
    (q1) x wrist (q5) x elbow (q3), each branch's first value first; ok (N, 8) where the branch
    exists; wrist_r (N,) the wrist centre's distance from the base axis [m] (none exists
    within the shoulder cylinder, d4); span (N, 2, 2) the planar arm's reach, the wrist's
    distance from the shoulder, of each shoulder x wrist branch [m] (none beyond a2 + a3)."""

    q: np.ndarray
    ok: np.ndarray
    wrist_r: np.ndarray
    span: np.ndarray

    def why(self, n: int) -> str:
        """Why pose n has no solution (the shoulder cylinder, else the first branch's span)."""
        if self.wrist_r[n] < D[3] + SINGULAR:
            return (f"wrist centre {self.wrist_r[n] * 1e3:.1f} mm from the base axis, inside the "
                    f"{D[3] * 1e3:.1f} mm shoulder cylinder")
        return (f"wrist {self.span[n, 0, 0] * 1e3:.1f} mm from the shoulder, the arm spans "
                f"{abs(A[1] - A[2]) * 1e3:.1f}-{abs(A[1] + A[2]) * 1e3:.1f} mm")


def branches(T_base_flange: ArrayLike, q6_free: ArrayLike = 0.0) -> Branches:
    """The Branches of flange poses (N, 4, 4), all at once (the planner asks thousands). q6 is
    free where the wrist is singular (q5 = 0 or pi): it then takes `q6_free` (scalar or (N,)).
    The usual derivation: the wrist centre p5 = p - d6 z6 fixes q1 (two shoulders), z1 . p fixes
    q5 (two wrists), the tool's x and y along z1 fix q6, and the planar arm of a2, a3 to frame
    4's origin gives q3 (two elbows), q2 and q4."""
    T = np.asarray(T_base_flange, float).reshape(-1, 4, 4)
    q6_free = np.broadcast_to(np.asarray(q6_free, float), (len(T),))[:, None, None]
    x6, y6, z6, p = T[:, None, :3, 0], T[:, None, :3, 1], T[:, None, :3, 2], T[:, None, :3, 3]
    p5 = T[:, :3, 3] - D[5] * T[:, :3, 2]                   # wrist centre (origin of frame 5)
    r = np.hypot(p5[:, 0], p5[:, 1])
    inside = r < D[3] + SINGULAR
    with np.errstate(invalid="ignore", divide="ignore"):
        psi, phi = np.arctan2(p5[:, 1], p5[:, 0]), np.arcsin(D[3] / r)
        q1 = np.column_stack([psi + phi, psi + np.pi - phi])                  # (N, 2)
        z1 = np.stack([np.sin(q1), -np.cos(q1), np.zeros_like(q1)], axis=-1)  # joint 2 axis; p5 . z1 = d4
        c5 = np.clip((_dot(p, z1) - D[3]) / D[5], -1.0, 1.0)
        T16 = np.linalg.inv(dh(0, q1)) @ T[:, None]        # frame 6 in frame 1: both q5 branches share it
        q5 = np.stack([np.arccos(c5), -np.arccos(c5)], axis=-1)               # (N, 2, 2)
        s5 = np.sin(q5)
        q6 = np.where(np.abs(s5) < SINGULAR, q6_free, np.arctan2(-_dot(y6, z1)[..., None] / s5,
                                                                 _dot(x6, z1)[..., None] / s5))
        T14 = T16[:, :, None] @ np.linalg.inv(dh(5, q6)) @ np.linalg.inv(dh(4, q5))
        x, y = T14[..., 0, 3], T14[..., 1, 3]               # frame 4 origin, planar arm of a2, a3
        c3 = (x * x + y * y - A[1] ** 2 - A[2] ** 2) / (2 * A[1] * A[2])
        q3 = np.stack([np.arccos(np.clip(c3, -1, 1)), -np.arccos(np.clip(c3, -1, 1))], axis=-1)
        q2 = (np.arctan2(y, x)[..., None]
              - np.arctan2(A[2] * np.sin(q3), A[1] + A[2] * np.cos(q3)))     # (N, 2, 2, 2)
        q4 = np.arctan2(T14[..., 1, 0], T14[..., 0, 0])[..., None] - q2 - q3
    shape = q3.shape
    q = np.stack([np.broadcast_to(q1[:, :, None, None], shape), q2, q3, q4,
                  np.broadcast_to(q5[..., None], shape), np.broadcast_to(q6[..., None], shape)], axis=-1)
    ok = ~inside[:, None, None, None] & ~(np.abs(c3) > 1.0 + 1e-12)[..., None]
    return Branches(_wrap(q).reshape(len(T), 8, 6), np.broadcast_to(ok, shape).reshape(len(T), 8),
                    r, np.hypot(x, y))


def inverse_all(T_base_flange: np.ndarray, q6_free: float = 0.0) -> np.ndarray:
    """All closed-form solutions (k, 6) of one flange pose, angles in [-pi, pi) (branches).
    Raises Unreachable with the reason."""
    b = branches(T_base_flange, q6_free)
    if not b.ok[0].any():
        raise Unreachable(b.why(0))
    return b.q[0][b.ok[0]]


def _nearest_within_limits(q, q_near):
    """Each joint of each solution q (k, 6) as q + 2 pi j (j in -1, 0, 1) nearest to q_near
    within the joint limits; q itself is in [-pi, pi), inside every limit, so a choice always
    exists (the first of equally near ones)."""
    options = q[..., None] + 2 * np.pi * np.array([-1.0, 0.0, 1.0])
    options = np.where(np.abs(options) <= JOINT_LIMITS[:, None], options, np.inf)
    pick = np.argmin(np.abs(options - q_near[:, None]), axis=-1)
    return np.take_along_axis(options, pick[..., None], axis=-1)[..., 0]


def nearest(T_base_flange: ArrayLike, q_near: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(q (N, 6), reached (N,)) of N flange poses (N, 4, 4): each one's solution nearest the
    joints q_near (6,) (smallest largest joint step; the first of equally near ones), within the
    joint limits (+-2 pi, elbow +-pi); q NaN where no solution exists. All poses at once, each
    the joints `inverse` gives it alone."""
    q_near = np.asarray(q_near, float)
    b = branches(T_base_flange, q_near[5])
    candidates = _nearest_within_limits(b.q, q_near)
    steps = np.where(b.ok, np.max(np.abs(candidates - q_near), axis=-1), np.inf)
    q = np.take_along_axis(candidates, np.argmin(steps, axis=1)[:, None, None], axis=1)[:, 0]
    reached = np.asarray(b.ok.any(axis=1))
    q[~reached] = np.nan
    return q, reached


def inverse(T_base_flange: np.ndarray, q_near: ArrayLike) -> np.ndarray:
    """The solution nearest the current joints q_near (nearest). Raises Unreachable with the reason."""
    q, reached = nearest(T_base_flange, q_near)
    if not reached[0]:
        raise Unreachable(branches(T_base_flange).why(0))
    return q[0]
