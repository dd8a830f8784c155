"""Hard-case stability suite (bench.stress) on an untrained `tiny` NEMSim checkpoint, plus the
fast rollout path (precompute/step) against the per-step forward."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bench.stress import CORNER_AXES, StressConfig, corner_bits, format_table, run_stress

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def loaded(tiny_checkpoint):
    from nemsim.inference.checkpoint import load_checkpoint

    return load_checkpoint(tiny_checkpoint)


@pytest.fixture(scope="module")
def x0(tiny_scene):
    """Initial geometry: flat Si slab and resist with a round opening (normalized SDF)."""
    s = tiny_scene
    D, H, W = s.field_shape
    z = np.arange(D)[:, None, None] - 1.0
    y = np.arange(H)[None, :, None] - 1.0 - s.opening_centre[1]
    x = np.arange(W)[None, None, :] - 1.0 - s.opening_centre[0]
    r = np.sqrt(x**2 + y**2)
    si = np.broadcast_to(z - (s.si_top - 0.5), (D, H, W))
    mask = np.maximum(np.maximum(z - (s.resist_top - 0.5), (s.si_top - 0.5) - z), s.opening_radius_vox - r)
    return np.clip(np.stack([mask, si]) / s.d_max_vox, -1, 1).astype(np.float32)


@pytest.fixture(scope="module")
def report(loaded, x0):
    # untrained: the random decoder moves every voxel by O(0.1) per step (a drift, not an instability), so
    # the bound is the drift budget 1 + 0.5 * steps; the trained-model bound is StressConfig's default
    cfg = StressConfig(steps=12, max_corners=4, noise_cases=2, batch_size=8, abs_bound=1.0 + 0.5 * 12)
    return run_stress(loaded.model, loaded.scene, x0, cfg)


def test_corner_subset_includes_extremes():
    assert len(corner_bits(None)) == 2 ** len(CORNER_AXES) == 128
    bits = corner_bits(4)
    assert len(bits) == 4
    assert bits[0] == (0,) * 7 and bits[-1] == (1,) * 7
    with pytest.raises(ValueError, match="max_corners"):
        corner_bits(1)


def test_case_list(report):
    names = [c["name"] for c in report["cases"]]
    assert names[0] == "centre"
    assert sum(n.startswith("corner-") for n in names) == 4
    assert {"angle-min", "angle-max", "noise-0", "noise-1"} <= set(names)
    assert report["summary"]["n_cases"] == len(names) == 9


def test_untrained_tiny_is_finite_and_bounded(report):
    for case in report["cases"]:
        assert case["finite"], case
        assert case["max_abs"] <= report["config"]["abs_bound"], case
        assert case["norm_ratio"] is not None and 0.0 < case["norm_ratio"] < 10.0
        assert case["max_step_growth"] is not None and case["max_step_growth"] < 2.0
        assert 0.0 < case["max_step_change"] <= 0.5, case
        assert case["depth_decreases"] >= 0
    assert report["summary"]["passed"]


def test_output_projection_bounds_every_noise_free_case(report, loaded):
    """clamp_output (default on) keeps every state of a noise-free rollout in [-1, 1], even untrained."""
    assert loaded.model.config.clamp_output
    for case in report["cases"]:
        if not case["name"].startswith("noise-"):
            assert case["max_abs"] <= 1.0 + 1e-6, case


def test_report_is_json_and_table(report):
    text = json.dumps(report)
    assert "NaN" not in text and "Infinity" not in text
    table = format_table(report)
    assert "centre" in table and ("PASS" in table or "FAIL" in table)


def test_nonfinite_model_is_reported(loaded, x0):
    class Broken(torch.nn.Module):
        def forward(self, x, u):
            return x * float("nan")

    rep = run_stress(Broken(), loaded.scene, x0, StressConfig(steps=2, max_corners=2, noise_cases=0,
                                                              angles=False))
    assert rep["summary"]["n_nonfinite"] == rep["summary"]["n_cases"] == 3
    assert not rep["summary"]["passed"]
    assert all(c["first_nonfinite_step"] == 1 for c in rep["cases"])
    json.dumps(rep)


def test_fast_path_matches_forward(loaded, x0):
    """rollout's precompute/step path equals calling forward every step (float tolerance)."""
    from nemsim.evaluation.rollout import rollout

    model = loaded.model
    torch.manual_seed(1)
    with torch.no_grad():  # make the zero-initialized branches matter
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    try:
        x = torch.as_tensor(x0)[None].repeat(2, 1, 1, 1, 1)
        u = torch.rand(2, 6, 14) * 2 - 1
        u[:, 3:] = u[:, 3:4]  # a recipe: controls change once, then stay
        slow = [x]
        with torch.no_grad():
            for t in range(6):
                slow.append(model(slow[-1], u[:, t]))
            fast = rollout(model, x, u, monotone=False)  # the fast path alone (projection: test_monotone)
        assert torch.allclose(fast, torch.stack(slow, 1), atol=1e-4, rtol=0)
        with torch.no_grad():
            y1, a1 = model(x, u[:, 0], return_aux=True)
            y2, a2 = model.step(x, model.precompute(u[:, 0]), return_aux=True)
        assert torch.allclose(y1, y2, atol=1e-5)
        for k in ("lambda", "alpha", "T", "w"):
            assert torch.allclose(a1[k], a2[k], atol=1e-6), k
    finally:
        from nemsim.inference.checkpoint import load_checkpoint

        model.load_state_dict(load_checkpoint(loaded.path).model.state_dict())


