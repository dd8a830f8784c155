"""k-step training (steps_per_call = k), its loss, and checkpoints that record k and the simulator config."""

from __future__ import annotations

import csv
import dataclasses
import json
from contextlib import nullcontext

import pytest
import torch

from nemsim.inference.checkpoint import (
    checkpoint_sim_config,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from nemsim.registry import build_model, model_config
from nemsim.scenes import SMALL as SMALL_SCENE
from nemsim.training.config import TrainConfig
from nemsim.training.loop import (
    ModelMeta,
    PairTerms,
    TrainData,
    multistep_loss,
    pushforward_loss,
    seed_everything,
    train,
)

STEPS, VISIBLE = 4, 5  # as in tests/training/conftest.py
K = 3
SMALL_NET = {"stem": 4, "widths": [4, 6, 6], "latent_channels": 6, "context_dim": 8, "readout_width": 6,
             "decoder_widths": [6, 6]}  # a narrow NEMSim: trains on tiny in seconds


class Affine(torch.nn.Module):
    """x̂_{t+j} = a^j x for j = 1..k: a hand-checkable k-step model."""

    def __init__(self, k: int):
        super().__init__()
        self.k = k
        self.a = torch.nn.Parameter(torch.tensor(2.0))

    def forward(self, x, u, all_steps=False):
        out = torch.stack([self.a ** (j + 1) * x for j in range(self.k)], dim=1)  # (B, k, ...)
        return out if all_steps else out[:, 0]


def test_multistep_loss_by_hand():
    x = torch.ones(1, 2, 1, 1, 1)
    y = torch.zeros(1, 4, 2, 1, 1, 1)
    m = Affine(2)
    # call 1: preds 2, 4 -> MSE 4, 16; call 2 from detached 4: preds 8, 16 -> MSE 64, 256
    loss = multistep_loss(m, x, torch.zeros(1, 4, 14), y, 2, nullcontext())
    assert loss.item() == pytest.approx(((4 + 16) / 2 + (64 + 256) / 2) / 2)
    weighted = multistep_loss(m, x, torch.zeros(1, 2, 14), y[:, :2], 2, nullcontext(),
                              weights=torch.tensor([3.0, 1.0]))
    assert weighted.item() == pytest.approx(0.75 * 4 + 0.25 * 16)
    with pytest.raises(ValueError, match="whole number of calls"):
        multistep_loss(m, x, torch.zeros(1, 3, 14), y[:, :3], 2, nullcontext())
    # k = 1 is the pushforward loss
    one = Affine(1)
    args = (x, torch.zeros(1, 3, 14), y[:, :3])
    assert multistep_loss(one, *args, 1, nullcontext()).item() == pytest.approx(
        pushforward_loss(one, *args, nullcontext()).item())


def _run(out, cfg, tiny_data, manifest, tiny_scene, rules, k=K, sim_config=None):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    seed_everything(cfg.seed)
    overrides = {"steps_per_call": k, **SMALL_NET}
    model = build_model("nemsim", tiny_scene, rules, overrides)
    meta = ModelMeta("nemsim", dataclasses.asdict(model_config("nemsim", tiny_scene, overrides)), tiny_scene,
                     rules, sim_config=sim_config)
    data = TrainData(TransitionDataset(tiny_data, manifest, "train", visible_transitions=VISIBLE,
                                       unroll=cfg.unroll_steps * k),
                     TrajectoryDataset(tiny_data, manifest, "val"))
    return model, train(cfg, model, data, out, meta)


def _cfg(**kw) -> TrainConfig:
    base = dict(max_epochs=1, warmup_epochs=0, val_every=1, batch_size=2, rollout_steps=STEPS,
                val_batch_size=1,
                progress=False, bf16=False, lr=2e-3)
    return TrainConfig(**{**base, **kw})


def _batch_loss(model, tiny_data, manifest, k=K):
    from nemsim.data.dataset import TransitionDataset

    ds = TransitionDataset(tiny_data, manifest, "train", visible_transitions=VISIBLE, unroll=k)
    items = [ds[i] for i in range(len(ds))]
    x, u, y = (torch.stack(v) for v in zip(*items, strict=True))
    with torch.no_grad():
        return multistep_loss(model, x, u, y, k, nullcontext()).item()


def test_one_epoch_k3_training_lowers_the_loss(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    seed_everything(0)
    fresh = build_model("nemsim", tiny_scene, rules, {"steps_per_call": K, **SMALL_NET}).eval()
    before = _batch_loss(fresh, tiny_data, tiny_manifest)
    gen = {"kind": "synthetic-test", "seed": 7}
    model, summary = _run(tmp_path, _cfg(), tiny_data, tiny_manifest, tiny_scene, rules, sim_config=gen)
    after = _batch_loss(model.eval(), tiny_data, tiny_manifest)
    assert after < before
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert rows[0]["val_avg_rmse"]  # the validation rollout ran with k = 3
    loaded = load_checkpoint(tmp_path / "best.pt", scene=tiny_scene, rules=rules)
    assert loaded.model.config.steps_per_call == K and loaded.config["steps_per_call"] == K
    assert checkpoint_sim_config(loaded) == gen == checkpoint_sim_config(tmp_path / "best.pt")


def test_pushforward_over_two_calls_and_weights(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    """unroll_steps=2 calls of k=2 (4-transition items) with per-state weights trains and validates."""
    _, summary = _run(tmp_path, _cfg(unroll_steps=2, step_loss_weights=[1.0, 2.0]), tiny_data, tiny_manifest,
                      tiny_scene, rules, k=2)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert summary["epochs"] == 1 and float(rows[0]["train_loss"]) > 0 and rows[0]["val_avg_rmse"]


def test_mismatched_window_and_weights_refused(tmp_path, tiny_data, tiny_manifest, tiny_scene, rules):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    model = build_model("nemsim", tiny_scene, rules, {"steps_per_call": K})
    meta = ModelMeta("nemsim", {"steps_per_call": K}, tiny_scene, rules)
    one = TrainData(TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE),
                    TrajectoryDataset(tiny_data, tiny_manifest, "val"))
    with pytest.raises(ValueError, match="steps_per_call=3"):
        train(_cfg(), model, one, tmp_path, meta)
    three = TrainData(TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE,
                                        unroll=K), TrajectoryDataset(tiny_data, tiny_manifest, "val"))
    with pytest.raises(ValueError, match="step_loss_weights"):
        train(_cfg(step_loss_weights=[1.0, 1.0]), model, three, tmp_path, meta)
    with pytest.raises(ValueError, match="step_loss_weights"):
        TrainConfig(step_loss_weights=(-1.0, 2.0))


def test_checkpoint_round_trip_k3(tmp_path, tiny_scene, rules):
    torch.manual_seed(1)
    overrides = {"steps_per_call": K}
    model = build_model("nemsim", tiny_scene, rules, overrides).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    cfg = dataclasses.asdict(model_config("nemsim", tiny_scene, overrides))
    gen = {"simulator": "nemsim.sim", "seed": 42, "constants": {"capacity": 4}}
    save_checkpoint(tmp_path / "k3.pt", model, model_name="nemsim", model_config=cfg, scene=tiny_scene,
                    rules=rules, sim_config=gen)
    loaded = load_checkpoint(tmp_path / "k3.pt", scene=tiny_scene, rules=rules)
    assert loaded.model.config.steps_per_call == K
    x = torch.rand(2, *tiny_scene.state_shape) * 2 - 1
    u = torch.rand(2, 14) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(loaded.model.predict(x, loaded.model.precompute(u)),
                                   model.predict(x, model.precompute(u)), rtol=0, atol=0)
    assert checkpoint_sim_config(loaded) == gen
    # older checkpoints: no sim_config key, no steps_per_call in the model config -> None and k = 1
    raw = read_checkpoint(tmp_path / "k3.pt")
    del raw["sim_config"]
    assert checkpoint_sim_config(raw) is None


def test_cli_trains_k3_and_records_the_data_generator(tmp_path, tiny_data, capsys):
    from nemsim.cli import main

    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "model": {"steps_per_call": 3, **SMALL_NET}}))
    out = tmp_path / "run"
    args = ["train", "--model", "nemsim", "--data", str(tiny_data), "--setting", "control-id", "--out",
            str(out), "--splits", str(tiny_data.parent / "splits"), "--epochs", "1", "--rollout-steps",
            str(STEPS), "--config", str(cfg), "--no-progress", "--no-test"]
    assert main(args) == 0
    assert "steps_per_call=3" in (out / "train.log").read_text()
    raw = read_checkpoint(out / "best.pt")
    assert raw["model_config"]["steps_per_call"] == 3
    assert checkpoint_sim_config(raw) == {"kind": "synthetic-test"}  # the data file's `generator` attribute
    cfg.write_text("model:\n  steps_per_call: 0\n")
    assert main(args) == 2 and "steps_per_call" in capsys.readouterr().err


