"""The ``yolov8`` detector: ultralytics YOLO with optional sliced inference."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from core.devices import cuda_problem
from core.settings_model import Settings
from core.types import Detection
from plugins.yolov8 import tiling

# The NEU-DET model trained by `inspect train detector`, committed with its model card.
DEFAULT_WEIGHTS = Path(__file__).resolve().parents[2] / "models" / "yolov8n-neu-det.pt"
# A whole frame larger than this is shrunk to it where imgsz is null: fed a 2K frame's 2208 px, the committed model
# found half the defects it finds at 960 and boxed sound plate ten times as often (models/README.md, the scale it
# expects).
WHOLE_FRAME_MAX_IMGSZ = 960


class YoloSettings(Settings):
    weights: str | None = Field(None, description="set from the recipe's detector.weights")
    confidence: float = Field(0.25, ge=0.0, le=1.0)
    iou: float = Field(0.5, gt=0.0, le=1.0)
    imgsz: int | None = Field(224, ge=32, le=4096, description="network input size (per tile when tiling); null = "
                              "the image's own size (a tile's edge, or the whole frame's long side up to "
                              f"{WHOLE_FRAME_MAX_IMGSZ} px, beyond which the frame is shrunk to it)")
    tile_size: int | None = Field(224, ge=32, description="tile edge in frame pixels; null = whole frame")
    tile_overlap: float = Field(0.25, ge=0.0, lt=0.9)
    # NEU-DET boxes whole images of texture-like classes (pitted surface, crazing), so on a tile of
    # plain rolled steel the model may answer "this whole tile is pitted": a box as large as the
    # tile locates nothing. Tiled mode drops boxes covering this share of their tile both ways.
    drop_full_tile: float | None = Field(0.95, gt=0.0, le=1.0)
    device: str = "auto"
    max_det: int = Field(100, ge=1)
    # Checkpoints are pickles. By default they are read with torch's weights_only loader against the
    # classes a YOLO checkpoint is made of, so a file that would run code is refused; true reads any
    # pickle in full, which runs whatever the file holds: only for a file you made yourself.
    trust_pickle: bool = False

    @field_validator("device", mode="before")
    @classmethod
    def _a_device(cls, value: object) -> object:
        """Any other name failed every part's detection ("Invalid CUDA 'device=...' requested")."""
        if isinstance(value, int) and not isinstance(value, bool):  # ultralytics' `device: 0`
            value = str(value)
        if not isinstance(value, str) or re.fullmatch(r"auto|cpu|mps|cuda(:\d+)?|\d+(,\d+)*", value) is None:
            raise ValueError(f"{value!r}: one of auto, cpu, cuda, cuda:N (or ultralytics' N, N,M and mps)")
        return value


def whole_frame_imgsz(width: int, height: int) -> int:
    """The network's input for a whole ``width`` x ``height`` frame where ``imgsz`` is null: its long side, at
    most WHOLE_FRAME_MAX_IMGSZ."""
    return min(max(width, height), WHOLE_FRAME_MAX_IMGSZ)


class DetectionLimit(RuntimeError):
    """An image gave as many boxes as ``max_det``, where the network stops: the list may be cut short."""


def _without_full_tile(part: tuple[np.ndarray, np.ndarray, np.ndarray], limit: float):
    boxes, scores, classes = part
    keep = ~(((boxes[:, 2] - boxes[:, 0]) >= limit) & ((boxes[:, 3] - boxes[:, 1]) >= limit))
    return boxes[keep], scores[keep], classes[keep]


def import_yolo():
    """``ultralytics.YOLO``, imported without its process-wide side effects: on import it sets
    OMP_NUM_THREADS=1 (so torch, if not yet started, would use one thread) and turns OpenCV's
    threading off, which would slow every other stage (stereo above all)."""
    import cv2
    import torch

    torch_threads, cv_threads = torch.get_num_threads(), cv2.getNumThreads()
    from ultralytics import YOLO

    torch.set_num_threads(torch_threads)
    cv2.setNumThreads(cv_threads)
    return YOLO


SAFE_MODULES = ("torch.", "ultralytics.", "numpy.", "collections.", "pathlib.", "builtins.getattr")


