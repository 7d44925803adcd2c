"""``sim/raycast.py``: the second, independent renderer, and ``inspect sim raycast``."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from core.cli import _build
from drivers.sequence_folder import read_calibration, read_labels
from sim import raycast


def _eyes(z0, axes, pits, texture):
    left = raycast.render_eye(0.0, z0, axes, pits, texture, supersample=2)
    right = raycast.render_eye(raycast.CALIB["baseline_mm"], z0, axes, pits, texture, supersample=2)
    return left, right


@pytest.fixture(scope="module")
def texture():
    return raycast.plate_texture(np.random.default_rng(0), 1100.0, raycast.KINDS["textured"])


class TestRenderEye:
    def test_a_plate_facing_the_camera_lies_at_its_disparity_in_the_right_eye(self, texture):
        z0 = 400.0
        left, right = _eyes(z0, raycast.rotation(0, 0), [], texture)
        assert left.shape == (raycast.CALIB["height"], raycast.CALIB["width"])
        d = raycast.CALIB["focal_px"] * raycast.CALIB["baseline_mm"] / z0  # 105.02 px
        x0 = 200  # a band the right eye sees: left column x is right column x - d
        band_l = left[100:228, x0:x0 + 256].astype(np.float64)
        band_r = right[100:228, x0 - 105:x0 - 105 + 256].astype(np.float64)
        (shift, rows), _ = cv2.phaseCorrelate(band_r, band_l)
        assert shift == pytest.approx(d - 105, abs=0.05)
        assert rows == pytest.approx(0.0, abs=0.05)

    def test_a_pits_floor_lies_at_the_floors_disparity_and_its_wall_is_darker(self, texture):
        z0 = 400.0
        scale = z0 / raycast.CALIB["focal_px"]
        pit = raycast.Pit(0.0, 0.0, 110 * scale, 70 * scale, 2.0, False)  # at the image centre, 220 x 140 px
        left, right = _eyes(z0, raycast.rotation(0, 0), [pit], texture)
        plain, _ = _eyes(z0, raycast.rotation(0, 0), [], texture)
        cx, cy = int(raycast.CALIB["cx"]), int(raycast.CALIB["cy"])
        d = raycast.CALIB["focal_px"] * raycast.CALIB["baseline_mm"] / (z0 + 2.0)
        band_l = left[cy - 48:cy + 48, cx - 64:cx + 64].astype(np.float64)
        band_r = right[cy - 48:cy + 48, cx - 64 - 104:cx + 64 - 104].astype(np.float64)
        (shift, _), _ = cv2.phaseCorrelate(band_r, band_l, cv2.createHanningWindow((128, 96), cv2.CV_64F))
        assert shift == pytest.approx(d - 104, abs=0.05)

    def test_the_wall_facing_an_eye_is_seen_darker_inside_the_mouth(self, texture):
        z0 = 400.0
        scale = z0 / raycast.CALIB["focal_px"]
        deep = raycast.Pit(0.0, 0.0, 110 * scale, 70 * scale, 8.0, False)
        left, _ = _eyes(z0, raycast.rotation(0, 0), [deep], texture)
        plain, _ = _eyes(z0, raycast.rotation(0, 0), [], texture)
        cx, cy = int(raycast.CALIB["cx"]), int(raycast.CALIB["cy"])
        # 8 mm of wall 126 mm right of the axis: a pixel or two of the left eye's view before the mouth's edge
        wall = np.s_[cy - 30:cy + 30, cx + 107:cx + 110]
        assert (left[wall].mean(axis=0) - plain[wall].mean(axis=0)).min() < -30
        floor = np.s_[cy - 30:cy + 30, cx - 100:cx - 90]  # its left wall is turned away: floor up to the edge
        assert abs(left[floor].mean() - plain[floor].mean()) < 10


class TestTrueDisparity:
    def test_the_plate_and_a_pits_floor_lie_at_their_disparities_and_its_walls_are_unknown(self):
        z0, depth = 400.0, 2.0
        scale = z0 / raycast.CALIB["focal_px"]
        pit = raycast.Pit(0.0, 0.0, 110 * scale, 70 * scale, depth, False)  # at the image centre, 220 x 140 px
        d = raycast.true_disparity(z0, raycast.rotation(0, 0), [pit])
        assert d.shape == (raycast.CALIB["height"], raycast.CALIB["width"]) and d.dtype == np.float32
        fb = raycast.CALIB["focal_px"] * raycast.CALIB["baseline_mm"]
        cx, cy = int(raycast.CALIB["cx"]), int(raycast.CALIB["cy"])
        assert d[10, 10] == pytest.approx(fb / z0, rel=1e-6)  # the plate
        assert d[cy, cx] == pytest.approx(fb / (z0 + depth), rel=1e-6)  # the floor
        # the mouth's pixels whose ray meets a wall on its way down: a pixel or two inside each side
        row = d[cy, cx - 115:cx + 115]
        walls = np.isnan(row)
        assert 0 < walls.sum() <= 6 and not np.isnan(d[:, :cx - 115]).any()
        assert np.isfinite(row[~walls]).all()

    def test_on_a_tilted_plate_the_labels_distance_is_the_truths_at_the_boxs_centre(self):
        rng = np.random.default_rng(6)
        axes = raycast.rotation(8, -8)
        z0 = 500.0
        pits, labels = raycast.plan_pits(rng, z0, axes, raycast.KINDS["textured"])
        d = raycast.true_disparity(z0, axes, pits)
        fb = raycast.CALIB["focal_px"] * raycast.CALIB["baseline_mm"]
        for label in labels:
            x0, y0, x1, y1 = label["box"]
            # a box counts pixel edges: its centre (x0 + x1) / 2 is pixel (x0 + x1) / 2 - 0.5's centre
            u, v = (x0 + x1) / 2 - 0.5, (y0 + y1) / 2 - 0.5
            iu, iv = int(np.floor(u)), int(np.floor(v))
            fu, fv = u - iu, v - iv
            # a plane's disparity is linear in the pixel's position: between four floor pixels, exact
            at = ((1 - fv) * ((1 - fu) * d[iv, iu] + fu * d[iv, iu + 1])
                  + fv * ((1 - fu) * d[iv + 1, iu] + fu * d[iv + 1, iu + 1]))
            assert fb / at == pytest.approx(label["distance_mm"], abs=2e-3)
        assert labels


class TestPlanPits:
    def test_pits_lie_in_the_right_eyes_view_apart_and_their_labels_are_their_geometry(self):
        rng = np.random.default_rng(3)
        for _ in range(20):
            z0 = rng.uniform(350, 650)
            pits, labels = raycast.plan_pits(rng, z0, raycast.rotation(5, -5), raycast.KINDS["textured"])
            assert 2 <= len(pits) <= 4
            for pit, label in zip(pits, labels):
                x0, y0, x1, y1 = label["box"]
                disparity = raycast.CALIB["focal_px"] * raycast.CALIB["baseline_mm"] / label["distance_mm"]
                assert x0 > disparity and x1 < raycast.CALIB["width"] and y0 > 0 and y1 < raycast.CALIB["height"]
                assert label["deviation_mm"] == pytest.approx(pit.depth, abs=5e-4)
                assert z0 * 0.85 < label["distance_mm"] < z0 * 1.15  # a plate tilted by 5 and -5°
            boxes = [label["box"] for label in labels]
            for i, a in enumerate(boxes):
                for b in boxes[i + 1:]:
                    assert a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1]


    def test_on_a_tilted_plate_the_distance_is_the_floors_where_the_boxs_centre_looks(self):
        # as the engine measures it: a ray through the box's centre, not the floor's own centre a pixel or two away
        rng = np.random.default_rng(6)
        f, cx, cy = raycast.CALIB["focal_px"], raycast.CALIB["cx"], raycast.CALIB["cy"]
        axes = raycast.rotation(8, -8)
        n = axes[:, 2]
        for _ in range(10):
            z0 = rng.uniform(350, 650)
            pits, labels = raycast.plan_pits(rng, z0, axes, raycast.KINDS["textured"])
            for pit, label in zip(pits, labels):
                x0, y0, x1, y1 = label["box"]
                z = label["distance_mm"]
                point = np.array([((x0 + x1) / 2 - 0.5 - cx) * z / f, ((y0 + y1) / 2 - 0.5 - cy) * z / f, z])
                # that point lies on the floor's plane, pit.depth below the plate's along its normal
                assert (point - np.array([0.0, 0.0, z0])) @ n == pytest.approx(pit.depth, abs=2e-3)

    def test_a_box_counts_pixel_edges_as_the_engine_does_centred_on_its_pit(self):
        # the engine's pixel u spans u to u + 1 (core.depth.region_weights); a box half a pixel off moves every
        # defect's distance along a tilted plate's slope
        rng = np.random.default_rng(5)
        f, cx, cy = raycast.CALIB["focal_px"], raycast.CALIB["cx"], raycast.CALIB["cy"]
        axes = raycast.rotation(0, 0)
        off_u, off_v = [], []
        for _ in range(30):
            z0 = rng.uniform(350, 650)
            pits, labels = raycast.plan_pits(rng, z0, axes, raycast.KINDS["textured"])
            for pit, label in zip(pits, labels):
                centre = np.array([0.0, 0.0, z0]) + pit.s * axes[:, 0] + pit.t * axes[:, 1]
                u, v = f * centre[0] / centre[2] + cx, f * centre[1] / centre[2] + cy  # pixel centres from 0
                x0, y0, x1, y1 = label["box"]
                off_u.append((x0 + x1) / 2 - (u + 0.5))
                off_v.append((y0 + y1) / 2 - (v + 0.5))
                assert label["distance_mm"] == pytest.approx(z0 + pit.depth, abs=1e-3)  # the floor, facing the eye
        assert np.abs(off_u).max() <= 0.5 + 1e-9 and np.abs(off_v).max() <= 0.5 + 1e-9  # whole pixels, outwards
        assert abs(np.mean(off_u)) < 0.1 and abs(np.mean(off_v)) < 0.1

def test_inspect_sim_raycast_writes_a_sequence_that_inspect_eval_depth_measures_within_its_uncertainty(tmp_path):
    out = tmp_path / "rc"
    result = CliRunner().invoke(_build(), ["sim", "raycast", str(out), "--frames", "1", "--seed", "4"])
    assert result.exit_code == 0, result.output
    calib = read_calibration(out)
    assert calib["camera"] == "ZED WVGA (ray cast)"
    labels = read_labels(out / "labels" / "000000.json", (calib["height"], calib["width"]))
    assert labels["sensor"]["noise_sigma"] == raycast.NOISE_SIGMA and labels["defects"]

    truth = cv2.imread(str(out / "gt" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert truth.dtype == np.uint16 and truth.shape == (calib["height"], calib["width"])

    again = CliRunner().invoke(_build(), ["sim", "raycast", str(out), "--frames", "1"])
    assert again.exit_code == 2 and "--overwrite" in again.output

    report = tmp_path / "eval"
    result = CliRunner().invoke(_build(), ["eval", "depth", str(out), "--out", str(report), "--threads", "1",
                                           "--set", "stereo.working_distance_mm=[300,700]", "--no-figure"])
    assert result.exit_code == 0, result.output
    rows = [r for r in json.loads((report / "depth_eval.json").read_text())["rows"] if r["method"] == "surface"]
    assert len(rows) == len(labels["defects"])
    for row in rows:
        assert row["deviation_mm"] is not None, row["note"]
        assert abs(row["deviation_mm"] - row["true_deviation_mm"]) < 3 * row["deviation_sigma_mm"]
        # with the true disparity its error splits into parts; a pit's walls are vertical, so the region inside
        # the box holds its floor alone
        assert row["error_ring_mm"] is not None and abs(row["error_extent_mm"]) < 0.05


def test_inspect_sim_raycast_saves_the_same_scene_as_jpeg(tmp_path):
    # a camera's pipeline may save JPEG: the seed's scene, its truth and labels those of its PNG
    png, jpg = tmp_path / "png", tmp_path / "jpg"
    for out, image_format in ((png, "png"), (jpg, "jpg")):
        result = CliRunner().invoke(_build(), ["sim", "raycast", str(out), "--frames", "1", "--seed", "4", "--kind",
                                               "low", "--image-format", image_format])
        assert result.exit_code == 0, result.output
    assert "JPEG quality 95" in read_calibration(jpg)["generator"]
    assert (jpg / "labels" / "000000.json").read_text() == (png / "labels" / "000000.json").read_text()
    assert (jpg / "gt" / "000000.png").read_bytes() == (png / "gt" / "000000.png").read_bytes()
    for side in ("left", "right"):
        assert sorted(p.name for p in (jpg / side).iterdir()) == ["000000.jpg"]
        assert (jpg / side / "000000.jpg").read_bytes()[:2] == b"\xff\xd8"
        lossless = cv2.imread(str(png / side / "000000.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
        saved = cv2.imread(str(jpg / side / "000000.jpg"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
        # quality 95 rounds away about a grey level a pixel, most of it the sensor's noise (1.5), and no more
        assert 0.3 < np.abs(saved - lossless).mean() < 2.5


class TestLook:
    def test_the_defaults_are_the_evaluation_sets_and_name_nothing(self):
        plain = raycast.Look()
        assert (plain.wall_shade, plain.noise_sigma, plain.right_gain, plain.right_offset, plain.texel_mm) == (
            raycast.WALL_SHADE, raycast.NOISE_SIGMA, raycast.RIGHT_GAIN, raycast.RIGHT_OFFSET, raycast.TEXEL_MM)
        assert plain.vignetting == 0.0 and plain.words() == ""
        assert raycast.Look(noise_sigma=3.0, vignetting=0.3).words() == "noise 3, vignetting 0.3"

    def test_vignetting_darkens_towards_the_corners_from_the_principal_point(self):
        share = raycast.Look(vignetting=0.3).vignette()
        assert share.shape == (raycast.CALIB["height"], raycast.CALIB["width"])
        cx, cy = round(raycast.CALIB["cx"]), round(raycast.CALIB["cy"])
        assert share[cy, cx] == pytest.approx(1.0, abs=1e-4)
        assert share.min() == pytest.approx(0.7, abs=1e-6) and share[0, -1] < share[cy, cx + 100] < share[cy, cx]

    def test_a_lit_wall_is_seen_brighter_inside_the_mouth(self, texture):
        z0 = 400.0
        scale = z0 / raycast.CALIB["focal_px"]
        deep = raycast.Pit(0.0, 0.0, 110 * scale, 70 * scale, 8.0, False)
        lit = raycast.render_eye(0.0, z0, raycast.rotation(0, 0), [deep], texture, 2, wall_shade=1.4)
        plain = raycast.render_eye(0.0, z0, raycast.rotation(0, 0), [], texture, 2)
        cx, cy = int(raycast.CALIB["cx"]), int(raycast.CALIB["cy"])
        wall = np.s_[cy - 30:cy + 30, cx + 107:cx + 110]  # as the shaded wall's test
        assert (lit[wall].mean(axis=0) - plain[wall].mean(axis=0)).max() > 20

    def test_a_finer_texture_is_tabulated_finer(self):
        kind = raycast.KINDS["textured"]
        fine = raycast.plate_texture(np.random.default_rng(0), 100.0, kind, texel_mm=0.1)
        assert fine.shape == (1000, 1000) and raycast.texture_texels(650.0, 0.1) > raycast.texture_texels(650.0)


def _render(tmp_path, name, *options):
    out = tmp_path / name
    result = CliRunner().invoke(_build(), ["sim", "raycast", str(out), "--frames", "1", "--seed", "4", *options])
    assert result.exit_code == 0, result.output
    return out


def test_inspect_sim_raycast_lights_and_sees_the_same_scene_otherwise(tmp_path):
    plain = tmp_path / "plain"  # the scene as the evaluation sets see it; its truth does not depend on the rays
    raycast.render_sequence(plain, frames=1, seed=4, supersample=1)
    seen = _render(tmp_path, "seen", "--noise-sigma", "3", "--exposure", "0.9", "-8", "--vignetting", "0.3",
                   "--wall-shade", "1.4")
    # the geometry and its truth are the scene's, whatever the look
    assert (seen / "gt" / "000000.png").read_bytes() == (plain / "gt" / "000000.png").read_bytes()
    labels = json.loads((seen / "labels" / "000000.json").read_text())
    assert labels["sensor"]["noise_sigma"] == 3.0
    assert labels["defects"] == json.loads((plain / "labels" / "000000.json").read_text())["defects"]
    assert "noise 3, right eye's exposure 0.9 x + -8, vignetting 0.3" in read_calibration(seen)["generator"]
    left, right = (cv2.imread(str(seen / side / "000000.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
                   for side in ("left", "right"))
    # the right eye sees 0.9 of the left's light less 8 grey levels: the plate's mean grey shows it
    assert right.mean() == pytest.approx(0.9 * left.mean() - 8, abs=3)
    dark = cv2.imread(str(plain / "left" / "000000.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    corner, centre = np.s_[:60, :80], np.s_[158:218, 296:376]
    assert left[corner].mean() / left[centre].mean() < 0.85 * dark[corner].mean() / dark[centre].mean()


def test_inspect_sim_raycast_draws_the_plates_distance_from_the_range_given(tmp_path):
    out = _render(tmp_path, "near", "--kind", "low", "--distance-range-mm", "320", "330")  # the kind's: 380-460
    plate = json.loads((out / "labels" / "000000.json").read_text())["distance_mm"]
    assert 320 <= plate <= 330 and "320-330 mm" in read_calibration(out)["generator"]


@pytest.mark.parametrize("options, words", [
    (["--texel-mm", "0.05"], "--texel-mm 0.05"),
    (["--exposure", "3", "0"], "--exposure"),
    (["--distance-range-mm", "700", "400"], "--distance-range-mm"),
    (["--distance-range-mm", "200", "400"], "--distance-range-mm"),
])
def test_inspect_sim_raycast_refuses_a_look_it_cannot_render_in_one_line(tmp_path, options, words):
    result = CliRunner().invoke(_build(), ["sim", "raycast", str(tmp_path / "no"), *options])
    assert result.exit_code == 2 and words in result.output
    assert len(result.output.strip().splitlines()) == 1 and not (tmp_path / "no").exists()
