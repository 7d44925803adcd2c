"""Scene geometry: a tilted steel plate with heightfield defects on a conveyor belt.

Coordinates: the left camera at the origin looking along +Z, x right, y down (image axes);
the right camera at (+B, 0, 0). The plate is the plane through ``P0 = (0, 0, Z0)`` with
in-plane axes ``e1`` (≈ image x), ``e2`` (≈ image y) and unit normal ``n`` pointing away from
the camera, i.e. ``R = Ry(yaw) @ Rx(tilt)`` applied to the camera axes. A surface point is

    P(s, t) = P0 + s*e1 + t*e2 + h(s, t)*n          (s, t, h in mm)

so ``h > 0`` lies below the surface (farther from the camera) and ``h < 0`` is raised: the
same sign as ``DefectMeasurement.deviation_mm``. The belt is the parallel plane at
``h = belt_offset_mm`` behind the plate, visible where the plate (bounded in s) ends.

Defect heightfields: a superellipse plateau over the defect's footprint rectangle
(half-sizes a, b): ``h = D * (1 - smoothstep(r0, 1, r))``, ``r = (|ds/a|^p + |dt/b|^p)^(1/p)``:
flat at the design depth D over the middle, a smooth wall, zero at the rectangle's border.
``r0`` is the defect's ``plateau`` (0.55 by default; near 1, a flat-bottomed pit with a steep wall).
(ds, dt) are along the rectangle's own sides, which an evaluation set may turn on the plate (``angle_deg``:
a groove running diagonally across its box). The footprint rectangle is the (scaled) NEU-DET VOC box, so
the label box is the defect.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.types import Calibration

# class -> (shape name, superellipse exponent, raised?)
#   pits, grooves, cracks and inclusions lie below the surface; patches and rolled-in scale
#   (oxide pressed onto the strip) are modelled as raised.
CLASS_SHAPES: dict[str, tuple[str, float, bool]] = {
    "pitted_surface": ("pit", 4.0, False),
    "inclusion": ("pit", 4.0, False),
    "crazing": ("depression", 8.0, False),
    "scratches": ("groove", 8.0, False),
    "patches": ("raised_patch", 6.0, True),
    "rolled-in_scale": ("raised_scale", 6.0, True),
}
PLATEAU_R0 = 0.55  # the demo's and the default evaluation sets' floor: walls over the outer 45 %
ROUND_EXPONENT = 2.0  # an ellipse: ``--round-defects``


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    y = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return y * y * (3.0 - 2.0 * y)


def plate_axes(tilt_deg: float, yaw_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(e1, e2, n): the plate's in-plane axes and its normal (pointing away from the camera)."""
    a, b = np.radians(tilt_deg), np.radians(yaw_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    r = ry @ rx
    return r[:, 0].copy(), r[:, 1].copy(), r[:, 2].copy()


@dataclass
class Defect:
    class_name: str
    source: str  # NEU stem or "synthetic"
    shape: str
    exponent: float
    design_depth_mm: float  # signed: + below the surface, - raised
    center: tuple[float, float]  # (s, t) mm
    half: tuple[float, float]  # (a, b) mm
    patch: np.ndarray | None = None  # appearance (grey float32), box given by patch_box
    patch_box: tuple[int, int, int, int] = (0, 0, 0, 0)
    plateau: float = PLATEAU_R0  # share of the half-sizes that is flat floor; the wall rises over the rest
    angle_deg: float = 0.0  # the outline turned on the plate, from the s axis towards t (``half`` along its own axes)

    @property
    def extent(self) -> tuple[float, float]:
        """(s, t) half-sizes of the rectangle on the plate that holds the turned outline, mm."""
        return turned_extent(self.half, self.angle_deg)


@dataclass
class Lighting:
    light_pos: np.ndarray  # point light, camera coordinates (mm)
    ambient: float = 0.45
    diffuse: float = 0.55
    spec_broad: float = 50.0
    spec_broad_exp: float = 25.0
    spec_core: float = 90.0
    spec_core_exp: float = 400.0


@dataclass
class Sensor:
    noise_sigma: float = 1.8
    right_gain: float = 1.06
    right_offset: float = 3.0
    vignetting: float = 0.08
    lens_blur_px: float = 0.0  # Gaussian sigma of the optics, before the pixels integrate the light
    motion_blur_px: float = 0.0  # how far the plate moves across the image during the exposure, both eyes alike
    motion_angle_deg: float = 90.0  # which way: 0 along the rows (the baseline), 90 down the image


@dataclass
class Scene:
    calib: Calibration
    z0: float
    tilt_deg: float
    yaw_deg: float
    plate_s_range: tuple[float, float] | None  # None: the plate fills the view
    belt_offset_mm: float
    texel_mm: float
    grid_origin: tuple[float, float]  # (s, t) of texel (0, 0)
    albedo: np.ndarray
    height: np.ndarray
    belt: np.ndarray
    lighting: Lighting
    sensor: Sensor
    defects: list[Defect] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.e1, self.e2, self.n = plate_axes(self.tilt_deg, self.yaw_deg)
        self.p0 = np.array([0.0, 0.0, self.z0])
        self.update_gradients()

    def update_gradients(self) -> None:
        gt, gs = np.gradient(self.height.astype(np.float64), self.texel_mm)
        self.grad_s, self.grad_t = gs.astype(np.float32), gt.astype(np.float32)

    def to_texel(self, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (
            ((s - self.grid_origin[0]) / self.texel_mm).astype(np.float32),
            ((t - self.grid_origin[1]) / self.texel_mm).astype(np.float32),
        )

    def to_st(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.grid_origin[0] + col * self.texel_mm, self.grid_origin[1] + row * self.texel_mm


def flat_hit(calib: Calibration, scene_axes, origin: np.ndarray, u, v, offset: float = 0.0):
    """Hit of the rays through pixels (u, v) from ``origin`` with the plane ``h = offset``.

    Returns (Z, s, t). Ray direction is ((u-cx)/f, (v-cy)/f, 1), so the ray parameter is Z.
    """
    e1, e2, n, p0 = scene_axes
    rx = (np.asarray(u, np.float64) - calib.cx) / calib.focal_px
    ry = (np.asarray(v, np.float64) - calib.cy) / calib.focal_px
    rn = rx * n[0] + ry * n[1] + n[2]
    c = float((origin - p0) @ n)
    z = (offset - c) / rn
    d = [origin[i] - p0[i] for i in range(3)]
    s = (d[0] + z * rx) * e1[0] + (d[1] + z * ry) * e1[1] + (d[2] + z) * e1[2]
    t = (d[0] + z * rx) * e2[0] + (d[1] + z * ry) * e2[1] + (d[2] + z) * e2[2]
    return z, s, t


def turned_extent(half: tuple[float, float], angle_deg: float) -> tuple[float, float]:
    """(s, t) half-sizes of the rectangle that holds a rectangle of half-sizes ``half`` turned by ``angle_deg``."""
    a, b = half
    c, k = abs(math.cos(math.radians(angle_deg))), abs(math.sin(math.radians(angle_deg)))
    return a * c + b * k, a * k + b * c


def local_coords(defect: Defect, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plate coordinates (s, t) mm -> the defect's own (along ``half[0]``, along ``half[1]``), from its centre."""
    ds, dt = s - defect.center[0], t - defect.center[1]
    if not defect.angle_deg:
        return ds, dt
    c, k = math.cos(math.radians(defect.angle_deg)), math.sin(math.radians(defect.angle_deg))
    return ds * c + dt * k, dt * c - ds * k


def plate_coords(defect: Defect, ls: np.ndarray, lt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The defect's own coordinates (along ``half[0]``, along ``half[1]``) from its centre -> plate (s, t) mm:
    ``local_coords`` undone."""
    if not defect.angle_deg:
        return ls + defect.center[0], lt + defect.center[1]
    c, k = math.cos(math.radians(defect.angle_deg)), math.sin(math.radians(defect.angle_deg))
    return defect.center[0] + ls * c - lt * k, defect.center[1] + ls * k + lt * c


def heightfield_patch(defect: Defect, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b = defect.half
    p = defect.exponent
    ls, lt = local_coords(defect, s, t)
    r = (np.abs(ls / a) ** p + np.abs(lt / b) ** p) ** (1.0 / p)
    return defect.design_depth_mm * (1.0 - smoothstep(defect.plateau, 1.0, r))
