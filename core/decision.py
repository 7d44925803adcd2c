"""PASS / REJECT / ERROR from the recipe's rules.

A part passes only if every defect passes every rule that covers it AND every measurement
those rules need is available. A missing measurement is an ERROR (the part could not be
inspected), which rejects the part like a REJECT does but is counted apart.
"""
from __future__ import annotations

import operator

from core.recipe.schema import DecisionSection, Rule
from core.types import DefectMeasurement, Status, Verdict

_OPS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}


def rule_applies(rule: Rule, class_name: str) -> bool:
    return rule.class_ in ("any", class_name)


def judge_defect(m: DefectMeasurement, decision: DecisionSection) -> tuple[Status, list[str]]:
    """Status and reasons for one defect."""
    label = f"{m.detection.class_name} ({m.detection.confidence:.2f})"
    rules = [r for r in decision.rules if rule_applies(r, m.detection.class_name)]
    if not rules:
        if decision.reject_unruled_defects:
            return Status.REJECT, [f"{label}: no rule covers this class and unruled defects are rejected"]
        return Status.PASS, []
    status, reasons = Status.PASS, []
    for rule in rules:
        value = m.quantity(rule.quantity)
        if value is None:
            status = Status.ERROR
            why = m.note or f"{rule.quantity} unavailable"
            reasons.append(f"{label}: rule '{rule.describe()}' needs {rule.quantity}, {why}")
        elif _OPS[rule.op](value, rule.threshold):
            if status is not Status.ERROR:
                status = Status.REJECT
            reasons.append(f"{label}: {rule.quantity} {value:.2f} {rule.op} {rule.threshold:g} (rule '{rule.describe()}')")
    return status, reasons


def decide(measurements: list[DefectMeasurement], decision: DecisionSection) -> tuple[Verdict, list[tuple[Status, list[str]]]]:
    """The part's verdict and each defect's (status, reasons)."""
    per_defect = [judge_defect(m, decision) for m in measurements]
    statuses = {s for s, _ in per_defect}
    if Status.ERROR in statuses:
        overall = Status.ERROR
    elif Status.REJECT in statuses:
        overall = Status.REJECT
    else:
        overall = Status.PASS
    reasons = [r for _, rs in per_defect for r in rs]
    return Verdict(overall, reasons), per_defect


def error_verdict(message: str) -> Verdict:
    return Verdict(Status.ERROR, [message])
