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
