"""Active learning (`nemsim learn`): the candidates cover the region as stated, the acquisition puts a recipe
far outside the box before the centre, a batch is spread out, and one round on `tiny` runs and resumes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from nemsim.cli import main
from nemsim.controls import (
    CONTROL_INDEX,
    INT_INDICES,
    check_admissible,
    from_normalized,
    from_unit,
    heldout_corners,
    lhs_design,
)
from nemsim.training.active import (
    DEFAULT_ACQUISITION,
    LearnConfig,
    LearnJob,
    ProposalConfig,
    ScoreConfig,
    best_acquisition,
    from_unit_extended,
    propose,
    round_dir,
    run_learning,
    score_candidates,
    select_batch,
    spearman,
    to_unit,
)
from nemsim.training.config import TrainConfig

ROUND_OFF = 1.0 / 20  # an exponent rounded away from the box moves at most one unit: 1/20 of angle_cl's range


def test_proposals_cover_interior_faces_corners_and_band_in_the_stated_counts():
    cfg = ProposalConfig(interior=20, faces=28, corners=8, band=30, band_controls=3, seed=3)
    cands = propose(cfg)
    assert cands.counts() == {"interior": 20, "face": 28, "corner": 8, "band": 30}
    assert check_admissible(cands.raw) == []
    ints = cands.raw[:, list(INT_INDICES)]
    np.testing.assert_array_equal(ints, np.round(ints))  # whole exponents everywhere
    unit = cands.unit
    kind = {k: unit[cands.kind == k] for k in ("interior", "face", "corner", "band")}
    assert ((kind["interior"] >= 0) & (kind["interior"] <= 1)).all()
    faces = kind["face"]
    on_face = faces[np.arange(28), np.arange(28) % 14]  # face i puts control i mod 14 on a face
    assert set(np.round(on_face, 12)) <= {0.0, 1.0} and ((faces >= 0) & (faces <= 1)).all()
    corners = np.round(kind["corner"], 12)
    assert set(corners.ravel()) == {0.0, 1.0} and len({tuple(r) for r in corners}) == 8
    held = {tuple(r) for r in np.round(to_unit(heldout_corners()), 12)}
    assert not held & {tuple(r) for r in corners}  # the physics benchmark's corners stay held out
    past = np.maximum(-kind["band"], kind["band"] - 1)  # (30, 14) how far past the box
    outside = (past > 1e-12).sum(axis=1)
    assert ((outside >= 1) & (outside <= 3)).all()
    assert past.max() <= 0.25 + ROUND_OFF
    assert (kind["band"][:, CONTROL_INDEX["angle_cl"]] >= 0).all()  # no exponent below zero
    again = propose(cfg)
    np.testing.assert_array_equal(again.raw, cands.raw)
    np.testing.assert_array_equal(again.kind, cands.kind)
    assert not np.array_equal(
        propose(ProposalConfig(interior=20, faces=28, corners=8, band=30, seed=4)).raw, cands.raw
    )


def test_unit_coordinates_past_the_box_map_by_the_normalization_rounded_away():
    xi = np.full((1, 14), 0.5)
    np.testing.assert_array_equal(from_unit_extended(xi), from_unit(xi))  # inside: the design's mapping
    xi[0, CONTROL_INDEX["angle_cl"]] = 1.1  # 20 + 0.1 * 20 = 22
    xi[0, CONTROL_INDEX["angle_cl_plus"]] = -0.01  # 50 - 0.01 * 2950 = 20.5 -> 20 (away from the box)
    xi[0, CONTROL_INDEX["energy_mean_ar_plus"]] = 1.25  # 500 + 0.25 * 340 = 585 eV
    xi[0, CONTROL_INDEX["flux_ar_plus"]] = -0.25  # 10^(-4 - 0.25 log10(70)) mol m^-2 s^-1
    xi[0, CONTROL_INDEX["angle_ar_plus"]] = -0.5  # 50 - 1475 < 0 -> clamped at 0
    raw = from_unit_extended(xi)[0]
    assert raw[CONTROL_INDEX["angle_cl"]] == 22
    assert raw[CONTROL_INDEX["angle_cl_plus"]] == 20
    assert raw[CONTROL_INDEX["energy_mean_ar_plus"]] == pytest.approx(585.0)
    assert raw[CONTROL_INDEX["flux_ar_plus"]] == pytest.approx(10 ** (-4 - 0.25 * np.log10(70)), rel=1e-9)
    assert raw[CONTROL_INDEX["angle_ar_plus"]] == 0


def test_the_batch_is_spread_out_not_copies_of_the_best_corner():
    corner = np.ones(14)
    others = np.array([np.full(14, 0.0), np.full(14, 0.5), np.r_[np.zeros(7), np.ones(7)]])
    unit = np.vstack([np.tile(corner, (8, 1)), others])  # eight copies of the best-scored point
    scores = np.r_[np.full(8, 10.0), 5.0, 4.0, 3.0]
    chosen = select_batch(unit, scores, batch=4, pool_factor=3)
    assert chosen[0] == 0 and sorted(chosen[1:]) == [8, 9, 10]
    assert list(select_batch(unit, scores, batch=2, pool_factor=1)) == [0]  # pool: copies only


def test_a_trajectory_file_holds_recipes_past_the_box(tmp_path, tiny_scene):
    """Band recipes (admissible, beyond the design box) are stored with a warning, not refused; an
    inadmissible value still fails the file's check."""
    from nemsim.data.hdf5 import TrajectoryWriter, check_dataset

    band = propose(ProposalConfig(interior=0, faces=0, corners=0, band=4)).raw
    writer = TrajectoryWriter(tmp_path / "band.h5", scene=tiny_scene, case_ids=[0, 1, 2, 3],
                              controls_raw=band, generator={"kind": "probe"}, rules_sha256="ab" * 32)
    writer.close(validate=True)
    rep = check_dataset(tmp_path / "band.h5", require_complete=False)
    assert any("beyond the design box" in w for w in rep.warnings)


