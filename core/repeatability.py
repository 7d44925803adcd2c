"""Repeatability: one part inspected several times as it stands under the camera, with no reference to compare.

What a quality engineer asks of a gauge before trusting its decisions on the line (a type 1 gauge study, here
without a reference value): does the same part get the same verdict every time, does the detector find each of its
defects every time, and do the measurements scatter no more than the uncertainty they are reported with allows. That
uncertainty holds more than the noise (the defect's wall, an uneven floor, a box that may be off), so an honest one is
at least the scatter of repeated captures; a scatter beyond it, at 99 % confidence, contradicts it, and with it every
guard band drawn from it. Only captures can tell this of a real camera, whose noise no evaluation set was rendered
with. ``inspect eval repeatability`` runs the line's stages on each capture; this module holds what is made of them.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from core.boxes import box_iou
from core.types import Status

SAME_DEFECT_IOU = 0.5  # a box of another capture overlapping a defect's this much is that defect again
SCATTER_Z = 2.3263  # the standard normal's upper 99 % point: the chi-square's quantile a scatter may not pass
MIN_MEASURED = 3  # captures measured that say anything of a scatter (two give one degree of freedom)
BOX_MOVED_PX = 0.5  # a box's centre scattering this much between captures may be what moved a reading
TREND_Z = 2.5758  # the standard normal's two-sided 99 % point: Student's t at it bounds a trend the noise may show
MIN_TREND = 5  # captures measured that tell a trend from the scatter about it (three degrees of freedom)
PROOFS = {Status.REJECT: "beyond", Status.PASS: "inside", Status.FLAG: "undecided", Status.ERROR: "unavailable"}


@dataclass(frozen=True)
class Reading:
    """One defect as one capture measured it. ``proof``: what its rules proved, an undecided measurement as FLAG
    (neither side of a limit proven), whatever the recipe's ``decision.uncertain`` then makes of it; ERROR where a
    rule's quantity was unavailable."""

    class_name: str
    box: tuple[float, float, float, float]
    deviation_mm: float | None
    deviation_sigma_mm: float | None
    distance_mm: float | None
    distance_sigma_mm: float | None
    proof: Status


@dataclass(frozen=True)
class Labelled:
    """A defect as the part's labels give it: its class, box and, where measured on the plate, its deviation."""

    class_name: str | None
    box: tuple[float, float, float, float]
    deviation_mm: float | None = None


@dataclass(frozen=True)
class Capture:
    """One inspection of the part: the frame, the part's verdict as the line decides it, each defect's reading, and
    why the capture could not be inspected where it could not."""

    frame_id: str
    verdict: Status
    readings: tuple[Reading, ...]
    error: str = ""


def chi2_upper_ratio(dof: int, z: float = SCATTER_Z) -> float:
    """The chi-square's upper quantile at ``z`` standard normal deviates over its ``dof`` degrees of freedom
    (Wilson-Hilferty): how far a sample variance may exceed the variance it is drawn with."""
    a = 2.0 / (9.0 * dof)
    return (1.0 - a + z * math.sqrt(a)) ** 3


def t_quantile(dof: int, z: float = TREND_Z) -> float:
    """Student's t quantile over ``dof`` degrees of freedom at the standard normal's quantile ``z`` (Cornish-Fisher's
    expansion in 1 / dof: within 3.5 % from three degrees of freedom, 0.2 % from eight)."""
    z3, z5, z7 = z ** 3, z ** 5, z ** 7
    return (z + (z3 + z) / (4 * dof) + (5 * z5 + 16 * z3 + 3 * z) / (96 * dof ** 2)
            + (3 * z7 + 19 * z5 + 17 * z3 - 15 * z) / (384 * dof ** 3))


