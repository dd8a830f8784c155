"""Fixtures for the model tests: the real compiled Event Rules Library."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def rules():
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    return compile_rules(load_rules())
