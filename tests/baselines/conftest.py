"""Fixtures for the baseline tests: the compiled rules (real library; tests needing RuleFeat values skip
until ``nemsim.controls`` exists) and a structural stand-in that is enough to construct the +Prior models."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch


class ShapeOnlyRules:
    """Just enough of RuleTensors to build RuleBuffers (E = 37 events, M = 3 families); no kinetics."""

    names = tuple(f"event_{i}" for i in range(37))
    sha256 = "shape-only"

    def torch_buffers(self) -> dict[str, torch.Tensor]:
        return {"alpha0": torch.full((37, 3), 1.0 / 3.0)}


@pytest.fixture(scope="session")
def shape_rules():
    return ShapeOnlyRules()


@pytest.fixture(scope="session")
def rules():
    if importlib.util.find_spec("nemsim.controls") is None:
        pytest.skip("nemsim.controls (data module) not available: the rules library cannot be compiled")
    from nemsim.rules import compile_rules, load_rules

    return compile_rules(load_rules())


@pytest.fixture
def tiny_batch(tiny_scene):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, *tiny_scene.state_shape, generator=g) * 2 - 1  # (2, 2, 35, 15, 15)
    u = torch.rand(2, 14, generator=g) * 2 - 1
    return x, u


def as_np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()
