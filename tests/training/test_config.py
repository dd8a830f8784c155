"""TrainConfig holds the paper's hyper-parameters; the LR schedule is warm-up + cosine ([supp_training])."""

from __future__ import annotations

import math

import pytest

from nemsim.training.config import TrainConfig, from_dict, read_config_file
from nemsim.training.loop import lr_at


def test_paper_defaults():
    c = TrainConfig()
    assert (c.lr, c.weight_decay, c.min_lr, c.grad_clip) == (5e-4, 1e-5, 1e-5, 1.0)
    got = (c.warmup_epochs, c.batch_size, c.max_epochs, c.val_every, c.patience, c.seed)
    assert got == (10, 24, 350, 10, 20, 0)
    assert c.rollout_steps is None  # full horizon


def test_schedule_warmup_then_cosine_to_min():
    c = TrainConfig()
    spe = 7
    lrs = [lr_at(s, spe, c) for s in range(c.max_epochs * spe)]
    warm = c.warmup_epochs * spe
    assert lrs[0] == pytest.approx(c.lr / warm)
    assert all(b > a for a, b in zip(lrs[: warm - 1], lrs[1:warm], strict=True))  # linear increase
    assert lrs[warm - 1] == pytest.approx(c.lr)
    assert all(b <= a for a, b in zip(lrs[warm:], lrs[warm + 1:], strict=False))  # monotone cosine decay
    assert lr_at(c.max_epochs * spe, spe, c) == pytest.approx(c.min_lr)
    mid = warm + (c.max_epochs * spe - warm) // 2
    assert lrs[mid] == pytest.approx(c.min_lr + 0.5 * (c.lr - c.min_lr), rel=1e-2)
    assert all(math.isfinite(v) and v > 0 for v in lrs)


