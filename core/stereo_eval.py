"""Scoring disparity maps against Middlebury ground truth, and running a backend over a scene folder.

Two scores per scene, both over non-occluded pixels with finite ground truth (mask0nocc == 255):
- dense: every such pixel counts; a missing (NaN/inf) prediction is a bad pixel, as in
  Middlebury's SDK. Its average error counts a missing prediction as disparity 0.
- sparse: only the pixels the backend claims (finite output, or its own validity mask when it has
  ``compute_with_mask``, e.g. torch_sgm's left-right check); ``coverage`` is their share.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from drivers.file_writes import write_text
from drivers.sequence_folder import SequenceError, read_image, read_middlebury_calib, read_pfm

THRESHOLDS = (0.5, 1.0, 2.0, 4.0)


@dataclass
class SceneScore:
    scene: str
    backend: str
    dense: dict[str, float]  # bad-0.5 ... bad-4.0 (%), avgerr
    sparse: dict[str, float]
    coverage: float  # % of scored pixels in the sparse result
    invalid: float  # % of scored pixels with no prediction in the output
    runtime_s: float
    pixels: int = 0
    extra: dict = field(default_factory=dict)
    note: str = ""  # the scene's ``SceneData.note``


def _bad(err: np.ndarray) -> dict[str, float]:
    if err.size == 0:
        return {**{f"bad{t}": float("nan") for t in THRESHOLDS}, "avgerr": float("nan")}
    out = {f"bad{t}": float(100.0 * np.mean(~(err <= t))) for t in THRESHOLDS}
    out["avgerr"] = float(np.mean(err))
    return out


def score(pred: np.ndarray, gt: np.ndarray, nonocc: np.ndarray, claimed: np.ndarray | None = None) -> dict:
    """pred, gt: HxW float (NaN/inf = none); nonocc: HxW bool. ``claimed`` defaults to finite pred."""
    if pred.shape != gt.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} differ in size")
    scored = nonocc & np.isfinite(gt)
    have = np.isfinite(pred)
    claimed = have if claimed is None else (claimed & have)
    with np.errstate(invalid="ignore"):
        diff = np.abs(np.where(have, pred, 0.0) - gt)  # a missing prediction reads as disparity 0
    dense = _bad(np.where(have, diff, np.inf)[scored])
    dense["avgerr"] = float(np.mean(diff[scored])) if scored.any() else float("nan")
    sparse = _bad(diff[scored & claimed])
    n = int(scored.sum())
    return {
        "dense": dense,
        "sparse": sparse,
        "coverage": float(100.0 * (scored & claimed).sum() / max(n, 1)),
        "invalid": float(100.0 * (scored & ~have).sum() / max(n, 1)),
        "pixels": n,
    }


def _is_scene(folder: Path) -> bool:
    return folder.is_dir() and (folder / "im0.png").exists() and (folder / "calib.txt").exists()


def list_scenes(folder: Path, only: list[str] | None = None) -> list[Path]:
    """The scene folders (im0.png and calib.txt) inside ``folder``, or ``folder`` itself where it is one;
    ``only`` picks them by name (ValueError naming those not there)."""
    folder = Path(folder)
    scenes = [folder] if _is_scene(folder) else sorted(p for p in folder.iterdir() if _is_scene(p))
    if only:
        by_name = {p.name: p for p in scenes}
        missing = [s for s in only if s not in by_name]
        if missing:
            raise ValueError(f"scenes not found in {folder}: {', '.join(missing)}")
        scenes = [by_name[s] for s in only]
    return scenes


@dataclass
class SceneData:
    name: str
    left: np.ndarray
    right: np.ndarray
    gt: np.ndarray
    nonocc: np.ndarray
    ndisp: int
    note: str = ""  # what the score of this scene counts differently, said beside it


GROUND_TRUTH = ("disp0GT.pfm", "disp0.pfm")  # MiddEval3's name (ETH3D's too), the Middlebury 2014 datasets'


def ground_truth_path(folder: Path) -> Path | None:
    """The scene's left disparity ground truth under either name, or None."""
    return next((folder / name for name in GROUND_TRUTH if (folder / name).is_file()), None)


