"""Procedural appearance: rolled steel, conveyor belt, stand-in defect patches.

All textures live on a grid in plate millimetres (``texel_mm`` per texel), so both eyes sample
the same surface pattern at their own ray hits.
"""
from __future__ import annotations

import cv2
import numpy as np

PLATE_MEAN = 125.0


def _blur_noise(rng: np.random.Generator, shape: tuple[int, int], sx: float, sy: float,
                angle_deg: float = 0.0) -> np.ndarray:
    """White noise blurred with a Gaussian of sigma (sx, sy) texels, its y axis turned ``angle_deg`` towards the
    grid's x axis, normalised to unit std."""
    noise = rng.standard_normal(shape).astype(np.float32)
    sx, sy = max(sx, 0.3), max(sy, 0.3)
    if angle_deg % 360.0 == 0.0:
        kx, ky = 2 * int(3 * sx) + 1, 2 * int(3 * sy) + 1
        out = cv2.GaussianBlur(noise, (kx, ky), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT)
    else:
        out = cv2.filter2D(noise, -1, _turned_gaussian(sx, sy, angle_deg), borderType=cv2.BORDER_REFLECT)
    std = float(out.std())
    return out / std if std > 0 else out


def _turned_gaussian(sx: float, sy: float, angle_deg: float) -> np.ndarray:
    """A normalised Gaussian kernel of sigma ``sx`` across and ``sy`` along its long axis, that axis turned
    ``angle_deg`` from the grid's y axis towards its x axis."""
    a = np.deg2rad(angle_deg)
    r = int(3 * max(sx, sy))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    along = yy * np.cos(a) + xx * np.sin(a)
    across = -yy * np.sin(a) + xx * np.cos(a)
    kernel = np.exp(-0.5 * ((across / sx) ** 2 + (along / sy) ** 2))
    return (kernel / kernel.sum()).astype(np.float32)


def _coarse_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth large-scale noise: a small random grid upsampled (cheap for big sigmas)."""
    gh, gw = max(int(shape[0] / cell) + 2, 2), max(int(shape[1] / cell) + 2, 2)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    small = cv2.GaussianBlur(small, (3, 3), 0.8)
    out = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    std = float(out.std())
    return out / std if std > 0 else out


def steel_albedo(rng: np.random.Generator, shape: tuple[int, int], texel_mm: float, contrast: float = 1.0,
                 grain_angle_deg: float = 0.0) -> np.ndarray:
    """Rolled/brushed steel, grey ~125: streaks along the rolling direction, fine isotropic grain (what stereo
    matches on), mill-scale mottling and a few stains. ``contrast`` scales every variation about the mean (below
    1: polished, low-texture metal); ``grain_angle_deg`` turns the rolling direction from the plate's t axis (0,
    down the image: the streaks cross a horizontal baseline) towards its s axis (90: along the baseline)."""
    t = texel_mm
    streaks = _blur_noise(rng, shape, sx=0.35 / t, sy=8.0 / t, angle_deg=grain_angle_deg)
    grain = _blur_noise(rng, shape, sx=0.6 / t, sy=0.6 / t)
    medium = _blur_noise(rng, shape, sx=2.5 / t, sy=4.0 / t, angle_deg=grain_angle_deg)
    mottle = _coarse_noise(rng, shape, cell=60.0 / t)
    stains = np.clip(_coarse_noise(rng, shape, cell=25.0 / t) - 1.6, 0, None)
    albedo = PLATE_MEAN + 9.0 * streaks + 8.0 * grain + 6.0 * medium + 12.0 * mottle - 25.0 * stains
    if contrast != 1.0:
        albedo = PLATE_MEAN + contrast * (albedo - PLATE_MEAN)
    return albedo.astype(np.float32)


def belt_albedo(rng: np.random.Generator, shape: tuple[int, int], texel_mm: float) -> np.ndarray:
    """Dark rubber conveyor belt with a fine weave and wear."""
    t = texel_mm
    grain = _blur_noise(rng, shape, sx=0.7 / t, sy=0.7 / t)
    wear = _coarse_noise(rng, shape, cell=80.0 / t)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    weave = np.sin(2 * np.pi * xx * t / 6.0) * np.sin(2 * np.pi * yy * t / 6.0)
    return (48.0 + 7.0 * grain + 5.0 * wear + 3.0 * weave).astype(np.float32)


def synthetic_defect_patch(
    rng: np.random.Generator, class_name: str, width: int, height: int
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """A stand-in defect appearance (used when NEU-DET is not available), grey float32 around
    ``PLATE_MEAN``, with a margin; returns (patch, box inside patch) like ``NeuCrops.patch``."""
    width, height = max(int(width), 8), max(int(height), 8)
    m = int(round(0.15 * max(width, height))) + 3
    H, W = height + 2 * m, width + 2 * m
    base = PLATE_MEAN + 6.0 * _blur_noise(rng, (H, W), 1.0, 1.0)
    ink = np.zeros((H, W), np.float32)
    x0, y0, x1, y1 = m, m, m + width, m + height
    area = width * height
    if class_name == "scratches":
        vertical = height >= width
        for _ in range(int(rng.integers(1, 4))):
            if vertical:
                a = (int(rng.integers(x0, x1)), y0)
                b = (int(np.clip(a[0] + rng.integers(-width // 3 - 1, width // 3 + 2), x0, x1 - 1)), y1 - 1)
            else:
                a = (x0, int(rng.integers(y0, y1)))
                b = (x1 - 1, int(np.clip(a[1] + rng.integers(-height // 3 - 1, height // 3 + 2), y0, y1 - 1)))
            cv2.line(ink, a, b, float(rng.uniform(0.6, 1.0)), thickness=int(rng.integers(1, 3)), lineType=cv2.LINE_AA)
    elif class_name == "crazing":
        for _ in range(max(6, area // 120)):
            a = np.array([rng.integers(x0, x1), rng.integers(y0, y1)])
            b = np.clip(a + rng.integers(-8, 9, size=2), [x0, y0], [x1 - 1, y1 - 1])
            cv2.line(ink, tuple(int(v) for v in a), tuple(int(v) for v in b), 0.7, 1, cv2.LINE_AA)
    elif class_name in ("pitted_surface", "inclusion"):
        for _ in range(max(3, area // 250)):
            c = (int(rng.integers(x0, x1)), int(rng.integers(y0, y1)))
            ax = (int(rng.integers(1, max(2, width // 8))), int(rng.integers(1, max(2, height // 8))))
            cv2.ellipse(ink, c, ax, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(0.6, 1.0)), -1, cv2.LINE_AA)
    else:  # patches, rolled-in_scale: irregular blotches
        blot = _blur_noise(rng, (H, W), max(width, height) / 10.0, max(width, height) / 10.0)
        ink = np.clip(blot - 0.3, 0, 1.5)
        ink[: y0] = ink[y1:] = 0
        ink[:, : x0] = ink[:, x1:] = 0
    ink = cv2.GaussianBlur(ink, (3, 3), 0.7)
    sign = 1.0 if class_name != "patches" else -0.6  # patches read brighter in NEU
    return (base - sign * 70.0 * ink).astype(np.float32), (x0, y0, x1, y1)
