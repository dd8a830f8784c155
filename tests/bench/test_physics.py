"""Physics benchmark (bench.physics) and the shared simulator-truth helpers on `tiny`."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bench.physics import (
    PhysicsConfig,
    box_corners,
    format_markdown,
    heldout_recipes,
    planned_runs,
    run_physics,
    sweep_recipes,
)
from nemsim.controls import CONTROL_GROUPS, CONTROL_INDEX, HIGH, LOW, to_normalized
from nemsim.evaluation.truth import SimTruth, compare_case

torch.set_num_threads(1)
STEPS = 4


CFG = PhysicsConfig(levels=3, heldout=1, corners=2)


def test_sweeps_move_only_their_group():
    sweeps = sweep_recipes(4)
    assert list(sweeps) == list(CONTROL_GROUPS) and len(sweeps) == 7
    for group, rec in sweeps.items():
        idx = [CONTROL_INDEX[n] for n in CONTROL_GROUPS[group]]
        u = to_normalized(rec["raw"])  # (4, 14)
        rest = [j for j in range(14) if j not in idx]
        assert np.allclose(rec["raw"][:, rest], rec["raw"][0, rest])
        assert np.all(np.diff(rec["raw"][:, idx], axis=0) > 0), group  # increasing levels
        np.testing.assert_allclose(u[[0, -1]][:, idx], [[-1.0] * len(idx), [1.0] * len(idx)], atol=1e-9)
    angles = sweeps["ion_angle"]["raw"][:, CONTROL_INDEX["angle_ar_plus"]]
    assert np.all(angles == np.round(angles))  # integer exponents
    with pytest.raises(ValueError, match="levels"):
        PhysicsConfig(levels=2)


def test_heldout_and_corners():
    names, raw = heldout_recipes(PhysicsConfig(heldout=3, corners=3))
    assert names == ["lhs-0", "lhs-1", "lhs-2", "corner-min", "corner-max", "corner-2"]
    assert np.all((raw >= LOW * (1 - 1e-9)) & (raw <= HIGH * (1 + 1e-9)))
    assert np.array_equal(box_corners(2, 0), np.stack([LOW, HIGH]))
    # two seeds per recipe; the median recipe is shared by the seven sweeps
    runs = planned_runs(PhysicsConfig(levels=3, heldout=3, corners=3), raw)
    assert len(runs) == 2 * (7 * 3 + 6)


def test_compare_case_against_the_simulator_itself(truth):
    """A 'surrogate' that returns seed 1's trajectory: its error is half the seed difference exactly."""
    raw = sweep_recipes(3)["flux_ar_plus"]["raw"][-1]
    a = truth.states(raw, 1)
    c = compare_case(truth, raw, a, (1, 2))
    assert c["floor"] > 0
    assert c["avg_rmse"] == pytest.approx(0.5 * c["floor"], rel=1e-9)
    for m, err in c["error"].items():
        assert abs(err) == pytest.approx(0.5 * c["seed_diff"][m], abs=1e-9), m
    assert not c["worse_than_no_change"]


def test_run_physics_no_change_and_plausible(truth, x0, stubs):
    flat = run_physics(stubs.NoChange(), truth, x0, CFG)
    dep = flat["sweeps"]["flux_ar_plus"]["metrics"]["etch_depth"]
    assert dep["resolved"] and dep["slope_sim"] > 0  # the simulator deepens the hole with Ar+
    assert dep["slope_model"] == 0 and dep["slope_ratio"] == 0 and not dep["same_sign"]
    assert len(flat["heldout"]) == 3
    # predicting x_0 is the no-change baseline itself: never strictly worse
    assert flat["summary"]["heldout_worse_than_no_change"] == 0
    moving = run_physics(stubs.Plausible(), truth, x0, CFG)
    dep = moving["sweeps"]["flux_ar_plus"]["metrics"]["etch_depth"]
    assert dep["slope_model"] > 0 and dep["same_sign"] and dep["slope_ratio"] > 0
    # the plausible stub also etches under the mask region: its Avg RMSE is worse than no change somewhere
    assert moving["summary"]["sweep_worse_than_no_change"] >= 1
    md = format_markdown(moving)
    assert "| flux_ar_plus | depth |" in md and "worse than predicting no change" in md
    json.dumps(moving)