def test_cli_init_from_a_one_step_checkpoint(tmp_path, tiny_data, tiny_scene, rules, capsys):
    """--init-from: a k=3 run starts from a one-step checkpoint's weights (its extra-step head from zero, so
    it starts as the one-step model's linear extrapolation); another model is refused; another scene's
    checkpoint is a warm start too (NEMSim's weights fit any grid), named in the log, and the trained model
    records the data's scene."""
    from nemsim.cli import main

    one = tmp_path / "one.pt"
    _save_k1 = build_model("nemsim", tiny_scene, rules, dict(SMALL_NET))
    save_checkpoint(one, _save_k1, model_name="nemsim", model_config=dataclasses.asdict(
        model_config("nemsim", tiny_scene, dict(SMALL_NET))), scene=tiny_scene, rules=rules)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "lr": 1e-12,
                               "min_lr": 0.0, "model": {"steps_per_call": 3, **SMALL_NET}}))
    out = tmp_path / "run"
    args = ["train", "--model", "nemsim", "--data", str(tiny_data), "--setting", "control-id", "--out",
            str(out), "--splits", str(tiny_data.parent / "splits"), "--epochs", "1", "--rollout-steps",
            str(STEPS), "--config", str(cfg), "--no-progress", "--no-test", "--init-from", str(one)]
    assert main(args) == 0
    assert "initialized from" in (out / "train.log").read_text()
    trained = read_checkpoint(out / "last.pt")["model_state"]
    start = read_checkpoint(one)["model_state"]
    for name, value in start.items():  # lr 1e-12: the weights are still the one-step checkpoint's
        torch.testing.assert_close(trained[name], value, atol=1e-6, rtol=0)
    assert set(trained) - set(start) == {"decoder.extra.weight", "decoder.extra.bias"}
    capsys.readouterr()
    other = tmp_path / "small.pt"  # the same weights, recorded as a `small` model
    save_checkpoint(other, _save_k1, model_name="nemsim", model_config={}, scene=SMALL_SCENE, rules=rules)
    args[args.index(str(one))] = str(other)
    args[args.index("--out") + 1] = str(tmp_path / "run2")
    assert main(args) == 0
    log = (tmp_path / "run2" / "train.log").read_text()
    assert "weights of scene 'small'" in log and "a model of scene 'tiny'" in log
    run2 = read_checkpoint(tmp_path / "run2" / "last.pt")
    assert run2["scene"] == tiny_scene.to_json()
    for name, value in start.items():
        torch.testing.assert_close(run2["model_state"][name], value, atol=1e-6, rtol=0)
    bad = tmp_path / "bad.pt"
    save_checkpoint(bad, _save_k1, model_name="fno", model_config={}, scene=tiny_scene, rules=rules)
    args[args.index(str(other))] = str(bad)
    args[args.index("--out") + 1] = str(tmp_path / "run3")
    assert main(args) == 2
    assert "a 'fno' checkpoint, training 'nemsim'" in capsys.readouterr().err


