"""``NEMSimConfig.flux_gate``: no ion flux, no change (by construction); ~1 inside the training box."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nemsim.controls import CONTROL_INDEX, HIGH, LOW, lhs_design, to_normalized
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.model.gate import GAMMA_REF, ION_FLUX_INDICES, ion_flux_gate
from nemsim.scenes import TINY


def normalized(raw: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(to_normalized(np.atleast_2d(raw))).float()


def median_raw() -> np.ndarray:
    return 0.5 * (LOW + HIGH)


@pytest.fixture(scope="module")
def pair(rules):
    """The same weights with and without the gate."""
    torch.manual_seed(0)
    plain = NEMSim(rules, NEMSimConfig(flux_gate=False)).eval()
    gated = NEMSim(rules, NEMSimConfig(flux_gate=True)).eval()
    gated.load_state_dict(plain.state_dict())
    return plain, gated


def rollout(model, x0: torch.Tensor, u: torch.Tensor, steps: int) -> torch.Tensor:
    cache = model.precompute(u)
    x = x0
    with torch.no_grad():
        for _ in range(steps):
            x = model.step(x, cache)
    return x


def initial_state() -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return (torch.rand(1, *TINY.state_shape, generator=g) * 1.6 - 0.8).float()  # (1, 2, D, H, W)


def test_zero_flux_and_ion_free_rollouts_do_not_change(pair):
    plain, gated = pair
    x0 = initial_state()
    zero = median_raw()
    zero[list(ION_FLUX_INDICES) + [CONTROL_INDEX["flux_cl"]]] = 0.0
    ion_free = median_raw()
    ion_free[list(ION_FLUX_INDICES)] = 0.0
    ion_free[CONTROL_INDEX["flux_cl"]] = 10 * HIGH[CONTROL_INDEX["flux_cl"]]
    for raw in (zero, ion_free):
        u = normalized(raw)
        assert (rollout(gated, x0, u, 5) - x0).abs().max() < 1e-6
        assert (rollout(plain, x0, u, 5) - x0).abs().max() > 1e-3  # the ungated model does change it


def test_gate_is_one_in_the_box_and_costs_nothing(pair):
    plain, gated = pair
    u = normalized(lhs_design(64, seed=3))
    g = ion_flux_gate(u.double())
    assert g.shape == (64,) and (g > 1 - 1e-8).all() and (g <= 1).all()
    corner = normalized(LOW).double()  # every flux at its lower edge
    assert float(ion_flux_gate(corner)) > 1 - 1e-8
    assert (ion_flux_gate(u) == 1.0).all()  # float32: exactly 1
    x0 = initial_state()
    uc = normalized(median_raw())
    torch.testing.assert_close(rollout(gated, x0, uc, 3), rollout(plain, x0, uc, 3), rtol=0, atol=1e-6)


@pytest.mark.parametrize("j", ION_FLUX_INDICES)
def test_gate_monotone_saturating_in_each_ion_flux(j):
    """From zero flux through the box: non-decreasing, 0 at zero, -> 1; the neutral flux does not enter."""
    flux = np.concatenate([[0.0], np.logspace(-9, -1, 60)])
    raw = np.tile(np.zeros(14), (len(flux), 1))
    raw[:, j] = flux
    raw[:, CONTROL_INDEX["flux_cl"]] = 1e-2
    g = ion_flux_gate(torch.from_numpy(to_normalized(raw)))  # float64
    assert float(g[0]) < 1e-12
    assert (g.diff() >= 0).all() and float(g[-1]) > 1 - 1e-12 and (g < 1 + 1e-15).all()
    # linear below the reference flux, as the simulator's ion count
    small = flux < 1e-2 * GAMMA_REF
    np.testing.assert_allclose(g[small].numpy(), flux[small] / GAMMA_REF, rtol=2e-2)


def test_gate_gradient():
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(4, 14, generator=gen, dtype=torch.float64) * 2 - 1
    u[:, list(ION_FLUX_INDICES)] -= 2.5  # below the box, where the gate is not saturated
    u.requires_grad_(True)
    assert torch.autograd.gradcheck(ion_flux_gate, (u,))
    ion_flux_gate(u).sum().backward()
    assert (u.grad[:, list(ION_FLUX_INDICES)] > 0).all()
    assert (u.grad[:, CONTROL_INDEX["flux_cl"]] == 0).all()


def test_gate_reaches_training_gradients(pair, rules):
    """With the gate on, the loss still trains every parameter (the gate is ~1 in the box)."""
    torch.manual_seed(0)
    model = NEMSim(rules, NEMSimConfig(flux_gate=True, kinetics="physical"))
    x0 = initial_state()
    u = normalized(median_raw())
    loss = model(x0, u).square().mean()
    loss.backward()
    missing = [
        n for n, p in model.named_parameters()
        if p.requires_grad and (p.grad is None or not torch.isfinite(p.grad).all())
    ]  # fmt: skip
    assert not missing
