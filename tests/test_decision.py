from __future__ import annotations

from core.decision import decide
from core.recipe.schema import DecisionSection
from core.types import DefectMeasurement, Detection, Status


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


def test_unruled_defects_optionally_rejected():
    section = DecisionSection.model_validate({"rules": [], "reject_unruled_defects": True})
    assert decide([_m()], section)[0].status is Status.REJECT
    assert decide([_m()], DecisionSection())[0].status is Status.PASS


def test_confidence_rule():
    section = DecisionSection.model_validate({"rules": [{"class": "any", "quantity": "confidence", "op": ">=", "threshold": 0.5}]})
    assert decide([_m(conf=0.6)], section)[0].status is Status.REJECT
    assert decide([_m(conf=0.4)], section)[0].status is Status.PASS