TRUST_HINT = "set detector.settings.trust_pickle: true only for a file you made yourself"
# YOLO tasks whose predictions hold no axis-aligned boxes (segmentation and pose models give them beside their masks
# and keypoints, and serve as detectors)
UNBOXED_TASKS = {"classify": "gives one class per image, no boxes", "obb": "gives rotated boxes, which it does not read"}


def read_checkpoint(weights: Path, trust_pickle: bool = False, hint: str | None = TRUST_HINT) -> dict:
    """The checkpoint's contents, read without running code unless ``trust_pickle`` (module docstring of
    the settings). A missing, unreadable or refused file is a one-line error naming it; a refusal ends with
    ``hint``, the way to read it anyway where the caller has one."""
    import torch

    weights = Path(weights)
    if not weights.is_file():
        raise FileNotFoundError(f"{weights}: detector weights not found")
    with open(weights, "rb") as f:
        head = f.read(4)
    if not head.startswith((b"PK\x03\x04", b"\x80")):  # what torch.save writes: a zip archive, or a pickle
        what = "is empty" if not head else f"starts with {head!r}"
        raise ValueError(f"{weights}: not a YOLO checkpoint: a torch file is a zip archive or a pickle, and this "
                         f"one {what}")
    import_yolo()
    from ultralytics.nn.tasks import torch_safe_load

    try:
        ckpt, _ = torch_safe_load(str(weights), safe_only=not trust_pickle)
    except TypeError as exc:
        try:
            needed = torch.serialization.get_unsafe_globals_in_checkpoint(str(weights))
        except Exception:
            needed = []
        foreign = [g for g in needed if not g.startswith(SAFE_MODULES)]
        if foreign and not trust_pickle:
            raise ValueError(f"{weights}: refused: reading it would call {', '.join(foreign)}, which a YOLO checkpoint "
                             "never needs (a pickle can run code)" + (f"; {hint}" if hint else "")) from None
        raise ValueError(f"{weights}: not a loadable YOLO checkpoint: {_first_line(exc)}") from None
    except Exception as exc:
        raise ValueError(f"{weights}: not a loadable YOLO checkpoint: {_first_line(exc)}") from None
    model = (ckpt.get("ema") or ckpt.get("model")) if isinstance(ckpt, dict) else None
    if not isinstance(model, torch.nn.Module):
        raise ValueError(f"{weights}: not a YOLO checkpoint (no model inside)")
    from ultralytics.nn.tasks import guess_model_task

    task = guess_model_task(model)
    if task in UNBOXED_TASKS:  # loaded as a detector, every part's detection would fail on it
        raise ValueError(f"{weights}: the checkpoint of a YOLO {task} model, not a detector's: it {UNBOXED_TASKS[task]} "
                         f"(train a detector with `inspect train detector`)")
    # a model with one NaN tensor scores every box NaN, and NMS keeps none: no defect is found, every part passes
    broken = [name for name, tensor in model.state_dict().items()
              if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all())]
    if broken:
        hold = "holds" if len(broken) == 1 else "hold"
        raise ValueError(f"{weights}: {len(broken)} of the model's weight tensors {hold} NaN or infinite values (the "
                         f"first {broken[0]}): a training that diverged or a damaged file, whose model finds no defect "
                         f"at all")
    return ckpt


def checkpoint_class_names(weights: Path, trust_pickle: bool = False) -> list[str]:
    """The class names a checkpoint's model was trained on, in index order."""
    ckpt = read_checkpoint(weights, trust_pickle)
    names = getattr(ckpt.get("model") or ckpt.get("ema"), "names", None) or {}
    return [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)


def _first_line(exc: Exception) -> str:
    """The exception's first line of text, with its type where that line alone says nothing (a pickle's
    KeyError reads ``101``, the byte it did not expect)."""
    line = next((line for line in str(exc).splitlines() if line.strip()), "").strip()
    if not line or not any(c.isalpha() for c in line):
        return f"{exc.__class__.__name__}: {line}".rstrip(": ")
    return line


