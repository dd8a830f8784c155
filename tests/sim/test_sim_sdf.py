"""Psi (voxels -> SDF): sub-voxel accuracy, unit gradient, layout."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.sim.sdf import closest_point_sdf, psi, signed_distance, smoothed_indicator


def _volume_fraction(inside, n: int, sub: int = 8) -> np.ndarray:
    """(n, n, n) exact-ish volume fraction of {inside(x, y, z)} (voxel i centred at i)."""
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    x = (np.arange(n)[:, None] + offs[None, :]).reshape(-1)
    val = inside(x[:, None, None], x[None, :, None], x[None, None, :])
    return val.reshape(n, sub, n, sub, n, sub).mean(axis=(1, 3, 5))


@pytest.mark.parametrize("sigma", [0.0, 0.5, 0.7])
def test_sphere_distance_and_unit_gradient(sigma):
    n, c, r = 32, np.array([15.2, 14.7, 16.1]), 7.3
    frac = _volume_fraction(lambda x, y, z: (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < r * r, n)
    phi = signed_distance(frac, sigma, 8.0)[1:-1, 1:-1, 1:-1]  # drop the one-voxel pad
    exact = np.linalg.norm(np.indices((n, n, n)).transpose(1, 2, 3, 0) - c, axis=-1) - r
    band = np.abs(exact) < 5
    err = phi[band] - exact[band]
    # curvature shrinks a smoothed sphere by ~sigma^2 / r; otherwise sub-voxel accurate
    assert abs(err.mean()) < 0.02 + sigma**2 / r, err.mean()
    assert np.abs(err).max() < 0.35, np.abs(err).max()
    grad = np.sqrt(sum(g**2 for g in np.gradient(phi)))
    near = (np.abs(exact) < 4) & (np.abs(exact) > 0.5)
    assert abs(grad[near].mean() - 1) < 0.02
    assert grad[near].std() < 0.05


def test_tilted_plane_has_no_staircase():
    n = 24
    normal = np.array([0.3, 0.5, 0.81])
    normal /= np.linalg.norm(normal)
    frac = _volume_fraction(lambda x, y, z: x * normal[0] + y * normal[1] + z * normal[2] < 12.3, n)
    phi = signed_distance(frac, 0.5, 8.0)[1:-1, 1:-1, 1:-1]
    exact = np.indices((n, n, n)).transpose(1, 2, 3, 0) @ normal - 12.3
    inner = np.zeros_like(exact, dtype=bool)
    inner[4:-4, 4:-4, 4:-4] = True
    sel = inner & (np.abs(exact) < 3)
    assert np.abs(phi[sel] - exact[sel]).max() < 0.15


def test_half_filled_layer_moves_interface_by_half_a_voxel():
    frac = np.zeros((6, 6, 12))
    frac[:, :, :5] = 1.0
    full = signed_distance(frac, 0.0, 5.0)[3, 3, 1:-1]
    frac[:, :, 5] = 0.5
    half = signed_distance(frac, 0.0, 5.0)[3, 3, 1:-1]
    unclipped = (np.abs(full) < 4) & (np.abs(half) < 4)
    assert unclipped.sum() >= 6
    np.testing.assert_allclose((full - half)[unclipped], 0.5, atol=0.02)


def test_psi_layout_and_signs(tiny_scene):
    from nemsim.sim.domain import initial_domain

    dom = initial_domain(tiny_scene, 16, 16)
    state = psi(*dom.fractions(), tiny_scene, 0.7)
    assert state.shape == tiny_scene.state_shape and state.dtype == np.float32
    assert state.min() >= -1 and state.max() <= 1
    s = tiny_scene
    cx = s.nx // 2 + 1  # padded index of the centre column
    # (z, y, x): Si inside below si_top, vacuum above; mask inside the resist away from the opening
    assert state[1, s.si_top // 2 + 1, 1, 1] < 0 < state[1, s.resist_top + 1, 1, 1]
    assert state[0, (s.si_top + s.resist_top) // 2 + 1, 1, 1] < 0
    assert state[0, (s.si_top + s.resist_top) // 2 + 1, cx, cx] > 0  # the opening is empty
    # interface of the Si channel half a voxel below the first vacuum layer (native z = si_top - 0.5)
    col = state[1, :, 1, 1] * s.d_max_vox
    z = np.arange(len(col)) - 1  # native z of each depth index
    keep = np.abs(col) < s.d_max_vox - 0.5  # unclipped, strictly increasing part
    zero = np.interp(0.0, col[keep], z[keep])
    assert abs(zero - (s.si_top - 0.5)) < 0.05


def test_empty_field_is_clipped():
    g = smoothed_indicator(np.zeros((5, 5, 5)), 0.7)
    assert np.all(closest_point_sdf(g, 0.5, 3.0) == 3.0)
