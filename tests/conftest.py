"""Shared fixtures. Tests run on CPU, on the `tiny` scene, in seconds."""

from __future__ import annotations

import os

import pytest

# Keep numba/torch from oversubscribing the 2-core CI machine.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")


@pytest.fixture(scope="session")
def tiny_scene():
    from nemsim.scenes import TINY

    return TINY


@pytest.fixture(scope="session")
def rules():
    """The compiled Event Rules Library (rules/cl_si.yaml), shared by every test."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    return compile_rules(load_rules())


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory, tiny_scene, rules):
    """An untrained NEMSim checkpoint on `tiny`, written with the real save_checkpoint (full model config,
    as ``nemsim train`` stores it)."""
    import dataclasses

    import torch

    from nemsim.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, rules)
    path = tmp_path_factory.mktemp("ckpt") / "tiny_nemsim.pt"
    save_checkpoint(
        path,
        model,
        model_name="nemsim",
        model_config=dataclasses.asdict(model_config("nemsim", tiny_scene)),
        scene=tiny_scene,
        rules=rules,
        summary={"note": "untrained, for tests"},
        metrics={"avg_rmse": 0.5},
    )
    return path


def _synthetic_states(scene, rate: float):
    """(T, 2, D, H, W) float32 in [-1, 1]: a fixed mask slab and a Si plane that moves down at ``rate``."""
    import numpy as np

    C, D, H, W = scene.state_shape
    depth = np.arange(D, dtype=np.float32)[:, None, None]
    out = np.empty((scene.n_states, C, D, H, W), dtype=np.float32)
    for t in range(scene.n_states):
        out[t, 0] = np.clip((np.abs(depth - scene.resist_top + 3) - 3) / scene.d_max_vox, -1, 1)
        out[t, 1] = np.clip((depth - scene.si_top + rate * t) / scene.d_max_vox, -1, 1)
    return out


@pytest.fixture(scope="session")
def synthetic_states():
    """states(scene, rate) -> the synthetic trajectory states the tests write into data files."""
    return _synthetic_states
