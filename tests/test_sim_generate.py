"""The synthetic scene generator: determinism, exact GT, labels (small frames, synthetic defects)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from core.depth import DepthRule, measure_defect
from core.types import Detection
from drivers.sequence_folder import list_frames, read_calibration, read_disparity_png, read_image
from sim.generate import (
    BELOW_CLASSES, FrameSpec, _Deck, build_scene, generate_sequence, plan_frame, render_frame, zed_calibration,
)
from sim.neu_crops import NEU_CLASSES
from sim.render import render_pair
from sim.scene import heightfield_patch

W, H = 320, 180  # half WVGA: same field of view, small enough to be fast


def _warp_right(right: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    h, w = disparity.shape
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(right, uu - disparity.astype(np.float32), vv, cv2.INTER_LINEAR, borderValue=np.nan)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "seq"
    labels = generate_sequence(out, frames=4, seed=3, width=W, height=H)
    return out, labels


def test_same_seed_same_arrays_and_prefix(sequence, tmp_path):
    out, labels = sequence
    again = generate_sequence(tmp_path / "again", frames=2, seed=3, width=W, height=H)
    assert again == labels[:2]
    for fid in ("000000", "000001"):
        for sub in ("left", "right", "gt"):
            a = cv2.imread(str(out / sub / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
            b = cv2.imread(str(tmp_path / "again" / sub / f"{fid}.png"), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(a, b), (sub, fid)
    other = generate_sequence(tmp_path / "other", frames=1, seed=4, width=W, height=H)
    left0 = cv2.imread(str(out / "left" / "000000.png"))
    assert not np.array_equal(left0, cv2.imread(str(tmp_path / "other" / "left" / "000000.png")))
    assert other[0]["distance_mm"] != labels[0]["distance_mm"]


def test_sequence_folder_format(sequence):
    out, labels = sequence
    calib = read_calibration(out)
    assert calib["width"] == W and calib["height"] == H and calib["doffs"] == 0.0
    assert calib["baseline_mm"] == 120.0 and calib["focal_px"] == pytest.approx(350.06 * W / 672)
    assert calib["cx"] == (W - 1) / 2 and calib["cy"] == (H - 1) / 2
    frames = list_frames(out)
    assert [f.frame_id for f in frames] == ["000000", "000001", "000002", "000003"]
    for f in frames:
        assert read_image(f.left).shape == (H, W, 3) and read_image(f.right).shape == (H, W, 3)
        gt = read_disparity_png(f.gt)
        assert gt.shape == (H, W) and np.isfinite(gt).all()
        lab = json.loads(f.labels.read_text())
        assert lab["frame_id"] == f.frame_id
        assert set(lab) >= {"frame_id", "distance_mm", "tilt_deg", "defects"}


def test_labels_consistent(sequence):
    out, labels = sequence
    calib = zed_calibration(W, H)
    n_defects = 0
    for lab in labels:
        gt = read_disparity_png(out / "gt" / f"{lab['frame_id']}.png")
        for d in lab["defects"]:
            n_defects += 1
            x0, y0, x1, y1 = d["box"]
            assert 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H
            assert d["class"] in NEU_CLASSES and d["source"] == "synthetic"
            assert d["deviation_mm"] is not None and d["distance_mm"] is not None
            assert np.sign(d["deviation_mm"]) == np.sign(d["design_depth_mm"])
            assert abs(d["deviation_mm"]) <= abs(d["design_depth_mm"]) + 0.03
            assert abs(d["deviation_mm"]) >= 0.7 * abs(d["design_depth_mm"])
            assert abs(d["distance_mm"] - lab["distance_mm"]) < 60
            # the labels are measure_defect on the GT file as stored
            m = measure_defect(gt, Detection(d["class"], 1.0, tuple(d["box"])), calib, DepthRule())
            assert m.deviation_mm == pytest.approx(d["deviation_mm"], abs=1e-3)
            assert m.distance_mm == pytest.approx(d["distance_mm"], abs=1e-3)
    assert n_defects >= 3


def _pair_residual(nuisances: bool):
    calib = zed_calibration(W, H)
    rng = np.random.default_rng(7)
    spec = FrameSpec(410.0, 6.0, 1.5, [("pitted_surface", 2.5), ("scratches", 1.0)])
    scene = build_scene(rng, calib, spec, None)
    if not nuisances:
        scene.lighting.spec_broad = scene.lighting.spec_core = 0.0
    left, right, disparity, hits = render_pair(scene, rng, ss=2, nuisances=nuisances)
    plate = hits.on_plate.reshape(H, W)
    lg, rg = left[..., 0].astype(np.float32), right[..., 0].astype(np.float32)

    def residual(shift: float) -> float:
        warped = _warp_right(rg, disparity - shift)
        ok = np.isfinite(warped) & plate
        gain, offset = np.polyfit(warped[ok], lg[ok], 1)  # exposure difference between the eyes
        return float(np.median(np.abs(lg[ok] - (gain * warped[ok] + offset))))

    return residual, lg, rg


def test_right_image_is_the_left_warped_by_gt_exactly():
    """Without noise, highlight and exposure difference the GT warp reproduces the left image up to
    resampling, and any sub-pixel shift of the GT makes it worse."""
    residual, _, _ = _pair_residual(nuisances=False)
    exact = residual(0.0)
    assert exact < 2.0
    for shift in (-0.25, 0.25, 1.0):
        assert exact < 0.8 * residual(shift), shift


def test_a_rectification_error_puts_the_right_eyes_rows_that_far_below():
    calib = zed_calibration(W, H)
    spec = FrameSpec(410.0, 6.0, 1.5, [("pitted_surface", 2.5)])
    exact = render_pair(build_scene(np.random.default_rng(7), calib, spec, None), None, nuisances=False)[1]
    off = render_pair(build_scene(np.random.default_rng(7), calib, spec, None), None, nuisances=False,
                      rectification_error_px=0.5)[1]
    exact, off = exact[..., 0].astype(np.float32), off[..., 0].astype(np.float32)
    inner = (slice(8, -8), slice(8, -8))

    def misfit(rows: float) -> float:  # the exact eye moved down by ``rows`` against the offset one
        moved = cv2.warpAffine(exact, np.float32([[1, 0, 0], [0, 1, rows]]), exact.shape[::-1],
                               flags=cv2.INTER_LANCZOS4)
        return float(np.mean(np.abs(moved - off)[inner]))

    best = misfit(0.5)  # the highlight and the sampling leave a floor: the least of the rows tried
    assert best < min(misfit(0.4), misfit(0.6)) and best < 0.6 * min(misfit(0.0), misfit(1.0))


def test_right_image_with_nuisances_still_matches_gt():
    residual, lg, rg = _pair_residual(nuisances=True)
    exact = residual(0.0)
    assert exact < 6.0  # sensor noise in both eyes, resampling, the highlight at different places
    assert exact < 0.75 * residual(1.0)
    assert exact < residual(0.3) and exact < residual(-0.3)
    assert np.median(rg) > np.median(lg)  # the right eye's gain/offset


def test_plate_centre_distance_and_tilt(tmp_path):
    labels = generate_sequence(tmp_path / "s", frames=1, seed=0, distance_mm=430.0, tilt_deg=6.0,
                               width=W, height=H, jitter=False)
    assert labels[0]["distance_mm"] == 430.0 and labels[0]["tilt_deg"] == 6.0 and labels[0]["defects"] == []
    gt = read_disparity_png(tmp_path / "s" / "gt" / "000000.png")
    calib = zed_calibration(W, H)
    # cx, cy are pixel-centre coordinates ((W-1)/2): the centre disparity is the interpolated 2x2 block
    d_centre = float(gt[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1].mean())
    assert calib.distance_mm(d_centre) == pytest.approx(430.0, abs=0.5)
    # tilt about x: disparity changes along v (Z grows downwards for a positive tilt), not along u
    col = gt[:, W // 2]
    a = np.polyfit(np.arange(H), col, 1)[0]
    row = gt[H // 2, W // 4 : 3 * W // 4]
    assert abs(np.polyfit(np.arange(row.size), row, 1)[0]) < 1e-3
    z_top, z_bottom = calib.distance_mm(col[5]), calib.distance_mm(col[-6])
    expected = np.tan(np.radians(6.0))  # dZ/dY for a plane tilted by 6 degrees
    y_top, y_bottom = (5 - calib.cy) / calib.focal_px * z_top, (H - 6 - calib.cy) / calib.focal_px * z_bottom
    assert (z_bottom - z_top) / (y_bottom - y_top) == pytest.approx(expected, rel=0.02)
    assert a != 0


def test_plan_covers_every_class_and_splits_pass_reject():
    rng = np.random.default_rng(0)
    decks = (_Deck(NEU_CLASSES, rng), _Deck(BELOW_CLASSES, rng))
    specs = [plan_frame(rng, i, 400.0, 5.0, True, decks) for i in range(10)]
    classes = {c for s in specs for c, _ in s.requests}
    assert classes == set(NEU_CLASSES)
    depths = [d for s in specs for _, d in s.requests]
    assert all(abs(d) <= 0.7 or d >= 1.8 for d in depths)
    assert any(d >= 1.8 for d in depths) and any(abs(d) <= 0.7 for d in depths)
    assert sum(1 for s in specs if not s.requests) >= 2
    assert all(380 <= s.distance_mm <= 450 and 0 <= s.tilt_deg <= 8 for s in specs)


def test_raised_defect_has_negative_deviation():
    calib = zed_calibration(W, H)
    rng = np.random.default_rng(11)
    spec = FrameSpec(400.0, 3.0, 0.0, [("rolled-in_scale", -1.2)])
    _, _, gt, labels, _ = render_frame(rng, calib, spec, None, "000000")
    (d,) = labels["defects"]
    assert d["shape"] == "raised_scale" and -1.2 - 0.03 <= d["deviation_mm"] < -0.9


def test_rays_land_on_the_heightfield():
    """Every plate hit satisfies the surface equation (P - P0).n = h(s, t), also on steep defect walls."""
    from sim.render import _sample, pixel_grid, trace

    calib = zed_calibration(W, H)
    rng = np.random.default_rng(2)
    scene = build_scene(rng, calib, FrameSpec(390.0, 8.0, 2.0, [("pitted_surface", 3.0), ("scratches", 2.5)]), None)
    assert scene.defects
    for origin in (np.zeros(3), np.array([calib.baseline_mm, 0.0, 0.0])):
        uu, vv = pixel_grid(calib, 2)
        hits = trace(scene, origin, uu, vv)
        p = np.stack(hits.point, -1)
        h = _sample(scene.height, *scene.to_texel(hits.s, hits.t))
        err = np.abs((p - scene.p0) @ scene.n - h)[hits.on_plate]
        assert err.max() < 1e-3
        assert (np.abs(h) > 0.5).any()  # the defects are in view


def test_evaluation_ranges_are_respected(tmp_path):
    from sim.generate import EvalRanges

    ranges = EvalRanges(distance_mm=(350.0, 650.0), defect_px=(20.0, 40.0), depth_mm=(0.5, 1.5), defects_per_frame=(1, 2))
    labels = generate_sequence(tmp_path / "eval", frames=4, seed=8, width=336, height=188, ranges=ranges, supersample=1)
    for lab in labels:
        assert 350.0 <= lab["distance_mm"] <= 650.0
        assert 1 <= len(lab["defects"]) <= 2 and lab["sensor"]["noise_sigma"] > 0
        for d in lab["defects"]:
            assert 0.5 <= d["design_depth_mm"] <= 1.5 and d["class"] in BELOW_CLASSES
            x0, y0, x1, y1 = d["box"]
            # the box is the footprint's projection: within a few pixels of the drawn size
            assert 20.0 - 3 <= x1 - x0 <= 40.0 + 3 and 20.0 - 3 <= y1 - y0 <= 40.0 * 1.2 + 3


def test_texture_contrast_flattens_the_plate_and_the_default_plan_is_unchanged(tmp_path):
    calib = zed_calibration(W, H)
    spec = FrameSpec(400.0, 0.0, 0.0, [])
    low = build_scene(np.random.default_rng(3), calib, spec, None, texture_contrast=0.3)
    base = build_scene(np.random.default_rng(3), calib, spec, None)
    assert np.std(low.albedo) == pytest.approx(0.3 * np.std(base.albedo), rel=0.02)
    assert np.array_equal(base.albedo, build_scene(np.random.default_rng(3), calib, spec, None, texture_contrast=1.0).albedo)
    # no range given: the demo's plan, draw for draw
    plain = plan_frame(np.random.default_rng(5), 2, 400.0, 5.0, True, (_Deck(NEU_CLASSES, np.random.default_rng(0)),
                                                                       _Deck(BELOW_CLASSES, np.random.default_rng(1))))
    assert plain.sizes_px is None and [c for c, _ in plain.requests] and plain.requests[0][1] >= 1.8


def test_raised_depths_draw_raised_classes(tmp_path):
    from sim.generate import RAISED_CLASSES, EvalRanges

    rng = np.random.default_rng(4)
    decks = (_Deck(NEU_CLASSES, rng), _Deck(BELOW_CLASSES, rng), _Deck(RAISED_CLASSES, rng))
    spec = plan_frame(rng, 0, 400.0, 5.0, False, decks, EvalRanges(depth_mm=(-1.0, -0.5), defects_per_frame=(3, 3)))
    assert len(spec.requests) == 3 and all(c in RAISED_CLASSES and -1.0 <= d <= -0.5 for c, d in spec.requests)


def test_flat_floor_gives_flat_bottomed_pits_with_steep_walls(tmp_path):
    """``flat_floor``: the share of each half-size that is floor; near 1 the pit is flat to its rim."""
    from sim.generate import EvalRanges

    calib = zed_calibration(W, H)
    spec = FrameSpec(400.0, 0.0, 0.0, [("pitted_surface", 1.0)], [(40.0, 40.0)])
    share = {}
    for name, floor in (("default", None), ("flat", (0.9, 0.9))):
        scene = build_scene(np.random.default_rng(6), calib, spec, None, flat_floor=floor)
        (d,) = scene.defects
        assert d.plateau == pytest.approx(0.55 if floor is None else 0.9)
        inside = scene.height[scene.height > 1e-6]
        share[name] = float(np.mean(inside >= 0.999))  # of the footprint below the surface, the floor's share
    assert share["flat"] > share["default"] + 0.3
    labels = generate_sequence(tmp_path / "flat", frames=2, seed=2, width=336, height=188, supersample=1,
                               ranges=EvalRanges(depth_mm=(1.0, 2.0), flat_floor=(0.8, 0.95)))
    plateaus = [d["plateau"] for lab in labels for d in lab["defects"]]
    assert plateaus and all(0.8 <= p <= 0.95 for p in plateaus)
    # a flat floor under the whole region: the platform's deviation is the design depth
    assert all(abs(d["deviation_mm"] - d["design_depth_mm"]) < 0.05 for lab in labels for d in lab["defects"])


def test_round_defects_are_ellipses_whose_wall_reaches_into_the_measured_region(tmp_path):
    """``round_defects``: an ellipse's wall reaches the corners of the central 60 % of its box, which a
    class's squarer outline keeps on its floor."""
    from sim.generate import EvalRanges

    calib = zed_calibration(W, H)
    spec = FrameSpec(400.0, 0.0, 0.0, [("pitted_surface", 1.0)], [(40.0, 40.0)])
    depth_at_corner = {}
    for name, round_defects in (("class", False), ("round", True)):
        scene = build_scene(np.random.default_rng(6), calib, spec, None, round_defects=round_defects)
        (d,) = scene.defects
        assert d.exponent == (2.0 if round_defects else 4.0)
        (sc, tc), (a, b) = d.center, d.half
        depth_at_corner[name] = float(heightfield_patch(d, np.array([sc + 0.6 * a]), np.array([tc + 0.6 * b]))[0])
        assert float(heightfield_patch(d, np.array([sc]), np.array([tc]))[0]) == pytest.approx(1.0)
    assert depth_at_corner["round"] < depth_at_corner["class"] - 0.3
    labels = generate_sequence(tmp_path / "round", frames=1, seed=2, width=336, height=188, supersample=1,
                               ranges=EvalRanges(depth_mm=(1.0, 2.0), round_defects=True))
    assert labels[0]["defects"] and all(d["exponent"] == 2.0 for d in labels[0]["defects"])


