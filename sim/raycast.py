"""A second, independent renderer of plates: flat-bottomed pits with vertical walls, ray cast.

``sim/render.py`` draws the evaluation sets; a depth method tuned on them could fit that renderer's
habits (its texture, its walls, its aliasing) rather than plates. This one shares none of its code:
each pixel is the mean of SUPERSAMPLE x SUPERSAMPLE rays cast from the eye onto a tilted plane with
rectangular or elliptical pits, a texture tabulated on the plate (``TEXEL_MM``) and sampled where each
ray lands, a pit's floor as textured as the plate and its walls darker. The truth is the geometry's
own: ``deviation_mm`` the pit's depth along the plate's normal, ``distance_mm`` the depth of its
floor where the centre of its box looks. ZED WVGA geometry, as the goals' independently rendered plates.

``render_sequence(out, kind, frames, seed)`` writes the sequence-folder layout (``left/``, ``right/``,
``labels/``, ``gt/``, ``calib.yaml``; ``true_disparity``: the left eye's ray through each pixel's centre, unknown
on a wall); ``kind`` is ``textured`` (pits 30-80 px at 350-650 mm) or ``low``
(faint texture, pits 10-25 px at 380-460 mm); ``image_format`` ``jpg`` saves the eyes as JPEG (quality 95), the
same scene as the seed's PNG. ``look`` (``Look``) changes how the same scene is lit and seen: walls the light
falls on, more noise and a larger exposure difference between the eyes, a finer texture, vignetting.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from drivers.sequence_folder import JPEG_QUALITY, write_calibration, write_frame

CALIB = dict(focal_px=350.06, baseline_mm=120.0, cx=335.5, cy=187.5, width=672, height=376, doffs=0.0)
TEXEL_MM = 0.25
SUPERSAMPLE = 4
WALL_SHADE = 0.55  # a wall turned from the light
NOISE_SIGMA = 1.5  # grey levels, each eye
RIGHT_GAIN, RIGHT_OFFSET = 1.03, 2.0


@dataclass(frozen=True)
class Look:
    """How a scene is lit and seen, its geometry and its draws the same: ``wall_shade`` a wall's grey level over
    the plate's where the ray meets it (below 1 turned from the light, above 1 lit), ``noise_sigma`` each eye's
    sensor noise (grey levels), ``right_gain`` and ``right_offset`` the right eye's exposure against the left's,
    ``texel_mm`` the texture's finest detail on the plate (a pixel spans 1-2 mm), ``vignetting`` how much darker
    each eye sees the frame's corners than its centre (falling off with the square of the distance from the
    principal point). The defaults are the evaluation sets' own."""

    wall_shade: float = WALL_SHADE
    noise_sigma: float = NOISE_SIGMA
    right_gain: float = RIGHT_GAIN
    right_offset: float = RIGHT_OFFSET
    texel_mm: float = TEXEL_MM
    vignetting: float = 0.0

    def words(self) -> str:
        """What differs from the defaults, as ``inspect sim raycast``'s options say it ("" for none)."""
        plain = Look()
        parts = [f"wall shade {self.wall_shade:g}" if self.wall_shade != plain.wall_shade else "",
                 f"noise {self.noise_sigma:g}" if self.noise_sigma != plain.noise_sigma else "",
                 f"right eye's exposure {self.right_gain:g} x + {self.right_offset:g}"
                 if (self.right_gain, self.right_offset) != (plain.right_gain, plain.right_offset) else "",
                 f"texel {self.texel_mm:g} mm" if self.texel_mm != plain.texel_mm else "",
                 f"vignetting {self.vignetting:g}" if self.vignetting else ""]
        return ", ".join(p for p in parts if p)

    def vignette(self) -> np.ndarray:
        """HxW float32: each pixel's share of the light an eye sees at its principal point."""
        v, u = np.mgrid[0:CALIB["height"], 0:CALIB["width"]].astype(np.float32)
        r2 = (u - CALIB["cx"]) ** 2 + (v - CALIB["cy"]) ** 2
        return (1.0 - self.vignetting * r2 / r2.max()).astype(np.float32)


