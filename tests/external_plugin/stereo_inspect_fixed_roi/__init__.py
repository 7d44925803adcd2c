"""A detector plugin that reports fixed regions of interest as "defects".

Use: measure known places of a part (a weld seam, a boss, a gauge block) with the stereo
pipeline, or commission a line before a trained model exists. It is also the worked example
of docs/writing-a-plugin.md: a package of its own, found through the ``stereo_inspect``
entry-point group, selected in a recipe with ``detector.plugin: fixed_roi``.
"""
from __future__ import annotations

from pydantic import Field

from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.settings_model import Settings
from core.types import Detection


class Region(Settings):
    name: str = Field(min_length=1)
    box: tuple[float, float, float, float]


class FixedRoiSettings(Settings):
    regions: list[Region] = Field(default_factory=list)
    # The host passes these to every detector; a fixed region is always "found" with certainty.
    weights: str | None = None
    confidence: float = 0.25


class FixedRoiDetector:
    def __init__(self, settings: FixedRoiSettings):
        self.regions = settings.regions
        self.class_names = sorted({r.name for r in settings.regions})

    def detect(self, image):
        h, w = image.shape[:2]
        return [
            Detection(r.name, 1.0, (max(r.box[0], 0.0), max(r.box[1], 0.0), min(r.box[2], w), min(r.box[3], h)))
            for r in self.regions
        ]


@hookimpl
def stereo_inspect_detectors():
    return [
        PluginSpec(
            name="fixed_roi",
            kind="detector",
            factory=lambda settings, ctx: FixedRoiDetector(FixedRoiSettings(**settings)),
            settings_model=FixedRoiSettings,
            description="reports fixed regions of interest (example third-party plugin)",
        )
    ]
