"""Fixtures for the simulator tests: compiled rules, the tiny scene and a mid-range control vector."""

from __future__ import annotations

import numpy as np
import pytest

# A moderate process condition (raw units, CONTROL_NAMES order): few particles, so fast on `tiny`.
BASE_CONTROLS = dict(
    flux_ar_plus=1e-3, flux_cl_plus=1e-3, flux_cl2_plus=1e-5, flux_cl=5e-3,
    angle_cl=5, angle_cl_plus=500, angle_cl2_plus=500, angle_ar_plus=500,
    energy_mean_cl_plus=300, energy_std_cl_plus=7, energy_mean_cl2_plus=300, energy_std_cl2_plus=10,
    energy_mean_ar_plus=300, energy_std_ar_plus=10,
)  # fmt: skip


def controls(**overrides: float) -> np.ndarray:
    """(14,) raw controls: BASE_CONTROLS with overrides, in CONTROL_NAMES order."""
    from nemsim.controls import CONTROL_NAMES

    unknown = set(overrides) - set(CONTROL_NAMES)
    assert not unknown, f"unknown controls {unknown}"
    values = {**BASE_CONTROLS, **overrides}
    return np.array([float(values[n]) for n in CONTROL_NAMES])



@pytest.fixture(scope="session")
def sim_config():
    from nemsim.sim import SimConfig

    return SimConfig()


@pytest.fixture(scope="session")
def make_controls():
    """controls(**overrides) -> (14,) raw controls around BASE_CONTROLS."""
    return controls


@pytest.fixture(scope="session")
def tiny_run(rules):
    """run(overrides: ((name, value), ...), seed) -> TrajectoryResult on `tiny`, cached per session."""
    import functools

    from nemsim.scenes import TINY
    from nemsim.sim import SimConfig, run_trajectory

    @functools.lru_cache(maxsize=None)
    def run(key: tuple, seed: int):
        return run_trajectory(TINY, rules, controls(**dict(key)), np.random.default_rng(seed), SimConfig())

    return run


def _etch_depth_nm(res, scene) -> float:
    """Si removed from the core of the opening, as a depth (micro state; exact bookkeeping, no SDF)."""
    from nemsim.sim.domain import SI_CLASS

    si = res.domain.mat[..., list(SI_CLASS)].sum(-1) / res.domain.capacity
    cx, cy = scene.opening_centre
    ii, jj = np.meshgrid(np.arange(scene.nx), np.arange(scene.ny), indexing="ij")
    core = np.hypot(ii - cx, jj - cy) <= 1.0
    return float((scene.si_top - si[core].sum(-1).mean()) * scene.voxel_nm)


@pytest.fixture(scope="session")
def etch_depth_nm():
    """(TrajectoryResult, scene) -> etch depth in nm on the opening's core, from the voxel contents."""
    return _etch_depth_nm
