"""NEMSim model: shapes, constraints of the compiled quantities, initialization, gradients, switches."""

from __future__ import annotations

import pytest
import torch

from nemsim.model import NEMSim, NEMSimConfig
from nemsim.registry import available_models, build_model, model_config
from nemsim.rules import kinetics
from nemsim.scenes import PAPER, SMALL, TINY

PAPER_PARAMS = 253_000  # the paper's figure (0.253 M)
NEMSIM_PARAMS = 212_122  # this implementation, paper configuration (checkpoints/README.md)


def n_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def inputs(scene, batch: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(batch, *scene.state_shape, generator=g) * 2 - 1).float()  # (B, 2, D, H, W)
    u = (torch.rand(batch, 14, generator=g) * 2 - 1).float()  # (B, U)
    return x, u


@pytest.fixture(scope="module")
def model(rules):
    torch.manual_seed(0)
    return NEMSim(rules).eval()


@pytest.fixture(scope="module")
def tiny_out(model):
    x, u = inputs(TINY)
    with torch.no_grad():
        return model(x, u, return_aux=True), x, u


def test_shapes_tiny(tiny_out, rules):
    (y, aux), x, _ = tiny_out
    B, E = x.shape[0], len(rules.names)
    assert y.shape == x.shape == (B, *TINY.state_shape)
    assert aux["lambda"].shape == (B, E)
    assert aux["alpha"].shape == aux["T"].shape == (B, E, 3)
    assert aux["S"].shape == (E, 3, 4)
    assert aux["P"].shape == aux["G"].shape == aux["w"].shape == (B, 3, 4)
    assert torch.isfinite(y).all()


@pytest.mark.parametrize("scene", [SMALL, PAPER], ids=["small", "paper"])
def test_shapes_larger_scenes(model, scene):
    x, u = inputs(scene, batch=1)
    with torch.no_grad():
        y = model(x, u)
    assert y.shape == x.shape


def test_padding_does_not_leak(model):
    """A state whose size is already a multiple of 4 and the odd tiny size both round-trip."""
    x = torch.zeros(1, 2, 36, 16, 16)
    with torch.no_grad():
        assert model(x, torch.zeros(1, 14)).shape == x.shape


def test_lambda_nonnegative(tiny_out):
    (_, aux), _, _ = tiny_out
    assert (aux["lambda"] >= 0).all()
    assert (aux["lambda_p"] >= 0).all() and (aux["lambda_d"] >= 0).all()


def test_alpha_on_simplex(tiny_out):
    (_, aux), _, _ = tiny_out
    a = aux["alpha"]
    assert (a >= 0).all()
    torch.testing.assert_close(a.sum(-1), torch.ones_like(a[..., 0]))
    torch.testing.assert_close(aux["T"], aux["lambda"][..., None] * a)


def test_signature_on_simplex(tiny_out):
    (_, aux), _, _ = tiny_out
    S = aux["S"]
    assert (S >= 0).all()
    torch.testing.assert_close(S.sum(-1), torch.ones_like(S[..., 0]))


def test_amplitude_bounds(tiny_out, model):
    (_, aux), _, _ = tiny_out
    w, A = aux["w"], model.mrc.capacity
    assert (w >= 0).all() and (w < A).all()
    assert ((aux["G"] > 0) & (aux["G"] < 1)).all() and (aux["P"] >= 0).all()


def test_amplitude_bound_under_huge_drive(model, rules):
    """0 ≤ w < A holds even when the drive P is enormous (saturation)."""
    x, u = inputs(TINY, batch=1)
    z, b, z_bar = model.encoder(model._pad(x))
    T = torch.full((1, len(rules.names), 3), 1e6)
    amp = model.mrc.amplitudes(z_bar, u, T, model.rules)
    assert (amp["w"] >= 0).all() and (amp["w"] < model.mrc.capacity).all()


def test_eic_reproduces_rule_intensities_at_init(tiny_out, rules):
    (_, aux), _, u = tiny_out
    expected = kinetics.formula_intensities(u, rules)
    torch.testing.assert_close(aux["lambda"], expected, rtol=1e-5, atol=1e-7)
    assert (aux["delta_l"] == 0).all()


def test_mac_initial_strength_and_zero_context(model):
    torch.testing.assert_close(model.mac.rho, torch.sigmoid(torch.tensor(-1.0)))
    assert (model.mac.ctx_out.weight == 0).all() and (model.mac.ctx_out.bias == 0).all()


