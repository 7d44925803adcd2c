"""``inspect sim``: synthetic stereo scenes with exact ground truth (see the ``sim`` package)."""
from __future__ import annotations

import re
import time
from pathlib import Path

import click

from core.commands.params import FINITE, Finite, make_folder

FRAME_FILE = re.compile(r"^\d{6}\.(png|jpg|jpeg|json)$")
# The ZED's largest mode (2K) and the end of its depth range: a frame of 4096x4096 took 20 GB and three
# minutes to render, a plate a kilometre away a texture larger than any memory.
MAX_WIDTH, MAX_HEIGHT = 2208, 1242
MAX_DISTANCE_MM = 20_000.0
MAX_RAYS = 16_000_000  # per eye: 2K at the default supersampling (11 M) took 3.3 GB
MAX_DEPTH_MM = 50.0  # a pit or bump deeper than a thick plate; 1e300 left the truth unmeasurable


def existing_frame_files(out: Path) -> list[Path]:
    """Frame files a previous run left in OUT (only names this generator writes)."""
    files = [p for sub in ("left", "right", "gt", "labels") if (out / sub).is_dir()
             for p in sorted((out / sub).iterdir()) if FRAME_FILE.match(p.name)]
    return files + ([out / "calib.yaml"] if (out / "calib.yaml").exists() else [])


def prepare_folder(out: Path, overwrite: bool) -> None:
    """OUT made ready for a new sequence, or a one-line error (exit 2): it may not hold one already unless
    ``overwrite``, whose frames are then removed (stale frames, or another image format, would mix into
    the new sequence), and never a recording (frames without gt/)."""
    old = existing_frame_files(out)
    if old and not overwrite:
        click.echo(f"error: {out} already holds a sequence ({len(old)} files); give --overwrite to replace it", err=True)
        raise SystemExit(2)
    if any(p.parent.name == "left" for p in old) and not any(p.parent.name == "gt" for p in old):
        # frames without a true disparity are no render of ours: a camera's recording, which nothing can make again
        click.echo(f"error: {out} holds frames without ground truth (gt/), a recording rather than a render: "
                   f"--overwrite replaces only rendered sequences; choose a new folder", err=True)
        raise SystemExit(2)
    for path in old:
        path.unlink()
    problem = make_folder(out)
    if problem is not None:
        click.echo(f"error: {problem}", err=True)
        raise SystemExit(2)


def refuse_bad_ranges(ranges) -> None:
    """A one-line error (exit 2) for the first range option given (name, (MIN, MAX) or None, lowest or None,
    highest or None) whose MIN exceeds its MAX or whose ends leave the bounds."""
    for name, pair, low, high in ranges:
        if pair is None:
            continue
        if pair[0] > pair[1]:
            click.echo(f"error: {name}: MIN {pair[0]:g} is larger than MAX {pair[1]:g}", err=True)
            raise SystemExit(2)
        if low is not None and pair[0] < low:
            click.echo(f"error: {name}: {pair[0]:g} is below the smallest allowed, {low:g}", err=True)
            raise SystemExit(2)
        if high is not None and pair[1] > high:
            click.echo(f"error: {name}: {pair[1]:g} is beyond the largest allowed, {high:g}", err=True)
            raise SystemExit(2)


def discard_and_fail(out: Path, exc: Exception) -> None:
    """End a render that failed with a one-line error (exit 2), the frames it wrote to OUT removed again:
    half a sequence would evaluate as a whole one."""
    written = existing_frame_files(out)
    for path in written:
        path.unlink(missing_ok=True)
    frames_written = sum(p.parent.name == "left" for p in written)
    gone = {0: "", 1: "; the frame written before it was removed again"}.get(
        frames_written, f"; the {frames_written} frames written before it were removed again")
    click.echo(f"error: {exc}{gone}", err=True)
    raise SystemExit(2) from None


