"""Small exact stereo scenes for tests: a textured tilted plane with an optional spherical-cap pit.

The geometry is ray-cast for both eyes so disparity is exact; kept tiny so tests stay fast.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from core.types import Calibration


@dataclass
class Pit:
    u: float  # centre in left-image pixels
    v: float
    radius_mm: float
    depth_mm: float  # + below the surface


def calib_for(width: int, height: int, focal_px: float = 350.06, baseline_mm: float = 120.0) -> Calibration:
    return Calibration(focal_px, baseline_mm, (width - 1) / 2, (height - 1) / 2, width, height)


def _texture(seed: int, size: int = 1024) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.random((size, size)).astype(np.float32)
    tex = sum(cv2.resize(cv2.resize(noise, (size // s, size // s), interpolation=cv2.INTER_AREA), (size, size)) * w
              for s, w in ((1, 0.35), (4, 0.35), (16, 0.3)))
    return np.clip(40 + 180 * (tex - tex.min()) / (tex.max() - tex.min()), 0, 255).astype(np.float32)


def render(calib: Calibration, distance_mm: float, tilt_deg: float = 0.0, pits: list[Pit] = (), seed: int = 0):
    """Left, right (HxWx3 uint8) and the left image's exact disparity (HxW float32)."""
    f, b = calib.focal_px, calib.baseline_mm
    tex = _texture(seed)
    t = np.deg2rad(tilt_deg)
    normal = np.array([0.0, -np.sin(t), np.cos(t)])  # plane tilted about the x axis, facing the camera
    point = np.array([0.0, 0.0, distance_mm])
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(normal, e1)
    # Pit centres in plate coordinates, from the left pixel where the caller wants them.
    centres = []
    for pit in pits:
        ray = np.array([(pit.u - calib.cx) / f, (pit.v - calib.cy) / f, 1.0])
        hit = ray * (normal @ point) / (normal @ ray)
        centres.append((np.array([(hit - point) @ e1, (hit - point) @ e2]), pit))

    def depth_at(local: np.ndarray) -> np.ndarray:
        depth = np.zeros(local.shape[:-1])
        for c, pit in centres:
            r2 = ((local - c) ** 2).sum(-1) / pit.radius_mm**2
            depth += np.where(r2 < 1, pit.depth_mm * (1 - r2), 0.0)
        return depth

    def hit(origin_x: float):
        v, u = np.mgrid[0 : calib.height, 0 : calib.width].astype(np.float64)
        rays = np.stack([(u - calib.cx) / f, (v - calib.cy) / f, np.ones_like(u)], axis=-1)
        origin = np.array([origin_x, 0.0, 0.0])
        # The surface is (q - point).n = depth(q) (n points away from the camera, so + is below);
        # depth varies slowly along a ray, so a few fixed-point steps converge.
        depth = np.zeros(u.shape)
        for _ in range(8):
            s = ((normal @ point) - (origin @ normal) + depth) / (rays @ normal)
            p = origin + rays * s[..., None]
            local = np.stack([(p - point) @ e1, (p - point) @ e2], axis=-1)
            depth = depth_at(local)
        return p, local

    images = []
    for origin_x in (0.0, b):
        p, local = hit(origin_x)
        mx = (local[..., 0] * 2.0 + 512).astype(np.float32)
        my = (local[..., 1] * 2.0 + 512).astype(np.float32)
        grey = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        images.append(np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2))
        if origin_x == 0.0:
            disparity = (f * b / p[..., 2]).astype(np.float32)
    return images[0], images[1], disparity