@dataclass(frozen=True)
class Kind:
    distance_mm: tuple[float, float]
    width_px: tuple[float, float]
    contrast: float
    scales: tuple[tuple[float, float], ...]  # (blur in texels, weight) of each noise layer
    streaks: float  # weight of the rolling marks' directional layer


KINDS = {
    "textured": Kind((350.0, 650.0), (30.0, 80.0), 1.0, ((1.0, 1.0), (3.0, 0.7), (10.0, 0.5)), 0.6),
    "low": Kind((380.0, 460.0), (10.0, 25.0), 0.35, ((1.5, 0.25), (25.0, 1.0)), 0.0),
}


@dataclass(frozen=True)
class Pit:
    s: float  # centre on the plate (mm, along its in-plane axes)
    t: float
    a: float  # half-sizes (mm)
    b: float
    depth: float  # along the plate's normal, away from the camera (mm)
    round: bool

    def holds(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        if self.round:
            return ((s - self.s) / self.a) ** 2 + ((t - self.t) / self.b) ** 2 < 1.0
        return (np.abs(s - self.s) < self.a) & (np.abs(t - self.t) < self.b)


MAX_TEXELS = 17_000  # a side of the plate's texture: each of its float32 layers then takes up to 1.2 GB


def texture_texels(z0: float, texel_mm: float = TEXEL_MM) -> int:
    """The side, in texels, of the texture ``render_sequence`` tabulates for a plate ``z0`` mm away."""
    return int(_plate_mm(z0) / texel_mm)


def _plate_mm(z0: float) -> float:
    # the plate the view holds, tilted by up to 8° (its far side a seventh farther), with room to spare
    return 1.3 * z0 * CALIB["width"] / CALIB["focal_px"]


def plate_texture(rng: np.random.Generator, size_mm: float, kind: Kind, texel_mm: float = TEXEL_MM) -> np.ndarray:
    """A square of the plate's grey level, ``size_mm`` a side, ``texel_mm`` a texel."""
    n = int(size_mm / texel_mm)
    tex = np.zeros((n, n), np.float32)
    for blur, weight in kind.scales:
        layer = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), blur)
        tex += weight * layer / layer.std()
    if kind.streaks:
        layer = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), sigmaX=12.0, sigmaY=0.8)
        tex += kind.streaks * layer / layer.std()
    return 120.0 + kind.contrast * 28.0 * tex / tex.std()


def rotation(tilt_deg: float, yaw_deg: float) -> np.ndarray:
    """Columns: the plate's in-plane axes and its normal, in camera coordinates."""
    tx, ty = np.radians(tilt_deg), np.radians(yaw_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(tx), -np.sin(tx)], [0, np.sin(tx), np.cos(tx)]])
    ry = np.array([[np.cos(ty), 0, np.sin(ty)], [0, 1, 0], [-np.sin(ty), 0, np.cos(ty)]])
    return ry @ rx


