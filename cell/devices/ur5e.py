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


def dh(i: int, theta: float) -> np.ndarray:
    """A_i = Rz(theta) Tz(d_i) Tx(a_i) Rx(alpha_i)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(ALPHA[i]), np.sin(ALPHA[i])
    return np.array([[ct, -st * ca, st * sa, A[i] * ct],
                     [st, ct * ca, -ct * sa, A[i] * st],
                     [0.0, sa, ca, D[i]],
                     [0.0, 0.0, 0.0, 1.0]])


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


def inverse_all(T_base_flange: np.ndarray, q6_free: float = 0.0) -> np.ndarray:
    """All closed-form solutions (k, 6), angles in [-pi, pi). q6 is free when the wrist is
    singular (q5 = 0 or pi): it then takes `q6_free`. Raises Unreachable with the reason."""
    T = np.asarray(T_base_flange, float)
    x6, y6, z6, p = T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3]
    p5 = p - D[5] * z6                                  # wrist centre (origin of frame 5)
    r = np.hypot(p5[0], p5[1])
    if r < D[3] + SINGULAR:
        raise Unreachable(f"wrist centre {r * 1e3:.1f} mm from the base axis, inside the "
                          f"{D[3] * 1e3:.1f} mm shoulder cylinder")
    psi, phi = np.arctan2(p5[1], p5[0]), np.arcsin(D[3] / r)
    reasons, solutions = [], []
    for q1 in (psi + phi, psi + np.pi - phi):
        z1 = np.array([np.sin(q1), -np.cos(q1), 0.0])  # joint 2 axis; p5 . z1 = d4 by construction
        c5 = np.clip((p @ z1 - D[3]) / D[5], -1.0, 1.0)
        T16 = np.linalg.inv(dh(0, q1)) @ T              # frame 6 in frame 1: both q5 branches share it
        for q5 in (np.arccos(c5), -np.arccos(c5)):
            s5 = np.sin(q5)
            q6 = q6_free if abs(s5) < SINGULAR else np.arctan2(-(y6 @ z1) / s5, (x6 @ z1) / s5)
            T14 = T16 @ np.linalg.inv(dh(5, q6)) @ np.linalg.inv(dh(4, q5))
            x, y = T14[0, 3], T14[1, 3]                 # frame 4 origin, planar arm of a2, a3
            c3 = (x * x + y * y - A[1] ** 2 - A[2] ** 2) / (2 * A[1] * A[2])
            if abs(c3) > 1.0 + 1e-12:
                reach = np.hypot(x, y)
                reasons.append(f"wrist {reach * 1e3:.1f} mm from the shoulder, the arm spans "
                               f"{abs(A[1] - A[2]) * 1e3:.1f}-{abs(A[1] + A[2]) * 1e3:.1f} mm")
                continue
            for q3 in (np.arccos(np.clip(c3, -1, 1)), -np.arccos(np.clip(c3, -1, 1))):
                q2 = np.arctan2(y, x) - np.arctan2(A[2] * np.sin(q3), A[1] + A[2] * np.cos(q3))
                q4 = np.arctan2(T14[1, 0], T14[0, 0]) - q2 - q3
                solutions.append(_wrap(np.array([q1, q2, q3, q4, q5, q6])))
    if not solutions:
        raise Unreachable(reasons[0])
    return np.array(solutions)


def _nearest_within_limits(q, q_near):
    """Each joint of each solution q (k, 6) as q + 2 pi j (j in -1, 0, 1) nearest to q_near
    within the joint limits; q itself is in [-pi, pi), inside every limit, so a choice always
    exists (the first of equally near ones)."""
    options = q[..., None] + 2 * np.pi * np.array([-1.0, 0.0, 1.0])
    options = np.where(np.abs(options) <= JOINT_LIMITS[:, None], options, np.inf)
    pick = np.argmin(np.abs(options - q_near[:, None]), axis=-1)
    return np.take_along_axis(options, pick[..., None], axis=-1)[..., 0]


def inverse(T_base_flange: np.ndarray, q_near: ArrayLike) -> np.ndarray:
    """The solution nearest the current joints q_near (smallest largest joint step; the first
    of equally near ones), within the joint limits (+-2 pi, elbow +-pi). Raises Unreachable
    with the reason."""
    q_near = np.asarray(q_near, float)
    candidates = _nearest_within_limits(inverse_all(T_base_flange, q6_free=q_near[5]), q_near)
    return candidates[int(np.argmin(np.max(np.abs(candidates - q_near), axis=1)))]

