"""Field and surface metrics of [supp_protocols] on hand values and analytic SDFs (tiny scene)."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.evaluation import metrics as M


def _grid(scene):
    d, h, w = scene.field_shape
    z = np.arange(d, dtype=np.float64)[:, None, None]
    y = np.arange(h, dtype=np.float64)[None, :, None]
    x = np.arange(w, dtype=np.float64)[None, None, :]
    return z, y, x


def _state(scene, mask_phi, si_phi):
    shape = scene.field_shape
    st = np.stack([np.broadcast_to(mask_phi, shape), np.broadcast_to(si_phi, shape)])
    return np.clip(st / scene.d_max_vox, -1, 1).astype(np.float32)


def _cylinder_state(scene, radius, cx=7.0, cy=7.0):
    """Si channel: vacuum cylinder of ``radius`` voxels (axis along depth) through the Si crop;
    mask channel: a flat plane inside the mask crop."""
    z, y, x = _grid(scene)
    si = radius - np.hypot(x - cx, y - cy)  # negative outside the cylinder (material)
    mask = z - 25.3
    return _state(scene, mask, si)


# ----- RMSE ------------------------------------------------------------------------------------


def test_rmse_hand_values():
    true = np.zeros((2, 3, 2, 1, 1, 2))
    pred = np.zeros_like(true)
    pred[0, 1] = 1.0  # case 0, step 1: all four elements off by 1 -> e = 1
    pred[1, 2, 0] = 2.0  # case 1, step 2: two of four elements off by 2 -> e = 2
    r = M.rmse_per_step(pred, true)
    np.testing.assert_allclose(r, [0.0, np.sqrt(0.5), 1.0])
    assert M.avg_rmse(pred, true) == pytest.approx((np.sqrt(0.5) + 1.0) / 3)
    assert M.avg_rmse(pred, true, skip_initial=True) == pytest.approx((np.sqrt(0.5) + 1.0) / 2)
    assert M.avg_rmse(r) == pytest.approx(r.mean())
    # Avg RMSE is the mean of per-step RMSEs, not sqrt of the mean MSE
    assert M.avg_rmse(r) != pytest.approx(np.sqrt((r**2).mean()))
    assert M.final_rmse(pred, true) == pytest.approx(1.0)


def test_step_rmse_streaming_matches_and_accepts_torch():
    import torch

    rng = np.random.default_rng(0)
    pred, true = rng.normal(size=(5, 4, 2, 3, 3, 3)), rng.normal(size=(5, 4, 2, 3, 3, 3))
    acc = M.StepRmse()
    acc.update(torch.from_numpy(pred[:2]), torch.from_numpy(true[:2]))
    acc.update(pred[2:], true[2:])
    np.testing.assert_allclose(acc.rmse_per_step(), M.rmse_per_step(pred, true))
    assert acc.avg() == pytest.approx(M.avg_rmse(pred, true))
    assert acc.final() == pytest.approx(M.final_rmse(pred, true))
    with pytest.raises(ValueError, match="shape"):
        M.rmse_per_step(pred, true[:, :2])


# ----- Chamfer distance ------------------------------------------------------------------------


def test_chamfer_identical_is_zero(tiny_scene):
    a = _cylinder_state(tiny_scene, 3.2)
    assert M.chamfer_distance(a, a.copy(), tiny_scene, case_id=0, step=100) == 0.0


def test_chamfer_plane_shift(tiny_scene):
    sc = tiny_scene
    z, _, _ = _grid(sc)
    a = _state(sc, z - 25.3, z - 8.2)
    b = _state(sc, z - 25.3, z - 10.7)  # Si plane shifted by 2.5 voxels, mask identical
    cm, cs = M.chamfer_channels(a, b, sc, case_id=1, step=3)
    assert cm == 0.0
    assert cs == pytest.approx(2.5, abs=0.03)
    assert M.chamfer_distance(a, b, sc, 1, 3) == pytest.approx(0.5 * 2.5, abs=0.02)


def test_chamfer_cylinder_and_shifted_copy(tiny_scene):
    sc = tiny_scene
    # concentric copy with a radius larger by s: every point is s from the other surface
    s = 1.5
    cm, cs = M.chamfer_channels(_cylinder_state(sc, 2.5), _cylinder_state(sc, 2.5 + s), sc, 2, 50)
    assert cs == pytest.approx(s, abs=0.05)
    # laterally shifted copy: for small shifts the mean normal distance is 2 s / pi
    s = 0.4
    cm, cs = M.chamfer_channels(_cylinder_state(sc, 3.0), _cylinder_state(sc, 3.0, cx=7.0 + s), sc, 2, 50)
    assert cs == pytest.approx(2 * s / np.pi, rel=0.1)


def test_chamfer_sphere_radius_change(tiny_scene):
    sc = tiny_scene
    z, y, x = _grid(sc)
    r = np.sqrt((x - 7) ** 2 + (y - 7) ** 2 + (z - 10) ** 2)
    mask = z - 25.3
    cm, cs = M.chamfer_channels(_state(sc, mask, r - 3.0), _state(sc, mask, r - 4.0), sc, 0, 0)
    assert cs == pytest.approx(1.0, abs=0.05)


def test_sampling_is_seeded_and_area_weighted(tiny_scene):
    z, _, _ = _grid(tiny_scene)
    field = (z - 8.2)[:21] * np.ones(tiny_scene.field_shape)[:21]
    p1, fb = M.sample_surface_points(field, (3, 4, 1))
    p2, _ = M.sample_surface_points(field, (3, 4, 1))
    p3, _ = M.sample_surface_points(field, (3, 5, 1))
    assert not fb and p1.shape == (M.N_SURFACE_SAMPLES, 3)
    np.testing.assert_array_equal(p1, p2)
    assert not np.array_equal(p1, p3)
    np.testing.assert_allclose(p1[:, 0], 8.2, atol=1e-5)
    # uniform over the plane: each half of the H extent gets about half the samples
    h = tiny_scene.field_shape[1] - 1
    assert abs((p1[:, 1] < h / 2).mean() - 0.5) < 0.02


def test_fallback_without_zero_crossing(tiny_scene):
    sc = tiny_scene
    z, y, x = _grid(sc)
    field = np.ones(sc.field_shape)
    field[5, 3, 4] = 0.2  # smallest |SDF| voxel
    pts, fb = M.sample_surface_points(field, (0, 0, 1))
    assert fb
    np.testing.assert_array_equal(pts, [[5.0, 3.0, 4.0]])
    # a state whose Si crop has no surface still gets a finite, deterministic CD
    a = _state(sc, z - 25.3, np.ones_like(z) * sc.d_max_vox)  # fully clipped: all voxels tie
    b = _state(sc, z - 25.3, z - 8.2)
    d1 = M.chamfer_distance(a, b, sc, 0, 1)
    assert np.isfinite(d1) and d1 > 0 and d1 == M.chamfer_distance(a, b, sc, 0, 1)


def test_chamfer_matrix_cache_and_batch(tiny_scene):
    sc = tiny_scene
    states = np.stack([_cylinder_state(sc, r) for r in (2.0, 2.5, 3.0)])  # (3, 2, D, H, W)
    pred = np.stack([states, states[::-1]], axis=1)  # (N=3, S=2, ...)
    true = np.stack([states, states], axis=1)
    cache: dict = {}
    mat = M.chamfer_matrix(pred, true, sc, case_ids=[0, 1, 2], steps=[50, 100], cache=cache)
    assert mat.shape == (3, 2)
    np.testing.assert_array_equal(mat[:, 0], 0.0)
    assert mat[1, 1] == 0.0 and mat[0, 1] > 0 and mat[2, 1] > 0
    assert len(cache) == 3 * 2 * 2
    # the cached reference surfaces give the same numbers as a fresh computation
    assert M.mean_chamfer(pred, true, sc, [0, 1, 2], [50, 100], cache=cache) == pytest.approx(mat.mean())
    single = M.chamfer_matrix(pred[:2, 1], true[:2, 1], sc, [0, 1])  # (N, 2, D, H, W): final step
    assert single.shape == (2,) and single[1] == 0.0


# ----- Params ------------------------------------------------------------------------------------


def test_count_params_trainable_shared_once():
    import torch
    from torch import nn

    lin = nn.Linear(3, 4)  # 16
    model = nn.Sequential(lin, nn.ReLU(), lin, nn.Linear(4, 2))  # shared lin counted once; +10
    model.register_buffer("rules", torch.ones(37, 22))  # buffers excluded
    frozen = nn.Linear(5, 5)
    frozen.requires_grad_(False)
    model.add_module("frozen", frozen)
    assert M.count_params(model) == 26