def test_rules_are_buffers_not_parameters(model):
    names = {n for n, _ in model.named_parameters()}
    assert not any(n.startswith("rules.") for n in names)
    buffers = dict(model.named_buffers())
    for key in ("rules.phi", "rules.psi", "rules.alpha0", "rules.r_mech", "rules.w_src", "rules.w_sink"):
        assert key in buffers
    assert "rules.phi" in model.state_dict()


def test_gradients_reach_every_parameter(rules):
    torch.manual_seed(0)
    m = NEMSim(rules).train()
    # Zero-initialized last layers (h_rate, h_ctx) block gradients to the layers before them at step 0
    # by design; move them off zero (as one optimizer step would) before checking every parameter.
    with torch.no_grad():
        for layer in (m.eic.h_rate[-1], m.mac.ctx_out):
            layer.weight.normal_(0, 0.1)
            layer.bias.normal_(0, 0.1)
    x, u = inputs(TINY)
    loss = (m(x, u) - x.flip(2)).square().mean()
    loss.backward()
    missing = [n for n, p in m.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert not missing, f"no gradient for {missing}"


@pytest.mark.parametrize("name", ["nemsim-no-eic", "nemsim-no-mac", "nemsim-no-mrc"])
def test_ablation_switches_run_and_train(name, rules):
    torch.manual_seed(0)
    m = build_model(name, TINY, rules)
    x, u = inputs(TINY)
    y, aux = m(x, u, return_aux=True)
    assert y.shape == x.shape and (aux["lambda"] >= 0).all()
    torch.testing.assert_close(aux["alpha"].sum(-1), torch.ones_like(aux["alpha"][..., 0]))
    y.square().mean().backward()
    cfg = model_config(name, TINY)
    assert (cfg.use_eic, cfg.use_mac, cfg.use_mrc).count(False) == 1


def test_registry(rules):
    names = available_models()
    for n in ("nemsim", "nemsim-no-eic", "nemsim-no-mac", "nemsim-no-mrc"):
        assert n in names
    with pytest.raises(ValueError, match="unknown model"):
        build_model("nope", TINY, rules)
    cfg = model_config("nemsim", TINY, {"mac.kappa": 0.5, "eic": {"delta_max": 0.3}})
    assert cfg.mac.kappa == 0.5 and cfg.eic.delta_max == 0.3
    assert NEMSimConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown config key"):
        model_config("nemsim", TINY, {"not_a_field": 1})


def test_perturbed_rules_pass_through(rules):
    """A rule library with events dropped just builds and runs (perturbation is data, not a fork)."""
    import numpy as np

    mask = np.ones(len(rules.names), dtype=np.float64)
    mask[:12] = 0
    dropped = rules.replace(event_mask=mask)
    m = NEMSim(dropped).eval()
    x, u = inputs(TINY, batch=1)
    with torch.no_grad():
        _, aux = m(x, u, return_aux=True)
    assert (aux["lambda"][:, :12] == 0).all()


def test_param_count_paper_config(rules):
    """The paper reports 0.253 M trainable parameters but not every layer's width; this implementation of its
    configuration has NEMSIM_PARAMS (16 % fewer). The count is pinned so that an architecture change is
    deliberate (and the model card's figure changes with it)."""
    n = n_params(NEMSim(rules))
    assert n == NEMSIM_PARAMS
    assert n / PAPER_PARAMS == pytest.approx(0.84, abs=0.01)
    # The count does not depend on the scene: the model pads internally.
    assert n_params(build_model("nemsim", PAPER, rules)) == n_params(build_model("nemsim", SMALL, rules)) == n


def test_output_projection(rules):
    """clamp_output: the next state is clamp(x + Dec, -1, 1); off, it is the paper's x + Dec (same Dec)."""
    import dataclasses

    torch.manual_seed(0)
    on = NEMSim(rules, NEMSimConfig(decoder_out_scale=5.0)).eval()  # large steps: the projection acts
    off = NEMSim(rules, dataclasses.replace(on.config, clamp_output=False)).eval()
    off.load_state_dict(on.state_dict())
    x, u = inputs(TINY)
    with torch.no_grad():
        y_on, y_off = on(x, u), off(x, u)
    assert y_on.abs().max() <= 1.0 and y_off.abs().max() > 1.0
    assert torch.equal(y_on, y_off.clamp(-1.0, 1.0))
