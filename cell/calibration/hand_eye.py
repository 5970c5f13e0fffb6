"""Operator routine for the camera's focal length and the hand-eye transform T_flange_cam with the
ChArUco board of calibration.board (`cell calibrate hand-eye`).

The arm takes the camera to `poses` viewpoints around the board (cell.task.board: its place in the
cell says where to look) at DISTANCE x the board-filling distance, each tilted TILT_DEG from the
board's normal toward another azimuth and rolled ROLL_DEG about the optical axis, so that the
rotations between views turn about different axes (what hand-eye calibration needs most); a
viewpoint outside the workspace box or the arm's reach is skipped and counted. In each frame the
board's ChArUco corners are detected (cv2.aruco.CharucoDetector) and matched to the board's
points (Board.matchImagePoints). cv2.calibrateCamera fits the views in the cell's own camera
model (cell.physics.projection: one focal length, the principal point at the sensor's centre, no
distortion), the task's lens as the first guess, giving each view's board pose T_cam_board; so
the hand-eye holds what the cell's model needs (a real principal point off centre becomes a
small turn of T_flange_cam, which a narrow field barely tells from it). A fit freeing the
principal point, fx, fy, k1 and k2 is reported as a check (the simulator has no distortion).
The flange poses read back from the arm (the reported camera pose with the task's hand-eye taken
off) and the board poses give AX = XB, solved by cv2.calibrateHandEye with each of METHODS; the
one reprojecting the corners best is refined (refine) with the board's pose in the cell and the
focal length on every corner's reprojection error. Residuals: the spread of the board's pose in
the cell over the views, and the corners' reprojection error through the result.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import cv2
import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from scipy.spatial.transform import Rotation

from cell.physics.sensor import levels, saturation_level
from cell.core import geometry

from cell.run import motion
from cell.run.acquisition import acquire
from cell.devices.interfaces import check_arm_motion
from cell.core.files import write_yaml
from cell.core.errors import DeviceFault, GoalNotReached
from cell.physics.projection import intrinsics
from cell.report.recorder import Ending, Recorder
from cell.report.result import Result

if TYPE_CHECKING:
    from cell.devices.interfaces import Devices
    from cell.task.board import Board
    from cell.task.types import Task

MIN_POSES = 10
TILT_DEG = (18.0, 30.0, 24.0)       # the optical axis from the board's normal, in turn
ROLL_DEG = (-40.0, 0.0, 40.0, 20.0, -20.0)  # about the optical axis, in turn
# the viewing distance's factor, in turn: distances that differ (known from the arm) part the focal
# length from the camera's offset along its axis, which at one distance trade off (f / (d + dz))
DISTANCE = (1.0, 0.8, 1.2, 0.9)
FILL = 1.0                          # the board's larger side over the field of view, seen square on
F_NUMBER = 8.0                      # a middle stop (clipped to the lens's): depth over the tilted board
REACH_M = 0.85                      # the UR5e's reach from its base (datasheet: 850 mm)
MIN_CORNERS = 8                     # a view with fewer ChArUco corners is left out
EXPOSURE_TARGET = 0.7               # the board's white (99th percentile) at this share of the range
EXPOSURE_BAND = (0.45, 0.9)
MAX_EXPOSURE_PROBES = 6
METHODS = {"TSAI": cv2.CALIB_HAND_EYE_TSAI, "PARK": cv2.CALIB_HAND_EYE_PARK,
           "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS}
# the cell's camera model (cell.physics.projection): one focal length, the principal point at the sensor's
# centre, no distortion; the check fit frees the principal point, fx, fy, k1 and k2
PINHOLE_FLAGS = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
                 | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
FREE_FLAGS = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3


def viewpoints(board: Board, distance_m: float, count: int) -> list[np.ndarray]:
    """`count` camera poses T_cell_cam looking at the board's centre, the i-th from DISTANCE[i % 4]
    x distance_m, tilted TILT_DEG[i % 3] from the board's face normal toward azimuth i * 360 /
    count (about the normal, from the board's x) and rolled ROLL_DEG[i % 5] about the optical axis."""
    T = board.T_cell_centre
    centre, x, normal = T[:3, 3], T[:3, 0], -T[:3, 2]           # the face looks along -z (board frame)
    side = np.cross(normal, x)
    poses = []
    for i in range(count):
        tilt, azimuth = np.radians(TILT_DEG[i % len(TILT_DEG)]), 2 * np.pi * i / count
        direction = np.cos(tilt) * normal + np.sin(tilt) * (np.cos(azimuth) * x + np.sin(azimuth) * side)
        z = -direction
        x_cam = geometry.unit(x - (x @ z) * z)
        R = np.column_stack([x_cam, np.cross(z, x_cam), z])
        roll = Rotation.from_euler("z", ROLL_DEG[i % len(ROLL_DEG)], degrees=True).as_matrix()
        poses.append(geometry.transform(R @ roll, centre + DISTANCE[i % len(DISTANCE)] * distance_m * direction))
    return poses


def viewing_distance(task: Task) -> float:
    """The distance at which the board's larger side fills FILL of the field of view, seen
    square on (pinhole: the field at distance d is d * side_px * pitch / f)."""
    sensor, lens = task.camera.sensor, task.camera.lens
    field = np.array([sensor.width_px, sensor.height_px]) * sensor.pixel_pitch_m / lens.focal_length_m
    return float(np.max(task.board.size_m / field) / FILL)


def refused(task: Task, T_cell_cam: np.ndarray) -> str | None:
    """Why the arm would refuse this camera pose (the interface's workspace check, or the flange
    beyond REACH_M of the robot base), or None."""
    config, frames = task.cell.devices.arm, task.frames
    try:
        check_arm_motion(config, frames, T_cell_cam, config.speed_m_s)
    except DeviceFault as why:                  # refused before moving
        return why.reason
    flange = frames.T_base_cell @ frames.T_cell_flange(T_cell_cam)
    reach = float(np.linalg.norm(flange[:3, 3]))
    return None if reach <= REACH_M else f"flange {1e3 * reach:.0f} mm from the robot base, beyond its reach " \
                                          f"of {1e3 * REACH_M:.0f} mm"


@dataclass(frozen=True)
class View:
    """One viewpoint: the flange pose read back, the picture with the corners drawn, the ChArUco
    corners found and their board and image points; `usable` with at least MIN_CORNERS."""

    pose: int
    picture: str
    T_cell_flange: np.ndarray
    object_points: np.ndarray       # (N, 3) board frame
    image_points: np.ndarray        # (N, 2) px

    @property
    def corners(self) -> int:
        return len(self.object_points)

    @property
    def usable(self) -> bool:
        return self.corners >= MIN_CORNERS

    def to_json(self) -> dict[str, Any]:
        return {"pose": self.pose, "picture": self.picture, "corners": self.corners,
                "T_cell_flange": self.T_cell_flange}


def to_8_bit(image: np.ndarray, bit_depth: int) -> np.ndarray:
    """The frame as 8-bit levels for the ArUco detector."""
    gray = levels(image, bit_depth).astype(float)
    return np.clip(np.rint(gray * 255.0 / saturation_level(bit_depth)), 0, 255).astype(np.uint8)


def detect(board: Board, image8: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(object points (N, 3), image points (N, 2), charuco corners, ids) of the board in an 8-bit
    frame; N = 0 when nothing was found."""
    charuco = board.charuco()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(charuco).detectBoard(image8)
    if corners is None or len(corners) < 4:
        return np.zeros((0, 3)), np.zeros((0, 2)), corners, ids
    obj, img = charuco.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(float), img.reshape(-1, 2).astype(float), corners, ids


def draw_corners(image8: np.ndarray, corners: np.ndarray | None, ids: np.ndarray | None) -> np.ndarray:
    """The frame in colour with the detected corners and their ids drawn (evidence)."""
    picture = cv2.cvtColor(image8, cv2.COLOR_GRAY2BGR)
    if corners is not None and len(corners):
        cv2.aruco.drawDetectedCornersCharuco(picture, corners, ids, (0, 0, 255))
    return picture


def auto_exposure(devices: Devices, recorder: Recorder, task: Task, f_number: float, focus_m: float,
                  frames: list[str]) -> float:
    """The shutter putting the board's white (the frame's 99th percentile) at EXPOSURE_TARGET of
    the range: probes from the shutter range's geometric middle, rescaled (G ~ t), 4x shorter
    while saturated. GoalNotReached when the range ends first."""
    lo, hi = task.camera.shutter_range_s
    top = saturation_level(task.camera.sensor.bit_depth)
    shutter = float(np.sqrt(lo * hi))
    for _ in range(MAX_EXPOSURE_PROBES):
        capture = acquire(devices, recorder, len(frames) + 1, shutter, f_number, focus_m)
        frames.append(capture.name)
        image = np.asarray(capture.image, float)
        white = float(np.percentile(image, 99))
        share, saturated = white / top, white >= top
        recorder.step("exposure", f"{1e3 * capture.shutter_s:.3f} ms: white at {100 * share:.0f} % of the range"
                                  + (" (saturated)" if saturated else ""), shutter_s=capture.shutter_s,
                      white=white, saturated=bool(saturated))
        if not saturated and EXPOSURE_BAND[0] <= share <= EXPOSURE_BAND[1]:
            return capture.shutter_s
        wanted = capture.shutter_s / 4 if saturated else capture.shutter_s * EXPOSURE_TARGET / max(share, 1e-3)
        nxt = float(np.clip(wanted, lo, hi))
        if np.isclose(nxt, capture.shutter_s):
            break
        shutter = nxt
    raise GoalNotReached(f"no shutter time in {1e3 * lo:.3g}-{1e3 * hi:.3g} ms shows the board's white within "
                         f"{100 * EXPOSURE_BAND[0]:.0f}-{100 * EXPOSURE_BAND[1]:.0f} % of the range: is the light "
                         "over the board on, and not too bright?", "exposure")


def collect(devices: Devices, recorder: Recorder, task: Task, poses: list[np.ndarray]
            ) -> tuple[list[View], list[dict[str, Any]]]:
    """Visit each pose the arm accepts (refused ones skipped, logged and counted), take a frame,
    detect the board, save the frame with its corners drawn. Returns (views, refused)."""
    board, bit_depth = task.board, task.camera.sensor.bit_depth
    f_number = float(np.clip(F_NUMBER, *task.camera.lens.f_number_range))
    views: list[View] = []
    skipped: list[dict[str, Any]] = []
    frames: list[str] = []
    shutter: float | None = None
    with recorder.stage("poses", len(poses)) as stage:      # the log has every step, the terminal a bar
        for k, T in enumerate(stage.each(poses), 1):
            why = refused(task, T)
            move = None if why else motion.check(task, devices, T, to=f"pose {k}")
            if move is not None and not move.clear:
                why = str(motion.refusal(move))
            if why:
                skipped.append({"pose": k, "reason": why})
                recorder.step("refused", f"pose {k}/{len(poses)} skipped: {why}", pose=k, reason=why)
                continue
            T_cell_cam = motion.move_camera(task, devices, T, recorder, f"pose {k}", checked=move)
            focus_m = float((board.T_cell_centre[:3, 3] - T_cell_cam[:3, 3]) @ T_cell_cam[:3, 2])
            recorder.step("move_camera", f"pose {k}/{len(poses)}: camera at "
                          f"{np.round(T_cell_cam[:3, 3], 4).tolist()} m", pose=k, position_m=T_cell_cam[:3, 3])
            if shutter is None:
                shutter = auto_exposure(devices, recorder, task, f_number, focus_m, frames)
            capture = acquire(devices, recorder, len(frames) + 1, shutter, f_number, focus_m)
            frames.append(capture.name)
            image8 = to_8_bit(capture.image, bit_depth)
            obj, img, corners, ids = detect(board, image8)
            name = recorder.write_image(f"board-{k}.png", draw_corners(image8, corners, ids))
            T_cell_flange = task.frames.T_cell_flange(capture.T_cell_cam)
            views.append(View(k, name, T_cell_flange, obj, img))
            left_out = "" if views[-1].usable else f", fewer than {MIN_CORNERS}: left out"
            recorder.step("board", f"pose {k}: {len(obj)} corners{left_out}", pose=k, corners=len(obj), picture=name)
    return views, skipped


@dataclass(frozen=True)
class Intrinsics:
    """cv2.calibrateCamera's camera matrix in the cell's model, its RMS reprojection error, each
    view's board pose T_cam_board, and the free fit's check (free_fit)."""

    K: np.ndarray
    distortion: np.ndarray              # (k1, k2, p1, p2, k3): zeros in the cell's model
    rms_px: float
    T_cam_board: tuple[np.ndarray, ...]
    check: dict[str, Any]               # free_fit's

    @property
    def focal_length_px(self) -> float:
        return float(np.mean(np.diag(self.K)[:2]))

    def to_json(self) -> dict[str, Any]:
        return {"focal_length_px": self.focal_length_px, "fx_px": self.K[0, 0], "fy_px": self.K[1, 1],
                "principal_point_px": self.K[:2, 2], "reprojection_error_px": self.rms_px,
                "free_fit": self.check}


def free_fit(rms: float, K: np.ndarray, distortion: np.ndarray) -> dict[str, Any]:
    """The check fit's numbers (JSON-ready)."""
    return {"fx_px": K[0, 0], "fy_px": K[1, 1], "principal_point_px": K[:2, 2], "k1": distortion[0],
            "k2": distortion[1], "reprojection_error_px": rms}


def calibrate_intrinsics(task: Task, views: list[View]) -> Intrinsics:
    """cv2.calibrateCamera over the views in the cell's model (PINHOLE_FLAGS) and the check fit
    (FREE_FLAGS), the task's pinhole K as the first guess of both."""
    sensor = task.camera.sensor
    objects = [v.object_points.astype(np.float32) for v in views]
    images = [v.image_points.astype(np.float32) for v in views]
    size, K0 = (sensor.width_px, sensor.height_px), intrinsics(sensor, task.camera.lens)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objects, images, size, K0.copy(), np.zeros(5),
                                                     flags=PINHOLE_FLAGS)
    free = cv2.calibrateCamera(objects, images, size, K0.copy(), np.zeros(5), flags=FREE_FLAGS)
    poses = tuple(geometry.transform(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs))
    return Intrinsics(K, dist.ravel(), float(rms), poses, free_fit(free[0], free[1], free[2].ravel()))