def register(cli: click.Group) -> None:
    if "sim" in cli.commands:
        return

    @cli.group("sim")
    def sim_group() -> None:
        """Synthetic stereo scenes of steel plates with exact ground truth."""

    @sim_group.command("generate")
    @click.argument("out", type=click.Path(file_okay=False, path_type=Path))
    @click.option("--frames", default=10, show_default=True, type=click.IntRange(min=1), help="Number of frames.")
    @click.option("--seed", default=0, show_default=True, type=click.IntRange(0), help="Random seed (the output is a function of it).")
    @click.option("--distance-mm", default=400.0, show_default=True, type=Finite(min=100.0, max=MAX_DISTANCE_MM),
                  help="Plate distance at the image centre (jittered by -20..+50 mm per frame unless --no-jitter).")
    @click.option("--tilt-deg", default=5.0, show_default=True, type=Finite(-30.0, 30.0),
                  help="Plate tilt about the image x axis (jittered by -5..+3 deg, floored at 0, unless --no-jitter).")
    @click.option("--jitter/--no-jitter", default=True, show_default=True,
                  help="Vary distance, tilt and a small yaw per frame.")
    @click.option("--neu-det", "neu_det", default="../shared/data/neu-det", show_default=True,
                  type=click.Path(path_type=Path), help="NEU-DET folder (val crops give the defects' appearance).")
    @click.option("--synthetic-defects", is_flag=True,
                  help="Do not use NEU-DET: draw stand-in defect appearances instead.")
    @click.option("--width", default=672, show_default=True, type=click.IntRange(32, MAX_WIDTH),
                  help="Frame width in pixels, up to the ZED's largest mode (2K). The focal length scales with it, "
                       "and with it the nearest plate whose disparity the 16-bit ground truth holds (164 mm at WVGA, "
                       "539 mm at 2K).")
    @click.option("--height", default=376, show_default=True, type=click.IntRange(32, MAX_HEIGHT),
                  help="Frame height in pixels, likewise.")
    @click.option("--image-format", type=click.Choice(["png", "jpg"]), default="png", show_default=True,
                  help="left/right images as lossless PNG or JPEG quality 95 (GT disparity is always 16-bit PNG).")
    @click.option("--overwrite", is_flag=True,
                  help="Replace the frames of an existing sequence in OUT (otherwise that is an error).")
    @click.option("--supersample", default=2, show_default=True, type=click.IntRange(1, 4),
                  help="Rays per pixel along each axis (anti-aliasing).")
    @click.option("--distance-range-mm", nargs=2, type=FINITE, default=None, metavar="NEAR FAR",
                  help="Evaluation set: plate distance drawn uniformly per frame (instead of --distance-mm).")
    @click.option("--defect-size-px", nargs=2, type=FINITE, default=None, metavar="MIN MAX",
                  help="Evaluation set: each side of every defect's box drawn uniformly, in frame pixels.")
    @click.option("--depth-range-mm", nargs=2, type=FINITE, default=None, metavar="MIN MAX",
                  help="Evaluation set: every frame carries defects (see --defects-per-frame) whose depth is drawn "
                       "uniformly (+ below the surface, - raised), instead of the demo's plan of sound, shallow and "
                       "deep plates.")
    @click.option("--defects-per-frame", nargs=2, type=click.IntRange(1, 6), default=(1, 3), show_default=True,
                  metavar="MIN MAX", help="With --depth-range-mm: defects per frame, drawn uniformly.")
    @click.option("--texture-contrast", default=1.0, show_default=True, type=Finite(0.05, 3.0),
                  help="Scale of the plate texture's variation (0.3: polished, low-texture metal).")
    @click.option("--grain-angle-deg", default=0.0, show_default=True, type=Finite(-180.0, 180.0),
                  help="The plate's rolling direction (its streaks) turned this far from down the image, where they "
                       "cross the cameras' baseline, towards its rows (90: along the baseline, which leaves the "
                       "matcher the fine grain alone).")
    @click.option("--flat-floor", nargs=2, type=FINITE, default=None, metavar="MIN MAX",
                  help="Evaluation set: the share of each defect's half-size that is flat floor, drawn per defect "
                       "(the wall rises over the rest; near 1: a flat-bottomed pit with a steep wall). Default: "
                       "0.55 for every defect.")
    @click.option("--round-defects", is_flag=True, default=False,
                  help="Evaluation set: every defect an ellipse (a round pit or bump) instead of its class's "
                       "squarer outline, so that the central part of its box the depth is measured on reaches "
                       "further into its wall.")
    @click.option("--defect-aspect", nargs=2, type=FINITE, default=None, metavar="MIN MAX",
                  help="Evaluation set: each defect's length over its width, drawn uniformly (a groove: 4 or more); "
                       "its length is drawn from --defect-size-px, which it needs.")
    @click.option("--defect-angle-deg", nargs=2, type=FINITE, default=None, metavar="MIN MAX",
                  help="Evaluation set: each defect's outline turned on the plate by an angle drawn uniformly (45: "
                       "a groove running diagonally across its box, which then holds the surface beside it too); "
                       "--defect-size-px gives its length and width before it is turned.")
    @click.option("--rectification-error-px", default=0.0, show_default=True, type=Finite(-5.0, 5.0),
                  help="The right eye's rows this far below the left's (what a real camera's rectification "
                       "leaves, a few tenths of a pixel; 0: exactly rectified).")
    @click.option("--noise-sigma", default=None, type=Finite(0.0, 20.0),
                  help="Grey levels of Gaussian noise added to each eye (default: drawn per frame, 1.5-2; 0: none "
                       "but the 8-bit rounding).")
    @click.option("--specular/--no-specular", default=True, show_default=True,
                  help="The point light's highlight and sheen on the steel, which each eye sees elsewhere "
                       "(off: a matte plate).")
    @click.option("--lens-blur-px", default=0.0, show_default=True, type=Finite(0.0, 3.0),
                  help="The optics' blur (Gaussian sigma, px) before the pixels integrate the light (0: the "
                       "pixels alone, sharper than a real lens gives).")
    @click.option("--motion-blur-px", default=0.0, show_default=True, type=Finite(0.0, 20.0),
                  help="How far the plate moves across the image while the shutters are open (the conveyor's speed "
                       "times the exposure, in pixels), both eyes alike; 0: it stands still.")
    @click.option("--motion-angle-deg", default=90.0, show_default=True, type=Finite(-180.0, 180.0),
                  help="Which way it moves: 90 down the image, 0 along its rows (along the cameras' baseline).")
    @click.option("--baseline-mm", default=120.0, show_default=True, type=Finite(20.0, 500.0),
                  help="The eyes this far apart: the ZED's 120 mm, or another camera's (a ZED Mini's 63 mm), with the "
                       "same optics.")
    @click.option("--captures", default=1, show_default=True, type=click.IntRange(1, 1000),
                  help="Each plate captured this many times in a row, the sensor's noise drawn anew each time (a "
                       "plate standing still under the camera: what `inspect eval repeatability` reads). --frames "
                       "plates make frames x captures frames.")
    @click.option("--capture-drift-px", default=0.0, show_default=True, type=Finite(-1.0, 1.0),
                  help="With --captures: each capture's right eye this much further right than the one before (a "
                       "camera whose calibration drifts as it warms up; the truth stays the scene's).")
    def generate(out, frames, seed, distance_mm, tilt_deg, jitter, neu_det, synthetic_defects, width, height,
                 image_format, overwrite, supersample, distance_range_mm, defect_size_px, depth_range_mm,
                 defects_per_frame, texture_contrast, grain_angle_deg, flat_floor, round_defects, defect_aspect,
                 defect_angle_deg, rectification_error_px, noise_sigma, specular, lens_blur_px, motion_blur_px,
                 motion_angle_deg, baseline_mm, captures, capture_drift_px) -> None:
        """Render a sequence folder OUT: calib.yaml, left/, right/, gt/ (exact left disparity), labels/.

        The defaults render the demo's plan (sound, shallow and deep plates around 400 mm); the range
        options make an evaluation set for ``inspect eval depth``."""
        from sim.generate import (DISTANCE_JITTER_MM, CameraModel, EvalRanges, GenerateError, generate_sequence,
                                  largest_defect_px, nearest_plate_mm, zed_calibration)
        from sim.neu_crops import NeuDetError

        refuse_bad_ranges((("--distance-range-mm", distance_range_mm, 100.0, MAX_DISTANCE_MM),
                           ("--defect-size-px", defect_size_px, 4.0, None),
                           ("--depth-range-mm", depth_range_mm, -MAX_DEPTH_MM, MAX_DEPTH_MM),
                           ("--defects-per-frame", defects_per_frame, 1, None),
                           ("--flat-floor", flat_floor, 0.0, None),
                           ("--defect-aspect", defect_aspect, 1.0, None),
                           ("--defect-angle-deg", defect_angle_deg, -180.0, 180.0)))
        if capture_drift_px and captures < 2:
            click.echo("error: --capture-drift-px: a drift from capture to capture needs --captures 2 or more", err=True)
            raise SystemExit(2)
        rays = width * height * supersample**2
        if rays > MAX_RAYS:
            click.echo(f"error: --supersample {supersample} at {width}x{height} casts {rays / 1e6:.0f} M rays per eye, "
                       f"more than the {MAX_RAYS / 1e6:.0f} M that fit about 5 GB of memory: a lower --supersample or a "
                       f"smaller frame", err=True)
            raise SystemExit(2)
        largest = largest_defect_px(width, height)
        if defect_size_px is not None and defect_size_px[1] >= largest:
            click.echo(f"error: --defect-size-px: a side of {defect_size_px[1]:g} px does not fit a {width}x{height} "
                       f"frame with room for the ring around it (below {largest:.0f} px)", err=True)
            raise SystemExit(2)
        nearest = nearest_plate_mm(zed_calibration(width, height, baseline_mm))
        if distance_range_mm is not None:
            option, plate, jittered = f"--distance-range-mm {distance_range_mm[0]:g}", distance_range_mm[0], ""
        elif jitter:
            option, plate = f"--distance-mm {distance_mm:g}", distance_mm + DISTANCE_JITTER_MM[0]
            jittered = f" jittered by {DISTANCE_JITTER_MM[0]:g} mm,"
        else:
            option, plate, jittered = f"--distance-mm {distance_mm:g}", distance_mm, ""
        if plate < nearest:
            click.echo(f"error: {option}:{jittered} a plate at {plate:g} mm is nearer than the {nearest:.0f} mm whose "
                       f"disparity the ground truth's 16-bit PNG holds at {width}x{height}: plates from {nearest:.0f} "
                       f"mm on, or a narrower frame", err=True)
            raise SystemExit(2)
        if flat_floor is not None and flat_floor[1] >= 1.0:
            click.echo(f"error: --flat-floor: {flat_floor[1]:g} leaves no wall (give a share below 1)", err=True)
            raise SystemExit(2)
        if defect_aspect is not None and defect_size_px is None:
            click.echo("error: --defect-aspect: needs --defect-size-px, which gives each defect's length", err=True)
            raise SystemExit(2)
        ranges = EvalRanges(distance_mm=distance_range_mm, defect_px=defect_size_px, depth_mm=depth_range_mm,
                            defects_per_frame=tuple(defects_per_frame),
                            flat_floor=None if flat_floor is None else tuple(flat_floor), round_defects=round_defects,
                            aspect=None if defect_aspect is None else tuple(defect_aspect),
                            angle_deg=None if defect_angle_deg is None else tuple(defect_angle_deg))

        if not synthetic_defects and not Path(neu_det).is_dir():
            click.echo(f"error: NEU-DET folder not found: {neu_det} (give --neu-det DIR or --synthetic-defects)", err=True)
            raise SystemExit(2)
        prepare_folder(out, overwrite)
        start = time.perf_counter()
        try:
            generate_sequence(
                out, frames=frames, seed=seed, distance_mm=distance_mm, tilt_deg=tilt_deg,
                neu_det=None if synthetic_defects else neu_det, width=width, height=height, jitter=jitter,
                supersample=supersample, image_format=image_format, log=click.echo, ranges=ranges,
                texture_contrast=texture_contrast, grain_angle_deg=grain_angle_deg,
                camera=CameraModel(noise_sigma, specular, lens_blur_px, rectification_error_px, motion_blur_px,
                                   motion_angle_deg), captures=captures, baseline_mm=baseline_mm,
                capture_drift_px=capture_drift_px,
            )
        except (NeuDetError, GenerateError, OSError) as exc:  # OSError: a full disk, the folder removed under it
            discard_and_fail(out, exc)
        click.echo(f"wrote {frames * captures} frames to {out} in {time.perf_counter() - start:.1f} s")

    @sim_group.command("raycast")
    @click.argument("out", type=click.Path(file_okay=False, path_type=Path))
    @click.option("--kind", type=click.Choice(["textured", "low"]), default="textured", show_default=True,
                  help="textured: pits 30-80 px at 350-650 mm; low: faint texture, pits 10-25 px at 380-460 mm")
    @click.option("--frames", default=8, show_default=True, type=click.IntRange(1, 1000))
    @click.option("--seed", default=0, show_default=True, type=click.IntRange(0))
    @click.option("--image-format", type=click.Choice(["png", "jpg"]), default="png", show_default=True,
                  help="left/right images as lossless PNG or JPEG quality 95, as a camera's pipeline may save them "
                       "(the true disparity is always a 16-bit PNG)")
    @click.option("--overwrite", is_flag=True, help="replace the frames of a sequence already in OUT")
    @click.option("--distance-range-mm", nargs=2, type=FINITE, default=None, metavar="NEAR FAR",
                  help="plate distance drawn uniformly per frame instead of the kind's (300-1200 mm)")
    @click.option("--wall-shade", type=Finite(0.05, 3.0), default=None,
                  help="a pit wall's grey level over the plate's (default 0.55, a wall turned from the light; above 1: "
                       "lit)")
    @click.option("--noise-sigma", type=Finite(0.0, 20.0), default=None,
                  help="each eye's sensor noise, grey levels (default 1.5)")
    @click.option("--exposure", nargs=2, type=FINITE, default=None, metavar="GAIN OFFSET",
                  help="the right eye's exposure against the left's (default 1.03 2; gain 0.5-2, offset -50-50)")
    @click.option("--texel-mm", type=Finite(0.02, 2.0), default=None,
                  help="the texture's finest detail on the plate, mm (default 0.25; a pixel spans 1-2 mm)")
    @click.option("--vignetting", type=Finite(0.0, 0.8), default=0.0, show_default=True,
                  help="how much darker each eye sees the frame's corners than its centre")
    def raycast(out, kind, frames, seed, image_format, overwrite, distance_range_mm, wall_shade, noise_sigma,
                exposure, texel_mm, vignetting) -> None:
        """Render a labelled sequence with the second, independent renderer (sim/raycast.py): flat-bottomed
        pits with vertical walls, ray cast, for checking ``inspect eval depth`` against plates that
        ``inspect sim generate`` did not draw. The look options light and see the same scene otherwise."""
        from sim.raycast import KINDS, MAX_TEXELS, Look, render_sequence, texture_texels

        refuse_bad_ranges((("--distance-range-mm", distance_range_mm, 300.0, 1200.0),))
        if exposure is not None and not (0.5 <= exposure[0] <= 2.0 and -50.0 <= exposure[1] <= 50.0):
            click.echo(f"error: --exposure: gain {exposure[0]:g} must lie in 0.5-2 and offset {exposure[1]:g} in -50-50",
                       err=True)
            raise SystemExit(2)
        given = dict(wall_shade=wall_shade, noise_sigma=noise_sigma, texel_mm=texel_mm, vignetting=vignetting,
                     **({} if exposure is None else dict(right_gain=exposure[0], right_offset=exposure[1])))
        look = Look(**{name: value for name, value in given.items() if value is not None})  # the rest as Look's own
        far = KINDS[kind].distance_mm[1] if distance_range_mm is None else distance_range_mm[1]
        texels = texture_texels(far, look.texel_mm)
        if texels > MAX_TEXELS:
            click.echo(f"error: --texel-mm {look.texel_mm:g}: a plate {far:g} mm away needs a texture of {texels} x "
                       f"{texels} texels, beyond the {MAX_TEXELS} a side that fit a few GB of memory: a larger "
                       f"--texel-mm or nearer plates", err=True)
            raise SystemExit(2)
        prepare_folder(out, overwrite)
        start = time.perf_counter()
        try:
            render_sequence(out, kind, frames, seed, image_format=image_format, look=look,
                            distance_mm=distance_range_mm)
        except OSError as exc:  # a full disk, the folder removed under it
            discard_and_fail(out, exc)
        click.echo(f"wrote {frames} frames to {out} in {time.perf_counter() - start:.1f} s")

    @sim_group.command("faults")
    @click.argument("out", type=click.Path(file_okay=False, path_type=Path))
    @click.option("--parts", default=200, show_default=True, type=click.IntRange(10), help="parts to inspect in all")
    @click.option("--kills", default=2, show_default=True, type=click.IntRange(0), help="SIGKILLs on the way")
    @click.option("--damage", default=0.1, show_default=True, type=Finite(0.0, 1.0),
                  help="share of the frames whose left or right image is cut short")
    @click.option("--rate-fps", default=6.0, show_default=True, type=Finite(min=0.5))
    @click.option("--seed", default=0, show_default=True, type=click.IntRange(0))
    @click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="passed to inspect run")
    def faults(out, parts, kills, damage, rate_fps, seed, overrides) -> None:
        """The demo line under faults (damaged frames, a PLC link cut at random, the process killed and
        restarted), then an account of every part: exit 0 when each reject was delivered or alarmed, no
        damaged frame passed and the store is intact; the account is saved as OUT/faults.json."""
        from core.commands.inspection import _load, fail
        from sim.faults import RECIPE, FaultsError, run_faults

        if kills > parts:  # each kill lands between two parts: more would only restart a process that did nothing
            fail(f"--kills: at most one per part ({kills} kills for --parts {parts})")
        _load(RECIPE, tuple(overrides))  # a bad --set is said here, before anything is rendered or started
        try:
            report = run_faults(out, parts, kills, seed, damage, tuple(overrides), rate_fps, log=click.echo)
        except FaultsError as exc:
            fail(str(exc))
        for line in report.lines():
            click.echo(line)
        click.echo(f"{'every part accounted for' if report.ok else 'NOT every part accounted for'}; "
                   f"saved {out / 'faults.json'}")
        raise SystemExit(0 if report.ok else 1)
