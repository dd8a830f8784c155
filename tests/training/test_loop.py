"""The training loop: outputs, determinism for a seed, and resume-after-kill reproducing the run."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import pytest
import torch

from nemsim.inference.checkpoint import load_checkpoint, read_checkpoint
from nemsim.registry import build_model, model_config
from nemsim.training.config import TrainConfig
from nemsim.training.loop import Clock, ModelMeta, TrainData, seed_everything, train

STEPS, VISIBLE = 4, 5  # as in tests/training/conftest.py


def _cfg(**kw) -> TrainConfig:
    base = dict(max_epochs=2, warmup_epochs=1, val_every=1, batch_size=4, rollout_steps=STEPS,
                val_batch_size=2, progress=False)
    return TrainConfig(**{**base, **kw})


def _run(out, cfg, tiny_data, manifest, tiny_scene, rules, resume=False, clock=None):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    seed_everything(cfg.seed)
    model = build_model("test-standin", tiny_scene, rules)
    if clock is not None:  # a _WorkClock: every model call advances it
        model.register_forward_hook(clock.advance)
    mcfg = dataclasses.asdict(model_config("test-standin", tiny_scene))
    meta = ModelMeta("test-standin", mcfg, tiny_scene, rules)
    data = TrainData(TransitionDataset(tiny_data, manifest, "train", visible_transitions=VISIBLE,
                                       unroll=cfg.unroll_steps),
                     TrajectoryDataset(tiny_data, manifest, "val"))
    return train(cfg, model, data, out, meta, resume=resume,
                 clock=None if clock is None else Clock(wall=clock))


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


def test_batches_per_epoch_caps_each_epoch(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    """batches_per_epoch ends every epoch after N batches (and validates there); epochs draw different
    batches, and a resumed capped run reproduces the uninterrupted one."""
    from nemsim.data.dataset import TransitionDataset

    cfg = _cfg(max_epochs=3, batches_per_epoch=2, val_every=1, warmup_steps=1)
    n_items = len(TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE))
    assert n_items > 2 * cfg.batch_size  # the cap binds
    _run(tmp_path / "a", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    rows = list(csv.DictReader((tmp_path / "a" / "metrics.csv").open()))
    assert [int(r["step"]) for r in rows] == [2, 4, 6] and all(r["val_avg_rmse"] for r in rows)
    _run(tmp_path / "b", cfg.replace(max_epochs=1), tiny_data, tiny_manifest, tiny_scene, rules)
    _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True)
    wa, wb = _weights(tmp_path / "a" / "last.pt"), _weights(tmp_path / "b" / "last.pt")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


class _Killed(RuntimeError):
    pass


def test_step_budget_and_mid_epoch_resume_reproduces(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules,
                                                     monkeypatch):
    """max_steps ends the run inside an epoch; a run killed mid-epoch resumes from the step-wise last.pt."""
    from nemsim.data.dataset import TransitionDataset

    cfg = _cfg(max_epochs=3, max_steps=5, warmup_steps=1, checkpoint_every=1)
    full = _run(tmp_path / "a", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    last = read_checkpoint(tmp_path / "a" / "last.pt")["train_state"]
    assert last["schedule_step"] == 5 and full["epochs"] == last["epoch"]
    rows = list(csv.DictReader((tmp_path / "a" / "metrics.csv").open()))
    assert int(rows[-1]["step"]) == 5 and rows[-1]["val_avg_rmse"]  # validated at the end of the budget

    original = TransitionDataset.__getitem__
    calls = {"n": 0}

    def dying(self, i):
        calls["n"] += 1
        if calls["n"] > 4 * 3:  # inside the 4th batch of 4: three steps done
            raise _Killed
        return original(self, i)

    monkeypatch.setattr(TransitionDataset, "__getitem__", dying)
    with pytest.raises(_Killed):
        _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    state = read_checkpoint(tmp_path / "b" / "last.pt")["train_state"]
    assert state["schedule_step"] == 3 and state["epoch_batches"] == 3 and state["epoch_loss"][1] > 0
    monkeypatch.setattr(TransitionDataset, "__getitem__", original)
    _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True)
    wa, wb = _weights(tmp_path / "a" / "last.pt"), _weights(tmp_path / "b" / "last.pt")
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    rows_b = list(csv.DictReader((tmp_path / "b" / "metrics.csv").open()))
    assert [r["train_loss"] for r in rows_b] == [r["train_loss"] for r in rows]


def test_pushforward_unroll_trains(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    """unroll_steps=2: k-transition items and the pushforward loss run, decrease, and validate."""
    from nemsim.data.dataset import TransitionDataset

    ds = TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE, unroll=2)
    x, u, y = ds[0]
    assert u.shape == (2, 14) and y.shape == (2, *x.shape)
    one = TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE)
    assert len(ds) == len(one) // VISIBLE * (VISIBLE - 1)
    x1, u1, y1 = one[1]  # the item's second transition is the one-step item at t + 1
    assert torch.equal(y[0], x1) and torch.equal(u[1], u1) and torch.equal(y[1], y1)
    summary = _run(tmp_path, _cfg(max_epochs=3, unroll_steps=2), tiny_data, tiny_manifest, tiny_scene, rules)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert float(rows[-1]["train_loss"]) < float(rows[0]["train_loss"]) and summary["epochs"] == 3


def test_pushforward_loss_is_mean_of_detached_steps():
    """Hand check: for an affine model the loss equals the mean of the two one-step MSEs, with the second
    step's gradient not flowing into the first step's prediction."""
    from contextlib import nullcontext

    from nemsim.training.loop import pushforward_loss

    class Scale(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.a = torch.nn.Parameter(torch.tensor(2.0))

        def forward(self, x, u):
            return self.a * x

    m = Scale()
    x = torch.ones(1, 2, 1, 1, 1)
    y = torch.zeros(1, 2, 2, 1, 1, 1)
    loss = pushforward_loss(m, x, torch.zeros(1, 2, 14), y, nullcontext())
    # step 1: pred 2, mse 4; step 2 input detached 2 -> pred 4, mse 16; mean 10
    assert loss.item() == pytest.approx(10.0)
    loss.backward()
    # d/da [ (a·1)^2 + (a·2)^2 ] / 2 with the input 2 held fixed = (2a + 8a) / 2 = 5a = 10
    assert m.a.grad.item() == pytest.approx(10.0)


def test_continue_with_pushforward_after_one_step_training(tmp_path, tiny_data, tiny_manifest, tiny_scene,
                                                            rules):
    """Resuming an epoch-end last.pt with another unroll (other steps per epoch) trains the whole next
    epoch."""
    from nemsim.data.dataset import TransitionDataset

    _run(tmp_path, _cfg(max_epochs=1), tiny_data, tiny_manifest, tiny_scene, rules)
    first = int(list(csv.DictReader((tmp_path / "metrics.csv").open()))[0]["step"])
    _run(tmp_path, _cfg(max_epochs=2, unroll_steps=2), tiny_data, tiny_manifest, tiny_scene, rules,
         resume=True)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    n2 = len(TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE, unroll=2))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    assert int(rows[1]["step"]) - first == math.ceil(n2 / _cfg().batch_size)  # no batch skipped


TICK = 3.0  # wall seconds of one model call under _WorkClock


class _WorkClock:
    """A deterministic wall clock for budget tests: TICK seconds per model call (training step or one
    validation rollout step), nothing else; so a run's time is a known function of the work it did."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def advance(self, *_) -> None:
        self.t += TICK