def test_cli_init_from_fewer_states_per_call_grows_the_head(tmp_path, tiny_data, tiny_scene, rules):
    """--init-from a k=2 checkpoint into a k=3 run: the stored corrections kept, the new one continued from
    them (``extend_steps``), said in the log."""
    from nemsim.cli import main

    two = tmp_path / "two.pt"
    net = {**SMALL_NET, "steps_per_call": 2}
    model = build_model("nemsim", tiny_scene, rules, dict(net))
    with torch.no_grad():
        model.decoder.extra.weight.normal_(0, 0.05)
    save_checkpoint(two, model, model_name="nemsim", model_config=dataclasses.asdict(
        model_config("nemsim", tiny_scene, dict(net))), scene=tiny_scene, rules=rules)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "lr": 1e-12, "min_lr": 0.0, "model": {**SMALL_NET, "steps_per_call": 3}}))
    out = tmp_path / "run"
    args = ["train", "--model", "nemsim", "--data", str(tiny_data), "--setting", "control-id",
            "--out", str(out), "--splits", str(tiny_data.parent / "splits"), "--epochs", "1",
            "--rollout-steps", str(STEPS), "--config", str(cfg), "--no-progress", "--no-test",
            "--init-from", str(two)]
    assert main(args) == 0
    assert "the extra-step head grown from 2 to 3 states per call" in (out / "train.log").read_text()
    w = read_checkpoint(out / "last.pt")["model_state"]["decoder.extra.weight"]
    torch.testing.assert_close(w[:16], model.decoder.extra.weight, atol=1e-6, rtol=0)
    torch.testing.assert_close(w[16:], 2 * model.decoder.extra.weight, atol=1e-6, rtol=0)


