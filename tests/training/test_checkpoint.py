"""Checkpoint round-trip and refusal of a mismatched rules library or scene (issue 4, item 7)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nemsim.inference.checkpoint import CheckpointMismatch, load_checkpoint, read_checkpoint, save_checkpoint
from nemsim.registry import build_model, model_config
from nemsim.scenes import SMALL


def _save(path, name, scene, rules, overrides=None):
    torch.manual_seed(1)
    model = build_model(name, scene, rules, overrides)
    with torch.no_grad():  # move away from the initialization so a round-trip is a real test
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    cfg = dataclasses.asdict(model_config(name, scene, overrides))
    save_checkpoint(path, model, model_name=name, model_config=cfg, scene=scene, rules=rules,
                    summary={"epochs": 1}, metrics={"control-id": {"avg_rmse": 0.1}})
    return model


@pytest.mark.parametrize("name,overrides", [("test-standin", {"width": 3}), ("nemsim", None)])
def test_round_trip_same_outputs(tmp_path, tiny_scene, rules, name, overrides):
    path = tmp_path / "m.pt"
    model = _save(path, name, tiny_scene, rules, overrides).eval()
    loaded = load_checkpoint(path, rules=rules, scene=tiny_scene)
    assert not loaded.model.training
    assert loaded.name == name and loaded.scene == tiny_scene
    assert loaded.rules.sha256 == rules.sha256
    assert loaded.summary == {"epochs": 1} and loaded.metrics["control-id"]["avg_rmse"] == 0.1
    x = torch.randn(2, *tiny_scene.state_shape).clamp(-1, 1)
    u = torch.rand(2, 14) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(loaded.model(x, u), model(x, u))
    raw = read_checkpoint(path)
    for key in ("format_version", "model_name", "model_config", "model_state", "scene", "rules_sha256",
                "rules_source", "control_ranges", "summary", "metrics"):
        assert key in raw
    assert len(raw["control_ranges"]) == 14


def test_refuses_mismatched_scene(tmp_path, tiny_scene, rules):
    path = tmp_path / "m.pt"
    _save(path, "test-standin", tiny_scene, rules)
    with pytest.raises(CheckpointMismatch, match="scene") as err:
        load_checkpoint(path, scene=SMALL)
    assert "rules" not in str(err.value)


def test_refuses_mismatched_rules(tmp_path, tiny_scene, rules):
    path = tmp_path / "m.pt"
    _save(path, "test-standin", tiny_scene, rules)
    other = dataclasses.replace(rules, sha256="0" * 64)
    with pytest.raises(CheckpointMismatch, match="rules") as err:
        load_checkpoint(path, rules=other, scene=tiny_scene)
    assert "scene" not in str(err.value)


def test_rejects_non_checkpoint(tmp_path):
    bad = tmp_path / "x.pt"
    torch.save({"weights": 1}, bad)
    with pytest.raises(ValueError, match="not a NEMSim checkpoint"):
        read_checkpoint(bad)
