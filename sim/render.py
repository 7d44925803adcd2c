"""Ray casting of a ``Scene`` per eye, shading, and sensor nuisances.

Each eye casts its own pixel rays (``ss x ss`` supersamples per pixel, box-filtered) against
the plate: the flat plane first, then Newton iterations on the heightfield along the ray (the
residual along the normal is checked in the tests to stay below 1e-3 mm). Rays that
miss the plate's extent hit the belt behind it. The texture is sampled bilinearly in plate
millimetres at the hit point, so the right image is consistent with the left image and
its ground-truth disparity to sub-pixel level.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sim.scene import Scene, flat_hit

HEIGHT_ITERATIONS = 5


def _sample(grid: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return cv2.remap(grid, x, y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@dataclass
class Hits:
    z: np.ndarray  # distance along the optical axis of the hit (mm)
    s: np.ndarray
    t: np.ndarray
    on_plate: np.ndarray  # bool
    point: tuple[np.ndarray, np.ndarray, np.ndarray]  # X, Y, Z camera coordinates


def trace(scene: Scene, origin: np.ndarray, u: np.ndarray, v: np.ndarray) -> Hits:
    """Hit points of the rays from ``origin`` through pixel positions (u, v) (float arrays)."""
    calib = scene.calib
    axes = (scene.e1, scene.e2, scene.n, scene.p0)
    n = scene.n
    rx = (u - calib.cx) / calib.focal_px
    ry = (v - calib.cy) / calib.focal_px
    rn = rx * n[0] + ry * n[1] + n[2]
    c = float((origin - scene.p0) @ n)
    z, s, t = flat_hit(calib, axes, origin, u, v, 0.0)
    d = origin - scene.p0
    # Newton on f(Z) = (P(Z) - P0).n - h(s(Z), t(Z)); f'(Z) = r.n - h_s r.e1 - h_t r.e2
    re1 = rx * scene.e1[0] + ry * scene.e1[1] + scene.e1[2]
    re2 = rx * scene.e2[0] + ry * scene.e2[1] + scene.e2[2]
    for _ in range(HEIGHT_ITERATIONS):
        tx, ty = scene.to_texel(s, t)
        h = _sample(scene.height, tx, ty).astype(np.float64)
        slope = _sample(scene.grad_s, tx, ty) * re1 + _sample(scene.grad_t, tx, ty) * re2
        f = c + z * rn - h
        z = z - f / np.maximum(rn - slope, 0.25 * rn)
        px, py, pz = d[0] + z * rx, d[1] + z * ry, d[2] + z
        s = px * scene.e1[0] + py * scene.e1[1] + pz * scene.e1[2]
        t = px * scene.e2[0] + py * scene.e2[1] + pz * scene.e2[2]
    if scene.plate_s_range is None:
        on_plate = np.ones(z.shape, bool)
    else:
        lo, hi = scene.plate_s_range
        on_plate = (s >= lo) & (s <= hi)
    zb, sb, tb = flat_hit(calib, axes, origin, u, v, scene.belt_offset_mm)
    z = np.where(on_plate, z, zb)
    s = np.where(on_plate, s, sb)
    t = np.where(on_plate, t, tb)
    point = (origin[0] + z * rx, origin[1] + z * ry, z)
    return Hits(z, s, t, on_plate, point)


def pixel_grid(calib, ss: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Sample positions: pixel centres (ss=1) or an ss x ss grid inside each pixel."""
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(calib.width)[:, None] + offs[None, :]).reshape(-1)
    v = (np.arange(calib.height)[:, None] + offs[None, :]).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    return uu, vv


def shade(scene: Scene, origin: np.ndarray, hits: Hits) -> np.ndarray:
    """Radiance (grey levels, unclipped) at the hits seen from ``origin``: Lambert on the
    textured albedo, Blinn-Phong highlight (broad sheen + sharp core) on the steel only."""
    lt = scene.lighting
    tx, ty = scene.to_texel(hits.s, hits.t)
    albedo = np.where(hits.on_plate, _sample(scene.albedo, tx, ty), _sample(scene.belt, tx, ty)).astype(np.float64)
    gs = np.where(hits.on_plate, _sample(scene.grad_s, tx, ty), 0.0)
    gt = np.where(hits.on_plate, _sample(scene.grad_t, tx, ty), 0.0)
    m = -scene.n  # flat surface normal, towards the camera
    nx = m[0] + gs * scene.e1[0] + gt * scene.e2[0]
    ny = m[1] + gs * scene.e1[1] + gt * scene.e2[1]
    nz = m[2] + gs * scene.e1[2] + gt * scene.e2[2]
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    px, py, pz = hits.point
    lx, ly, lz = lt.light_pos[0] - px, lt.light_pos[1] - py, lt.light_pos[2] - pz
    ln = np.sqrt(lx * lx + ly * ly + lz * lz)
    lx, ly, lz = lx / ln, ly / ln, lz / ln
    vx, vy, vz = origin[0] - px, origin[1] - py, origin[2] - pz
    vn = np.sqrt(vx * vx + vy * vy + vz * vz)
    vx, vy, vz = vx / vn, vy / vn, vz / vn
    ndotl = np.clip(nx * lx + ny * ly + nz * lz, 0.0, None)
    # reference: the flat plate lit at its centre, so the plate's mean grey stays ~ its albedo
    lref = lt.light_pos - scene.p0
    ref = max(float(m @ (lref / np.linalg.norm(lref))), 0.2)
    radiance = albedo * (lt.ambient + lt.diffuse * ndotl) / (lt.ambient + lt.diffuse * ref)
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
    ndoth = np.clip((nx * hx + ny * hy + nz * hz) / hn, 0.0, 1.0)
    spec = lt.spec_broad * ndoth**lt.spec_broad_exp + lt.spec_core * ndoth**lt.spec_core_exp
    return radiance + np.where(hits.on_plate, spec, 0.0)


