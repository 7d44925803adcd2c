"""Recorded stereo sequences on disk: reading and writing, nothing else.

Layout (written by the synthetic generator and by ``inspect camera record``)::

    SEQ/calib.yaml           focal_px, baseline_mm, cx, cy, width, height, doffs
    SEQ/left/<id>.png        rectified left image
    SEQ/right/<id>.png       rectified right image
    SEQ/gt/<id>.png          optional ground-truth disparity, uint16 = round(d * 256), 0 = unknown (KITTI)
    SEQ/labels/<id>.json     optional ground-truth labels

A Middlebury scene folder (``im0.png``, ``im1.png``, ``calib.txt``) reads as a one-frame sequence.
This module imports nothing from the rest of stereo-inspect, so it can be tried alone.
"""
from __future__ import annotations

import difflib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from drivers import text_files, yaml_reader
from drivers.file_writes import write_bytes, write_text
from drivers.stereo_geometry import calibration_problem

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
# Ten times the largest frame a stereo camera or Middlebury's full size gives (6 MP): a 600 KB PNG declaring
# 30000x20000 pixels decoded into 3.5 GB before its size could be checked against the calibration's.
MAX_IMAGE_PIXELS = 64_000_000
CALIB_KEYS = ("focal_px", "baseline_mm", "cx", "cy", "width", "height")
# Keys beyond these (a recorder's notes, a serial number) are left alone, but one that reads like a misspelt
# calibration key is refused: "dofs: 40" would leave doffs at 0, and every distance off without a word.
CALIB_SPELLING_CUTOFF = 0.75


class SequenceError(Exception):
    """A sequence folder or one of its files cannot be used; the message names the file."""


@dataclass(frozen=True)
class FrameFiles:
    frame_id: str
    left: Path | None
    right: Path | None
    gt: Path | None = None
    labels: Path | None = None


def is_middlebury_scene(folder: Path) -> bool:
    return (folder / "im0.png").exists() and (folder / "calib.txt").exists()


def read_text(path: Path, what: str) -> str:
    """A text file's contents (UTF-8, with or without the byte-order mark a Windows editor writes); ``SequenceError``
    naming the file, and the line of the first byte that is not UTF-8, where it cannot be read."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SequenceError(f"{path}: {what} cannot be read ({exc.strerror})") from None
    try:
        return text_files.decode(data)
    except text_files.NotUtf8 as exc:
        raise SequenceError(f"{path}:{exc.line}: {what} is {exc}: save it as UTF-8") from None


def read_middlebury_calib(path: Path) -> dict:
    """Parse Middlebury's ``calib.txt`` (cam0=[f 0 cx; 0 f cy; 0 0 1], doffs, baseline, ndisp, ...)."""
    values: dict[str, str] = {}
    first: dict[str, int] = {}
    for number, line in enumerate(read_text(path, "calibration").splitlines(), 1):
        if "=" in line:
            key, value = (part.strip() for part in line.split("=", 1))
            if key in first:
                raise SequenceError(f"{path}:{number}: {key}: {yaml_reader.given_twice(first[key])}")
            values[key], first[key] = value, number
    try:
        cam0 = [float(x) for x in re.split(r"[\s;\[\]]+", values["cam0"]) if x]
        calib = {
            "focal_px": cam0[0],
            "cx": cam0[2],
            "cy": cam0[5],
            "doffs": float(values.get("doffs", 0.0)),
            "baseline_mm": float(values["baseline"]),
            "width": int(values["width"]),
            "height": int(values["height"]),
            "ndisp": int(values["ndisp"]),
        }
    except (KeyError, IndexError, ValueError) as exc:
        raise SequenceError(f"{path}: not a Middlebury calibration ({exc})") from None
    if not 0 < calib["ndisp"] <= calib["width"]:
        # the disparities searched: none, or more than the image holds, would score a backend on nothing
        raise SequenceError(f"{path}: ndisp must be a number of disparities from 1 to the width, {calib['width']} "
                            f"(got {calib['ndisp']})")
    return calib


def _checked_calibration(path: Path, data: dict) -> dict:
    """``data`` when its values are a camera's (``stereo_geometry.calibration_problem``); else
    ``SequenceError`` naming the file and the value. A negative focal length or a zero baseline would
    otherwise turn every distance into nonsense."""
    def number(key):
        value = _as_number(data[key])
        if value is None:
            raise SequenceError(f"{path}: {key} must be a number (got {data[key]!r})")
        data[key] = value
        return value
    for key in ("focal_px", "baseline_mm"):
        if number(key) <= 0:
            raise SequenceError(f"{path}: {key} must be positive (got {data[key]!r})")
    for key in ("width", "height"):
        if not (number(key) > 0 and float(data[key]).is_integer()):
            raise SequenceError(f"{path}: {key} must be a whole number of pixels above 0 (got {data[key]!r})")
        data[key] = int(data[key])
    for key in ("cx", "cy", "doffs"):
        number(key)
    problem = calibration_problem(*(data[k] for k in CALIB_KEYS), data["doffs"])
    if problem is not None:
        raise SequenceError(f"{path}: {problem}")
    return data


