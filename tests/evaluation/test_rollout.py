"""Autoregressive rollout protocol (eq. supp_autoregressive_rollout): x0 first, predictions fed back."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from nemsim.evaluation.rollout import rollout


class AddControl(nn.Module):
    """x_{t+1} = x_t + 0.1 * u[0]: a rollout of T steps adds 0.1 * Σ_t u_t[0]."""

    def forward(self, x, u):
        return x + 0.1 * u[:, :1, None, None, None]


def test_shape_initial_state_first_and_feedback():
    x0 = torch.randn(3, 2, 5, 4, 4)
    u = torch.rand(3, 7, 14)
    traj = rollout(AddControl(), x0, u)
    assert traj.shape == (3, 8, 2, 5, 4, 4)
    assert torch.equal(traj[:, 0], x0)
    expected = x0 + 0.1 * u[:, :, 0].sum(1)[:, None, None, None, None]
    torch.testing.assert_close(traj[:, -1], expected)


def test_no_clipping():
    x0 = torch.full((1, 2, 3, 3, 3), 0.95)
    traj = rollout(AddControl(), x0, torch.ones(1, 4, 14))
    assert traj[:, -1].max() > 1.0  # predictions leave [-1, 1] untouched


def test_constant_control_steps_and_keep_false():
    x0 = torch.zeros(2, 2, 3, 3, 3)
    u = torch.ones(2, 14)
    with pytest.raises(ValueError, match="needs steps"):
        rollout(AddControl(), x0, u)
    seen = []
    last = rollout(AddControl(), x0, u, steps=5, keep=False, on_step=lambda t, x: seen.append(t))
    assert last.shape == x0.shape and seen == [1, 2, 3, 4, 5]
    torch.testing.assert_close(last, torch.full_like(x0, 0.5))


def test_steps_prefix_and_errors():
    x0 = torch.zeros(1, 2, 3, 3, 3)
    u = torch.ones(1, 10, 14)
    assert rollout(AddControl(), x0, u, steps=3).shape[1] == 4
    with pytest.raises(ValueError, match="exceeds"):
        rollout(AddControl(), x0, u, steps=11)
    with pytest.raises(ValueError, match="x0"):
        rollout(AddControl(), x0[0], u)
