"""``inspect stereo`` (one disparity map) and ``inspect eval stereo`` (Middlebury scores).

torch and the backends are imported inside the commands so that ``inspect --help`` stays fast.
"""
from __future__ import annotations

from pathlib import Path

import click

from core.commands.params import FINITE, cuda_if_present, out_file, out_folder, overwritten_input
from core.recipe.schema import MAX_THREADS


def _fail(message: str) -> None:
    click.echo(f"error: {message}", err=True)
    raise click.exceptions.Exit(2)


def _parse_settings(pairs: tuple[str, ...], option: str = "--set") -> dict:
    from drivers.yaml_reader import Misread, option_value

    settings = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            _fail(f"{option} {pair!r}: expected KEY=VALUE")
        try:
            settings[key.strip()] = option_value(value) if value.strip() else ""
        except Misread as exc:
            _fail(f"{option} {pair}: {exc.described}")
    return settings


# One map at a time the best measured map is worth twice the time: torch_sgm's improved preset with both
# views (docs/benchmarks.md); the line runs the preset alone. Settings given win; the seed stays the seed.
BEST_SINGLE_MAP = {"torch_sgm": {"two_view": True}}


def best_single_map(name: str, settings: dict) -> dict:
    """``settings`` with the backend's best single-map configuration filled in where they are silent."""
    if settings.get("preset") == "seed":
        return dict(settings)
    return {**BEST_SINGLE_MAP.get(name, {}), **settings}


def make_backend(name: str, settings: dict, device: str):
    """A stereo backend from the registry; bad names or settings end the command with exit 2."""
    from pydantic import ValidationError

    from core.contracts import PluginContext
    from core.devices import plugin_device
    from core.recipe.loader import first_problem
    from core.registry import UnknownPlugin, default_registry

    try:
        plugin = default_registry().get("stereo", name)
    except UnknownPlugin as exc:
        _fail(f"--backend: {exc}")
    try:
        return plugin.spec.factory(dict(settings), PluginContext(**plugin_device(device)))
    except ValidationError as exc:
        # worded as a recipe's plugin settings are
        loc, message = first_problem(exc, plugin.spec.settings_model)
        _fail(f"--set {'.'.join(str(p) for p in loc)}: {message} (backend {name!r})")
    except (ValueError, TypeError) as exc:
        _fail(f"--set for backend {name!r}: {str(exc).splitlines()[0]}")


def _threads(n: int | None) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


def check_disparity_range(min_disp: float, max_disp: float, width: int) -> None:
    if max_disp <= min_disp:
        _fail(f"--max-disp {max_disp:g} must be larger than --min-disp {min_disp:g}")
    if max_disp > width:
        _fail(f"--max-disp {max_disp:g} is larger than the image width {width}")


def write_png(path: Path, disparity, vmin: float, vmax: float) -> None:
    """Colour-mapped view: the disparity range spans the colour map, invalid pixels are black."""
    import numpy as np

    from core.stereo_eval import colourise
    from drivers.sequence_folder import write_image

    try:
        write_image(path, colourise(np.asarray(disparity) - vmin, vmax - vmin))
    except OSError as exc:
        _fail(str(exc))


threads_option = click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None,
                              help="torch CPU threads (1 is fastest when the cores are shared)")
device_option = click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
                             callback=cuda_if_present,
                             help="passed to the backend as the engine's device")


@click.command("stereo")
@click.argument("left", type=click.Path(path_type=Path))
@click.argument("right", type=click.Path(path_type=Path))
@click.option("--backend", default="torch_sgm", show_default=True,
              help="stereo plugin, e.g. torch_sgm (its best map: the improved preset with two_view) or opencv_sgbm")
@click.option("--max-disp", type=FINITE, required=True, help="search min-disp <= d < max-disp (pixels)")
@click.option("--min-disp", type=FINITE, default=0.0, show_default=True)
@click.option("--out", type=click.Path(path_type=Path), callback=out_file,
              help="PFM, Middlebury convention (invalid = inf)")
@click.option("--png", type=click.Path(path_type=Path), help="colour-mapped view")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help="backend setting, repeatable")
@click.option("--stages", is_flag=True,
              help="match three times and print the time of each of the backend's stages in the third run (torch_sgm)")
