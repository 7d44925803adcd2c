"""sgm_triton: the Triton kernel gives ``sgm.sgm``'s path sums.

On a machine without a GPU the kernel runs in Triton's interpreter (TRITON_INTERPRET=1, which must be set
before the kernel is defined, so in a process of its own); on a GPU the compiled kernel runs instead.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from plugins.torch_sgm import sgm, sgm_triton

ROOT = Path(__file__).resolve().parents[1]
needs_triton = pytest.mark.skipif(sgm_triton.triton is None, reason="Triton is not installed")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

# Each case: (paths, shape (B, D, H, W), P2 as "paths" (one map per path), "one" (one map) or a number).
CASES = {
    "4 paths, one map per path": (4, (1, 7, 9, 13), "paths"),
    "8 paths, one map per path": (8, (2, 16, 11, 6), "paths"),
    "8 paths, one map": (8, (1, 5, 6, 8), "one"),
    "8 paths, a scalar": (8, (1, 4, 8, 3), 0.6),
    "a single row": (8, (1, 6, 1, 9), "paths"),
    "a single disparity": (4, (1, 1, 5, 4), "paths"),
}


def run_cases(device: str, interpret: bool) -> dict:
    """Each case's largest difference from the reference on ``device``; ``interpret`` runs the kernel in
    Triton's interpreter (CPU tensors, TRITON_INTERPRET=1 set before ``sgm_triton`` was imported)."""
    torch.manual_seed(0)
    result = {}
    for name, (n_paths, shape, p2) in CASES.items():
        paths = sgm.PATHS_8 if n_paths == 8 else sgm.PATHS_4
        volume = torch.rand(shape, device=device)
        if p2 == "paths":
            p2 = 0.3 + torch.rand(shape[0], len(paths), *shape[2:], device=device)
        elif p2 == "one":
            p2 = 0.3 + torch.rand(shape[0], *shape[2:], device=device)
        out = sgm_triton.sgm_triton(volume, 0.1, p2, paths, interpret=interpret)
        ref = sgm.sgm(volume, 0.1, p2, paths)
        # the reference with the maps swapped between paths: how far a wrong pairing of map and path lands
        swapped = sgm.sgm(volume, 0.1, p2.flip(1), paths) if torch.is_tensor(p2) and p2.dim() == 4 else ref
        result[name] = {"shape": list(out.shape), "error": (out - ref).abs().max().item(),
                        "swapped": (swapped - ref).abs().max().item(),
                        "single": (out - len(paths) * volume).abs().max().item()}
    return result


_SCRIPT = """
import json, sys
sys.path.insert(0, sys.argv[1])
import test_sgm_triton
print(json.dumps(test_sgm_triton.run_cases("cpu", interpret=True)))
"""


@pytest.fixture(scope="module")
def kernel_results():
    """Each case's largest difference from the reference: the compiled kernel where there is a GPU, else the
    kernel run by Triton's interpreter in a process of its own."""
    if torch.cuda.is_available():
        return run_cases("cuda", interpret=False)
    env = {**os.environ, "TRITON_INTERPRET": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", _SCRIPT, str(ROOT / "tests")], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@needs_triton
class TestSgmTriton:
    @pytest.mark.parametrize("name", list(CASES))
    def test_equals_the_reference(self, kernel_results, name):
        case = kernel_results[name]
        assert case["shape"] == list(CASES[name][1])
        assert case["error"] < 1e-5

    def test_each_path_reads_its_own_p2_map(self, kernel_results):
        # the test above could not tell the maps apart if swapping them changed nothing
        assert kernel_results["8 paths, one map per path"]["swapped"] > 1e-3

    def test_a_single_disparity_is_the_cost_times_the_paths(self, kernel_results):
        assert kernel_results["a single disparity"]["single"] < 1e-6

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CUDA tensor"):
            sgm_triton.sgm_triton(torch.rand(1, 4, 5, 6), 0.1, 0.5)
        with pytest.raises(ValueError, match="float32 CUDA tensor"):
            sgm_triton.sgm_triton(torch.rand(1, 4, 5, 6).double(), 0.1, 0.5, interpret=True)
        with pytest.raises(ValueError, match=r"\(B, D, H, W\)"):
            sgm_triton.sgm_triton(torch.rand(4, 5, 6), 0.1, 0.5, interpret=True)

    def test_is_offered_for_cuda_float32_tensors_only(self):
        assert not sgm_triton.available(torch.rand(1, 2, 3, 4))


@needs_triton
class TestLines:
    @pytest.mark.parametrize("path", sgm.PATHS_8)
    def test_every_pixel_lies_on_exactly_one_line(self, path):
        h, w = 5, 7
        start, length, longest = sgm_triton._lines(h, w, *path, torch.device("cpu"))
        assert longest == length.max()
        seen = torch.zeros(h, w, dtype=torch.long)
        for (y, x), n in zip(start.tolist(), length.tolist()):
            for i in range(n):
                seen[y + i * path[0], x + i * path[1]] += 1
        assert (seen == 1).all()


@needs_cuda
@needs_triton
class TestOnCuda:
    @pytest.mark.parametrize("paths", [sgm.PATHS_4, sgm.PATHS_8])
    def test_equals_the_reference_on_a_wvga_sized_volume(self, paths):
        torch.manual_seed(1)
        volume = torch.rand(1, 96, 188, 336, device="cuda")
        p2 = 0.3 + torch.rand(1, len(paths), 188, 336, device="cuda")
        out = sgm_triton.sgm_triton(volume, 0.08, p2, paths)
        assert out.is_cuda
        assert torch.allclose(out, sgm.sgm(volume, 0.08, p2, paths), atol=1e-4)

    def test_the_pipeline_uses_the_gpu_kernels(self, monkeypatch):
        from plugins.torch_sgm import pipeline, refine_numba
        from plugins.torch_sgm.synthetic import layered_scene

        called = []
        for module, name in ((sgm_triton, "sgm_triton"), (refine_numba, "out_of_view_numba")):
            original = getattr(module, name)

            def spy(*args, _original=original, _name=name, **kwargs):
                called.append(_name)
                assert all(a.device.type == ("cuda" if _name == "sgm_triton" else "cpu")
                           for a in args if torch.is_tensor(a))
                return _original(*args, **kwargs)
            monkeypatch.setattr(module, name, spy)
        left, right, _, _ = layered_scene(seed=5)
        disp, _ = pipeline.compute_disparity(left, right, 0, 32, pipeline.TorchSGMParams(), device="cuda")
        assert {"sgm_triton", "out_of_view_numba"} <= set(called)
        assert torch.isfinite(torch.from_numpy(disp)).mean(dtype=torch.float32) > 0.9
