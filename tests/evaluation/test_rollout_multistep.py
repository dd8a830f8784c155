"""Rollout of multi-step models: every state returned, chunks of k calls that never span a control change."""

from __future__ import annotations

import math

import pytest
import torch

from nemsim.evaluation.rollout import rollout, steps_per_call
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.scenes import TINY


def _model(rules, k):
    torch.manual_seed(0)
    # the chunk protocol on its own: the monotone projection is off here (tests/model/test_monotone.py)
    model = NEMSim(rules, NEMSimConfig(steps_per_call=k, monotone_eps=None)).eval()
    with torch.no_grad():  # a non-zero extra-step head, so the k states are not a linear extrapolation
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return model


def _chunked_reference(model, x0, u, chunks):
    """The trajectory by hand: predict(x, precompute(u_t))[:, :n] for each (t, n) in chunks."""
    states, x = [x0], x0
    with torch.no_grad():
        for t, n in chunks:
            out = model.predict(x, model.precompute(u[:, t]))[:, :n]
            states.extend(out.unbind(1))
            x = out[:, -1]
    return torch.stack(states, dim=1)


@pytest.mark.parametrize("k", [1, 3])
def test_constant_controls_match_per_chunk_predict(rules, k):
    model = _model(rules, k)
    assert steps_per_call(model) == k
    T = 7
    x0 = (torch.rand(2, *TINY.state_shape) * 2 - 1) * 0.9
    u = torch.rand(2, 14) * 2 - 1
    calls = []
    orig = model._latent_update  # every network call (predict, or the fused predict_into) runs it once
    model._latent_update = lambda *a: calls.append(1) or orig(*a)
    seen = []
    traj = rollout(model, x0, u, T, on_step=lambda t, x: seen.append(t))
    n_calls = len(calls)
    assert traj.shape == (2, T + 1, *TINY.state_shape)
    assert torch.equal(traj[:, 0], x0) and seen == list(range(1, T + 1))
    chunks = [(t, min(k, T - t)) for t in range(0, T, k)]
    torch.testing.assert_close(traj, _chunked_reference(model, x0, u[:, None].expand(2, T, 14), chunks))
    assert n_calls == math.ceil(T / k)  # one network call per k states
    last = rollout(model, x0, u, T, keep=False)
    torch.testing.assert_close(last, traj[:, -1])


def test_recipe_chunks_split_at_control_changes(rules):
    """T = 7, k = 3, controls change at t = 4: calls at t = 0 (3 states), 3 (1 state), 4 (3 states)."""
    model = _model(rules, 3)
    T = 7
    x0 = (torch.rand(1, *TINY.state_shape) * 2 - 1) * 0.9
    a, b = torch.rand(1, 14) * 2 - 1, torch.rand(1, 14) * 2 - 1
    u = torch.cat([a[:, None].expand(1, 4, 14), b[:, None].expand(1, 3, 14)], dim=1)  # (1, 7, 14)
    traj = rollout(model, x0, u)
    assert traj.shape[1] == T + 1
    torch.testing.assert_close(traj, _chunked_reference(model, x0, u, [(0, 3), (3, 1), (4, 3)]))
    wrong = _chunked_reference(model, x0, u, [(0, 3), (3, 3), (6, 1)])  # a chunk across the change differs
    assert not torch.allclose(traj[:, 5:], wrong[:, 5:])


def test_one_step_models_have_k1():
    class Plain(torch.nn.Module):
        def forward(self, x, u):
            return x + 0.1

    assert steps_per_call(Plain()) == 1
    assert rollout(Plain(), torch.zeros(1, 2, 3, 3, 3), torch.zeros(1, 14), 4).shape[1] == 5
