"""Pascal VOC -> YOLO dataset layout, tolerant of real-world annotation faults.

Labels are read from each XML ``<object><name>``; file names are never used for
labels (NEU-DET has boxes whose class differs from their image's file name).
Every fault is reported with the file it came from; none stops the conversion.
"""
from __future__ import annotations

import math

import shutil
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from drivers.file_writes import write_text
from drivers.sequence_folder import MAX_IMAGE_PIXELS, declared_pixels, incomplete, read_text

NEU_DET_CLASSES = (
    "crazing",
    "inclusion",
    "patches",
    "pitted_surface",
    "rolled-in_scale",
    "scratches",
)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


@dataclass
class ConversionReport:
    images: int = 0
    boxes: int = 0
    faults: Counter = field(default_factory=Counter)
    messages: list[str] = field(default_factory=list)

    def fault(self, kind: str, message: str) -> None:
        self.faults[kind] += 1
        self.messages.append(f"{kind}: {message}")

    def summary(self) -> str:
        parts = [f"{self.images} images", f"{self.boxes} boxes"]
        parts += [f"{n} {kind}" for kind, n in sorted(self.faults.items())]
        return "converted " + ", ".join(parts)


def _find_image(images_dir: Path, stem: str) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        candidate = images_dir / f"{stem}{suffix}"
        if candidate.exists():
            return candidate
    return None


def _image_size(path: Path, report: ConversionReport) -> tuple[int, int] | None:
    """The image's (width, height), or None with the fault reported: a file cut short decodes as a picture
    padded with grey, which a detector would learn as steel."""
    import cv2
    import numpy as np

    try:
        data = path.read_bytes()
    except OSError as exc:
        report.fault("unreadable_image", f"{path.name}: cannot be read ({exc.strerror})")
        return None
    why = incomplete(data, path.suffix)
    if why is not None:
        report.fault("truncated_image", f"{path.name}: {why}")
        return None
    if declared_pixels(data) > MAX_IMAGE_PIXELS:  # decoded, a few hundred KB could fill the memory
        report.fault("unreadable_image", f"{path.name}: declares more than {MAX_IMAGE_PIXELS / 1e6:.0f} MP")
        return None
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        report.fault("unreadable_image", f"{path.name}: cannot be decoded")
        return None
    return img.shape[1], img.shape[0]


def parse_voc(
    xml_path: Path, classes: tuple[str, ...], report: ConversionReport, size: tuple[int, int] | None
) -> list[str] | None:
    """YOLO label lines for one VOC file, or None when the file is unusable.

    ``size`` is the decoded image size (w, h); it wins over the XML's ``<size>``
    because annotation tools get that field wrong more often than decoders do.
    """
    name = xml_path.name
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError as exc:
        report.fault("malformed_xml", f"{name}: {exc}")
        return None
    if root.tag != "annotation":  # read as it was, another tool's XML became an image without defects
        report.fault("malformed_xml", f"{name}: root element <{root.tag}>, not a VOC <annotation>")
        return None
    if size is None:
        try:
            size = (int(root.findtext("size/width")), int(root.findtext("size/height")))
        except (TypeError, ValueError):
            report.fault("malformed_xml", f"{name}: no image size")
            return None
    width, height = size
    lines: list[str] = []
    for index, obj in enumerate(root.iter("object")):
        label = (obj.findtext("name") or "").strip()
        if label not in classes:
            report.fault("unknown_class", f"{name} object {index}: class {label!r} not in {list(classes)}")
            continue
        try:
            box = [float(obj.findtext(f"bndbox/{k}")) for k in ("xmin", "ymin", "xmax", "ymax")]
        except (TypeError, ValueError):
            report.fault("malformed_xml", f"{name} object {index}: missing or non-numeric bndbox")
            continue
        if not all(math.isfinite(v) for v in box):  # 'nan' parses, and would reach the labels as nan
            report.fault("malformed_xml", f"{name} object {index}: bndbox {box} is not finite")
            continue
        clamped = [
            min(max(box[0], 0.0), width),
            min(max(box[1], 0.0), height),
            min(max(box[2], 0.0), width),
            min(max(box[3], 0.0), height),
        ]
        if clamped != box:
            report.fault("box_clamped", f"{name} object {index}: box {box} clamped to image {width}x{height}")
        x0, y0, x1, y1 = clamped
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:
            report.fault("empty_box", f"{name} object {index}: empty box {box}")
            continue
        cx, cy = (x0 + x1) / 2 / width, (y0 + y1) / 2 / height
        bw, bh = (x1 - x0) / width, (y1 - y0) / height
        lines.append(f"{classes.index(label)} {cx:.6f} {cy:.6f} {bw:.6f} {bh:.6f}")
    return lines