def read_calibration(folder: Path) -> dict:
    """The sequence's calibration as a dict (``CALIB_KEYS`` and ``doffs``), checked; ``SequenceError`` naming
    the file and the key otherwise."""
    folder = Path(folder)
    if is_middlebury_scene(folder):
        return _checked_calibration(folder / "calib.txt", read_middlebury_calib(folder / "calib.txt"))
    path = folder / "calib.yaml"
    if not path.exists():
        raise SequenceError(f"{path}: calibration file missing")
    try:
        data = yaml_reader.safe_load(read_text(path, "calibration"))
    except yaml_reader.Misread as exc:
        raise SequenceError(f"{path}:{exc.line}: {exc.described}") from None
    except yaml.YAMLError as exc:
        raise SequenceError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise SequenceError(f"{path}: expected a mapping with {', '.join(CALIB_KEYS)}")
    misspelt = _misspelt_keys(data)
    if misspelt:
        raise SequenceError(f"{path}: " + "; ".join(f"unknown key {key!r}, did you mean {known!r}?"
                                                   for key, known in misspelt.items()))
    missing = [k for k in CALIB_KEYS if k not in data]
    if missing:
        raise SequenceError(f"{path}: missing {', '.join(missing)}")
    data.setdefault("doffs", 0.0)
    return _checked_calibration(path, data)


def _misspelt_keys(data: dict) -> dict[str, str]:
    """{key: the calibration key it reads like} for each key of ``data`` that is no calibration key but close to
    one that ``data`` lacks (difflib's ratio at least CALIB_SPELLING_CUTOFF): beside focal_px, focal_mm is a note."""
    keys = (*CALIB_KEYS, "doffs")
    lacking = [k for k in keys if k not in data]
    found = {}
    for key in data:
        if isinstance(key, str) and key not in keys:
            close = difflib.get_close_matches(key, lacking, n=1, cutoff=CALIB_SPELLING_CUTOFF)
            if close:
                found[key] = close[0]
    return found


def write_calibration(folder: Path, calib: dict) -> None:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    clean = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in calib.items()}
    write_text(folder / "calib.yaml", yaml.safe_dump(clean, sort_keys=False))


def _by_stem(folder: Path) -> dict[str, Path]:
    """The images of ``folder`` by frame id; ``SequenceError`` where one id has two (``000001.jpg`` and
    ``000001.png``): which of them the part was is not the reader's guess to make."""
    if not folder.is_dir():
        return {}
    found: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        if p.stem in found:
            raise SequenceError(f"{folder}: two images for frame {p.stem} ({found[p.stem].name} and {p.name}): "
                                f"keep one")
        found[p.stem] = p
    return found


def list_frames(folder: Path) -> list[FrameFiles]:
    """Every frame id found in ``left/`` or ``right/``; a frame missing one eye keeps ``None`` there
    so that the reader reports it instead of silently skipping it."""
    folder = Path(folder)
    if is_middlebury_scene(folder):
        gt = folder / "disp0GT.pfm"
        return [FrameFiles(folder.name, folder / "im0.png", folder / "im1.png", gt if gt.exists() else None)]
    if not (folder / "left").is_dir():
        raise SequenceError(f"{folder}: no left/ folder (expected left/, right/ and calib.yaml)")
    left, right = _by_stem(folder / "left"), _by_stem(folder / "right")
    gt, labels = _by_stem(folder / "gt"), {p.stem: p for p in sorted((folder / "labels").glob("*.json"))}
    return [
        FrameFiles(i, left.get(i), right.get(i), gt.get(i), labels.get(i)) for i in sorted(set(left) | set(right))
    ]


PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def incomplete(data: bytes, suffix: str) -> str | None:
    """Why an encoded image is not whole, or None: a JPEG must start and end with its image markers and a PNG
    with its signature and its IEND chunk. A decoder fills what a truncated file lacks with grey and says so only on stderr,
    so a cut file would otherwise give a picture of a plate with half of it missing."""
    suffix = suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        if not data.startswith(b"\xff\xd8"):
            return "not a JPEG (no start-of-image marker)"
        if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
            return "truncated JPEG (no end-of-image marker)"
    elif suffix == ".png":
        if not data.startswith(b"\x89PNG\r\n\x1a\n"):
            return "not a PNG (no PNG signature)"
        if not data.endswith(PNG_END):
            return "truncated PNG (no IEND chunk at its end)"
    return None