def _budget_cfg(**kw) -> TrainConfig:
    # 15 items / batch 4 = 4 steps per epoch; validation = 1 case x STEPS rollout calls
    return _cfg(max_epochs=10, warmup_steps=1, max_train_minutes=0.5, **kw)  # 0.5 min = 10 calls


def test_wall_budget_ends_run_inside_an_epoch(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    """Epoch 1: steps 1-4 (12 s), validation (4 calls, 24 s); epoch 2: step 5 (27 s), step 6 (30 s = the
    budget) -> stop inside the epoch, validate once more (42 s), write best.pt / last.pt."""
    cfg = _budget_cfg()
    summary = _run(tmp_path, cfg, tiny_data, tiny_manifest, tiny_scene, rules, clock=_WorkClock())
    assert summary["steps"] == 6 and summary["budget_spent"] and summary["budget_minutes"] == 0.5
    assert summary["wall_s"] == 14 * TICK and summary["val_wall_s"] == 2 * STEPS * TICK
    assert summary["cpu_s"] > 0 and summary["final_loss_steps"] == 6 and summary["final_train_loss"] > 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [(int(r["step"]), float(r["wall_s"]), float(r["val_wall_s"])) for r in rows] == \
        [(4, 4 * TICK, 0.0), (6, 10 * TICK, STEPS * TICK)]
    assert all(r["val_avg_rmse"] and float(r["cpu_s"]) > 0 for r in rows)
    assert float(rows[1]["cpu_s"]) >= float(rows[0]["cpu_s"])
    # the cosine spans the budget: step 6 trained at 27 s of 30 s, progress 0.9
    expected = cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr) * (1 + math.cos(math.pi * 0.9))
    assert float(rows[1]["lr"]) == pytest.approx(expected)
    last = read_checkpoint(tmp_path / "last.pt")["train_state"]
    assert last["schedule_step"] == 6 and last["wall_s"] == 14 * TICK and last["val_wall_s"] == 8 * TICK
    assert (tmp_path / "best.pt").is_file()
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["steps"] == 6 and written["wall_s"] == summary["wall_s"]
    # resuming a spent budget trains nothing; a larger budget goes on from the stored time
    again = _run(tmp_path, cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True, clock=_WorkClock())
    assert again["steps"] == 6 and len(list(csv.DictReader((tmp_path / "metrics.csv").open()))) == 2
    more = _run(tmp_path, cfg.replace(max_train_minutes=1.0), tiny_data, tiny_manifest, tiny_scene, rules,
                resume=True, clock=_WorkClock())
    # from 42 s, the next epoch (the rest of epoch 2 is skipped, as after max_steps): steps 7-10 (54 s),
    # validation (66 s >= 60 s) -> stop there, without starting another step
    assert more["steps"] == 10 and more["wall_s"] == 22 * TICK and more["epochs"] == 3


