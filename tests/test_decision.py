from __future__ import annotations

from dataclasses import replace

import pytest

from core.decision import decide, holds_at_the_surface, judge_defect, unruled_classes
from core.recipe.schema import DecisionSection, Rule
from core.types import DefectMeasurement, Detection, Status, UncertaintyPart


def _m(cls="scratches", conf=0.8, distance=400.0, deviation=0.5, note=""):
    return DefectMeasurement(Detection(cls, conf, (0, 0, 10, 10)), distance, deviation, 0.9, 0.9, 100.0, note)


RULES = DecisionSection.model_validate({"rules": [
    {"class": "any", "quantity": "deviation_mm", "op": ">", "threshold": 1.0},
    {"class": "scratches", "quantity": "area_mm2", "op": ">=", "threshold": 500},
]})


def test_no_defect_passes():
    verdict, per = decide([], RULES)
    assert verdict.status is Status.PASS and verdict.reasons == [] and per == []


def test_shallow_defect_passes_deep_rejects_with_reason():
    assert decide([_m(deviation=0.9)], RULES)[0].status is Status.PASS
    verdict, per = decide([_m(deviation=0.9), _m(cls="patches", deviation=1.4)], RULES)
    assert verdict.status is Status.REJECT
    assert [s for s, _ in per] == [Status.PASS, Status.REJECT]
    assert "patches (0.80): deviation_mm 1.40 > 1 " in verdict.reasons[0]


def test_missing_measurement_is_an_error_not_a_pass():
    verdict, _ = decide([_m(deviation=None, note="deviation unavailable: 3 valid surface points")], RULES)
    assert verdict.status is Status.ERROR
    assert "needs deviation_mm" in verdict.reasons[0] and "3 valid surface points" in verdict.reasons[0]


@pytest.mark.parametrize("deviation, sigma", [
    (float("nan"), 0.1), (float("inf"), 0.1), (0.2, float("nan")), (0.2, float("inf")), (0.2, -0.1),
])
def test_a_value_that_is_not_a_number_is_an_error_not_a_pass(deviation, sigma):
    # every comparison with NaN is false, so without the check it would read as inside the limit
    m = replace(_m(deviation=deviation), deviation_sigma_mm=sigma)
    verdict, _ = decide([m], RULES)
    assert verdict.status is Status.ERROR, verdict
    assert "not a measurement to decide on" in verdict.reasons[0]


def test_error_wins_over_reject():
    verdict, _ = decide([_m(deviation=5.0), _m(cls="inclusion", deviation=None)], RULES)
    assert verdict.status is Status.ERROR and len(verdict.reasons) == 2


def test_class_specific_rule_only_for_its_class():
    big = dict(deviation=0.1)
    m = _m(**big)
    m.area_mm2 = 800.0
    assert decide([m], RULES)[0].status is Status.REJECT
    m.detection = Detection("patches", 0.8, (0, 0, 10, 10))
    assert decide([m], RULES)[0].status is Status.PASS


def test_the_classes_no_rule_covers_are_named_unless_they_are_rejected():
    classes = ["scratches", "inclusion", "patches"]
    assert unruled_classes(RULES, classes) == []  # a rule for any covers every class
    scratches_only = DecisionSection.model_validate({"rules": [RULES.rules[1].model_dump(by_alias=True)]})
    assert unruled_classes(scratches_only, classes) == ["inclusion", "patches"]
    assert unruled_classes(DecisionSection.model_validate({"rules": []}), classes) == classes
    rejecting = scratches_only.model_copy(update={"reject_unruled_defects": True})
    assert unruled_classes(rejecting, classes) == []


def test_unruled_defects_optionally_rejected():
    section = DecisionSection.model_validate({"rules": [], "reject_unruled_defects": True})
    assert decide([_m()], section)[0].status is Status.REJECT
    assert decide([_m()], DecisionSection())[0].status is Status.PASS


