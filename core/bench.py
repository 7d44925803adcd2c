"""Timing every stage of the loop on the same frames, for each stereo backend.

Stages are the engine's (``core.engine``): capture (the replay read), detection, stereo, depth,
decision and outputs; "loop" is the whole time per frame. For each stage the figure is the
per-frame mean of one pass; the table gives the median, min and max over the passes.

Regions: ``full`` runs stereo on every frame over the whole image (depth for every frame, whatever
the recipe's schedule) so backends compare on equal work. ``defects`` is the live setting
(``stereo.region: defects``): stereo only on frames with detections and only around them; its row
also gives the largest difference of each defect's depth to the same box measured on full-frame
disparity of the same frame (computed untimed). Backend ``none`` times detection alone, the frame
rate that depth is measured against.

``soak`` runs the real loop (``core.engine.run``) for many frames of a looped replay and reports the
resident memory at its start and end.
"""
from __future__ import annotations

import os
import platform
import resource
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2

from core import depth
from core.decision import decide
from core.depth import DepthRule, measure_frame
from core.engine import compute_disparity, disparity_range, frame_disparity, make_plugin, plugin_context
from core.recipe import LoadedRecipe
from core.recipe.loader import detector_settings
from core.registry import Registry
from core.types import FrameError, PartResult, StereoFrame
from drivers.zed_calibration import RESOLUTIONS as ZED_MODES

STAGES = ("capture", "detection", "stereo", "depth", "decision", "outputs", "loop")
RESOLUTIONS = {name.lower(): size for name, size in ZED_MODES.items()}  # wvga, hd720, hd1080, 2k


class BenchInputError(Exception):
    """A frame of the sequence timed cannot be read; the message names it. Timings of a loop that skipped
    it would be of other frames than the table says."""


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


NO_STEREO = "none"


