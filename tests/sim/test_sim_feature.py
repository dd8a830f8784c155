"""The simulator on any Feature: holes of any CD and mask, the 3-D trench and the trench's cross-section."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.controls import from_unit
from nemsim.geometry.feature import Feature
from nemsim.scenes import TINY
from nemsim.sim import SimConfig, initial_state, run_trajectory

CENTRE = from_unit(np.full(14, 0.5))  # (14,) the centre of the control box
SECTION = SimConfig(domain="section")
TRENCH = Feature("trench", 40.0, 80.0).apply(TINY)


def test_hole_of_any_cd_and_mask_simulates(rules):
    scene = Feature("hole", 24.0, 120.0).apply(TINY)
    r = run_trajectory(scene, rules, CENTRE, np.random.default_rng(0), n_transitions=5)
    assert r.states.shape == (6, *TINY.state_shape)
    np.testing.assert_array_equal(r.states[0], initial_state(scene))
    assert r.counters["primary"] > 0


def test_section_refuses_a_hole_and_records_its_domain():
    with pytest.raises(ValueError, match="cross-section"):
        initial_state(TINY, SECTION)
    meta = SimConfig(domain="section", section_ny=3).to_meta(TRENCH)
    assert meta["domain"] == "section" and meta["section_ny"] == 3
    assert SimConfig.from_meta(meta).section_ny == 3
    assert "section_ny" not in SimConfig().to_meta(TRENCH)  # the default is not a record's change


def test_section_states_are_full_y_invariant_and_mirrored(rules):
    r = run_trajectory(TRENCH, rules, CENTRE, np.random.default_rng(3), SECTION, n_transitions=10)
    assert r.states.shape == (11, *TINY.state_shape)
    np.testing.assert_array_equal(r.states[0], initial_state(TRENCH, SECTION))
    np.testing.assert_array_equal(r.states, np.broadcast_to(r.states[:, :, :, :1], r.states.shape))
    np.testing.assert_array_equal(r.states, r.states[..., ::-1])
    assert r.full_domain().mat.shape == (TINY.nx, TINY.ny, TINY.nz, 5)
    # the section's x0 is the 3-D trench's up to Psi's raster-order error
    d = initial_state(TRENCH, SECTION) - initial_state(TRENCH)
    assert float(np.sqrt((d**2).mean())) < 5e-3


def test_section_agrees_with_the_3d_trench(rules):
    """The y-mean Si field of the 3-D trench against the cross-section's, two seeds each, after 5 s: their
    difference is within a few seed-to-seed spreads (a loose bound; the measurement on small is the
    report's)."""
    steps = 50

    def run(cfg: SimConfig, seed: int) -> np.ndarray:
        r = run_trajectory(TRENCH, rules, CENTRE, np.random.default_rng(seed), cfg, n_transitions=steps)
        return r.states[-1, 1].mean(axis=1)  # (D, W) y-mean Si channel

    full = [run(SimConfig(), s) for s in (1, 2)]
    sec = [run(SECTION, s) for s in (1, 2)]
    rms = lambda a: float(np.sqrt((a**2).mean()))  # noqa: E731
    diff = rms(0.5 * (full[0] + full[1]) - 0.5 * (sec[0] + sec[1]))
    noise = np.hypot(rms(full[0] - full[1]), rms(sec[0] - sec[1])) / 2.0  # sd of the difference of means
    assert diff < 4.0 * noise + 1e-3, (diff, noise)
    assert np.any(full[0] < 0.9) and np.any(full[0] > 0.0)  # the trench etched
