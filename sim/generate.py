"""Synthetic stereo sequences with exact ground truth, in the sequence-folder format.

``generate_sequence(out, frames=10, seed=0, ...)`` writes ``calib.yaml``, ``left/``,
``right/``, ``gt/`` (exact left disparity, KITTI uint16) and ``labels/<id>.json``. Everything
is drawn from one ``np.random.default_rng(seed)`` frame after frame, so the first k frames of
a longer run equal a k-frame run with the same seed and options.

Ground-truth ``distance_mm``/``deviation_mm`` per defect are ``core.depth.measure_defect`` on the
GT disparity as stored (quantised to 1/256 px) with the default ``DepthRule``, i.e. the
platform's own definitions; ``design_depth_mm`` is the shape's true plateau depth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from core.depth import DepthRule, measure_defect
from core.types import Calibration, Detection
from drivers.sequence_folder import KITTI_MAX_DISPARITY, write_calibration, write_frame
from sim.neu_crops import NEU_CLASSES, NeuCrops
from sim.render import render_pair
from sim.scene import (
    CLASS_SHAPES, PLATEAU_R0, ROUND_EXPONENT, Defect, Lighting, Scene, Sensor, flat_hit, heightfield_patch, local_coords,
    plate_axes, plate_coords, turned_extent,
)
from sim.texture import PLATE_MEAN, belt_albedo, steel_albedo, synthetic_defect_patch

ZED_WVGA = dict(width=672, height=376, focal_px=350.06, baseline_mm=120.0)
# per frame (cyclic): no defect / shallow defects (pass at a 1.0 mm deviation threshold) /
# one deep defect (reject) / a shallow and a deep one
FRAME_PLAN = ("none", "shallow", "deep", "mixed", "shallow", "none", "deep", "shallow", "mixed", "deep")
SHALLOW_MM = (0.25, 0.7)
DEEP_MM = (1.8, 3.0)
BELOW_CLASSES = tuple(c for c in NEU_CLASSES if not CLASS_SHAPES[c][2])
DEFECT_SCALE = (0.6, 1.2)  # NEU px -> WVGA frame px
MAX_SIDE_PX, MIN_SIDE_PX = 150.0, 18.0  # at WVGA
EDGE_MARGIN_PX = 24.0  # box to image border: room for the ring the deviation is fitted on
GAP_PX = 24.0  # between defects
DISTANCE_JITTER_MM = (-20.0, 50.0)  # added to --distance-mm per frame
RAISED_CLASSES = tuple(c for c in NEU_CLASSES if CLASS_SHAPES[c][2])


@dataclass(frozen=True)
class EvalRanges:
    """What an evaluation set varies, each drawn uniformly per frame or per defect. ``None`` keeps the
    demo plan's draw for that quantity (``FRAME_PLAN``, sizes from the appearance, jittered distance).

    With ``depth_mm`` every frame carries ``defects_per_frame`` defects of a depth in that range (signed:
    + below the surface, - raised; a range across zero draws both), so the set concentrates where the
    decision is hard instead of on the plan's sound and clear-cut plates."""

    distance_mm: tuple[float, float] | None = None
    defect_px: tuple[float, float] | None = None  # each side of the box, in frame pixels
    depth_mm: tuple[float, float] | None = None
    defects_per_frame: tuple[int, int] = (1, 3)
    flat_floor: tuple[float, float] | None = None  # each defect's plateau (sim.scene), None: PLATEAU_R0
    round_defects: bool = False  # every defect an ellipse, its wall as steep all round, not its class's superellipse
    aspect: tuple[float, float] | None = None  # each defect's length over its width; its length from ``defect_px``
    angle_deg: tuple[float, float] | None = None  # each defect's outline turned on the plate by this much

    @property
    def plans_defects(self) -> bool:
        return self.depth_mm is not None


@dataclass(frozen=True)
class CameraModel:
    """What the camera does to the light that the defaults draw or leave out. ``noise_sigma``: the grey
    levels of Gaussian noise added to each eye (None: drawn per frame, 1.5-2; 0: none but the 8-bit
    rounding); ``specular``: the point light's highlight and sheen on the steel (False: a matte plate);
    ``lens_blur_px``: the optics' Gaussian blur before the pixels integrate the light (0: the pixels alone);
    ``rectification_error_px``: the right eye's rows that far below the left's (0: exactly rectified);
    ``motion_blur_px``: how far the plate moves across the image during the exposure (0: it stands still), towards
    ``motion_angle_deg`` (0: along the rows, the baseline; 90: down the image)."""

    noise_sigma: float | None = None
    specular: bool = True
    lens_blur_px: float = 0.0
    rectification_error_px: float = 0.0
    motion_blur_px: float = 0.0
    motion_angle_deg: float = 90.0