def test_a_groove_turned_on_the_plate_crosses_its_box_and_its_truth_is_its_own_depth(tmp_path):
    """``aspect`` and ``angle_deg``: a long narrow outline turned by 45 degrees runs corner to corner of its
    box, whose central region then holds the surface beside it too; the label's deviation is the groove's
    where the region lies on it, not the region's median (the surface)."""
    from sim.generate import EvalRanges

    calib = zed_calibration(W, H)
    spec = FrameSpec(400.0, 0.0, 0.0, [("scratches", 2.0)], [(80.0, 12.0)], [45.0])
    scene = build_scene(np.random.default_rng(6), calib, spec, None, flat_floor=(0.8, 0.8))
    (d,) = scene.defects
    assert d.angle_deg == 45.0 and d.extent[0] == pytest.approx(d.extent[1])
    (sc, tc), a = d.center, d.half[0]
    along = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4)])
    on_axis = heightfield_patch(d, np.array([sc + 0.5 * a * along[0]]), np.array([tc + 0.5 * a * along[1]]))[0]
    corner = heightfield_patch(d, np.array([sc + 0.5 * a * along[0]]), np.array([tc - 0.5 * a * along[1]]))[0]
    assert on_axis == pytest.approx(2.0) and corner == 0.0  # along the diagonal, and not across it
    left, right, gt, labels, _ = render_frame(np.random.default_rng(7), calib, spec, None, "000000", ss=1,
                                              flat_floor=(0.8, 0.8))
    (label,) = labels["defects"]
    x0, y0, x1, y1 = label["box"]
    assert abs((x1 - x0) - (y1 - y0)) < 6 and label["angle_deg"] == 45.0
    truth = label["deviation_mm"]
    region_median = measure_defect(gt, Detection("scratches", 1.0, tuple(label["box"])), calib, DepthRule()).deviation_mm
    assert truth == pytest.approx(2.0, abs=0.1) and region_median < 1.0
    labels = generate_sequence(tmp_path / "grooves", frames=2, seed=2, width=336, height=188, supersample=1,
                               ranges=EvalRanges(depth_mm=(1.0, 2.0), defect_px=(40.0, 60.0), aspect=(4.0, 6.0),
                                                 angle_deg=(30.0, 60.0)))
    drawn = [dd for lab in labels for dd in lab["defects"]]
    assert drawn and all(30.0 <= dd["angle_deg"] <= 60.0 for dd in drawn)