def bench_backend(loaded: LoadedRecipe, registry: Registry, backend: str, size: tuple[int, int],
                  device: str, repeats: int, frames: int | None, detector: Any, region: str = "full",
                  versus: dict[str, Any] | None = None) -> dict[str, Any]:
    """``versus``: settings of the backend that change for the reference the depth numbers are compared
    against (full frame, untimed); without it, regions other than ``full`` are compared with ``full``."""
    recipe = loaded.recipe
    ctx = plugin_context(loaded, device)
    settings = loaded.plugin_settings["stereo"] if backend == recipe.stereo.backend else {}
    stereo = None if backend == NO_STEREO else make_plugin(loaded, registry, ctx, "stereo", backend, "stereo", settings)
    reference = stereo
    if versus and stereo is not None:
        reference = make_plugin(loaded, registry, ctx, "stereo", backend, "stereo", {**settings, **versus})
    compare = stereo is not None and (region != "full" or bool(versus))
    rule = DepthRule.from_recipe(recipe)
    # what the surface fit is added to: the backend's plane and median alone, without the check of where the plate
    # lies that the line's method: disparity adds (a settled fit makes it unneeded)
    plain = replace(rule, method="disparity") if rule.method == "surface" and stereo is not None else None
    section = recipe.stereo.model_copy(update={"region": region})
    diffs = {"defects": 0, "distance_mm": 0.0, "deviation_mm": 0.0, "availability_differs": 0}
    def open_camera(max_frames):
        settings = {**loaded.plugin_settings["camera"], "rate_fps": 0.0, "loop": False, "max_frames": max_frames}
        return make_plugin(loaded, registry, ctx, "camera", recipe.camera.plugin, "camera", settings)

    with tempfile.TemporaryDirectory() as tmp:
        output = registry.get("output", "log").spec.factory({"file": str(Path(tmp) / "bench.log")}, ctx)
        passes: list[dict[str, float]] = []
        plain_passes: list[float] = []
        _warm_up(open_camera(1), loaded, detector, stereo, size)
        for _ in range(repeats):
            camera = open_camera(frames)
            totals = dict.fromkeys(STAGES, 0.0)
            plain_total = 0.0
            count = 0
            iterator = iter(camera.frames())
            while True:
                t_loop = time.perf_counter()
                item = next(iterator, None)
                if item is None:
                    break
                if isinstance(item, FrameError):
                    raise BenchInputError(item.message)
                frame = resize_frame(item, size)
                t = {"capture": time.perf_counter()}
                try:
                    detections = detector.detect(frame.left)
                except Exception as exc:  # timings of a loop that skipped it would be of other frames
                    raise BenchInputError(f"frame {item.frame_id}: detection failed: {type(exc).__name__}: "
                                          f"{exc}") from None
                t["detection"] = time.perf_counter()
                measurements = []
                if stereo is not None and (region == "full" or detections):
                    disparity = frame_disparity(stereo, frame, section, detections, rule)
                    t["stereo"] = time.perf_counter()
                    measurements = measure_frame(disparity, detections, frame, rule,
                                                 disparity_range(section, frame.calib))
                    t["depth"] = time.perf_counter()
                else:
                    t["stereo"] = t["depth"] = t["detection"]
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
                if plain is not None and measurements:  # untimed in the loop: the next frame's clock starts later
                    t0 = time.perf_counter()
                    measure_frame(disparity, detections, frame, plain)
                    plain_total += time.perf_counter() - t0
                if compare and measurements and not passes:  # untimed: the next frame's clock starts later
                    _compare_to_full(diffs, reference, frame, recipe.stereo, detections, rule, measurements)
            camera.close()
            passes.append({stage: totals[stage] / max(count, 1) for stage in STAGES})
            plain_passes.append(plain_total / max(count, 1))
        output.close()
    result: dict[str, Any] = {"backend": backend, "region": region if stereo is not None else "-", "frames": count,
                              "repeats": repeats, "stages_ms": {}}
    if compare:
        result["depth_vs_full_frame"] = diffs
        if versus:
            result["versus"] = versus
    for stage in STAGES:
        values = [p[stage] * 1000.0 for p in passes]
        result["stages_ms"][stage] = {"median": statistics.median(values), "min": min(values), "max": max(values)}
    loop_s = result["stages_ms"]["loop"]["median"] / 1000.0
    result["fps"] = 1.0 / loop_s if loop_s > 0 else 0.0
    # what measuring costs against what finding costs, on the same frames (a ratio: this machine's speed drifts)
    ms = {stage: result["stages_ms"][stage]["median"] for stage in ("stereo", "depth", "detection")}
    result["stereo_and_depth_over_detection"] = ((ms["stereo"] + ms["depth"]) / ms["detection"]
                                                 if stereo is not None and ms["detection"] > 0 else None)
    if plain is not None:
        result["plane_and_median_ms"] = statistics.median(p * 1000.0 for p in plain_passes)
    result["peak_rss_mb"] = _peak_rss_mb()
    import torch

    if ctx.device.startswith("cuda") and torch.cuda.is_available():
        result["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    # where the backend matched, if it says: torch_sgm's device auto sends small pairs to the CPU
    used = getattr(stereo, "devices_used", None)
    if used:
        result["stereo_devices"] = sorted(str(d) for d in used)
    return result


def _compare_to_full(diffs: dict[str, Any], stereo: Any, frame: StereoFrame, section, detections, rule: DepthRule,
                     measurements) -> None:
    """Each defect's depth against the same box measured on this frame's full-frame disparity."""
    reference = frame_disparity(stereo, frame, section.model_copy(update={"region": "full"}), detections, rule)
    for det, m, ref in zip(detections, measurements, measure_frame(reference, detections, frame, rule)):
        diffs["defects"] += 1
        for key in ("distance_mm", "deviation_mm"):
            a, b = getattr(ref, key), getattr(m, key)
            if (a is None) != (b is None):
                diffs["availability_differs"] += 1
            elif a is not None:
                diffs[key] = max(diffs[key], abs(a - b))


def _warm_up(camera: Any, loaded: LoadedRecipe, detector: Any, stereo: Any, size: tuple[int, int]) -> None:
    """One untimed frame of ``camera``, which it closes: first calls build models, allocate buffers and compile
    kernels (the surface fit's too)."""
    depth.warm_up()
    for item in camera.frames():
        if isinstance(item, StereoFrame):
            frame = resize_frame(item, size)
            detector.detect(frame.left)
            if stereo is not None:
                compute_disparity(stereo, frame, *disparity_range(loaded.recipe.stereo, frame.calib), loaded.recipe.stereo.scale)
    camera.close()


def run_bench(loaded: LoadedRecipe, registry: Registry, backends: list[str], resolution: str, device: str,
              repeats: int, frames: int | None, regions: tuple[str, ...] = ("full",),
              versus: dict[str, Any] | None = None) -> dict[str, Any]:
    recipe = loaded.recipe
    ctx = plugin_context(loaded, device)
    detector = make_plugin(loaded, registry, ctx, "detector", recipe.detector.plugin, "detector",
                           detector_settings(loaded))
    size = RESOLUTIONS[resolution]
    results = [bench_backend(loaded, registry, b, size, device, repeats, frames, detector, r,
                             versus if b == recipe.stereo.backend else None)
               for b in backends for r in (regions if b != NO_STEREO else ("full",))]
    return {"recipe": str(loaded.path), "resolution": f"{size[0]}x{size[1]}", "device": ctx.device,
            "machine": machine(), "when": time.strftime("%Y-%m-%d %H:%M"), "results": results}


def markdown(report: dict[str, Any]) -> str:
    m = report["machine"]
    versus = next((", ".join(f"{k}={v}" for k, v in r["versus"].items()) for r in report["results"] if r.get("versus")), "")
    lines = [
        f"Recipe `{Path(report['recipe']).name}`, {report['resolution']}, device {report['device']}; "
        f"machine: {m['cpu']}, {m['cores']} cores, {m['torch_threads']} torch threads"
        + (f", GPU {m['gpu']}" if "gpu" in m else "") + f"; {report['when']}",
        "",
        "| backend | region | " + " | ".join(f"{s} ms (median, min-max)" for s in STAGES)
        + " | (stereo + depth) ÷ detection | fps | peak RSS MB | depth vs full frame" + (f" with {versus}" if versus else "")
        + ": max abs diff distance / deviation mm (defects) |",
        "|---|---|" + "---|" * (len(STAGES) + 4),
    ]
    for r in report["results"]:
        cells = [f"{r['stages_ms'][s]['median']:.1f} ({r['stages_ms'][s]['min']:.1f}-{r['stages_ms'][s]['max']:.1f})" for s in STAGES]
        diff = r.get("depth_vs_full_frame")
        versus = "" if diff is None else (f"{diff['distance_mm']:.3f} / {diff['deviation_mm']:.3f} ({diff['defects']}"
                                         + (f", {diff['availability_differs']} available in one only" if diff["availability_differs"] else "") + ")")
        ratio = r.get("stereo_and_depth_over_detection")
        elsewhere = [d for d in r.get("stereo_devices", ()) if d != report["device"]]
        backend = r["backend"] + (f" (matched on {', '.join(r['stereo_devices'])})" if elsewhere else "")
        lines.append(f"| {backend} | {r['region']} | " + " | ".join(cells)
                     + f" | {'' if ratio is None else f'{ratio:.2f}'} | {r['fps']:.2f} | {r['peak_rss_mb']:.0f} | {versus} |")
    return "\n".join(lines) + "\n"


def current_rss_mb() -> float:
    """Resident memory now (``VmRSS``), not the peak: what a leak makes grow."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _looped(loaded: LoadedRecipe, folder: Path, **recipe_changes: Any) -> LoadedRecipe:
    """The recipe with its camera looped as fast as it runs, its store in ``folder``, a log output as its
    only one (no PLC needed) and no master parts (the loop's speed is measured, not its detector);
    ``recipe_changes`` replace top-level sections (e.g. ``detector``)."""
    from core.recipe.schema import PluginRef, VerifySection

    recipe = loaded.recipe
    log = {"file": str(folder / "rejects.log")}
    return LoadedRecipe(
        recipe=recipe.model_copy(update={
            "outputs": [PluginRef(plugin="log", settings=log)],
            "results": recipe.results.model_copy(update={"path": str(folder / "results")}),
            "verify": VerifySection(),
            **recipe_changes,
        }),
        path=loaded.path, text_hash=loaded.text_hash,
        plugin_settings={**{k: v for k, v in loaded.plugin_settings.items() if not k.startswith("outputs.")},
                         "outputs.0": log, "camera": {**loaded.plugin_settings["camera"], "loop": True, "rate_fps": 0.0}},
    )


def run_soak(loaded: LoadedRecipe, registry: Registry, frames: int, device: str, every: int = 1000,
             on_sample=None) -> dict[str, Any]:
    """The real loop (``core.engine.run``) over ``frames`` frames of the recipe's camera, looped, as fast as
    it runs, with its results store and a log output in a temporary folder (no PLC needed). Resident
    memory is sampled after the first frame (models loaded, buffers allocated), every ``every`` frames
    and at the end."""
    from core import engine

    samples: list[tuple[int, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        done = [0]

        def on_part(outcome) -> None:
            done[0] += 1
            if done[0] == 1 or done[0] % every == 0 or done[0] == frames:
                samples.append((done[0], current_rss_mb()))
                if on_sample:
                    on_sample(*samples[-1])

        start = time.perf_counter()
        summary = engine.run(_looped(loaded, Path(tmp)), registry=registry, on_part=on_part, device=device,
                             max_frames=frames)
        elapsed = time.perf_counter() - start
    return {"recipe": str(loaded.path), "frames": summary.frames, "requested": frames, "seconds": elapsed,
            "fps": summary.fps, "counts": {k.value: v for k, v in summary.counts.items()},
            "rss_mb": samples, "rss_start_mb": samples[0][1] if samples else None,
            "rss_end_mb": samples[-1][1] if samples else None,
            # VmRSS is read from per-thread counters that can run a little ahead of ru_maxrss
            "peak_rss_mb": max([_peak_rss_mb(), *(mb for _, mb in samples)]),
            "machine": machine(), "when": time.strftime("%Y-%m-%d %H:%M")}


def run_live(loaded: LoadedRecipe, registry: Registry, frames: int, device: str, rounds: int = 3) -> dict[str, Any]:
    """The real loop as the recipe runs it (detection a frame ahead where ``stereo.concurrent``), ``frames``
    frames of its looped camera with detection alone (no detection passes the confidence, so no stereo or
    depth), with the matcher's depth for every defect (``depth.method: disparity``, the reference the surface fit
    is added to; left out where the recipe's method is that already) and with the recipe's depth, in ``rounds``
    rounds, the order of the loops reversed from one round to the next: each loop's median frame rate and each
    round's ratio, the ratio their median. A shared machine's speed drifts within minutes; a ratio of loops run
    side by side in time follows the loops, not the drift. The stage table times the stages one after another and
    cannot show what running them side by side gains."""
    from core import engine

    recipe = loaded.recipe
    # each loop's recipe changes, in the order of a round
    changes: dict[str, dict] = {"detection alone": {"detector": recipe.detector.model_copy(update={"confidence": 1.0})}}
    if recipe.depth.method != "disparity":
        changes["the matcher's depth"] = {"depth": recipe.depth.model_copy(update={"method": "disparity"})}
    changes["with depth"] = {}
    loops = tuple(changes)
    runs: dict[str, list] = {name: [] for name in loops}
    order = [name for r in range(rounds) for name in (loops if r % 2 == 0 else loops[::-1])]
    for name in order:
        with tempfile.TemporaryDirectory() as tmp:
            runs[name].append(engine.run(_looped(loaded, Path(tmp), **changes[name]), registry=registry,
                                         device=device, max_frames=frames))
    rows = {}
    for name, summaries in runs.items():
        parts = sum(s.frames for s in summaries)
        stages = dict.fromkeys(k for s in summaries for k in s.stage_seconds)  # in the order they first ran
        counts: dict[str, int] = {}
        for s in summaries:
            for k, v in s.counts.items():
                counts[k.value] = counts.get(k.value, 0) + v
        rows[name] = {"frames": summaries[0].frames, "fps": statistics.median(s.fps for s in summaries),
                      "fps_rounds": [s.fps for s in summaries],
                      "mean_ms": {k: sum(s.stage_seconds.get(k, 0.0) for s in summaries) / max(parts, 1) * 1000.0
                                  for k in stages},
                      "counts": counts}
    ratios = paired_ratios(rows["with depth"], rows["detection alone"])
    fit_ratios = paired_ratios(rows["with depth"], rows.get("the matcher's depth"))
    return {"concurrent": recipe.stereo.concurrent, "threads": recipe.threads, "rounds": rounds,
            "order": order, "rows": rows, "ratios": ratios, "ratio": statistics.median(ratios) if ratios else None,
            "fit_ratios": fit_ratios, "fit_ratio": statistics.median(fit_ratios) if fit_ratios else None,
            "depth_share": depth_share(rows["with depth"]),
            "added_share": added_share(rows["with depth"], rows.get("the matcher's depth"))}


def paired_ratios(row: dict[str, Any], reference: dict[str, Any] | None) -> list[float]:
    """``row``'s rate over ``reference``'s, round by round (each pair ran within a minute of each other, so that
    the machine's drift between rounds falls on both); empty without a reference."""
    if reference is None:
        return []
    return [r / ref for ref, r in zip(reference["fps_rounds"], row["fps_rounds"]) if ref]


def depth_share(row: dict[str, Any]) -> float | None:
    """The share of the loop's frame time that depth takes: its mean ms a part over the frame time at the loop's
    median rate; None where the loop ran no depth or no frame."""
    depth = row["mean_ms"].get("depth")
    return depth * row["fps"] / 1000.0 if depth and row["fps"] > 0 else None


def added_share(row: dict[str, Any], reference: dict[str, Any] | None) -> float | None:
    """The share of the loop's frame time (``row``'s, at its median rate) that the recipe's depth takes beyond the
    matcher's depth (``reference``'s loop): what the surface fit adds to a part, its mean ms a part less the
    reference's; None without a reference or where either loop ran no depth."""
    if reference is None or not reference["mean_ms"].get("depth") or not row["mean_ms"].get("depth") \
            or row["fps"] <= 0:
        return None
    return (row["mean_ms"]["depth"] - reference["mean_ms"]["depth"]) * row["fps"] / 1000.0


def add_own_share(live: dict[str, Any], report: dict[str, Any], backend: str, region: str) -> None:
    """Add to ``live`` the share of its frame time that the surface fit's own work takes (``own_share``): depth's
    share less the part of depth the backend's plane and median take (``plane_and_median_of_depth``), as the stage
    table's row of the recipe's ``backend`` and ``region`` timed them one after another. Nothing where that row,
    its plane and median, or the loop's depth are missing."""
    row = next((r for r in report["results"] if r["backend"] == backend and r["region"] == region), None)
    share = live.get("depth_share")
    if row is None or share is None or row.get("plane_and_median_ms") is None:
        return
    depth_ms = row["stages_ms"]["depth"]["median"]
    if depth_ms > 0:
        fraction = min(1.0, row["plane_and_median_ms"] / depth_ms)
        live["plane_and_median_of_depth"] = fraction
        live["own_share"] = share * (1.0 - fraction)


def live_markdown(live: dict[str, Any]) -> str:
    mode = "detection a frame ahead" if live["concurrent"] else "one frame at a time"
    rounds = live["rounds"]
    lines = [f"The real loop ({mode}, threads {live['threads']}), looped replay, as fast as it runs, {rounds} "
             f"round{'s' if rounds > 1 else ''} of every loop:", "",
             "| loop | frames a round | fps, median (each round) | mean ms per part |", "|---|---|---|---|"]
    for name, row in live["rows"].items():
        stages = ", ".join(f"{k} {v:.0f}" for k, v in row["mean_ms"].items())
        each = ", ".join(f"{f:.2f}" for f in row["fps_rounds"])
        lines.append(f"| {name} | {row['frames']} | {row['fps']:.2f} ({each}) | {stages} |")
    if live["ratio"] is not None:
        each = ", ".join(f"{r:.2f}" for r in live["ratios"])
        lines += ["", f"with depth ÷ detection alone: {live['ratio']:.2f} (round by round {each})"]
    if live.get("fit_ratio") is not None:
        each = ", ".join(f"{r:.2f}" for r in live["fit_ratios"])
        # the loop as it runs: depth on the second core beside the next frame's detection costs the rate only
        # what it takes from detection's share of the machine
        lines.append(f"with depth ÷ the matcher's depth: {live['fit_ratio']:.2f} (round by round {each}): what the "
                     f"surface fit costs the loop's rate as it runs")
    share = live.get("depth_share")
    if share is not None:
        depth = live["rows"]["with depth"]
        lines += ["", f"depth's share of a frame with depth: {share:.0%} ({depth['mean_ms']['depth']:.0f} ms a part of "
                      f"{1000.0 / depth['fps']:.0f} ms a frame)"]
        added = live.get("added_share")
        if added is not None:
            matcher = live["rows"]["the matcher's depth"]["mean_ms"]["depth"]
            # the matcher's depth (method: disparity) also checks where the plate lies around each box, which a
            # settled surface fit makes unneeded: the fit's own work is more than this difference
            lines.append(f"the surface fit's share beyond the matcher's depth: {added:.0%} "
                         f"({depth['mean_ms']['depth'] - matcher:.0f} ms a part more than its {matcher:.0f}, which "
                         f"holds the check of where the plate lies)")
        own = live.get("own_share")
        if own is not None:
            lines.append(f"the surface fit's own work: {own:.0%} of a frame (depth's share less what the backend's "
                         f"plane and median take of depth in the stage table, {live['plane_and_median_of_depth']:.0%})")
    return "\n".join(lines) + "\n"
