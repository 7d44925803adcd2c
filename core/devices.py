"""The torch device a command or a plugin runs on, and why a CUDA one cannot be had."""
from __future__ import annotations


def resolve_device(device: str) -> str:
    """``auto``: CUDA where torch sees a device, else the CPU; any other name as it is."""
    if device != "auto":
        return device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def plugin_device(device: str) -> dict:
    """The device fields of a ``PluginContext`` for a command's ``device``: ``device`` (``auto`` resolved) and
    ``device_auto``, whether ``auto`` chose it rather than the command naming it."""
    return {"device": resolve_device(device), "device_auto": device == "auto"}


def cuda_problem(index: int | None = None) -> str | None:
    """Why torch cannot run on CUDA (on device ``index``, where given), in words, or None. Said before the first
    part: a device the machine lacks made every part's detection or stereo an ERROR."""
    import torch

    if not torch.cuda.is_available():
        return "torch sees no CUDA device on this machine (cpu, or auto for what there is)"
    if index is not None and index >= torch.cuda.device_count():
        return f"torch sees {torch.cuda.device_count()} CUDA device(s), cuda:0 on"
    return None