def zed_calibration(width: int = 672, height: int = 376, baseline_mm: float = ZED_WVGA["baseline_mm"]) -> Calibration:
    """The ZED WVGA pair, scaled to ``width`` (focal length scales with the width); ``baseline_mm``: another
    camera's eyes that far apart (a ZED Mini's 63 mm)."""
    f = ZED_WVGA["focal_px"] * width / ZED_WVGA["width"]
    return Calibration(f, baseline_mm, (width - 1) / 2.0, (height - 1) / 2.0, width, height, 0.0)


class _Deck:
    """Classes drawn without replacement, reshuffled when empty: every class shows up."""

    def __init__(self, items, rng):
        self.items, self.rng, self.stack = list(items), rng, []

    def draw(self) -> str:
        if not self.stack:
            self.stack = [self.items[i] for i in self.rng.permutation(len(self.items))]
        return self.stack.pop()


@dataclass
class FrameSpec:
    distance_mm: float
    tilt_deg: float
    yaw_deg: float
    requests: list[tuple[str, float]]  # (class, signed design depth)
    sizes_px: list[tuple[float, float]] | None = None  # (width, height) of each request's box, or from its appearance
    angles_deg: list[float] | None = None  # each request's outline turned on the plate (sizes along its own sides)


def plan_frame(rng, index: int, distance_mm: float, tilt_deg: float, jitter: bool, decks,
               ranges: EvalRanges = EvalRanges()) -> FrameSpec:
    all_deck, deep_deck = decks[:2]
    if ranges.distance_mm is not None:
        distance = rng.uniform(*ranges.distance_mm)
    elif jitter:
        distance = distance_mm + rng.uniform(*DISTANCE_JITTER_MM)
    else:
        distance = distance_mm
    tilt, yaw = _jittered_pose(rng, tilt_deg) if jitter else (tilt_deg, 0.0)
    if ranges.plans_defects:
        return _planned_defects(rng, float(distance), float(tilt), float(yaw), decks, ranges)
    kind = FRAME_PLAN[index % len(FRAME_PLAN)]
    reqs: list[tuple[str, float]] = []

    def shallow():
        cls = all_deck.draw()
        depth = rng.uniform(*SHALLOW_MM)
        reqs.append((cls, -depth if CLASS_SHAPES[cls][2] else depth))

    def deep():
        reqs.append((deep_deck.draw(), rng.uniform(*DEEP_MM)))

    if kind == "shallow":
        for _ in range(int(rng.integers(1, 3))):
            shallow()
    elif kind == "deep":
        deep()
    elif kind == "mixed":
        shallow()
        deep()
    return FrameSpec(float(distance), float(tilt), float(yaw), reqs, *_outlines(rng, ranges, len(reqs)))


def _jittered_pose(rng, tilt_deg: float) -> tuple[float, float]:
    tilt = tilt_deg + rng.uniform(-5.0, 3.0)
    if tilt_deg >= 0:  # 0..8 deg around the default 5; the sign of the tilt is kept
        tilt = max(tilt, 0.0)
    return tilt, rng.uniform(-2.0, 2.0)


def _outlines(rng, ranges: EvalRanges, count: int) -> tuple[list[tuple[float, float]] | None, list[float] | None]:
    """Each defect's (length, width) in frame pixels (None: from its appearance) and its angle on the plate
    (None: 0). Only the options given draw, so that a seed renders the same plates as before them."""
    sizes = None
    if ranges.defect_px is not None:
        sizes = [(float(rng.uniform(*ranges.defect_px)), float(rng.uniform(*ranges.defect_px))) for _ in range(count)]
        if ranges.aspect is not None:
            sizes = [(length, length / float(rng.uniform(*ranges.aspect))) for length, _ in sizes]
    angles = None if ranges.angle_deg is None else [float(rng.uniform(*ranges.angle_deg)) for _ in range(count)]
    return sizes, angles