def test_flat_floor_must_leave_a_wall(tmp_path):
    from click.testing import CliRunner

    from core.cli import _build

    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects", "--frames", "1",
                                      "--depth-range-mm", "1", "2", "--flat-floor", "0.9", "1.0"])
    assert result.exit_code == 2 and "--flat-floor" in result.output and "no wall" in result.output


def test_an_aspect_needs_the_size_it_divides_and_angles_stay_within_a_turn(tmp_path):
    from click.testing import CliRunner

    from core.cli import _build

    base = ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects", "--frames", "1", "--depth-range-mm", "1", "2"]
    result = CliRunner().invoke(_build(), base + ["--defect-aspect", "4", "8"])
    assert result.exit_code == 2 and "--defect-aspect" in result.output and "--defect-size-px" in result.output
    result = CliRunner().invoke(_build(), base + ["--defect-angle-deg", "0", "270"])
    assert result.exit_code == 2 and "--defect-angle-deg" in result.output and "180" in result.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("angle, across_over_along", [(0.0, (1.5, 4.0)), (90.0, (0.2, 0.5)), (45.0, (0.8, 1.25))])
def test_the_grain_turns_the_streaks_from_across_the_baseline_to_along_it(angle, across_over_along):
    calib = zed_calibration(W, H)
    spec = FrameSpec(400.0, 0.0, 0.0, [])
    albedo = build_scene(np.random.default_rng(3), calib, spec, None, grain_angle_deg=angle).albedo.astype(np.float64)
    # the albedo's columns run along the plate's s axis, the image's rows: streaks down the image vary along them
    along_rows, along_columns = np.mean(np.diff(albedo, axis=1) ** 2), np.mean(np.diff(albedo, axis=0) ** 2)
    low, high = across_over_along
    assert low < along_rows / along_columns < high
    base = build_scene(np.random.default_rng(3), calib, spec, None)
    if angle == 0.0:
        assert np.array_equal(albedo, base.albedo)  # the default plates, draw for draw
    else:
        assert np.std(albedo) == pytest.approx(np.std(base.albedo), rel=0.02)  # the same texture, turned