def hand_eye_linear(views: list[View], T_cam_board: tuple[np.ndarray, ...], method: str) -> np.ndarray:
    """cv2.calibrateHandEye (method by keyword: as the 5th positional argument it is ignored):
    T_flange_cam from the flange poses (in the cell) and the board poses in the camera."""
    R, t = cv2.calibrateHandEye([v.T_cell_flange[:3, :3] for v in views], [v.T_cell_flange[:3, 3] for v in views],
                                [T[:3, :3] for T in T_cam_board], [T[:3, 3] for T in T_cam_board],
                                method=METHODS[method])
    return geometry.transform(R, t.ravel())


def board_in_cell(views: list[View], T_cam_board: tuple[np.ndarray, ...], X: np.ndarray) -> np.ndarray:
    """The board's pose in the cell each view implies, T_cell_flange X T_cam_board, (V, 4, 4)."""
    return np.array([v.T_cell_flange @ X @ T for v, T in zip(views, T_cam_board)])


def mean_pose(Ts: np.ndarray) -> np.ndarray:
    """The mean of rigid transforms: mean translation, the rotations' chordal mean."""
    R = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    return geometry.transform(R, Ts[:, :3, 3].mean(axis=0))


def reprojection(views: list[View], X: np.ndarray, T_cell_board: np.ndarray, K: np.ndarray,
                 distortion: np.ndarray) -> np.ndarray:
    """Each corner's image residual (detected - projected through X: the board at T_cell_board
    seen from T_cell_flange X), concatenated (2 N,) [px]."""
    out = []
    for v in views:
        T = np.linalg.inv(v.T_cell_flange @ X) @ T_cell_board
        rvec = cv2.Rodrigues(T[:3, :3])[0]
        projected, _ = cv2.projectPoints(v.object_points, rvec, T[:3, 3], K, distortion)
        out.append((v.image_points - projected.reshape(-1, 2)).ravel())
    return np.concatenate(out)