def load_scene(folder: Path) -> SceneData:
    folder = Path(folder)
    calib = read_middlebury_calib(folder / "calib.txt")
    gt_path = ground_truth_path(folder) or folder / GROUND_TRUTH[0]
    gt = read_pfm(gt_path)
    if gt.ndim != 2:  # its size then read as the image's, but not its shape: "741x497, but im0.png is 741x497"
        raise SequenceError(f"{gt_path}: a colour PFM (PF, 3 channels): a disparity map is a grey one (Pf)")
    mask_path = folder / "mask0nocc.png"
    note = ""
    if mask_path.exists():
        nonocc = read_image(mask_path, "occlusion mask")[..., 0] == 255
    else:  # a scene published without one: every pixel with ground truth is scored, and the line says so
        nonocc, note = np.ones(gt.shape, bool), "no mask0nocc.png: occluded pixels scored too"
    left, right = read_image(folder / "im0.png", "left image"), read_image(folder / "im1.png", "right image")
    for name, shape in (("im1.png", right.shape[:2]), (gt_path.name, gt.shape), ("mask0nocc.png", nonocc.shape)):
        if shape != left.shape[:2]:
            raise SequenceError(f"{folder / name}: {shape[1]}x{shape[0]}, but im0.png is {left.shape[1]}x{left.shape[0]}")
    known = gt[np.isfinite(gt)]
    if not (np.isfinite(gt) & nonocc).any():
        # scored against nothing, every figure of the scene and of the average came out NaN
        raise SequenceError(f"{gt_path}: no pixel has a known disparity" + (" where mask0nocc.png marks it visible"
                            if known.size else "") + ": nothing to score the scene on")
    if known.min() < 0 or not 0.5 <= known.max() < gt.shape[1]:
        # what a PFM read in the wrong byte order, or another scene's, gives: every score would be nonsense
        raise SequenceError(f"{gt_path}: disparities from {known.min():.4g} to {known.max():.4g} px, not "
                            f"within the image's 0-{gt.shape[1]} or all under half a pixel: not this scene's disparity "
                            f"map (or its scale's sign gives the wrong byte order)")
    return SceneData(folder.name, left, right, gt, nonocc, calib["ndisp"], note)


def run_backend(backend, scene: SceneData) -> tuple[np.ndarray, np.ndarray | None, float]:
    """(disparity, claimed mask or None, seconds)."""
    start = time.perf_counter()
    if hasattr(backend, "compute_with_mask"):
        disp, claimed = backend.compute_with_mask(scene.left, scene.right, 0, scene.ndisp)
    else:
        disp, claimed = backend.compute(scene.left, scene.right, 0, scene.ndisp), None
    return np.asarray(disp, np.float32), claimed, time.perf_counter() - start


def evaluate_scene(backend, name: str, scene: SceneData) -> tuple[SceneScore, np.ndarray]:
    disp, claimed, seconds = run_backend(backend, scene)
    s = score(disp, scene.gt, scene.nonocc, claimed)
    return SceneScore(scene.name, name, s["dense"], s["sparse"], s["coverage"], s["invalid"], seconds, s["pixels"],
                       note=scene.note), disp


def average(scores: list[SceneScore]) -> SceneScore:
    """Unweighted mean over scenes (each scene counts once, as in the seed's table)."""
    keys = scores[0].dense.keys()
    mean = lambda xs: float(np.nanmean(xs)) if len(xs) else float("nan")
    return SceneScore(
        "average", scores[0].backend,
        {k: mean([s.dense[k] for s in scores]) for k in keys},
        {k: mean([s.sparse[k] for s in scores]) for k in keys},
        mean([s.coverage for s in scores]), mean([s.invalid for s in scores]),
        mean([s.runtime_s for s in scores]), sum(s.pixels for s in scores))