def test_spearman_and_the_best_acquisition():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    assert spearman(a, 10 * a) == 1.0 and spearman(a, -a) == -1.0
    assert spearman(a, np.ones(4)) is None  # a constant acquisition cannot rank
    assert spearman(np.r_[a, np.nan], np.r_[a, 5.0]) == 1.0  # undefined values are left out
    table = {"distance": {"avg_rmse": 0.4}, "change": {"avg_rmse": 0.6}, "jitter": {"avg_rmse": None}}
    assert best_acquisition(table) == "change"


@pytest.mark.parametrize("name", sorted({"distance", DEFAULT_ACQUISITION}))
def test_a_recipe_far_outside_the_box_ranks_above_the_centre(name, tiny_checkpoint, tiny_scene, rules):
    import torch

    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.registry import build_model
    from nemsim.sim.process import initial_state

    loaded = load_checkpoint(tiny_checkpoint)
    torch.manual_seed(1)
    other = build_model("nemsim", tiny_scene, rules).eval()  # another model of the same architecture
    raw = np.stack([from_normalized(np.zeros(14)), from_normalized(np.full(14, 1.5))])  # centre, far out
    train_unit = to_unit(lhs_design(50, seed=7))
    cfg = ScoreConfig(members=2, every=2, steps=4)
    score = score_candidates(
        loaded.model, initial_state(tiny_scene), raw, [name], cfg, 4, train_unit=train_unit, second=other
    )[name]
    assert score.shape == (2,) and score[1] > score[0]


def _base_data(tmp_path, tiny_scene, rules):
    """A `tiny` trajectory file of three cheap simulated cases and its control-id split."""
    from nemsim.sim.generate import generate_dataset

    raw = lhs_design(n=3, seed=3)
    raw[:, :4] = [2e-4, 2e-4, 2e-6, 1e-3]  # low fluxes: a fraction of a second per case
    path = tmp_path / "base.h5"
    generate_dataset(path, tiny_scene, rules, raw, [0, 1, 2], seed=0, progress=False)
    splits = tmp_path / "splits"
    splits.mkdir()
    manifest = {
        "setting": "control-id",
        "train": [0],
        "val": [1],
        "test": [2],
        "unused": [],
        "visible_transitions": 100,
    }
    (splits / "control-id.json").write_text(json.dumps(manifest))
    return path, splits