def test_profile_loss_is_the_soft_metric_error_in_voxels(tiny_scene, make_hole):
    from nemsim.training.loop import profile_loss

    a = torch.from_numpy(make_hole(tiny_scene, 3.0, 4.0))[None]  # (1, 2, D, H, W)
    b = torch.from_numpy(make_hole(tiny_scene, 3.0, 6.0))[None]  # 2 voxels deeper, same widths at the top
    assert profile_loss(a, a, tiny_scene).item() == 0.0
    # depth differs by 2 voxels -> (2^2 + top 0 + bottom 0 + mask 0) / 4 = 1 (flat bottom: same width there)
    assert profile_loss(a, b, tiny_scene).item() == pytest.approx(1.0, abs=0.05)
    p = a.clone().requires_grad_(True)
    profile_loss(p, b, tiny_scene).backward()
    assert p.grad is not None and p.grad.abs().sum() > 0  # gradients reach the voxels next to the surface


def test_profile_loss_measures_each_trench_at_its_own_si_top(tiny_scene):
    from nemsim.geometry.feature import Feature
    from nemsim.geometry.soft_profile import soft_profile_metrics
    from nemsim.sim.process import initial_state
    from nemsim.symmetry import FieldFold
    from nemsim.training.loop import (
        PROFILE_LOSS_METRICS,
        _profile_voxels,
        full_states,
        profile_loss,
        section_si_tops,
    )

    fold = FieldFold("section", tiny_scene.state_shape[-1])
    cd = 2.0 * tiny_scene.opening_radius_vox * tiny_scene.voxel_nm
    cases = [Feature("trench", cd, mask).apply(tiny_scene) for mask in (80.0, 48.0, 112.0)]
    q = torch.stack([fold.fold(torch.from_numpy(initial_state(c)).float()) for c in cases])  # (3, 2, D, 2, c)
    full = full_states(q, tiny_scene)
    assert [c.si_top for c in cases] == [20, 24, 16]
    assert section_si_tops(q, tiny_scene).tolist() == [20, 24, 16]
    got = _profile_voxels(q, tiny_scene)  # (4, 3): each column its own case's, in the input's order
    for i, c in enumerate(cases):
        m = soft_profile_metrics(full[i:i + 1], c)
        want_i = [float(m[k]) / c.voxel_nm for k in PROFILE_LOSS_METRICS]
        assert got[:, i].tolist() == pytest.approx(want_i, abs=1e-5)
    # a 2-voxel deeper trench below each case's own Si top: the depth term alone, (2^2) / 4 = 1 voxel^2
    deeper = []
    for c in cases:
        st = initial_state(c)
        axis = int(round(c.opening_centre[0])) + 1
        st[1, c.si_top - 1 : c.si_top + 1, :, axis - 1 : axis + 2] = 1.0  # 2 Si rows of the axis opened
        deeper.append(fold.fold(torch.from_numpy(st).float()))
    d = torch.stack(deeper)
    assert profile_loss(q, q, tiny_scene).item() == 0.0
    want = sum(float(((soft_profile_metrics(full_states(d, tiny_scene)[i:i + 1], c)[k]
                       - soft_profile_metrics(full[i:i + 1], c)[k]) / c.voxel_nm) ** 2)
               for i, c in enumerate(cases) for k in PROFILE_LOSS_METRICS) / (4 * len(cases))
    assert profile_loss(d, q, tiny_scene).item() == pytest.approx(want, rel=1e-5)
    depth = [float(soft_profile_metrics(full_states(d, tiny_scene)[i:i + 1], c)["etch_depth"]
                   - soft_profile_metrics(full[i:i + 1], c)["etch_depth"]) / c.voxel_nm
             for i, c in enumerate(cases)]
    assert depth == pytest.approx([2.0, 2.0, 2.0], abs=0.05)  # measured at each case's own top


