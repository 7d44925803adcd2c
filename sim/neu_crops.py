"""NEU-DET val crops as defect appearance.

Layout expected (the one in ``../shared/data/neu-det``): ``images/<stem>.jpg`` (200x200 grey
JPEG), ``annotations/<stem>.xml`` (Pascal VOC), ``val.txt`` (one stem per line).
The class of a box is the XML ``<object><name>``, never the file name: some NEU images
carry boxes of another class than their file name says.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers import text_files
from drivers.sequence_folder import incomplete

NEU_CLASSES = ("crazing", "inclusion", "patches", "pitted_surface", "rolled-in_scale", "scratches")


class NeuDetError(Exception):
    """NEU-DET folder missing or unusable; the message names what is wrong."""


@dataclass(frozen=True)
class NeuBox:
    stem: str
    class_name: str
    box: tuple[int, int, int, int]  # xmin, ymin, xmax, ymax in NEU image px

    @property
    def width(self) -> int:
        return self.box[2] - self.box[0]

    @property
    def height(self) -> int:
        return self.box[3] - self.box[1]


def parse_voc(path: Path) -> list[tuple[str, tuple[int, int, int, int]]]:
    root = ET.parse(path).getroot()
    out = []
    for obj in root.iter("object"):
        name = (obj.findtext("name") or "").strip()
        bb = obj.find("bndbox")
        if not name or bb is None:
            continue
        box = tuple(int(round(float(bb.findtext(k)))) for k in ("xmin", "ymin", "xmax", "ymax"))
        out.append((name, box))
    return out


class NeuCrops:
    """Index of the val-split boxes of a NEU-DET folder, by class (from the XML)."""

    def __init__(self, root: Path):
        self.root = Path(root)
        split = self.root / "val.txt"
        if not self.root.is_dir():
            raise NeuDetError(f"NEU-DET folder not found: {self.root}")
        if not split.exists():
            raise NeuDetError(f"{split}: val split list missing (not a NEU-DET folder?)")
        self.stems = [s.strip() for s in text_files.decode(split.read_bytes()).splitlines() if s.strip()]
        self.by_class: dict[str, list[NeuBox]] = {c: [] for c in NEU_CLASSES}
        for stem in self.stems:
            xml = self.root / "annotations" / f"{stem}.xml"
            if not xml.exists():
                continue
            for name, box in parse_voc(xml):
                if name in self.by_class:
                    self.by_class[name].append(NeuBox(stem, name, box))
        if not any(self.by_class.values()):
            raise NeuDetError(f"{self.root}: no annotated val boxes found")
        self._cache: dict[str, np.ndarray] = {}

    def candidates(self, class_name: str, min_side: int = 16, max_aspect: float = 6.0) -> list[NeuBox]:
        """Boxes usable as one defect: not tiny, not a sliver, not (almost) the whole image."""
        out = []
        for b in self.by_class.get(class_name, []):
            w, h = b.width, b.height
            if min(w, h) < min_side or max(w, h) / max(min(w, h), 1) > max_aspect:
                continue
            if w * h > 0.8 * 200 * 200:
                continue
            out.append(b)
        return out or list(self.by_class.get(class_name, []))

    def image(self, stem: str) -> np.ndarray:
        """The NEU image as float32 grey."""
        if stem not in self._cache:
            path = self.root / "images" / f"{stem}.jpg"
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise NeuDetError(f"{path}: cannot be read ({exc.strerror})") from None
            why = incomplete(data, path.suffix)  # it would decode padded with grey, a defect half flat
            if why is not None:
                raise NeuDetError(f"{path}: not whole: {why}")
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise NeuDetError(f"{path}: not an image")
            self._cache[stem] = img.astype(np.float32)
        return self._cache[stem]

    def pick(self, rng: np.random.Generator, class_name: str) -> NeuBox:
        cands = self.candidates(class_name)
        if not cands:
            raise NeuDetError(f"{self.root}: no val boxes of class {class_name}")
        return cands[int(rng.integers(len(cands)))]

    def patch(self, box: NeuBox, margin_frac: float = 0.15) -> tuple[np.ndarray, tuple[int, int, int, int]]:
        """The box region with a context margin (clipped to the image), and the box inside that patch."""
        img = self.image(box.stem)
        h, w = img.shape
        x0, y0, x1, y1 = box.box
        m = int(round(margin_frac * max(x1 - x0, y1 - y0))) + 3
        px0, py0, px1, py1 = max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h)
        return img[py0:py1, px0:px1].copy(), (x0 - px0, y0 - py0, x1 - px0, y1 - py0)
