"""Drawing a part's defects on its left image, for the store and the operator."""
from __future__ import annotations

import cv2
import numpy as np

from core.types import DefectMeasurement, PartResult, Status

_COLOURS = {Status.PASS: (60, 180, 60), Status.REJECT: (40, 40, 230), Status.ERROR: (0, 165, 255),
            Status.FLAG: (216, 91, 142)}


def _fmt(value: float | None, unit: str) -> str:
    return "n/a" if value is None else f"{value:.1f}{unit}"


def annotate(image: np.ndarray, part: PartResult, defect_status: list[Status]) -> np.ndarray:
    out = image.copy()
    for m, status in zip(part.measurements, defect_status):
        _draw_defect(out, m, _COLOURS[status])
    banner = f"{part.part_id} {part.verdict.status.value}"
    cv2.rectangle(out, (0, 0), (out.shape[1], 22), (0, 0, 0), -1)
    cv2.putText(out, banner, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.55, _COLOURS[part.verdict.status], 1, cv2.LINE_AA)
    return out


def _draw_defect(out: np.ndarray, m: DefectMeasurement, colour: tuple[int, int, int]) -> None:
    x0, y0, x1, y1 = (int(round(v)) for v in m.detection.box)
    cv2.rectangle(out, (x0, y0), (x1, y1), colour, 2)
    lines = [
        f"{m.detection.class_name} {m.detection.confidence:.2f}",
        f"Z {_fmt(m.distance_mm, 'mm')} dev {_fmt(m.deviation_mm, 'mm')}",
    ]
    y = max(y0 - 18, 30)
    for i, text in enumerate(lines):
        org = (x0, y + 13 * i)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