def _split_stems(path: Path, split: str, report: ConversionReport) -> list[str]:
    """The stems a split file lists, in its order, each once (a stem listed again is reported)."""
    stems: dict[str, None] = {}  # ordered, and a stem looked up at once
    for line in read_text(path, "split file").splitlines():
        stem = line.strip()
        if stem in stems:
            report.fault("listed_twice", f"{stem}: listed twice in {split} ({path.name}), converted once")
        elif stem:
            stems[stem] = None
    return list(stems)


def _report_shared_stems(splits: dict[str, list[str]], report: ConversionReport) -> None:
    """A stem in two splits: a score on the second is then partly a score on images the model was trained on."""
    names = list(splits)
    for i, first in enumerate(names):
        for second in names[i + 1:]:
            for stem in sorted(set(splits[first]) & set(splits[second])):
                report.fault("in_two_splits", f"{stem}: listed in {first} and in {second}: a score on {second} then "
                                              f"counts an image the model was trained on")


def convert_voc(
    src: Path,
    dst: Path,
    split_files: dict[str, Path] | None = None,
    classes: tuple[str, ...] = NEU_DET_CLASSES,
) -> ConversionReport:
    """Convert ``src/{images,annotations}`` into ``dst/{images,labels}/<split>`` plus ``dst/data.yaml``.

    ``split_files`` maps a split name (``train``, ``val``) to a file of stems; without it,
    every image goes to ``train`` and ``val`` reads the same folder.
    """
    src, dst = Path(src), Path(dst)
    images_dir, ann_dir = src / "images", src / "annotations"
    report = ConversionReport()
    xml_stems = {p.stem for p in ann_dir.glob("*.xml")}
    image_stems = {p.stem for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES}
    for stem in sorted(image_stems - xml_stems):
        report.fault("image_without_xml", f"{stem}: image has no annotation file")
    for stem in sorted(xml_stems - image_stems):
        report.fault("xml_without_image", f"{stem}.xml: annotation has no image")

    if split_files:
        splits = {name: _split_stems(Path(path), name, report) for name, path in split_files.items()}
        _report_shared_stems(splits, report)
    else:
        splits = {"train": sorted(image_stems & xml_stems)}

    for split, stems in splits.items():
        (dst / "images" / split).mkdir(parents=True, exist_ok=True)
        (dst / "labels" / split).mkdir(parents=True, exist_ok=True)
        converted = report.images
        for stem in stems:
            image = _find_image(images_dir, stem)
            xml = ann_dir / f"{stem}.xml"
            if image is None or not xml.exists():
                if stem in image_stems or stem in xml_stems:
                    continue  # already reported above
                report.fault("missing_in_split", f"{stem}: listed in {split} but neither image nor xml exists")
                continue
            size = _image_size(image, report)
            if size is None:
                continue
            lines = parse_voc(xml, classes, report, size)
            if lines is None:
                continue
            shutil.copy2(image, dst / "images" / split / image.name)
            write_text(dst / "labels" / split / f"{stem}.txt", "".join(f"{line}\n" for line in lines))
            report.images += 1
            report.boxes += len(lines)
        if report.images == converted:  # a detector cannot be trained or scored on a split without images
            report.fault("empty_split", f"{split}: no image of the split could be converted")

    data = {
        "path": str(dst.resolve()),
        **{split: f"images/{split}" for split in splits},
        **({} if "val" in splits else {"val": "images/train"}),
        "names": dict(enumerate(classes)),
    }
    write_text(dst / "data.yaml", yaml.safe_dump(data, sort_keys=False))
    return report
