"""``nemsim.inference.runtime``: the OpenVINO step graph against PyTorch eager on trained `tiny` weights,
and the fallback to PyTorch.

"Trained" here: the untrained model after a few Adam steps on a synthetic target, so every zero-initialized
head (MRC amplitudes, ...) is non-zero and takes part in the comparison. Tolerances (normalized SDF units,
whole trajectory): f32 max |Δ| <= 1e-4 (float rounding of a different kernel order; measured ~1e-6);
bf16 max |Δ| <= 0.05 and RMS Δ <= 0.01 (bf16 has 8 mantissa bits; the rule side stays in fp32 because
``precompute`` runs in PyTorch).
"""

from __future__ import annotations

import logging
import threading

import pytest
import torch
from torch import nn

from nemsim.evaluation.rollout import rollout
from nemsim.inference import runtime
from nemsim.inference.precision import cpu_flags
from nemsim.inference.runtime import compile_model, openvino_available

torch.set_num_threads(1)

needs_openvino = pytest.mark.skipif(not openvino_available(), reason="openvino not installed (nemsim[fast])")

STEPS = 6


def _trained(tiny_scene, config: dict | None = None):
    """(model, x0 (2, 2, D, H, W), u (2, STEPS, 14)): NEMSim after 5 Adam steps; a recipe per case."""
    from bench.stress import initial_state
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, compile_rules(load_rules()), config)
    zero = [n for n, p in model.named_parameters() if p.abs().max() == 0]
    x0 = torch.as_tensor(initial_state(tiny_scene))[None].repeat(2, 1, 1, 1, 1)  # (2, 2, D, H, W)
    g = torch.Generator().manual_seed(1)
    target = (x0 + 0.05 * torch.randn(x0.shape, generator=g)).clamp(-1, 1)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(5):
        u = torch.rand(2, 14, generator=g) * 2 - 1
        loss = (model(x0, u, all_steps=True) - target[:, None]).pow(2).mean()  # all k states
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    assert zero and all(dict(model.named_parameters())[n].abs().max() > 0 for n in zero)
    u = torch.rand(2, 1, 14, generator=g).repeat(1, STEPS, 1) * 2 - 1  # (2, STEPS, 14)
    u[:, STEPS // 2 :] = torch.rand(2, 1, 14, generator=g) * 2 - 1  # the controls change mid-rollout
    return model, x0, u


@pytest.fixture(scope="module")
def trained(tiny_scene):
    return _trained(tiny_scene)


@pytest.fixture(scope="module")
def trained_multistep(tiny_scene):
    """The served model's form: k = 4 states per call (STEPS = 6 with a control change at 3: chunks of 3),
    flux gate on."""
    return _trained(tiny_scene, {"steps_per_call": 4, "flux_gate": True})


@pytest.mark.slow
@needs_openvino
def test_openvino_f32_matches_pytorch(trained):
    model, x0, u = trained
    ref = rollout(model, x0, u)  # (2, STEPS+1, 2, D, H, W) PyTorch eager, the reference
    pred = compile_model(model, "openvino", "f32", threads=1)
    assert pred.backend == "openvino" and pred.fallback_reason is None
    assert pred.describe()["inference_precision"] is None  # nothing compiled yet
    out = rollout(pred, x0, u)
    assert pred.describe()["inference_precision"] == "f32"
    assert out.shape == ref.shape and out.dtype == torch.float32
    assert (out[:, 1:] - out[:, :1]).abs().max() > 1e-3  # the trajectory moves: the check is not vacuous
    assert (out - ref).abs().max() <= 1e-4
    # one compiled graph per (state shape, input shapes), reused across the steps and the control change
    assert len(pred._compiled) == 1
    # a kept trajectory is not overwritten by later steps (outputs are copied out of the request)
    assert not torch.equal(out[:, 1], out[:, 2])
    # concurrent rollouts (a server's threads) each get their own infer request from the pool
    results: list[torch.Tensor] = []
    threads = [threading.Thread(target=lambda: results.append(rollout(pred, x0, u))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 3 and all(torch.equal(r, out) for r in results)
    (idle,) = pred._idle.values()
    assert 1 <= len(idle) <= 3  # as many requests as calls ran at once, all returned to the pool


@pytest.mark.slow
@needs_openvino
@pytest.mark.parametrize(("precision", "unpack"), [("f32", True), ("bf16", True), ("f32", False)])
def test_openvino_multistep_matches_pytorch(trained_multistep, precision, unpack, monkeypatch):
    """The exported multi-step graph (extra-step head, flux gate, GroupNorm on its 4-D view, static
    shapes) against PyTorch eager on trained weights: exported up to the decoder's packed residuals with the
    states formed by ``write_states`` (the default), or whole with the states as its output."""
    model, x0, u = trained_multistep
    ref = rollout(model, x0, u)
    monkeypatch.setattr(runtime.OpenVINORuntime, "unpack_states", unpack)
    pred = compile_model(model, "openvino", precision)
    out = rollout(pred, x0, u)
    assert pred.backend == "openvino" and pred.k == 4 and out.shape == ref.shape
    assert (out[:, 1:] - out[:, :1]).abs().max() > 1e-3
    (compiled,) = pred._compiled.values()
    assert all(i.get_partial_shape().is_static for i in compiled.inputs)  # compiled for the state's shape
    if unpack:  # the packed residuals (B, 16k, ..) on the padded half grid
        assert [tuple(o.get_partial_shape().to_shape())[:2] for o in compiled.outputs] == [(2, 64)]
    else:  # the decoder's voxel shuffle runs as the plugin's DepthToSpace (runtime._fuse_depth_to_space)
        layers = {op.get_rt_info()["layerType"].astype(str) for op in compiled.get_runtime_model().get_ops()}
        assert "DepthToSpace" in layers
    d = out - ref
    if precision == "f32":
        assert d.abs().max() <= 1e-4
    else:
        assert d.abs().max() <= 0.05 and d.pow(2).mean().sqrt() <= 0.01


@pytest.mark.slow
@needs_openvino
def test_openvino_bf16_close_to_pytorch(trained):
    model, x0, u = trained
    ref = rollout(model, x0[:1], u[:1])
    pred = compile_model(model, "openvino", "bf16")
    with torch.inference_mode():  # how the service calls it: the graph is traced from inference tensors
        out = rollout(pred, x0[:1], u[:1])
    assert pred.backend == "openvino" and pred.precision == "bf16"
    # the CPU plugin takes a bf16 hint only on AVX-512 (emulated without AVX-512 BF16 or AMX); f32 elsewhere
    avx512 = {"avx512f", "avx512bw", "avx512vl", "avx512dq"} <= cpu_flags()
    assert pred.describe()["inference_precision"] == ("bf16" if avx512 else "f32")
    d = out - ref
    assert d.abs().max() <= 0.05 and d.pow(2).mean().sqrt() <= 0.01


@pytest.mark.slow
@needs_openvino
def test_openvino_exports_the_decoder_refinement_and_angle_columns(tiny_scene):
    """A model grown by a decoder refinement block (``decoder_refine``; trained, so the block is not the
    identity) and reading the angle columns (``angle_features``: 18 control columns) exports and matches
    PyTorch in f32."""
    model, x0, u = _trained(tiny_scene, {"steps_per_call": 2, "decoder_refine": 1, "angle_features": True})
    assert model.decoder.refine[0].body[-1].weight.abs().max() > 0
    assert model.eic.h_s.weight.shape[1] == 18 and model.eic.h_s.weight[:, 14:].abs().max() > 0
    ref = rollout(model, x0, u)
    out = rollout(compile_model(model, "openvino", "f32"), x0, u)
    assert (out[:, 1:] - out[:, :1]).abs().max() > 1e-3
    assert (out - ref).abs().max() <= 1e-4


def test_torch_backend_is_the_reference(trained):
    model, x0, u = trained
    ref = rollout(model, x0, u)
    pred = compile_model(model, "torch", "f32")
    assert pred.backend == "torch" and torch.equal(rollout(pred, x0, u), ref)
    with torch.no_grad():  # the per-call form, too
        assert torch.equal(pred(x0, u[:, 0]), model.step(x0, model.precompute(u[:, 0])))
    bf = rollout(compile_model(model, "torch", "bf16"), x0, u)
    assert 0 < (bf - ref).abs().max() <= 0.05  # autocast really ran in bf16


def test_fallback_when_openvino_is_missing(trained, monkeypatch, caplog):
    model, x0, u = trained
    monkeypatch.setattr(runtime, "openvino_available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="nemsim.inference.runtime"):
        pred = compile_model(model, "openvino", "f32")
    assert pred.backend == "torch" and "not installed" in pred.fallback_reason
    assert "not installed" in caplog.text
    assert torch.equal(rollout(pred, x0, u), rollout(model, x0, u))


@needs_openvino
def test_fallback_when_the_export_fails(trained, monkeypatch, caplog):
    model, x0, u = trained

    def broken(self, *args, **kwargs):
        raise RuntimeError("unsupported operation\nmore detail")

    monkeypatch.setattr(runtime.OpenVINORuntime, "_compile", broken)
    pred = compile_model(model, "openvino", "f32")
    with caplog.at_level(logging.WARNING, logger="nemsim.inference.runtime"):
        out = rollout(pred, x0, u)
    assert pred.backend == "torch"
    assert pred.fallback_reason == "openvino export failed: RuntimeError: unsupported operation"
    assert "unsupported operation" in caplog.text
    assert torch.equal(out, rollout(model, x0, u))


class _TwoStep(nn.Module):
    """A k = 2 stand-in: predict(x, cache) -> (B, 2, ...) = (x + u0, x + 2 u0)."""

    class config:  # noqa: N801 -- attribute access like a dataclass config
        steps_per_call = 2

    def precompute(self, u):
        return {"u": u}

    def predict(self, x, cache):
        a = cache["u"][:, :1, None, None, None]  # (B, 1, 1, 1, 1)
        return torch.stack([x + a, x + 2 * a], dim=1)  # (B, 2, 2, D, H, W)

    def forward(self, x, u):
        return self.predict(x, self.precompute(u))[:, 0]


def test_multi_step_models_go_through_predict():
    pred = compile_model(_TwoStep(), "torch")
    x, u = torch.zeros(1, 2, 3, 3, 3), torch.ones(1, 14)
    out = pred.predict(x, pred.precompute(u))
    assert pred.k == 2 and out.shape == (1, 2, 2, 3, 3, 3) and out[0, 1].max() == 2
    with pytest.raises(ValueError, match="steps_per_call"):
        pred.step(x, pred.precompute(u))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"backend": "onnx"}, "unknown backend 'onnx'"), ({"precision": "fp16"}, "unknown precision 'fp16'"),
     ({"threads": 0}, "threads must be >= 1")],  # fmt: skip
)
def test_bad_options_name_the_choices(kwargs, match):
    with pytest.raises(ValueError, match=match):
        compile_model(nn.Identity(), **kwargs)


