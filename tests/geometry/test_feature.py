"""Feature: geometry as data (nemsim.geometry.feature), hand-computed on tiny and small."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nemsim.geometry.feature import Feature
from nemsim.scenes import SMALL, TINY, Scene
from nemsim.sim import SimConfig, initial_state
from nemsim.sim.domain import RESIST, SI, initial_domain, opening_coverage


@pytest.mark.parametrize("scene", [TINY, SMALL], ids=["tiny", "small"])
def test_default_is_the_scenes_hole(scene):
    f = Feature.default(scene)
    assert f == Feature("hole", 40.0, 80.0)
    assert f.symmetry == "d4"
    assert f.apply(scene) == scene  # the named scenes are their default feature
    assert scene.with_feature(f) == scene


def test_dict_round_trip_and_errors():
    f = Feature("trench", 32.0, 100.0)
    assert Feature.from_dict(f.to_dict()) == f
    assert f.symmetry == "mirror_x_translate_y"
    with pytest.raises(ValueError, match="kind"):
        Feature("via", 40.0, 80.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cd_nm"):
        Feature("hole", -1.0, 80.0)
    with pytest.raises(ValueError, match="unknown"):
        Feature.from_dict({"kind": "hole", "cd_nm": 40, "mask_nm": 80, "pitch": 3})


def test_per_case_scene_small():
    s = Feature("hole", 24.0, 120.0).apply(SMALL)
    assert (s.si_top, s.resist_top, s.opening_radius_vox, s.kind, s.symmetry) == (30, 60, 3.0, "hole", "d4")
    assert (s.nx, s.ny, s.nz, s.voxel_nm) == (SMALL.nx, SMALL.ny, SMALL.nz, SMALL.voxel_nm)
    t = Feature("trench", 64.0, 40.0).apply(SMALL)
    assert (t.si_top, t.opening_radius_vox, t.kind, t.symmetry) == (50, 8.0, "trench", "mirror_x_translate_y")
    assert Scene.from_json(t.to_json()) == t
    assert '"kind"' not in SMALL.to_json()  # a hole scene's record is what it was before features
    assert Feature.of(t) == Feature("trench", 64.0, 40.0)
    # the mask thickness is whole voxels: 82 nm on 4 nm voxels is built as 80 nm
    assert Feature("hole", 40.0, 82.0).on_grid(SMALL) == Feature("hole", 40.0, 80.0)


@pytest.mark.parametrize(("feature", "match"), [
    (Feature("hole", 100.0, 80.0), "cd_nm=100"),  # no mask left between neighbours on the 104 nm pitch
    (Feature("trench", 8.0, 80.0), "cd_nm=8"),  # under two 8 nm voxels on tiny
    (Feature("hole", 40.0, 200.0), "mask_nm=200"),  # leaves under half of tiny's 160 nm of Si
    (Feature("hole", 40.0, 2.0), "mask_nm=2"),  # under one voxel
])
def test_check_refuses_what_does_not_fit(feature, match):
    with pytest.raises(ValueError, match=match) as err:
        feature.check(TINY)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=match):
        feature.apply(TINY)
    Feature("hole", 24.0, 160.0).check(TINY)  # the limits themselves fit


def test_x0_volumes_small():
    cfg = SimConfig().resolved(SMALL)
    cap, rcap = cfg.capacity, cfg.resist_capacity
    # trench 40 nm = 10 voxels exactly: slot columns 8..17 of 26, along all 26 rows; mask 120 nm = 30 layers
    t = Feature("trench", 40.0, 120.0).apply(SMALL)
    dom = initial_domain(t, cap, rcap)
    assert dom.mat[..., SI].sum() == 26 * 26 * 30 * cap
    assert dom.mat[..., RESIST].sum() == (26 - 10) * 26 * 30 * rcap
    # trench 42 nm: half-width 5.25 voxels, the two edge columns a quarter open: open area = cd exactly
    cov = opening_coverage(Feature("trench", 42.0, 80.0).apply(SMALL))
    assert np.allclose((1.0 - cov).sum(axis=0), 42.0 / 4.0)
    # hole 64 nm: open area pi r^2 (r = 8 voxels) within the 16x16 sub-sampling error
    cov = opening_coverage(Feature("hole", 64.0, 80.0).apply(SMALL))
    assert (1.0 - cov).sum() == pytest.approx(math.pi * 64.0, rel=0.01)


def test_x0_volumes_tiny():
    cfg = SimConfig().resolved(TINY)
    h = Feature("hole", 24.0, 40.0).apply(TINY)  # r = 1.5 voxels; mask 5 layers, Si 25 layers
    dom = initial_domain(h, cfg.capacity, cfg.resist_capacity)
    assert (h.si_top, h.resist_top) == (25, 30)
    assert dom.mat[..., SI].sum() == 13 * 13 * 25 * cfg.capacity
    assert dom.mat[:, :, 25:30, RESIST].sum() == dom.mat[..., RESIST].sum()
    assert (1.0 - opening_coverage(h)).sum() == pytest.approx(math.pi * 1.5**2, rel=0.02)


def _close(a, b) -> bool:
    """Equal up to Psi's raster-order error (normalized SDF: RMS under 5e-3, at most 0.1 at a voxel)."""
    d = a - b
    return float(np.sqrt((d**2).mean())) < 5e-3 and float(np.abs(d).max()) < 0.1