def test_the_camera_model_changes_only_what_it_names(tmp_path):
    """The same seed renders the same plates whatever the camera does; noise, highlight and lens blur
    each change the images the way they say."""
    from sim.generate import CameraModel, EvalRanges

    ranges = EvalRanges(depth_mm=(0.5, 1.5), defects_per_frame=(1, 2))

    def render(name, **camera):
        labels = generate_sequence(tmp_path / name, frames=2, seed=4, width=W, height=H, supersample=1,
                                   ranges=ranges, camera=CameraModel(**camera))
        frames = list_frames(tmp_path / name)
        return labels, [read_image(f.left).astype(np.float64)[..., 0] for f in frames]

    drawn, noisy = render("drawn")
    _, sharp = render("sharp", noise_sigma=0.0)
    matte_labels, matte = render("matte", noise_sigma=0.0, specular=False)
    _, blurred = render("blurred", noise_sigma=0.0, specular=False, lens_blur_px=0.8)
    assert [lab["defects"] for lab in matte_labels] == [lab["defects"] for lab in drawn]
    assert matte_labels[0]["sensor"]["noise_sigma"] == 0.0 and matte_labels[0]["specular"] is False
    for lab, a, b in zip(drawn, noisy, sharp):  # the noise drawn, as the labels say, and nothing else
        assert np.std(a - b) == pytest.approx(lab["sensor"]["noise_sigma"], rel=0.15)
    for a, b in zip(sharp, matte):  # the highlight only adds light
        assert (a - b).min() >= -1 and (a - b).max() > 5
    for a, b in zip(matte, blurred):  # the optics take contrast, not light
        assert np.mean(np.diff(b, axis=1) ** 2) < 0.7 * np.mean(np.diff(a, axis=1) ** 2)
        assert abs(np.mean(a) - np.mean(b)) < 1.0


