"""Training YOLOv8n from scratch on a YOLO-layout dataset (the seed's recipe by default).

No pretrained checkpoint can be fetched here, so the model is built from the
architecture file that ships inside ultralytics (``yolov8n.yaml``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path


@dataclass
class TrainSettings:
    epochs: int = 100
    patience: int = 20
    imgsz: int = 200
    batch: int = 16
    device: str = "auto"
    workers: int = 2
    seed: int = 0
    # The seed's augmentation: flips both ways, HSV jitter, rotation, scale, mosaic, MixUp, copy-paste.
    fliplr: float = 0.5
    flipud: float = 0.5
    hsv_h: float = 0.015
    hsv_s: float = 0.7
    hsv_v: float = 0.4
    degrees: float = 10.0
    scale: float = 0.5
    mosaic: float = 1.0
    mixup: float = 0.1
    copy_paste: float = 0.1
    close_mosaic: int = 10
    # The schedule. ultralytics' "auto" optimiser picks its own learning rate and ignores lr0;
    # a low-rate fine-tune of an earlier stage names the optimiser to set lr0.
    optimizer: str = "auto"
    lr0: float = 0.01
    lrf: float = 0.01
    warmup_epochs: float = 3.0
    save_period: int = -1


def resolve_device(device: str) -> str:
    if device != "auto":
        return device
    import torch

    return "0" if torch.cuda.is_available() else "cpu"


def last_checkpoint(out_dir: Path, name: str) -> Path:
    """Where the run ``name`` under ``out_dir`` keeps its latest weights, from which a training resumes."""
    return Path(out_dir) / name / "weights" / "last.pt"


def train_detector(data_yaml: Path, out_dir: Path, settings: TrainSettings, name: str = "yolov8n-neu",
                   init: Path | None = None) -> Path:
    """Train (or resume, when ``out_dir/name/weights/last.pt`` exists) and return the best weights' path.

    ``init`` starts a new run from weights of an earlier run with a fresh learning-rate schedule:
    how a CPU-bound training is continued in stages once its first schedule has run out.
    """
    from ultralytics import YOLO

    last = last_checkpoint(out_dir, name)
    if last.exists():
        model = YOLO(str(last))
        model.train(resume=True)
    else:
        model = YOLO(str(init) if init is not None else "yolov8n.yaml")
        params = asdict(settings)
        params["device"] = resolve_device(settings.device)
        model.train(
            data=str(Path(data_yaml).resolve()),
            project=str(Path(out_dir).resolve()),
            name=name,
            exist_ok=True,
            # ultralytics loads no weights at all with pretrained=False, not even those of ``init``
            pretrained=init is not None,
            amp=False,
            plots=True,
            **params,
        )
    return last.with_name("best.pt")