def test_cli_bench_physics(tiny_checkpoint, tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "phys"
    rc = main(["bench", "physics", "--checkpoint", str(tiny_checkpoint), "--sim-steps", "2", "--heldout", "1",
               "--corners", "0", "--no-progress", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "planned: " in text and "simulator runs" in text
    rep = json.loads((out / "physics.json").read_text())
    assert set(rep["sweeps"]) == set(CONTROL_GROUPS) and len(rep["heldout"]) == 1
    assert rep["simulator_cost"]["rng_mode"] == "counter"  # common random numbers by default
    assert (out / "physics.png").stat().st_size > 1000
    assert (out / "physics.md").read_text().startswith("# Physics")
    assert main(["bench", "physics", "--checkpoint", str(tiny_checkpoint), "--levels", "2"]) == 2
    assert main(["bench", "physics", "--checkpoint", str(tiny_checkpoint), "--sim-steps", "1000"]) == 2


def test_truth_runs_share_their_random_numbers_unless_told(tiny_checkpoint):
    import argparse

    from bench.cli.common import add_truth_options, sim_truth
    from nemsim.inference.checkpoint import load_checkpoint

    parser = argparse.ArgumentParser()
    add_truth_options(parser)
    loaded = load_checkpoint(tiny_checkpoint)
    cases = (([], "counter"), (["--sim-rng", "stream"], "stream"),
             (["--sim-rng", "stream", "--set", "rng_mode=counter"], "counter"))  # --set has the last word
    for argv, want in cases:
        with sim_truth(parser.parse_args(argv), loaded) as truth:
            assert truth.config.rng_mode == want


def test_sim_truth_cache(tiny_scene, tmp_path):
    """Runs are cached by (controls, seed) on disk: duplicates simulate once, a rerun reuses the directory."""
    from nemsim.rules import compile_rules, load_rules

    rules = compile_rules(load_rules())
    raws = sweep_recipes(3)["flux_cl_plus"]["raw"][1:]  # (2, 14)
    runs = [(raws[0], 1), (raws[1], 1), (raws[0], 1)]  # one duplicate
    with SimTruth(tiny_scene, rules, steps=2, cache_dir=tmp_path) as truth:
        assert len(truth.missing(runs)) == 2
        assert truth.ensure(runs) == 2 and truth.ensure(runs) == 0 and truth.n_simulated == 2
        first = truth.states(*runs[0])
        assert first.shape == (3, *tiny_scene.state_shape)
        assert not np.array_equal(first, truth.states(raws[0], 2))  # another seed, another run
    with SimTruth(tiny_scene, rules, steps=2, cache_dir=tmp_path) as again:
        assert again.missing(runs) == [] and np.array_equal(again.states(*runs[0]), first)
    from nemsim.sim import SimConfig

    with SimTruth(tiny_scene, rules, SimConfig(flux_scale=0.3), steps=2, cache_dir=tmp_path) as other:
        assert len(other.missing(runs)) == 2  # another simulator configuration: nothing is reused
    with pytest.raises(ValueError, match="steps"):
        SimTruth(tiny_scene, rules, steps=tiny_scene.n_transitions + 1)


@pytest.mark.slow  # two spawned workers import torch and numba
def test_sim_truth_workers_match_serial(tiny_scene, tmp_path):
    from nemsim.rules import compile_rules, load_rules

    rules = compile_rules(load_rules())
    runs = [(r, 1) for r in sweep_recipes(3)["flux_cl_plus"]["raw"][1:]]
    with (SimTruth(tiny_scene, rules, steps=2) as serial,
          SimTruth(tiny_scene, rules, steps=2, workers=2) as pool):
        serial.ensure(runs)
        pool.ensure(runs)
        for raw, seed in runs:
            assert np.array_equal(pool.states(raw, seed), serial.states(raw, seed))


def test_cli_bench_physics_heldout_from_a_data_file(tiny_checkpoint, tiny_scene, tmp_path):
    """--data/--splits: the split's controls become the held-out cases (re-simulated with two seeds)."""
    from nemsim.cli import main
    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter
    from nemsim.rules import compile_rules, load_rules
    from nemsim.sim import SimConfig, initial_state
    from nemsim.sim.generate import generator_meta

    data = tmp_path / "tiny.h5"
    design = lhs_design()[:3]
    # only the controls matter (the benchmark re-simulates them): every case holds x_0 for every step
    still = np.repeat(initial_state(tiny_scene)[None], tiny_scene.n_states, axis=0)
    with TrajectoryWriter(data, scene=tiny_scene, case_ids=[0, 1, 2], controls_raw=design,
                          generator=generator_meta(tiny_scene, SimConfig(), 0),
                          rules_sha256=compile_rules(load_rules()).sha256) as writer:
        for row in range(3):
            writer.write(row, still, seed=row)
    splits = tmp_path / "splits"
    splits.mkdir()
    (splits / "control-id.json").write_text(json.dumps(
        {"setting": "control-id", "train": [0], "val": [], "test": [2, 1], "unused": [],
         "visible_transitions": 100}))
    out = tmp_path / "phys"
    rc = main(["bench", "physics", "--checkpoint", str(tiny_checkpoint), "--data", str(data), "--splits",
               str(splits), "--sim-steps", "1", "--no-progress", "--out", str(out)])
    assert rc == 0
    rep = json.loads((out / "physics.json").read_text())
    assert [c["name"] for c in rep["heldout"]] == ["case-2", "case-1"]
    np.testing.assert_allclose([c["controls"] for c in rep["heldout"]], design[[2, 1]])
    args = ["bench", "physics", "--checkpoint", str(tiny_checkpoint), "--data", str(tmp_path / "no.h5")]
    assert main(args) == 2
