"""Synthetic rectified pairs with exact ground truth: textured planar layers seen from two cameras.

Used by the tests and as a held-out check that nothing was tuned only on Middlebury.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Layer:
    """A plane d = a + b*x + c*y (left-image pixels) visible where ``mask`` (left coords) is true."""

    a: float
    b: float = 0.0
    c: float = 0.0
    box: tuple[int, int, int, int] | None = None  # x0, y0, x1, y1 in the left image; None = everywhere


def texture(h: int, w: int, rng: np.random.Generator, scale: float = 1.5) -> np.ndarray:
    """HxWx3 float32 in [0, 1]: smoothed noise, so that bilinear resampling stays faithful."""
    noise = rng.random((h, w, 3)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), scale)
    lo, hi = smooth.min(), smooth.max()
    return (smooth - lo) / max(hi - lo, 1e-6)


def _inside(layer: Layer, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    if layer.box is None:
        return np.ones(np.broadcast(x, y).shape, bool)
    x0, y0, x1, y1 = layer.box
    return (x >= x0) & (x < x1) & (y >= y0) & (y < y1)


def render(h: int, w: int, layers: list[Layer], seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Layers back to front. Returns (left BGR uint8, right BGR uint8, left disparity float32,
    non-occluded bool mask)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    left = np.zeros((h, w, 3), np.float32)
    right = np.zeros((h, w, 3), np.float32)
    gt = np.zeros((h, w), np.float32)
    front_left = np.full((h, w), -1)
    front_right = np.full((h, w), -1)
    for k, layer in enumerate(layers):
        tex = texture(h, w + 2 * w, rng)  # wide enough for what the right camera sees beyond the left's edge
        offset = float(w)
        inside = _inside(layer, xs, ys)
        d = layer.a + layer.b * xs + layer.c * ys
        left[inside] = cv2.remap(tex, xs + offset, ys, cv2.INTER_LINEAR)[inside]
        gt[inside], front_left[inside] = d[inside], k
        # The right pixel xr sees left coordinate xl with xl - d(xl) = xr.
        xl = (xs + layer.a + layer.c * ys) / (1.0 - layer.b)
        seen = _inside(layer, np.floor(xl + 0.5), ys)
        right[seen] = cv2.remap(tex, xl + offset, ys, cv2.INTER_LINEAR)[seen]
        front_right[seen] = k
    target = np.clip(np.round(xs - gt).astype(int), 0, w - 1)
    nonocc = (front_right[ys.astype(int), target] == front_left) & (xs - gt >= 0)
    to_u8 = lambda im: (np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8)
    return to_u8(left), to_u8(right), gt, nonocc


def fronto_parallel(h: int, w: int, disparity: float, seed: int = 0):
    return render(h, w, [Layer(disparity)], seed)


def layered_scene(h: int = 96, w: int = 128, seed: int = 0):
    """A slanted background and a nearer slanted box: occlusions, a depth edge, sub-pixel slopes."""
    return render(h, w, [Layer(6.0, 0.02, 0.01), Layer(16.5, -0.015, 0.0, (w // 3, h // 4, 2 * w // 3, 3 * h // 4))], seed)
