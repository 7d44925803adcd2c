"""Timing every stage of the loop on the same frames, for each stereo backend.

Stages are the engine's (``core.engine``): capture (the replay read), detection, stereo, depth,
decision and outputs; "loop" is the whole time per frame. For each stage the figure is the
per-frame mean of one pass; the table gives the median, min and max over the passes. Stereo runs
on every frame (depth for every frame, whatever the recipe's schedule) so backends compare on
equal work.
"""
from __future__ import annotations

import os
import platform
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2

from core.contracts import PluginContext
from core.decision import decide
from core.depth import DepthRule, measure_defect
from core.engine import compute_disparity, disparity_range, resolve_device
from core.recipe import LoadedRecipe
from core.registry import Registry
from core.types import FrameError, PartResult, StereoFrame

STAGES = ("capture", "detection", "stereo", "depth", "decision", "outputs", "loop")
RESOLUTIONS = {"wvga": (672, 376), "hd720": (1280, 720)}


def resize_frame(frame: StereoFrame, size: tuple[int, int]) -> StereoFrame:
    """The same pair at another resolution, with its calibration scaled (rectified pairs scale exactly)."""
    width, height = size
    if (frame.calib.width, frame.calib.height) == (width, height):
        return frame
    factor = width / frame.calib.width
    return StereoFrame(
        frame.frame_id, frame.index,
        cv2.resize(frame.left, size, interpolation=cv2.INTER_LINEAR),
        cv2.resize(frame.right, size, interpolation=cv2.INTER_LINEAR),
        frame.calib.scaled(factor), frame.timestamp, frame.source, frame.meta,
    )


def machine() -> dict[str, Any]:
    import torch

    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else platform.processor()
    info = {"cpu": model, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "python": platform.python_version()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_backend(loaded: LoadedRecipe, registry: Registry, backend: str, size: tuple[int, int],
                  device: str, repeats: int, frames: int | None, detector: Any) -> dict[str, Any]:
    recipe = loaded.recipe
    ctx = PluginContext(recipe_dir=loaded.directory, recipe_name=recipe.name, device=device)
    stereo = registry.get("stereo", backend).spec.factory(
        loaded.plugin_settings["stereo"] if backend == recipe.stereo.backend else {}, ctx)
    rule = DepthRule(**recipe.depth.model_dump())
    camera_spec = registry.get("camera", recipe.camera.plugin).spec
    with tempfile.TemporaryDirectory() as tmp:
        output = registry.get("output", "log").spec.factory({"file": str(Path(tmp) / "bench.log")}, ctx)
        passes: list[dict[str, float]] = []
        _warm_up(camera_spec, loaded, ctx, detector, stereo, size)
        for _ in range(repeats):
            camera = camera_spec.factory({**loaded.plugin_settings["camera"], "rate_fps": 0.0, "loop": False,
                                          "max_frames": frames}, ctx)
            totals = dict.fromkeys(STAGES, 0.0)
            count = 0
            iterator = iter(camera.frames())
            while True:
                t_loop = time.perf_counter()
                item = next(iterator, None)
                if item is None:
                    break
                if isinstance(item, FrameError):
                    raise RuntimeError(f"bench input: {item.message}")
                frame = resize_frame(item, size)
                t = {"capture": time.perf_counter()}
                detections = detector.detect(frame.left)
                t["detection"] = time.perf_counter()
                lo, hi = disparity_range(recipe.stereo, frame.calib)
                disparity = compute_disparity(stereo, frame, lo, hi, recipe.stereo.scale)
                t["stereo"] = time.perf_counter()
                measurements = [measure_defect(disparity, d, frame.calib, rule) for d in detections]
                t["depth"] = time.perf_counter()
                verdict, _ = decide(measurements, recipe.decision)
                t["decision"] = time.perf_counter()
                output.submit(PartResult(f"B-{count:06d}", frame.frame_id, frame.index, frame.timestamp, verdict, measurements))
                output.poll()
                t["outputs"] = time.perf_counter()
                previous = t_loop
                for stage in STAGES[:-1]:
                    totals[stage] += t[stage] - previous
                    previous = t[stage]
                totals["loop"] += t["outputs"] - t_loop
                count += 1
            camera.close()
            passes.append({stage: totals[stage] / max(count, 1) for stage in STAGES})
        output.close()
    result: dict[str, Any] = {"backend": backend, "frames": count, "repeats": repeats, "stages_ms": {}}
    for stage in STAGES:
        values = [p[stage] * 1000.0 for p in passes]
        result["stages_ms"][stage] = {"median": statistics.median(values), "min": min(values), "max": max(values)}
    loop_s = result["stages_ms"]["loop"]["median"] / 1000.0
    result["fps"] = 1.0 / loop_s if loop_s > 0 else 0.0
    result["peak_rss_mb"] = _peak_rss_mb()
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        result["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return result


def _warm_up(camera_spec, loaded: LoadedRecipe, ctx: PluginContext, detector: Any, stereo: Any, size: tuple[int, int]) -> None:
    """One untimed frame: first calls build models, allocate buffers and compile kernels."""
    camera = camera_spec.factory({**loaded.plugin_settings["camera"], "rate_fps": 0.0, "loop": False, "max_frames": 1}, ctx)
    for item in camera.frames():
        if isinstance(item, StereoFrame):
            frame = resize_frame(item, size)
            detector.detect(frame.left)
            compute_disparity(stereo, frame, *disparity_range(loaded.recipe.stereo, frame.calib), loaded.recipe.stereo.scale)
    camera.close()


def run_bench(loaded: LoadedRecipe, registry: Registry, backends: list[str], resolution: str, device: str,
              repeats: int, frames: int | None) -> dict[str, Any]:
    device = resolve_device(device)
    recipe = loaded.recipe
    ctx = PluginContext(recipe_dir=loaded.directory, recipe_name=recipe.name, device=device)
    detector_settings = dict(loaded.plugin_settings["detector"], confidence=recipe.detector.confidence)
    if recipe.detector.weights is not None:
        detector_settings["weights"] = str(loaded.resolve(recipe.detector.weights))
    detector = registry.get("detector", recipe.detector.plugin).spec.factory(detector_settings, ctx)
    size = RESOLUTIONS[resolution]
    results = [bench_backend(loaded, registry, b, size, device, repeats, frames, detector) for b in backends]
    return {"recipe": str(loaded.path), "resolution": f"{size[0]}x{size[1]}", "device": device,
            "machine": machine(), "when": time.strftime("%Y-%m-%d %H:%M"), "results": results}


def markdown(report: dict[str, Any]) -> str:
    m = report["machine"]
    lines = [
        f"Recipe `{Path(report['recipe']).name}`, {report['resolution']}, device {report['device']}; "
        f"machine: {m['cpu']}, {m['cores']} cores, {m['torch_threads']} torch threads"
        + (f", GPU {m['gpu']}" if "gpu" in m else "") + f"; {report['when']}",
        "",
        "| backend | " + " | ".join(f"{s} ms (median, min-max)" for s in STAGES) + " | fps | peak RSS MB |",
        "|---|" + "---|" * (len(STAGES) + 2),
    ]
    for r in report["results"]:
        cells = [f"{r['stages_ms'][s]['median']:.1f} ({r['stages_ms'][s]['min']:.1f}-{r['stages_ms'][s]['max']:.1f})" for s in STAGES]
        lines.append(f"| {r['backend']} | " + " | ".join(cells) + f" | {r['fps']:.2f} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines) + "\n"
