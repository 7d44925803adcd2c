"""Detector evaluation on a YOLO-layout split: mAP, precision, recall, per-class AP, PR curve."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from drivers.file_writes import write_text

# The seed paper's YOLOv8n figures on NEU-DET (percent), shown beside ours.
SEED_METRICS = {
    "mAP50": 70.0,
    "mAP50-95": 33.8,
    "precision": 63.4,
    "recall": 63.5,
    "AP50": {
        "crazing": 44.2,
        "inclusion": 80.6,
        "patches": 89.6,
        "pitted_surface": 78.4,
        "rolled-in_scale": 45.9,
        "scratches": 81.3,
    },
}


def evaluate_detector(data_yaml: Path, weights: Path, split: str, out_dir: Path, imgsz: int = 224, device: str = "cpu",
                      iou: float = 0.5) -> dict:
    """``iou`` is the IoU above which non-maximum suppression merges two boxes of a class; it changes
    mAP by several points (ultralytics' own ``val`` uses 0.7, YOLOv5's 0.6), so it is recorded."""
    from plugins.yolov8.detector import load_model

    out_dir = Path(out_dir).resolve()
    model = load_model(weights)
    metrics = model.val(
        data=str(Path(data_yaml).resolve()), split=split, imgsz=imgsz, batch=16, device=device, iou=iou,
        project=str(out_dir), name="val", exist_ok=True, plots=True, verbose=False, workers=0,
    )
    box = metrics.box
    per_class = {model.names[int(c)]: round(float(box.ap50[i]) * 100, 1) for i, c in enumerate(box.ap_class_index)}
    result = {
        "weights": str(weights),
        "split": split,
        "imgsz": imgsz,
        "nms_iou": iou,
        "mAP50": round(float(box.map50) * 100, 1),
        "mAP50-95": round(float(box.map) * 100, 1),
        "precision": round(float(box.mp) * 100, 1),
        "recall": round(float(box.mr) * 100, 1),
        "AP50": per_class,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text(out_dir / "detector_metrics.json", json.dumps(result, indent=2))
    write_text(out_dir / "detector_metrics.md", metrics_markdown(result))
    pr = Path(metrics.save_dir) / "BoxPR_curve.png"
    if pr.exists():
        shutil.copy(pr, out_dir / "pr_curve.png")
    return result


def metrics_markdown(result: dict) -> str:
    rows = [("mAP@0.50", "mAP50"), ("mAP@0.50:0.95", "mAP50-95"), ("precision", "precision"), ("recall", "recall")]
    lines = [f"NMS IoU {result['nms_iou']:g}, {result['imgsz']} px, split {result['split']}", "",
             "| metric | ours | seed |", "|---|---|---|"]
    lines += [f"| {label} | {result[key]:.1f} | {SEED_METRICS[key]:.1f} |" for label, key in rows]
    for name, seed in SEED_METRICS["AP50"].items():
        ours = result["AP50"].get(name)
        lines.append(f"| AP@0.50 {name} | {'-' if ours is None else f'{ours:.1f}'} | {seed:.1f} |")
    return "\n".join(lines) + "\n"
