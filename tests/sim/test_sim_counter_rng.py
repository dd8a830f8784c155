"""Counter-based random numbers (``SimConfig.rng_mode = "counter"``, kernels module docstring): common
random numbers for paired recipes, keyed by (seed, macro step, source, particle)."""

from __future__ import annotations

import functools

import h5py
import numpy as np
import pytest

from nemsim.rules.vocab import PROJECTILES
from nemsim.scenes import SMALL
from nemsim.sim import SimConfig, run_trajectory
from nemsim.sim import kernels as K

SEEDS = (11, 12, 13, 14, 15, 16)
CL, CL_PLUS = PROJECTILES.index("Cl"), PROJECTILES.index("Cl+")
# Ar+ at 0 eV is below every Ar+ rule's threshold: it reflects until it leaves and never changes the surface
GHOST_AR = (("energy_mean_ar_plus", 0.0), ("energy_std_ar_plus", 0.0))


@pytest.fixture(scope="module")
def run(tiny_scene, rules, make_controls):
    """run(mode, overrides, seed, n_transitions, extra config, scene) -> TrajectoryResult, cached."""

    @functools.lru_cache(maxsize=None)
    def _run(mode: str, overrides: tuple, seed: int, n_tr: int | None = None, extra: tuple = (), scene=None):
        cfg = SimConfig(rng_mode=mode, **dict(extra))
        u = make_controls(**dict(overrides))
        sc = tiny_scene if scene is None else scene
        return run_trajectory(sc, rules, u, np.random.default_rng(seed), cfg, n_transitions=n_tr)

    return _run


def _draws(seed: int, step: int, species: int, j: int, n: int) -> list[float]:
    """The first n numbers of particle j of source ``species`` in macro step ``step``, seated as
    ``run_particles_crn`` seats it (keys are uint64; numba hands them back as Python ints)."""
    source_key = np.uint64(K.stream_key(np.uint64(K.counter_seed(seed, step)), np.uint64(species)))
    rs = K.new_rng_state(True)
    K.seat_particle(rs, np.uint64(K.stream_key(source_key, np.uint64(j))))
    return [K.uniform(rs) for _ in range(n)]


def test_mix64_is_splitmix64():
    # SplitMix64 seeded with 0: the state advances by the golden gamma, its first output is the finalizer's
    # image of the gamma (the reference value of Vigna's splitmix64.c)
    assert int(K.mix64(np.uint64(0x9E3779B97F4A7C15))) == 0xE220A8397B1DCDAF
    assert int(K.mix64(np.uint64(0))) == 0


def test_a_particle_stream_depends_only_on_its_key():
    """Particle j's numbers are a function of (seed, step, source, j): not of what the others drew."""
    alone = _draws(7, 3, CL_PLUS, 5, 20)
    rs = K.new_rng_state(True)
    for other, n in ((4, 3), (4, 300), (6, 1)):  # other particles drawing any amount in between
        K.seat_particle(rs, np.uint64(K.stream_key(np.uint64(other), np.uint64(1))))
        for _ in range(n):
            K.uniform(rs)
        assert _draws(7, 3, CL_PLUS, 5, 20) == alone
    for key in ((7, 3, CL_PLUS, 6), (7, 4, CL_PLUS, 5), (8, 3, CL_PLUS, 5), (7, 3, CL, 5)):
        assert _draws(*key, 20) != alone  # another particle, macro step, seed or source


