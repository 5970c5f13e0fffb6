"""What planning produces (sec. 5), as plain values that pickle: a Plan made of Shots, its
verdict like scipy's OptimizeResult (feasible, binding, each requirement, the search's counters),
the dense certificate of a shot (Verification) and a feature judged on a shot (Coverage), and
plan.json (docs/formats.md) made from it in one place."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from cell.planning import regions
from cell.physics.costs import RequirementValue

if TYPE_CHECKING:
    from cell.collision.paths import Move
    from cell.collision.scene import Clearance
    from cell.planning.scene import Scene


@dataclass(frozen=True)
class PlannerSettings:
    """Resolution knobs (what accuracy costs in time: `cell bench` sweeps them)."""

    grid_step_deg: float = 2.0      # visibility / region map cell size
    pan_step_deg: float = 10.0      # global candidate grid on the rig
    tilt_step_deg: float = 5.0
    radius_steps: int = 6
    samples: int | None = None      # feature samples (None: the task's)
    refine: bool = True             # Nelder-Mead from the best starts
    starts: int = 4
    # False skips the collision scene (no shot's clearance, no collision pruning of viewpoints):
    # only `cell bench` sets it, to time planning with the checks against without (issue 26)
    collisions: bool = True

    def __post_init__(self) -> None:
        cells = 180.0 / self.grid_step_deg
        if not (self.grid_step_deg > 0 and abs(cells - round(cells)) < 1e-9):
            raise ValueError(f"grid_step_deg {self.grid_step_deg:g} must divide 180 deg (the map's rows "
                             f"must reach the poles and its columns close the circle)")


@dataclass(frozen=True)
class Exposure:
    shutter_s: float
    f_number: float
    focus_m: float
    depth_of_field_m: float


@dataclass(frozen=True)
class Maps:
    """The paper's spherical maps in the feature frame (sec. 2.2, 5.2), for pictures and tests."""

    grid: regions.SphereGrid
    visible: np.ndarray          # (E, A) every sample sees this direction
    dominant: np.ndarray         # (E, A) dominant term where visible, brdf.OCCLUDED elsewhere
    wanted: np.ndarray           # (E, A) wanted reflection and visible
    distance: regions.RegionDistance    # signed haversine distance to the wanted region [rad], found where read
    candidate_pan: np.ndarray    # (C,) global candidates [rad]
    candidate_tilt: np.ndarray
    candidate_objective: np.ndarray
    # (D, E, A) each of the feature's defects' signed CNR with the spot in that direction at the
    # shot's distance, exposure and drives (defects.direction_map; NaN where not visible; D = 0
    # without defects)
    defect_cnr: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))


@dataclass(frozen=True)
class Refinement:
    """One local refinement (Nelder-Mead) with its solver's own verdict."""

    success: bool
    nfev: int
    message: str
    objective: float             # eq. (22) where it ended


@dataclass(frozen=True)
class Search:
    """The search's counters: global candidates, the starts taken from them, and the local
    refinements from those starts."""

    candidates: int
    starts: int
    refinements: tuple[Refinement, ...] = ()


@dataclass(frozen=True)
class DefectCnr:
    """One declared defect on one shot (cell.planning.defects): its predicted CNR (the worst over the feature's points and its
    orientation range) against min_cnr, the scratch's worst orientation [rad] (None for a dent or
    a coating) and the point where it is worst (cell frame), with the good and the defect's gray there."""

    name: str
    kind: str
    min_cnr: float
    predicted_cnr: float
    orientation_rad: float | None
    position_m: np.ndarray
    gray_good: float
    gray_defect: float

    @property
    def met(self) -> bool:
        return bool(self.predicted_cnr >= self.min_cnr)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "min_cnr": self.min_cnr, "predicted_cnr": self.predicted_cnr,
                "met": self.met, "orientation_deg": None if self.orientation_rad is None
                else float(np.degrees(self.orientation_rad)), "position_m": self.position_m.tolist()}


