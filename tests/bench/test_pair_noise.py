"""`nemsim bench pair-noise`: the noise of a sweep pair's difference with and without common random numbers,
checked by hand on constant synthetic states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.noise import bench_pair_noise, pair_group
from nemsim.cli import main
from nemsim.controls import lhs_design, set_group
from nemsim.data.hdf5 import TrajectoryWriter


def _pair_file(path, scene, levels: tuple[float, float], seed: int, raw: np.ndarray) -> None:
    """Cases 0 (a) and 1 (b) sharing ``seed``, every state after t = 0 the constant ``levels[m]``."""
    with TrajectoryWriter(path, scene=scene, case_ids=[0, 1], controls_raw=raw,
                          generator={"kind": "synthetic-test"}, rules_sha256="ab" * 32) as w:
        for row, level in enumerate(levels):
            states = np.full((scene.n_states, *scene.state_shape), level, dtype=np.float32)
            states[0] = 0.0
            w.write(row, states, seed=seed, meta={})


def test_pair_noise_by_hand(tmp_path, tiny_scene, capsys):
    base = lhs_design(1, 3)[0]
    raw = np.stack([base, set_group(base, ("flux_cl",), 0.9)])
    assert pair_group(raw[0], raw[1]) == "flux_cl" and pair_group(raw[0], raw[0]) == "none"
    assert pair_group(raw[0], set_group(base, ("flux_cl", "angle_cl"), 0.37)) == "mixed"
    one, two = tmp_path / "s1.h5", tmp_path / "s2.h5"
    _pair_file(one, tiny_scene, (0.0, 0.3), 11, raw)  # D_1 = 0.3
    _pair_file(two, tiny_scene, (0.1, 0.5), 12, raw)  # D_2 = 0.4
    rep = bench_pair_noise(str(one), str(two))
    field = rep["all"]["field"]
    assert rep["all"]["n_pairs"] == 1 and list(rep["by_group"]) == ["flux_cl"]
    assert field["response"] == pytest.approx(0.35)
    assert field["crn_noise"] == pytest.approx(0.1 / math.sqrt(2))
    # independent seeds: (0.5 - 0.0) - (0.3 - 0.1) = 0.3
    assert field["independent_noise"] == pytest.approx(0.3 / math.sqrt(2))

    assert main(["bench", "pair-noise", "--data", str(one), "--other", str(two)]) == 0
    out = capsys.readouterr().out
    assert "1 pairs under two base seeds" in out and "flux_cl" in out and "0.3500 / 0.0707 / 0.2121" in out
    assert main(["bench", "pair-noise", "--data", str(one), "--other", str(tmp_path / "none.h5")]) == 2
    assert "no such file" in capsys.readouterr().err
