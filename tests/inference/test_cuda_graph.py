"""``nemsim.inference.cuda_graph``: CUDA-graph replay against PyTorch eager.

On a CUDA machine (tests marked ``gpu``): the graphed rollouts of the eager kernels (one replay per call
through ``nemsim.evaluation.rollout.rollout``, and the whole rollout as one replay) agree with the eager
rollout within max |Δ| < 1e-5 in fp32 over the whole trajectory (the default fused capture within 1e-4),
on `tiny` (a k = 4 model after a few Adam steps, controls changing mid-rollout) and on `small` (the served
checkpoint), at batch 1 and 4.
Without CUDA: the runtime refuses to build and ``compile_model(model, "cuda")`` falls back to eager torch
with the reason; and the runtime's bookkeeping (static buffers, one graph per batch size, the control cache
reloaded on a control change, the whole-rollout loop) runs on the CPU with the capture replaced by
re-running the captured function on the same static buffers (what a replay does).
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

from nemsim.evaluation.rollout import rollout
from nemsim.inference import cuda_graph
from nemsim.inference.cuda_graph import CUDAGraphRuntime, CUDAUnavailable, cuda_runtime
from nemsim.inference.runtime import TorchRuntime

torch.set_num_threads(1)

CUDA = torch.cuda.is_available()
gpu = pytest.mark.gpu
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
SERVED = Path(__file__).resolve().parents[2] / "checkpoints" / "nemsim-small.pt"
TOL = 1e-5


def _trained(scene, config: dict | None = None, steps: int = 5):
    """NEMSim on ``scene`` after a few Adam steps on a synthetic target (every zero-initialized head is
    non-zero, so it takes part in the comparison), in eval mode, on the CPU; and x0 (2, D, H, W)."""
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.sim import initial_state

    torch.manual_seed(0)
    model = build_model("nemsim", scene, compile_rules(load_rules()), config)
    x0 = torch.as_tensor(initial_state(scene), dtype=torch.float32)  # (2, D, H, W)
    xb = x0[None].repeat(2, 1, 1, 1, 1)  # (2, 2, D, H, W)
    g = torch.Generator().manual_seed(1)
    target = (xb + 0.05 * torch.randn(xb.shape, generator=g)).clamp(-1, 1)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(steps):
        u = torch.rand(2, 14, generator=g) * 2 - 1
        loss = (model(xb, u, all_steps=True) - target[:, None]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval(), x0


def _controls(batch: int, steps: int, change_at: int | None, seed: int = 2) -> torch.Tensor:
    """(B, steps, 14) normalized controls, constant, or changing once at ``change_at``."""
    g = torch.Generator().manual_seed(seed)
    u = (torch.rand(batch, 1, 14, generator=g) * 2 - 1).repeat(1, steps, 1)
    if change_at is not None:
        u[:, change_at:] = torch.rand(batch, 1, 14, generator=g) * 2 - 1
    return u


@pytest.fixture(scope="module")
def tiny_k4(tiny_scene):
    """The served model's form on `tiny`: k = 4 states per call, flux gate on."""
    return _trained(tiny_scene, {"steps_per_call": 4, "flux_gate": True})


# -- without CUDA ----------------------------------------------------------------------------------------


@pytest.mark.skipif(CUDA, reason="checks the refusal without CUDA")
def test_refuses_without_cuda(tiny_k4):
    model, _ = tiny_k4
    with pytest.raises(CUDAUnavailable, match="CUDA is not available"):
        CUDAGraphRuntime(model)


@pytest.mark.skipif(CUDA, reason="checks the fallback without CUDA")
def test_cuda_backend_falls_back_to_eager_torch(tiny_k4):
    from nemsim.inference.runtime import compile_model

    model, x0 = tiny_k4
    for runtime in (cuda_runtime(model), compile_model(model, "cuda")):  # type: ignore[arg-type]
        assert isinstance(runtime, TorchRuntime) and runtime.backend == "torch"
        assert "CUDA is not available" in str(runtime.fallback_reason)
    u = _controls(1, 3, None)
    assert torch.equal(rollout(runtime, x0[None], u), rollout(model, x0[None], u))