@pytest.mark.parametrize("found", [{"surface_elsewhere_mm": 712.0}, {"eyes_swapped": True}])
def test_a_plate_the_images_show_elsewhere_is_an_error_whatever_the_rules(found):
    # the map's values are gone with it, but a rule that needs none of them, or none at all, passed the part
    m = replace(_m(distance=None, deviation=None, note="deviation unavailable: ... the plate lies outside ..."), **found)
    confidence = DecisionSection.model_validate(
        {"rules": [{"class": "any", "quantity": "confidence", "op": ">=", "threshold": 0.9}]})
    for section in (DecisionSection(), confidence, RULES):
        verdict, ((status, reasons),) = decide([m], section)
        assert verdict.status is status is Status.ERROR and reasons == [f"scratches (0.80): {m.note}"]
    assert decide([_m(distance=None, deviation=None)], DecisionSection())[0].status is Status.PASS  # unruled


def test_confidence_rule():
    section = DecisionSection.model_validate({"rules": [{"class": "any", "quantity": "confidence", "op": ">=", "threshold": 0.5}]})
    assert decide([_m(conf=0.6)], section)[0].status is Status.REJECT
    assert decide([_m(conf=0.4)], section)[0].status is Status.PASS


def _u(cls="pit", deviation=1.2, sigma=0.1):
    m = _m(cls=cls, deviation=deviation)
    m.deviation_sigma_mm = sigma
    return m


def _section(uncertain="reject", op=">", threshold=1.0, k=2.0):
    return DecisionSection.model_validate({"uncertain": uncertain, "coverage_factor": k, "rules": [
        {"class": "any", "quantity": "deviation_mm", "op": op, "threshold": threshold}]})


# (op, value, sigma, expected with uncertain: reject): the guard band is 2 sigma either side of the limit 1.0
GUARD_BAND_TABLE = [
    (">", 1.25, 0.1, Status.REJECT),  # beyond by more than the band: non-conformance proven
    (">", 1.15, 0.1, "undecided"),
    (">", 0.95, 0.1, "undecided"),
    (">", 0.75, 0.1, Status.PASS),  # inside by more than the band: conformance proven
    (">", 1.50, 0.4, "undecided"),  # the same value is undecided with a larger uncertainty
    (">=", 1.20, 0.1, Status.REJECT),  # exactly the band away: >= holds at the band's end
    (">", 1.20, 0.1, "undecided"),  # ... > does not
    ("<", 0.75, 0.1, Status.REJECT),  # "shallower than 1 mm" rules mirror it
    ("<", 1.25, 0.1, Status.PASS),
    ("<", 0.95, 0.1, "undecided"),
    ("<=", 0.80, 0.1, Status.REJECT),
    (">", 1.05, 0.0, Status.REJECT),  # no uncertainty: the plain comparison
    (">", 1.00, 0.0, Status.PASS),
]


@pytest.mark.parametrize("op,value,sigma,expected", GUARD_BAND_TABLE)
def test_guard_band_table(op, value, sigma, expected):
    status, reasons = judge_defect(_u(deviation=value, sigma=sigma), _section(op=op))
    if expected == "undecided":
        assert status is Status.REJECT and "conformance not proven" in reasons[0] and "uncertain: reject" in reasons[0]
        assert judge_defect(_u(deviation=value, sigma=sigma), _section("pass", op))[0] is Status.PASS
        assert judge_defect(_u(deviation=value, sigma=sigma), _section("flag", op))[0] is Status.FLAG
    else:
        assert status is expected
        for uncertain in ("pass", "flag"):  # proven outcomes do not depend on the uncertain choice
            assert judge_defect(_u(deviation=value, sigma=sigma), _section(uncertain, op))[0] is expected


