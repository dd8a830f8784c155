"""The training data path on the scene's symmetry: symmetrized and folded items, the in-memory training set,
and a quarter-domain model trained end to end through the CLI."""

from __future__ import annotations

import json

import pytest
import torch

from nemsim.data.dataset import MemoryTransitions, TransitionDataset, TransitionSets
from nemsim.inference.checkpoint import load_checkpoint
from nemsim.symmetry import fold, symmetrize

STEPS = 4  # as in tests/training/conftest.py

SMALL_NET = {"stem": 4, "widths": [4, 4, 4], "latent_channels": 4, "context_dim": 4, "readout_width": 4,
             "decoder_widths": [4, 4]}


def test_items_are_symmetrized_and_folded(tiny_data, tiny_manifest):
    raw = TransitionDataset(tiny_data, tiny_manifest, "train", unroll=2)
    sym = TransitionDataset(tiny_data, tiny_manifest, "train", unroll=2, symmetrize=True)
    quarter = TransitionDataset(tiny_data, tiny_manifest, "train", unroll=2, symmetrize=True, quarter=True)
    (x, u, y), (xs, us, ys), (xq, uq, yq) = raw[3], sym[3], quarter[3]
    assert torch.equal(u, us) and torch.equal(u, uq)
    torch.testing.assert_close(xs, symmetrize(x))
    torch.testing.assert_close(ys, symmetrize(y))
    for a in (xs, ys):
        torch.testing.assert_close(a, a.flip(-1))
        torch.testing.assert_close(a, a.transpose(-1, -2))
    assert torch.equal(xq, fold(xs)) and torch.equal(yq, fold(ys))
    assert xq.shape[-2:] == (8, 8)  # the tiny scene's 15 x 15 padded field: a quadrant of 8


@pytest.mark.parametrize("unroll", [1, 3])
def test_memory_transitions_match_the_streamed_items(tiny_data, tiny_manifest, unroll):
    shape = {"unroll": unroll, "symmetrize": True, "quarter": True}
    sets = [TransitionDataset(tiny_data, tiny_manifest, "train", **shape),
            TransitionDataset(tiny_data, None, "train", **shape)]
    streamed = TransitionSets(sets)
    mem = MemoryTransitions(sets)
    assert len(mem) == len(streamed)
    assert mem.nbytes_of(sets) == mem.states.numel() * 2 and mem.states.dtype == torch.float16
    picks = [0, 7, len(mem) - 1, 11]
    x, u, y = mem.__getitems__(picks)
    for b, i in enumerate(picks):
        xs, us, ys = streamed[i]
        torch.testing.assert_close(x[b], xs, atol=1e-3, rtol=0)  # float16 storage
        torch.testing.assert_close(y[b], ys, atol=1e-3, rtol=0)
        assert torch.equal(u[b], us)


def test_quarter_model_trains_in_memory_on_symmetrized_targets(tmp_path, tiny_data, tiny_scene, rules):
    from nemsim.cli import main
    from nemsim.evaluation.rollout import rollout

    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "symmetrize_targets": True, "in_memory": True,
                               "model": {"steps_per_call": 2, "domain": "quarter", **SMALL_NET}}))
    out = tmp_path / "run"
    args = ["train", "--model", "nemsim", "--data", str(tiny_data), "--setting", "control-id", "--out",
            str(out), "--splits", str(tiny_data.parent / "splits"), "--epochs", "1", "--rollout-steps",
            str(STEPS), "--config", str(cfg), "--no-progress", "--no-test"]
    assert main(args) == 0
    assert "training set in memory" in (out / "train.log").read_text()
    loaded = load_checkpoint(out / "best.pt")
    assert loaded.model.config.domain == "quarter" and loaded.model.config.full_size == 15
    x0 = torch.zeros(1, *tiny_scene.state_shape) + 0.3
    traj = rollout(loaded.model, x0, torch.zeros(1, 14), steps=STEPS)
    assert traj.shape == (1, STEPS + 1, *tiny_scene.state_shape)
    torch.testing.assert_close(traj[:, 1:], symmetrize(traj[:, 1:]), atol=0, rtol=0)
