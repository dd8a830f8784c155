"""Optional simulator mechanisms (``SimConfig``; off by default): literature-calibrated sputtering, resist
sputter scale, ion reflection (diffuse, specular lobe, retained energy), broad-angle ion wing, and the
equivalent-diameter bulge of ``bench bowing``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from bench.yields import LITERATURE, fire
from nemsim.rules import compile_rules, parse_rules
from nemsim.rules.vocab import PROJECTILES
from nemsim.sim import SimConfig
from nemsim.sim import kernels as K
from nemsim.sim.events import build_event_tables

AR = PROJECTILES.index("Ar+")

# One rule: Ar+ removes a unit of SiCl2 when it arrives above 20 eV (p >= 1 from 25 eV); Ar+ on Si has no
# rule, so Si walls always reflect it. Floors are SiCl2, walls Si: where the floor loses material is where
# the reflected ion landed.
_FLOOR_RULES = """
version: 1
name: floor_only
events:
  - name: Arp_on_SiCl2_floor
    group: both
    projectile: Ar+
    target: SiCl2
    effect: etch
    flux_key: flux_ar_plus
    angle_key: angle_ar_plus
    E_mean_key: energy_mean_ar_plus
    E_std_key: energy_std_ar_plus
    prob_model: probModel
    prob_params: {E_th: 20, E_ref: 25, p0: 1.0, n: 0.5, angle: None}
    yield_model: const
    yield_params: {Y_const: 1.0}
    products: []