@dataclass(frozen=True)
class Verification:
    """The dense check of one shot (cell.planning.certificate): `holds` when every point meets
    every requirement the certificate judges (certificate.JUDGED); the points checked, their
    gray range, the worst point (farthest out of the band, else the one nearest its edge), the
    specular point (where the mirror direction of the lamp is nearest the camera's) and the
    requirements that failed there."""

    holds: bool
    points: int
    gray_min: float
    gray_max: float
    worst_m: np.ndarray
    worst_gray: float
    specular_m: np.ndarray
    specular_gray: float
    judged: tuple[RequirementValue, ...]  # each judged requirement's value on the dense patch
    rounds: int = 0                       # searches again with worst points added
    defects: tuple[DefectCnr, ...] = ()   # each declared defect's CNR on the dense patch

    @property
    def failing(self) -> tuple[RequirementValue, ...]:
        return tuple(r for r in self.judged if not r.met)

    def to_json(self) -> dict[str, Any]:
        return {"holds": self.holds, "points": self.points, "gray_min": self.gray_min, "gray_max": self.gray_max,
                "worst": {"position_m": self.worst_m.tolist(), "gray": self.worst_gray},
                "specular": {"position_m": self.specular_m.tolist(), "gray": self.specular_gray},
                "failing": [{"name": r.name, "value": r.value, "detail": r.detail} for r in self.failing],
                "rounds": self.rounds}


@dataclass(frozen=True)
class Coverage:
    """One feature judged on one shot (cell.planning.coverage): covered when every requirement
    is met on the samples and the certificate holds on the dense patch; the predicted gray per
    sample (clipped at full scale), each requirement's value (costs.RequirementValue, where
    worse: samples or dense) and the certificate (None when the samples fail already: nothing
    to certify)."""

    feature: str
    covered: bool
    gray: np.ndarray
    requirements: tuple[RequirementValue, ...]
    verification: Verification | None = None
    lights: tuple[LightSetting, ...] = ()      # each light's share of this feature's gray on the shot
    defects: tuple[DefectCnr, ...] = ()        # each declared defect's predicted CNR on the shot

    @property
    def worst(self) -> float:
        """The largest requirement value (max f_i, met when <= 1)."""
        return max(r.value for r in self.requirements)


@dataclass(frozen=True)
class LightSetting:
    """One light of a shot: which (name, type, mount, its controller channel or None), its drive
    level (0..1), its pose in the cell frame (emitting centre, unit axis) and what it adds to the
    shot's feature: gray per sample at this drive and the shot's exposure (the black level not
    included)."""

    name: str
    type: str
    mount: str
    channel: int | None
    drive: float
    position_m: np.ndarray
    axis: np.ndarray
    gray: np.ndarray

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "type": self.type, "mount": self.mount, "channel": self.channel,
                "drive": self.drive, "pose": {"position_m": self.position_m.tolist(), "axis": self.axis.tolist()}}


@dataclass(frozen=True)
class Shot:
    """One capture of a plan: camera pose, lamp joints and position, exposure, the model's gray
    at every feature sample and each requirement's value there (costs.RequirementValue)."""

    T_cell_cam: np.ndarray       # 4x4 camera pose
    joints: tuple[float, ...]    # (pan, tilt, radius) [rad, rad, m]
    lamp_position: np.ndarray    # cell frame [m]
    exposure: Exposure
    gray: np.ndarray             # predicted gray per feature sample, at most the sensor's full scale
    distance_m: float            # lamp -> feature centre
    phase_angle_rad: float       # between lamp and camera, at the feature centre
    requirements: tuple[RequirementValue, ...]
    covers: tuple[Coverage, ...] = ()# a multi-feature plan's: the Coverage of each feature it covers
    arm_joints: tuple[float, ...] | None = None# a planned viewpoint's: the UR5e joints reaching T_cell_cam [rad]
    lights: tuple[LightSetting, ...] = ()      # the spot and the task's other lights, in the task's order
    defects: tuple[DefectCnr, ...] = ()        # the feature's declared defects: predicted CNR (cell.planning.defects)
    clearance: Clearance | None = None         # the cell's bodies at this shot (cell.collision); None: not checked

    @property
    def drive(self) -> np.ndarray | None:
        """(1 + K,) the lights' drive levels, the spot's first (None: none set, all at full)."""
        return np.array([light.drive for light in self.lights]) if self.lights else None

    @property
    def camera_position(self) -> np.ndarray:
        return self.T_cell_cam[:3, 3]


@dataclass(frozen=True)
class FeatureVerdict:
    """A feature of a multi-feature plan: the shot covering it (an index into Plan.shots), or
    None with the requirement that binds in its own plan and what would fix it."""

    name: str
    covered_by: int | None
    binding: str = ""
    hint: str = ""