def _rays(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(H, W, 3) directions of the rays through the columns ``xs`` and rows ``ys`` (pixel centres at whole
    numbers), their third component 1."""
    x, y = np.meshgrid(xs, ys)
    f = CALIB["focal_px"]
    return np.stack([(x - CALIB["cx"]) / f, (y - CALIB["cy"]) / f, np.ones_like(x)], -1)


def _landing(rays: np.ndarray, eye: np.ndarray, z0: float, axes: np.ndarray, depth: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where ``rays`` from ``eye`` meet the plane ``depth`` mm below the plate (through (0, 0, z0), ``axes`` as
    ``rotation``): (s, t) along the plate's axes, and each ray's parameter there."""
    p0 = np.array([0.0, 0.0, z0])
    e1, e2, n = axes[:, 0], axes[:, 1], axes[:, 2]
    k = ((p0 + depth * n - eye) @ n) / (rays @ n)
    rel = eye + k[..., None] * rays - p0
    return rel @ e1, rel @ e2, k


def render_eye(eye_x: float, z0: float, axes: np.ndarray, pits: list[Pit], texture: np.ndarray,
               supersample: int = SUPERSAMPLE, texel_mm: float = TEXEL_MM, wall_shade: float = WALL_SHADE
               ) -> np.ndarray:
    """HxW float32 grey image of the plate (through (0, 0, z0), ``axes`` as ``rotation``; ``texture`` tabulated
    ``texel_mm`` a texel) seen by a rectified eye at (eye_x, 0, 0) mm, a wall ``wall_shade`` of the plate's grey."""
    w, h = CALIB["width"], CALIB["height"]
    rays = _rays((np.arange(w * supersample) + 0.5) / supersample - 0.5,
                 (np.arange(h * supersample) + 0.5) / supersample - 0.5)
    eye = np.array([eye_x, 0.0, 0.0])
    origin = -texture.shape[0] * texel_mm / 2

    def landing(depth: float) -> tuple[np.ndarray, np.ndarray]:
        return _landing(rays, eye, z0, axes, depth)[:2]

    def grey(s: np.ndarray, t: np.ndarray) -> np.ndarray:
        return cv2.remap(texture, ((s - origin) / texel_mm).astype(np.float32),
                         ((t - origin) / texel_mm).astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)

    s, t = landing(0.0)
    image = grey(s, t)
    for pit in pits:
        mouth = pit.holds(s, t)
        sf, tf = landing(pit.depth)
        floor = mouth & pit.holds(sf, tf)
        image = np.where(floor, grey(sf, tf), image)
        # a ray through the mouth that misses the floor meets a wall on its way down
        image = np.where(mouth & ~floor, wall_shade * grey(0.5 * (s + sf), 0.5 * (t + tf)), image)
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)


def true_disparity(z0: float, axes: np.ndarray, pits: list[Pit]) -> np.ndarray:
    """HxW float32: the disparity where the left eye's ray through each pixel's centre meets the plate (through
    (0, 0, z0), ``axes`` as ``rotation``) or a pit's floor; NaN where it meets a wall, whose depth varies across the
    pixel."""
    rays = _rays(np.arange(CALIB["width"], dtype=np.float64), np.arange(CALIB["height"], dtype=np.float64))
    eye = np.zeros(3)
    # from the left eye, a ray's parameter where it lands is the hit's z: the rays' third component is 1
    s, t, z = _landing(rays, eye, z0, axes, 0.0)
    for pit in pits:
        mouth = pit.holds(s, t)
        sf, tf, zf = _landing(rays, eye, z0, axes, pit.depth)
        floor = mouth & pit.holds(sf, tf)
        z = np.where(floor, zf, np.where(mouth, np.nan, z))
    return (CALIB["focal_px"] * CALIB["baseline_mm"] / z).astype(np.float32)


