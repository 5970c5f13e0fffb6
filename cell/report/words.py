"""Results in the words of a process engineer: each requirement by its name in the shop ("depth of
field"), with what it compares in its own unit ("21.0 mm needed, 21.0 mm available") from the
requirement's Amount (cell.planning.requirements), else its sentence; never a raw objective value
f_i; counts with their grammar ("1 shot covers 1 of 2 features")."""

from __future__ import annotations

from dataclasses import replace

from collections.abc import Iterable
from typing import TYPE_CHECKING

from cell.core.numbers import LARGE as LARGE, number as number   # said as everywhere a person reads
from cell.physics.costs import Amount, RequirementValue

if TYPE_CHECKING:
    from cell.planning.plan import Plan

# plan.json's requirement names, as a person says them
LABELS = {
    "gray_min": "gray band, dark end",
    "gray_max": "gray band, bright end",
    "reflection_region": "reflection type",
    "lamp_tolerance": "tolerance to lamp position errors",
    "no_shadow": "no shadow on the feature",
    "cone_coverage": "lamp cone over the feature",
    "camera_view": "camera view of the feature",
    "view_angle": "view angle",
    "resolution": "pixel size on the part",
    "shutter_min": "shutter time, short end",
    "shutter_max": "shutter time",
    "f_number_min": "lens aperture, open end",
    "f_number_max": "lens aperture, closed end",
    "depth_of_field": "depth of field",
    "defect_cnr": "defect contrast over noise",
    "viewpoint": "camera viewpoint",
}


def label(name: str) -> str:
    """A requirement's name in words (the name with spaces where it has no label)."""
    return LABELS.get(name, name.replace("_", " "))


def count(n: int, thing: str, plural: str | None = None) -> str:
    """'1 shot', '2 shots', '0 iterations' (none at all is said by the sentence: covering())."""
    return f"{n} {thing if n == 1 else plural or thing + 's'}"


def covering(shots: int, covered: int, features: int) -> str:
    """'1 shot covers 1 of 1 feature', '2 shots cover 3 of 3 features', 'no shot covers the 1
    feature', 'no shot covers any of the 2 features'."""
    if covered == 0:
        return "no shot covers the 1 feature" if features == 1 else f"no shot covers any of the {features} features"
    verb = "covers" if shots == 1 else "cover"
    return f"{count(shots, 'shot')} {verb} {covered} of {count(features, 'feature')}"


# how each requirement's Amount is said, {actual} and {limit} with their unit
PHRASES = {
    "gray_min": "darkest {actual}, the band starts at {limit}",
    "gray_max": "brightest {actual}, the band ends at {limit}",
    "cone_coverage": "samples up to {actual} off the lamp's axis, it lights up to {limit}",
    "view_angle": "seen up to {actual} from the normals, at most {limit} wanted",
    "resolution": "{actual} per pixel, at most {limit} wanted",
    "shutter_min": "{actual}, the camera's shortest is {limit}",
    "shutter_max": "{actual} needed, the camera's longest is {limit}",
    "f_number_min": "f/{actual}, the lens opens to f/{limit}",
    "f_number_max": "f/{actual}, the lens closes to f/{limit}",
    "depth_of_field": "{limit} needed, {actual} available",
    "defect_cnr": "CNR {actual}, at least {limit} wanted",
}


# the unit of a miss where the Amount's numbers have none
BY_UNIT = {"gray_min": " gray levels", "gray_max": " gray levels", "defect_cnr": " in CNR"}


def compared(name: str, a: Amount) -> str:
    """What an Amount compares: '21.0 mm needed, 21.0 mm available'."""
    actual, limit = number(a.actual, a.unit, a.digits), number(a.limit, a.unit, a.digits)
    default = "{actual}, at most {limit} allowed" if a.at_most else "{limit} needed, {actual} available"
    return PHRASES.get(name, default).format(actual=actual, limit=limit)


def _agrees(r: RequirementValue) -> bool:
    """Whether r's Amount says what its verdict says (a depth of field wide enough but placed
    wrong fails with an Amount that is met: its sentence says why)."""
    a = r.amount
    if a is None:
        return False
    within = a.actual <= a.limit if a.at_most else a.actual >= a.limit
    return within == r.met


def holds(r: RequirementValue) -> str:
    """A met requirement: 'depth of field (21.0 mm needed, 21.0 mm available)'."""
    if r.amount is not None and _agrees(r):
        return f"{label(r.name)} ({compared(r.name, r.amount)})"
    return f"{label(r.name)} ({r.detail})" if r.detail else label(r.name)


def fails(r: RequirementValue) -> str:
    """A missed requirement and by how much in its own unit: 'shutter time fails by 25.0 ms
    (45.0 ms needed, the camera's longest is 20.0 ms)', else its sentence."""
    if r.amount is not None and _agrees(r):
        a = r.amount
        unit = a.unit or BY_UNIT.get(r.name)
        if unit is None:                           # an f-number: no "by", the comparison says it
            return f"{label(r.name)} fails ({compared(r.name, a)})"
        by = number(abs(a.actual - a.limit), unit, a.digits)
        return f"{label(r.name)} fails by {by} ({compared(r.name, a)})"
    return f"{label(r.name)} fails: {r.detail}" if r.detail else f"{label(r.name)} fails"


def tightest(requirements: Iterable[RequirementValue], name: str | None = None) -> str:
    """The binding requirement in words: `name`'s (plan.binding) or the largest value's; 'tightest
    requirement: ...' when it holds, '... fails ...' when not."""
    values = list(requirements)
    if not values:
        return "no requirement judged"
    r = next((v for v in values if v.name == name), None) or max(values, key=lambda v: v.value)
    return f"tightest requirement: {holds(r)}" if r.met else fails(r)


def why(r: RequirementValue) -> str:
    """A missed requirement in one line: fails() and, where its numbers came from the Amount, the
    requirement's sentence after them (what would fix it)."""
    said = fails(r)
    return said if not r.detail or said.endswith(r.detail) else f"{said}; {r.detail}"


# what a `collision` binding says besides the bodies: the optics held (cell.planning.whole_part.cleared,
# cell.run.moves.with_moves), so moving a body is what fixes it
OPTICS_MET = "the lighting, exposure and view meet every requirement"


def uncovered(feature: str, binding: str, hint: str) -> str:
    """A feature no shot covers: 'feature end_face: no shot covers it: camera view of the feature
    fails: ...' (its own plan's binding requirement and sentence); a collision as its hint says it,
    'feature shank: no shot covers it: collision: fixture and wrist_3 touch or overlap, ...'."""
    if binding == "collision":
        return f"feature {feature}: no shot covers it: {hint}"
    return f"feature {feature}: no shot covers it: {label(binding)} fails: {hint}"


def reason(plan: Plan) -> str:
    """Why a plan is not feasible, one line for a person, its true cause first: the first feature
    no shot covers, else a collision with both bodies (at the shot or on a move: the hint) where
    the optics held, else the binding requirement with its numbers and what would fix it.
    (plan.message keeps the machine's names: plan.json, report.json.)"""
    first = next((f for f in plan.features if f.covered_by is None), None)
    if first is not None:
        return uncovered(first.name, first.binding, first.hint)
    if plan.binding == "collision":
        return f"{plan.hint}; {OPTICS_MET}"
    r = next((v for v in plan.requirements if v.name == plan.binding), None)
    if r is None:
        return f"{label(plan.binding)} fails: {plan.hint}"
    return why(replace(r, detail=plan.hint) if plan.hint.startswith(r.detail) else r)
