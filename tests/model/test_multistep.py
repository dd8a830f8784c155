"""Multi-step NEMSim (steps_per_call = k): shapes, k = 1 unchanged, the extra-step head, gradients."""

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


def _model(rules, k: int, seed: int = 0) -> NEMSim:
    torch.manual_seed(seed)
    return NEMSim(rules, NEMSimConfig(steps_per_call=k)).eval()


@pytest.mark.parametrize("k", [1, 3])
def test_predict_shape_and_step_is_first_state(rules, k):
    model = _model(rules, k)
    x, u = _inputs()
    with torch.no_grad():
        cache = model.precompute(u)
        out = model.predict(x, cache)
        first = model.step(x, cache)
        fwd = model(x, u, all_steps=True)
    assert out.shape == (2, k, *TINY.state_shape)
    assert torch.equal(out[:, 0], first)
    assert out.abs().max() <= 1.0  # every predicted state is projected onto [-1, 1]
    torch.testing.assert_close(fwd, out)  # forward uses the unfused MRC form: equal up to rounding
    assert model(x, u).shape == x.shape
    with torch.no_grad():
        states, aux = model.predict(x, cache, return_aux=True)
        first, aux1 = model.step(x, cache, return_aux=True)
    assert torch.equal(states, out) and torch.equal(first, out[:, 0])
    assert torch.equal(aux["lambda"], aux1["lambda"])


def test_k1_is_the_one_step_model(rules):
    """k = 1 builds no extra parameters and predict == step[:, None] exactly."""
    model = _model(rules, 1)
    default = NEMSim(rules)
    assert set(model.state_dict()) == set(default.state_dict())
    assert not any("extra" in name for name in model.state_dict())
    x, u = _inputs()
    with torch.no_grad():
        cache = model.precompute(u)
        assert torch.equal(model.predict(x, cache), model.step(x, cache)[:, None])


def test_first_state_shared_and_zero_head_extrapolates_linearly(rules):
    """The k-step model's first state is the one-step model's (same shared weights); at initialization the
    extra-step head is zero, so x̂_{t+j} = clamp(x_t + j·r_1, -1, 1)."""
    one, three = _model(rules, 1), _model(rules, 3, seed=5)
    missing, unexpected = three.load_state_dict(one.state_dict(), strict=False)
    assert sorted(missing) == ["decoder.extra.bias", "decoder.extra.weight"] and not unexpected
    x, u = _inputs()
    with torch.no_grad():
        ref = one.step(x, one.precompute(u))
        out = three.predict(x, three.precompute(u))
        r1 = dataclasses.replace(one.config, clamp_output=False)
        raw = NEMSim(rules, r1).eval()
        raw.load_state_dict(one.state_dict())
        residual = raw.step(x, raw.precompute(u)) - x  # (B, 2, D, H, W)
    assert torch.equal(out[:, 0], ref)
    for j in (1, 2):
        torch.testing.assert_close(out[:, j], (x + (j + 1) * residual).clamp(-1, 1), atol=1e-5, rtol=0)


def test_gradients_reach_every_head(rules):
    model = _model(rules, 3).train()
    # zero-initialized last layers block gradients at step 0 by design (see test_model); move them off zero
    with torch.no_grad():
        for layer in (model.eic.h_rate[-1], model.mac.ctx_out, model.decoder.extra):
            layer.weight.normal_(0, 0.1)
            layer.bias.normal_(0, 0.1)
    x, u = _inputs()
    x = 0.5 * x  # away from the projection's saturation
    target = torch.zeros(2, 3, *TINY.state_shape)
    loss = ((model(x, u, all_steps=True) - target) ** 2).mean()
    loss.backward()
    no_grad = [n for n, p in model.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert not no_grad, no_grad
    # the extra-step head gets gradient only from the states it predicts
    model.zero_grad()
    ((model(x, u, all_steps=True)[:, 0] - target[:, 0]) ** 2).mean().backward()
    assert model.decoder.extra.weight.grad is None or not torch.any(model.decoder.extra.weight.grad != 0)


@pytest.mark.parametrize("bad", [0, -1, 2.5])
def test_bad_steps_per_call(rules, bad):
    with pytest.raises(ValueError, match="steps_per_call"):
        NEMSim(rules, NEMSimConfig(steps_per_call=bad))


def test_deepcopy_after_inference(rules):
    """A model that has run inference (oneDNN-packed weights cached) can still be deep-copied."""
    import copy

    model = _model(rules, 1)
    x, u = _inputs()
    with torch.no_grad():
        y = model(x, u)
        twin = copy.deepcopy(model)
        assert torch.equal(twin(x, u), y)


@pytest.mark.parametrize("k_old", [1, 3])
def test_extend_steps_keeps_the_first_states_and_continues_the_trend(rules, k_old):
    """A k_old head grown to k_new = 5 (``extend_steps``): the first k_old predicted states are those of the
    k_old model; the added corrections continue E_k_old linearly (zero from k = 1: r_j = j r_1)."""
    from nemsim.model.decoder import extend_steps

    old = _model(rules, k_old, seed=1)
    with torch.no_grad():  # a trained-like head: nonzero corrections
        if k_old > 1:
            old.decoder.extra.weight.normal_(0, 0.05)
            old.decoder.extra.bias.normal_(0, 0.01)
    new = _model(rules, 5, seed=2)
    state = extend_steps(old.state_dict(), new.state_dict())
    new.load_state_dict(state)
    x, u = _inputs()
    with torch.no_grad():
        a = old.predict(x, old.precompute(u))
        b = new.predict(x, new.precompute(u))
    torch.testing.assert_close(b[:, :k_old], a)
    w_old, w_new = old.state_dict().get("decoder.extra.weight"), new.decoder.extra.weight
    if w_old is None:
        assert not w_new.any()
    else:
        torch.testing.assert_close(w_new[-16:], w_old[-16:] * (4 / (k_old - 1)))
    with pytest.raises(ValueError, match="does not extend"):
        extend_steps(new.state_dict(), _model(rules, 3).state_dict())