@dataclass(frozen=True)
class Trend:
    """A quantity's straight-line change over the captures in the order taken (least squares over the captures'
    positions): ``change`` from the first capture to the last (mm) and its standard error, from the scatter about
    the line; ``n`` the captures that measured it."""

    n: int
    change: float
    se: float

    @property
    def t(self) -> float:
        return self.change / self.se if self.se > 0 else (math.inf if self.change else 0.0)

    @property
    def drifts(self) -> bool:
        """Whether the change stands beyond what the scatter about the line shows by chance at 99 % (two-sided),
        over MIN_TREND captures or more: the camera warming up, the part or the camera moving (a finding where it
        also exceeds the uncertainty reported, ``Defect.findings``)."""
        return self.n >= MIN_TREND and abs(self.t) > t_quantile(self.n - 2)

    @staticmethod
    def of(positions: list[int], values: list[float | None]) -> Trend | None:
        """The trend of ``values`` taken at ``positions`` (each capture's place in the order taken; None where the
        capture did not measure it); None where fewer than three were measured."""
        pairs = [(p, v) for p, v in zip(positions, values) if v is not None]
        if len(pairs) < 3:
            return None
        x = np.array([p for p, _ in pairs], dtype=np.float64)
        y = np.array([v for _, v in pairs], dtype=np.float64)
        x -= x.mean()
        sxx = float(x @ x)
        slope = float(x @ (y - y.mean())) / sxx
        residual = y - y.mean() - slope * x
        sd = math.sqrt(float(residual @ residual) / (len(pairs) - 2))
        span = float(x.max() - x.min())
        return Trend(len(pairs), slope * span, sd / math.sqrt(sxx) * span)


@dataclass(frozen=True)
class Spread:
    """A quantity's values over the captures that measured it: their mean and standard deviation (the
    repeatability), against ``sigma``, the root mean square of the standard uncertainties reported with them."""

    n: int
    mean: float
    sd: float
    sigma: float

    @property
    def ratio(self) -> float:
        """The scatter over the reported uncertainty: at most about 1 where that uncertainty is honest."""
        return self.sd / self.sigma if self.sigma > 0 else math.inf

    @property
    def contradicts(self) -> bool:
        """Whether the values scatter more than ``sigma`` allows at 99 % confidence (MIN_MEASURED of them at least)."""
        if self.n < MIN_MEASURED:
            return False
        return self.ratio ** 2 > chi2_upper_ratio(self.n - 1)

    @staticmethod
    def of(values: list[float | None], sigmas: list[float | None]) -> Spread | None:
        """The spread of the ``values`` given with their ``sigmas``; None where fewer than two were measured."""
        pairs = [(v, s) for v, s in zip(values, sigmas) if v is not None and s is not None]
        if len(pairs) < 2:
            return None
        x = np.array([v for v, _ in pairs], dtype=np.float64)
        s = np.array([s for _, s in pairs], dtype=np.float64)
        return Spread(len(pairs), float(x.mean()), float(x.std(ddof=1)), float(np.sqrt(np.mean(s * s))))


