"""Decoder refinement blocks (NEMSimConfig.decoder_refine): absent by default, the identity when grown onto a
trained model, and trainable from there."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nemsim.model import NEMSim, NEMSimConfig
from nemsim.scenes import TINY


def _inputs(batch: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, *TINY.state_shape, generator=g) * 2 - 1  # (B, 2, D, H, W)
    u = torch.rand(batch, 14, generator=g) * 2 - 1  # (B, 14)
    return x, u


def test_default_builds_no_refinement(rules):
    assert not any("refine" in name for name in NEMSim(rules).state_dict())


@pytest.mark.parametrize("k", [1, 3])
def test_grown_model_predicts_what_its_parent_did(rules, k):
    """A parent whose weights are all perturbed away from their initialization (as a trained model's are),
    grown by two refinement blocks: the same k states, bit for bit up to float rounding."""
    torch.manual_seed(0)
    parent = NEMSim(rules, NEMSimConfig(steps_per_call=k)).eval()
    with torch.no_grad():
        for p in parent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    grown = NEMSim(rules, dataclasses.replace(parent.config, decoder_refine=2)).eval()
    missing, unexpected = grown.load_state_dict(parent.state_dict(), strict=False)
    assert not unexpected
    assert missing and all(name.startswith("decoder.refine.") for name in missing)
    x, u = _inputs()
    with torch.no_grad():
        want = parent.predict(x, parent.precompute(u))
        got = grown.predict(x, grown.precompute(u))
    assert want.abs().max() > 0
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)


def test_refinement_trains(rules):
    """The zero scale of each block's last GroupNorm receives a gradient, and one optimizer step makes the
    block (and so the prediction) differ from the identity."""
    torch.manual_seed(1)
    model = NEMSim(rules, NEMSimConfig(decoder_refine=1))
    x, u = _inputs()
    target = (x + 0.1 * torch.randn_like(x)).clamp(-1, 1)
    loss = torch.nn.functional.mse_loss(model(x, u), target)
    loss.backward()
    scale = model.decoder.refine[0].body[-1].weight
    assert scale.grad is not None and scale.grad.abs().sum() > 0
    before = model(x, u).detach()
    with torch.no_grad():
        scale.sub_(0.1 * scale.grad.sign())
    assert not torch.allclose(model(x, u), before)


def test_negative_refine_refused(rules):
    with pytest.raises(ValueError, match="refine"):
        NEMSim(rules, NEMSimConfig(decoder_refine=-1))