def _pose(params: np.ndarray) -> np.ndarray:
    return geometry.transform(Rotation.from_rotvec(params[:3]).as_matrix(), params[3:])


def _params(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def with_focal(K: np.ndarray, focal_px: float) -> np.ndarray:
    """K with fx = fy = focal_px."""
    K = np.array(K, float)
    K[0, 0] = K[1, 1] = focal_px
    return K


def refine(views: list[View], X: np.ndarray, T_cell_board: np.ndarray, K: np.ndarray, distortion: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, OptimizeResult]:
    """X, the board's pose in the cell and the focal length by least squares on the corners'
    reprojection error (scipy.optimize.least_squares, trust region): the views' different
    distances, known from the arm, part the focal length from the camera's offset along its axis,
    which at one distance trade off (f / (d + dz)) and a narrow field's perspective pins only to
    about 0.2 %. Returns (X, T_cell_board, K, the solver's result)."""
    def residual(p: np.ndarray) -> np.ndarray:
        return reprojection(views, _pose(p[1:7]), _pose(p[7:]), with_focal(K, p[0]), distortion)

    start = np.concatenate([[K[0, 0]], _params(X), _params(T_cell_board)])
    scale = np.r_[1.0, [0.01] * 3, [0.001] * 3, [0.01] * 3, [0.001] * 3]
    fit = least_squares(residual, start, x_scale=scale, method="trf")
    return _pose(fit.x[1:7]), _pose(fit.x[7:]), with_focal(K, fit.x[0]), fit


@dataclass(frozen=True)
class HandEye:
    """T_flange_cam by one method, with its residuals: the spread of the board's pose in the cell
    over the views (rms distance from their mean [m], rms angle [rad]) and the corners' rms
    reprojection error through it [px]."""

    method: str
    T_flange_cam: np.ndarray
    T_cell_board: np.ndarray
    focal_length_px: float
    board_spread_m: float
    board_spread_rad: float
    reprojection_error_px: float

    @property
    def position_m(self) -> np.ndarray:
        return self.T_flange_cam[:3, 3]

    @property
    def rpy_deg(self) -> np.ndarray:
        return Rotation.from_matrix(self.T_flange_cam[:3, :3]).as_euler("xyz", degrees=True)

    def to_json(self) -> dict[str, Any]:
        return {"method": self.method, "hand_eye_position_m": self.position_m, "hand_eye_rpy_deg": self.rpy_deg,
                "T_flange_cam": self.T_flange_cam, "T_cell_board": self.T_cell_board,
                "focal_length_px": self.focal_length_px,
                "board_spread_m": self.board_spread_m, "board_spread_deg": np.degrees(self.board_spread_rad),
                "reprojection_error_px": self.reprojection_error_px}


def judge(method: str, views: list[View], T_cam_board: tuple[np.ndarray, ...], X: np.ndarray, K: np.ndarray,
          distortion: np.ndarray, T_cell_board: np.ndarray | None = None) -> HandEye:
    """The HandEye of X with its residuals; the board's pose the views' mean unless given."""
    boards = board_in_cell(views, T_cam_board, X)
    T_cell_board = mean_pose(boards) if T_cell_board is None else T_cell_board
    spread_m = float(np.sqrt(np.mean(np.sum((boards[:, :3, 3] - T_cell_board[:3, 3]) ** 2, axis=1))))
    turn = Rotation.from_matrix(boards[:, :3, :3]) * Rotation.from_matrix(T_cell_board[:3, :3]).inv()
    spread_rad = float(np.sqrt(np.mean(turn.magnitude() ** 2)))
    residual = reprojection(views, X, T_cell_board, K, distortion).reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    return HandEye(method, X, T_cell_board, float(K[0, 0]), spread_m, spread_rad, rms)


def board_poses(views: list[View], K: np.ndarray, distortion: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each view's T_cam_board by cv2.solvePnP with this camera matrix."""
    poses = []
    for v in views:
        _, rvec, tvec = cv2.solvePnP(v.object_points, v.image_points, K, distortion)
        poses.append(geometry.transform(cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return tuple(poses)


def solve(views: list[View], intrinsics_: Intrinsics) -> tuple[HandEye, dict[str, HandEye], dict[str, Any]]:
    """Every method of METHODS judged, the refinement of the best (smallest reprojection error),
    judged with its focal length: (the refined HandEye, {method: HandEye}, the solver's verdict)."""
    K, dist, T_cam_board = intrinsics_.K, intrinsics_.distortion, intrinsics_.T_cam_board
    linear = {m: judge(m, views, T_cam_board, hand_eye_linear(views, T_cam_board, m), K, dist) for m in METHODS}
    best = min(linear.values(), key=lambda h: h.reprojection_error_px)
    X, T_cell_board, K, fit = refine(views, best.T_flange_cam, best.T_cell_board, K, dist)
    refined = judge(f"{best.method} refined", views, board_poses(views, K, dist), X, K, dist, T_cell_board)
    return refined, linear, {"success": bool(fit.success), "nfev": int(fit.nfev), "message": fit.message}


def hand_eye_document(result: HandEye) -> dict[str, Any]:
    """The hand-eye file: the task's cell.arm keys in their place, which a task names as
    cell.arm.hand_eye (or copies)."""
    return {"cell": {"arm": {"hand_eye_position_m": [round(float(v), 6) for v in result.position_m],
                             "hand_eye_rpy_deg": [round(float(v), 4) for v in result.rpy_deg]}}}


@dataclass(frozen=True)
class HandEyeCalibration(Result):
    """What the routine achieved (cell.report.result's verdict: `success`, the hand-eye solved
    and its file written; `message`, why not; the device fault), the intrinsics, the hand-eye
    (refined) and each method's, the views, the poses refused and the hand-eye file.
    calibration.json is to_json(), with `reason` (the message) as well."""

    SUCCEEDED: ClassVar[str] = "calibrated"
    NOT_REACHED: ClassVar[str] = "not_calibrated"

    task: str
    success: bool
    message: str
    views: tuple[View, ...] = ()
    refused: tuple[dict[str, Any], ...] = ()            # {pose, reason}
    intrinsics: Intrinsics | None = None
    hand_eye: HandEye | None = None
    methods: dict[str, HandEye] | None = None
    refinement: dict[str, Any] | None = None      # least_squares' success, nfev, message
    hand_eye_file: str | None = None
    fault: dict[str, Any] | None = None
    cause: str | None = None

    @property
    def solved_hand_eye(self) -> HandEye:
        """The refined hand-eye of a successful calibration (ValueError on one that solved none)."""
        return self._made(self.hand_eye, "hand-eye")

    @property
    def solved_methods(self) -> dict[str, HandEye]:
        """Each method's hand-eye of a successful calibration (ValueError on one that solved none)."""
        return self._made(self.methods, "hand-eye of each method")

    @property
    def calibrated_intrinsics(self) -> Intrinsics:
        """The intrinsics of a successful calibration (ValueError on one that calibrated none)."""
        return self._made(self.intrinsics, "intrinsics")

    @property
    def written_hand_eye_file(self) -> str:
        """The hand-eye file a successful calibration wrote (ValueError when it wrote none)."""
        return self._made(self.hand_eye_file, "hand-eye file")

    def fitted(self) -> dict[str, Any]:
        """The hand-eye's position and angles, the focal length and the reprojection error ({}
        without a result)."""
        if not self.hand_eye or not self.intrinsics:
            return {}
        return {"hand_eye_position_m": self.hand_eye.position_m, "hand_eye_rpy_deg": self.hand_eye.rpy_deg,
                "focal_length_px": self.intrinsics.focal_length_px,
                "reprojection_error_px": self.intrinsics.rms_px}

    def summary(self) -> dict[str, Any]:
        """--json's keys: fitted()'s and the hand-eye file."""
        return self.fitted() | {"hand_eye_file": self.hand_eye_file}

    @property
    def counters(self) -> dict[str, int]:
        return {"poses": len(self.views) + len(self.refused), "views": len(self.views),
                "views_used": sum(v.usable for v in self.views), "refused": len(self.refused)}

    def details(self) -> dict[str, Any]:
        return {"task": self.task, **self.fitted(),
                "intrinsics": self.intrinsics.to_json() if self.intrinsics else None,
                "hand_eye": self.hand_eye.to_json() if self.hand_eye else None,
                "methods": {m: h.to_json() for m, h in (self.methods or {}).items()}, "refinement": self.refinement,
                "views": [v.to_json() for v in self.views], "refused": list(self.refused),
                "hand_eye_file": self.hand_eye_file}


def run(task: Task, out: str | Path, connect: Callable[[], Devices], hand_eye_file: str | Path, poses: int = 12,
        force: bool = False) -> HandEyeCalibration:
    """connect() -> Devices; the views, intrinsics and hand-eye; out/log.jsonl as it happens,
    out/calibration.json however it ends, a board-K.png per view, the hand-eye file on success.
    Raises GoalNotReached with fewer than MIN_POSES usable views (exit 1), DeviceFault after the
    safe stop (exit 3). Returns the HandEyeCalibration."""
    out = Path(out)
    views: list[View] = []
    skipped: list[dict[str, Any]] = []
    calibrated: Intrinsics | None = None
    result: HandEye | None = None
    linear: dict[str, HandEye] | None = None
    solver: dict[str, Any] | None = None
    written: str | None = None

    def done(reason: str, fault: dict[str, Any] | None) -> HandEyeCalibration:
        return HandEyeCalibration(str(task.path), result is not None and not reason, reason, tuple(views),
                                  tuple(skipped), calibrated, result, linear, solver, written, fault)

    with Recorder(out) as recorder, Ending(recorder, "no calibration", "calibration.json", done) as end:
        distance = viewing_distance(task)
        near, far = (distance * f(DISTANCE) for f in (min, max))
        recorder.step("setup", f"{poses} viewpoints {1e3 * near:.0f}-{1e3 * far:.0f} mm from the board's centre "
                               f"{np.round(task.board.T_cell_centre[:3, 3], 4).tolist()} m, tilted "
                               f"{min(TILT_DEG):g} to {max(TILT_DEG):g} deg, rolled {min(ROLL_DEG):g} to "
                               f"{max(ROLL_DEG):g} deg", distance_m=distance)
        with end.session:
            end.session.devices = connect()
            views, skipped = collect(end.session.devices, recorder, task, viewpoints(task.board, distance, poses))
        usable = [v for v in views if v.usable]
        if len(usable) < MIN_POSES:
            raise GoalNotReached(f"the board was seen at {len(usable)} of {poses} viewpoints ({len(skipped)} "
                                 f"refused by the arm, {len(views) - len(usable)} with fewer than {MIN_CORNERS} "
                                 f"corners), at least {MIN_POSES} are needed: is the board where "
                                 "calibration.board says, and lit?", "too_few_views")
        calibrated = calibrate_intrinsics(task, usable)
        result, linear, solver = solve(usable, calibrated)
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        header = (f"cell calibrate hand-eye {task.path.name} on {stamp}: {len(usable)} views, corners' "
                  f"reprojection error {result.reprojection_error_px:.3f} px, run folder {out}\n"
                  f"a task uses this file as cell.arm.hand_eye: {Path(hand_eye_file).name} (relative to the task file), "
                  "or these keys copied into its cell.arm")
        written = str(write_yaml(hand_eye_file, hand_eye_document(result), replace=force, header=header))
        recorder.step("done", f"T_flange_cam at {np.round(1e3 * result.position_m, 3).tolist()} mm, rpy "
                              f"{np.round(result.rpy_deg, 3).tolist()} deg; f {calibrated.focal_length_px:.1f} px; "
                              f"wrote {written}", hand_eye_file=written, **result.to_json())
    return end.result