def markdown_table(results: dict[str, list[SceneScore]]) -> str:
    """One row per scene, backends side by side: dense Bad-0.5/1/2/4 and avgerr, invalid %, sparse
    Bad-1.0 with its coverage, runtime."""
    names = list(results)
    head = ["scene"]
    for n in names:
        head += [f"{n} d-bad0.5", f"{n} d-bad1", f"{n} d-bad2", f"{n} d-bad4", f"{n} d-avgerr",
                 f"{n} invalid%", f"{n} s-bad1", f"{n} cov%", f"{n} s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = [[s.scene for s in results[names[0]]]]
    for n in names:
        rows.append(results[n])
    for i, scene in enumerate(rows[0] + ["average"]):
        cells = [f"**{scene}**" if scene == "average" else scene]
        for n in names:
            s = average(results[n]) if scene == "average" else results[n][i]
            d = s.dense
            cells += [f"{d['bad0.5']:.2f}", f"{d['bad1.0']:.2f}", f"{d['bad2.0']:.2f}", f"{d['bad4.0']:.2f}",
                      f"{d['avgerr']:.2f}", f"{s.invalid:.1f}", f"{s.sparse['bad1.0']:.2f}", f"{s.coverage:.1f}",
                      f"{s.runtime_s:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def save_results(out: Path, results: dict[str, list[SceneScore]], meta: dict) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    payload = {"meta": meta, "scoring": __doc__.strip(),
               "backends": {n: {"scenes": [asdict(s) for s in r], "average": asdict(average(r))}
                            for n, r in results.items()}}
    json_path, md_path = out / "stereo_eval.json", out / "stereo_eval.md"
    write_text(json_path, json.dumps(payload, indent=2))
    write_text(md_path, "d- = dense (missing = bad), s- = sparse (claimed pixels only, cov% of them); "
                       "Bad-x in %, quarter-resolution pixels, non-occluded mask.\n\n" + markdown_table(results))
    return json_path, md_path


def colourise(disp: np.ndarray, vmax: float) -> np.ndarray:
    """HxW disparity -> HxWx3 uint8 BGR, invalid black."""
    scaled = np.clip(np.nan_to_num(disp, nan=0.0, posinf=0.0, neginf=0.0) / max(vmax, 1e-6), 0, 1)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_JET)
    image[~np.isfinite(disp)] = 0
    return image


def save_figure(path: Path, scenes: list[SceneData], disparities: dict[str, list[np.ndarray]]) -> Path:
    """Per scene a row: left image, then for each backend its disparity and its error map
    (|error| clipped at 4 px; pixels without ground truth grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(disparities)
    cols = 1 + 2 * len(names)
    fig, axes = plt.subplots(len(scenes), cols, figsize=(3.2 * cols, 2.4 * len(scenes)), squeeze=False)
    for r, scene in enumerate(scenes):
        axes[r][0].imshow(scene.left[..., ::-1])
        axes[r][0].set_title(scene.name, fontsize=8)
        for j, n in enumerate(names):
            disp = disparities[n][r]
            axes[r][1 + 2 * j].imshow(colourise(disp, scene.ndisp)[..., ::-1])
            axes[r][1 + 2 * j].set_title(f"{n} disparity", fontsize=8)
            err = np.abs(np.nan_to_num(disp, nan=0.0, posinf=0.0) - scene.gt)
            err = np.where(np.isfinite(disp), err, 4.0)
            err = np.ma.masked_where(~(scene.nonocc & np.isfinite(scene.gt)), np.clip(err, 0, 4))
            cmap = plt.get_cmap("magma").with_extremes(bad="0.5")
            axes[r][2 + 2 * j].imshow(err, cmap=cmap, vmin=0, vmax=4)
            axes[r][2 + 2 * j].set_title(f"{n} |error| (0-4 px)", fontsize=8)
        for ax in axes[r]:
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    plt.close(fig)
    return path