def test_a_moving_plate_blurs_both_eyes_along_its_motion_alone(tmp_path):
    """The same plates; the exposure's travel takes the contrast along the motion and leaves it across."""
    from sim.generate import CameraModel, EvalRanges

    ranges = EvalRanges(depth_mm=(0.5, 1.5), defects_per_frame=(1, 2))

    def render(name, **camera):
        labels = generate_sequence(tmp_path / name, frames=1, seed=4, width=W, height=H, supersample=2,
                                   ranges=ranges, camera=CameraModel(noise_sigma=0.0, **camera))
        frame = list_frames(tmp_path / name)[0]
        return labels[0], [read_image(p).astype(np.float64)[..., 0] for p in (frame.left, frame.right)]

    still_labels, still = render("still")
    down_labels, down = render("down", motion_blur_px=3.0, motion_angle_deg=90.0)
    _, along = render("along", motion_blur_px=3.0, motion_angle_deg=0.0)
    assert down_labels["defects"] == still_labels["defects"] and "motion_blur_px" not in still_labels
    assert (down_labels["motion_blur_px"], down_labels["motion_angle_deg"]) == (3.0, 90.0)

    def energy(image, axis):
        return np.mean(np.diff(image, axis=axis) ** 2)

    for eye in (0, 1):  # both eyes alike
        kept = {name: [energy(image[eye], axis) / energy(still[eye], axis) for axis in (0, 1)]
                for name, image in (("down", down), ("along", along))}
        # the contrast along the motion goes; across it, what the texture's own grain shares between neighbours
        assert kept["down"][0] < 0.6 * kept["down"][1] and kept["along"][1] < 0.6 * kept["along"][0], kept
        assert abs(np.mean(down[eye]) - np.mean(still[eye])) < 1.0 and abs(np.mean(along[eye]) - np.mean(still[eye])) < 1.0


