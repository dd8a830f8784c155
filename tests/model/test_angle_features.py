"""Angle-feature columns (NEMSimConfig.angle_features): the values of the module docstring computed by hand,
absent by default, exact when grown onto a trained model (``widen_control_inputs``), and trainable from
there."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from nemsim.controls import ANGLE_CONTROLS, N_CONTROLS, control_index
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.model.angle_features import angle_features, widen_control_inputs
from nemsim.scenes import TINY

torch.set_num_threads(1)
ANGLE_IDX = [control_index(n) for n in ANGLE_CONTROLS]


def _inputs(batch: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(batch, *TINY.state_shape, generator=g) * 2 - 1  # (B, 2, D, H, W)
    u = torch.rand(batch, N_CONTROLS, generator=g) * 2 - 1  # (B, 14)
    return x, u


def test_hand_values():
    """Box ends and centre: s(m) = sqrt(2 / (m + 3)), a = +1 at the design minimum of m, -1 at its maximum;
    the centre m = 10 (Cl, range 0..20) and m = 1,525 (ions, 50..3000) by hand."""
    u = torch.zeros(3, N_CONTROLS, dtype=torch.float64)
    u[0, ANGLE_IDX], u[2, ANGLE_IDX] = -1.0, 1.0
    a = angle_features(u)  # (3, 4)
    s = lambda m: math.sqrt(2.0 / (m + 3.0))  # noqa: E731
    cl_mid = 2 * (s(10) - s(20)) / (s(0) - s(20)) - 1  # (0.39223 - 0.29488) / 0.52162 * 2 - 1 = -0.6267
    ion_mid = 2 * (s(1525) - s(3000)) / (s(50) - s(3000)) - 1  # (0.036179 - 0.025807) / 0.168453 * 2 - 1
    assert cl_mid == pytest.approx(-0.6267, abs=1e-4) and ion_mid == pytest.approx(-0.8768, abs=1e-4)
    torch.testing.assert_close(a[0], torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(a[2], -torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(a[1], torch.tensor([cl_mid, ion_mid, ion_mid, ion_mid], dtype=torch.float64))


def test_broader_is_larger_and_only_angles_count():
    """a falls as m rises (a narrower launch), is clamped at m = 0 below the box, reads no other control."""
    u = torch.zeros(5, N_CONTROLS, dtype=torch.float64)
    u[:, ANGLE_IDX] = torch.tensor([-3.0, -1.0, -0.5, 0.5, 1.0], dtype=torch.float64)[:, None]
    a = angle_features(u)
    assert (a[1:-1] > a[2:]).all() and (a[0] >= a[1]).all() and torch.isfinite(a).all()
    v = u.clone()
    v[:, [i for i in range(N_CONTROLS) if i not in ANGLE_IDX]] = 0.7
    torch.testing.assert_close(angle_features(v), a)


def test_default_builds_no_angle_columns(rules):
    model = NEMSim(rules)
    assert model.eic.h_s.weight.shape[1] == N_CONTROLS
    assert NEMSim(rules, NEMSimConfig(angle_features=True)).eic.h_s.weight.shape[1] == N_CONTROLS + 4


@pytest.mark.parametrize("parts", [{}, {"steps_per_call": 3}, {"use_eic": False}, {"use_mrc": False}])
def test_widened_model_predicts_what_its_parent_did(rules, parts):
    """A parent with every weight perturbed (as a trained model's are), widened: the same states, up to float
    rounding, for the full model, k = 3, and the two ablations whose control inputs are laid out otherwise."""
    torch.manual_seed(0)
    parent = NEMSim(rules, NEMSimConfig(**parts)).eval()
    with torch.no_grad():
        for p in parent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    grown = NEMSim(rules, dataclasses.replace(parent.config, angle_features=True)).eval()
    state = widen_control_inputs(parent.state_dict(), grown.state_dict(), parent.config.context_dim)
    grown.load_state_dict(state)  # strict: every tensor fits
    x, u = _inputs()
    with torch.no_grad():
        want = parent.predict(x, parent.precompute(u))
        got = grown.predict(x, grown.precompute(u))
    assert (want - x[:, None]).abs().max() > 1e-3
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5)  # a wider matmul sums in another order


def test_angle_columns_train(rules):
    """Grown from a trained-like parent, the zero columns receive a gradient."""
    torch.manual_seed(1)
    parent = NEMSim(rules)
    with torch.no_grad():  # trained-like: the zero-initialized heads pass gradients on
        for p in parent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    grown = NEMSim(rules, dataclasses.replace(parent.config, angle_features=True))
    ctx = parent.config.context_dim
    grown.load_state_dict(widen_control_inputs(parent.state_dict(), grown.state_dict(), ctx))
    x, u = _inputs()
    target = (x + 0.1 * torch.randn_like(x)).clamp(-1, 1)
    torch.nn.functional.mse_loss(grown(x, u), target).backward()
    cols = grown.eic.h_s.weight
    assert cols.grad is not None and cols.grad[:, N_CONTROLS:].abs().sum() > 0
    assert cols[:, N_CONTROLS:].abs().max() == 0


def test_widen_refuses_another_layout(rules):
    old = {"w": torch.zeros(3, 10), "b": torch.zeros(3)}
    with pytest.raises(ValueError, match="does not widen"):
        widen_control_inputs(old, {"w": torch.zeros(3, 15), "b": torch.zeros(3)}, 24)
    with pytest.raises(ValueError, match="does not widen"):
        widen_control_inputs(old, {"w": torch.zeros(3, 14), "b": torch.zeros(3)}, 24)  # 10 < 14 controls


def test_init_from_widens_a_checkpoint_without_the_columns(tmp_path, rules, tiny_scene):
    """``nemsim train --init-from`` of a checkpoint without the columns into a model with them: the stored
    weights in place, the columns at zero, the same predictions."""
    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.training.run import init_from

    torch.manual_seed(2)
    parent = NEMSim(rules).eval()
    with torch.no_grad():
        for p in parent.parameters():
            p.add_(0.05 * torch.randn_like(p))
    path = save_checkpoint(tmp_path / "parent.pt", parent, model_name="nemsim",
                           model_config=dataclasses.asdict(parent.config), scene=tiny_scene, rules=rules)
    grown = NEMSim(rules, dataclasses.replace(parent.config, angle_features=True)).eval()
    init_from(grown, path, "nemsim", rules, tiny_scene)
    assert grown.mac.ctx_state.weight[:, 24 + N_CONTROLS:].abs().max() == 0
    x, u = _inputs()
    with torch.no_grad():
        want = parent.predict(x, parent.precompute(u))
        torch.testing.assert_close(grown.predict(x, grown.precompute(u)), want, rtol=0, atol=1e-5)