@device_option
@threads_option
def stereo_command(left, right, backend, max_disp, min_disp, out, png, settings, stages, device, threads):
    """Disparity map of the LEFT image of a rectified pair."""
    import cv2
    import numpy as np

    from drivers.sequence_folder import SequenceError, read_image, write_pfm

    if png and not cv2.haveImageWriter(str(png)):  # said before the map is computed, not after
        _fail(f"--png {png}: no image format has the extension {png.suffix!r} (give .png, .jpg, .bmp or .tif)")
    overwrite = overwritten_input({"--out": out, "--png": png}, [left, right])
    if overwrite is not None:  # a map written over the left image, say, by a completed file name
        _fail(overwrite)
    try:
        left_img, right_img = read_image(left, "left image"), read_image(right, "right image")
    except SequenceError as exc:
        _fail(str(exc))
    if left_img.shape != right_img.shape:
        _fail(f"{left} is {left_img.shape[1]}x{left_img.shape[0]} but {right} is "
              f"{right_img.shape[1]}x{right_img.shape[0]}; a rectified pair has one size")
    check_disparity_range(min_disp, max_disp, left_img.shape[1])
    _threads(threads)
    matcher = make_backend(backend, best_single_map(backend, _parse_settings(settings)), device)
    from core.stereo_memory import memory_problem, search_disparities

    memory = memory_problem(matcher, left_img.shape[0], left_img.shape[1], search_disparities(min_disp, max_disp),
                            name=backend)
    if memory is not None:
        _fail(f"{left}: {memory}: match a downscaled pair or a narrower range")
    if stages and not callable(getattr(matcher, "compute_timed", None)):
        _fail(f"--stages: the {backend} backend does not time its stages")
    import time

    # A backend that matches this pair on a CUDA device also reports the peak GPU memory of this one map.
    device_for = getattr(matcher, "device_for", None)
    on_gpu = str(device_for(*left_img.shape[:2]) if callable(device_for) else getattr(matcher, "device", "")).startswith("cuda")
    if on_gpu:
        import torch

        torch.cuda.reset_peak_memory_stats()
    try:
        if stages:
            # the first map loads the compiled kernels; until the heap has grown to hold a map's volumes, fresh
            # pages fault in on first touch (40 ms of SGM's kernel on a WVGA frame): time the map after both,
            # as a line's frames run
            for _ in range(2):
                matcher.compute(left_img, right_img, min_disp, max_disp)
        start = time.perf_counter()
        if stages:
            disp, stage_seconds = matcher.compute_timed(left_img, right_img, min_disp, max_disp)
        else:
            disp = matcher.compute(left_img, right_img, min_disp, max_disp)
    except ValueError as exc:  # the backend refuses this pair (e.g. narrower than its search)
        _fail(f"{left}: {backend}: {exc}")
    disp = np.asarray(disp, np.float32)
    seconds = time.perf_counter() - start
    valid = np.isfinite(disp)
    gpu = torch.cuda.max_memory_allocated() / 2**20 if on_gpu else None
    click.echo(f"{backend}: {disp.shape[1]}x{disp.shape[0]}, disparities {min_disp:g}..{max_disp:g}, "
               f"{100 * valid.mean():.1f}% valid, {seconds:.2f} s"
               + (f", peak GPU memory {gpu:.0f} MiB" if gpu is not None else ""))
    if stages:
        click.echo(stage_table(stage_seconds, seconds))
    if out:
        try:
            write_pfm(out, disp)
        except OSError as exc:  # it names the file
            _fail(str(exc))
        click.echo(f"wrote {out}")
    if png:
        write_png(png, disp, min_disp, max_disp)
        click.echo(f"wrote {png}")


def stage_table(stage_seconds: dict[str, float], total: float) -> str:
    """A Markdown table of the stages' milliseconds and shares of ``total`` seconds, slowest first, then
    what no stage accounts for (the backend's own bookkeeping) and the total."""
    lines = ["| stage | ms | share |", "|---|---|---|"]
    for stage, s in sorted(stage_seconds.items(), key=lambda item: -item[1]):
        lines.append(f"| {stage} | {1000 * s:.1f} | {100 * s / total:.0f} % |")
    rest = total - sum(stage_seconds.values())
    lines.append(f"| other | {1000 * rest:.1f} | {100 * rest / total:.0f} % |")
    lines.append(f"| total | {1000 * total:.1f} | 100 % |")
    return "\n".join(lines)


def _split(values: tuple[str, ...]) -> list[str]:
    return [v.strip() for value in values for v in value.split(",") if v.strip()]