class TestMotionKernel:
    @pytest.mark.parametrize("length, angle", [(3.0, 0.0), (6.0, 90.0), (4.5, 30.0)])
    def test_a_centred_line_of_the_length_that_sums_to_one(self, length, angle):
        from sim.render import motion_kernel

        kernel = motion_kernel(length, angle).astype(np.float64)
        assert kernel.sum() == pytest.approx(1.0, abs=1e-6)
        r = kernel.shape[0] // 2
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        assert (kernel * xx).sum() == pytest.approx(0.0, abs=1e-6) and (kernel * yy).sum() == pytest.approx(0.0, abs=1e-6)
        a = np.deg2rad(angle)
        along = xx * np.cos(a) + yy * np.sin(a)
        across = -xx * np.sin(a) + yy * np.cos(a)
        # a uniform line's variance is length^2 / 12; the splatting and the line's samples add under a third of a
        # pixel squared
        assert length ** 2 / 12 <= (kernel * along ** 2).sum() < length ** 2 / 12 + 0.3
        assert (kernel * across ** 2).sum() < 0.2


class TestDisparityTheTruthCanHold:
    """A KITTI PNG holds disparities up to 255.996 px; a nearer plate's truth clipped there read as a farther,
    flat one (a 2K frame at 490 mm: every label 539 mm away and 0 mm deep)."""

    def _generate(self, tmp_path, *options):
        from click.testing import CliRunner

        from core.cli import _build

        return CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "s"), "--synthetic-defects", *options])

    def test_the_png_writer_refuses_what_it_would_clip(self, tmp_path):
        from drivers.sequence_folder import KITTI_MAX_DISPARITY, write_disparity_png

        write_disparity_png(tmp_path / "ok.png", np.full((4, 4), KITTI_MAX_DISPARITY, np.float32))
        assert read_disparity_png(tmp_path / "ok.png").max() == pytest.approx(KITTI_MAX_DISPARITY)
        with pytest.raises(ValueError, match=r"far\.png: a disparity of 281\.70 px does not fit"):
            write_disparity_png(tmp_path / "far.png", np.full((4, 4), 281.7, np.float32))
        assert not (tmp_path / "far.png").exists()

    @pytest.mark.parametrize("options, said", [
        (["--distance-range-mm", "400", "700", "--width", "2208", "--height", "1242"],
         "--distance-range-mm 400: a plate at 400 mm is nearer than the 539 mm"),
        (["--distance-mm", "170"], "--distance-mm 170: jittered by -20 mm, a plate at 150 mm is nearer than the 164 mm"),
        (["--distance-mm", "150", "--no-jitter"], "--distance-mm 150: a plate at 150 mm is nearer"),
    ])
    def test_a_range_too_near_is_refused_before_rendering(self, tmp_path, options, said):
        result = self._generate(tmp_path, "--frames", "1", *options)
        assert result.exit_code == 2 and said in result.output, result.output
        assert not (tmp_path / "s" / "calib.yaml").exists()

    def test_a_frame_tilted_too_near_stops_the_set_and_takes_its_frames_back(self, tmp_path):
        # seed 6: frames 0-2 lie beyond 164 mm, frame 3's tilted plate comes to 157 mm
        result = self._generate(tmp_path, "--frames", "4", "--seed", "6", "--distance-mm", "185", "--tilt-deg", "25",
                                "--height", "96", "--supersample", "1")
        assert result.exit_code == 2
        assert "frame 000003: the plate comes to 157 mm, 268.1 px of disparity" in result.output
        assert "the 3 frames written before it were removed again" in result.output
        assert not [p for p in (tmp_path / "s").rglob("*") if p.is_file()]

    def test_the_nearest_plate_that_fits_is_generated_whole(self, tmp_path):
        result = self._generate(tmp_path, "--frames", "1", "--distance-mm", "170", "--no-jitter", "--tilt-deg", "0",
                                "--height", "96", "--supersample", "1")
        assert result.exit_code == 0, result.output
        gt = read_disparity_png(tmp_path / "s" / "gt" / "000000.png")
        assert 240 < np.nanmax(gt) < 256