@dataclass(frozen=True)
class Plan:
    """A plan with its verdict, like scipy's OptimizeResult: `feasible` (max f_i <= 1 over every
    shot's requirements), the `binding` requirement, how far it misses, and `hint`, what would
    fix it. A one-feature task's plan has one shot (`plan.shot`); a multi-feature task's
    (cell.planning.whole_part) has the fewest shots covering its features, `features` saying which covers
    which, `plans` each feature's own plan (whose shots were the candidates: their scene and
    maps; the plan's own `scene` and `maps` are None) and `cover` the set cover's numbers."""

    task_name: str
    feasible: bool
    binding: str
    miss: float
    objective: float
    hint: str
    shots: tuple[Shot, ...]
    maps: Maps | None
    settings: PlannerSettings
    scene: Scene | None                        # the Scene planned on (plain arrays; None: a multi-feature plan's)
    search: Search
    timing_s: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()                # what the user should know although it is no requirement
    verification: Verification | None = None   # the shot's dense certificate (None: infeasible already)
    features: tuple[FeatureVerdict, ...] = ()  # FeatureVerdict of each feature (a multi-feature plan)
    plans: tuple[Plan, ...] = ()               # each feature's own one-shot Plan (a multi-feature plan)
    cover: dict[str, Any] | None = None        # candidate shots, coverage matrix, travel, chosen (plain values)
    moves: tuple[Move, ...] = ()               # the checked moves of its route from the home pose (cell.run.moves)
    gray_any: bool = False                     # `gray_band: any`: plan.json's `gray_band` says "any"

    @property
    def success(self) -> bool:
        """OptimizeResult's name for the verdict: the plan is feasible."""
        return self.feasible

    @property
    def message(self) -> str:
        if self.feasible:
            return "feasible"
        uncovered = next((f for f in self.features if f.covered_by is None), None)
        if uncovered is not None:
            return f"feature '{uncovered.name}' is covered by no shot: {uncovered.binding} binds: {uncovered.hint}"
        return f"{self.binding} binds: {self.hint}"

    def as_chosen(self, shot: Shot, own: Coverage, features: Iterable[str]) -> Plan:
        """This one-shot plan with its shot replaced by `shot`, its drives solved over `features`
        (cell.planning.joint), judged on its own feature as `own`: the verdict, certificate,
        gray, requirements and lights of that shot, and a note naming the features, so that the
        plan's keys and a run of it read the drives the cover chose."""
        worst = max(own.requirements, key=lambda r: r.value)
        note = f"drive levels solved over the features {', '.join(features)} together, each in its own band"
        return replace(self, feasible=own.covered, binding=worst.name, miss=worst.value - 1.0,
                       hint="" if own.covered else worst.detail, verification=own.verification,
                       notes=(*self.notes, note),
                       shots=(replace(shot, gray=own.gray, requirements=own.requirements, lights=own.lights,
                                      defects=own.defects, covers=()),))

    @property
    def planned_scene(self) -> Scene:
        """The Scene a one-feature plan was planned on (a multi-feature plan has none of its own:
        its features' plans, in `plans`, have theirs)."""
        if self.scene is None:
            raise ValueError("a multi-feature plan has no scene of its own: its features' plans have theirs")
        return self.scene

    @property
    def shot(self) -> Shot:
        """The plan's only shot."""
        if len(self.shots) != 1:
            raise ValueError(f"the plan has {len(self.shots)} shots; pick one from plan.shots")
        return self.shots[0]

    @property
    def requirements(self) -> list[RequirementValue]:
        return [r for shot in self.shots for r in shot.requirements]

    def to_json(self) -> dict[str, Any]:
        """plan.json as docs/formats.md gives it (a one-feature plan; a multi-feature plan's
        adds `shots`, `features` and `cover`, and keeps these keys when it has one shot)."""
        if self.features:
            return self._features_json()
        shot = self.shot
        return {
            "task": self.task_name,
            "feasible": self.feasible,
            "binding": self.binding,
            "miss": self.miss,
            "objective": self.objective,
            "hint": self.hint,
            "notes": list(self.notes),
            "requirements": requirements_json(shot.requirements),
            "lamp": lamp_json(shot),
            "lights": [light.to_json() for light in shot.lights],
            "contributions": contributions_json(shot.lights),
            "camera": camera_json(shot),
            "predicted_gray": gray_stats(shot.gray),
            **({"gray_band": "any"} if self.gray_any else {}),
            **({"defects": [d.to_json() for d in shot.defects]} if shot.defects else {}),
            "verified": self.verification.to_json() if self.verification else None,
            **clearance_json(shot),
            **moves_json(self.moves),
            "search": asdict(self.search),
            "timing_s": self.timing_s,
            "settings": asdict(self.settings),
        }

    def _features_json(self):
        doc = {"task": self.task_name, "feasible": self.feasible, "binding": self.binding, "miss": self.miss,
               "objective": self.objective, "hint": self.hint, "notes": list(self.notes),
               "shots": [{"camera": {"T_cell_cam": shot.T_cell_cam.tolist(), **camera_json(shot),
                                     **({} if shot.arm_joints is None else
                                        {"arm_joints_deg": np.degrees(shot.arm_joints).tolist()})},
                          "lamp": lamp_json(shot), **clearance_json(shot),
                          "lights": [light.to_json() for light in shot.lights],
                          "covers": [{"feature": c.feature, "predicted_gray": gray_stats(c.gray),
                                      **({"defects": [d.to_json() for d in c.defects]} if c.defects else {}),
                                      "contributions": contributions_json(c.lights),
                                      "requirements": requirements_json(c.requirements),
                                      "verified": c.verification.to_json() if c.verification else None}
                                     for c in shot.covers]} for shot in self.shots],
               "features": [{"name": f.name, "covered_by": f.covered_by,
                             **({} if f.covered_by is not None else {"binding": f.binding, "hint": f.hint})}
                            for f in self.features],
               "cover": self.cover, **moves_json(self.moves)}
        if len(self.shots) == 1:                     # a one-shot plan keeps the one-shot keys
            own = self.plans[self.cover["chosen"][0]].to_json()
            doc.update({k: own[k] for k in ("requirements", "lamp", "lights", "contributions", "camera",
                                            "predicted_gray", "verified", "search")})
        return {**doc, "timing_s": self.timing_s, "settings": asdict(self.settings)}


