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


def _split_images(source) -> list[Path]:
    """The image files of a split as data.yaml gives it (resolved by ultralytics): folders, list files, or a
    list of either."""
    from ultralytics.data.utils import IMG_FORMATS

    images: list[Path] = []
    for entry in source if isinstance(source, (list, tuple)) else [source]:
        path = Path(entry)
        if path.is_dir():
            images += sorted(p for p in path.rglob("*") if p.suffix.lower().lstrip(".") in IMG_FORMATS)
        elif path.is_file() and path.suffix == ".txt":
            lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
            images += [(path.parent / line).resolve() if not Path(line).is_absolute() else Path(line) for line in lines]
    return images


def _label_line_problem(values: list[str], classes: int) -> str | None:
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        return f"{' '.join(values)!r} is not numbers"
    if len(numbers) != 5 and not (len(numbers) >= 7 and len(numbers) % 2 == 1):
        return f"{len(numbers)} numbers, expected 'class x y w h' (or a class and polygon points)"
    cls = numbers[0]
    if not (cls.is_integer() and 0 <= cls < classes):
        return f"class {values[0]}, but the dataset has classes 0-{classes - 1}"
    if not all(0.0 <= v <= 1.0 for v in numbers[1:]):
        return f"coordinates {' '.join(values[1:])}: each is a share of the image, 0 to 1"
    return None


def label_problem(data_yaml: Path, splits: tuple[str, ...]) -> str | None:
    """The first label line of the dataset's ``splits`` that ultralytics drops with its image (left out of
    training or of the scores, said only in its scan log), naming the file and line, or None."""
    from ultralytics.data.utils import check_det_dataset

    return _label_problem(check_det_dataset(str(data_yaml), autodownload=False), splits)


def _label_problem(info: dict, splits: tuple[str, ...]) -> str | None:
    """``label_problem`` of a dataset as ultralytics' ``check_det_dataset`` resolved it."""
    from ultralytics.data.utils import img2label_paths

    problems = []
    for split in splits:
        for label in img2label_paths([str(p) for p in _split_images(info[split])]):
            path = Path(label)
            if not path.is_file():
                continue  # an image without labels is a background image
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                why = _label_line_problem(line.split(), int(info["nc"])) if line.strip() else None
                if why is not None:
                    problems.append(f"{path}: line {number}: {why}")
                    break
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more label files)" if len(problems) > 1 else ""
    return problems[0] + more + "; ultralytics would leave such images out"


def dataset_problem(data_yaml: Path, split: str, model_names: list[str]) -> str | None:
    """Why scoring a model of ``model_names`` on the dataset's ``split`` would say nothing of it, naming the file,
    or None: the dataset's classes are not the model's in its order (each score would be another class's), or
    a label line ultralytics drops (``label_problem``)."""
    from ultralytics.data.utils import check_det_dataset

    info = check_det_dataset(str(data_yaml), autodownload=False)
    names = info["names"]
    names = [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)
    if names != list(model_names):
        return (f"{data_yaml}: names {names} are not the model's classes {list(model_names)}: each score would be "
                f"another class's (label the dataset with the model's classes, in its order)")
    return _label_problem(info, (split,))


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