@dataclass(frozen=True)
class Defect:
    """One defect of the part as the captures saw it: ``box`` where the first capture that found it put it,
    ``readings`` (frame id, reading) of each capture that found it, ``captures`` how many there were."""

    box: tuple[float, float, float, float]
    readings: tuple[tuple[str, Reading], ...]
    captures: int
    label: str | None = None  # the class the part's labels give it, where they list it
    reference_mm: float | None = None  # the deviation they give it (measured on the plate), where they do
    taken: tuple[str, ...] = ()  # every capture's frame id in the order taken; the readings' order where not given

    @property
    def found(self) -> int:
        return len(self.readings)

    @property
    def classes(self) -> Counter:
        return Counter(r.class_name for _, r in self.readings)

    @property
    def proofs(self) -> Counter:
        return Counter(PROOFS[r.proof] for _, r in self.readings)

    @property
    def box_scatter_px(self) -> float | None:
        """How far the box's centre moves between the captures that found the defect: the root of the sum of its
        coordinates' variances (px); None where fewer than two found it."""
        if self.found < 2:
            return None
        centres = np.array([((r.box[0] + r.box[2]) / 2, (r.box[1] + r.box[3]) / 2) for _, r in self.readings])
        return float(np.sqrt(np.sum(centres.var(axis=0, ddof=1))))

    @property
    def deviation(self) -> Spread | None:
        return Spread.of(*self._measured("deviation"))

    @property
    def distance(self) -> Spread | None:
        return Spread.of(*self._measured("distance"))

    def trend(self, quantity: str) -> Trend | None:
        """The straight-line trend of ``quantity`` (``deviation`` or ``distance``) over the captures in the order
        taken, each reading at its capture's place in it, as ``Spread.of`` counts them (those with an uncertainty)."""
        place = {frame: i for i, frame in enumerate(self.taken)}
        positions = [place.get(frame, i) for i, (frame, _) in enumerate(self.readings)]
        values, sigmas = self._measured(quantity)
        return Trend.of(positions, [v if s is not None else None for v, s in zip(values, sigmas)])

    def _measured(self, quantity: str) -> tuple[list[float | None], list[float | None]]:
        """Each reading's ``quantity`` (``deviation`` or ``distance``) in mm and its standard uncertainty."""
        return ([getattr(r, f"{quantity}_mm") for _, r in self.readings],
                [getattr(r, f"{quantity}_sigma_mm") for _, r in self.readings])

    def name(self) -> str:
        x0, y0, x1, y1 = self.box
        what = self.label if self.label is not None else self.classes.most_common(1)[0][0]
        return f"{what} at ({x0:.0f}, {y0:.0f})-({x1:.0f}, {y1:.0f})" + (" (labelled)" if self.label else "")

    def findings(self) -> list[str]:
        """One line for each way this defect was not measured alike every time, scattered beyond its uncertainty,
        or drifted over the captures."""
        said = []
        if self.found < self.captures:
            said.append(f"{self.name()}: found in {self.found} of {self.captures} captures")
        proofs = self.proofs
        if proofs["beyond"] and proofs["inside"]:
            said.append(f"{self.name()}: proven beyond its limit in {proofs['beyond']} captures and inside it in "
                        f"{proofs['inside']}: the uncertainty does not hold")
        moved = self.box_scatter_px
        spreads = (("deviation", self.deviation), ("distance", self.distance))
        for what, spread in spreads:
            if spread is not None and spread.contradicts:
                why = "" if moved is None or moved < BOX_MOVED_PX else (
                    f"; the box's centre moved {moved:.1f} px between captures, and with it where the {what} is read "
                    f"(--boxes labels holds the boxes still)")
                said.append(f"{self.name()}: its {what} scatters {spread.sd:.3f} mm over {spread.n} captures, "
                            f"{spread.ratio:.1f}x the {spread.sigma:.3f} mm uncertainty it is reported with: more than "
                            f"that uncertainty allows at 99 % confidence{why}")
        for what, spread in spreads:
            trend = self.trend(what)
            # a drift within the uncertainty reported is covered by its guard band, however sure the trend
            if trend is not None and trend.drifts and spread is not None and abs(trend.change) > spread.sigma:
                said.append(f"{self.name()}: its {what} drifts {trend.change:+.3f} mm from the first capture to the "
                            f"last, more than its {spread.sigma:.3f} mm uncertainty ({trend.n} captures in the order "
                            f"taken, {abs(trend.t):.1f} standard errors of that trend): not the noise; the camera "
                            f"warming up, or the part or the camera moving")
        return said


def same_defects(captures: list[Capture], labelled: tuple[Labelled, ...] = ()) -> list[Defect]:
    """The captures' readings gathered into defects: each reading joins the defect, not yet read in its capture,
    whose first box it overlaps most, at SAME_DEFECT_IOU or more; a reading overlapping none starts a defect.
    ``labelled``: the part's defects as its labels list them, each a defect from the start (found in no capture if
    none reads it), in their order; then the others in the order the captures first found them."""
    boxes: list[tuple[float, float, float, float]] = [tuple(float(v) for v in d.box) for d in labelled]
    read: list[list[tuple[str, Reading]]] = [[] for _ in labelled]
    for capture in captures:
        taken: set[int] = set()
        for reading in capture.readings:
            best, at = None, SAME_DEFECT_IOU
            if boxes:
                iou = box_iou(np.array([reading.box], float), np.array(boxes, float))[0]
                for j in np.argsort(-iou, kind="stable"):
                    if iou[j] < at:
                        break
                    if int(j) not in taken:
                        best = int(j)
                        break
            if best is None:
                boxes.append(tuple(float(v) for v in reading.box))
                read.append([])
                best = len(boxes) - 1
            taken.add(best)
            read[best].append((capture.frame_id, reading))
    labels = list(labelled) + [Labelled(None, box) for box in boxes[len(labelled):]]
    taken = tuple(c.frame_id for c in captures)
    return [Defect(box, tuple(r), len(captures), label.class_name, label.deviation_mm, taken)
            for box, r, label in zip(boxes, read, labels)]


