"""Master parts: plates whose verdicts are known, inspected before the line's first part.

A detector that finds nothing passes every part without a word: weights that score too low, a confidence set
too high, an image shrunk below what the model can see, the wrong model. Nothing on the line tells such a
failure from a run of good plates. A plant's answer is the master part: a plate with known defects put
through the machine at the start, which must come out rejected. ``verify.path`` names a recording of such
parts with each defect's true depth in its labels; the engine inspects them as parts (detector, stereo,
depth and the recipe's rules) before the first plate, and a defective one that passes, or defective ones
none of which could be measured, stop the run before it starts (``core.engine.run``).

A part is known defective when a labelled defect lies beyond one of the recipe's depth limits by CLEAR_CUT_MM
or more, and known good when every labelled defect lies inside every limit by as much; a part near a limit
is inspected and counted but decides nothing, since a measurement may prove neither side of it. Each such
defect must be rejected by a box of its own: a part rejected for another box (a sound patch read undecided, a
box the wrong model put anywhere) says nothing of whether the line finds that defect. And where a defect's box lies
more than a third of its size off it, the tally warns: depth read in such a box may prove a defect beyond its limit
inside it. A defective part rejected only because no rule could decide (``decision.uncertain``) is caught, but its
measurement did not prove the defect beyond its limit: the tally says so, with what its uncertainty was mostly made
of, since a master defect well beyond its limit that the line cannot prove so says the line's depth is marginal.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.boxes import MATCH_IOU, UNSAFE_SHIFT, box_iou, matched_placement
from core.decision import CLEAR_CUT_MM, NOT_PROVEN, rule_applies
from core.types import FrameError, Status, StereoFrame, Verdict
from drivers.sequence_folder import list_frames, read_labels

DEPTH_QUANTITIES = ("deviation_mm", "distance_mm")
REJECTING = (Status.REJECT, Status.FLAG, Status.ERROR)  # a defect's own outcomes that keep its part off the line


def known_verdict(labels: dict, decision) -> Status | None:
    """What a part's labels (``labels['defects']``, each with ``class`` and a true ``deviation_mm`` and
    ``distance_mm`` where known) call for under ``decision`` (a recipe's ``DecisionSection``), counting only
    its depth rules: REJECT where a defect lies CLEAR_CUT_MM or more beyond a limit, PASS where every defect
    lies that far inside every limit that applies to it, None where neither is clear (a defect near a limit,
    one whose truth lacks a quantity a rule needs, one only rules on other quantities cover). A defect no rule
    covers is REJECT where the decision rejects unruled defects."""
    calls = [_known(defect, decision) for defect in labels.get("defects", [])]
    if Status.REJECT in calls:
        return Status.REJECT
    return Status.PASS if all(call is Status.PASS for call in calls) else None


def beyond_a_limit(labels: dict, decision) -> list[dict]:
    """The labelled defects of ``labels`` that ``known_verdict`` rejects the part for, each of which the line must
    reject."""
    return [defect for defect in labels.get("defects", []) if _known(defect, decision) is Status.REJECT]


def _known(defect: dict, decision) -> Status | None:
    """``known_verdict`` of one labelled defect: REJECT, PASS (every rule on it clear of its limit, or none covers
    it) or None."""
    ruled = [r for r in decision.rules if rule_applies(r, defect["class"])]
    if not ruled:
        return Status.REJECT if decision.reject_unruled_defects else Status.PASS
    applying = [r for r in ruled if r.quantity in DEPTH_QUANTITIES]
    clear_pass = len(applying) == len(ruled)  # a confidence or area rule: the labels do not say how it decides
    for rule in applying:
        value = defect.get(rule.quantity)
        if value is None:
            clear_pass = False
            continue
        beyond = _beyond(value, rule.op, rule.threshold)
        if beyond >= CLEAR_CUT_MM:
            return Status.REJECT
        if beyond > -CLEAR_CUT_MM:
            clear_pass = False
    return Status.PASS if clear_pass else None


def missed_defects(defects: list[dict], boxes: list[tuple[tuple[float, float, float, float], Status]]) -> list[str]:
    """Of the labelled ``defects`` (``beyond_a_limit``), those no box of ``boxes`` (each box and its own outcome)
    that overlaps it by MATCH_IOU rejects, each as "class at (x0, y0)-(x1, y1)"."""
    iou = box_iou(np.array([d["box"] for d in defects], float).reshape(-1, 4),
                  np.array([found for found, _ in boxes], float).reshape(-1, 4))
    missed = []
    for defect, overlaps in zip(defects, iou):
        if not any(boxes[j][1] in REJECTING for j in np.flatnonzero(overlaps >= MATCH_IOU)):
            x0, y0, x1, y1 = (float(v) for v in defect["box"])
            missed.append(f"{defect['class']} at ({x0:.0f}, {y0:.0f})-({x1:.0f}, {y1:.0f})")
    return missed


def boxes_off(defects: list[dict], boxes: list[tuple[float, float, float, float]]) -> list[str]:
    """Of the labelled ``defects``, those whose box among ``boxes`` (matched by IoU, ``core.boxes.match_boxes``)
    lies more than UNSAFE_SHIFT of the defect's size off its centre, each as "class (0.38 of its size off)": depth
    read in such a box may prove a defect beyond its limit inside it (docs/depth-conditions.md, boxes that are
    off)."""
    placed = matched_placement([d["box"] for d in defects], boxes, MATCH_IOU)
    return [f"{defects[i]['class']} ({shift:.2f} of its size off)" for i, shift, _ in placed if shift > UNSAFE_SHIFT]


def _beyond(value: float, op: str, threshold: float) -> float:
    """How far ``value`` lies beyond the limit ``op threshold`` (a rule rejects ``value op threshold``): above
    0 where it is rejected, below where it is inside."""
    return value - threshold if op in (">", ">=") else threshold - value


@dataclass(frozen=True)
class MasterPart:
    """One master part: its frame, what its labels call for (None: near a limit), the verdict it got and that
    verdict's first reason, and its defects beyond a limit that no box of their own rejected (``missed_defects``;
    none counted where the part could not be inspected)."""

    frame_id: str
    known: Status | None
    got: Status
    why: str = ""
    missed: tuple[str, ...] = ()
    off: tuple[str, ...] = ()  # its labelled defects whose box lies more than a third off them (``boxes_off``)
    # rejected (or flagged) only by rules that could not decide: the first such reason, else ""
    undecided: str = ""

    @property
    def passed_defective(self) -> bool:
        """A known defective part passed, or a defect of it beyond a limit went unrejected while another box
        rejected the part: the line would pass a part with that defect alone."""
        return self.known is Status.REJECT and (self.got is Status.PASS or bool(self.missed))


@dataclass(frozen=True)
class Verification:
    """The master parts of ``folder`` and their verdicts."""

    folder: str
    parts: tuple[MasterPart, ...]

    @property
    def failed(self) -> bool:
        """A defective master part passed, or none of them was measured (all ERROR): then nothing showed that
        the detector finds a defect (a blind one's parts are ERROR too where their plate lies outside the
        working distance)."""
        return any(p.passed_defective for p in self.parts) or bool(self._defective) and not self._measured

    @property
    def _defective(self) -> list[MasterPart]:
        return [p for p in self.parts if p.known is Status.REJECT]

    @property
    def _measured(self) -> list[MasterPart]:
        return [p for p in self._defective if p.got in (Status.REJECT, Status.FLAG)]

    def _count(self, known: Status, got: tuple[Status, ...]) -> tuple[int, int]:
        of = [p for p in self.parts if p.known is known]
        return sum(p.got in got for p in of), len(of)

    def summary(self) -> str:
        """One line: how many master parts were inspected and how each kind came out."""
        caught, defective = self._count(Status.REJECT, (Status.REJECT, Status.FLAG, Status.ERROR))
        passed, good = self._count(Status.PASS, (Status.PASS,))
        errors = sum(p.got is Status.ERROR for p in self.parts)
        near = sum(p.known is None for p in self.parts)
        return (f"master parts {self.folder}: {len(self.parts)} inspected, {caught} of {defective} defective "
                f"ones rejected, {passed} of {good} good ones passed"
                + (f", {errors} could not be inspected (ERROR)" if errors else "")
                + (f", {near} near a limit (not counted)" if near else "")
                + self._undecided_note()
                + self._boxes_off_warning())

    def _undecided_note(self) -> str:
        """Of the defective master parts caught, those no rule proved beyond its limit (``MasterPart.undecided``),
        with the first one's reason, or ""."""
        undecided = [p for p in self._defective if p.undecided]
        if not undecided:
            return ""
        first = undecided[0]
        return (f"; {len(undecided)} of them only as undecided, not proven beyond the limit (frame {first.frame_id}: "
                f"{first.undecided})")

    def _boxes_off_warning(self) -> str:
        """The tally's closing warning of the boxes more than a third off their defects (``boxes_off``), or ""."""
        off = [f"{p.frame_id}'s {defect}" for p in self.parts for defect in p.off]
        if not off:
            return ""
        many = len(off) > 1
        shown = ", ".join(off[:3]) + (f" and {len(off) - 3} more" if len(off) > 3 else "")
        return (f"; warning: the detector's box{'es' if many else ''} on {shown} lie{'' if many else 's'} more than a "
                f"third off {'their defects' if many else 'its defect'}, where depth may prove a defect beyond its "
                f"limit inside it (docs/depth-conditions.md, boxes that are off): check the detector with inspect "
                f"eval detector-frames")

    def refusal(self) -> str:
        """Why the run does not start: the defective master parts that passed, or that none was measured."""
        passed = [p.frame_id for p in self.parts if p.passed_defective]
        if not passed:
            first = self._defective[0]
            said = first.why if first.why.startswith(f"frame {first.frame_id}") else \
                f"frame {first.frame_id}: {first.why}"
            return (f"none of the {len(self._defective)} defective master parts of {self.folder} could be inspected "
                    f"({said}): nothing shows that the line finds a defect; the run does not start")
        shown = ", ".join(passed[:5]) + (f" and {len(passed) - 5} more" if len(passed) > 5 else "")
        missed = [f"{p.frame_id}'s {m}" for p in self.parts if p.passed_defective and p.got is not Status.PASS
                  for m in p.missed]
        unboxed = (f"; {', '.join(missed[:3])}{' and more' if len(missed) > 3 else ''} rejected by no box of "
                   f"{'its' if len(missed) == 1 else 'their'} own") if missed else ""
        how = "got through (passed, or rejected only for another box)" if missed else "passed"
        return (f"{len(passed)} master part{'s' if len(passed) > 1 else ''} with a defect beyond a limit {how} "
                f"(frame{'s' if len(passed) > 1 else ''} {shown} of {self.folder}{unboxed}): the line would pass "
                f"such parts; the run does not start (check the detector's weights, confidence and image size, and "
                f"decision.uncertain)")


