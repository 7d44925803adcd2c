"""Untrained YOLOv8n checkpoints built from ultralytics' own architecture file (no download), for
tests that need real weights files without the committed model."""
from __future__ import annotations

import os
from pathlib import Path

import torch

NEU_NAMES = ["crazing", "inclusion", "patches", "pitted_surface", "rolled-in_scale", "scratches"]


def untrained_checkpoint(path: Path, nc: int = len(NEU_NAMES), seed: int | None = None,
                         vary_statistics: bool = False) -> Path:
    """Save a fresh YOLOv8n with the first ``nc`` NEU-DET class names to ``path``.

    ``vary_statistics`` fills the batch-norm buffers at random: a fresh model's are all equal, so two
    checkpoints would otherwise agree on them whatever the seed.
    """
    os.environ.setdefault("YOLO_OFFLINE", "1")
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    if seed is not None:
        torch.manual_seed(seed)
    model = YOLO("yolov8n.yaml")
    model.model = DetectionModel("yolov8n.yaml", nc=nc, verbose=False)
    model.model.names = dict(enumerate(NEU_NAMES[:nc]))
    if vary_statistics:
        with torch.no_grad():
            for buffer in model.model.buffers():
                if buffer.is_floating_point():
                    buffer.uniform_(0.5, 1.5)
    model.save(str(path))
    return path