def test_cli_stress(tiny_checkpoint, tmp_path, monkeypatch, x0):
    import bench.stress as stress
    from nemsim.cli import main

    monkeypatch.setattr(stress, "initial_state", lambda scene: x0)
    out = tmp_path / "stress.json"
    rc = main(["stress", "--checkpoint", str(tiny_checkpoint), "--steps", "3", "--max-corners", "2",
               "--noise-cases", "1", "--abs-bound", "3", "--no-invariants", "--json", str(out)])
    assert rc == 0
    rep = json.loads(out.read_text())
    assert rep["summary"]["n_cases"] == 6 and rep["summary"]["passed"]


def test_cli_bench_rollout(tiny_checkpoint, tmp_path, monkeypatch, x0, capsys):
    import bench.stress as stress
    from nemsim.cli import main

    monkeypatch.setattr(stress, "initial_state", lambda scene: x0)
    out = tmp_path / "bench.json"
    rc = main(["bench", "rollout", "--checkpoint", str(tiny_checkpoint), "--steps", "3", "--repeats", "1",
               "--json", str(out)])
    assert rc == 0
    rep = json.loads(out.read_text())
    assert set(rep["variants"]) == {"fp32", "fp32-percall", "bf16", "channels_last"}
    assert rep["variants"]["fp32"]["max_abs_diff_vs_fp32"] == 0.0
    assert rep["variants"]["fp32-percall"]["max_abs_diff_vs_fp32"] < 1e-4
    assert rep["variants"]["channels_last"]["max_abs_diff_vs_fp32"] < 1e-4
    assert "median s" in capsys.readouterr().out
    assert main(["bench", "rollout", "--scene", "tiny", "--variants", "fp64"]) == 2


def test_cli_bench_rollout_window(tiny_checkpoint, tmp_path, monkeypatch, x0):
    """The depth-windowed variant reports its share of voxels computed and stays near the full rollout."""
    import bench.stress as stress
    from nemsim.cli import main

    monkeypatch.setattr(stress, "initial_state", lambda scene: x0)
    out = tmp_path / "bench.json"
    rc = main(["bench", "rollout", "--checkpoint", str(tiny_checkpoint), "--steps", "3", "--repeats", "1",
               "--variants", "fp32,fp32-window", "--json", str(out)])
    assert rc == 0
    win = json.loads(out.read_text())["variants"]["fp32-window"]
    assert 0.0 < win["fraction_computed"] <= 1.0
    assert win["max_abs_diff_vs_fp32"] < 0.25  # the stated tolerance is per-step RMS; a bound on max


def test_cli_bench_rollout_arms(tmp_path, capsys):
    """--arm times an untrained model of the configuration with overrides beside the variants (speed only);
    a malformed arm or an unknown key is a one-line error."""
    from bench.cli.stress import _parse_arm
    from nemsim.cli import main

    assert _parse_arm("lean:decoder_refine=0,decoder_widths=[24,8]") == (
        "lean", {"decoder_refine": 0, "decoder_widths": (24, 8)})
    out = tmp_path / "bench.json"
    rc = main(["bench", "rollout", "--scene", "tiny", "--variants", "fp32", "--steps", "4", "--repeats", "1",
               "--arm", "k2:steps_per_call=2", "--json", str(out)])
    assert rc == 0
    arm = json.loads(out.read_text())["variants"]["arm:k2"]
    assert arm["max_abs_diff_vs_fp32"] is None and arm["cpu_median_s"] > 0
    assert "untrained" in capsys.readouterr().out
    assert main(["bench", "rollout", "--scene", "tiny", "--arm", "k2"]) == 2
    assert main(["bench", "rollout", "--scene", "tiny", "--arm", "k2:no_such_key=1"]) == 2
    assert "no_such_key" in capsys.readouterr().err
