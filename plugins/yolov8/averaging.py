"""Averaging the weights of several runs of one architecture (a "model soup", Wortsman et al. 2022).

Our detector is trained in CPU-sized stages, each a fine-tune of the one before, so every stage's
weights lie in one basin of the loss; their mean is often better than any one of them, at no
inference cost. Which weights to average is chosen on the validation split, like ``best.pt`` itself.
"""
from __future__ import annotations

import io
from pathlib import Path

import torch

from drivers.file_writes import write_bytes


class AveragingError(ValueError):
    """The checkpoints cannot be averaged (unreadable file, other architecture)."""


def _load(path: Path) -> dict:
    """The checkpoint, read as the detector reads its weights: a pickle that would call anything but torch's,
    ultralytics' and NumPy's own classes is refused, never run. A run's epoch checkpoints (save_period) carry
    only the EMA weights, with model = None."""
    from plugins.yolov8.detector import read_checkpoint

    try:
        return read_checkpoint(path, hint=None)
    except (OSError, ValueError) as exc:
        raise AveragingError(str(exc)) from None


def _weights_module(checkpoint: dict) -> torch.nn.Module:
    # ultralytics evaluates and predicts with the EMA weights when a checkpoint carries them
    module = checkpoint.get("ema")
    return (module if module is not None else checkpoint["model"]).float()


def _class_names(module: torch.nn.Module) -> list[str]:
    names = getattr(module, "names", None) or {}
    return [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)


def average_state_dicts(state_dicts: list[dict[str, torch.Tensor]], weights: list[float] | None = None,
                        ) -> dict[str, torch.Tensor]:
    """Weighted mean of floating-point entries; integer entries (counters) come from the first.

    Shapes: every ``state_dicts[i][key]`` has the shape of ``state_dicts[0][key]``.
    """
    if not state_dicts:
        raise AveragingError("nothing to average")
    weights = weights or [1.0 / len(state_dicts)] * len(state_dicts)
    if len(weights) != len(state_dicts) or abs(sum(weights) - 1.0) > 1e-6:
        raise AveragingError("averaging weights must be one per checkpoint and sum to 1")
    keys = list(state_dicts[0])
    for index, sd in enumerate(state_dicts[1:], start=1):
        if list(sd) != keys or any(sd[k].shape != state_dicts[0][k].shape for k in keys):
            raise AveragingError(f"checkpoint {index + 1} has another architecture than the first")
    return {
        key: sum(w * sd[key].double() for w, sd in zip(weights, state_dicts)).to(state_dicts[0][key].dtype)
        if state_dicts[0][key].is_floating_point() else state_dicts[0][key].clone()
        for key in keys
    }


def average_checkpoints(paths: list[Path], out: Path, weights: list[float] | None = None) -> Path:
    """Write to ``out`` a checkpoint whose model is the (weighted) mean of the given checkpoints' models."""
    checkpoints = [_load(Path(p)) for p in paths]
    modules = [_weights_module(c) for c in checkpoints]
    averaged = average_state_dicts([m.state_dict() for m in modules], weights)
    names = [_class_names(m) for m in modules]
    for index, other in enumerate(names[1:], start=1):
        if other != names[0]:
            # the same shapes, but each output channel means another class: their mean detects nothing
            raise AveragingError(f"checkpoint {index + 1} ({paths[index]}) has classes {other}, the first "
                                 f"{names[0]}: average checkpoints of one class list only")
    # the loaded checkpoints are ours alone: the first one's module takes the mean in place
    model = modules[0]
    model.load_state_dict(averaged)
    first = checkpoints[0]
    # half precision, as ultralytics saves its own best.pt; no EMA or optimiser state: not a run to resume
    result = {**first, "model": model.half(), "ema": None, "optimizer": None, "updates": None,
              "train_args": {**(first.get("train_args") or {}), "averaged_from": [str(p) for p in paths]}}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # serialised in memory first: torch's zip writer reports a full disk as "enforce fail at inline_container"
    buffer = io.BytesIO()
    torch.save(result, buffer)
    try:
        write_bytes(out, buffer.getvalue())  # a checkpoint cut short is removed: it must not be taken for weights
    except OSError as exc:
        raise AveragingError(str(exc)) from None
    return out
