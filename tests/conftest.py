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