def _planned_defects(rng, distance: float, tilt: float, yaw: float, decks, ranges: EvalRanges) -> FrameSpec:
    """An evaluation frame: ``defects_per_frame`` defects, each of a depth drawn from ``depth_mm``."""
    below, raised = decks[1], decks[2]
    reqs = []
    for _ in range(int(rng.integers(ranges.defects_per_frame[0], ranges.defects_per_frame[1] + 1))):
        depth = float(rng.uniform(*ranges.depth_mm))
        reqs.append(((raised if depth < 0 else below).draw(), depth))
    return FrameSpec(distance, tilt, yaw, reqs, *_outlines(rng, ranges, len(reqs)))


def _appearance(rng, cls: str, crops: NeuCrops | None, scale_px: float):
    """(patch, box in patch, source, frame px per patch px)."""
    max_side, min_side = MAX_SIDE_PX * scale_px, max(MIN_SIDE_PX * scale_px, 8.0)
    if crops is not None:
        box = crops.pick(rng, cls)
        patch, pbox = crops.patch(box)
        k = rng.uniform(*DEFECT_SCALE) * scale_px
        bw, bh = box.width, box.height
        if min(bw, bh) * k < min_side:
            k = min_side / min(bw, bh)
        if max(bw, bh) * k > max_side:  # the size limit wins over the minimum for slivers
            k = max_side / max(bw, bh)
        return patch, pbox, box.stem, k
    long_side = rng.uniform(40.0, 130.0) * scale_px
    aspect = rng.uniform(3.0, 5.0) if cls == "scratches" else rng.uniform(1.0, 2.0)
    w, h = long_side, max(long_side / aspect, min_side)
    if rng.random() < 0.5:
        w, h = h, w
    # stand-in patches are drawn at 2x the frame size
    patch, pbox = synthetic_defect_patch(rng, cls, round(2 * w), round(2 * h))
    return patch, pbox, "synthetic", 0.5  # stand-in patches are drawn at 2x the frame size


PLACEMENT_SLACK = 1.15  # perspective: a defect's projected box differs a little from the estimate it is placed by


def ring_margin_px(width: int) -> float:
    """Pixels kept between a defect's box and the frame's border: room for the ring that ``measure_defect``
    fits the surface on (3 + 12 px, not scaled)."""
    return max(EDGE_MARGIN_PX * width / ZED_WVGA["width"], 16.0)


def largest_defect_px(width: int, height: int) -> float:
    """The side a defect's box must stay below to be placed in a width x height frame, either way round."""
    return (min(width, height) - 2 * ring_margin_px(width)) / PLACEMENT_SLACK