"""


@pytest.fixture(scope="module")
def floor_rules():
    return compile_rules(parse_rules(_FLOOR_RULES))


def _wall_and_floor(nx=8, ny=16, nz=24):
    """Si walls at x = 6, 7 and (periodically) x = 0 over the full height; one SiCl2 floor layer at z = 0."""
    mat = np.zeros((nx, ny, nz, 5), dtype=np.int32)
    mat[6:, :, :, 0] = 16
    mat[0, :, :, 0] = 16
    mat[1:6, :, 0, 2] = 16
    return mat


def _landings(rules, config, n, energy=60.0, seed=0):
    """Fire n Ar+ from (3, 8.5, top) towards the x = 6 wall (0.3 of the way sideways); per ion, the floor
    voxel (x, y) that lost material, or None. The domain is restored before every ion."""
    tables = build_event_tables(rules, config)
    mat0 = _wall_and_floor()
    fill0 = (mat0[..., :4].sum(-1) / 16.0).astype(np.float64)
    prm = K.transport_params(config, 16.0, 16.0)
    tab = tables.kernel_tables()
    d = (0.3, 0.0, -math.sqrt(1.0 - 0.09))
    K.seed_rng(seed)
    out = []
    for _ in range(n):
        mat, fill = mat0.copy(), fill0.copy()
        buf = K.WorkBuffers.new(tables.max_channels, len(tables.action), 64)
        K.fly(AR, energy, 3.0, 8.5, mat.shape[2] - 1e-9, *d, mat, fill, tab, prm, buf, 0, 0)
        lost = np.argwhere(mat0[:, :, 0, 2] - mat[:, :, 0, 2] > 0)
        out.append(tuple(int(v) for v in lost[0]) if len(lost) else None)
    return out


def test_specular_ion_lands_where_geometry_says(floor_rules):
    # wall x = 6 reached after 3 voxels sideways, at z = 24 - 3 * 0.954 / 0.3 = 14.46; mirrored, it falls
    # 13.46 voxels to the floor top (z = 1) and moves 13.46 * 0.3 / 0.954 = 4.23 back: x = 1.77, y = 8.5
    hits = _landings(floor_rules, SimConfig(ion_reflect_spread_deg=0.0), 20)  # a mirror, no lobe
    assert hits == [(1, 8)] * 20


def test_specular_lobe_spreads_landings_about_the_specular_point(floor_rules):
    sigma = 10.0
    hits = _landings(floor_rules, SimConfig(ion_reflect_spread_deg=sigma), 400, seed=1)
    pts = np.array([h for h in hits if h is not None], dtype=float)
    assert len(pts) > 300  # most still reach the floor
    # landing y spread ~ path length after the wall (14.1 voxels) x sigma (rad) = 2.5 voxels (uniform over
    # the 16-voxel periodic y would be 4.6)
    spread_y = pts[:, 1].std()
    assert 1.5 < spread_y < 3.5
    assert abs(pts[:, 1].mean() + 0.5 - 8.5) < 0.4  # centred on the specular point (voxel centres + 0.5)
    assert np.mean([h == (1, 8) for h in hits]) < 0.2  # most land off the specular voxel (100 % without lobe)


def test_diffuse_reflection_sends_ions_back_up(floor_rules):
    lobe = _landings(floor_rules, SimConfig(ion_reflect_spread_deg=10.0), 300, seed=2)
    diffuse = _landings(floor_rules, SimConfig(ion_reflect_diffuse=1.0), 300, seed=2)
    # a cosine lobe about the wall normal (-x) points upward half the time: far fewer ions reach the floor
    # on their first descent, and the ones that do are spread over the floor
    assert sum(h is None for h in diffuse) > sum(h is None for h in lobe) + 30
    landed = np.array([h for h in diffuse if h is not None], dtype=float)
    assert landed[:, 1].std() > 1.0


def test_retained_energy_decides_whether_the_reflected_ion_still_etches(floor_rules):
    # 30 eV ion, grazing the wall (incidence cosine 0.3): the mass-ratio law keeps 91 % (27 eV > E_th =
    # 20 eV, etches the floor); keeping 50 % leaves 15 eV, below threshold: it reflects off the floor
    mirror = SimConfig(ion_reflect_spread_deg=0.0)
    mass_law = _landings(floor_rules, mirror, 10, energy=30.0)
    half = _landings(floor_rules, replace(mirror, ion_reflect_energy=0.5), 10, energy=30.0)
    assert mass_law == [(1, 8)] * 10 and half == [None] * 10


def test_broad_angle_wing_reaches_the_sidewalls(rules):
    """Near-vertical ions (m = 3000) launched over a 6-voxel-wide, 40-voxel-deep slot hardly touch its
    walls; a wing at m = 5 (typical tilt 24 deg: ~18 voxels sideways over the depth) mostly does."""
    nx, ny, nz = 8, 8, 40
    mat = np.zeros((nx, ny, nz, 5), dtype=np.int32)
    mat[6:, :, :, 0] = 16  # walls x = 6, 7 (periodic box: slot 0 <= x < 6)
    fill = (mat[..., :4].sum(-1) / 16.0).astype(np.float64)
    src = K.Sources(np.array([AR]), np.array([1.0]), np.array([3000.0]), np.array([1.0]), np.array([0.0]))

    def hits_per_ion(wing: float) -> float:
        cfg = SimConfig(ion_wing_fraction=wing, ion_wing_m=5.0)
        tables = build_event_tables(rules, cfg)
        buf = K.WorkBuffers.new(tables.max_channels, len(tables.action), 1 << 10)
        prm = K.transport_params(cfg, 16.0, 16.0)
        K.run_particles(mat.copy(), fill.copy(), 4000, True, src, 0.2, tables.kernel_tables(), prm, buf, 3)
        assert buf.counters[K.C_REACTIONS] == 0  # 1 eV Ar+: only reflections
        return buf.counters[K.C_HITS] / 4000

    # without the wing: the quarter of the ions launched over the walls' top (x >= 6) hit once, the
    # slot's near-vertical ions (1 deg rms, 0.7 voxel sideways over the depth) rarely touch a wall; with
    # it, half of the slot's ions bounce between the walls ~3 times on the way down
    none, half = hits_per_ion(0.0), hits_per_ion(0.5)
    assert none < 0.45
    assert half > none + 0.5


def test_laegreid_wehner_calibration_brings_ar_sputtering_within_factor_2(rules):
    cal = SimConfig(sputter_calibration="laegreid_wehner")
    refs = [(x, ref) for case, _, x, ref, _ in LITERATURE if case == "ar+_on_si" and ref is not None]
    assert len(refs) == 4
    for energy, ref in refs:
        y_cal = fire(rules, cal, "Ar+", "Si", energy, 0.0, 1500, seed=4)[0]
        assert 0.5 <= y_cal / ref <= 2.0, (energy, y_cal, ref)
    # the paper's table (default) is 3-6x low at the high end
    assert fire(rules, SimConfig(), "Ar+", "Si", 600.0, 0.0, 1500, seed=4)[0] / 0.53 < 0.5


def test_rule_options_change_only_their_rules(rules):
    names = list(rules.names)
    base = build_event_tables(rules, SimConfig()).prob_params
    np.testing.assert_array_equal(base, rules.prob_params)  # defaults: the rules as written
    cal = build_event_tables(rules, SimConfig(sputter_calibration="laegreid_wehner")).prob_params
    changed = sorted(names[e] for e in np.flatnonzero((cal != base).any(axis=1)))
    assert changed == ["Arp_on_Si_phys"]
    e = names.index("Arp_on_Si_phys")
    assert cal[e, 2] == pytest.approx(0.075 / SimConfig().flux_scale) and cal[e, 3] == 1.0
    facet = build_event_tables(rules, SimConfig(resist_sputter_scale=3.0)).prob_params
    changed = sorted(names[e] for e in np.flatnonzero((facet != base).any(axis=1)))
    assert changed == ["Arp_on_Resist_phys", "Cl2p_on_Resist_phys", "Clp_on_Resist_phys"]
    np.testing.assert_allclose(facet[names.index("Clp_on_Resist_phys"), 2], 0.03)


def test_resist_sputter_scale_multiplies_the_resist_yield(rules):
    base, se0 = fire(rules, SimConfig(), "Cl+", "Resist", 300.0, 60.0, 4000, seed=5)
    scaled, se1 = fire(rules, SimConfig(resist_sputter_scale=3.0), "Cl+", "Resist", 300.0, 60.0, 4000, seed=5)
    assert abs(scaled - 3.0 * base) < 4.0 * math.hypot(se1, 3.0 * se0)


def test_options_are_validated_recorded_and_absent_from_default_records():
    meta = SimConfig().to_meta()
    for key in ("sputter_calibration", "resist_sputter_scale", "ion_reflect_diffuse", "ion_wing_fraction"):
        assert key not in meta  # files made before the options existed stay resumable
    assert meta["ion_reflect_spread_deg"] == 10.0  # the lobe is on by default and recorded
    old = {k: v for k, v in meta.items() if k != "ion_reflect_spread_deg"}  # a file made before the lobe
    assert SimConfig.from_meta(old).ion_reflect_spread_deg == 0.0
    cfg = SimConfig(sputter_calibration="laegreid_wehner", ion_reflect_spread_deg=8.0, resist_sputter_scale=2)
    assert SimConfig.from_meta(cfg.to_meta()) == cfg
    for bad in ({"sputter_calibration": "nope"}, {"ion_reflect_diffuse": 1.5}, {"ion_reflect_spread_deg": 60},
                {"resist_sputter_scale": -1.0}, {"ion_wing_fraction": 2.0}):  # fmt: skip
        with pytest.raises(ValueError):
            SimConfig(**bad)  # type: ignore[arg-type]


def test_bulge_of_an_equivalent_diameter_profile():
    from bench.bowing import bulge, equivalent_diameters
    from nemsim.scenes import TINY

    # straight 4-voxel-wide square hole: no bulge; widen rows 3 and 4 below the top Si row by a voxel a side
    si = np.ones((TINY.nx, TINY.ny, TINY.nz), dtype=np.float32)
    top = TINY.si_top - 1
    si[4:8, 4:8, top - 9 : top + 1] = 0.0
    d = equivalent_diameters(si, TINY)
    assert d[0] == pytest.approx(2 * math.sqrt(16 * 64 / math.pi))
    assert bulge(d, TINY.voxel_nm) == (0.0, 0.0)
    si[3:9, 3:9, top - 4 : top - 2] = 0.0
    bow, depth = bulge(equivalent_diameters(si, TINY), TINY.voxel_nm)
    assert bow == pytest.approx(2 * math.sqrt(36 * 64 / math.pi) - 2 * math.sqrt(16 * 64 / math.pi))
    assert depth == pytest.approx(3.5 * TINY.voxel_nm)  # rows 3 and 4 below the top Si row: the first
