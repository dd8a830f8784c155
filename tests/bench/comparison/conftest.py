"""Fixtures for `nemsim bench compare`: a tiny trajectory file with its splits, a tiny training recipe and a
plan writer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

N_CASES = 5

# a few optimizer steps per "epoch", a validation after each, 3-step rollouts on one trajectory
TINY_RECIPE = """\
batch_size: 2
warmup_steps: 1
checkpoint_every: 2
batches_per_epoch: 2
val_every: 1
patience: 1000
val_cases: 1
test_cases: 1
rollout_steps: 3
"""


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory, tiny_scene, rules, synthetic_states) -> Path:
    """tiny.h5 of N_CASES synthetic cases and splits/<setting>.json next to it (3 train, 1 val, 1 test)."""
    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter

    root = tmp_path_factory.mktemp("comparedata")
    path = root / "tiny.h5"
    raw = lhs_design(N_CASES, seed=2)
    with TrajectoryWriter(path, scene=tiny_scene, case_ids=range(N_CASES), controls_raw=raw,
                          generator={"kind": "synthetic-test"}, rules_sha256=rules.sha256) as w:  # fmt: skip
        for row in range(N_CASES):
            w.write(row, synthetic_states(tiny_scene, 0.02 * (row + 1)), seed=row)
    (root / "splits").mkdir()
    for setting in ("control-id", "ood-joint", "vis-50"):
        manifest = {"setting": setting, "train": [0, 1, 2], "val": [3], "test": [4], "unused": [],
                    "visible_transitions": 5}
        (root / "splits" / f"{setting}.json").write_text(json.dumps(manifest))
    return path


@pytest.fixture()
def write_plan(tmp_path, tiny_data):
    """write_plan(runs_yaml, **top) -> plan path: a plan on the tiny data with the tiny recipe."""

    def write(runs: str, baselines: str = "[fno, cno]", sizes: str = "{fno: {small: {width: 4}}}",
              data: Path | None = None) -> Path:
        (tmp_path / "recipe.yaml").write_text(TINY_RECIPE)
        data = data or tiny_data
        plan = tmp_path / "plan.yaml"
        plan.write_text(
            f"recipe: recipe.yaml\nrecord: record\ndata: {data}\nsplits: {data.parent / 'splits'}\n"
            f"make_data: ['nemsim generate --scene tiny --out {data}', 'nemsim splits --data {data}']\n"
            f"baselines: {baselines}\nsizes: {sizes}\nruns:\n{runs}"
        )
        return plan

    return write
