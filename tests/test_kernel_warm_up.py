"""The compiled kernels' warm-up in two processes where numba's cache lacks them (plugins/torch_sgm/kernel_warm_up.py)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from core.contracts import PluginContext
from plugins.torch_sgm import kernel_warm_up
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.plugin import _factory

COLD = "from plugins.torch_sgm import kernel_warm_up; import json, sys; print(kernel_warm_up.cold(json.loads(sys.argv[1])))"


def cold_in(cache: str, settings: str = "{}") -> str:
    """``cold(settings)`` in a fresh process whose numba cache is the folder ``cache``."""
    result = subprocess.run([sys.executable, "-c", COLD, settings], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "NUMBA_CACHE_DIR": cache})
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


class TestCold:
    def test_the_cache_the_session_filled_is_warm_for_every_preset(self):
        assert kernel_warm_up.cold({}) is False
        assert kernel_warm_up.cold(TorchSGMParams(preset="seed").model_dump(mode="json")) is False

    def test_an_empty_cache_is_cold_whatever_the_implementation(self, tmp_path):
        assert cold_in(str(tmp_path)) == "True"
        # the reference implementation compiles none of torch_sgm's kernels, but depth's still
        assert cold_in(str(tmp_path), '{"implementation": "reference"}') == "True"


class TestStartAndFinish:
    def test_the_later_half_runs_to_its_end(self):
        helper = kernel_warm_up.start("later", {}, (1,))
        kernel_warm_up.finish(helper)
        assert helper.returncode == 0

    def test_a_helper_past_its_time_is_stopped(self):
        helper = kernel_warm_up.start("first", {})
        kernel_warm_up.finish(helper, timeout_s=0.05)
        assert helper.returncode not in (None, 0)

    def test_settings_it_cannot_use_end_the_helper_not_the_caller(self):
        helper = kernel_warm_up.start("later", {"paths": 3})
        kernel_warm_up.finish(helper)
        assert helper.returncode not in (None, 0)


class TestBackendWarmUp:
    def test_no_helper_where_the_cache_holds_the_kernels(self, monkeypatch):
        started = []
        monkeypatch.setattr(kernel_warm_up, "start", lambda *a: started.append(a))
        _factory({}, PluginContext(device="cpu")).warm_up()
        assert started == []

    def test_where_the_cache_lacks_them_a_helper_compiles_the_later_stages_with_the_backends_settings(self, monkeypatch):
        started, real = [], kernel_warm_up.start
        monkeypatch.setattr(kernel_warm_up, "cold", lambda settings: True)
        monkeypatch.setattr(kernel_warm_up, "start", lambda *a: started.append(real(*a)) or started[-1])
        backend = _factory({"paths": 4, "device": "cpu"}, PluginContext(device="cpu"))
        backend.warm_up()
        (helper,) = started
        assert helper.args[3] == "later" and helper.args[5] == str(torch.get_num_threads())
        assert TorchSGMParams.model_validate_json(helper.args[4]) == backend.params
        assert helper.returncode == 0  # waited for, and it ran to its end

    def test_a_warm_up_that_fails_stops_its_helper_at_once(self, monkeypatch):
        from plugins.torch_sgm import pipeline

        started, real = [], kernel_warm_up.start
        monkeypatch.setattr(kernel_warm_up, "cold", lambda settings: True)
        monkeypatch.setattr(kernel_warm_up, "start", lambda *a: started.append(real(*a)) or started[-1])

        def interrupted(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr(pipeline, "compute_disparity", interrupted)
        with pytest.raises(KeyboardInterrupt):
            _factory({"device": "cpu"}, PluginContext(device="cpu")).warm_up()
        (helper,) = started
        assert helper.returncode not in (None, 0)  # stopped, not waited for to its end
