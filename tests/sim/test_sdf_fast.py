"""The optimised Psi equals the original implementation (tests/sim/sdf_reference.py) bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import sdf_reference as ref  # tests/sim is on sys.path (rootdir-relative test modules)

from nemsim.scenes import SMALL, TINY
from nemsim.sim import sdf
from nemsim.sim.domain import initial_domain


def _small_etched(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(mask, Si) fractions on `small`: a tapered hole 14 voxels into the Si with rough, partly filled
    walls and a partly eroded resist top (a stand-in for a mid-etch snapshot)."""
    rng = np.random.default_rng(seed)
    s = SMALL
    mask, si = (f.astype(np.float64) for f in initial_domain(s, 16, 16).fractions())
    cx, cy = s.opening_centre
    ii, jj = np.meshgrid(np.arange(s.nx), np.arange(s.ny), indexing="ij")
    r = np.hypot(ii - cx, jj - cy)
    for z in range(s.si_top - 14, s.si_top):
        radius = s.opening_radius_vox - 0.15 * (s.si_top - z) + rng.normal(0, 0.3, r.shape)
        si[..., z] *= np.clip(r - radius + 0.5, 0.0, 1.0)  # partial voxels on the wall
    top = s.resist_top - 1
    mask[..., top] *= rng.uniform(0.2, 1.0, r.shape)  # eroded top layer
    noise = rng.uniform(-0.05, 0.05, si.shape) * ((si > 0) & (si < 1))
    return mask.astype(np.float32), np.clip(si + noise, 0, 1).astype(np.float32)


def _tiny_snapshots(tiny_run) -> list[tuple[np.ndarray, np.ndarray]]:
    dom = initial_domain(TINY, 16, 16)
    return [dom.fractions(), tiny_run((), 0).domain.fractions()]


def test_psi_equals_reference_on_tiny(tiny_run):
    for mask, si in _tiny_snapshots(tiny_run):
        for sigma in (0.0, 0.7):
            new = sdf.psi(mask, si, TINY, sigma)
            old = ref.psi(mask, si, TINY, sigma)
            assert new.dtype == old.dtype and new.shape == old.shape
            assert np.abs(new - old).max() == 0.0  # bit-identical


@pytest.mark.parametrize("seed", [0, 1])
def test_psi_equals_reference_on_synthetic_small(seed):
    mask, si = _small_etched(seed)
    new = sdf.psi(mask, si, SMALL, 0.7)
    old = ref.psi(mask, si, SMALL, 0.7)
    band = np.abs(old) < 1  # the unclipped part carries the geometry
    assert band.sum() > 10_000
    assert np.abs(new - old).max() == 0.0


@pytest.mark.parametrize("sigma", [0.0, 0.5, 0.7, 1.3])
def test_smoothing_equals_scipy(sigma):
    frac = np.random.default_rng(3).uniform(0, 1, (9, 7, 11)).astype(np.float32)
    for pad in (1, 2):
        new = sdf.smoothed_indicator(frac, sigma, pad)
        assert np.array_equal(new, ref.smoothed_indicator(frac, sigma, pad))


@pytest.mark.parametrize("n_sweeps", [0, 1, 2])
def test_closest_point_sdf_equals_reference_on_a_rough_sphere(n_sweeps):
    rng = np.random.default_rng(7)
    n = 24
    x = np.indices((n, n, n)).transpose(1, 2, 3, 0)
    dist = np.linalg.norm(x - np.array([11.3, 12.6, 10.8]), axis=-1)
    frac = np.clip(6.2 - dist + 0.5 + rng.normal(0, 0.2, dist.shape), 0, 1)
    g = ref.smoothed_indicator(frac, 0.7)
    new = sdf.closest_point_sdf(g, 0.5, 6.0, n_sweeps)
    old = ref.closest_point_sdf(g, 0.5, 6.0, n_sweeps)
    assert np.array_equal(new, old)
    # and the work buffers are reused without leaking state between calls of different shapes
    g2 = ref.smoothed_indicator(frac[:20, :18, :22], 0.7)
    old2 = ref.closest_point_sdf(g2, 0.5, 6.0, n_sweeps)
    assert np.array_equal(sdf.closest_point_sdf(g2, 0.5, 6.0, n_sweeps), old2)
    assert np.array_equal(sdf.closest_point_sdf(g, 0.5, 6.0, n_sweeps), old)
