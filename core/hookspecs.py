"""Hook specifications: everything a plugin package can add to stereo-inspect.

A plugin is a module listed in the ``stereo_inspect`` entry-point group of its package's
``pyproject.toml``; it implements any of these hooks with ``@hookimpl``. The built-in plugins
register the same way, so a third-party package has exactly the powers they have.
"""
from __future__ import annotations

import pluggy

from core.contracts import PluginSpec

PROJECT = "stereo_inspect"
ENTRY_POINT_GROUP = "stereo_inspect"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def stereo_inspect_cameras() -> list[PluginSpec]:
    """Camera plugins: each factory returns an object with ``frames()`` and ``close()``
    (``core.contracts.Camera``) that yields rectified ``StereoFrame``s or ``FrameError``s."""


@hookspec
def stereo_inspect_stereo_backends() -> list[PluginSpec]:
    """Stereo backends: each factory returns a ``core.contracts.StereoBackend`` whose
    ``compute(left, right, min_disp, max_disp)`` gives an HxW float32 disparity, NaN = invalid."""


@hookspec
def stereo_inspect_detectors() -> list[PluginSpec]:
    """Defect detectors: each factory returns a ``core.contracts.Detector``."""


@hookspec
def stereo_inspect_outputs() -> list[PluginSpec]:
    """Reject outputs: each factory returns a ``core.contracts.RejectOutput`` that acts on
    decided parts (fires a reject, logs it, ...) and reports what it sent."""


@hookspec
def stereo_inspect_commands(cli) -> None:
    """Add command-line commands: ``cli`` is the ``inspect`` click group. Use
    ``cli.commands["eval"]`` etc. to add to an existing group."""