def build_scene(rng, calib: Calibration, spec: FrameSpec, crops: NeuCrops | None, texture_contrast: float = 1.0,
                flat_floor: tuple[float, float] | None = None, camera: CameraModel = CameraModel(),
                round_defects: bool = False, grain_angle_deg: float = 0.0) -> Scene:
    z0 = spec.distance_mm
    e1, e2, n = plate_axes(spec.tilt_deg, spec.yaw_deg)
    p0 = np.array([0.0, 0.0, z0])
    axes = (e1, e2, n, p0)
    texel = z0 / calib.focal_px / 2.2  # ~2.2 texels per pixel
    belt_offset = float(rng.uniform(25.0, 40.0))
    # texture grid: everything either eye can see of the plate or the belt
    cu = np.array([-0.5, calib.width - 0.5, -0.5, calib.width - 0.5])
    cv = np.array([-0.5, -0.5, calib.height - 0.5, calib.height - 0.5])
    ss, ts = [], []
    for origin in (np.zeros(3), np.array([calib.baseline_mm, 0, 0])):
        for off in (-5.0, belt_offset):
            _, s, t = flat_hit(calib, axes, origin, cu, cv, off)
            ss += list(s)
            ts += list(t)
    pad = 6 * texel
    s0, s1, t0, t1 = min(ss) - pad, max(ss) + pad, min(ts) - pad, max(ts) + pad
    shape = (int(np.ceil((t1 - t0) / texel)) + 1, int(np.ceil((s1 - s0) / texel)) + 1)
    albedo = steel_albedo(rng, shape, texel, texture_contrast, grain_angle_deg)
    belt = belt_albedo(rng, shape, texel)
    height = np.zeros(shape, np.float32)

    half_fov = (calib.width / 2.0) / calib.focal_px * z0
    if rng.random() < 0.25:
        s_range = None
    else:
        s_range = (-half_fov * rng.uniform(0.72, 0.95), half_fov * rng.uniform(0.72, 0.95))
    # point light placed so that the left eye sees the mirror highlight on the flat plate at a
    # random spot; the right eye, 120 mm away, sees it elsewhere on the surface
    hu, hv = rng.uniform(0.12, 0.88) * calib.width, rng.uniform(0.1, 0.9) * calib.height
    hz, hs, ht = flat_hit(calib, axes, np.zeros(3), np.array([hu]), np.array([hv]))
    p_h = p0 + float(hs[0]) * e1 + float(ht[0]) * e2
    view = -p_h / np.linalg.norm(p_h)
    m = -n
    refl = 2 * float(m @ view) * m - view
    # every value is drawn whatever ``camera`` overrides, so that a seed renders the same plates either way
    lighting = Lighting(
        light_pos=p_h + refl * rng.uniform(350.0, 650.0),
        spec_broad=float(rng.uniform(25.0, 45.0)),
        spec_core=float(rng.uniform(35.0, 75.0)),
    )
    if not camera.specular:
        lighting.spec_broad = lighting.spec_core = 0.0
    sensor = Sensor(
        noise_sigma=float(rng.uniform(1.5, 2.0)),
        right_gain=float(rng.uniform(1.03, 1.08)),
        right_offset=float(rng.uniform(1.0, 5.0)),
        vignetting=float(rng.uniform(0.05, 0.12)),
        lens_blur_px=camera.lens_blur_px,
        motion_blur_px=camera.motion_blur_px,
        motion_angle_deg=camera.motion_angle_deg,
    )
    if camera.noise_sigma is not None:
        sensor.noise_sigma = camera.noise_sigma

    scale_px = calib.width / ZED_WVGA["width"]
    mm_per_px = z0 / calib.focal_px
    placed: list[Defect] = []
    for i, (cls, depth) in enumerate(spec.requests):
        patch, pbox, source, k = _appearance(rng, cls, crops, scale_px)
        bw, bh = (pbox[2] - pbox[0]) * k, (pbox[3] - pbox[1]) * k  # frame px
        if spec.sizes_px is not None:  # the appearance is stretched over the footprint (_paste)
            bw, bh = spec.sizes_px[i]
        a, b = bw / 2 * mm_per_px, bh / 2 * mm_per_px / np.cos(np.radians(spec.tilt_deg))
        angle = 0.0 if spec.angles_deg is None else spec.angles_deg[i]
        ea, eb = turned_extent((float(a), float(b)), angle)  # what the turned outline covers along s and t
        if angle:  # the box it makes in the frame
            bw, bh = 2 * ea / mm_per_px, 2 * eb * np.cos(np.radians(spec.tilt_deg)) / mm_per_px
        margin = ring_margin_px(calib.width)
        gap = max(GAP_PX * scale_px, 16.0) * mm_per_px
        slack = PLACEMENT_SLACK
        ulo, uhi = margin + slack * bw / 2, calib.width - margin - slack * bw / 2
        vlo, vhi = margin + slack * bh / 2, calib.height - margin - slack * bh / 2
        if ulo >= uhi or vlo >= vhi:
            continue
        for _ in range(200):
            u, v = rng.uniform(ulo, uhi), rng.uniform(vlo, vhi)
            _, s, t = flat_hit(calib, axes, np.zeros(3), np.array([u]), np.array([v]))
            s, t = float(s[0]), float(t[0])
            if s_range is not None and not (s_range[0] + ea + gap <= s <= s_range[1] - ea - gap):
                continue
            if any(
                abs(s - d.center[0]) < ea + d.extent[0] + gap and abs(t - d.center[1]) < eb + d.extent[1] + gap
                for d in placed
            ):
                continue
            shape_name, p, _ = CLASS_SHAPES[cls]
            p = ROUND_EXPONENT if round_defects else p
            plateau = PLATEAU_R0 if flat_floor is None else float(rng.uniform(*flat_floor))
            placed.append(Defect(cls, source, shape_name, p, float(depth), (s, t), (float(a), float(b)), patch, pbox,
                                 plateau, angle))
            break

    for d in placed:
        _paste(d, albedo, height, (s0, t0), texel)
    return Scene(calib, z0, spec.tilt_deg, spec.yaw_deg, s_range, belt_offset, texel, (s0, t0),
                 albedo, height, belt, lighting, sensor, placed)