@pytest.mark.parametrize("scene", [TINY, SMALL], ids=["tiny", "small"])
def test_x0_symmetry(scene):
    cfg = SimConfig().resolved(scene)
    # hole: the square's 8 symmetries about the axis, exactly on the voxel amounts
    h = Feature("hole", 32.0, 96.0).apply(scene)
    m = initial_domain(h, cfg.capacity, cfg.resist_capacity).mat[..., RESIST]  # (nx, ny, nz)
    for img in (m[::-1], m[:, ::-1], m.transpose(1, 0, 2)):
        assert np.array_equal(img, m)
    x0 = initial_state(h)  # (2, D, H, W): Psi is symmetric up to its sweeps' raster error
    for img in (x0[..., ::-1], x0[..., ::-1, :], x0.swapaxes(-1, -2)):
        assert _close(img, x0)
    # trench: the mirror x -> -x and every translation along y
    t = Feature("trench", 32.0, 96.0).apply(scene)
    m = initial_domain(t, cfg.capacity, cfg.resist_capacity).mat[..., RESIST]
    assert np.array_equal(m[::-1], m)
    assert np.array_equal(np.roll(m, 3, axis=1), m)
    x0 = initial_state(t)
    assert _close(x0[..., ::-1], x0)
    assert _close(x0, np.broadcast_to(x0[:, :, :1, :], x0.shape))  # every y row the same


@pytest.mark.parametrize("scene", [TINY, SMALL], ids=["tiny", "small"])
def test_profile_metrics_read_the_per_case_scene(scene):
    """A feature cut 6 voxels into the Si by its own opening: depth 6 voxels, widths = its CD (hole: the
    diameter; trench: across x), no mask loss, the soft metrics agree."""
    import torch

    from nemsim.geometry.profile import profile_metrics
    from nemsim.geometry.soft_profile import soft_profile_metrics
    from nemsim.sim.sdf import psi

    cfg = SimConfig().resolved(scene)
    for feature in (Feature("hole", 48.0, 96.0), Feature("trench", 32.0, 64.0)):
        s = feature.apply(scene)
        dom = initial_domain(s, cfg.capacity, cfg.resist_capacity)
        cut = np.rint(opening_coverage(s) * cfg.capacity).astype(np.int32)  # (nx, ny) Si left per column
        dom.mat[:, :, s.si_top - 6 : s.si_top, SI] = cut[:, :, None]
        x = psi(*dom.fractions(), s, cfg.psi_sigma_vox)  # (2, D, H, W)
        m = profile_metrics(x, s)
        assert m["etch_depth"] == pytest.approx(6 * scene.voxel_nm, abs=0.5 * scene.voxel_nm)
        assert m["neck_width"] == pytest.approx(feature.cd_nm, abs=0.5 * scene.voxel_nm)
        assert m["top_width"] == pytest.approx(feature.cd_nm, abs=scene.voxel_nm)  # Psi rounds the corner
        assert abs(m["mask_loss"]) < 0.25 * scene.voxel_nm
        soft = soft_profile_metrics(torch.as_tensor(x)[None], s)
        for name in ("etch_depth", "top_width"):
            assert float(soft[name][0]) == pytest.approx(m[name], abs=0.5 * scene.voxel_nm)