def test_profile_loss_weight_adds_lambda_times_the_profile_term(tiny_scene, make_hole):
    from nemsim.training.loop import profile_loss

    x = torch.from_numpy(make_hole(tiny_scene, 3.0, 4.0))[None]
    y = torch.from_numpy(make_hole(tiny_scene, 3.0, 6.0))[None, None]  # (1, 1, 2, D, H, W)

    class Hold(torch.nn.Module):  # predicts x_t for every step
        def forward(self, x, u, all_steps=False):
            return x[:, None] if all_steps else x

    base = multistep_loss(Hold(), x, torch.zeros(1, 1, 14), y, 1, nullcontext())
    both = multistep_loss(Hold(), x, torch.zeros(1, 1, 14), y, 1, nullcontext(), profile=(0.5, tiny_scene))
    assert both.item() == pytest.approx(base.item() + 0.5 * profile_loss(x, y[:, 0], tiny_scene).item())
    with pytest.raises(ValueError, match="profile_loss_weight"):
        TrainConfig(profile_loss_weight=-1.0)


def test_profile_loss_weight_trains_k_step_and_refuses_the_one_step_pushforward(
    tmp_path, tiny_data, tiny_manifest, tiny_scene, rules
):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    _, summary = _run(tmp_path / "k2", _cfg(profile_loss_weight=1e-3), tiny_data, tiny_manifest, tiny_scene,
                      rules, k=2)
    rows = list(csv.DictReader((tmp_path / "k2" / "metrics.csv").open()))
    assert summary["epochs"] == 1 and float(rows[0]["train_loss"]) > 0 and rows[0]["val_avg_rmse"]
    model = build_model("nemsim", tiny_scene, rules, {})
    meta = ModelMeta("nemsim", {}, tiny_scene, rules)
    items = TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE, unroll=2)
    two = TrainData(items, TrajectoryDataset(tiny_data, tiny_manifest, "val"))
    with pytest.raises(ValueError, match="one-step pushforward"):
        train(_cfg(unroll_steps=2, profile_loss_weight=1e-3), model, two, tmp_path / "pf", meta)