def load_model(weights: Path, trust_pickle: bool = False):
    """The YOLO model in ``weights``, read as ``read_checkpoint`` does; errors are one line naming the file."""
    read_checkpoint(weights, trust_pickle)  # refuses what the restricted loader refuses, with the reason
    YOLO = import_yolo()
    from ultralytics.nn import tasks

    restricted = tasks.SAFE_LOAD
    tasks.SAFE_LOAD = not trust_pickle  # the model's own load (and its construction) as restricted
    try:
        return YOLO(str(weights), task="detect")
    except Exception as exc:  # ultralytics words its own errors over several lines
        raise ValueError(f"{weights}: not a loadable YOLO checkpoint: {_first_line(exc)}") from exc
    finally:
        tasks.SAFE_LOAD = restricted


class YoloDetector:
    def __init__(self, settings: YoloSettings, device: str = "cpu"):
        self.settings = settings
        self.weights_path = Path(settings.weights) if settings.weights else DEFAULT_WEIGHTS
        self.model = load_model(self.weights_path, settings.trust_pickle)
        self.class_names = [self.model.names[i] for i in sorted(self.model.names)]
        if settings.device != "auto":
            device = settings.device
        if device.startswith("cuda") or device[0].isdigit():
            problem = cuda_problem()  # said before the first part, not as every part's ERROR
            if problem is not None:
                raise ValueError(f"device {device!r}: {problem}")
        self.device = device

    def _predict(self, images: list[np.ndarray], imgsz: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        import torch

        s = self.settings
        # ultralytics sets torch to cpu_count - 1 threads when it sets up on a CPU (1 on a 2-core
        # machine), which would halve every torch stage after it; keep the process's setting.
        threads = torch.get_num_threads()
        try:
            results = self.model.predict(
                images, imgsz=imgsz, conf=s.confidence, iou=s.iou, device=self.device, verbose=False, max_det=s.max_det
            )
        finally:
            torch.set_num_threads(threads)
        out = []
        for r in results:
            b = r.boxes
            if len(b) >= s.max_det:
                # the network stops at max_det boxes, the most confident first: a defect beyond them is not
                # reported, and a part whose inspection is not whole must not pass
                raise DetectionLimit(f"the detector reached its max_det of {s.max_det} boxes in one image: more may "
                                     f"have been left out (raise detector.settings.max_det)")
            out.append((b.xyxy.cpu().numpy(), b.conf.cpu().numpy(), b.cls.cpu().numpy().astype(int)))
        return out

    def warm_up(self) -> None:
        """The model's first prediction sets ultralytics' predictor up (seconds on a CPU): before the first part."""
        self.detect(np.zeros((64, 64, 3), dtype=np.uint8))

    def detect(self, image: np.ndarray) -> list[Detection]:
        s = self.settings
        h, w = image.shape[:2]
        if s.tile_size is None or (w <= s.tile_size and h <= s.tile_size):
            boxes, scores, classes = self._predict([image], s.imgsz or whole_frame_imgsz(w, h))[0]
        else:
            xs = tiling.tile_origins(w, s.tile_size, s.tile_overlap)
            ys = tiling.tile_origins(h, s.tile_size, s.tile_overlap)
            origins = [(x, y) for y in ys for x in xs]
            tiles = [image[y : y + s.tile_size, x : x + s.tile_size] for x, y in origins]
            parts = self._predict(tiles, s.imgsz or s.tile_size)
            if s.drop_full_tile is not None:
                parts = [_without_full_tile(p, s.tile_size * s.drop_full_tile) for p in parts]
            boxes = np.concatenate([p[0] + np.array([x, y, x, y], dtype=np.float32) for p, (x, y) in zip(parts, origins)])
            scores = np.concatenate([p[1] for p in parts])
            classes = np.concatenate([p[2] for p in parts])
            if len(boxes):
                keep = tiling.nms(boxes, scores, classes, s.iou)
                boxes, scores, classes = boxes[keep], scores[keep], classes[keep]
                boxes, scores, classes = tiling.merge_cut_boxes(
                    boxes, scores, classes,
                    tiling.interior_cuts(xs, s.tile_size, w), tiling.interior_cuts(ys, s.tile_size, h),
                    max_size=1.5 * s.tile_size,
                )
        return [
            Detection(self.class_names[int(c)], float(sc), tuple(float(v) for v in bx))
            for bx, sc, c in sorted(zip(boxes, scores, classes), key=lambda t: -t[1])
        ]
