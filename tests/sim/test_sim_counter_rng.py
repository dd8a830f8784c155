"""Counter-based random numbers (``SimConfig.rng_mode = "counter"``, kernels module docstring): common
random numbers for paired recipes, keyed by (seed, macro step, particle)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from nemsim.sim import SimConfig, run_trajectory
from nemsim.sim import kernels as K

SEEDS = (11, 12, 13, 14, 15, 16)


@pytest.fixture(scope="module")
def run(tiny_scene, rules, make_controls):
    """run(mode, overrides, seed, n_transitions) -> TrajectoryResult on `tiny`, cached per module."""

    @functools.lru_cache(maxsize=None)
    def _run(mode: str, overrides: tuple, seed: int, n_tr: int | None = None, extra: tuple = ()):
        cfg = SimConfig(rng_mode=mode, **dict(extra))
        u = make_controls(**dict(overrides))
        return run_trajectory(tiny_scene, rules, u, np.random.default_rng(seed), cfg, n_transitions=n_tr)

    return _run


def _seat(rs: np.ndarray, seed: int, step: int, i: int) -> None:
    """Start particle i of macro step ``step`` as ``run_particles`` does."""
    K.seat_particle(rs, np.uint64(K.stream_key(np.uint64(K.counter_seed(seed, step)), np.uint64(i))))


def _particle_draws(seed: int, step: int, i: int, n: int) -> list[float]:
    rs = K.new_rng_state(True)
    _seat(rs, seed, step, i)
    return [K.uniform(rs) for _ in range(n)]


def test_a_particle_stream_depends_only_on_its_key():
    """Particle i's numbers are a function of (seed, step, i): not of how many numbers the others drew."""
    alone = _particle_draws(7, 3, 5, 20)
    rs = K.new_rng_state(True)
    for other, n in ((4, 3), (4, 300), (6, 1)):  # other particles drawing any amount in between
        _seat(rs, 7, 3, other)
        for _ in range(n):
            K.uniform(rs)
        assert _particle_draws(7, 3, 5, 20) == alone
    assert _particle_draws(7, 3, 6, 20) != alone  # another particle
    assert _particle_draws(7, 4, 5, 20) != alone  # another macro step
    assert _particle_draws(8, 3, 5, 20) != alone  # another seed


def test_counter_draws_are_uniform_and_independent_across_particles():
    u = np.array([_particle_draws(1, 0, i, 8) for i in range(4000)])  # (particles, launch slots)
    counts = np.histogram(u.ravel(), bins=16, range=(0.0, 1.0))[0]
    expected = u.size / 16
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 45.0, chi2  # 15 degrees of freedom: p ~ 1e-4
    assert 0.0 <= u.min() and u.max() < 1.0
    corr = np.corrcoef(u.T)  # slots of one particle
    assert np.abs(corr - np.eye(8)).max() < 0.06
    assert abs(np.corrcoef(u[:-1, 0], u[1:, 0])[0, 1]) < 0.06  # consecutive particles


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
    assert ions["stream"] == ions["counter"]  # the ion count per step is deterministic in both
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