@pytest.mark.slow
def test_one_round_on_tiny_runs_end_to_end_then_resumes_without_simulating(
    tmp_path, tiny_checkpoint, tiny_scene, rules, monkeypatch
):
    import nemsim.sim.generate as generate

    data, splits = _base_data(tmp_path, tiny_scene, rules)
    train = TrainConfig(
        max_steps=2,
        batch_size=2,
        warmup_steps=0,
        val_every=1,
        val_cases=1,
        rollout_steps=4,
        progress=False,
        device="cpu",
    )
    proposals = ProposalConfig(interior=4, faces=2, corners=2, band=2)
    job = LearnJob(
        checkpoint=tiny_checkpoint,
        data=data,
        out=tmp_path / "learn",
        train=train,
        splits=splits,
        config=LearnConfig(rounds=1, batch=2, acquisition="distance", proposals=proposals),
        progress=False,
    )
    (state,) = run_learning(job)
    rdir = round_dir(job.out, 1)
    assert state["ran_now"] == ["selected", "simulated", "trained"] and state["simulated_now"] == 2
    assert state["sim_domain"] == "full"  # tiny's odd grid has no quarter domain
    assert (rdir / "train" / "best.pt").is_file() and state["checkpoint"] == str(rdir / "train" / "best.pt")
    assert json.loads((rdir / "round.json").read_text())["status"] == "trained"
    from nemsim.controls import read_controls_csv
    from nemsim.data.hdf5 import open_trajectories

    with open_trajectories(rdir / "data.h5") as tf:
        assert tf.complete.all() and len(tf.case_ids) == 2
        np.testing.assert_array_equal(tf.controls_raw, read_controls_csv(rdir / "batch.csv"))
    cands = (rdir / "candidates.csv").read_text().splitlines()
    assert len(cands) == 1 + 10 and sum(line.endswith(",1") for line in cands[1:]) == 2

    def no_simulation(*args, **kwargs):
        raise AssertionError("a resumed round simulated again")

    monkeypatch.setattr(generate, "generate_dataset", no_simulation)
    (again,) = run_learning(job)
    assert again["ran_now"] == [] and again["checkpoint"] == state["checkpoint"]
    stopped = {**json.loads((rdir / "round.json").read_text()), "status": "simulated"}
    (rdir / "round.json").write_text(json.dumps(stopped))  # as if stopped while fine-tuning
    (resumed,) = run_learning(job)
    assert resumed["ran_now"] == ["trained"]
    other = dataclasses.replace(job, config=LearnConfig(rounds=1, batch=3, proposals=proposals))
    with pytest.raises(ValueError, match="other options"):
        run_learning(other)

    monkeypatch.undo()  # the baseline arm: each round's batch is `nemsim design --n 2 --seed S`
    lhs = dataclasses.replace(
        job, out=tmp_path / "lhs", config=LearnConfig(rounds=1, batch=2, acquisition="lhs")
    )
    (base,) = run_learning(lhs)
    seed = int(base["design_command"].split()[-1])
    np.testing.assert_array_equal(read_controls_csv(round_dir(lhs.out, 1) / "batch.csv"), lhs_design(2, seed))
    assert base["ran_now"] == ["selected", "simulated", "trained"]

    out = tmp_path / "measure"  # the measurement runs end to end (one test case: no correlation defined)
    argv = [
        "learn",
        "measure",
        "--checkpoint",
        str(tiny_checkpoint),
        "--data",
        str(data),
        "--splits",
        str(splits),
        "--acquisitions",
        "distance,change",
        "--every",
        "5",
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main(argv) == 0
    report = json.loads((out / "acquisitions.json").read_text())
    assert report["table"]["control-id-test"]["n"] == 1 and len(report["cases"]) == 1
    assert set(report["cases"][0]["scores"]) == {"distance", "change"} and report["cases"][0]["avg_rmse"] > 0


def test_cli_propose_writes_the_candidates_and_refuses_bad_counts(tmp_path, capsys):
    out = tmp_path / "c.csv"
    assert (
        main(
            [
                "learn",
                "propose",
                "--interior",
                "3",
                "--faces",
                "2",
                "--corners",
                "1",
                "--band",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "8 candidates (3 interior, 2 face, 1 corner, 2 band)" in capsys.readouterr().out
    lines = out.read_text().splitlines()
    assert lines[0].endswith(",kind") and [line.rsplit(",", 1)[1] for line in lines[1:]] == (
        ["interior"] * 3 + ["face"] * 2 + ["corner"] + ["band"] * 2
    )
    assert (
        main(
            [
                "learn",
                "propose",
                "--interior",
                "0",
                "--faces",
                "0",
                "--corners",
                "0",
                "--band",
                "0",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "at least one candidate" in capsys.readouterr().err


def test_a_trench_model_is_refused_with_the_reason(tmp_path, tiny_section_checkpoint):
    """Active learning simulates the checkpoint's own scene (a hole): a cross-section model is refused
    before anything is selected or simulated."""
    from nemsim.training.active import LearnConfig, LearnJob, round_dir, run_learning
    from nemsim.training.config import TrainConfig

    job = LearnJob(checkpoint=tiny_section_checkpoint, data=tmp_path / "unused.h5", out=tmp_path / "learn",
                   train=TrainConfig(max_steps=1), splits=None, config=LearnConfig(rounds=1, batch=2),
                   progress=False)
    with pytest.raises(ValueError, match="does not cover trenches"):
        run_learning(job)
    assert not (round_dir(job.out, 1) / "candidates.csv").exists()
