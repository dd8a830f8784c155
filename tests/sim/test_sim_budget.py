"""Particle budget (``SimConfig.particle_budget``): fewer, heavier particles, the same expected etch."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.sim import SimConfig, run_trajectory


def test_quarter_budget_traces_a_quarter_of_the_particles_and_etches_as_deep(
    etch_depth_nm, tiny_scene, rules, make_controls, tiny_run
):
    u = make_controls()
    full = [tiny_run((), s) for s in (1, 2)]  # shared with the other tests of the session
    quarter = [
        run_trajectory(tiny_scene, rules, u, np.random.default_rng(s), SimConfig(particle_budget=0.25))
        for s in (1, 2)
    ]
    ratio = np.mean([q.counters["primary"] for q in quarter]) / np.mean([f.counters["primary"] for f in full])
    assert 0.22 < ratio < 0.28, ratio
    d_full = [etch_depth_nm(r, tiny_scene) for r in full]
    d_quarter = [etch_depth_nm(r, tiny_scene) for r in quarter]
    # seed-to-seed spread is ~2 nm at full and ~3 nm at 1/4 budget (4 seeds, calibration); one voxel = 8 nm
    assert abs(np.mean(d_quarter) - np.mean(d_full)) < 8.0, (d_full, d_quarter)
    # the bookkeeping still balances with weighted events
    for res in quarter:
        c = res.counters
        for t in range(5):
            expect = (res.initial_totals[t] - c[f"removed_{t}"] + c[f"deposited_{t}"]
                      - c[f"converted_from_{t}"] + c[f"converted_to_{t}"])  # fmt: skip
            assert res.final_totals[t] == expect, f"species {t}"
        assert res.domain.mat.min() >= 0 and res.domain.fill.max() <= 1 + 1e-9


def test_budget_one_is_the_calibrated_default():
    assert SimConfig().particle_budget == 1.0 and SimConfig().particle_weight == 1.0
    # not recorded at 1, so files generated before the field existed keep their generator metadata
    assert "particle_budget" not in SimConfig().to_meta()
    assert SimConfig(particle_budget=0.25).to_meta()["particle_budget"] == 0.25
    assert SimConfig.from_meta(SimConfig(particle_budget=0.25).to_meta()).particle_budget == 0.25


@pytest.mark.parametrize("bad", [0.0, -0.5, float("nan"), float("inf")])
def test_bad_budget_is_rejected(bad):
    with pytest.raises(ValueError, match="particle_budget"):
        SimConfig(particle_budget=bad)