def _whole_bytes(path: Path, what: str) -> bytes:
    """The encoded image's bytes; ``SequenceError`` naming the file when it is missing, unreadable or cut short."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SequenceError(f"{path}: {what} missing") from None
    except OSError as exc:
        raise SequenceError(f"{path}: {what} cannot be read ({exc.strerror})") from None
    why = incomplete(data, path.suffix)
    if why is not None:
        raise SequenceError(f"{path}: {what} is not whole: {why}")
    return data


def declared_size(path: Path) -> tuple[int, int] | None:
    """(width, height) that an image file's header states, read without decoding its pixels; None where the file
    or its header cannot be read, or Pillow refuses the size as a decompression bomb (the frame's reader says why
    when it comes to it)."""
    size = _header_size(path)
    return None if size is None or not all(np.isfinite(size)) else (int(size[0]), int(size[1]))


def first_frame_problem(folder: Path, calib: dict) -> str | None:
    """Where the first frame's left image is not of the calibration's size, a sentence naming both (a calibration
    from another camera mode would otherwise make every part an ERROR only once the line runs); else None, and
    where the frames cannot be listed (the camera says why when it opens)."""
    try:
        frames = list_frames(folder)
    except SequenceError:
        return None
    first = next((f.left for f in frames if f.left is not None), None)
    size = None if first is None else declared_size(first)
    if size is None or size == (calib["width"], calib["height"]):
        return None
    return (f"{first} is {size[0]}x{size[1]} but the calibration is for {calib['width']}x{calib['height']} images: "
            f"the calibration file is not this recording's")


def declared_pixels(data: bytes) -> float:
    """The pixels an encoded image's header states, read without decoding them (infinity where Pillow refuses
    the size as a decompression bomb); 0 where the header cannot be read, for the decoder to say why."""
    import io

    size = _header_size(io.BytesIO(data))
    return 0.0 if size is None else size[0] * size[1]


def _header_size(source) -> tuple[float, float] | None:
    """(width, height) from the header of the image ``source`` (a path or a binary file), its pixels not decoded;
    (inf, inf) where Pillow refuses the size as a decompression bomb, None where the header cannot be read."""
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a damaged header's warnings (bombs, EXIF): the decoder says why
            with Image.open(source) as image:
                return float(image.size[0]), float(image.size[1])
    except Image.DecompressionBombError:
        return float("inf"), float("inf")
    except Exception:  # Pillow raises many kinds for a header it cannot read
        return None


def read_image(path: Path | None, what: str = "image") -> np.ndarray:
    """HxWx3 uint8 BGR; raises ``SequenceError`` naming the file when it is missing, truncated or corrupt."""
    if path is None:
        raise SequenceError(f"{what} missing")
    path = Path(path)
    data = _whole_bytes(path, what)
    if declared_pixels(data) > MAX_IMAGE_PIXELS:
        raise SequenceError(f"{path}: {what} declares more than {MAX_IMAGE_PIXELS / 1e6:.0f} MP, more than any "
                            f"camera's frame")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise SequenceError(f"{path}: {what} cannot be decoded (corrupt or not an image)")
    return image


def read_disparity_png(path: Path) -> np.ndarray:
    """KITTI-style 16-bit disparity PNG -> float32, NaN where unknown."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16:
        raise SequenceError(f"{path}: not a 16-bit disparity PNG")
    disp = raw.astype(np.float32) / 256.0
    disp[raw == 0] = np.nan
    return disp


def write_image(path: Path, image: np.ndarray, params: tuple[int, ...] = ()) -> None:
    """The image encoded by its file's extension and written; OSError naming the file where it was not (a
    full disk, a folder removed under it). ``cv2.imwrite`` returns False at most, and True for a small PNG
    whose bytes the full disk refused only when the file was closed: a sequence would silently lack it."""
    path = Path(path)
    try:
        ok, encoded = cv2.imencode(path.suffix, image, list(params))
    except cv2.error:  # no encoder for the extension: OpenCV raises rather than returning False
        raise OSError(f"{path}: no image format has the extension {path.suffix!r} (give .png, .jpg, .bmp or "
                      f".tif)") from None
    if not ok:
        raise OSError(f"{path}: could not be encoded as {path.suffix}")
    write_bytes(path, encoded.tobytes())