def requirements_json(values: Iterable[RequirementValue]) -> list[dict[str, Any]]:
    return [{"name": r.name, "value": r.value, "met": r.met, "detail": r.detail} for r in values]


def lamp_json(shot: Shot) -> dict[str, Any]:
    pan, tilt, radius = shot.joints
    return {"position_m": shot.lamp_position.tolist(), "distance_m": shot.distance_m,
            "phase_angle_deg": float(np.degrees(shot.phase_angle_rad)),
            "joints": {"pan_deg": float(np.degrees(pan)), "tilt_deg": float(np.degrees(tilt)),
                       "radius_m": float(radius)}}


def contributions_json(lights: Iterable[LightSetting]) -> list[dict[str, Any]]:
    """Each light's share of a feature's gray, by channel, at the shot's drive and exposure."""
    return [{"name": light.name, "channel": light.channel, "drive": light.drive, "gray": gray_stats(light.gray)}
            for light in lights]


def clearance_json(shot: Shot) -> dict[str, Any]:
    """`clearance_m`, the smallest distance at the shot between two bodies that may not touch,
    and `clearance_bodies`, which two (none when the shot was not checked)."""
    if shot.clearance is None:
        return {}
    return {"clearance_m": shot.clearance.distance_m, "clearance_bodies": list(shot.clearance.bodies)}


def moves_json(moves: Iterable[Move]) -> dict[str, Any]:
    """`moves`, the route's checked moves in their order (cell.collision.paths.Move.to_json;
    none when they were not planned)."""
    moves = list(moves)
    return {"moves": [m.to_json() for m in moves]} if moves else {}


def camera_json(shot: Shot) -> dict[str, Any]:
    e = shot.exposure
    return {"shutter_s": e.shutter_s, "f_number": e.f_number, "focus_m": e.focus_m,
            "depth_of_field_m": e.depth_of_field_m, "position_m": shot.camera_position.tolist()}


def gray_stats(gray: ArrayLike) -> dict[str, float]:
    gray = np.asarray(gray, dtype=float)
    return {"mean": float(gray.mean()), "min": float(gray.min()), "max": float(gray.max())}
