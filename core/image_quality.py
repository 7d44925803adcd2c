"""Whether a frame's images can show a defect at all: lit, not blinded, with texture.

The detector reads the left image alone, and finding nothing there passes the part. On a black frame
(the lights failed, a covered lens), a washed-out one (blinded, the exposure run away) or a featureless
one (fogged, far out of focus, something in front of the lens) it finds nothing too, and the part would
pass on a picture that showed nothing. Such a frame is its part's ERROR instead (``core.engine``).
The right image is held to the same limits: without it no defect is measured, and a part without defects
passes only once its images show the plate where the recipe expects it (``core.plate_view``), which a dark
or covered right eye would leave blind. The limits are the recipe's ``camera.image_check``; the defaults
trip only on images with no usable content, and ``docs/recipe-reference.md`` says how to tighten them for a
line.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SATURATED_GREY = 245  # a pixel at or above this grey level (of 255) holds no texture: blinded


@dataclass(frozen=True)
class ImageStats:
    """mean_grey: of 255. saturated: share of pixels at ``SATURATED_GREY`` or more. texture: the standard
    deviation, in grey levels, of the image's detail at 1-4 px (a difference of Gaussians), which sensor
    noise alone keeps below about 0.5 and a plate's grain above 1."""

    mean_grey: float
    saturated: float
    texture: float


def image_stats(image: np.ndarray) -> ImageStats:
    """HxWx3 uint8 BGR (or HxW uint8 grey) -> its ``ImageStats``, read at half the resolution (averaging
    2 x 2 pixels halves the sensor noise; 0.4 ms for a WVGA frame)."""
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"image_stats: needs an HxW or HxWx3 uint8 image, got {image.dtype} of shape {image.shape}")
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = grey.shape
    small = (cv2.resize(grey, (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA)
             if min(h, w) >= 16 else grey).astype(np.float32)
    detail = cv2.GaussianBlur(small, (0, 0), 0.5) - cv2.GaussianBlur(small, (0, 0), 2.0)
    return ImageStats(float(small.mean()), float((small >= SATURATED_GREY).mean()), float(detail.std()))


def image_problem(stats: ImageStats, min_mean_grey: float, max_saturated: float, min_texture: float,
                  image: str = "the image") -> str | None:
    """What makes an image with these ``stats`` unable to show a defect, in words naming it ``image``, or None."""
    if stats.mean_grey < min_mean_grey:
        return (f"{image} is too dark to inspect (mean grey {stats.mean_grey:.0f} of 255, at least "
                f"{min_mean_grey:g} needed: camera.image_check.min_mean_grey): the lights, the exposure or a covered lens")
    if stats.saturated > max_saturated:
        return (f"{image} is washed out ({stats.saturated:.0%} of it saturated, at most {max_saturated:.0%}: "
                f"camera.image_check.max_saturated): the exposure, or a light shining into the lens")
    if stats.texture < min_texture:
        return (f"{image} shows no texture to inspect ({stats.texture:.2f} grey levels of detail, at least "
                f"{min_texture:g}: camera.image_check.min_texture): out of focus, a fogged lens or something in "
                f"front of it")
    return None
