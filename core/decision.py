"""PASS / REJECT / FLAG / ERROR from the recipe's rules, with guard bands (ISO 14253-1).

A rule ``quantity op threshold`` names when a defect is out of tolerance. Every measurement comes
with a standard uncertainty u; the guard band is ``coverage_factor * u`` (2u by default, about 95 %
for a normal error). A rule's outcome is

- REJECT when the measurement is beyond the limit by more than the band (non-conformance proven),
- PASS when it is inside by more than the band (conformance proven),
- otherwise undecided, resolved by the recipe's ``uncertain``: reject (the default), pass, or flag
  (a FLAG part is diverted for a manual check), always with the reason recorded.

A part passes only if every defect passes every rule that covers it AND every measurement those
rules need is available. A missing measurement is an ERROR (the part could not be inspected), which
rejects the part like a REJECT does but is counted apart; so is a defect whose images show the plate
outside the working distance or the camera's eyes swapped, whatever rules cover it. Precedence: ERROR,
REJECT, FLAG, PASS.
"""
from __future__ import annotations

import math
import operator

from core import uncertainty_budget
from core.recipe.schema import DecisionSection, Rule
from core.types import DefectMeasurement, Status, Verdict

# a defect whose true value lies at least this far from every limit is clear-cut: the evaluations and the
# master parts (core.verification) hold a measurement to the right side of such a limit only
CLEAR_CUT_MM = 0.3

_OPS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}
_PRECEDENCE = (Status.ERROR, Status.REJECT, Status.FLAG, Status.PASS)
_UNCERTAIN = {"reject": Status.REJECT, "pass": Status.PASS, "flag": Status.FLAG}


def rule_applies(rule: Rule, class_name: str) -> bool:
    return rule.class_ in ("any", class_name)


def unruled_classes(decision: DecisionSection, classes: list[str]) -> list[str]:
    """Those of ``classes`` that no rule covers and that therefore pass whatever is measured (none where
    ``reject_unruled_defects`` rejects them)."""
    if decision.reject_unruled_defects:
        return []
    return [c for c in classes if not any(rule_applies(r, c) for r in decision.rules)]


def holds_at_the_surface(rule: Rule) -> bool:
    """A ``deviation_mm`` rule that holds for a deviation of 0: it rejects a defect level with the surface and
    passes every defect beyond its threshold the other way (``deviation_mm < 1`` passes all deeper than 1 mm),
    which is an operator written the wrong way round."""
    return rule.quantity == "deviation_mm" and _OPS[rule.op](0.0, rule.threshold)


def conformance(value: float, band: float, op: str, threshold: float) -> str:
    """``beyond`` (the rule's condition holds even at the far end of the band), ``inside`` (it fails
    even at the near end) or ``undecided``."""
    test = _OPS[op]
    toward_reject = -band if op in (">", ">=") else band  # the end of the band that is least out of tolerance
    if test(value + toward_reject, threshold):
        return "beyond"
    if not test(value - toward_reject, threshold):
        return "inside"
    return "undecided"


NOT_PROVEN = "conformance not proven"  # in the reason of a rule that could not decide


def judge_defect(m: DefectMeasurement, decision: DecisionSection) -> tuple[Status, list[str]]:
    """Status and reasons for one defect."""
    label = f"{m.detection.class_name} ({m.detection.confidence:.2f})"
    if m.surface_elsewhere_mm is not None or m.eyes_swapped:
        # the images show the plate where the recipe does not expect it: no rule may pass the part, whether it
        # needs depth or not (a confidence rule, a class no rule covers)
        return Status.ERROR, [f"{label}: {m.note}"]
    rules = [r for r in decision.rules if rule_applies(r, m.detection.class_name)]
    if not rules:
        if decision.reject_unruled_defects:
            return Status.REJECT, [f"{label}: no rule covers this class and unruled defects are rejected"]
        return Status.PASS, []
    outcomes, reasons = [], []
    for rule in rules:
        value = m.quantity(rule.quantity)
        if value is None:
            outcomes.append(Status.ERROR)
            why = m.note or f"{rule.quantity} unavailable"
            reasons.append(f"{label}: rule '{rule.describe()}' needs {rule.quantity}, {why}")
            continue
        sigma = m.uncertainty(rule.quantity) or 0.0
        if not (math.isfinite(value) and math.isfinite(sigma) and sigma >= 0):
            # every comparison with NaN is false: such a value would read as "inside" and pass
            outcomes.append(Status.ERROR)
            reasons.append(f"{label}: rule '{rule.describe()}' needs {rule.quantity}, measured as {value} "
                           f"± {sigma}: not a measurement to decide on")
            continue
        band = decision.coverage_factor * sigma
        shown = f"{rule.quantity} {value:.2f}" + (f" ± {band:.2f}" if band > 0 else "")
        state = conformance(value, band, rule.op, rule.threshold)
        if state == "beyond":
            outcomes.append(Status.REJECT)
            reasons.append(f"{label}: {shown} {rule.op} {rule.threshold:g} (rule '{rule.describe()}')")
        elif state == "undecided":
            outcome = _UNCERTAIN[decision.uncertain]
            outcomes.append(outcome)
            # what the uncertainty is made of says what would let the rule decide (more light, better boxes)
            cause = uncertainty_budget.cause_clause(m.uncertainty_parts) if rule.quantity == "deviation_mm" else ""
            reasons.append(f"{label}: {shown} straddles {rule.threshold:g}, {NOT_PROVEN} "
                           f"(rule '{rule.describe()}', uncertain: {decision.uncertain})"
                           + (f"; {cause}" if cause else ""))
    return _worst(outcomes), reasons


def _worst(statuses) -> Status:
    present = set(statuses)
    return next((s for s in _PRECEDENCE if s in present), Status.PASS)


def decide(measurements: list[DefectMeasurement], decision: DecisionSection) -> tuple[Verdict, list[tuple[Status, list[str]]]]:
    """The part's verdict and each defect's (status, reasons)."""
    per_defect = [judge_defect(m, decision) for m in measurements]
    reasons = [r for _, rs in per_defect for r in rs]
    return Verdict(_worst(s for s, _ in per_defect), reasons), per_defect


def error_verdict(message: str) -> Verdict:
    return Verdict(Status.ERROR, [message])
