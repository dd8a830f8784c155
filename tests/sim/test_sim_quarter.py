"""The quarter domain (``SimConfig.domain = "quarter"``): mirror walls in the kernels, the mirrored states,
the bookkeeping, the odd-grid refusal and the record. `tiny` is odd (13 x 13), so these runs use `small` for
a few transitions."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from nemsim.rules.vocab import PROJECTILES
from nemsim.scenes import SMALL, TINY
from nemsim.sim import SimConfig, initial_state, run_trajectory
from nemsim.sim import kernels as K
from nemsim.sim.events import build_event_tables

QUARTER = SimConfig(domain="quarter")


@pytest.fixture(scope="module")
def small_runs(rules, make_controls):
    """(full, quarter) `small` runs of 10 transitions, same controls and seed."""
    u = make_controls()
    full = run_trajectory(SMALL, rules, u, np.random.default_rng(0), SimConfig(), n_transitions=10)
    quarter = run_trajectory(SMALL, rules, u, np.random.default_rng(0), QUARTER, n_transitions=10)
    return full, quarter


def test_wall_fold_is_a_specular_reflection_into_the_box():
    rng = np.random.default_rng(0)
    n = 13
    for x in rng.uniform(-200.0, 200.0, 2000):
        d, f = rng.normal(), rng.choice([-1.0, 1.0])
        xf, df, ff = K.wall_fold(x, d, f, n)
        assert 0.0 <= xf <= n
        assert abs(df) == abs(d) and abs(ff) == abs(f)  # |v| conserved, only the sign may flip
        odd = (x // n) % 2 == 1  # odd mirror images come back reflected
        assert (df == -d) == odd and (ff == -f) == odd
        # the voxel the unfolded traversal looks up is the one the folded position lies in
        assert K.wall_index(int(np.floor(x)), n, True) == min(int(np.floor(xf)), n - 1)
    assert [K.wall_index(i, 4, True) for i in range(-5, 9)] == [3, 3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0]
    assert [K.wall_index(i, 4, False) for i in range(-2, 6)] == [2, 3, 0, 1, 2, 3, 0, 1]


def _fly(rules, mat, fill, species, energy, pos, direction, mirror):
    tables = build_event_tables(rules, SimConfig())
    counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
    buf = K.WorkBuffers(np.zeros((64, 8)), np.zeros(tables.max_channels), counters,
                        np.zeros(len(tables.action), dtype=np.int64))  # fmt: skip
    prm = K.TransportParams(cap=16.0, rcap=16.0, product_energy=2.0, max_steps=10_000, mirror_walls=mirror)
    K.seed_rng(0)
    K.fly(species, energy, *pos, *direction, mat, fill, tables.kernel_tables(), prm, buf, 0, 0)
    return counters


@pytest.mark.parametrize("mirror, hits", [(True, 1), (False, 0)])
def test_particle_bounces_between_mirror_walls_and_lands_where_the_unfolding_says(rules, mirror, hits):
    # a tall 4-wide box, empty but for one Si voxel at (3, *, 0); a steep sub-threshold Ar+ (dx : dz =
    # 1 : 4) from x = 1.5, z = 429.5 runs 107.125 voxels in x while it falls to z = 1: unfolded x =
    # 108.625, which is 4.625 in the period 8 of the mirrored box, i.e. x = 3.375 (column 3) after 27 wall
    # reflections, but 0.625 (column 0, empty: out of the bottom) with periodic walls
    mat = np.zeros((4, 4, 430, 5), dtype=np.int32)
    mat[3, :, 0, 0] = 16
    fill = (mat[..., :4].sum(-1) / 16.0).astype(np.float64)
    d = np.array([1.0, 0.0, -4.0])
    d /= np.linalg.norm(d)
    c = _fly(rules, mat, fill, PROJECTILES.index("Ar+"), 1.0, (1.5, 1.5, 429.5), d, mirror)
    assert c[K.C_HITS] == hits and c[K.C_REACTIONS] == 0
    if mirror:  # specular off the voxel's top, back up between the walls and out of the top
        assert c[K.C_ESC_TOP] == 1 and c[K.C_ESC_BOTTOM] == 0
    else:
        assert c[K.C_ESC_BOTTOM] == 1


def test_surface_normal_sees_mirror_images_beyond_the_walls():
    # solid columns x = 0, 1 of a 4-wide box: periodically column 0 borders the empty column 3 (normal
    # towards -x); between mirror walls its image beyond x = 0 is itself (no x component)
    fill = np.zeros((4, 4, 6))
    fill[:2, :, :3] = 1.0
    periodic = K.surface_normal(fill, 0, 1, 2, False)
    mirrored = K.surface_normal(fill, 0, 1, 2, True)
    assert periodic[0] < -0.1 and abs(mirrored[0]) < 1e-12 and mirrored[2] > 0.9
    np.testing.assert_allclose(np.linalg.norm(mirrored), 1.0)


def test_quarter_states_are_exactly_mirror_symmetric(small_runs):
    full, quarter = small_runs
    s = quarter.states
    assert s.shape == full.states.shape == (11, *SMALL.state_shape)
    np.testing.assert_array_equal(s, s[..., ::-1])  # mirror x -> -x about the opening's axis
    np.testing.assert_array_equal(s, s[..., ::-1, :])  # mirror y -> -y
    assert np.abs(s[-1] - s[0]).max() > 0.1  # it did etch
    # the first state is the quarter config's initial state, the full one's up to Psi's sweep asymmetry
    np.testing.assert_array_equal(s[0], initial_state(SMALL, QUARTER))
    np.testing.assert_allclose(s[0], full.states[0], atol=0.05)
    # the simulated box is the lower quadrant; its mirrored voxel state is symmetric too
    assert quarter.domain.mat.shape == (13, 13, SMALL.nz, 5) and quarter.simulated == "quarter"
    whole = quarter.full_domain()
    assert whole.mat.shape == full.domain.mat.shape
    np.testing.assert_array_equal(whole.mat, whole.mat[::-1])
    np.testing.assert_array_equal(whole.mat, whole.mat[:, ::-1])
    np.testing.assert_array_equal(whole.mat[:13, :13], quarter.domain.mat)
    assert full.full_domain() is full.domain


def test_quarter_bookkeeping_balances_with_a_quarter_of_the_particles(small_runs):
    full, res = small_runs
    c = res.counters
    for t in range(5):
        expect = (res.initial_totals[t] - c[f"removed_{t}"] + c[f"deposited_{t}"] - c[f"converted_from_{t}"]
                  + c[f"converted_to_{t}"])  # fmt: skip
        assert res.final_totals[t] == expect, f"species {t}"
    np.testing.assert_array_equal(res.initial_totals * 4, full.initial_totals)  # the quadrant's material
    assert c["removed_0"] + c["removed_1"] + c["removed_2"] + c["removed_3"] > 0
    assert c["stuck"] == sum(c[f"deposited_{t}"] for t in range(5))
    assert c["dropped"] == 0 and c["step_limit"] < 0.01 * c["primary"]
    assert res.domain.fill.max() <= 1 + 1e-9 and res.domain.mat.min() >= 0
    # the rate follows the launch area: a quarter of the ions (the carried remainder: within one)
    assert abs(c["ions"] - full.counters["ions"] / 4) <= 1


def test_full_mode_is_unchanged_and_unrecorded():
    assert SimConfig().domain == "full" and "domain" not in SimConfig().to_meta(SMALL)
    meta = QUARTER.to_meta(SMALL)
    assert meta["domain"] == "quarter"
    assert SimConfig.from_meta(meta).domain == "quarter"
    old = {k: v for k, v in SimConfig().to_meta(SMALL).items()}
    assert SimConfig.from_meta(old).domain == "full"  # records made before the option read as "full"
    # the rate per flux of the simulated box is a quarter of the scene's
    q_rate = QUARTER.particle_rate_per_flux(QUARTER.simulated_scene(SMALL))
    assert q_rate == pytest.approx(SimConfig().particle_rate_per_flux(SMALL) / 4)
    assert K.transport_params(QUARTER, 16, 12).mirror_walls
    assert not K.transport_params(SimConfig(), 16, 12).mirror_walls
    with pytest.raises(ValueError, match="domain is one of"):
        SimConfig(domain="half")


def test_odd_grid_is_refused(rules, make_controls):
    with pytest.raises(ValueError, match="needs even nx and ny.*13 x 13"):
        run_trajectory(TINY, rules, make_controls(), np.random.default_rng(0), QUARTER, n_transitions=1)


def test_cli_generate_records_the_quarter_domain(tmp_path, make_controls, capsys):
    from nemsim.cli import main
    from nemsim.controls import write_controls_csv

    csv = tmp_path / "c.csv"
    low = dict(flux_ar_plus=2e-4, flux_cl_plus=2e-4, flux_cl2_plus=2e-6, flux_cl=1e-3)
    write_controls_csv(csv, make_controls(**low)[None])
    out = tmp_path / "q.h5"
    assert main(["generate", "--scene", "small", "--controls", str(csv), "--sim-domain", "quarter",
                 "--out", str(out), "--no-progress"]) == 0  # fmt: skip
    with h5py.File(out, "r") as f:
        assert '"domain": "quarter"' in f.attrs["generator"]
        states = f["states"][0]
    assert states.shape == (SMALL.n_states, *SMALL.state_shape)
    np.testing.assert_array_equal(states, states[..., ::-1])
    capsys.readouterr()
    args = ["generate", "--scene", "tiny", "--n", "1", "--sim-domain", "quarter", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "t.h5")]) == 2
    assert "even nx and ny" in capsys.readouterr().err
    assert not (tmp_path / "t.h5").exists()


def test_bench_sim_quarter_reports_both_domains(rules, tmp_path, capsys):
    from bench.sim_quarter import METRICS, bench_quarter, to_markdown
    from nemsim.cli import main
    from nemsim.controls import lhs_design
    from nemsim.scenes import Scene

    # an even 12 x 12 grid with 8 nm voxels and a 0.3 s horizon: three transitions per run
    scene = Scene("even-test", nx=12, ny=12, nz=33, voxel_nm=8.0, si_top=20, resist_top=30,
                  opening_radius_vox=2.5, horizon_s=0.3)  # fmt: skip
    rep = bench_quarter(scene, rules, lhs_design(2, seed=7), seeds=(1, 2))
    assert rep["n_recipes"] == 2 and len(rep["rows"]) == 2
    for row in rep["rows"]:
        assert {len(row["runs"][d]) for d in ("full", "quarter")} == {2}
        for k in METRICS:
            m = row[k]
            assert m["diff"] == pytest.approx(m["quarter_mean"] - m["full_mean"])
            assert m["ratio"] is None or m["ratio"] == pytest.approx(abs(m["diff"]) / m["spread"])
        assert all(v >= 0 for v in row["avg_rmse"].values())
    q, f = rep["speed"]["quarter"], rep["speed"]["full"]
    assert q["primaries"]["median"] < 0.4 * f["primaries"]["median"]
    text = to_markdown(rep, "cmd", "cpu")
    assert "| etch_depth |" in text and "Speed-up full / quarter" in text
    assert main(["bench", "sim-quarter", "--recipes", "1"]) == 2
    assert "--recipes" in capsys.readouterr().err