def test_counter_draws_are_uniform_and_independent_across_keys():
    u = np.array([_draws(1, 0, CL, j, 8) for j in range(4000)])  # (particles, launch slots)
    x = u.ravel()
    assert 0.0 <= x.min() and x.max() < 1.0
    sd = np.sqrt(1 / 12 / x.size)  # standard error of the mean of U[0, 1)
    assert abs(x.mean() - 0.5) < 4 * sd
    assert abs(x.var() - 1 / 12) < 4 * np.sqrt(1 / 180 / x.size)  # var of (x - 1/2)^2 is 1/80 - 1/144
    assert abs(((x - 0.5) ** 3).mean()) < 4 * np.sqrt(1 / 448 / x.size)  # E (x - 1/2)^6 = 1/448
    counts = np.histogram(x, bins=16, range=(0.0, 1.0))[0]
    expected = x.size / 16
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 45.0, chi2  # 15 degrees of freedom: p ~ 1e-4
    bound = 4 / np.sqrt(len(u))  # 4 standard errors of a correlation of independent variables
    assert np.abs(np.corrcoef(u.T) - np.eye(8)).max() < bound  # slots of one particle
    assert abs(np.corrcoef(u[:-1, 0], u[1:, 0])[0, 1]) < bound  # consecutive particles
    for key in ((1, 0, CL_PLUS), (1, 1, CL), (2, 0, CL)):  # another source, macro step, seed; same index
        v = np.array([_draws(*key, j, 1)[0] for j in range(4000)])
        assert abs(np.corrcoef(u[:, 0], v)[0, 1]) < bound


def test_launch_order_keeps_the_common_particles_in_order():
    """CRN at the launch: a macro step with more particles of one source holds every particle of the
    other step, in the same order, with the extra ones inserted among them."""
    species = np.array([CL, CL_PLUS, PROJECTILES.index("Cl2+"), PROJECTILES.index("Ar+")])
    a = np.array([40, 12, 0, 9])
    b = np.array([40, 15, 0, 9])
    oa = list(zip(*K.launch_order(12345, a, species), strict=True))
    ob = list(zip(*K.launch_order(12345, b, species), strict=True))
    assert sorted(oa) == [(k, j) for k in range(4) for j in range(a[k])]  # every particle once
    assert [p for p in ob if p[1] < a[p[0]]] == oa
    extra = [i for i, p in enumerate(ob) if p[0] == 1 and p[1] >= 12]
    assert len(extra) == 3 and min(extra) < len(ob) - 3  # inserted at their times, not appended
    assert list(zip(*K.launch_order(99, a, species), strict=True)) != oa  # another step: another order


@pytest.mark.parametrize("scene, n_tr", [(None, 12), (SMALL, 4)], ids=["tiny-full", "small-quarter"])
def test_a_flux_of_inert_particles_leaves_the_others_untouched(run, scene, n_tr):
    """Twice the flux of Ar+ ions launched at 0 eV (they never react) adds particles and nothing else:
    with counter streams every other particle is the same in both runs and the surface evolves identically;
    the shared stream of the default mode is shifted by the extra particles."""
    extra = (("domain", "quarter"),) if scene is SMALL else ()
    for mode in ("counter", "stream"):
        one = run(mode, (*GHOST_AR, ("flux_ar_plus", 1e-3)), 3, n_tr, extra, scene)
        two = run(mode, (*GHOST_AR, ("flux_ar_plus", 2e-3)), 3, n_tr, extra, scene)
        assert two.counters["ions"] > one.counters["ions"]
        assert np.array_equal(one.states, two.states) == (mode == "counter"), mode
        assert np.array_equal(one.domain.mat, two.domain.mat) == (mode == "counter"), mode
    assert sum(one.counters[f"removed_{t}"] for t in range(4)) > 50  # the surface did evolve
    assert np.abs(one.states[-1] - one.states[0]).max() > 0.01
    if scene is SMALL:  # the quarter's states stay exactly mirror symmetric
        s = run("counter", GHOST_AR, 3, n_tr, extra, scene).states
        np.testing.assert_array_equal(s, s[..., ::-1])
        np.testing.assert_array_equal(s, s[..., ::-1, :])


def test_same_seed_same_recipe_is_identical_and_prefix_consistent(run):
    full = run("counter", (), 3, 12)
    fresh = run.__wrapped__("counter", (), 3, 12)  # not the cached object
    np.testing.assert_array_equal(fresh.states, full.states)
    assert fresh.counters == full.counters
    short = run("counter", (), 3, 5)  # a shorter run is the same trajectory's beginning
    np.testing.assert_array_equal(short.states, full.states[:6])
    assert not np.array_equal(run("counter", (), 4, 5).states, short.states)  # another seed