@click.command("stereo")
@click.option("--middlebury", "folder", type=click.Path(path_type=Path), required=True,
              help="a Middlebury scene folder (im0.png, im1.png, calib.txt, disp0GT.pfm or the 2014 datasets' "
                   "disp0.pfm, and mask0nocc.png where there is one), or a folder of them")
@click.option("--backend", "backends", multiple=True, help="repeatable or comma-separated; default torch_sgm")
@click.option("--scenes", multiple=True, help="scene names, repeatable or comma-separated; default all")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/stereo_eval"), show_default=True,
              callback=out_folder)
@click.option("--set", "settings", multiple=True, metavar="BACKEND.KEY=VALUE", help="backend setting, repeatable")
@click.option("--figure/--no-figure", default=True, show_default=True, help="save the per-scene figure")
@device_option
@threads_option
def eval_stereo_command(folder, backends, scenes, out, settings, figure, device, threads):
    """Bad-0.5/1/2/4 (dense and sparse), average error, invalid share and runtime per scene."""
    import platform

    from core import stereo_eval as ev
    from drivers.sequence_folder import SequenceError

    names = _split(backends) or ["torch_sgm"]
    per_backend: dict[str, dict] = {n: {} for n in names}
    for key, value in _parse_settings(settings).items():
        name, dot, sub = key.partition(".")
        if not dot or name not in per_backend:
            _fail(f"--set {key}: expected BACKEND.KEY with BACKEND one of {', '.join(names)}")
        per_backend[name][sub] = value
    if not folder.is_dir():
        _fail(f"--middlebury {folder}: not a folder")
    try:
        scene_dirs = ev.list_scenes(folder, _split(scenes) or None)
    except ValueError as exc:
        _fail(f"--scenes: {exc}")
    if not scene_dirs:
        _fail(f"--middlebury {folder}: not a scene folder (im0.png + calib.txt), nor one that holds any")
    # before any scene is matched: a test scene without ground truth would otherwise end the run halfway
    unscored = [d for d in scene_dirs if ev.ground_truth_path(d) is None]
    if unscored:
        more = f" (and in {len(unscored) - 1} more scenes)" if len(unscored) > 1 else ""
        _fail(f"{unscored[0] / ev.GROUND_TRUTH[0]}: file missing, nor {ev.GROUND_TRUTH[1]}{more}: a scene without "
              f"ground truth cannot be scored (--scenes picks the others)")
    from core.stereo_memory import memory_problem

    _threads(threads)
    per_backend = {n: best_single_map(n, per_backend[n]) for n in names}
    matchers = {n: make_backend(n, per_backend[n], device) for n in names}
    results = {n: [] for n in names}
    maps = {n: [] for n in names}
    loaded = []
    for scene_dir in scene_dirs:
        try:
            scene = ev.load_scene(scene_dir)
        except SequenceError as exc:
            _fail(str(exc))
        loaded.append(scene)
        for n, matcher in matchers.items():
            memory = memory_problem(matcher, scene.left.shape[0], scene.left.shape[1], int(scene.ndisp), name=n)
            if memory is not None:
                _fail(f"{scene_dir}: {memory}")
            s, disp = ev.evaluate_scene(matcher, n, scene)
            results[n].append(s)
            if figure:
                maps[n].append(disp)
            click.echo(f"{scene.name:12s} {n:12s} dense bad1.0 {s.dense['bad1.0']:6.2f}%  "
                       f"sparse {s.sparse['bad1.0']:6.2f}% @ {s.coverage:5.1f}%  {s.runtime_s:6.2f} s"
                       + (f"  ({scene.note})" if scene.note else ""))
    import torch

    from core.devices import resolve_device

    meta = {"folder": str(folder), "backends": {n: per_backend[n] for n in names},
            "machine": f"{platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}",
            "device": resolve_device(device)}
    json_path, md_path = ev.save_results(out, results, meta)
    click.echo("")
    click.echo(ev.markdown_table(results))
    click.echo("dense: missing predictions count as bad; sparse: only claimed pixels, cov% = their share")
    click.echo(f"wrote {json_path} and {md_path}")
    if figure:
        click.echo(f"wrote {ev.save_figure(out / 'stereo_eval.png', loaded, maps)}")


def register(cli: click.Group) -> None:
    cli.add_command(stereo_command, "stereo")
    cli.commands["eval"].add_command(eval_stereo_command, "stereo")