def test_pair_loss_adds_lambda_times_the_error_of_the_predicted_differences():
    from nemsim.training.loop import pair_loss

    m = Affine(2)  # predictions 2x, 4x
    x = torch.tensor([1.0, 1.0, 3.0]).reshape(3, 1, 1, 1, 1).expand(3, 2, 1, 1, 1)  # a sample, then a pair
    y = torch.zeros(3, 2, 2, 1, 1, 1)
    y[2] = 1.0  # the simulated difference of the pair is 1 at both steps
    u = torch.zeros(3, 2, 14)
    base = multistep_loss(m, x, u, y, 2, nullcontext())
    # predicted differences 2 (3 - 1) = 4 and 4 (3 - 1) = 8 against 1: errors 3 and 7 -> (9 + 49) / 2 = 29
    both = multistep_loss(m, x, u, y, 2, nullcontext(), pairs=PairTerms(1, 0.5, 0.0, SMALL_SCENE))
    assert both.item() == pytest.approx(base.item() + 0.5 * 29.0)
    with torch.no_grad():
        pred = m(x, u[:, 0], all_steps=True)
    assert pair_loss(pred, y, 1).item() == pytest.approx(29.0)
    off = PairTerms(1, 0.0, 0.0, SMALL_SCENE)
    assert multistep_loss(m, x, u, y, 2, nullcontext(), pairs=off).item() == pytest.approx(base.item())
    with pytest.raises(ValueError, match="pair_loss_weight"):
        TrainConfig(pair_loss_weight=-1.0)


def test_response_loss_is_the_error_of_the_pairs_metric_differences_in_voxels(make_hole):
    from nemsim.symmetry import fold
    from nemsim.training.loop import response_loss

    def hole(depth: float, radius: float = 5.0) -> torch.Tensor:
        return torch.from_numpy(make_hole(SMALL_SCENE, radius, depth))

    # a sample, then one pair whose second member is 2 voxels deeper; the prediction moves nothing
    target = torch.stack([hole(4.0), hole(4.0), hole(6.0)])
    pred = torch.stack([hole(9.0), hole(4.0), hole(4.0)])
    # errors of the differences in voxels: depth 2, top, bottom and mask 0 -> 2^2 / 4 = 1; the lone
    # sample's error (depth 5 voxels) does not count
    assert response_loss(pred, target, 1, SMALL_SCENE).item() == pytest.approx(1.0, abs=0.05)
    assert response_loss(target, target, 1, SMALL_SCENE).item() == 0.0
    moved = torch.stack([hole(9.0), hole(7.0), hole(9.0)])  # any pair with the simulated difference
    assert response_loss(moved, target, 1, SMALL_SCENE).item() == pytest.approx(0.0, abs=0.05)
    # a quarter-domain model's quadrants give the same loss; k states per sample all count
    quad = response_loss(fold(pred)[:, None], fold(target)[:, None], 1, SMALL_SCENE)
    assert quad.item() == pytest.approx(response_loss(pred, target, 1, SMALL_SCENE).item(), rel=1e-6)
    p = fold(pred).clone().requires_grad_(True)
    response_loss(p, fold(target), 1, SMALL_SCENE).backward()
    assert p.grad is not None and p.grad[-2:].abs().sum() > 0 and p.grad[0].abs().sum() == 0
    with pytest.raises(ValueError, match="response_loss_weight"):
        TrainConfig(response_loss_weight=-1.0)


def test_pair_terms_add_both_weighted_differences(make_hole):
    from nemsim.training.loop import pair_loss, response_loss

    states = [torch.from_numpy(make_hole(SMALL_SCENE, 5.0, d)) for d in (4.0, 5.0, 7.0, 3.0)]
    target, pred = torch.stack(states[:2]), torch.stack(states[2:])
    terms = PairTerms(1, 0.3, 0.02, SMALL_SCENE)
    want = 0.3 * pair_loss(pred, target, 1) + 0.02 * response_loss(pred, target, 1, SMALL_SCENE)
    assert float(terms.loss(pred, target)) == pytest.approx(want.item())
    assert PairTerms(1, 0.0, 0.0, SMALL_SCENE).loss(pred, target) == 0.0


