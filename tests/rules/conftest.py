"""Fixtures for the Event Rules Library tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def rules_text() -> str:
    from nemsim.rules.schema import default_rules_path

    return default_rules_path().read_text()


@pytest.fixture(scope="session")
def spec():
    from nemsim.rules import load_rules

    return load_rules()


@pytest.fixture(scope="session")
def tensors(spec):
    from nemsim.rules import compile_rules

    return compile_rules(spec)
