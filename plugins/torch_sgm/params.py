"""Every torch_sgm setting. The field defaults are the seed paper's values; ``preset: improved`` (the
default) starts from ``IMPROVED`` instead, ``preset: seed`` reproduces the paper. Kept free of torch so
that validating a recipe (and starting the CLI) does not load it."""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from core.settings_model import Settings

# Changes to the seed measured on Middlebury trainingQ and on synthetic pairs (docs/research-log.md).
IMPROVED: dict = {"refine_radius": 0, "agg_radius": 2, "agg_detail_radius": 1, "paths": 8, "p1": 0.08, "p2": 1.3,
                  "search": "coarse_to_fine", "uniqueness": 0.3, "plane_fill": True, "wmf_radius": 4, "fit_radius": 3,
                  "align": "projective", "p2_edge": "path", "p2_alpha": 40.0, "view_check_edge": 0.01,
                  "fill_slope": True, "plane_local": True}


class TorchSGMParams(Settings):
    """``preset: improved`` (the default) is the configuration measured best on Middlebury and on the
    plates (docs/benchmarks.md); ``preset: seed`` is the seed paper's parameters (cost weights, guided
    filter r = 3 / eps = 0.001, 4 paths, P1 = 0.04, P2 = 0.65 / (1 + 20 |edge|), 1 px LR check), the
    field defaults below. Settings given explicitly win over either."""

    preset: Literal["seed", "improved"] = "improved"

    @model_validator(mode="before")
    @classmethod
    def _apply_preset(cls, data):
        if isinstance(data, dict) and data.get("preset", "improved") == "improved":
            return {**IMPROVED, **data}
        return data

    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="auto: the command's device; where that "
                                                  "is auto too (CUDA where there is one), pairs under 100,000 "
                                                  "pixels on the CPU, where they match several times faster "
                                                  "(plugin.SMALL_ON_CPU_PIXELS)")
    # 1. matching cost
    w_ad: float = Field(0.10, ge=0)
    w_census: float = Field(0.60, ge=0)
    w_grad: float = Field(0.30, ge=0)
    lam_ad: float = Field(1.0, gt=0)
    lam_census: float = Field(6.0, gt=0, description="in bits of the 24-bit census string")
    lam_grad: float = Field(0.02, gt=0, description="in normalised Sobel units of [0, 1] intensity")
    znorm_radius: int = Field(3, ge=1, description="window radius of the local zero-normalisation")
    znorm_eps: float = Field(0.001, gt=0, description="added to the local std; larger = less noise boost in flat areas")
    # 2. aggregation
    agg_radius: int = Field(3, ge=0)
    agg_eps: float = Field(0.001, gt=0)
    agg_detail_radius: int = Field(-1, ge=-1, description="guided-filter radius for textured pixels: each "
                                   "pixel's cost is a mix of this aggregation and agg_radius's, leaning on "
                                   "agg_radius where the left image is flat; -1 = off, one radius (the seed)")
    agg_texture: float = Field(0.02, gt=0, description="grey standard deviation over a 5x5 window, in [0, 1] "
                               "intensity, at which a pixel's cost takes 1/e of agg_radius's aggregation "
                               "(exp(-std / agg_texture)); only with agg_detail_radius >= 0")
    # 3. SGM
    paths: Literal[4, 8] = 4
    p1: float = Field(0.04, ge=0)
    p2: float = Field(0.65, ge=0)
    p2_alpha: float = Field(20.0, ge=0, description="P2 = p2 / (1 + p2_alpha * |edge|)")
    p2_edge: Literal["magnitude", "path"] = Field(
        "magnitude", description="the |edge| that lowers P2: magnitude = the grey image's Sobel gradient "
        "magnitude at the pixel, one P2 for every path (the seed); path = the grey step from the pixel's "
        "predecessor on each path, so P2 drops only for the paths that cross an edge")
    # 4. selection
    uniqueness: float = Field(0.0, ge=0, description="a pixel whose best aggregated cost does not beat every "
                              "disparity more than 1 step away by this share of itself counts as unmatched (and is "
                              "filled); 0 = off (the seed)")
    # 5. refinement
    lr_tolerance: float = Field(1.0, gt=0)
    fill: Literal["none", "background"] = Field(
        "background", description="background: each hole along its row from the farther of its two sides (the "
        "seed's); none: holes stay NaN")
    refine_radius: int = Field(3, ge=0, description="radius of the guided filter over the whole filled map (the "
                               "seed's), 0 = off")
    refine_eps: float = Field(0.001, gt=0)
    median_radius: int = Field(2, ge=0, le=10, description="median over filled pixels, 0 = off")
    plane_fill: bool = Field(False, description="holes inside a region of the left image bounded by colour edges "
                             "take the robust plane of that region's matched pixels, where it has one")
    plane_edge: float = Field(0.0025, gt=0, description="finest normalised Sobel magnitude (of [0, 1] "
                              "intensity) that bounds a region")
    plane_levels: int = Field(5, ge=1, le=10, description="edge thresholds tried, each twice the last, finest first")
    plane_samples: int = Field(32, ge=0, description="RANSAC triples per region that start the robust fit; "
                               "0 = start from plain least squares")
    plane_seed: int = Field(0, ge=0, description="seed of the RANSAC triples: a frame always gets the same triples, "
                            "on any device; another seed draws others (docs/benchmarks.md gives the spread)")
    plane_sigma: float = Field(1.0, ge=0, le=50, description="Gaussian blur before the edges are found, in pixels")
    plane_min_pixels: int = Field(100, ge=3, description="matched pixels a region needs for a plane")
    plane_inliers: float = Field(0.6, ge=0, le=1, description="share of a region's matched pixels that must lie "
                                 "within 1 px of its plane")
    plane_local: bool = Field(False, description="with plane_fill, a region that its matched pixels give no plane "
                              "and of which fewer than plane_local_max_matched matched takes the robust plane of "
                              "the winners of the cost before SGM that pass their own left-right check, where "
                              "plane_local_inliers of them lie within 1 px of it and those cover plane_local_density "
                              "of the region (a textureless tabletop that SGM gives its neighbour's disparity); "
                              "off = the seed")
    plane_local_inliers: float = Field(0.3, ge=0, le=1)
    plane_local_density: float = Field(0.18, ge=0, le=1)
    plane_local_max_matched: float = Field(0.25, ge=0, le=1)
    view_check_edge: float = Field(0.0, ge=0, description="before filling, drop the matches near the left border "
                                   "whose surface, carried from the trusted matches to their right within a region "
                                   "bounded by edges above this normalised Sobel magnitude, would have its match left "
                                   "of the right image (refine.out_of_view); 0 = off (the seed)")
    fill_slope: bool = Field(False, description="the row-wise filling carries each side's plane slope into the hole "
                             "(with plane_fill) instead of copying its value; off = the seed")
    wmf_radius: int = Field(0, ge=0, le=10, description="last, a median over every pixel's (2r+1)^2 window "
                            "weighted by colour similarity and distance, which moves disparity edges onto colour "
                            "edges; 0 = off (the seed)")
    wmf_sigma_colour: float = Field(0.1, gt=0, description="colour distance (RGB in [0, 1]) at which a "
                                    "neighbour's weight falls to 1/e")
    wmf_sigma_space: float = Field(7.0, gt=0, description="distance in pixels at which a neighbour's weight "
                                   "falls to 1/e")
    wmf_jump: float = Field(1.0, ge=0, description="only pixels whose window spans more than this many "
                            "disparity pixels are filtered; 0 = every pixel")
    fit_radius: int = Field(0, ge=0, le=10, description="after the weighted median, each pixel takes the plane "
                            "fitted to its (2r+1)^2 window (weighted like the median, neighbours within "
                            "fit_tolerance only), which undoes the pull of sub-pixel values towards integers; "
                            "0 = off (the seed)")
    fit_sigma_colour: float = Field(0.1, gt=0, description="as wmf_sigma_colour, for the plane fit")
    fit_sigma_space: float = Field(5.0, gt=0, description="as wmf_sigma_space, for the plane fit")
    fit_tolerance: float = Field(1.0, gt=0, description="disparity pixels a neighbour may differ by to take "
                                 "part in the fit, and the most the fit may move a pixel")
    two_view: bool = Field(False, description="last, the whole pipeline again with the right image as "
                           "reference; left pixels that its map contradicts by more than lr_tolerance take "
                           "the closest neighbouring value that it confirms (refine.two_view_choice), the plane "
                           "fit of fit_radius runs again, where the two maps agree within lr_tolerance the pixel "
                           "takes their mean (refine.two_view_average), and the plane fit runs once more. Twice "
                           "the time; off = the seed")
    two_view_reach: int = Field(16, ge=2, le=64, description="the farthest neighbour, in pixels left, right, "
                                "above and below (every second pixel), whose value two_view may take")
    two_view_iterations: int = Field(2, ge=1, le=16, description="rounds of two_view's choice")
    # search
    search: Literal["full", "coarse_to_fine"] = Field(
        "full", description="full: every disparity of the range at full resolution; coarse_to_fine: a pass at "
        "1/coarse_factor of the resolution finds the disparities the scene occupies, and only those are "
        "searched at full resolution (a plate spans a fraction of the working-distance range)")
    coarse_factor: int = Field(4, ge=2, le=8, description="downsampling of the coarse pass")
    coarse_margin: float = Field(6.0, ge=0, description="full-resolution pixels added on each side of the "
                                 "occupied range (1 px is about 4 mm at 420 mm from a ZED)")
    coarse_quantile: float = Field(0.005, ge=0, lt=0.5, description="share of the coarse matches ignored at "
                                   "each end of the range as mismatches")
    coarse_min_coverage: float = Field(0.2, ge=0, le=1, description="below this share of matched coarse "
                                       "pixels the whole range is searched")
    # rectification
    align: Literal["none", "projective"] = Field(
        "none", description="projective: measure how far the right image's rows sit from the left's (Lucas-Kanade "
        "at the coarse pass's disparities), fit a field of vertical offsets over the image (1, x, y, x y and y^2, "
        "as a small relative rotation of the cameras gives) and resample the right image by it before the "
        "full-resolution pass; none: trust the rectification (the seed)")
    align_radius: int = Field(3, ge=1, le=10, description="window radius of the Lucas-Kanade offsets")
    # memory and speed
    chunk_disparities: int = Field(32, ge=1, description="disparity slices built and filtered at once "
                                   "(the fast implementation uses at most 8)")
    implementation: Literal["fast", "reference"] = Field(
        "fast", description="fast: batched, in-place versions of the cost, aggregation and SGM stages; "
        "reference: the plain stage functions they are tested against (same result up to float rounding)")