def _pair_copy(tiny_data, tmp_path):
    """A copy of the tiny data whose cases (0, 1) and (2, 3) share a simulator seed: two sweep pairs."""
    import shutil

    import h5py

    path = tmp_path / "pairs.h5"
    shutil.copy(tiny_data, path)
    with h5py.File(path, "r+") as f:
        f["seeds"][:] = [0, 0, 2, 2, 4, 5]
    return path


def test_training_with_sweep_pairs_adds_them_to_every_batch(tmp_path, tiny_data, tiny_manifest, tiny_scene,
                                                            rules):
    from nemsim.data.dataset import PairDataset, TrajectoryDataset, TransitionDataset
    from nemsim.training.loop import Clock, _Run

    pairs = PairDataset(_pair_copy(tiny_data, tmp_path), unroll=K)
    overrides = {"steps_per_call": K, **SMALL_NET}
    seed_everything(0)
    model = build_model("nemsim", tiny_scene, rules, overrides)
    meta = ModelMeta("nemsim", dataclasses.asdict(model_config("nemsim", tiny_scene, overrides)), tiny_scene,
                     rules)
    items = TransitionDataset(tiny_data, tiny_manifest, "train", visible_transitions=VISIBLE, unroll=K)
    val = TrajectoryDataset(tiny_data, tiny_manifest, "val")
    cfg = _cfg(pair_loss_weight=1.0, pairs_per_step=3)
    run = _Run(cfg, model, TrainData(items, val, pairs), tmp_path / "pairs-run", meta, Clock())
    x, u, y = run.pair_batch()  # 3 pairs: the first members, then the second ones, at the same times
    assert x.shape == (6, *tiny_scene.state_shape) and u.shape == (6, K, 14) and y.shape[:2] == (6, K)
    again = run.pair_batch()
    assert all(torch.equal(a, b) for a, b in zip((x, u, y), again, strict=True))  # a function of the step
    summary = train(cfg, model, TrainData(items, val, pairs), tmp_path / "pairs-train", meta)
    rows = list(csv.DictReader((tmp_path / "pairs-train" / "metrics.csv").open()))
    assert summary["epochs"] == 1 and float(rows[0]["train_loss"]) > 0 and rows[0]["val_avg_rmse"]
    with pytest.raises(ValueError, match="need sweep pairs"):
        train(cfg, model, TrainData(items, val), tmp_path / "no-pairs", meta)
    with pytest.raises(ValueError, match="need sweep pairs"):
        train(_cfg(response_loss_weight=1e-3), model, TrainData(items, val), tmp_path / "no-pairs-r", meta)


def test_unroll_grad_backpropagates_through_the_chained_calls():
    x = torch.ones(1, 2, 1, 1, 1)
    y = torch.zeros(1, 4, 2, 1, 1, 1)
    grads = []
    for detach in (True, False):
        m = Affine(2)  # call 1: a, a^2; call 2 from s = a^2: a s, a^2 s
        loss = multistep_loss(m, x, torch.zeros(1, 4, 14), y, 2, nullcontext(), detach=detach)
        assert loss.item() == pytest.approx(((4 + 16) / 2 + (64 + 256) / 2) / 2)  # the same value
        loss.backward()
        grads.append(m.a.grad.item())
    # loss = (a^2 + a^4 + (a s)^2 + (a^2 s)^2) / 4 at a = 2: with s = 4 held (detached)
    # (2a + 4a^3 + 2a s^2 + 4a^3 s^2) / 4 = 153; through the chain (s = a^2)
    # (2a + 4a^3 + 6a^5 + 8a^7) / 4 = 313
    assert grads == pytest.approx([153.0, 313.0])
    grads = []
    for detach in (True, False):
        one = Affine(1)  # steps a, a s with s = a: loss (a^2 + (a s)^2) / 2
        pushforward_loss(one, x, torch.zeros(1, 2, 14), y[:, :2], nullcontext(), detach=detach).backward()
        grads.append(one.a.grad.item())
    assert grads == pytest.approx([10.0, 18.0])  # (2a + 2a s^2) / 2 with s = 2 held; (2a + 4a^3) / 2