def test_unknown_keys_and_bad_values(tmp_path):
    with pytest.raises(ValueError, match="unknown training config keys"):
        from_dict({"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="batch_size"):
        TrainConfig(batch_size=0)
    f = tmp_path / "c.yaml"
    f.write_text("max_epochs: 3\nbetas: [0.8, 0.9]\nmodel:\n  width: 2\n")
    cfg, model = read_config_file(f)
    assert cfg.max_epochs == 3 and cfg.betas == (0.8, 0.9) and model == {"width": 2}


def test_step_budget_schedule():
    """max_steps shortens the cosine to the budget; warmup_steps replaces the epoch-based warm-up."""
    c = TrainConfig(max_steps=250, warmup_steps=25)
    spe = 1250
    assert lr_at(0, spe, c) == pytest.approx(c.lr / 25)
    assert lr_at(24, spe, c) == pytest.approx(c.lr)
    assert lr_at(250, spe, c) == pytest.approx(c.min_lr)
    assert lr_at(25 + 225 // 2, spe, c) == pytest.approx(c.min_lr + 0.5 * (c.lr - c.min_lr), rel=1e-2)
    # an epoch budget smaller than max_steps still wins
    long_budget = TrainConfig(max_epochs=2, warmup_epochs=1, max_steps=10**6)
    assert lr_at(2 * 7, 7, long_budget) == pytest.approx(c.min_lr)
    with pytest.raises(ValueError, match="max_steps"):
        TrainConfig(max_steps=0)


def test_yaml_exponent_floats_and_step_weights(tmp_path):
    """YAML 1.1 reads `1e-4` (no dot) as a string: float fields accept it; k-step weights become a tuple."""
    path = tmp_path / "c.yaml"
    path.write_text("lr: 1e-4\nmin_lr: 1e-6\nstep_loss_weights: [1, 1, 2]\nmodel:\n  steps_per_call: 3\n")
    cfg, model = read_config_file(path)
    assert cfg.lr == pytest.approx(1e-4) and cfg.min_lr == pytest.approx(1e-6)
    assert cfg.step_loss_weights == (1.0, 1.0, 2.0) and model == {"steps_per_call": 3}
    with pytest.raises(ValueError, match="lr must be a number"):
        from_dict({"lr": "fast"})


@pytest.mark.parametrize("value", ["0", "-1"])
def test_bad_budget_in_a_config_file_is_refused(tmp_path, value):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"max_train_minutes: {value}\n")
    with pytest.raises(ValueError, match="max_train_minutes must be None or > 0"):
        read_config_file(cfg)
    cfg.write_text("max_train_minutes: 4.5e1\n")  # YAML 1.1 reads this as a string
    assert read_config_file(cfg)[0].max_train_minutes == 45.0


def test_wall_budget_schedule_spans_the_budget():
    """Under max_train_minutes the cosine follows the wall time spent, not the step count: the same wall
    fraction gives the same lr at any step or step budget; warm-up scales it; min_lr once spent."""
    cfg = TrainConfig(lr=1e-3, min_lr=1e-5, warmup_steps=10, max_train_minutes=10.0, max_steps=50)
    half = cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr)
    assert lr_at(100, 7, cfg, wall_s=300.0) == pytest.approx(half)
    assert lr_at(100, 7, cfg.replace(max_steps=None, max_epochs=3), wall_s=300.0) == pytest.approx(half)
    assert lr_at(4, 7, cfg, wall_s=300.0) == pytest.approx(half * 5 / 10)  # warm-up step 5 of 10
    assert lr_at(10, 7, cfg, wall_s=0.0) == pytest.approx(cfg.lr)
    assert lr_at(10, 7, cfg, wall_s=600.0) == lr_at(10, 7, cfg, wall_s=5000.0) == pytest.approx(cfg.min_lr)


def test_bf16_by_default_only_where_the_device_computes_in_it(monkeypatch):
    from nemsim.inference import precision as config_mod

    assert TrainConfig().bf16 is None  # resolved by the training run for its device
    monkeypatch.setattr(config_mod, "cpu_flags", lambda: {"avx2", "fma"})
    assert not config_mod.native_bf16("cpu") and config_mod.native_bf16("cuda")
    for flag in ("avx512_bf16", "amx_bf16"):
        monkeypatch.setattr(config_mod, "cpu_flags", lambda flag=flag: {"avx2", flag})
        assert config_mod.native_bf16("cpu")


def test_budgets_in_items_and_the_device_batch_resolve_to_the_same_training_amount(tmp_path):
    """One recipe on any device: budgets in items become steps at the batch the device takes (rounded up),
    the CUDA overrides apply on a CUDA device only, and the square-root rule scales lr and min_lr from
    the batch they were tuned at; a resolved config resolves to itself."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("batch_size: 24\nlr: 5.0e-4\nmin_lr: 1.0e-5\nmax_samples: 288000\nwarmup_samples: 7200\n"
                   "samples_per_epoch: 24000\nlr_scaling: sqrt\nbase_batch_size: 24\n"
                   "cuda: {batch_size: 96, val_batch_size: 50}\n")
    base, _ = read_config_file(cfg)
    cpu, gpu = base.resolved("cpu"), base.resolved("cuda")
    assert (cpu.batch_size, cpu.max_steps, cpu.warmup_steps, cpu.batches_per_epoch) == (24, 12000, 300, 1000)
    assert cpu.lr == pytest.approx(5e-4) and cpu.val_batch_size == TrainConfig().val_batch_size
    assert (gpu.batch_size, gpu.max_steps, gpu.warmup_steps, gpu.batches_per_epoch) == (96, 3000, 75, 250)
    assert gpu.val_batch_size == 50
    assert gpu.lr == pytest.approx(1e-3) and gpu.min_lr == pytest.approx(2e-5)  # sqrt(96 / 24) = 2
    assert gpu.max_steps * gpu.batch_size == cpu.max_steps * cpu.batch_size == 288000
    assert gpu.resolved("cuda") == gpu and cpu.resolved("cpu") == cpu
    odd = TrainConfig(batch_size=7, max_samples=100, lr_scaling="linear", base_batch_size=14).resolved("cpu")
    assert odd.max_steps == 15 and odd.lr == pytest.approx(TrainConfig().lr / 2)


@pytest.mark.parametrize("bad, match", [({"cuda": {"patience": 3}}, "cuda: a mapping of some of"),
                                        ({"lr_scaling": "cube"}, "lr_scaling='cube'"),
                                        ({"max_samples": 0}, "max_samples must be None or >= 1")])
def test_bad_device_and_item_budget_fields_are_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**bad)