def plan_pits(rng: np.random.Generator, z0: float, axes: np.ndarray, kind: Kind) -> tuple[list[Pit], list[dict]]:
    """2-4 pits that do not crowd each other, wholly in the right eye's view, and their labels."""
    c = CALIB
    f = c["focal_px"]
    e1, e2, n = axes[:, 0], axes[:, 1], axes[:, 2]
    p0 = np.array([0.0, 0.0, z0])
    margin = f * c["baseline_mm"] / (z0 * 0.8) + 30  # the right eye sees columns beyond the disparity
    pits, labels, boxes = [], [], []
    for _ in range(rng.integers(2, 5)):
        for _try in range(30):
            wpx = rng.uniform(*kind.width_px)
            hpx = wpx * rng.uniform(0.7, 1.4)
            u = rng.uniform(margin + wpx / 2, c["width"] - 30 - wpx / 2)
            v = rng.uniform(30 + hpx / 2, c["height"] - 30 - hpx / 2)
            box = (u - wpx / 2, v - hpx / 2, u + wpx / 2, v + hpx / 2)
            if all(box[2] + 30 < q[0] or q[2] + 30 < box[0] or box[3] + 30 < q[1] or q[3] + 30 < box[1]
                   for q in boxes):
                break
        else:
            continue
        ray = np.array([(u - c["cx"]) / f, (v - c["cy"]) / f, 1.0])
        hit = (p0 @ n) / (ray @ n) * ray
        scale = hit[2] / f  # mm a pixel there
        pit = Pit(float((hit - p0) @ e1), float((hit - p0) @ e2), wpx / 2 * scale, hpx / 2 * scale,
                  float(rng.uniform(0.3, 2.6)), bool(rng.random() < 0.4))
        corners = np.array([p0 + (pit.s + i * pit.a) * e1 + (pit.t + j * pit.b) * e2
                            for i in (-1, 1) for j in (-1, 1)])
        us, vs = f * corners[:, 0] / corners[:, 2] + c["cx"], f * corners[:, 1] / corners[:, 2] + c["cy"]
        # us, vs count pixel centres from 0 (``render_eye``'s rays); a box counts pixel edges, pixel u spanning
        # u to u + 1 (``Detection``, ``core.depth.region_weights``), half a pixel further on
        us, vs = us + 0.5, vs + 0.5
        box = [float(np.floor(us.min())), float(np.floor(vs.min())), float(np.ceil(us.max())), float(np.ceil(vs.max()))]
        # the floor's depth where the box's centre looks, as the engine measures a defect's distance (at its
        # region's centre; sim/generate.py's truth is the engine's own definition): a box rounded to whole pixels
        # around a rectangle seen in perspective is centred up to a pixel or two off the floor's own centre,
        # 0.1-0.3 mm of distance on a plate tilted by 8 degrees
        centre = np.array([((box[0] + box[2]) / 2 - 0.5 - c["cx"]) / f, ((box[1] + box[3]) / 2 - 0.5 - c["cy"]) / f, 1.0])
        floor_z = float(((p0 + pit.depth * n) @ n) / (centre @ n))
        pits.append(pit)
        boxes.append(box)
        labels.append({"class": "pitted_surface", "box": box, "distance_mm": round(floor_z, 3),
                       "deviation_mm": round(pit.depth, 3), "shape": "round" if pit.round else "rectangle",
                       "source": "raycast"})
    return pits, labels


def render_sequence(out: Path, kind: str = "textured", frames: int = 8, seed: int = 0,
                    supersample: int = SUPERSAMPLE, image_format: str = "png", look: Look = Look(),
                    distance_mm: tuple[float, float] | None = None) -> None:
    """``frames`` plates of ``kind``, drawn from ``seed``, lit and seen as ``look`` says, at the kind's distances or
    ``distance_mm`` (near, far), written to ``out`` (the module docstring)."""
    spec = KINDS[kind] if distance_mm is None else replace(KINDS[kind], distance_mm=tuple(distance_mm))
    rng = np.random.default_rng(seed)
    out = Path(out)
    saved = f", JPEG quality {JPEG_QUALITY}" if image_format == "jpg" else ""
    words = look.words()
    seen = f", {words}" if words else ""
    at = f", {spec.distance_mm[0]:g}-{spec.distance_mm[1]:g} mm" if distance_mm is not None else ""
    write_calibration(out, dict(CALIB, camera="ZED WVGA (ray cast)",
                                generator=f"sim.raycast {kind} (seed {seed}{saved}{at}{seen})"))
    vignette = look.vignette() if look.vignetting else None
    for i in range(frames):
        z0 = float(rng.uniform(*spec.distance_mm))
        axes = rotation(rng.uniform(-8, 8), rng.uniform(-8, 8))
        texture = plate_texture(rng, _plate_mm(z0), spec, look.texel_mm)
        pits, labels = plan_pits(rng, z0, axes, spec)
        eyes = [render_eye(x, z0, axes, pits, texture, supersample, look.texel_mm, look.wall_shade)
                for x in (0.0, CALIB["baseline_mm"])]
        if vignette is not None:
            eyes = [eye * vignette for eye in eyes]
        left, right = eyes[0], look.right_gain * eyes[1] + look.right_offset
        eyes = [np.clip(np.round(img + rng.normal(0, look.noise_sigma, img.shape)), 0, 255).astype(np.uint8)
                for img in (left, right)]
        frame_id = f"{i:06d}"
        write_frame(out, frame_id, *(cv2.cvtColor(e, cv2.COLOR_GRAY2BGR) for e in eyes),
                    gt_disparity=true_disparity(z0, axes, pits),
                    labels={"frame_id": frame_id, "distance_mm": round(z0, 3),
                            "sensor": {"noise_sigma": look.noise_sigma}, "defects": labels},
                    image_format=image_format)
