"""torch_sgm's and depth's compiled kernels put in numba's cache by two processes at once, where it lacks them.

One process compiles them one after another, the second core idle: a first ``inspect run`` on a machine (or after
an update of the code) waited 77 s on the 2-core development machine before its first part. ``TorchSGM.warm_up``
therefore starts ``later`` in a process of its own where the cache is ``cold`` and meanwhile matches its own scene,
which compiles the first stages; by the time it reaches the later stages the helper has put most of them in the
cache. The tests' session start runs both halves (``tests/conftest.py``).

``python -m plugins.torch_sgm.kernel_warm_up first [SETTINGS] [THREADS]``: torch_sgm's whole pipeline (its first
stages' kernels: the cost and its aggregation, the vertical alignment, SGM), at each of THREADS (comma-separated,
default 1).
``python -m plugins.torch_sgm.kernel_warm_up later [SETTINGS] [THREADS]``: depth's kernels, then torch_sgm's pipeline
with those first stages in torch, their references, so that it goes straight on to the later stages' kernels (the
winners, the plane filling, the medians, the plane fits).
SETTINGS: the backend's settings as JSON (default: its defaults), matched on the CPU.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HELPER_TIMEOUT_S = 600  # a helper that has not finished by then is stopped: the parts compile what it left


def first(settings: dict, threads: tuple[int, ...] = (1,)) -> None:
    import torch

    from core.contracts import PluginContext
    from plugins.torch_sgm.plugin import _factory

    backend = _factory({**settings, "device": "cpu"}, PluginContext(device="cpu"))
    for count in threads:
        torch.set_num_threads(count)
        backend.warm_up(helper=False)


def later(settings: dict, threads: tuple[int, ...] = (1,)) -> None:
    from core.depth import warm_up
    from plugins.torch_sgm import align, align_numba, pipeline, sgm, sgm_numba

    def pixel_major_sgm(*args):  # the memory order sgm_numba returns, which the winners' kernels are compiled for
        return sgm.sgm_fast(*args).permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)

    warm_up()
    for module, name, reference in ((pipeline, "cost_volume_fast", pipeline.cost_volume),
                                    (sgm_numba, "sgm_numba", pixel_major_sgm),
                                    (align_numba, "vertical_offsets_numba", align.vertical_offsets),
                                    (align_numba, "resample_rows_numba", align.resample_rows)):
        getattr(module, name)  # the pipeline looks each up at every call; renamed there, this raises
        setattr(module, name, reference)
    first(settings, threads)


def _cached(kernel) -> bool:
    """Whether numba's cache holds a current entry for ``kernel`` (a dispatcher compiled with ``cache=True``)."""
    try:
        return bool(kernel._cache._cache_file._load_index())
    except Exception:  # another numba's internals: take it as cold, which costs a helper that loads from the cache
        return False


def cold(settings: dict) -> bool:
    """Whether numba's cache lacks depth's Gauss-Newton kernel or, for the compiled implementation, torch_sgm's
    winners (kernels every warm-up compiles, the one late in the pipeline): a warm-up would compile for a minute."""
    from core import surface_fit_numba
    from plugins.torch_sgm import select_numba
    from plugins.torch_sgm.params import TorchSGMParams

    kernels = [surface_fit_numba._system]
    if TorchSGMParams(**settings).implementation == "fast":
        kernels.append(select_numba._checked_winners)
    return not all(_cached(k) for k in kernels)


def start(part: str, settings: dict, threads: tuple[int, ...] = (1,)) -> subprocess.Popen:
    """``part`` (first or later) in a process of its own, its output discarded (a failure there leaves the kernels
    to whoever calls them next, which then says why)."""
    return subprocess.Popen([sys.executable, "-m", "plugins.torch_sgm.kernel_warm_up", part, json.dumps(settings),
                             ",".join(str(t) for t in threads)], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def finish(helper: subprocess.Popen, timeout_s: float = HELPER_TIMEOUT_S) -> None:
    """Wait for ``helper`` up to ``timeout_s``, then stop it."""
    try:
        helper.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        helper.kill()
        helper.wait()


def main(argv: list[str]) -> None:
    part, settings = argv[0], json.loads(argv[1]) if len(argv) > 1 else {}
    threads = tuple(int(t) for t in argv[2].split(",")) if len(argv) > 2 else (1,)
    {"first": first, "later": later}[part](settings, threads)


if __name__ == "__main__":
    main(sys.argv[1:])