def only_undecided(verdict: Verdict) -> str:
    """The first reason of a part rejected or flagged only by rules that could not decide (every reason of its verdict
    one of theirs), else ""."""
    reasons = verdict.reasons
    if verdict.status not in (Status.REJECT, Status.FLAG) or not reasons or not all(NOT_PROVEN in r for r in reasons):
        return ""
    return reasons[0]


def known_verdicts(folder: Path, decision) -> dict[str, Status | None]:
    """``known_verdict`` of each frame of the labelled sequence ``folder``, by frame id (a frame without
    labels: None). ``SequenceError`` naming the file where labels cannot be read."""
    return {f.frame_id: None if f.labels is None else known_verdict(read_labels(f.labels), decision)
            for f in list_frames(folder)}


def verify(folder: Path, frames: Iterable[StereoFrame | FrameError],
           inspect: Callable[[StereoFrame | FrameError], tuple[Verdict, list[tuple[tuple[float, float, float, float],
                                                                                  Status]]]],
           decision) -> Verification:
    """The master parts of the labelled sequence ``folder``, its ``frames`` (as its camera delivers them) each
    ``inspect``-ed to its verdict and each box's own outcome, and held against what its labels call for under
    ``decision``, defect by defect. ``SequenceError`` naming the file where a frame's labels cannot be read."""
    labels = {f.frame_id: None if f.labels is None else read_labels(f.labels) for f in list_frames(folder)}
    parts = []
    for item in frames:
        verdict, boxes = inspect(item)
        said = labels.get(item.frame_id)
        known = None if said is None else known_verdict(said, decision)
        # a part that could not be inspected (no box measured) counts as such, not as one whose defects were missed
        inspected = verdict.status is not Status.ERROR or bool(boxes)
        missed = tuple(missed_defects(beyond_a_limit(said, decision), boxes)) \
            if known is Status.REJECT and inspected and verdict.status is not Status.PASS else ()
        off = tuple(boxes_off(said.get("defects", []), [found for found, _ in boxes])) if said else ()
        parts.append(MasterPart(item.frame_id, known, verdict.status, verdict.reasons[0] if verdict.reasons else "",
                                missed, off, only_undecided(verdict)))
    return Verification(str(folder), tuple(parts))