@pytest.mark.slow
@needs_openvino
def test_bench_rollout_has_openvino_variants(trained):
    from bench.rollout_speed import bench_rollout

    model, x0, _ = trained
    rep = bench_rollout(model, x0[0], steps=3, repeats=1, variants=["fp32", "openvino-f32"])
    assert rep["variants"]["openvino-f32"]["max_abs_diff_vs_fp32"] <= 1e-4
    assert all(0 < v["cpu_median_s"] and len(v["cpu_times_s"]) == 1 for v in rep["variants"].values())


@pytest.mark.slow
@needs_openvino
def test_bench_rollout_int8_variant_quantizes_the_graph(trained, monkeypatch):
    """The int8 lever (NNCF post-training quantization) runs and is measured against fp32: its graph holds
    FakeQuantize/quantized nodes, and its trajectory differs from fp32 (quantization is not exact)."""
    pytest.importorskip("nncf")
    import bench.rollout_speed as rs
    from bench.rollout_speed import bench_rollout

    monkeypatch.setattr(rs, "INT8_CALIBRATION_ROLLOUTS", 3)
    model, x0, _ = trained
    rep = bench_rollout(model, x0[0], steps=3, repeats=1, variants=["fp32", "openvino-int8"])
    assert 0 < rep["variants"]["openvino-int8"]["max_abs_diff_vs_fp32"] < 2.0


def test_bench_rollout_int8_needs_nncf(trained, monkeypatch):
    import sys

    from bench.rollout_speed import bench_rollout

    monkeypatch.setitem(sys.modules, "nncf", None)  # as if not installed
    model, x0, _ = trained
    with pytest.raises(ValueError, match="pip install nncf"):
        bench_rollout(model, x0[0], steps=3, repeats=1, variants=["fp32", "openvino-int8"])
