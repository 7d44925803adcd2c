"""Small exact stereo scenes for tests: a textured tilted plane with optional pits (spherical caps or flat-bottomed).

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
    floor: float = 0.0  # share of the radius that is flat at depth_mm, its wall a cone beyond; 0 = a paraboloid


@dataclass
class Groove:
    """A straight groove, flat-bottomed between sloping walls, with sloping ends."""

    u: float  # centre in left-image pixels
    v: float
    angle_deg: float  # of its length from the image's rows
    length_mm: float
    width_mm: float
    depth_mm: float
    floor: float = 0.5  # share of its width that is flat at depth_mm

    def depth(self, local: np.ndarray) -> np.ndarray:
        """Depth (mm) at plate coordinates ``local`` (..., 2), relative to the groove's centre."""
        a = np.deg2rad(self.angle_deg)
        along = local[..., 0] * np.cos(a) + local[..., 1] * np.sin(a)
        across = -local[..., 0] * np.sin(a) + local[..., 1] * np.cos(a)
        wall = (1 - np.abs(across) / (self.width_mm / 2)) / (1 - self.floor)
        end = (1 - np.abs(along) / (self.length_mm / 2)) / 0.1
        return self.depth_mm * np.clip(np.minimum(wall, end), 0.0, 1.0)


def calib_for(width: int, height: int, focal_px: float = 350.06, baseline_mm: float = 120.0) -> Calibration:
    return Calibration(focal_px, baseline_mm, (width - 1) / 2, (height - 1) / 2, width, height)


def _texture(seed: int, size: int = 1024) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.random((size, size)).astype(np.float32)
    tex = sum(cv2.resize(cv2.resize(noise, (size // s, size // s), interpolation=cv2.INTER_AREA), (size, size)) * w
              for s, w in ((1, 0.35), (4, 0.35), (16, 0.3)))
    # as a lens would: texel-sized noise sampled at ~2 texels per pixel otherwise aliases, and the two
    # eyes, sampling it at other phases, would not see the same pattern
    tex = cv2.GaussianBlur(tex, (0, 0), 1.0)
    return np.clip(40 + 180 * (tex - tex.min()) / (tex.max() - tex.min()), 0, 255).astype(np.float32)


def render(calib: Calibration, distance_mm: float, tilt_deg: float = 0.0, pits: list[Pit | Groove] = (), seed: int = 0,
           shading: float = 0.0, contrast=None):
    """Left, right (HxWx3 uint8) and the left image's exact disparity (HxW float32). ``shading``: the walls lit
    from one side, the texture brightened by that much per unit of the surface's slope down the plate (mm per
    mm; the same for both eyes, as diffuse light is). ``contrast``: the texture's contrast about its mean at plate
    coordinates (..., 2) mm from the first pit's centre (or the plate's), as a function of them (1 = as drawn)."""
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
            if isinstance(pit, Groove):
                depth += pit.depth(local - c)
                continue
            r2 = ((local - c) ** 2).sum(-1) / pit.radius_mm**2
            if pit.floor > 0:
                wall = (1 - np.sqrt(r2)) / (1 - pit.floor)
                depth += pit.depth_mm * np.clip(wall, 0.0, 1.0)
            else:
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
        if contrast is not None:
            mean = float(tex.mean())
            grey = mean + (grey - mean) * contrast(local - (centres[0][0] if centres else 0.0)).astype(np.float32)
        if shading:
            slope = (depth_at(local + np.array([0.0, 0.05])) - depth_at(local - np.array([0.0, 0.05]))) / 0.1
            grey = grey * np.clip(1.0 + shading * slope, 0.2, 2.0).astype(np.float32)
        images.append(np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2))
        if origin_x == 0.0:
            disparity = (f * b / p[..., 2]).astype(np.float32)
    return images[0], images[1], disparity


def step_pair(width: int = 160, height: int = 120, plane: tuple[float, float, float] = (0.02, -0.01, 40.0),
              step_box: tuple[int, int, int, int] | None = (60, 45, 100, 75), step_px: float = -0.3,
              noise: float = 1.5, contrast: float = 30.0, gain: float = 1.05, offset: float = 3.0, seed: int = 0):
    """A textured plane d = a*u + b*v + c (disparity px) with a flat-bottomed step of ``step_px`` inside
    ``step_box`` (x0, y0, x1, y1 in left pixels; negative = farther, a pit), as a rectified pair of grey
    HxW float32 images with the exact left disparity (HxW float64).

    The texture is a sum of random sinusoids below the Nyquist frequency on the surface, so both eyes
    sample one pattern, band-limited to a quarter cycle per pixel: the left pixel u sees surface coordinate s = u, the right pixel x
    the point with x = s - d(s). The right eye has another exposure (gain, offset); both get noise."""
    rng = np.random.default_rng(seed)
    k = 40
    fu = rng.uniform(-0.25, 0.25, k) * 2 * np.pi  # well below Nyquist: interpolation is nearly exact there
    fv = rng.uniform(-0.25, 0.25, k) * 2 * np.pi
    ph = rng.uniform(0, 2 * np.pi, k)
    amp = contrast / np.sqrt(k) * rng.uniform(0.5, 1.5, k)

    def texture(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        return 120.0 + np.sum(amp[:, None, None] * np.sin(fu[:, None, None] * s + fv[:, None, None] * t + ph[:, None, None]),
                              axis=0)

    a, b, c = plane
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    disparity = a * u + b * v + c
    inside = np.zeros((height, width), bool)
    if step_box is not None:
        x0, y0, x1, y1 = step_box
        inside[y0:y1, x0:x1] = True
        disparity = disparity + step_px * inside
    left = texture(u, v)
    # right pixel x, row v: the surface point s with s - d(s) = x, on the plane or on the step's floor
    s_plane = (u + b * v + c) / (1 - a)
    s_step = (u + b * v + c + step_px) / (1 - a)
    on_step = np.zeros_like(inside)
    if step_box is not None:
        on_step = (s_step >= x0) & (s_step < x1) & (v >= y0) & (v < y1)
    s = np.where(on_step, s_step, s_plane)
    right = gain * texture(s, v) + offset
    left = left + rng.normal(0, noise, left.shape)
    right = right + rng.normal(0, noise, right.shape)
    return left.astype(np.float32), right.astype(np.float32), disparity


def census_window(radius_x: int, radius_y: int) -> tuple[tuple[int, int], ...]:
    """Census offsets of every pixel of a (2ry+1) x (2rx+1) window but its centre: at 4 x 3 the 62 bits that pack
    into three words, the census kernels' general case (the matcher's own star has 24, one word)."""
    return tuple((dy, dx) for dy in range(-radius_y, radius_y + 1) for dx in range(-radius_x, radius_x + 1)
                 if (dy, dx) != (0, 0))
