"""``nemsim bench monotone-eps`` / ``nemsim.model.monotone.measure_eps``: the data's fall below the running
maximum, per channel, over the voxels that change."""

from __future__ import annotations

import h5py
import numpy as np

from nemsim.model.monotone import measure_eps, running_max_drop


def test_measure_eps_matches_the_running_max_by_hand(make_file):
    path = make_file(n=4)
    rep = measure_eps(str(path), [0, 2], quantiles=(0.5, 1.0))
    with h5py.File(path, "r") as f:
        states = [np.asarray(f["states"][r], dtype=np.float32) for r in (0, 2)]
    for c, name in enumerate(("mask", "si")):
        falls = np.concatenate([
            -running_max_drop(s)[:, c][:, s[:, c].max(axis=0) > s[:, c].min(axis=0)].ravel() for s in states
        ])
        assert rep[name] == {"q0.5": float(np.quantile(falls, 0.5)), "q1": float(falls.max())}
    assert rep["cases"] == 2


def test_cli_refuses_bad_input(tmp_path, capsys):
    from nemsim.cli import main

    assert main(["bench", "monotone-eps", "--data", str(tmp_path / "missing.h5")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["bench", "monotone-eps", "--data", str(tmp_path / "x.h5"), "--max-cases", "0"]) == 2