def _paste(d: Defect, albedo: np.ndarray, height: np.ndarray, origin, texel: float) -> None:
    """Write the defect's heightfield and blend its appearance into the plate's albedo."""
    (sc, tc), (a, b) = d.center, d.half
    px0, py0, px1, py1 = d.patch_box
    mm_x, mm_y = 2 * a / (px1 - px0), 2 * b / (py1 - py0)  # mm per patch px
    ph, pw = d.patch.shape
    ps0, pt0 = sc - a - px0 * mm_x, tc - b - py0 * mm_y  # patch's top-left corner in mm
    lo_s, lo_t, hi_s, hi_t = ps0, pt0, ps0 + pw * mm_x, pt0 + ph * mm_y
    if d.angle_deg:  # the texels the turned patch covers
        ss, ts = plate_coords(d, np.array([ps0, hi_s, ps0, hi_s]) - sc, np.array([pt0, pt0, hi_t, hi_t]) - tc)
        lo_s, lo_t, hi_s, hi_t = ss.min(), ts.min(), ss.max(), ts.max()
    c0 = int(np.floor((lo_s - origin[0]) / texel))
    r0 = int(np.floor((lo_t - origin[1]) / texel))
    c1 = int(np.ceil((hi_s - origin[0]) / texel)) + 1
    r1 = int(np.ceil((hi_t - origin[1]) / texel)) + 1
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, albedo.shape[1]), min(r1, albedo.shape[0])
    cols = np.arange(c0, c1)
    rows = np.arange(r0, r1)
    S, T = np.meshgrid(origin[0] + cols * texel, origin[1] + rows * texel)
    height[r0:r1, c0:c1] += heightfield_patch(d, S, T).astype(np.float32)
    # appearance: sample the patch at each texel (bilinear), feathered towards the patch border
    if d.angle_deg:
        ls, lt = local_coords(d, S, T)
        S, T = ls + sc, lt + tc  # the texels in the patch's own axes
    mx = ((S - ps0) / mm_x - 0.5).astype(np.float32)
    my = ((T - pt0) / mm_y - 0.5).astype(np.float32)
    smooth = cv2.GaussianBlur(d.patch, (0, 0), max(0.5 * min(texel / mm_x, texel / mm_y), 0.01)) if min(mm_x, mm_y) < texel else d.patch
    vals = cv2.remap(smooth, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # feather over the context margin on each side (inside the box where the margin is clipped)
    bw, bh = px1 - px0, py1 - py0
    alpha = np.ones_like(mx)
    for dist, width in (
        (mx + 0.5, max(px0, 0.1 * bw)), (pw - 0.5 - mx, max(pw - px1, 0.1 * bw)),
        (my + 0.5, max(py0, 0.1 * bh)), (ph - 0.5 - my, max(ph - py1, 0.1 * bh)),
    ):
        alpha = np.minimum(alpha, np.clip(dist / width, 0.0, 1.0))
    alpha = alpha * alpha * (3 - 2 * alpha)
    med = float(np.median(d.patch))
    target = PLATE_MEAN + (vals - med) + 0.2 * (med - PLATE_MEAN)
    win = albedo[r0:r1, c0:c1]
    albedo[r0:r1, c0:c1] = ((1 - alpha) * win + alpha * target).astype(np.float32)


def on_footprint(d: Defect, centre_hits, h: int, w: int) -> np.ndarray:
    """HxW bool: the pixels whose centre ray hits the defect's footprint rectangle."""
    (a, b) = d.half
    s, t = local_coords(d, centre_hits.s.reshape(h, w), centre_hits.t.reshape(h, w))
    return (np.abs(s) <= a) & (np.abs(t) <= b) & centre_hits.on_plate.reshape(h, w)


def defect_box(footprint: np.ndarray) -> tuple[float, float, float, float] | None:
    """The defect's footprint rectangle as seen by the left image (``on_footprint``): the bounding box of
    its pixels."""
    rows, cols = np.nonzero(footprint)
    if rows.size == 0:
        return None
    return (float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1))