def test_wall_budget_resume_continues_the_same_budget(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules,
                                                      monkeypatch):
    """A run killed inside epoch 2 resumes with the time stored in last.pt: it stops at the same step with
    the same weights, learning rates and times as the uninterrupted run."""
    from nemsim.data.dataset import TransitionDataset

    cfg = _budget_cfg(checkpoint_every=1)
    full = _run(tmp_path / "a", cfg, tiny_data, tiny_manifest, tiny_scene, rules, clock=_WorkClock())
    original = TransitionDataset.__getitem__
    calls = {"n": 0}

    def dying(self, i):
        calls["n"] += 1
        if calls["n"] > 15 + 4:  # epoch 1 (15 items), then step 5: killed fetching step 6's batch
            raise _Killed
        return original(self, i)

    monkeypatch.setattr(TransitionDataset, "__getitem__", dying)
    with pytest.raises(_Killed):
        _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules, clock=_WorkClock())
    state = read_checkpoint(tmp_path / "b" / "last.pt")["train_state"]
    assert state["schedule_step"] == 5 and state["wall_s"] == 9 * TICK and len(state["recent_losses"]) == 5
    monkeypatch.setattr(TransitionDataset, "__getitem__", original)
    resumed = _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True,
                   clock=_WorkClock())  # a new process: its clock starts again at 0
    assert resumed["steps"] == full["steps"] == 6
    assert resumed["wall_s"] == full["wall_s"] and resumed["val_wall_s"] == full["val_wall_s"]
    assert resumed["final_train_loss"] == pytest.approx(full["final_train_loss"])
    wa, wb = _weights(tmp_path / "a" / "last.pt"), _weights(tmp_path / "b" / "last.pt")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    keys = ("step", "lr", "train_loss", "wall_s", "val_wall_s", "val_avg_rmse")
    ra, rb = (list(csv.DictReader((tmp_path / d / "metrics.csv").open())) for d in "ab")
    assert [[r[k] for k in keys] for r in ra] == [[r[k] for k in keys] for r in rb]


