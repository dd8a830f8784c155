"""Numba kernels: sampling laws, transport, reflection and the rules binding."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.sim import kernels as K
from nemsim.sim.events import ACT_DEPOSIT, ACT_REACT, ACT_REMOVE, build_event_tables


def test_cos_power_polar_mean():
    # p(Omega) ~ cos^m theta on the hemisphere -> E[cos theta] = (m + 1) / (m + 2)
    for m in (0.0, 5.0, 200.0):
        K.seed_rng(1)
        c = np.array([K.cos_power_polar(m) for _ in range(20_000)])
        assert abs(c.mean() - (m + 1) / (m + 2)) < 0.01
        assert c.min() >= 0 and c.max() <= 1


def test_cosine_about_is_lambertian_around_the_normal():
    K.seed_rng(2)
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    d = np.array([K.cosine_about(*n) for _ in range(20_000)])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-9)
    cos = d @ n
    assert cos.min() >= 0
    assert abs(cos.mean() - 2 / 3) < 0.01  # E[cos] of a cosine-weighted hemisphere


def test_stochastic_round_expectation():
    K.seed_rng(3)
    vals = np.array([K.stochastic_round(1.3) for _ in range(20_000)])
    assert set(np.unique(vals)) == {1, 2}
    assert abs(vals.mean() - 1.3) < 0.02
    assert K.stochastic_round(0.0) == 0 and K.stochastic_round(2.0) == 2


def test_unsaturated_probability_grows_above_e_ref(rules):
    from nemsim.rules.kinetics import prob_physical

    e = list(rules.names).index("Clp_on_SiCl2_chem")
    pp = np.ascontiguousarray(rules.prob_params[e])
    p = [prob_physical(1, pp, 2, en, 1.0) * K.unsaturated_factor(1, pp, en) for en in (50.0, 160.0, 500.0)]
    assert p[0] < p[1] < p[2]
    e_th, e_ref, p0, n_exp = pp[:4]
    assert p[2] == pytest.approx(p0 * ((500 - e_th) / (e_ref - e_th)) ** n_exp, rel=1e-5)


def test_event_tables_follow_the_rules(rules, sim_config):
    t = build_event_tables(rules, sim_config)
    names = list(rules.names)
    assert t.action[names.index("Cl_on_Si_to_SiCl")] == ACT_REACT
    assert t.conv_to[names.index("Cl_on_Si_to_SiCl")] == 1  # -> SiCl
    assert t.action[names.index("Clp_on_SiCl_chem")] == ACT_REMOVE
    assert t.action[names.index("SiCl_dep_on_Si")] == ACT_DEPOSIT
    # Cl+ on SiCl: the physical and the chemical branch compete
    from nemsim.rules.vocab import PROJECTILES, TARGETS

    pair = PROJECTILES.index("Cl+") * len(TARGETS) + TARGETS.index("SiCl")
    assert t.pair_count[pair] == 2
    # the four incident sources and their control bindings come from the rules
    assert sorted(PROJECTILES[s] for s in t.src_species) == ["Ar+", "Cl", "Cl+", "Cl2+"]
    # dropped events never fire
    drop = np.arange(len(names)) == names.index("Cl_on_Si_to_SiCl")
    masked = rules.replace(event_mask=np.where(drop, 0.0, 1.0))
    assert build_event_tables(masked, sim_config).action[names.index("Cl_on_Si_to_SiCl")] == 0


def _slab(nx=8, ny=8, nz=12, top=5, cap=16):
    mat = np.zeros((nx, ny, nz, 5), dtype=np.int32)
    mat[:, :, :top, 0] = cap
    fill = mat[..., :4].sum(-1) / cap
    return mat, fill.astype(np.float64)


def _fly(tables, mat, fill, species, energy, pos, direction, counters, max_steps=10_000):
    buf = K.WorkBuffers(np.zeros((64, 8)), np.zeros(tables.max_channels), counters,
                        np.zeros(len(tables.action), dtype=np.int64))  # fmt: skip
    prm = K.TransportParams(cap=16.0, rcap=16.0, product_energy=2.0, max_steps=max_steps)
    return K.fly(species, energy, *pos, *direction, mat, fill, tables.kernel_tables(), prm, buf, 0, 0)


def test_sub_threshold_ion_reflects_specularly_and_escapes(rules, sim_config):
    from nemsim.rules.vocab import PROJECTILES

    tables = build_event_tables(rules, sim_config)
    mat, fill = _slab()
    before = mat.copy()
    counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
    K.seed_rng(0)
    # Ar+ with 1 eV: below every threshold -> no reaction, specular reflection off the flat top, out the top
    d = np.array([0.3, 0.1, -1.0])
    d /= np.linalg.norm(d)
    _fly(tables, mat, fill, PROJECTILES.index("Ar+"), 1.0, (3.5, 3.5, 11.99), d, counters)
    assert counters[K.C_HITS] == 1 and counters[K.C_ESC_TOP] == 1 and counters[K.C_REACTIONS] == 0
    np.testing.assert_array_equal(mat, before)


def test_periodic_wrap_and_step_limit(rules, sim_config):
    from nemsim.rules.vocab import PROJECTILES

    tables = build_event_tables(rules, sim_config)
    mat, fill = _slab(top=0)  # empty box
    counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
    # nearly horizontal flight: wraps around x many times before it leaves through the bottom
    d = np.array([1.0, 0.0, -0.01])
    d /= np.linalg.norm(d)
    _fly(tables, mat, fill, PROJECTILES.index("Cl"), 0.2, (3.5, 3.5, 11.5), d, counters)
    assert counters[K.C_ESC_BOTTOM] == 1 and counters[K.C_STEPS] > 3 * 8
    counters[:] = 0
    _fly(tables, mat, fill, PROJECTILES.index("Cl"), 0.2, (3.5, 3.5, 11.5), d, counters, max_steps=50)
    assert counters[K.C_STEP_LIMIT] == 1 and counters[K.C_STEPS] == 50


# sha256 of (states, event_counts, final mat, counters) of a 10-transition `tiny` run of design row 3, seed 0,
# recorded with the simulator that generated the shipped data sets ("default", with the specular lobe) and
# the one before the lobe ("specular", the data of earlier checkpoints). The data files and the checkpoints
# trained on them depend on this output: a change to the kernels must keep it bit for bit, or be a
# deliberate simulator change that updates these digests and regenerates the data.
FIXED_SEED_DIGESTS = {
    "default": "b206bfd214b99fb936e9bc200307cca1f74a14eef890885525d0ca75791da6ce",
    "specular": "e16acac55b4534d60615d10100c4b54df4780db9926b888c654f890137f71c02",
    "budget-0.5+reflection": "697ed450f40335169f4407f1a31990fc202ada66d2e9681fd60a84023845800d",
}


@pytest.mark.parametrize("name", sorted(FIXED_SEED_DIGESTS))
def test_fixed_seed_output_is_bit_identical(name, rules):
    import hashlib

    from nemsim.controls import lhs_design
    from nemsim.scenes import TINY
    from nemsim.sim import SimConfig, run_trajectory

    cfg = {
        "default": SimConfig(),
        "specular": SimConfig(ion_reflect_spread_deg=0.0),
        "budget-0.5+reflection": SimConfig(
            particle_budget=0.5, ion_absorb_below_deg=20.0, ion_reflect_above_deg=70.0,
            excess_probability_yield=False, ion_reflect_spread_deg=0.0,
        ),
    }[name]  # fmt: skip
    res = run_trajectory(TINY, rules, lhs_design()[3], np.random.default_rng(0), cfg, n_transitions=10)
    if name.startswith("budget"):
        assert res.counters["absorbed"] > 0  # the reflection law and the weighted events are exercised
    digest = hashlib.sha256()
    counters = np.array(list(res.counters.values()), dtype=np.int64)
    for a in (res.states, res.event_counts, res.domain.mat, counters):
        digest.update(np.ascontiguousarray(a).tobytes())
    assert digest.hexdigest() == FIXED_SEED_DIGESTS[name]