class _Replayed(CUDAGraphRuntime):
    """The runtime on the CPU, a "capture" being the captured function run again on its static buffers at
    every replay (a CUDA graph replays the same kernels on the same memory)."""

    captures = 0

    def __init__(self, model, fuse: bool = False, **kwargs) -> None:  # unfused: no compile on the CPU
        super().__init__(model, fuse=fuse, **kwargs)

    @staticmethod
    def _resolve_device(model, device):
        return torch.device("cpu")

    def _on_device(self):
        return self._lock

    def _capture(self, body, warmup):
        for _ in range(warmup):
            body()
        out = body()
        type(self).captures += 1

        def replay() -> None:
            res = body()
            if res is not out:  # a call returns a fresh tensor; the rollout its static buffer
                out.copy_(res)

        return replay, out


def test_replayed_calls_match_eager_rollout(tiny_k4):
    """One graph per batch size, reused across rollouts; the static cache follows control changes."""
    model, x0 = tiny_k4
    runtime = _Replayed(model)
    _Replayed.captures = 0
    for batch, change_at in ((1, None), (3, 5), (1, 2), (3, None)):
        x = x0[None].repeat(batch, 1, 1, 1, 1)
        u = _controls(batch, 9, change_at, seed=batch)
        got = rollout(runtime, x, u)  # type: ignore[arg-type]
        want = rollout(model, x, u)
        assert (got - want).abs().max() <= 1e-6
    assert _Replayed.captures == 2 and runtime.describe()["graphs"] == [1, 3]
    assert runtime.backend == "cuda" and runtime.fallback_reason is None


def test_replayed_whole_rollout_matches_eager(tiny_k4):
    model, x0 = tiny_k4
    runtime = _Replayed(model)
    x = x0[None].repeat(2, 1, 1, 1, 1)
    for seed in (3, 4):  # the second replays the first's graph with other controls
        u = _controls(2, 1, None, seed=seed)[:, 0]  # (2, 14)
        got = runtime.rollout(x, u, 7)
        want = rollout(model, x, u, 7)
        assert got.shape == want.shape == (2, 8, *x.shape[1:])
        assert (got - want).abs().max() <= 1e-6
    assert runtime.describe()["rollout_graphs"] == [(2, 7)]


def test_a_fused_call_that_fails_is_captured_unfused(tiny_k4):
    """A fused call that cannot be compiled or captured leaves the graph path: the eager kernels are
    captured instead, and the reason is kept."""
    model, x0 = tiny_k4
    runtime = _Replayed(model, fuse=True)

    def broken(x, tree):
        raise RuntimeError("no Triton here")

    runtime._call = broken
    x, u = x0[None], _controls(1, 6, None)
    got = rollout(runtime, x, u)  # type: ignore[arg-type]
    assert (got - rollout(model, x, u)).abs().max() <= 1e-6
    described = runtime.describe()
    assert described["fuse"] is False and "no Triton here" in described["fuse_fallback_reason"]
    assert runtime.backend == "cuda" and runtime.fallback_reason is None and described["graphs"] == [1]


def test_refuses_a_cache_of_another_batch(tiny_k4):
    model, x0 = tiny_k4
    runtime = _Replayed(model)
    cache = runtime.precompute(_controls(2, 1, None)[:, 0])
    with pytest.raises(ValueError, match="B = 2"):
        runtime.predict(x0[None], cache)


# -- on a CUDA device -----------------------------------------------------------------------------------


