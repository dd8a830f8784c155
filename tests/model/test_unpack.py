"""``nemsim.model.unpack.write_states``: the fused inference path of NEMSim's last decoder step gives exactly
the states of ``predict``, at k = 1 and k > 1, with the flux gate closed or half open, into strided
destinations."""

from __future__ import annotations

import pytest
import torch

from nemsim.evaluation.rollout import rollout
from nemsim.model.unpack import write_states

torch.set_num_threads(1)


def _model(tiny_scene, k: int):
    """NEMSim on `tiny` with every head non-zero (the zero-initialized extra-step head gets random
    weights)."""
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, compile_rules(load_rules()),
                        {"steps_per_call": k, "flux_gate": True}).eval()
    with torch.no_grad():
        for p in model.decoder.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


@pytest.mark.parametrize("k", [1, 4])
def test_predict_into_matches_predict(tiny_scene, k):
    from bench.stress import initial_state

    model = _model(tiny_scene, k)
    x = torch.as_tensor(initial_state(tiny_scene))[None].repeat(3, 1, 1, 1, 1)  # (3, 2, D, H, W)
    x = (x + 0.3 * torch.randn(x.shape)).clamp(-1, 1)
    u = torch.rand(3, 14) * 2 - 1
    with torch.inference_mode():
        cache = model.precompute(u)
        cache["gate"] = cache["gate"].clone()
        cache["gate"][1] = 0.0  # as at zero ion flux: the gate closes, the states stay x
        cache["gate"][2] = 0.5  # and a partly open one
        ref = model.predict(x, cache)  # (3, k, 2, D, H, W)
        buf = torch.full((3, k + 2, *x.shape[1:]), float("nan"))  # a trajectory-like buffer: strided slice
        out = model.predict_into(x, cache, buf[:, 1 : 1 + k])
    assert out.data_ptr() == buf[:, 1].data_ptr()
    assert torch.equal(ref, out)
    assert (ref - x[:, None]).abs().max() > 1e-2  # the states move: the comparison is not vacuous
    assert torch.equal(out[1], x[1][None].expand_as(out[1]))  # the closed gate: exactly no change
    assert buf[:, 0].isnan().all() and buf[:, k + 1].isnan().all()  # nothing written outside the slice
    assert ((out >= -1) & (out <= 1)).all()  # the output clamp


def test_rollout_fused_matches_the_copy_path(tiny_scene, monkeypatch):
    """``rollout`` takes the fused path; the same rollout through ``predict`` and a copy agrees."""
    from bench.stress import initial_state
    from nemsim.model.surrogate import NEMSim

    model = _model(tiny_scene, 3)
    x0 = torch.as_tensor(initial_state(tiny_scene))[None].repeat(2, 1, 1, 1, 1)
    u = torch.rand(2, 9, 14) * 2 - 1
    with torch.inference_mode():
        fused = rollout(model, x0, u)
        monkeypatch.delattr(NEMSim, "predict_into")
        copied = rollout(model, x0, u)
    assert torch.equal(fused, copied) and (fused[:, -1] - x0).abs().max() > 1e-2


def test_quarter_rollout_fused_finish_matches_the_pass_by_pass_path(tiny_scene, monkeypatch):
    """A quarter-domain rollout writes each call's states, their diagonal mean and the monotone projection in
    one pass (``Finish``); ``predict`` (which symmetrizes itself) and the projection as a second pass give
    the same states exactly, and both move the state and project something."""
    from bench.stress import initial_state
    from nemsim.model.surrogate import NEMSim
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, compile_rules(load_rules()),
                        {"steps_per_call": 3, "flux_gate": True, "domain": "quarter",
                         "decoder_out_scale": 1.0}).eval()
    x0 = torch.as_tensor(initial_state(tiny_scene))[None].repeat(2, 1, 1, 1, 1)
    u = torch.rand(2, 8, 14, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.inference_mode():
        fused = rollout(model, x0, u)
        unprojected = rollout(model, x0, u, monotone=False)
        monkeypatch.delattr(NEMSim, "predict_into")
        passes = rollout(model, x0, u)
    assert torch.equal(fused, passes)
    assert (fused[:, -1] - x0).abs().max() > 1e-2
    assert not torch.equal(fused, unprojected)  # the projection acted: the comparison covers it


def test_write_states_refuses_other_dtypes():
    x = torch.zeros(1, 2, 4, 4, 4)
    with pytest.raises(ValueError, match="float32"):
        write_states(x, torch.zeros(1, 16, 2, 2, 2, dtype=torch.float64), None, True,
                     torch.zeros(1, 1, 2, 4, 4, 4))
