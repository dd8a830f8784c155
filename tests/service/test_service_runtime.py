"""The service's rollouts go through ``nemsim.inference.runtime`` (settings runtime_backend / _precision /
_threads): OpenVINO when installed, PyTorch otherwise, the same trajectory within float rounding."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.controls import CONTROL_SPECS
from nemsim.inference.runtime import openvino_available


def _controls(steps: int) -> np.ndarray:
    mid = np.array([(s.low + s.high) / 2 for s in CONTROL_SPECS])
    return np.repeat(mid[None], steps, axis=0)  # (T, 14) physical units


def test_runtime_settings_from_the_environment(monkeypatch):
    from service.config import Settings

    s = Settings()
    assert (s.runtime_backend, s.runtime_precision, s.runtime_threads) == ("openvino", "auto", 1)
    monkeypatch.setenv("NEMSIM_RUNTIME_BACKEND", "torch")
    monkeypatch.setenv("NEMSIM_RUNTIME_PRECISION", "f32")
    monkeypatch.setenv("NEMSIM_RUNTIME_THREADS", "2")
    s = Settings()
    assert (s.runtime_backend, s.runtime_precision, s.runtime_threads) == ("torch", "f32", 2)
    monkeypatch.setenv("NEMSIM_RUNTIME_BACKEND", "onnx")
    with pytest.raises(ValueError, match="runtime_backend"):
        Settings()


@pytest.mark.slow
@pytest.mark.skipif(not openvino_available(), reason="openvino not installed (nemsim[fast])")
def test_service_rollout_runs_on_openvino_and_matches_torch(tiny_checkpoint):
    from service.served_model import ServedModel

    fast = ServedModel.from_checkpoint(tiny_checkpoint, runtime_backend="openvino", runtime_precision="f32")
    ref = ServedModel.from_checkpoint(tiny_checkpoint, runtime_backend="torch", runtime_precision="f32")
    fast.warm_up(2)  # compiles the graph before the first request
    assert fast.predictor.runtime.backend == "openvino" and ref.predictor.runtime.backend == "torch"
    a, _ = fast.rollout(_controls(5))
    b, _ = ref.rollout(_controls(5))
    assert fast.predictor.runtime.backend == "openvino"  # no silent fallback inside the request
    # the API returns float16 states: compare at that resolution
    assert np.abs(a.states.decode().astype(np.float32) - b.states.decode().astype(np.float32)).max() <= 2e-3