@pytest.fixture
def strict_fp32():
    """fp32 convolutions and matrix products (no TF32), so that "agree in fp32" means fp32."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def _agree(model, x0: torch.Tensor, batch: int, steps: int, change_at: int | None) -> dict[str, float]:
    """max |Δ| of the graphed rollouts (per call; whole, for constant controls) against eager, on cuda."""
    dev = torch.device("cuda")
    model = copy.deepcopy(model).to(dev)  # the module's CPU tests keep theirs
    x = x0[None].repeat(batch, 1, 1, 1, 1).to(dev)
    u = _controls(batch, steps, change_at, seed=batch).to(dev)
    want = rollout(TorchRuntime(model), x, u)  # type: ignore[arg-type]
    runtime = CUDAGraphRuntime(model, fuse=False)  # the eager kernels: bit for bit
    diffs = {"calls": float((rollout(runtime, x, u) - want).abs().max())}  # type: ignore[arg-type]
    if change_at is None:
        diffs["whole"] = float((runtime.rollout(x, u[:, 0], steps) - want).abs().max())  # the capture
        # a replay after other allocations: memory the graph uses must not have been handed back meanwhile
        churn = [torch.full((1 << 18,), 7.0, device=dev) for _ in range(64)]
        diffs["whole_replay"] = float((runtime.rollout(x, u[:, 0], steps) - want).abs().max())
        del churn
    assert runtime.backend == "cuda" and runtime.fallback_reason is None, runtime.describe()
    return diffs


@gpu
@needs_cuda
@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("change_at", [None, 5])
def test_graphed_rollout_agrees_with_eager_tiny(tiny_k4, batch, change_at, strict_fp32):
    model, x0 = tiny_k4
    diffs = _agree(model, x0, batch, 12, change_at)
    assert max(diffs.values()) < TOL, diffs


@gpu
@needs_cuda
@pytest.mark.parametrize("batch", [1, 4])
def test_graphed_rollout_agrees_with_eager_small(batch, strict_fp32):
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.sim import initial_state

    loaded = load_checkpoint(SERVED, device="cuda")
    x0 = torch.as_tensor(initial_state(loaded.scene), dtype=torch.float32)
    diffs = _agree(loaded.model, x0, batch, loaded.scene.n_transitions, None)
    assert max(diffs.values()) < TOL, diffs


@gpu
@needs_cuda
def test_fused_capture_agrees_with_eager(tiny_k4, strict_fp32):
    """The default fused capture changes the order of the float32 arithmetic, not what is computed: the
    rollouts (per call and whole) agree with eager to float32 rounding."""
    model, x0 = tiny_k4
    dev = torch.device("cuda")
    model = copy.deepcopy(model).to(dev)
    x = x0[None].repeat(2, 1, 1, 1, 1).to(dev)
    u = _controls(2, 12, None, seed=7).to(dev)
    want = rollout(TorchRuntime(model), x, u)  # type: ignore[arg-type]
    runtime = CUDAGraphRuntime(model)
    calls = rollout(runtime, x, u)  # type: ignore[arg-type]
    whole = runtime.rollout(x, u[:, 0], 12)
    assert runtime.backend == "cuda" and runtime.fallback_reason is None, runtime.describe()
    assert runtime.describe()["fuse"] is True and runtime.fuse_fallback_reason is None
    assert float((calls - want).abs().max()) < 1e-4
    assert float((whole - want).abs().max()) < 1e-4


@gpu
@needs_cuda
def test_compile_model_cuda_backend(tiny_k4):
    from nemsim.inference.runtime import compile_model

    model, x0 = tiny_k4
    runtime = compile_model(copy.deepcopy(model), "cuda")  # type: ignore[arg-type]
    assert isinstance(runtime, CUDAGraphRuntime) and runtime.backend == "cuda"
    x = x0[None].cuda()
    u = _controls(1, 1, None)[:, 0].cuda()
    cache = runtime.precompute(u)
    a, b = runtime.predict(x, cache), runtime.predict(x, cache)  # replays write fresh tensors
    assert a.data_ptr() != b.data_ptr() and torch.equal(a, b)
    assert a.device.type == "cuda" and a.shape == (1, 4, *x.shape[1:])


@gpu
@needs_cuda
def test_uncapturable_model_falls_back_to_eager(tiny_k4, monkeypatch, strict_fp32):
    """A call that synchronizes with the host cannot be captured: eager on the GPU, the reason kept."""
    model, x0 = tiny_k4
    model = copy.deepcopy(model).cuda()
    real = cuda_graph.model_predict

    def syncing(m, x, cache):
        float(x.sum())  # a host synchronization: not allowed while capturing
        return real(m, x, cache)

    monkeypatch.setattr(cuda_graph, "model_predict", syncing)
    runtime = CUDAGraphRuntime(model, fuse=False)
    x = x0[None].cuda()
    u = _controls(1, 6, None).cuda()
    got = rollout(runtime, x, u)  # type: ignore[arg-type]
    assert runtime.backend == "torch" and "capture failed" in str(runtime.fallback_reason)
    assert (got - rollout(TorchRuntime(model), x, u)).abs().max() < TOL  # type: ignore[arg-type]
    # the failed capture left the allocator usable: the cache empties, and another model captures
    monkeypatch.undo()
    torch.cuda.empty_cache()
    again = CUDAGraphRuntime(model, fuse=False)
    assert (rollout(again, x, u) - got).abs().max() < TOL  # type: ignore[arg-type]
    assert again.backend == "cuda" and again.describe()["graphs"] == [1]


def test_replayed_whole_rollout_of_a_quarter_model(tiny_scene):
    """A quarter-domain model's whole-rollout graph runs on the quadrant and gives the library rollout's
    full fields, exactly symmetric."""
    from nemsim.symmetry import symmetrize

    model, x0 = _trained(tiny_scene, {"steps_per_call": 4, "flux_gate": True, "domain": "quarter"})
    runtime = _Replayed(model)
    x = x0[None].repeat(2, 1, 1, 1, 1)
    u = _controls(2, 1, None, seed=5)[:, 0]  # (2, 14)
    got = runtime.rollout(x, u, 7)
    want = rollout(model, x, u, 7)
    assert got.shape == want.shape == (2, 8, *x.shape[1:])
    assert (got - want).abs().max() <= 1e-6
    assert torch.equal(got[:, 1:], symmetrize(got[:, 1:]))
    c = (x.shape[-1] + 1) // 2  # the graph was captured on the quadrant
    assert list(runtime._rollouts) == [(2, 7, (2, x.shape[2], c, c), None)]


def test_predictor_rolls_constant_controls_as_one_graph(tiny_checkpoint):
    """``Predictor`` with a CUDA-graph runtime: constant controls take the whole-rollout graph, a recipe the
    per-call path; both give the reference predictor's states."""
    import numpy as np

    from nemsim.controls import CONTROL_SPECS
    from nemsim.inference import Predictor

    ref = Predictor.from_checkpoint(tiny_checkpoint, backend="torch")
    fast = Predictor(ref.loaded, backend="torch")
    fast.runtime = _Replayed(ref.loaded.model)
    mid = {s.name: (s.low + s.high) / 2 for s in CONTROL_SPECS}
    low = {s.name: s.low for s in CONTROL_SPECS}
    out = torch.empty(8, *ref.scene.state_shape)
    a, b = fast.rollout(mid, 6, out=out), ref.rollout(mid, 6)
    assert np.abs(a.states - b.states).max() <= 1e-6
    assert fast.runtime.describe()["rollout_graphs"] == [(1, 6)]  # one replay of the whole rollout
    recipe = [mid] * 3 + [low] * 3
    a, b = fast.rollout(recipe, out=out), ref.rollout(recipe)
    assert np.abs(a.states - b.states).max() <= 1e-6
    assert fast.runtime.describe()["rollout_graphs"] == [(1, 6)]  # the recipe went call by call


def test_predictor_warm_up_captures_the_scene_rollout(tiny_checkpoint):
    """``Predictor.warm_up`` on a CUDA-graph runtime captures the whole constant-control rollout of the
    scene's length, so a service's first request replays it instead of capturing (and compiling)."""
    from nemsim.inference import Predictor

    fast = Predictor.from_checkpoint(tiny_checkpoint, backend="torch")
    fast.runtime = _Replayed(fast.loaded.model)
    fast.warm_up(2)
    assert fast.runtime.describe()["rollout_graphs"] == [(1, fast.scene.n_transitions)]