def test_an_undecided_pass_keeps_its_reason_and_shows_the_band():
    verdict, _ = decide([_u(deviation=0.95, sigma=0.1)], _section("pass"))
    assert verdict.status is Status.PASS
    assert verdict.reasons == ["pit (0.80): deviation_mm 0.95 ± 0.20 straddles 1, conformance not proven "
                               "(rule 'any deviation_mm > 1', uncertain: pass)"]


BUDGET = (UncertaintyPart("surface", "placing the surface around the box", 0.01),
          UncertaintyPart("moved", "the region moved 12 px down, which reads 1.60 mm: the box may not hold its defect",
                          0.03))


def test_an_undecided_rule_names_what_its_uncertainty_is_mostly_made_of():
    m = replace(_u(deviation=0.95, sigma=0.2), uncertainty_parts=BUDGET)
    status, reasons = judge_defect(m, _section())
    assert status is Status.REJECT
    assert reasons == ["pit (0.80): deviation_mm 0.95 ± 0.40 straddles 1, conformance not proven (rule 'any "
                       "deviation_mm > 1', uncertain: reject); its uncertainty: 75 % from the region moved 12 px down, "
                       "which reads 1.60 mm: the box may not hold its defect"]


def test_a_proven_outcome_or_a_rule_on_another_quantity_says_nothing_of_the_deviation_s_uncertainty():
    m = replace(_u(deviation=1.5, sigma=0.1), uncertainty_parts=BUDGET)
    assert "its uncertainty" not in judge_defect(m, _section())[1][0]
    m = replace(_u(deviation=0.95, sigma=0.2), uncertainty_parts=BUDGET, distance_sigma_mm=0.1)
    distance_rule = DecisionSection.model_validate({"rules": [
        {"class": "any", "quantity": "distance_mm", "op": ">", "threshold": 400.1}]})
    status, reasons = judge_defect(m, distance_rule)
    assert "conformance not proven" in reasons[0] and "its uncertainty" not in reasons[0]


def test_coverage_factor_sets_the_band():
    assert judge_defect(_u(deviation=1.15, sigma=0.1), _section(k=1.0))[0] is Status.REJECT
    assert judge_defect(_u(deviation=1.15, sigma=0.1), _section("pass", k=2.0))[0] is Status.PASS


def test_precedence_error_reject_flag_pass():
    flagged = _u(deviation=1.05, sigma=0.1)
    section = _section("flag")
    assert decide([flagged, _u(deviation=0.2, sigma=0.1)], section)[0].status is Status.FLAG
    assert decide([flagged, _u(deviation=2.0, sigma=0.1)], section)[0].status is Status.REJECT
    assert decide([flagged, _m(deviation=None)], section)[0].status is Status.ERROR
    assert Status.FLAG.rejects  # a part to check is diverted, never passed


def test_area_and_confidence_uncertainty():
    m = _u(deviation=0.1, sigma=0.05)
    m.distance_sigma_mm = 2.0  # 0.5 % of 400 mm: the area (~Z^2) is known to 1 %
    assert m.uncertainty("area_mm2") == pytest.approx(1.0)
    assert m.uncertainty("confidence") == 0.0
    m.distance_sigma_mm = None
    assert m.uncertainty("area_mm2") is None


@pytest.mark.parametrize("quantity, op, threshold, wrong_way_round", [
    ("deviation_mm", ">", 1.0, False), ("deviation_mm", "<", -1.0, False),
    ("deviation_mm", "<", 1.0, True), ("deviation_mm", "<=", 0.5, True), ("deviation_mm", ">", -1.0, True),
    ("deviation_mm", ">=", 0.0, True), ("deviation_mm", ">", 0.0, False), ("deviation_mm", "<", 0.0, False),
    ("distance_mm", "<", 300.0, False), ("confidence", "<", 0.5, False),
])
def test_a_deviation_rule_that_holds_at_the_surface_is_told(quantity, op, threshold, wrong_way_round):
    rule = Rule(**{"class": "any", "quantity": quantity, "op": op, "threshold": threshold})
    assert holds_at_the_surface(rule) is wrong_way_round