class GenerateError(Exception):
    """A frame whose truth the sequence folder cannot hold."""


def nearest_plate_mm(calib: Calibration) -> float:
    """The nearest surface whose disparity the ground truth's KITTI PNG holds, for ``calib``'s eyes."""
    return calib.focal_px * calib.baseline_mm / KITTI_MAX_DISPARITY


def quantise_disparity(disparity: np.ndarray) -> np.ndarray:
    """The disparity exactly as the KITTI uint16 PNG stores it."""
    return (np.clip(np.round(disparity.astype(np.float64) * 256.0), 0, 65535) / 256.0).astype(np.float32)


def render_frame(rng, calib: Calibration, spec: FrameSpec, crops: NeuCrops | None, frame_id: str, ss: int = 2,
                 texture_contrast: float = 1.0, flat_floor: tuple[float, float] | None = None,
                 camera: CameraModel = CameraModel(), round_defects: bool = False, grain_angle_deg: float = 0.0):
    """(left, right, gt disparity (quantised), labels dict, scene)."""
    scene = build_scene(rng, calib, spec, crops, texture_contrast, flat_floor, camera, round_defects, grain_angle_deg)
    left, right, disparity, hits = render_pair(scene, rng, ss=ss, rectification_error_px=camera.rectification_error_px)
    largest = float(np.nanmax(disparity, initial=0.0))
    if largest > KITTI_MAX_DISPARITY:  # clipped, every label near it would read the plate as farther and flat
        raise GenerateError(
            f"frame {frame_id}: the plate comes to {calib.focal_px * calib.baseline_mm / largest:.0f} mm, "
            f"{largest:.1f} px of disparity at {calib.width}x{calib.height}, beyond the {KITTI_MAX_DISPARITY:.3f} px "
            f"its ground truth's 16-bit PNG holds: plates from {nearest_plate_mm(calib):.0f} mm on, less tilt, or a "
            f"narrower frame")
    gt = quantise_disparity(disparity)
    defects = []
    for d in scene.defects:
        footprint = on_footprint(d, hits, calib.height, calib.width)
        box = defect_box(footprint)
        if box is None:
            continue
        # the truth is the deviation where the region lies on the defect: a groove turned across its box leaves
        # the surface in the rest of it (for an outline along the rows, the region lies on it whole)
        on_defect = gt.copy()
        x0, y0, x1, y1 = (int(v) for v in box)
        on_defect[y0:y1, x0:x1][~footprint[y0:y1, x0:x1]] = np.nan
        m = measure_defect(on_defect, Detection(d.class_name, 1.0, box), calib, DepthRule())
        defects.append({
            "class": d.class_name,
            "box": [round(v, 1) for v in box],
            "distance_mm": None if m.distance_mm is None else round(m.distance_mm, 3),
            "deviation_mm": None if m.deviation_mm is None else round(m.deviation_mm, 3),
            "design_depth_mm": round(d.design_depth_mm, 3),
            "shape": d.shape,
            "source": d.source,
            **({} if flat_floor is None else {"plateau": round(d.plateau, 3)}),
            **({"exponent": d.exponent} if round_defects else {}),
            **({"angle_deg": round(d.angle_deg, 2)} if d.angle_deg else {}),
        })
    labels = {
        "frame_id": frame_id,
        "distance_mm": round(spec.distance_mm, 3),
        "tilt_deg": round(spec.tilt_deg, 3),
        "yaw_deg": round(spec.yaw_deg, 3),
        "plate_fills_view": scene.plate_s_range is None,
        # what the depth evaluation's noise floor needs: the grey-level noise added to each eye
        "sensor": {"noise_sigma": round(scene.sensor.noise_sigma, 4), "right_gain": round(scene.sensor.right_gain, 4),
                   "right_offset": round(scene.sensor.right_offset, 4)},
        "texture_contrast": texture_contrast,
        **({} if not grain_angle_deg else {"grain_angle_deg": grain_angle_deg}),
        **({} if not camera.rectification_error_px else {"rectification_error_px": camera.rectification_error_px}),
        **({} if camera.specular else {"specular": False}),
        **({} if not camera.lens_blur_px else {"lens_blur_px": camera.lens_blur_px}),
        **({} if not camera.motion_blur_px else {"motion_blur_px": camera.motion_blur_px,
                                                 "motion_angle_deg": camera.motion_angle_deg}),
        "defects": defects,
    }
    return left, right, gt, labels, scene


