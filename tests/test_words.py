"""cell.report.words: results in a process engineer's words, never a raw objective value f_i nor
an exponent, counts with their grammar."""
import math
from types import SimpleNamespace

import pytest
from hypothesis import given, strategies as st

from cell.physics.costs import Amount, RequirementValue
from cell.report import words

DOF = RequirementValue("depth_of_field", 1.0, "in focus 489.5-510.5 mm ...", Amount(21.0, 21.0, " mm", False))


def test_a_met_requirement_says_what_is_needed_and_available():
    assert words.tightest([RequirementValue("gray_max", 0.5, "brightest 119.7"), DOF]) == \
        "tightest requirement: depth of field (21.0 mm needed, 21.0 mm available)"


def test_a_missed_requirement_says_by_how_much_in_its_unit():
    shutter = RequirementValue("shutter_max", 2.7, "needs shutter 45.0 ms > max 20.0 ms", Amount(45.0, 20.0, " ms", True))
    assert words.tightest([DOF, shutter], "shutter_max") == \
        "shutter time fails by 25.0 ms (45.0 ms needed, the camera's longest is 20.0 ms)"
    dark = RequirementValue("gray_min", 1.8, "...", Amount(29.2, 100.0, "", False))
    assert words.fails(dark) == "gray band, dark end fails by 70.8 gray levels (darkest 29.2, the band starts at 100.0)"


def test_a_count_requirement_says_its_sentence_not_its_value():
    view = RequirementValue("camera_view", 1.014e304, "the camera cannot see 16 of 16 feature samples; change the "
                            "view direction")
    said = words.tightest([DOF, view], "camera_view")
    assert said == ("camera view of the feature fails: the camera cannot see 16 of 16 feature samples; change the "
                    "view direction")
    assert "1.014" not in said and "e+" not in said


def test_an_amount_that_contradicts_its_verdict_gives_way_to_the_sentence():
    # wide enough but placed wrong: the depth of field's near limit falls behind the nearest sample
    placed = RequirementValue("depth_of_field", 1.2, "in focus 495.0-530.0 mm, samples at 489.0-510.0 mm",
                              Amount(35.0, 21.0, " mm", False))
    assert words.fails(placed) == "depth of field fails: in focus 495.0-530.0 mm, samples at 489.0-510.0 mm"


@given(actual=st.floats(allow_nan=False), limit=st.floats(allow_nan=False), at_most=st.booleans(),
       value=st.floats(0.0, 1e308))
def test_no_number_is_said_with_an_exponent(actual, limit, at_most, value):
    r = RequirementValue("resolution", value, "a sentence", Amount(actual, limit, " um", at_most))
    said = words.tightest([r])
    assert "e+" not in said and "e-" not in said and "inf" not in said and len(said) < 200


def test_huge_and_unbounded_numbers_are_said_in_words():
    assert words.number(math.inf, " mm") == "unlimited"
    assert words.number(1e300, " W") == "over 1,000,000 W"
    assert words.number(-1e300, " W") == "below -1,000,000 W"


@pytest.mark.parametrize("shots, covered, features, said", [
    (1, 1, 1, "1 shot covers 1 of 1 feature"),
    (1, 2, 2, "1 shot covers 2 of 2 features"),
    (2, 3, 4, "2 shots cover 3 of 4 features"),
    (0, 0, 1, "no shot covers the 1 feature"),
    (0, 0, 3, "no shot covers any of the 3 features"),
])
def test_counts_have_their_grammar(shots, covered, features, said):
    assert words.covering(shots, covered, features) == said


def test_every_requirement_has_a_label():
    from cell.planning.requirements import REGISTRY
    assert {r.name for r in REGISTRY} <= set(words.LABELS)
    assert all("_" not in label for label in words.LABELS.values())


def test_plan_json_keeps_its_requirement_keys_and_values():
    from cell.planning.plan import requirements_json
    assert requirements_json([DOF]) == [{"name": "depth_of_field", "value": 1.0, "met": True,
                                         "detail": "in focus 489.5-510.5 mm ..."}]


def test_a_collision_is_said_as_its_hint_says_it_never_as_a_failing_requirement():
    """A `collision` binding (the optics held: whole_part.cleared) reads as the bodies first; any
    other binding keeps its requirement's label."""
    hit = "collision: fixture and wrist_3 touch or overlap, less than the padding 10 mm"
    assert words.uncovered("shank", "collision", hit) == f"feature shank: no shot covers it: {hit}"
    assert words.uncovered("end_face", "camera_view", "the camera cannot see 16 of 16 feature samples") == \
        "feature end_face: no shot covers it: camera view of the feature fails: the camera cannot see 16 of 16 " \
        "feature samples"
    plan = SimpleNamespace(features=(), binding="collision", hint=hit, requirements=[DOF])
    assert words.reason(plan) == f"{hit}; {words.OPTICS_MET}"
    assert words.OPTICS_MET == "the lighting, exposure and view meet every requirement"