def test_wall_budget_spent_outside_a_step_still_validates(tmp_path, tiny_data, tiny_manifest, tiny_scene,
                                                          rules, monkeypatch):
    """The budget runs out while epoch 1's last.pt is written (a slow disk), epoch 1 unvalidated (val_every
    5): the run trains one more step, which trips the budget, and validates that step's weights."""
    import nemsim.training.loop as loop

    clock = _WorkClock()
    write = loop.write_checkpoint_dict

    def slow_write(*args, **kw):
        clock.t += 100.0
        return write(*args, **kw)

    monkeypatch.setattr(loop, "write_checkpoint_dict", slow_write)
    cfg = _budget_cfg(val_every=5)
    summary = _run(tmp_path, cfg, tiny_data, tiny_manifest, tiny_scene, rules, clock=clock)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [int(r["step"]) for r in rows] == [4, 5]
    assert not rows[0]["val_avg_rmse"] and rows[1]["val_avg_rmse"]
    assert summary["steps"] == 5 and summary["budget_spent"] and (tmp_path / "best.pt").is_file()


def test_weight_average_by_hand():
    """avg <- avg + (1 - d_n)(w - avg), d_n = min(decay, (1 + n)/(10 + n)); ``applied`` swaps and restores."""
    from nemsim.training.average import WeightAverage

    lin = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        lin.weight.fill_(1.0)
    avg = WeightAverage(lin, decay=0.5)
    assert avg.rate() == pytest.approx(0.1)  # n = 0: 1/10 < 0.5
    with torch.no_grad():
        lin.weight.fill_(2.0)
    avg.update()  # 1 + 0.9 (2 - 1)
    assert float(avg.shadow[0]) == pytest.approx(1.9)
    assert avg.rate() == pytest.approx(2 / 11)
    avg.updates = 100  # the warm-up is over: the decay itself
    avg.update()  # 1.9 + 0.5 (2 - 1.9)
    assert float(avg.shadow[0]) == pytest.approx(1.95)
    with avg.applied():
        assert float(lin.weight.detach()) == pytest.approx(1.95)
    assert float(lin.weight.detach()) == 2.0
    restored = WeightAverage(lin, decay=0.5)
    restored.load_state_dict(avg.state_dict())
    assert float(restored.shadow[0]) == pytest.approx(1.95) and restored.updates == 101
    with pytest.raises(ValueError, match="decay"):
        WeightAverage(lin, decay=1.0)


def test_ema_validates_the_average_and_resume_carries_it(tmp_path, tiny_data, tiny_manifest, tiny_scene,
                                                          rules):
    """With ema_decay, best.pt holds the averaged weights (not the trained ones in last.pt), and a run killed
    after epoch 1 and resumed ends with the same average as the uninterrupted run."""
    cfg = _cfg(max_epochs=2, ema_decay=0.9, patience=5)
    _run(tmp_path / "a", cfg, tiny_data, tiny_manifest, tiny_scene, rules)
    _run(tmp_path / "b", cfg.replace(max_epochs=1), tiny_data, tiny_manifest, tiny_scene, rules)
    one_epoch = read_checkpoint(tmp_path / "b" / "last.pt")
    best_b = _weights(tmp_path / "b" / "best.pt")  # the only validation: the average after epoch 1
    model = build_model("test-standin", tiny_scene, rules)
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    shadow = one_epoch["train_state"]["ema"]["shadow"]
    assert len(names) == len(shadow) and one_epoch["train_state"]["ema"]["updates"] > 0
    for name, avg in zip(names, shadow, strict=True):
        assert torch.equal(best_b[name], avg), name
    trained = one_epoch["model_state"]
    assert any(not torch.equal(trained[n], avg) for n, avg in zip(names, shadow, strict=True))
    _run(tmp_path / "b", cfg, tiny_data, tiny_manifest, tiny_scene, rules, resume=True)
    ema_a = read_checkpoint(tmp_path / "a" / "last.pt")["train_state"]["ema"]
    ema_b = read_checkpoint(tmp_path / "b" / "last.pt")["train_state"]["ema"]
    assert ema_a["updates"] == ema_b["updates"]
    assert all(torch.equal(x, y) for x, y in zip(ema_a["shadow"], ema_b["shadow"], strict=True))
    with pytest.raises(ValueError, match="ema_decay"):
        _cfg(ema_decay=1.0)
