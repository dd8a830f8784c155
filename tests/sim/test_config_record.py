"""SimConfig.from_record: the one reader of a checkpoint's recorded simulator configuration."""

from __future__ import annotations

import dataclasses

from nemsim.sim import SimConfig


def test_from_record_reads_a_generator_record_a_bare_meta_and_nothing():
    changed = dataclasses.replace(SimConfig(), capacity=12, flux_scale=0.5)
    meta = changed.to_meta()
    generator = {"base_seed": 0, "simulator": "nemsim.sim", "config": meta}  # a data file's generator record
    assert SimConfig.from_record(generator) == SimConfig.from_meta(meta)
    assert SimConfig.from_record(generator).capacity == 12  # the nested entry, not the defaults
    assert SimConfig.from_record(meta).flux_scale == 0.5  # a bare to_meta dict
    assert SimConfig.from_record(None) is None and SimConfig.from_record({}) is None


def test_a_record_without_simulator_constants_is_nothing_not_todays_defaults():
    """A generator record that names no constant (e.g. synthetic test data) describes no simulator: reading
    it as SimConfig() would silently rerun today's defaults instead of what made the data."""
    assert SimConfig.from_record({"kind": "synthetic-test"}) is None
    assert SimConfig.from_record({"base_seed": 0, "config": {"note": "none"}}) is None
    mirror = SimConfig.from_record({"config": {"flux_scale": 0.6}})  # a record made before the lobe existed
    assert mirror is not None and mirror.ion_reflect_spread_deg == 0.0 != SimConfig().ion_reflect_spread_deg