KITTI_MAX_DISPARITY = 65535 / 256.0  # px: the largest value a KITTI 16-bit disparity PNG holds


def write_disparity_png(path: Path, disparity: np.ndarray) -> None:
    """HxW disparity (px, NaN or inf: unknown) as a KITTI 16-bit PNG; ValueError naming the file where a value
    is beyond ``KITTI_MAX_DISPARITY``: clipped, it would read as a farther surface than the one there."""
    values = np.nan_to_num(np.asarray(disparity, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    raw = np.round(values * 256.0)
    if raw.max(initial=0.0) > 65535:
        raise ValueError(f"{path}: a disparity of {values.max():.2f} px does not fit a 16-bit PNG (at most "
                         f"{KITTI_MAX_DISPARITY:.3f} px)")
    write_image(path, np.clip(raw, 0, 65535).astype(np.uint16))


JPEG_QUALITY = 95  # what ``write_frame`` saves a ``jpg`` pair at: a camera pipeline's usual setting


def write_frame(
    folder: Path,
    frame_id: str,
    left: np.ndarray,
    right: np.ndarray,
    gt_disparity: np.ndarray | None = None,
    labels: dict | list | None = None,
    image_format: str = "png",
) -> None:
    """The pair as ``image_format`` images (``png``, or ``jpg`` at JPEG_QUALITY), the ground truth as a 16-bit
    PNG and the labels as JSON, each where given."""
    folder = Path(folder)
    params = (cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY) if image_format == "jpg" else ()
    for sub, image in (("left", left), ("right", right)):
        (folder / sub).mkdir(parents=True, exist_ok=True)
        write_image(folder / sub / f"{frame_id}.{image_format}", image, params)
    if gt_disparity is not None:
        (folder / "gt").mkdir(exist_ok=True)
        write_disparity_png(folder / "gt" / f"{frame_id}.png", gt_disparity)
    if labels is not None:
        (folder / "labels").mkdir(exist_ok=True)
        write_text(folder / "labels" / f"{frame_id}.json", json.dumps(labels, indent=2))


class _KeyTwice(Exception):
    """A JSON object that gives a key twice, which ``json`` reads as the last without a word."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    found = dict(pairs)
    if len(found) < len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _KeyTwice(key)
            seen.add(key)
    return found


def read_labels(path: Path, shape: tuple[int, int] | None = None) -> dict:
    """A frame's labels: ``{"frame_id": ..., "defects": [{"class", "box": [x0, y0, x1, y1], "distance_mm",
    "deviation_mm", ...}, ...], "sensor": {"noise_sigma": ...}, ...}``, checked (boxes as floats, each
    overlapping the HxW image of ``shape`` where given). ``SequenceError`` naming the file and the entry
    when it is not one: the truth a result is compared with must be what it says."""
    path = Path(path)
    try:
        labels = json.loads(read_text(path, "labels"), object_pairs_hook=_unique_keys)
    except _KeyTwice as exc:
        raise SequenceError(f"{path}: {exc.args[0]!r} given twice in one object; one of them would be ignored") from None
    except ValueError as exc:
        raise SequenceError(f"{path}: labels are not JSON ({exc})") from None
    except RecursionError:  # Python's JSON decoder recurses once per level
        raise SequenceError(f"{path}: labels nest deeper than JSON can be read") from None
    if not isinstance(labels, dict) or not isinstance(labels.get("defects"), list):
        raise SequenceError(f"{path}: expected a mapping with a list of defects")
    for i, defect in enumerate(labels["defects"]):
        where = f"{path}: defects[{i}]"
        if not isinstance(defect, dict) or not isinstance(defect.get("class"), str):
            raise SequenceError(f"{where}: expected a mapping with a class name")
        box = defect.get("box")
        if not (isinstance(box, list) and len(box) == 4 and all(_number(v) for v in box)
                and box[0] < box[2] and box[1] < box[3]):
            raise SequenceError(f"{where}.box: expected [x0, y0, x1, y1] with x0 < x1 and y0 < y1, got {box!r}")
        defect["box"] = [float(v) for v in box]
        if defect.get("deviation_mm") is not None and not _number(defect["deviation_mm"]):
            raise SequenceError(f"{where}.deviation_mm: expected a number or null, got {defect['deviation_mm']!r}")
        distance = defect.get("distance_mm")
        if distance is not None and not (_number(distance) and distance > 0):  # in front of the camera
            raise SequenceError(f"{where}.distance_mm: expected a number > 0 or null, got {distance!r}")
    sensor = labels.get("sensor")
    if sensor is not None and not isinstance(sensor, dict):
        raise SequenceError(f"{path}: sensor: expected a mapping, got {sensor!r}")
    noise = (sensor or {}).get("noise_sigma")
    if noise is not None and not (_number(noise) and noise >= 0):
        raise SequenceError(f"{path}: sensor.noise_sigma: expected a number >= 0 or null, got {noise!r}")
    if shape is not None:
        check_label_boxes(labels, shape, path)
    return labels


def labelled_sequence_problem(folder: Path) -> str | None:
    """The first reason a labelled sequence cannot be evaluated to its end, in words naming the file, or None:
    its calibration, each frame's two images present and whole, and its labels present and valid for the
    calibration's image size. Checked from the files alone (nothing decoded), so that an evaluation stops
    before its first frame is matched rather than after the frames ahead of the broken one."""
    folder = Path(folder)
    try:
        calib = read_calibration(folder)
        frames = list_frames(folder)
    except SequenceError as exc:
        return str(exc)
    if not frames:
        return f"{folder}: no frames in left/"
    shape = (int(calib["height"]), int(calib["width"]))

    def frame_problem(f: FrameFiles) -> str | None:
        for path, eye in ((f.left, "left"), (f.right, "right")):
            if path is None:
                return f"{folder}: {eye} image of frame {f.frame_id} missing"
            _whole_bytes(path, f"{eye} image of frame {f.frame_id}")
        if f.labels is None:
            return f"{folder}: frame {f.frame_id} has no labels/{f.frame_id}.json (the truth to compare with)"
        read_labels(f.labels, shape)
        return None

    problems = []
    for f in frames:
        try:
            problem = frame_problem(f)
        except SequenceError as exc:
            problem = str(exc)
        if problem is not None:
            problems.append(problem)
    if not problems:
        return None
    more = len(problems) - 1
    more = f" (and {more} more frame{'s' if more > 1 else ''})" if more else ""
    return problems[0] + more


def check_label_boxes(labels: dict, shape: tuple[int, int], path: Path) -> None:
    """``SequenceError`` naming the file ``path`` and the entry where a box of ``labels`` (as ``read_labels``
    gives them) misses the HxW image of ``shape``: a defect there could only count as one not found."""
    h, w = shape
    for i, defect in enumerate(labels["defects"]):
        x0, y0, x1, y1 = defect["box"]
        if not (x0 < w and x1 > 0 and y0 < h and y1 > 0):
            raise SequenceError(f"{path}: defects[{i}].box: {defect['box']} lies outside the {w}x{h} image")


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)


def _as_number(value) -> float | int | None:
    """``value`` as a finite number, or None. A string that reads as one counts: YAML 1.1 reads ``1e9``
    (no decimal point) as a string, and calibration tools write such exponents."""
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            return None
    return value if _number(value) else None


def read_pfm(path: Path) -> np.ndarray:
    """A PFM image as float32 (rows top-to-bottom); grey PFMs give HxW."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: file missing")
    with open(path, "rb") as f:
        header = f.readline().decode("latin-1").strip()
        if header not in ("Pf", "PF"):
            raise SequenceError(f"{path}: not a PFM file")
        try:
            line = f.readline()
            while line and not line.split():  # blank lines before the size; at the end of the file, none
                line = f.readline()
            dims = line.decode("latin-1").split()
            width, height = int(dims[0]), int(dims[1])
            scale = float(f.readline().decode("latin-1").strip())
        except (ValueError, IndexError):
            raise SequenceError(f"{path}: PFM header is not 'width height' and a scale") from None
        if scale == 0 or not np.isfinite(scale):
            # its sign is the byte order: without one, the pixels could be read in either
            raise SequenceError(f"{path}: PFM scale must be a non-zero number, its sign the byte order (got {scale})")
        dtype = "<f4" if scale < 0 else ">f4"
        channels = 3 if header == "PF" else 1
        payload = f.read()
    count = width * height * channels
    if width <= 0 or height <= 0 or len(payload) < 4 * count:
        raise SequenceError(f"{path}: PFM is not whole ({len(payload)} bytes of pixels, {4 * count} for "
                            f"{width}x{height})")
    data = np.frombuffer(payload, dtype=dtype, count=count)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.flipud(data.reshape(shape)).astype(np.float32)


def write_pfm(path: Path, image: np.ndarray) -> None:
    """Middlebury convention: little-endian ``Pf``, rows bottom-to-top, invalid as +inf."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError("write_pfm expects an HxW array")
    out = np.where(np.isfinite(image), image, np.float32(np.inf)).astype("<f4")
    write_bytes(path, b"Pf\n" + f"{image.shape[1]} {image.shape[0]}\n".encode() + b"-1\n" + np.flipud(out).tobytes())
