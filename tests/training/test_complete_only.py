"""`nemsim train --complete-only`: training on a data file still being generated (a prefix of a design)."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np

STEPS = 4  # as in tests/training/conftest.py


def _partial_copy(src, dst, unfinished: list[int]):
    """A copy of ``src`` (and the splits/ next to it) with the rows of ``unfinished`` case ids unfinished."""
    dst.mkdir()
    shutil.copy(src, dst / src.name)
    shutil.copytree(src.parent / "splits", dst / "splits")
    with h5py.File(dst / src.name, "r+") as f:
        ids = [int(c) for c in np.asarray(f["case_ids"])]
        for c in unfinished:
            f["complete"][ids.index(c)] = 0
    return dst / src.name


def test_complete_only_trains_on_the_complete_cases_and_says_so(tmp_path, tiny_data, capsys):
    from nemsim.cli import main

    data = _partial_copy(tiny_data, tmp_path / "partial", unfinished=[1, 5])  # train [0, 1, 2], test [4, 5]
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "model": {"stem": 4, "widths": [4, 6, 6], "latent_channels": 6,
                                         "context_dim": 8, "readout_width": 6, "decoder_widths": [6, 6]}}))
    args = ["train", "--model", "nemsim", "--data", str(data), "--setting", "control-id", "--epochs", "1",
            "--rollout-steps", str(STEPS), "--config", str(cfg), "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "refused")]) == 2  # the default refuses unfinished cases
    assert "unfinished" in capsys.readouterr().err
    out = tmp_path / "run"
    assert main([*args, "--out", str(out), "--complete-only"]) == 0
    log = (out / "train.log").read_text()
    assert "--complete-only: train 2 of 3, val 1 of 1, test 1 of 2" in log
    assert "2 train / 1 val / 1 test cases" in log
    assert json.loads((out / "test_metrics.json").read_text())["n_cases"] == 1
