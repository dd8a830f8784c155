"""Baselines: shapes, gradients, parameter counts (paper scene), registry, RuleFeat (+Prior) deltas."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from nemsim.baselines import CNO3d, CNOConfig, DeepONet3d, DeepONetConfig, FNO3d, FNOConfig, UNO3d, UNOConfig
from nemsim.evaluation.metrics import count_params as count_trainable
from nemsim.registry import available_models, build_model
from nemsim.scenes import PAPER, TINY

BASELINES = ("convlstm", "fno", "uno", "cno", "deeponet", "cno-prior", "deeponet-prior")
HAS_NEURALOP = importlib.util.find_spec("neuralop") is not None

# exact trainable counts (complex Fourier weights as two reals); the paper's values in the comments
EXPECTED = {
    "convlstm": 634_098,  # 0.634 M
    "fno": 1_357_912,  # 1.358 M
    "uno": 2_440_378,  # 2.432 M
    "cno": 1_733_908,  # 1,733,908
    "deeponet": 1_721_202,  # 1,720,162
    "cno-prior": 1_750_876,  # 1,750,876
    "deeponet-prior": 1_736_914,  # 1,735,874
}
PAPER_M = {"convlstm": 0.634, "fno": 1.358, "uno": 2.432, "cno": 1.734, "deeponet": 1.720}


def test_registry_lists_baselines():
    assert set(BASELINES) <= set(available_models())


@pytest.mark.parametrize("name", ["convlstm", "fno", "uno", "cno", "deeponet"])
def test_forward_backward_tiny(name, tiny_batch):
    torch.manual_seed(0)
    model = build_model(name, TINY, None)
    x, u = tiny_batch
    y = model(x, u)
    assert y.shape == x.shape and torch.isfinite(y).all()
    (y - x).square().mean().backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


@pytest.mark.parametrize("name", ["cno-prior", "deeponet-prior"])
def test_prior_forward_backward_tiny(name, rules, tiny_batch):
    torch.manual_seed(0)
    model = build_model(name, TINY, rules)
    x, u = tiny_batch
    y = model(x, u)
    assert y.shape == x.shape and torch.isfinite(y).all()
    y.square().mean().backward()
    assert model.rule_proj[0].weight.grad is not None and model.rule_proj[0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("name", BASELINES)
def test_param_counts_paper(name, shape_rules):
    model = build_model(name, PAPER, shape_rules)  # counts do not depend on the grid: no forward needed
    n = count_trainable(model)
    assert n == EXPECTED[name]
    base = name.replace("-prior", "")
    assert abs(n / 1e6 - PAPER_M[base]) / PAPER_M[base] < 0.10 + (0.02 if name.endswith("prior") else 0)


def test_prior_deltas_exact(shape_rules):
    cno = count_trainable(CNO3d(CNOConfig()))
    cno_p = count_trainable(CNO3d(CNOConfig(rulefeat=True), shape_rules))
    don = count_trainable(DeepONet3d(DeepONetConfig()))
    don_p = count_trainable(DeepONet3d(DeepONetConfig(rulefeat=True), shape_rules))
    assert cno_p - cno == 16_968
    assert don_p - don == 15_712
    assert cno == 1_733_908 and cno_p == 1_750_876  # the paper's exact numbers


def test_cno_prior_widens_lifting_from_13_to_21(shape_rules):
    assert CNO3d(CNOConfig()).lift.inner.in_channels == 13
    assert CNO3d(CNOConfig(rulefeat=True), shape_rules).lift.inner.in_channels == 21


@pytest.mark.parametrize(
    "cls,cfg", [(FNO3d, FNOConfig(backend="native")), (UNO3d, UNOConfig(backend="native"))]
)
def test_native_fourier_backend_tiny(cls, cfg, tiny_batch):
    model = cls(cfg)
    x, u = tiny_batch
    y = model(x, u)
    assert y.shape == x.shape
    y.mean().backward()
    assert model.backend == "native"


@pytest.mark.skipif(not HAS_NEURALOP, reason="optional extra neuraloperator not installed")
@pytest.mark.parametrize("cls,cfg_cls", [(FNO3d, FNOConfig), (UNO3d, UNOConfig)])
def test_backends_have_equal_counts(cls, cfg_cls):
    a = count_trainable(cls(cfg_cls(backend="neuralop")))
    b = count_trainable(cls(cfg_cls(backend="native")))
    assert a == b


def test_bad_inputs_raise(tiny_batch):
    model = build_model("fno", TINY, None)
    x, u = tiny_batch
    with pytest.raises(ValueError, match="controls"):
        model(x, u[:, :13])
    with pytest.raises(ValueError, match="state"):
        model(x[:, :1], u)
    with pytest.raises(ValueError, match="backend"):
        FNO3d(FNOConfig(backend="jax"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="rules"):
        CNO3d(CNOConfig(rulefeat=True), None)
