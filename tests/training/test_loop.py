"""The training loop: outputs, determinism for a seed, and resume-after-kill reproducing the run."""

from __future__ import annotations

import csv
import dataclasses

import pytest
import torch

from nemsim.model.registry import build_model, model_config
from nemsim.training.checkpoint import load_checkpoint, read_checkpoint
from nemsim.training.config import TrainConfig
from nemsim.training.loop import ModelMeta, TrainData, seed_everything, train

STEPS, VISIBLE = 4, 5  # as in tests/training/conftest.py


def _cfg(**kw) -> TrainConfig:
    base = dict(max_epochs=2, warmup_epochs=1, val_every=1, batch_size=4, rollout_steps=STEPS,
                val_batch_size=2, progress=False)
    return TrainConfig(**{**base, **kw})


def _run(out, cfg, tiny_data, manifest, tiny_scene, rules, resume=False):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    seed_everything(cfg.seed)
    model = build_model("test-standin", tiny_scene, rules)
    meta = ModelMeta("test-standin", dataclasses.asdict(model_config("test-standin", tiny_scene)), tiny_scene, rules)
    data = TrainData(TransitionDataset(tiny_data, manifest, "train", visible_transitions=VISIBLE),
                     TrajectoryDataset(tiny_data, manifest, "val"))
    return train(cfg, model, data, out, meta, resume=resume)


def _weights(path):
    return read_checkpoint(path)["model_state"]


def test_outputs_and_loss_decreases(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    summary = _run(tmp_path, _cfg(max_epochs=3), tiny_data, tiny_manifest, tiny_scene, rules)
    for name in ("best.pt", "last.pt", "metrics.csv"):
        assert (tmp_path / name).is_file()
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3]
    assert float(rows[-1]["train_loss"]) < float(rows[0]["train_loss"])
    assert all(r["val_avg_rmse"] for r in rows)
    assert summary["epochs"] == 3 and 1 <= summary["best_epoch"] <= 3
    loaded = load_checkpoint(tmp_path / "best.pt", scene=tiny_scene, rules=rules)
    assert loaded.summary["best_epoch"] == summary["best_epoch"]
    assert read_checkpoint(tmp_path / "last.pt")["train_state"]["epoch"] == 3


def test_deterministic_and_resume_reproduces(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    cfg = _cfg()
    _run(tmp_path / "a", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    # "killed" after epoch 1, then resumed to the full budget
    _run(tmp_path / "c", cfg.replace(max_epochs=1), tiny_data, tiny_manifest, tiny_scene, rules)
    _run(tmp_path / "c", cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True)
    wa, wb, wc = (_weights(tmp_path / d / "last.pt") for d in "abc")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
        assert torch.equal(wa[k], wc[k]), k
    rows = list(csv.DictReader((tmp_path / "c" / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2]


def test_early_stopping(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    # lr so small nothing improves measurably after round 1 -> stop after `patience` rounds w/o gain
    cfg = _cfg(max_epochs=10, lr=1e-12, min_lr=0.0, patience=1, warmup_epochs=0)
    summary = _run(tmp_path, cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    assert summary["stopped_early"] and summary["epochs"] < 10


@pytest.mark.parametrize("flags", [dict(bf16=True), dict(channels_last=True)])
def test_precision_flags_run(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules, flags):
    summary = _run(tmp_path, _cfg(max_epochs=1, **flags), tiny_data, tiny_manifest, tiny_scene, rules)
    assert summary["epochs"] == 1 and summary["final_train_loss"] > 0
