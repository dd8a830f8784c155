"""``NEMSimConfig.control_saturation``: the learned parts read saturated controls outside the box, the
ion-flux gate the true ones; inside the box nothing changes, bit for bit."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nemsim.controls import CONTROL_INDEX, HIGH, LOW, lhs_design, to_normalized
from nemsim.evaluation.rollout import rollout
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.model.gate import ION_FLUX_INDICES
from nemsim.model.saturation import CONTROL_SATURATION, check_saturation, saturate_controls, saturation_point
from nemsim.scenes import TINY

KNEE, LIMIT = CONTROL_SATURATION


def _pair(rules, **cfg) -> tuple[NEMSim, NEMSim]:
    """The same (perturbed, so every head is non-zero) weights without and with saturation."""
    torch.manual_seed(0)
    off = NEMSim(rules, NEMSimConfig(control_saturation=None, **cfg)).eval()
    with torch.no_grad():
        for p in off.parameters():
            p.add_(0.05 * torch.randn_like(p))
    on = NEMSim(rules, NEMSimConfig(**cfg)).eval()
    on.load_state_dict(off.state_dict())
    return off, on


def _x0(batch: int = 1) -> torch.Tensor:
    from bench.stress import initial_state

    return torch.as_tensor(initial_state(TINY))[None].repeat(batch, 1, 1, 1, 1).float()


@pytest.mark.parametrize(("KNEE", "LIMIT"), [CONTROL_SATURATION, (0.5, 1.0), (0.0, 0.5)])
def test_identity_in_the_box_then_bounded_and_increasing(KNEE, LIMIT):  # noqa: N803
    g = torch.Generator().manual_seed(0)
    inside = torch.rand(1000, 14, generator=g) * 2 * (1 + KNEE) - (1 + KNEE)
    inside[0] = 1.0 + KNEE
    inside[1] = -1.0
    assert torch.equal(saturate_controls(inside, KNEE, LIMIT), inside)
    line = torch.linspace(-60.0, 60.0, 240_001, dtype=torch.float64)[:, None].expand(-1, 14)
    s = saturate_controls(line, KNEE, LIMIT)[:, 0]
    assert float(s.abs().max()) <= 1.0 + LIMIT
    assert bool((s.diff() >= 0).all())  # non-decreasing: a larger control is never read as a smaller one
    assert float(s.diff().max()) <= float(line[1, 0] - line[0, 0]) * (1 + 1e-9)  # slope <= 1: continuous
    far = torch.tensor([[1e6] * 14], dtype=torch.float64)
    assert float(saturate_controls(far, KNEE, LIMIT)[0, 0]) == pytest.approx(1.0 + LIMIT)
    hard = saturate_controls(line, 0.25, 0.25)[:, 0]
    assert float(hard.max()) == 1.25 and float(hard.min()) == -1.25
    # gradients stay finite everywhere (inverse design differentiates through the controls)
    u = torch.tensor([[0.3, -1.2, 2.0, -9.0, 1.5, 0.0, 1.0, -1.0, 3.0, -3.0, 0.9, 1.1, 40.0, -0.5]],
                     dtype=torch.float64, requires_grad=True)
    saturate_controls(u, KNEE, LIMIT).sum().backward()
    assert u.grad is not None and torch.isfinite(u.grad).all()
    assert saturation_point(100.0, KNEE, LIMIT) == pytest.approx(LIMIT)
    assert saturation_point(KNEE, KNEE, LIMIT) == KNEE
    assert saturation_point(0.5 * KNEE, KNEE, LIMIT) == 0.5 * KNEE
    if LIMIT > KNEE:  # the smooth form: strictly between the knee and both the given distance and the limit
        assert KNEE < saturation_point(KNEE + 0.3, KNEE, LIMIT) < min(KNEE + 0.3, LIMIT)
    else:  # a hard clamp
        assert saturation_point(KNEE + 0.3, KNEE, LIMIT) == KNEE


def test_config_default_and_validation(rules):
    assert NEMSimConfig.from_dict({"steps_per_call": 3}).control_saturation == CONTROL_SATURATION
    assert NEMSimConfig.from_dict({"control_saturation": None}).control_saturation is None
    assert NEMSimConfig.from_dict({"control_saturation": [0.0, 0.5]}).control_saturation == (0.0, 0.5)
    for bad in ((0.5, 0.2), (-0.1, 1.0), (0.0, float("inf")), (1.0,)):
        with pytest.raises(ValueError, match="control_saturation"):
            check_saturation(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="control_saturation"):
        NEMSim(rules, NEMSimConfig(control_saturation=(1.0, 0.5)))


@pytest.mark.parametrize("k", [1, 3])
def test_in_box_predictions_are_bit_identical(rules, k):
    off, on = _pair(rules, steps_per_call=k, flux_gate=True)
    u = torch.from_numpy(to_normalized(lhs_design(6, seed=5))).float()  # (6, 14) in the box
    u[0] = torch.from_numpy(to_normalized(LOW[None])).float()[0]  # the box's corners too
    u[1] = torch.from_numpy(to_normalized(HIGH[None])).float()[0]
    x0 = _x0(6)
    with torch.no_grad():
        for fused in (True, False):  # inference and training paths
            a, b = off.precompute(u, fused=fused), on.precompute(u, fused=fused)
            assert torch.equal(a["u"], b["u"]) and torch.equal(a["gate"], b["gate"])
            assert torch.equal(off.predict(x0, a), on.predict(x0, b))
        assert torch.equal(off(x0, u, all_steps=True), on(x0, u, all_steps=True))
    assert torch.equal(rollout(off, x0, u, 7), rollout(on, x0, u, 7))


def test_far_controls_are_read_at_the_saturation_point(rules):
    off, on = _pair(rules)  # no gate: the network's answer alone
    centre = torch.zeros(1, 14)
    j = CONTROL_INDEX["energy_mean_ar_plus"]
    far, farther, limit = centre.clone(), centre.clone(), centre.clone()
    far[0, j], farther[0, j], limit[0, j] = 12.0, 1e4, 1.0 + LIMIT
    x0 = _x0()
    r_limit = rollout(off, x0, limit, 4)  # the network reading the control at the limit
    torch.testing.assert_close(rollout(on, x0, far, 4), r_limit, atol=1e-5, rtol=0)
    assert torch.equal(rollout(on, x0, farther, 4), r_limit)
    assert (rollout(off, x0, farther, 4) - r_limit).abs().max() > 1e-2  # unsaturated it runs away


def test_the_gate_reads_the_true_controls(rules):
    _, on = _pair(rules, flux_gate=True)
    x0 = _x0()
    raw = 0.5 * (LOW + HIGH)
    raw[list(ION_FLUX_INDICES)] = 0.0  # zero ion flux: far below the box on the log axis
    u = torch.from_numpy(to_normalized(raw[None])).float()
    cache = on.precompute(u)
    assert float(cache["gate"].abs().max()) < 1e-9  # the gate sees zero flux ...
    assert float(cache["u"][0, list(ION_FLUX_INDICES)].min()) >= -(1.0 + LIMIT)  # ... the network a near one
    assert (rollout(on, x0, u, 20) - x0).abs().max() <= 1e-6  # still exactly no change
    one = raw.copy()
    one[CONTROL_INDEX["flux_cl_plus"]] = 0.5 * (LOW + HIGH)[CONTROL_INDEX["flux_cl_plus"]]  # Cl+ ions only
    u1 = torch.from_numpy(to_normalized(one[None])).float()
    c1 = on.precompute(u1)
    assert float(c1["gate"].min()) > 0.99  # ions present: the update is not gated off
    assert float(c1["u"][0, CONTROL_INDEX["flux_ar_plus"]]) >= -(1.0 + LIMIT)  # zero Ar+ read near the box


def test_runtime_and_inverse_design_paths_saturate(rules):
    from nemsim.analysis.inverse import rollout_to
    from nemsim.inference.runtime import compile_model

    off, on = _pair(rules, steps_per_call=3)
    x0 = _x0()
    u = torch.zeros(1, 14)
    u[0, CONTROL_INDEX["flux_cl"]] = -30.0
    lim = u.clone()
    lim[0, CONTROL_INDEX["flux_cl"]] = -(1.0 + LIMIT)
    ref = rollout(off, x0, lim, 5)  # the network reading the control at the limit
    pred = compile_model(on, "torch", "f32")
    with torch.inference_mode():
        torch.testing.assert_close(rollout(pred, x0, u, 5), ref, atol=1e-6, rtol=0)
    with torch.no_grad():
        torch.testing.assert_close(rollout_to(on, x0[0], u, 5), ref[:, -1], atol=1e-6, rtol=0)
    assert dataclasses.replace(on.config, control_saturation=None) == off.config