def test_extra_draws_shift_no_stream_in_counter_mode(run):
    """A wing and a diffuse-reflection fraction of 1e-12 change nothing physically but make every ion draw
    one more number at launch and at each reflection: today's shared stream shifts for every later
    particle, the counter streams do not move at all."""
    extra = (("ion_wing_fraction", 1e-12), ("ion_reflect_diffuse", 1e-12))
    for mode, same in (("counter", True), ("stream", False)):
        a, b = run(mode, (), 5, 5), run(mode, (), 5, 5, extra)
        assert np.array_equal(a.states, b.states) == same, mode
        assert (a.counters == b.counters) == same, mode


def test_default_stays_stream_and_counter_mode_is_recorded():
    assert SimConfig().rng_mode == "stream"
    assert "rng_mode" not in SimConfig().to_meta()  # files made before the field stay resumable
    meta = SimConfig(rng_mode="counter").to_meta()
    assert meta["rng_mode"] == "counter"
    assert SimConfig.from_meta(meta).rng_mode == "counter"
    assert SimConfig.from_meta(SimConfig().to_meta()).rng_mode == "stream"
    with pytest.raises(ValueError, match="rng_mode"):
        SimConfig(rng_mode="philox")


def test_counter_mode_etches_as_the_default_within_noise(run, tiny_scene, etch_depth_nm):
    """Same physics: mean etch depth and particle counts over seeds agree with the default's."""
    depth = {m: np.array([etch_depth_nm(run(m, (), s), tiny_scene) for s in SEEDS[:4]])
             for m in ("stream", "counter")}  # fmt: skip
    se = np.sqrt((depth["stream"].var(ddof=1) + depth["counter"].var(ddof=1)) / 4)
    assert abs(depth["stream"].mean() - depth["counter"].mean()) < 3.0 * se + 1.0, depth
    ions = {m: [run(m, (), s).counters["ions"] for s in SEEDS[:4]] for m in ("stream", "counter")}
    assert len(set(ions["counter"])) == 1  # one count per source and step in counter mode: no seed enters
    # each ion source carries its own remainder: the totals differ by less than one per ion source
    assert abs(ions["counter"][0] - ions["stream"][0]) < 3, ions
    prim = {m: np.mean([run(m, (), s).counters["primary"] for s in SEEDS[:4]]) for m in ("stream", "counter")}
    assert abs(prim["stream"] / prim["counter"] - 1.0) < 0.01, prim


def test_paired_difference_is_much_quieter_with_counter_streams(run):
    """One ion flux +10 %, both members of the pair simulated with the same seed: the seed-to-seed noise
    of their simulated difference (RMS over the first 20 transitions and every voxel) with counter
    streams is well under today's shared-stream noise. Later in the horizon the histories diverge and the
    gain shrinks (``bench.pair_noise`` measures it on a whole trajectory)."""
    n_tr = 20
    noise = {}
    for mode in ("stream", "counter"):
        pairs = [(run(mode, (), s, n_tr), run(mode, (("flux_cl_plus", 1.1e-3),), s, n_tr)) for s in SEEDS]
        d = np.stack([b.states[1:] - a.states[1:] for a, b in pairs])
        noise[mode] = float(np.sqrt(np.mean(d.var(axis=0, ddof=1))))
    assert noise["counter"] < 0.6 * noise["stream"], noise


def test_cli_generate_records_the_counter_streams(tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "c.h5"
    args = ["generate", "--scene", "tiny", "--n", "1", "--out", str(out), "--no-progress"]
    assert main([*args, "--sim-rng", "counter"]) == 0
    with h5py.File(out, "r") as f:
        assert '"rng_mode": "counter"' in f.attrs["generator"]
    capsys.readouterr()
    assert main(args) == 2  # the default streams do not resume a counter-stream file
    assert capsys.readouterr().err