def render_radiance(scene: Scene, origin: np.ndarray, ss: int = 2, row_offset_px: float = 0.0,
                    column_offset_px: float = 0.0) -> np.ndarray:
    """HxW radiance of one eye, box-filtered over ss x ss supersamples; ``row_offset_px``: the eye sees
    every point that many rows lower than a rectified eye would (what a calibration leaves), and
    ``column_offset_px`` that many columns further right (a principal point that moved since calibration). The
    optics' blur (``scene.sensor.lens_blur_px``) acts on the light before the pixels integrate it."""
    calib = scene.calib
    uu, vv = pixel_grid(calib, ss)
    img = shade(scene, origin, trace(scene, origin, uu - column_offset_px, vv - row_offset_px))
    blur = scene.sensor.lens_blur_px
    if blur > 0:
        img = cv2.GaussianBlur(img.reshape(calib.height * ss, calib.width * ss), (0, 0), blur * ss,
                               borderType=cv2.BORDER_REFLECT)
    travel = scene.sensor.motion_blur_px
    if travel > 0:
        img = cv2.filter2D(img.reshape(calib.height * ss, calib.width * ss), -1,
                           motion_kernel(travel * ss, scene.sensor.motion_angle_deg), borderType=cv2.BORDER_REFLECT)
    return img.reshape(calib.height, ss, calib.width, ss).mean(axis=(1, 3))


def motion_kernel(length_px: float, angle_deg: float, steps_per_px: int = 8) -> np.ndarray:
    """The exposure's average of the image moving ``length_px`` towards ``angle_deg`` (0: along the rows, 90:
    down the columns), centred: a line of that length, bilinearly splatted, summing to 1."""
    a = np.deg2rad(angle_deg)
    r = int(np.ceil(length_px / 2)) + 1
    kernel = np.zeros((2 * r + 1, 2 * r + 1), np.float64)
    n = max(2, int(np.ceil(length_px * steps_per_px)) + 1)
    for t in np.linspace(-length_px / 2, length_px / 2, n):
        x, y = r + t * np.cos(a), r + t * np.sin(a)
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return (kernel / kernel.sum()).astype(np.float32)


def sensor(
    radiance: np.ndarray, rng: np.random.Generator | None, gain: float, offset: float, noise: float, vignetting: float
) -> np.ndarray:
    """Vignetting, exposure (gain/offset), Gaussian noise, 8-bit quantisation -> BGR uint8."""
    h, w = radiance.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    img = radiance * (1.0 - vignetting * r2) * gain + offset
    if rng is not None:  # drawn at any sigma, so that a seed renders the same plates with and without noise
        img = img + rng.normal(0.0, noise, img.shape)
    grey = np.clip(np.round(img), 0, 255).astype(np.uint8)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)


def render_pair(scene: Scene, rng: np.random.Generator | None, ss: int = 2, nuisances: bool = True,
                rectification_error_px: float = 0.0, right_columns_px: float = 0.0):
    """(left BGR, right BGR, left GT disparity float32, left centre-ray hits). ``rectification_error_px``:
    the right eye's rows that far off the left's (0: an exactly rectified pair); ``right_columns_px``: its
    columns that far right of where the calibration puts them (every disparity that much smaller)."""
    calib = scene.calib
    left_o = np.zeros(3)
    right_o = np.array([calib.baseline_mm, 0.0, 0.0])
    rad_l = render_radiance(scene, left_o, ss)
    rad_r = render_radiance(scene, right_o, ss, rectification_error_px, right_columns_px)
    sn = scene.sensor
    if nuisances:
        left = sensor(rad_l, rng, 1.0, 0.0, sn.noise_sigma, sn.vignetting)
        right = sensor(rad_r, rng, sn.right_gain, sn.right_offset, sn.noise_sigma, sn.vignetting)
    else:
        left = sensor(rad_l, None, 1.0, 0.0, 0.0, 0.0)
        right = sensor(rad_r, None, 1.0, 0.0, 0.0, 0.0)
    uu, vv = pixel_grid(calib, 1)
    centre = trace(scene, left_o, uu, vv)
    disparity = (calib.focal_px * calib.baseline_mm / centre.z).astype(np.float32)
    return left, right, disparity, centre
