"""``inspect stereo`` and ``inspect eval stereo`` on small synthetic pairs."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import cli

from core.cli import _build
from drivers.sequence_folder import read_pfm, write_pfm
from plugins.torch_sgm.synthetic import layered_scene


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture
def pair(tmp_path):
    left, right, gt, nonocc = layered_scene(48, 72, seed=2)
    cv2.imwrite(str(tmp_path / "left.png"), left)
    cv2.imwrite(str(tmp_path / "right.png"), right)
    return tmp_path / "left.png", tmp_path / "right.png", gt


def invoke(*args):
    return CliRunner().invoke(_build(), [str(a) for a in args])


def test_stereo_writes_middlebury_pfm_and_png(pair, tmp_path):
    left, right, gt = pair
    out, png = tmp_path / "d.pfm", tmp_path / "d.png"
    result = invoke("stereo", left, right, "--max-disp", 32, "--out", out, "--png", png)
    assert result.exit_code == 0, result.output
    raw = out.read_bytes()
    assert raw.startswith(b"Pf\n72 48\n-1\n") and len(raw) == len(b"Pf\n72 48\n-1\n") + 48 * 72 * 4
    disp = read_pfm(out)
    assert disp.shape == (48, 72)
    assert np.median(np.abs(disp - gt)) < 0.5
    # Rows are stored bottom to top.
    first_stored_row = np.frombuffer(raw[len(b"Pf\n72 48\n-1\n"):][: 72 * 4], "<f4")
    assert np.array_equal(first_stored_row, disp[-1])
    view = cv2.imread(str(png))
    assert view.shape == (48, 72, 3)


@pytest.mark.parametrize("name, says", [("d.pngx", "no image format has the extension '.pngx'"),
                                         ("d", "no image format has the extension ''")])
def test_a_view_with_no_image_format_is_one_line(pair, tmp_path, name, says):
    left, right, _ = pair
    result = invoke("stereo", left, right, "--backend", "opencv_sgbm", "--max-disp", 32, "--png", tmp_path / name)
    _assert_error(result, "--png", says)  # before the map is computed


def test_pfm_round_trip_keeps_invalid_as_inf(tmp_path):
    disp = np.arange(12, dtype=np.float32).reshape(3, 4)
    disp[1, 2] = np.nan
    write_pfm(tmp_path / "x.pfm", disp)
    back = read_pfm(tmp_path / "x.pfm")
    assert np.isinf(back[1, 2]) and np.array_equal(back[np.isfinite(disp)], disp[np.isfinite(disp)])


def test_stereo_with_the_opencv_backend(pair, tmp_path):
    left, right, _ = pair
    result = invoke("stereo", left, right, "--backend", "opencv_sgbm", "--max-disp", 32, "--out", tmp_path / "o.pfm")
    assert result.exit_code == 0, result.output
    assert read_pfm(tmp_path / "o.pfm").shape == (48, 72)


def _assert_error(result, *words):
    assert result.exit_code == 2, result.output
    lines = [l for l in result.output.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "Traceback" not in result.output
    for word in words:
        assert word in lines[0]


def test_stages_prints_where_the_maps_time_went(pair, tmp_path):
    left, right, _ = pair
    plain = tmp_path / "plain.pfm"
    assert invoke("stereo", left, right, "--max-disp", 32, "--out", plain).exit_code == 0
    result = invoke("stereo", left, right, "--max-disp", 32, "--stages", "--out", tmp_path / "timed.pfm")
    assert result.exit_code == 0, result.output
    rows = [line.split("|")[1:-1] for line in result.output.splitlines() if line.startswith("| ") and "---" not in line]
    stages = {name.strip(): float(ms) for name, ms, _ in rows[1:]}
    assert {"cost and aggregation", "SGM", "winners", "local plane fit", "other"} <= set(stages)
    total = stages.pop("total")
    assert sum(stages.values()) == pytest.approx(total, abs=1.0)  # "other" closes the sum
    assert np.array_equal(read_pfm(tmp_path / "timed.pfm"), read_pfm(plain), equal_nan=True)


def test_stages_of_a_backend_that_does_not_time_them_is_refused(pair):
    left, right, _ = pair
    result = invoke("stereo", left, right, "--backend", "opencv_sgbm", "--max-disp", 32, "--stages")
    assert result.exit_code == 2 and "does not time its stages" in result.output


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has a CUDA device")
@pytest.mark.parametrize("command", [["stereo", "L", "R", "--max-disp", "32"], ["bench"], ["run", "recipe.yaml"],
                                     ["eval", "depth", "sequence"], ["eval", "stereo", "--middlebury", "m"]])
def test_cuda_asked_for_where_there_is_none_is_refused_not_run_on_the_cpu(command):
    result = invoke(*command, "--device", "cuda")
    assert result.exit_code == 2 and "no CUDA device" in result.output


@pytest.mark.parametrize("command", [["bench"], ["run", "recipe.yaml"], ["eval", "depth", "sequence"], ["bench-view"]])
@pytest.mark.parametrize("device", ["banana", "cuda:x", "gpu"])
def test_a_device_no_torch_knows_is_refused(command, device):
    # it reached the detector, and every part was an ERROR ("Invalid CUDA 'device=banana' requested")
    result = invoke(*command, "--device", device)
    assert result.exit_code == 2 and f"'{device}': one of auto, cpu, cuda or cuda:N" in result.output


def test_pair_of_different_sizes_is_refused(pair, tmp_path):
    left, _, _ = pair
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((40, 72, 3), np.uint8))
    _assert_error(invoke("stereo", left, tmp_path / "small.png", "--max-disp", 16), "small.png", "72x40")


def test_a_pair_narrower_than_opencvs_search_is_refused_and_torch_sgm_matches_it(tmp_path):
    # OpenCV failed an assertion in C++ (a traceback); torch_sgm's coarse pass pooled it to nothing
    left, right, _, _ = layered_scene(6, 9, seed=2)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    _assert_error(invoke("stereo", tmp_path / "l.png", tmp_path / "r.png", "--max-disp", 4, "--backend", "opencv_sgbm"),
                  "l.png: opencv_sgbm: the pair is 9 px wide", "disparities 0..15", "needs 19 px at least")
    result = invoke("stereo", tmp_path / "l.png", tmp_path / "r.png", "--max-disp", 4, "--out", tmp_path / "d.pfm")
    assert result.exit_code == 0, result.output
    assert read_pfm(tmp_path / "d.pfm").shape == (6, 9)


def test_a_pair_too_large_for_the_memory_is_refused_before_matching(tmp_path):
    # 4000 x 2000 over 3999 disparities: 24 bytes each for torch_sgm, 715 GiB, more than any machine has
    grey = np.full((2000, 4000, 3), 128, np.uint8)
    for side in ("left", "right"):
        cv2.imwrite(str(tmp_path / f"{side}.png"), grey)
    result = invoke("stereo", tmp_path / "left.png", tmp_path / "right.png", "--max-disp", 3999)
    _assert_error(result, "left.png", "torch_sgm would need 715.", "GiB of memory is available")


@pytest.mark.parametrize("args, word", [
    (["--max-disp", 8, "--min-disp", 8], "--max-disp"),
    (["--max-disp", 4, "--min-disp", 10], "--min-disp"),
    (["--max-disp", 100], "width"),
    (["--max-disp", 16, "--set", "p3=1"], "--set p3: unknown key"),
    (["--max-disp", 16, "--set", "wmf_radiu=3"], "did you mean 'wmf_radius'?"),
    (["--max-disp", 16, "--set", "p1=-1"], "--set p1: Input should be greater than or equal to 0 (got -1)"),
    (["--max-disp", 16, "--backend", "nope"], "nope"),
    (["--max-disp", 16, "--set", "fit_radius=["], "--set fit_radius: Input should be a valid integer"),  # not YAML
    (["--max-disp", 16, "--set", "fit_radius=010"], "010: YAML reads a leading zero as octal, 8; write 10"),
    (["--max-disp", 16, "--set", "plane_sigma=1e30"], "--set plane_sigma: Input should be less than or equal to 50"),
    (["--max-disp", 16, "--backend", "opencv_sgbm", "--set", "p1_per_channel=99999999999"],
     "--set p1_per_channel: Input should be less than or equal to 100000"),  # was OpenCV's C int, at run time
])
def test_bad_options_are_refused(pair, args, word):
    left, right, _ = pair
    _assert_error(invoke("stereo", left, right, *args), word)


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_a_search_range_that_is_not_a_number_is_refused(pair, value):
    left, right, _ = pair
    result = invoke("stereo", left, right, "--max-disp", value)
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert f"Invalid value for '--max-disp': '{value}' is not a finite number" in result.output


def test_unreadable_or_missing_file_is_refused(pair, tmp_path):
    left, _, _ = pair
    (tmp_path / "junk.png").write_bytes(b"not an image")
    _assert_error(invoke("stereo", left, tmp_path / "junk.png", "--max-disp", 16), "junk.png")
    _assert_error(invoke("stereo", tmp_path / "missing.png", left, "--max-disp", 16), "missing.png")


@pytest.mark.parametrize("outputs, says", [
    (["--out", "{left}"], "--out {left}: the command reads that file: writing it would destroy it"),
    (["--png", "{folder}/../{name}/right.png"], "--png {folder}/../{name}/right.png: the command reads that file (as "
                                                "{right}): writing it would destroy it"),
    (["--out", "{folder}/map.tif", "--png", "{folder}/map.tif"], "--png {folder}/map.tif: --out writes that file too"),
])
def test_an_output_over_an_input_or_the_other_output_is_refused_before_matching(pair, outputs, says):
    # the map was written over the left image, the input a completed file name had picked
    left, right, _ = pair
    names = {"left": left, "right": right, "folder": left.parent, "name": left.parent.name}
    before = left.read_bytes(), right.read_bytes()
    result = invoke("stereo", left, right, "--max-disp", 16, *[o.format(**names) for o in outputs])
    assert result.exit_code == 2 and result.output == f"error: {says.format(**names)}\n", result.output
    assert (left.read_bytes(), right.read_bytes()) == before


def test_an_image_opencv_cannot_decode_is_our_one_line_alone(pair, tmp_path):
    # OpenCV's own warning (a 32-bit float TIFF) came first on the terminal, from the library itself
    left, right, _ = pair
    cv2.imwrite(str(tmp_path / "float.tiff"), cv2.imread(str(left)).astype(np.float32) / 255)
    out = cli("stereo", str(tmp_path / "float.tiff"), str(right), "--max-disp", "16")
    assert out.returncode == 2 and out.stderr == (f"error: {tmp_path / 'float.tiff'}: left image cannot be decoded "
                                                  f"(corrupt or not an image)\n"), out.stderr


def write_scene(folder, seed, ndisp=32):
    left, right, gt, nonocc = layered_scene(40, 64, seed=seed)
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "im0.png"), left)
    cv2.imwrite(str(folder / "im1.png"), right)
    write_pfm(folder / "disp0GT.pfm", gt)
    cv2.imwrite(str(folder / "mask0nocc.png"), np.where(nonocc, 255, 128).astype(np.uint8))
    (folder / "calib.txt").write_text(
        "cam0=[100 0 32; 0 100 20; 0 0 1]\ncam1=[100 0 32; 0 100 20; 0 0 1]\ndoffs=0\n"
        f"baseline=100\nwidth=64\nheight=40\nndisp={ndisp}\n")


def test_eval_scores_each_scene_and_backends_side_by_side(tmp_path):
    for i, name in enumerate(["SceneA", "SceneB"]):
        write_scene(tmp_path / "mb" / name, seed=i)
    out = tmp_path / "out"
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--backend", "torch_sgm,opencv_sgbm",
                    "--out", out, "--threads", 1)
    assert result.exit_code == 0, result.output
    assert "torch_sgm d-bad1" in result.output and "opencv_sgbm d-bad1" in result.output
    data = json.loads((out / "stereo_eval.json").read_text())
    torch_rows = data["backends"]["torch_sgm"]["scenes"]
    assert [r["scene"] for r in torch_rows] == ["SceneA", "SceneB"]
    assert all(r["dense"]["bad1.0"] < 20 for r in torch_rows)
    # OpenCV leaves holes; dense scoring counts them as bad, sparse scoring does not.
    cv_avg = data["backends"]["opencv_sgbm"]["average"]
    assert cv_avg["invalid"] > 0 and cv_avg["dense"]["bad1.0"] > cv_avg["sparse"]["bad1.0"]
    md = (out / "stereo_eval.md").read_text()
    assert "SceneA" in md and "**average**" in md
    assert cv2.imread(str(out / "stereo_eval.png")) is not None


def test_eval_selects_scenes_and_passes_settings(tmp_path):
    for i, name in enumerate(["SceneA", "SceneB"]):
        write_scene(tmp_path / "mb" / name, seed=i)
    out = tmp_path / "out"
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--scenes", "SceneB", "--out", out,
                    "--set", "torch_sgm.fill=none", "--no-figure")
    assert result.exit_code == 0, result.output
    data = json.loads((out / "stereo_eval.json").read_text())
    rows = data["backends"]["torch_sgm"]["scenes"]
    assert [r["scene"] for r in rows] == ["SceneB"] and rows[0]["invalid"] > 0
    # torch_sgm's best single map (two_view) unless the settings say otherwise
    assert data["meta"]["backends"]["torch_sgm"] == {"two_view": True, "fill": "none"}
    assert not (out / "stereo_eval.png").exists()


def test_one_scene_folder_may_be_given_itself(tmp_path):
    write_scene(tmp_path / "mb" / "SceneA", seed=0)
    out = tmp_path / "out"
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb" / "SceneA", "--backend", "opencv_sgbm",
                    "--out", out, "--no-figure")
    assert result.exit_code == 0, result.output
    rows = json.loads((out / "stereo_eval.json").read_text())["backends"]["opencv_sgbm"]["scenes"]
    assert [r["scene"] for r in rows] == ["SceneA"]
    (tmp_path / "empty").mkdir()
    _assert_error(invoke("eval", "stereo", "--middlebury", tmp_path / "empty"), "not a scene folder")


def test_a_scene_without_an_occlusion_mask_is_scored_over_every_pixel_and_says_so(tmp_path):
    write_scene(tmp_path / "mb" / "Masked", seed=0)
    write_scene(tmp_path / "mb" / "Unmasked", seed=0)
    (tmp_path / "mb" / "Unmasked" / "mask0nocc.png").unlink()
    out = tmp_path / "out"
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--backend", "opencv_sgbm", "--out", out,
                    "--no-figure")
    assert result.exit_code == 0, result.output
    lines = {line.split()[0]: line for line in result.output.splitlines() if "dense bad1.0" in line}
    assert "occluded pixels scored too" in lines["Unmasked"] and "occluded" not in lines["Masked"]
    rows = {r["scene"]: r for r in json.loads((out / "stereo_eval.json").read_text())["backends"]["opencv_sgbm"]["scenes"]}
    assert rows["Unmasked"]["note"] and not rows["Masked"]["note"]
    # the occluded pixels, where a matcher cannot be right, now count: more pixels, and more of them bad
    assert rows["Unmasked"]["pixels"] > rows["Masked"]["pixels"]
    assert rows["Unmasked"]["dense"]["bad1.0"] > rows["Masked"]["dense"]["bad1.0"]


def test_scenes_without_ground_truth_are_named_before_any_is_matched(tmp_path):
    for name in ("SceneA", "SceneB", "SceneC"):
        write_scene(tmp_path / "mb" / name, seed=0)
    for name in ("SceneB", "SceneC"):  # as a benchmark's test scenes come
        (tmp_path / "mb" / name / "disp0GT.pfm").unlink()
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--backend", "opencv_sgbm")
    _assert_error(result, "SceneB/disp0GT.pfm: file missing, nor disp0.pfm (and in 1 more scenes): a scene without "
                          "ground truth")
    assert "dense bad1.0" not in result.output
    result = invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--backend", "opencv_sgbm", "--scenes", "SceneA",
                    "--out", tmp_path / "out", "--no-figure")
    assert result.exit_code == 0, result.output


def test_the_middlebury_2014_datasets_name_for_the_ground_truth_is_read_too(tmp_path):
    write_scene(tmp_path / "mb" / "SceneA", seed=0)
    write_scene(tmp_path / "mb14" / "SceneA", seed=0)
    (tmp_path / "mb14" / "SceneA" / "disp0GT.pfm").rename(tmp_path / "mb14" / "SceneA" / "disp0.pfm")
    scores = []
    for folder in ("mb", "mb14"):
        result = invoke("eval", "stereo", "--middlebury", tmp_path / folder, "--backend", "opencv_sgbm",
                        "--out", tmp_path / f"out_{folder}", "--no-figure")
        assert result.exit_code == 0, result.output
        row = json.loads((tmp_path / f"out_{folder}" / "stereo_eval.json").read_text())["backends"]["opencv_sgbm"]
        scores.append((row["scenes"][0]["dense"], row["scenes"][0]["sparse"]))
    assert scores[0] == scores[1]


def _rescale_pfm(path, scale: bytes):
    magic, size, _, pixels = path.read_bytes().split(b"\n", 3)
    path.write_bytes(b"\n".join([magic, size, scale, pixels]))


def _as_colour_pfm(path):
    magic, size, scale, pixels = path.read_bytes().split(b"\n", 3)
    grey = np.frombuffer(pixels, "<f4")
    path.write_bytes(b"\n".join([b"PF", size, scale, np.repeat(grey, 3).tobytes()]))


def test_eval_errors(tmp_path):
    _assert_error(invoke("eval", "stereo", "--middlebury", tmp_path / "nowhere"), "nowhere")
    write_scene(tmp_path / "mb" / "SceneA", seed=0)
    _assert_error(invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--scenes", "Nope"), "Nope")
    _assert_error(invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--set", "paths=8"), "--set")


@pytest.mark.parametrize("damage, says", [
    (lambda scene: (scene / "disp0GT.pfm").unlink(), "disp0GT.pfm: file missing"),
    (lambda scene: (scene / "disp0GT.pfm").write_bytes((scene / "disp0GT.pfm").read_bytes()[:300]),
     "disp0GT.pfm: PFM is not whole (288 bytes of pixels, 10240 for 64x40)"),
    (lambda scene: (scene / "disp0GT.pfm").write_bytes(b"Pf\nsixty-four 40\n-1\n"),
     "disp0GT.pfm: PFM header is not 'width height' and a scale"),
    (lambda scene: (scene / "disp0GT.pfm").write_bytes(b"Pf\n"),  # cut after its first line: read forever
     "disp0GT.pfm: PFM header is not 'width height' and a scale"),
    (lambda scene: cv2.imwrite(str(scene / "mask0nocc.png"), np.full((20, 30), 255, np.uint8)),
     "mask0nocc.png: 30x20, but im0.png is 64x40"),
    (lambda scene: (scene / "mask0nocc.png").write_bytes(b"not a PNG"), "mask0nocc.png: occlusion mask is not whole"),
    # each scored the backend against nothing, silently (99-100 % bad pixels)
    (lambda scene: _rescale_pfm(scene / "disp0GT.pfm", b"0"),
     "disp0GT.pfm: PFM scale must be a non-zero number, its sign the byte order (got 0.0)"),
    (lambda scene: _rescale_pfm(scene / "disp0GT.pfm", b"1"),  # little-endian pixels said to be big-endian
     "disp0GT.pfm: disparities from"),
    (lambda scene: _as_colour_pfm(scene / "disp0GT.pfm"),  # "64x40, but im0.png is 64x40"
     "disp0GT.pfm: a colour PFM (PF, 3 channels): a disparity map is a grey one (Pf)"),
    # each scored the scene, and the average of all scenes, as NaN
    (lambda scene: write_pfm(scene / "disp0GT.pfm", np.full((40, 64), np.inf, np.float32)),
     "disp0GT.pfm: no pixel has a known disparity: nothing to score the scene on"),
    (lambda scene: cv2.imwrite(str(scene / "mask0nocc.png"), np.zeros((40, 64), np.uint8)),
     "disp0GT.pfm: no pixel has a known disparity where mask0nocc.png marks it visible"),
    (lambda scene: (scene / "calib.txt").write_text((scene / "calib.txt").read_text().replace("ndisp=32", "ndisp=-32")),
     "calib.txt: ndisp must be a number of disparities from 1 to the width, 64 (got -32)"),
])
def test_a_damaged_scene_is_named_not_a_traceback(tmp_path, damage, says):
    scene = tmp_path / "mb" / "SceneA"
    write_scene(scene, seed=0)
    damage(scene)
    _assert_error(invoke("eval", "stereo", "--middlebury", tmp_path / "mb", "--backend", "opencv_sgbm"), says)