@dataclass(frozen=True)
class Study:
    """A part's captures and its defects across them (``same_defects``), those its labels list first."""

    part: str
    captures: tuple[Capture, ...]
    labelled: tuple[Labelled, ...] = ()

    @cached_property  # the findings, the table and the JSON each read them
    def defects(self) -> list[Defect]:
        return same_defects(list(self.captures), self.labelled)

    @property
    def verdicts(self) -> Counter:
        return Counter(c.verdict.value for c in self.captures)

    def findings(self) -> list[str]:
        """One line for each way the part was not inspected alike every time: its verdict, a defect found only
        sometimes, proven on both sides of a limit, scattering beyond its uncertainty, or drifting."""
        said = []
        if len(self.verdicts) > 1:
            counts = ", ".join(f"{v} {n}" for v, n in self.verdicts.most_common())
            said.append(f"the part's verdict differs between captures ({counts})")
        said += [f"capture {c.frame_id} could not be inspected: {c.error}" for c in self.captures if c.error]
        for defect in self.defects:
            said += defect.findings()
        return said

    def summary(self) -> str:
        """One line: the captures, the part's verdicts, and whether it was inspected alike every time."""
        counts = ", ".join(f"{v} {n}" for v, n in self.verdicts.most_common())
        found = self.findings()
        return (f"{self.part}: {len(self.captures)} captures, {counts}; {len(self.defects)} defects; "
                + ("inspected alike every time, every scatter within its uncertainty" if not found else
                   f"{len(found)} findings"))

    def rows(self) -> list[dict]:
        """One dict per defect, for the table and the JSON."""
        rows = []
        for d in self.defects:
            dev, dist = d.deviation, d.distance
            rows.append({
                "defect": d.name(), "box": list(d.box), "found": d.found, "captures": d.captures,
                "box_scatter_px": d.box_scatter_px,
                "classes": dict(d.classes), "proofs": dict(d.proofs),
                "deviation_mm": None if dev is None else {"n": dev.n, "mean": dev.mean, "sd": dev.sd,
                                                          "sigma": dev.sigma, "sd_over_sigma": dev.ratio},
                "reference_mm": d.reference_mm,
                "bias_mm": None if dev is None or d.reference_mm is None else dev.mean - d.reference_mm,
                "distance_mm": None if dist is None else {"n": dist.n, "mean": dist.mean, "sd": dist.sd,
                                                          "sigma": dist.sigma, "sd_over_sigma": dist.ratio},
                **{f"{what}_trend_mm": None if t is None else {"n": t.n, "change": t.change, "se": t.se,
                                                               "drifts": t.drifts}
                   for what, t in (("deviation", d.trend("deviation")), ("distance", d.trend("distance")))},
                "findings": d.findings(),
            })
        return rows

    def markdown(self) -> str:
        """The defects' table: found, deviation and distance (mean, scatter, reported uncertainty, their ratio),
        the deviation's mean against the labels' where they give one, what the rules proved."""
        lines = [f"### {self.part}", "",
                 f"{len(self.captures)} captures; the part's verdicts: "
                 + ", ".join(f"{v} {n}" for v, n in self.verdicts.most_common()), "",
                 "| defect | found | box's centre, sd px | deviation mm, mean | scatter (sd) | reported σ | sd ÷ σ | labelled | mean − labelled "
                 "| distance mm, mean | scatter (sd) | reported σ | sd ÷ σ | the rules proved |",
                 "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in self.rows():
            cells = [row["defect"], f"{row['found']} of {row['captures']}",
                     "n/a" if row["box_scatter_px"] is None else f"{row['box_scatter_px']:.1f}"]
            for key in ("deviation_mm", "distance_mm"):
                s = row[key]
                cells += ["n/a"] * 4 if s is None else [f"{s['mean']:+.3f}" if key == "deviation_mm" else
                                                         f"{s['mean']:.2f}", f"{s['sd']:.3f}", f"{s['sigma']:.3f}",
                                                         f"{s['sd_over_sigma']:.2f}"]
                if key == "deviation_mm":
                    cells += ["" if row["reference_mm"] is None else f"{row['reference_mm']:+.3f}",
                              "" if row["bias_mm"] is None else f"{row['bias_mm']:+.3f}"]
            cells.append(", ".join(f"{k} {n}" for k, n in sorted(row["proofs"].items())))
            lines.append("| " + " | ".join(cells) + " |")
        if not self.defects:
            lines.append("| (no defect labelled or found in any capture) |" + "  |" * 13)
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {"part": self.part, "captures": [c.frame_id for c in self.captures], "verdicts": dict(self.verdicts),
                "defects": self.rows(), "findings": self.findings()}
