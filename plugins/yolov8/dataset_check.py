"""What ultralytics would silently leave out of a YOLO-layout dataset, found before training or scoring.

ultralytics' ``verify_image_label`` drops an image whose label file or image it cannot use, said only in its
scan log; the rules here are its rules, one label line at a time so that the message can name the line.
Its own function is not called: it rewrites a truncated JPEG in place, and a check must not touch the data.
"""
from __future__ import annotations

import math
from pathlib import Path

# ultralytics' tolerance: a coordinate up to 1 % beyond the image, and down to -1 % where no box is negative
# in size, is kept.
COORDINATE_SLACK = 0.01
MIN_IMAGE_SIDE = 10


def split_images(source) -> list[Path]:
    """The image files of a split as data.yaml gives it (resolved by ultralytics): folders, list files, or a
    list of either."""
    from ultralytics.data.utils import IMG_FORMATS

    images: list[Path] = []
    for entry in source if isinstance(source, (list, tuple)) else [source]:
        path = Path(entry)
        if path.is_dir():
            images += sorted(p for p in path.rglob("*") if p.suffix.lower().lstrip(".") in IMG_FORMATS)
        elif path.is_file() and path.suffix == ".txt":
            lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
            images += [(path.parent / line).resolve() if not Path(line).is_absolute() else Path(line) for line in lines]
    return images


def _box(numbers: list[float], polygon: bool) -> list[float]:
    """A row's class and box (x, y, w, h), the polygon's bounds where the row is one, as ultralytics scores it."""
    if not polygon:
        return numbers
    xs, ys = numbers[1::2], numbers[2::2]
    return [numbers[0], (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2, max(xs) - min(xs), max(ys) - min(ys)]


def label_line_problem(values: list[str], classes: int, polygon: bool) -> str | None:
    """Why ultralytics would drop the image of this label line (its whitespace-separated ``values``), or None.
    ``polygon``: the file holds segment rows (any row longer than 6 values), as ultralytics decides per file."""
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        return f"{' '.join(values)!r} is not numbers"
    if polygon and (len(numbers) < 7 or len(numbers) % 2 == 0):
        return (f"{len(numbers)} numbers in a file of polygon rows: expected a class and x y pairs"
                if len(numbers) != 5 else "a box row in a file of polygon rows")
    if not polygon and len(numbers) != 5:
        return f"{len(numbers)} numbers, expected 'class x y w h' (or a class and polygon points)"
    if not all(math.isfinite(v) for v in numbers):
        return f"{' '.join(values)!r} holds a value that is not a finite number"
    cls, *box = _box(numbers, polygon)
    if not (cls.is_integer() and 0 <= cls < classes):
        return f"class {values[0]}, but the dataset has classes 0-{classes - 1}"
    coordinates = f"coordinates {' '.join(values[1:])}: each is a share of the image, 0 to 1"
    if max(box) > 1 + COORDINATE_SLACK:
        return coordinates
    if min(box) < 0 and (min(box) < -COORDINATE_SLACK or min(box[2:]) < 0):
        return coordinates
    return None


def label_file_problem(path: Path, classes: int) -> str | None:
    """The first reason, naming the line, why ultralytics would drop the image of label file ``path``, or None."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        return f"cannot be read as UTF-8 text ({exc.__class__.__name__})"
    rows = [(number, line.split()) for number, line in enumerate(text.splitlines(), 1) if line.strip()]
    polygon = any(len(values) > 6 for _, values in rows)
    for number, values in rows:
        why = label_line_problem(values, classes, polygon)
        if why is not None:
            return f"line {number}: {why}"
    return None


def image_problem(path: Path) -> str | None:
    """Why ultralytics would drop image ``path`` (missing, unreadable, under 10 px, not an image format), or
    None; read only."""
    from PIL import Image
    from ultralytics.data.utils import IMG_FORMATS

    try:
        with Image.open(path) as image:
            image.verify()
            width, height = image.size
            kind = (image.format or "").lower()
    except FileNotFoundError:
        return "not found"
    except ImportError:  # ultralytics' Pillow tries a HEIF plugin, not installed, for a file Pillow cannot identify
        return "not a readable image (no image format Pillow knows)"
    except Exception as exc:  # PIL raises many kinds for a damaged file; each means ultralytics drops it
        return f"not a readable image ({exc})"
    if min(width, height) < MIN_IMAGE_SIDE:
        return f"{width}x{height} px, under ultralytics' {MIN_IMAGE_SIDE} px"
    if kind not in IMG_FORMATS | {"jpeg2000"}:
        return f"a {kind or 'unknown'} image, not one of ultralytics' formats"
    return None


def label_problem(info: dict, splits: tuple[str, ...]) -> str | None:
    """The first image of the dataset's ``splits`` that ultralytics would drop with its labels (left out of
    training or of the scores, said only in its scan log), naming the file and line, or None. ``info`` is the
    dataset as ultralytics' ``check_det_dataset`` resolved it."""
    from ultralytics.data.utils import img2label_paths

    problems = []
    for split in splits:
        images = split_images(info[split])
        if not images:  # ultralytics' own error for it is two lines and a link, after the model has loaded
            return (f"{info.get('yaml_file', 'the dataset')}: {split}: no image at {info[split]}: nothing to train "
                    f"or score on")
        labels = img2label_paths([str(p) for p in images])
        if not any(Path(label).is_file() for label in labels):
            # each image would count as defect-free: a layout ultralytics does not read, not a set of sound parts
            return (f"{split}: none of its {len(images)} images has a label file where ultralytics looks for it (e.g. "
                    f"{labels[0]}): each would count as an image without defects")
        for image, label in zip(images, labels):
            why = image_problem(image)
            if why is not None:
                problems.append(f"{image}: {why}")
            elif Path(label).is_file():  # an image without a label file is a background image
                why = label_file_problem(Path(label), int(info["nc"]))
                if why is not None:
                    problems.append(f"{label}: {why}")
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more images)" if len(problems) > 1 else ""
    return problems[0] + more + "; ultralytics would leave such images out"


def resolved(data_yaml: Path) -> dict:
    """The dataset as ultralytics' ``check_det_dataset`` resolves ``data_yaml``: its splits' paths, ``nc``,
    ``names``."""
    from ultralytics.data.utils import check_det_dataset

    return check_det_dataset(str(data_yaml), autodownload=False)


def dataset_problem(data_yaml: Path, splits: tuple[str, ...], model_names: list[str] | None = None,
                    info: dict | None = None) -> str | None:
    """Why training on, or scoring a model of ``model_names`` on, the dataset's ``splits`` would not use what
    it holds, naming the file, or None: the dataset's classes are not the model's in its order (each score would
    be another class's), or an image ultralytics drops (``label_problem``). ``info``: ``resolved(data_yaml)``
    where already at hand."""
    info = info or resolved(data_yaml)
    if model_names is not None:
        names = info["names"]
        names = [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)
        if names != list(model_names):
            return (f"{data_yaml}: names {names} are not the model's classes {list(model_names)}: each score would "
                    f"be another class's (label the dataset with the model's classes, in its order)")
    return label_problem(info, splits)


def shared_with_train(info: dict, split: str) -> int:
    """How many of the ``split`` images of the dataset ``info`` (``resolved``) are also in its train split (0 for
    train itself): a score on them is a score on what the model may have learnt."""
    if split == "train" or not info.get("train"):
        return 0
    train = {p.resolve() for p in split_images(info["train"])}
    return sum(p.resolve() in train for p in split_images(info[split]))
