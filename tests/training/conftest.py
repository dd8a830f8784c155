"""Fixtures for training/evaluation tests: a stand-in model, a tiny synthetic dataset, split manifests.

The synthetic trajectories are smooth and control-dependent (the Si field rises by a control-set rate per
step), so a few epochs of training make a measurable difference; the stand-in model is a two-layer
conv net with FiLM-like control injection, registered only for these tests.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

N_CASES = 6
VISIBLE = 5  # transitions used for training in the tests
STEPS = 4  # rollout length used for validation / evaluation in the tests


@dataclass(frozen=True)
class StandInConfig:
    width: int = 4  # hidden channels


class StandIn(nn.Module):
    def __init__(self, cfg: StandInConfig) -> None:
        super().__init__()
        self.inp = nn.Conv3d(2, cfg.width, 3, padding=1)
        self.film = nn.Linear(14, cfg.width)
        self.out = nn.Conv3d(cfg.width, 2, 3, padding=1)

    def forward(self, x, u):
        h = torch.tanh(self.inp(x) + self.film(u)[:, :, None, None, None])  # (B, K, D, H, W)
        return x + 0.1 * self.out(h)


def _build_standin(scene, rules, cfg: StandInConfig) -> nn.Module:
    return StandIn(cfg)


@pytest.fixture(scope="session", autouse=True)
def standin_registered():
    from nemsim.registry import register_model

    register_model("test-standin", _build_standin, StandInConfig)
    return "test-standin"



def _synthetic_states(scene, controls_norm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(T, 2, D, H, W) float32: mask fixed, Si SDF plane rising at a rate set by the controls."""
    C, D, H, W = scene.state_shape
    T = scene.n_states
    depth = np.arange(D, dtype=np.float32)[:, None, None]
    mask = np.clip((np.abs(depth - (scene.si_top + scene.resist_top) / 2) - 5) / scene.d_max_vox, -1, 1)
    rate = 0.02 * (1.5 + controls_norm[1] + 0.5 * controls_norm[3])  # voxels/step
    noise = 0.01 * rng.standard_normal((H, W)).astype(np.float32)
    out = np.empty((T, C, D, H, W), dtype=np.float32)
    for t in range(T):
        out[t, 0] = np.broadcast_to(mask, (D, H, W))
        out[t, 1] = np.clip((depth - scene.si_top + rate * t) / scene.d_max_vox + noise, -1, 1)
    return out


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory, tiny_scene, rules) -> Path:
    """A tiny-scene HDF5 with N_CASES synthetic trajectories, plus splits/<setting>.json next to it."""
    from nemsim.controls import lhs_design, to_normalized
    from nemsim.data.hdf5 import TrajectoryWriter

    root = tmp_path_factory.mktemp("tinydata")
    path = root / "tiny.h5"
    raw = lhs_design(n=N_CASES, seed=3)
    norm = to_normalized(raw)
    rng = np.random.default_rng(0)
    ids = list(range(N_CASES))
    with TrajectoryWriter(path, scene=tiny_scene, case_ids=ids, controls_raw=raw,
                          generator={"kind": "synthetic-test"}, rules_sha256=rules.sha256) as w:
        for row in range(N_CASES):
            w.write(row, _synthetic_states(tiny_scene, norm[row], rng), seed=row, meta={})
    splits = root / "splits"
    splits.mkdir()
    for setting in ("control-id", "ood-joint", "vis-50"):
        manifest = {"setting": setting, "train": [0, 1, 2], "val": [3], "test": [4, 5], "unused": [],
                    "visible_transitions": VISIBLE}
        (splits / f"{setting}.json").write_text(json.dumps(manifest))
    return path


@pytest.fixture()
def tiny_manifest(tiny_data) -> dict:
    return json.loads((tiny_data.parent / "splits" / "control-id.json").read_text())