def generate_sequence(
    out: Path,
    frames: int = 10,
    seed: int = 0,
    distance_mm: float = 400.0,
    tilt_deg: float = 5.0,
    neu_det: Path | None = None,
    width: int = 672,
    height: int = 376,
    jitter: bool = True,
    supersample: int = 2,
    image_format: str = "png",
    log=None,
    ranges: EvalRanges = EvalRanges(),
    texture_contrast: float = 1.0,
    camera: CameraModel = CameraModel(),
    captures: int = 1,
    grain_angle_deg: float = 0.0,
    baseline_mm: float = ZED_WVGA["baseline_mm"],
    capture_drift_px: float = 0.0,
) -> list[dict]:
    """Write a sequence folder; returns the labels of every frame. ``neu_det=None`` uses the
    synthetic stand-in defect appearance. ``ranges``, ``texture_contrast``, ``grain_angle_deg`` (the rolling
    direction turned from down the image towards its rows, ``sim.texture.steel_albedo``) and ``camera`` make an
    evaluation set; left at their defaults, the draws (and so the files) are those of the demo plan. ``captures``:
    each of the ``frames`` plates captured that many times in a row, the sensor's noise drawn anew each time (a
    plate standing still under the camera, as ``inspect eval repeatability`` reads it); 1 draws what it always
    did. ``baseline_mm``: the eyes that far apart (``zed_calibration``). ``capture_drift_px``: each capture's right
    eye that much further right than the one before (a camera whose calibration drifts as it warms up; the truth
    stays the scene's)."""
    out = Path(out)
    crops = NeuCrops(Path(neu_det)) if neu_det is not None else None
    calib = zed_calibration(width, height, baseline_mm)
    rng = np.random.default_rng(seed)
    decks = (_Deck(NEU_CLASSES, rng), _Deck(BELOW_CLASSES, rng), _Deck(RAISED_CLASSES, rng))
    write_calibration(out, {
        "focal_px": calib.focal_px, "baseline_mm": calib.baseline_mm, "cx": calib.cx, "cy": calib.cy,
        "width": calib.width, "height": calib.height, "doffs": 0.0,
        "camera": "ZED WVGA (synthetic)" if baseline_mm == ZED_WVGA["baseline_mm"] else
                  f"ZED WVGA's optics, {baseline_mm:g} mm baseline (synthetic)",
        "generator": f"inspect sim generate (seed {seed})",
    })
    all_labels = []
    for i in range(frames):
        t_start = time.perf_counter()
        frame_id = f"{i * captures:06d}"
        spec = plan_frame(rng, i, distance_mm, tilt_deg, jitter, decks, ranges)
        left, right, gt, labels, scene = render_frame(rng, calib, spec, crops, frame_id, ss=supersample,
                                                      texture_contrast=texture_contrast, flat_floor=ranges.flat_floor,
                                                      camera=camera, round_defects=ranges.round_defects,
                                                      grain_angle_deg=grain_angle_deg)
        for k in range(captures):
            if k:  # the same light again, another draw of the sensor's noise
                frame_id = f"{i * captures + k:06d}"
                left, right = render_pair(scene, rng, ss=supersample,
                                          rectification_error_px=camera.rectification_error_px,
                                          right_columns_px=k * capture_drift_px)[:2]
            captured = labels if captures == 1 else {**labels, "frame_id": frame_id, "plate": i,
                                                     **({"right_columns_px": round(k * capture_drift_px, 6)}
                                                        if capture_drift_px else {})}
            write_frame(out, frame_id, left, right, gt, captured, image_format)
            all_labels.append(captured)
        if log is not None:
            summary = ", ".join(
                f"{d['class']} " + ("n/a" if d["deviation_mm"] is None else f"{d['deviation_mm']:+.2f} mm")
                for d in labels["defects"]) or "no defect"
            shots = f", {captures} captures" if captures > 1 else ""
            log(f"{labels['frame_id']}: Z={labels['distance_mm']:.0f} mm tilt={labels['tilt_deg']:.1f} deg: {summary}"
                f"{shots} ({time.perf_counter() - t_start:.1f} s)")
    return all_labels
