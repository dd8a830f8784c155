"""Whole trajectories on `tiny`: bookkeeping, determinism, controls, and the physics the design relies on.

The statistical tests compare two control settings with two seeds each (short `tiny` runs) and require the
ordering to hold for every seed pair, with margins several times the seed-to-seed spread measured when the
simulator was calibrated.
"""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.sim import SimConfig, run_trajectory, simulate_trajectory
from nemsim.sim.domain import SI_CLASS


def _mask_loss_nm(res, scene) -> float:
    from nemsim.geometry.profile import profile_metrics

    return profile_metrics(res.states[-1], scene)["mask_loss"]


def _lateral_etch_nm(res, scene) -> float:
    """Widest equivalent hole diameter in the Si (area based) minus the mask opening's diameter, nm."""
    si = res.domain.mat[..., list(SI_CLASS)].sum(-1) / res.domain.capacity
    vac = (1 - si[:, :, : scene.si_top]).sum(axis=(0, 1))  # (z,) vacuum area per Si row, voxels^2
    diam = 2 * np.sqrt(vac / np.pi) * scene.voxel_nm
    return float(diam.max() - 2 * scene.opening_radius_vox * scene.voxel_nm)


def test_bookkeeping_balances(tiny_scene, tiny_run):
    res = tiny_run((), 1)
    c = res.counters
    for t in range(5):
        expect = (res.initial_totals[t] - c[f"removed_{t}"] + c[f"deposited_{t}"] - c[f"converted_from_{t}"]
                  + c[f"converted_to_{t}"])  # fmt: skip
        assert res.final_totals[t] == expect, f"species {t}"
    assert c["removed_0"] + c["removed_1"] + c["removed_2"] + c["removed_3"] > 0
    assert c["stuck"] == sum(c[f"deposited_{t}"] for t in range(5))
    assert c["dropped"] == 0 and c["step_limit"] < 0.01 * c["primary"]
    # the domain is consistent: fill never exceeds one voxel
    assert res.domain.fill.max() <= 1 + 1e-9 and res.domain.mat.min() >= 0


def test_same_seed_same_states_other_seed_differs(tiny_scene, rules, make_controls):
    u = make_controls()
    a = simulate_trajectory(tiny_scene, rules, u, np.random.default_rng(7), SimConfig())
    b = simulate_trajectory(tiny_scene, rules, u, np.random.default_rng(7), SimConfig())
    c = simulate_trajectory(tiny_scene, rules, u, np.random.default_rng(8), SimConfig())
    assert a.shape == (tiny_scene.n_states, *tiny_scene.state_shape) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_zero_flux_changes_nothing(tiny_scene, rules, make_controls):
    u = make_controls(flux_ar_plus=0, flux_cl_plus=0, flux_cl2_plus=0, flux_cl=0)
    res = run_trajectory(tiny_scene, rules, u, np.random.default_rng(0), SimConfig())
    assert res.counters["primary"] == 0
    assert np.all(res.states == res.states[0])


def test_recipe_controls_one_vector_per_transition(tiny_scene, rules, make_controls):
    off = make_controls(flux_ar_plus=0, flux_cl_plus=0, flux_cl2_plus=0, flux_cl=0)
    on = make_controls(flux_ar_plus=3e-3, flux_cl_plus=3e-3)
    n = 20
    schedule = np.stack([off] * (n // 2) + [on] * (tiny_scene.n_transitions - n // 2))
    res = run_trajectory(tiny_scene, rules, schedule, np.random.default_rng(0), SimConfig(), n_transitions=n)
    assert np.all(res.states[: n // 2 + 1] == res.states[0])  # nothing happens while the plasma is off
    assert not np.array_equal(res.states[-1], res.states[0])


def test_bad_controls_are_rejected(tiny_scene, rules, make_controls):
    controls = make_controls
    with pytest.raises(ValueError, match="negative"):
        simulate_trajectory(tiny_scene, rules, controls(flux_cl=-1.0), np.random.default_rng(0))
    with pytest.raises(ValueError, match="shape"):
        simulate_trajectory(tiny_scene, rules, np.zeros(13), np.random.default_rng(0))
    with pytest.raises(ValueError, match="NaN"):
        simulate_trajectory(tiny_scene, rules, controls(flux_cl=np.nan), np.random.default_rng(0))


@pytest.mark.slow
def test_neutral_chlorine_alone_barely_etches(etch_depth_nm, tiny_scene, tiny_run):
    cl_only = (("flux_ar_plus", 0.0), ("flux_cl_plus", 0.0), ("flux_cl2_plus", 0.0), ("flux_cl", 2e-2))
    res = tiny_run(cl_only, 1)
    assert res.counters["neutrals"] > 0 and res.counters["ions"] == 0
    assert etch_depth_nm(res, tiny_scene) < 1.0  # < 1/8 of a voxel
    assert etch_depth_nm(tiny_run((), 1), tiny_scene) > 20.0  # while the base condition etches


def _ordered(run, low_key: tuple, high_key: tuple, metric, scene, margin: float) -> None:
    lows = [metric(run(low_key, s), scene) for s in (1, 2)]
    highs = [metric(run(high_key, s), scene) for s in (1, 2)]
    assert min(highs) > max(lows) + margin, (lows, highs)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, low, high, margin",
    [
        ("Cl+ flux", (("flux_cl_plus", 5e-4),), (("flux_cl_plus", 4e-3),), 10.0),
        ("Ar+ flux", (("flux_ar_plus", 5e-4),), (("flux_ar_plus", 4e-3),), 10.0),
        ("ion energy",
         (("energy_mean_cl_plus", 170), ("energy_mean_cl2_plus", 170), ("energy_mean_ar_plus", 170)),
         (("energy_mean_cl_plus", 490), ("energy_mean_cl2_plus", 490), ("energy_mean_ar_plus", 490)), 5.0),
    ],
)  # fmt: skip
def test_etch_depth_rises_with(etch_depth_nm, tiny_scene, tiny_run, name, low, high, margin):
    _ordered(tiny_run, low, high, etch_depth_nm, tiny_scene, margin)


@pytest.mark.slow
def test_mask_loss_rises_with_ion_energy(tiny_scene, tiny_run):
    low = (("energy_mean_cl_plus", 170), ("energy_mean_cl2_plus", 170), ("energy_mean_ar_plus", 170))
    high = (("energy_mean_cl_plus", 490), ("energy_mean_cl2_plus", 490), ("energy_mean_ar_plus", 490))
    _ordered(tiny_run, low, high, _mask_loss_nm, tiny_scene, 0.5)


@pytest.mark.slow
def test_larger_ion_exponent_gives_straighter_sidewalls(tiny_scene, tiny_run):
    """Broad ion distributions (m = 50) etch the sidewalls laterally, under the mask edge and into a bow;
    collimated ions (m = 3000) do not (their holes stay inside the mask opening and taper slightly,
    from redeposited SiCl_x that they do not reach)."""
    strong = (("flux_ar_plus", 3e-3), ("flux_cl_plus", 3e-3))
    broad = strong + (("angle_cl_plus", 50), ("angle_cl2_plus", 50), ("angle_ar_plus", 50))
    narrow = strong + (("angle_cl_plus", 3000), ("angle_cl2_plus", 3000), ("angle_ar_plus", 3000))
    _ordered(tiny_run, narrow, broad, _lateral_etch_nm, tiny_scene, 3.0)
