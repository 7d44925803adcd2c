"""Every numba kernel of the project releases the GIL: stereo and depth run beside the next frame's detection
in another thread, whose Python steps would otherwise wait for each kernel to finish."""
from __future__ import annotations

import importlib
import pathlib

import pytest
from numba.core.registry import CPUDispatcher

ROOT = pathlib.Path(__file__).resolve().parents[1]
MODULES = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts)
                 for folder in ("core", "plugins") for p in (ROOT / folder).rglob("*_numba.py"))


def test_the_kernel_modules_are_found():
    assert "core.surface_fit_numba" in MODULES and "plugins.torch_sgm.sgm_numba" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_every_kernel_called_from_python_releases_the_gil(name):
    module = importlib.import_module(name)
    kernels = {n: f for n, f in vars(module).items() if isinstance(f, CPUDispatcher) and f.__module__ == name}
    assert kernels, f"{name} has no compiled kernels"
    # an inlined kernel runs inside its caller, under the caller's options
    holding = sorted(n for n, f in kernels.items()
                     if f.targetoptions.get("inline") != "always" and not f.targetoptions.get("nogil"))
    assert not holding, f"{name}: {holding} hold the GIL (give them nogil=True)"
