"""Fixtures for the baseline tests: a structural stand-in for the rules that is enough to construct the +Prior
models (the real library is the shared ``rules`` fixture)."""

from __future__ import annotations

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



@pytest.fixture
def tiny_batch(tiny_scene):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, *tiny_scene.state_shape, generator=g) * 2 - 1  # (2, 2, 35, 15, 15)
    u = torch.rand(2, 14, generator=g) * 2 - 1
    return x, u


def as_np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()
