"""Surface physics of the simulator: ion reflection geometry, the ion reflection law, the excess-probability
yield, the resist's angular sputter yield and the ``bench yields`` command."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.yields import fire
from nemsim.rules.vocab import PROJECTILES
from nemsim.sim import SimConfig
from nemsim.sim import kernels as K
from nemsim.sim.events import build_event_tables


def _fly(tables, mat, fill, species, energy, pos, direction, counters, config=None):
    buf = K.WorkBuffers(np.zeros((64, 8)), np.zeros(tables.max_channels), counters,
                        np.zeros(len(tables.action), dtype=np.int64))  # fmt: skip
    prm = K.transport_params(config or SimConfig(), 16.0, 16.0)
    return K.fly(species, energy, *pos, *direction, mat, fill, tables.kernel_tables(), prm, buf, 0, 0)


def _two_walls(nx=8, ny=8, nz=12):
    """Vertical Si walls: columns x = 6, 7 and (periodically) x = 0 are solid over the full height."""
    mat = np.zeros((nx, ny, nz, 5), dtype=np.int32)
    mat[6:, :, :, 0] = 16
    mat[0, :, :, 0] = 16
    return mat, (mat[..., :4].sum(-1) / 16.0).astype(np.float64)


@pytest.mark.parametrize(
    "direction, hits",
    [
        # wall at x = 6 reached at z = 7.99, mirrored; wall at x = 1 reached at z = 1.32, mirrored; out the
        # bottom at x = 1.99 without a third hit
        ((0.6, 0.0, -0.8), 2),
        # steeper: after the first wall (z = 2.45) it leaves through the bottom at x = 5.23 < 6 - 4.77
        ((0.3, 0.0, -math.sqrt(1 - 0.09)), 1),
    ],
)
def test_ion_reflected_off_vertical_walls_lands_where_geometry_says(rules, direction, hits):
    tables = build_event_tables(rules, SimConfig())
    mat, fill = _two_walls()
    before = mat.copy()
    counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
    K.seed_rng(0)
    # Ar+ at 1 eV: below every threshold, so every wall contact is a specular reflection
    _fly(tables, mat, fill, PROJECTILES.index("Ar+"), 1.0, (3.0, 3.5, 11.99), direction, counters)
    assert counters[K.C_HITS] == hits
    assert counters[K.C_ESC_BOTTOM] == 1 and counters[K.C_ESC_TOP] == 0 and counters[K.C_REACTIONS] == 0
    np.testing.assert_array_equal(mat, before)


def test_reflection_probability_law():
    cfull, czero = math.cos(math.radians(75.0)), math.cos(math.radians(45.0))
    assert K.reflection_probability(1.0, cfull, czero) == 0.0
    assert K.reflection_probability(math.cos(math.radians(80.0)), cfull, czero) == 1.0
    assert K.reflection_probability(math.cos(math.radians(60.0)), cfull, czero) == pytest.approx(0.5)


def _slab(nx=8, ny=8, nz=12, top=5):
    mat = np.zeros((nx, ny, nz, 5), dtype=np.int32)
    mat[:, :, :top, 0] = 16
    return mat, (mat[..., :4].sum(-1) / 16.0).astype(np.float64)


@pytest.mark.parametrize("angle_deg, absorbed", [(0.0, 1), (82.0, 0)])
def test_ion_reflection_law_absorbs_near_normal_ions_only(rules, angle_deg, absorbed):
    cfg = SimConfig(ion_absorb_below_deg=45.0, ion_reflect_above_deg=75.0)
    tables = build_event_tables(rules, cfg)
    th = math.radians(angle_deg)
    d = (math.sin(th), 0.0, -math.cos(th))
    for config, expect in ((cfg, absorbed), (SimConfig(), 0)):  # default: every non-reacting ion reflects
        mat, fill = _slab()
        counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
        K.seed_rng(0)
        _fly(tables, mat, fill, PROJECTILES.index("Ar+"), 1.0, (3.5, 3.5, 11.99), d, counters, config)
        assert counters[K.C_ABSORBED] == expect
        assert counters[K.C_ESC_TOP] == 1 - expect


def test_reflection_law_config_is_validated():
    with pytest.raises(ValueError, match="ion_absorb_below_deg"):
        SimConfig(ion_absorb_below_deg=80.0, ion_reflect_above_deg=60.0)
    assert SimConfig().reflection_cosines == (1.0, 1.0)


def test_excess_probability_yield_keeps_cl_ion_yield_rising_with_energy(rules):
    # Cl+ on Cl-saturated Si at 500 eV: the chemical channels' unsaturated probabilities sum above 1
    on = fire(rules, SimConfig(), "Cl+", "SiCl2", 500.0, 0.0, 400, seed=1)[0]
    off = fire(rules, SimConfig(excess_probability_yield=False), "Cl+", "SiCl2", 500.0, 0.0, 400, seed=1)[0]
    assert off == pytest.approx(0.6)  # capped at one unit per ion (flux_scale x 1)
    assert on > 0.65  # p = 0.5 ((500 - 10) / 90)^0.5 = 1.17 units: 0.70 expected
    low = fire(rules, SimConfig(), "Cl+", "SiCl2", 100.0, 0.0, 400, seed=1)[0]
    assert low < on


def test_grazing_ion_sputters_resist_more_than_a_normal_one(rules):
    normal, se0 = fire(rules, SimConfig(), "Cl+", "Resist", 300.0, 0.0, 3000, seed=2)
    grazing, se1 = fire(rules, SimConfig(), "Cl+", "Resist", 300.0, 60.0, 3000, seed=2)
    assert grazing - normal > 3.0 * math.hypot(se0, se1)


def test_bench_yields_cli_writes_and_refuses_to_overwrite(tmp_path):
    from nemsim.cli import main

    out = tmp_path / "y"
    assert main(["bench", "yields", "--n", "4", "--out", str(out)]) == 0
    assert (tmp_path / "y.md").read_text().count("Laegreid & Wehner") == 4
    assert '"comparison"' in (tmp_path / "y.json").read_text()
    assert main(["bench", "yields", "--n", "4", "--out", str(out)]) == 2


def test_bench_bowing_cli_on_tiny(tmp_path):
    import json

    from nemsim.cli import main

    out = tmp_path / "b"
    args = ["bench", "bowing", "--scene", "tiny", "--m", "50", "--energies", "500", "--ion-q", "0.8"]
    assert main([*args, "--before", "--out", str(out)]) == 0
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["variant"] for r in rows] == ["after", "before"]
    assert all(r["bowing"] >= 0 and r["bowing_unsmoothed"] >= 0 and r["etch_depth"] > 0 for r in rows)
    assert "Command: nemsim bench bowing --scene tiny" in (tmp_path / "b.md").read_text()
    assert main([*args, "--out", str(out)]) == 2  # never overwrites
    assert main([*args, "--ion-q", "2", "--out", str(tmp_path / "c")]) == 2
    # optional mechanisms as named variants; every row carries the equivalent-diameter bulge and profile
    var = ["--variant", "facet:resist_sputter_scale=3,ion_reflect_spread_deg=9", "--out", str(tmp_path / "v")]
    assert main([*args, "--seed", "0", *var]) == 0
    rows = json.loads((tmp_path / "v.json").read_text())["rows"]
    assert [r["variant"] for r in rows] == ["base", "facet"]
    assert all(r["bowing_area"] >= 0 and len(r["diameter_profile"]) == 20 for r in rows)
    assert "--variant facet:resist_sputter_scale=3" in (tmp_path / "v.md").read_text()
    for bad in ("facet", "x:nope=1", "x:ion_reflect_diffuse=3", "base:ion_reflect_diffuse=0.5"):
        assert main([*args, "--variant", bad, "--out", str(tmp_path / "w")]) == 2


def test_config_meta_round_trip_and_records_made_before_the_mechanisms():
    cfg = SimConfig(ion_absorb_below_deg=30.0, ion_reflect_above_deg=70.0)
    assert SimConfig.from_meta(cfg.to_meta()) == cfg
    old = SimConfig().to_meta()
    for key in ("excess_probability_yield", "ion_absorb_below_deg", "ion_reflect_above_deg"):
        del old[key]
    restored = SimConfig.from_meta(old)  # a data file written before these fields existed
    assert restored.excess_probability_yield is False and restored.reflection_cosines == (1.0, 1.0)
