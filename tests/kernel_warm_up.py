"""Fill numba's cache beside the code before the tests start (``conftest.pytest_sessionstart``), in two processes
that compile different kernels at once: from a cold cache torch_sgm's kernels took 98-107 s on one core, the other
idle after depth's 13 s; split this way both are done in 70-72 s (docs/research-log.md).

``python tests/kernel_warm_up.py first``: torch_sgm's whole pipeline, at one thread and at two (its first stages'
kernels are compiled here; the later ones are, by then, mostly in the cache).
``python tests/kernel_warm_up.py later``: depth's kernels, then torch_sgm's pipeline with its first stages (the cost
and its aggregation, the vertical alignment, SGM) in torch, their references, so that it goes straight on to the
later stages' kernels (the winners, the plane filling, the medians, the plane fits).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _torch_sgm(threads: tuple[int, ...]) -> None:
    import torch

    from core.contracts import PluginContext
    from plugins.torch_sgm.plugin import _factory

    backend = _factory({}, PluginContext(device="cpu"))
    for count in threads:
        torch.set_num_threads(count)
        backend.warm_up()


def first() -> None:
    _torch_sgm((1, 2))


def later() -> None:
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
    _torch_sgm((1,))


if __name__ == "__main__":
    {"first": first, "later": later}[sys.argv[1]]()
