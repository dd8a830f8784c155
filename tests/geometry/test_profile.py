"""Profile metrics on analytic holes (tiny scene): known depth/width within half a voxel."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.geometry.profile import (
    BOW_SKIP_ROWS,
    METRIC_NAMES,
    measured_profile_metrics,
    profile_metrics,
    profile_metrics_batch,
)
from nemsim.scenes import SMALL


@pytest.mark.parametrize("depth", [0.0, 3.3, 7.0, 12.6])
def test_cylinder_depth_and_widths(tiny_scene, make_hole, depth):
    sc = tiny_scene
    m = profile_metrics(make_hole(sc, 2.0, depth), sc)
    v = sc.voxel_nm
    assert set(m) == set(METRIC_NAMES)
    assert m["etch_depth"] == pytest.approx(depth * v, abs=0.5 * v)
    if depth >= 1.0:
        for k in ("top_width", "neck_width", "bottom_width"):
            assert m[k] == pytest.approx(4.0 * v, abs=0.5 * v), k
    else:
        assert m["top_width"] == 0.0 and m["bottom_width"] == 0.0
    assert m["bowing"] == pytest.approx(0.0, abs=0.5 * v)
    assert m["mask_loss"] == pytest.approx(0.0, abs=1e-6)


def test_even_grid_axis_between_voxels(make_hole):
    # small has an even nx: the axis sits between voxel centres and is interpolated
    m = profile_metrics(make_hole(SMALL, 3.0, 10.4), SMALL)
    assert m["etch_depth"] == pytest.approx(10.4 * SMALL.voxel_nm, abs=0.5 * SMALL.voxel_nm)
    assert m["top_width"] == pytest.approx(6.0 * SMALL.voxel_nm, abs=0.5 * SMALL.voxel_nm)


def test_bowing_and_neck(tiny_scene, make_hole):
    sc = tiny_scene
    # hole radius 1.5, widened by 1.5 voxels around native z = 12 (Si top at 19.5), depth 14
    m = profile_metrics(make_hole(sc, 1.5, 14.0, bow=1.5, bow_depth=12.0), sc)
    v = sc.voxel_nm
    assert m["top_width"] == pytest.approx(3.0 * v, abs=0.5 * v)
    assert m["bowing"] == pytest.approx(3.0 * v, abs=0.5 * v)
    assert m["neck_width"] == pytest.approx(3.0 * v, abs=0.5 * v)
    assert m["bottom_width"] == pytest.approx(3.0 * v, abs=0.5 * v)


def test_mask_loss(tiny_scene, make_hole):
    sc = tiny_scene
    m = profile_metrics(make_hole(sc, 2.0, 5.0, mask_top=sc.resist_top - 0.5 - 2.7), sc)
    assert m["mask_loss"] == pytest.approx(2.7 * sc.voxel_nm, abs=1e-3)
    st = make_hole(sc, 2.0, 5.0)
    st[0] = 1.0  # mask gone entirely
    m = profile_metrics(st, sc)
    assert m["mask_loss"] == pytest.approx((sc.resist_top - sc.si_top) * sc.voxel_nm)


def test_etched_through(tiny_scene, make_hole):
    sc = tiny_scene
    st = make_hole(sc, 2.0, 5.0)
    st[1] = np.where(st[1] < 0, 1.0, st[1])  # no Si left anywhere: depth = full Si thickness
    st[1, :, 0, 0] = -1.0  # ... except a column far from the axis
    m = profile_metrics(st, sc)
    assert m["etch_depth"] == pytest.approx(sc.si_top * sc.voxel_nm)


def test_batch_matches_single_and_torch(tiny_scene, make_hole):
    import torch

    sc = tiny_scene
    states = np.stack([make_hole(sc, 2.0, d) for d in (0.0, 2.0, 5.5, 9.0)])
    batch = profile_metrics_batch(states, sc)
    for i, s in enumerate(states):
        single = profile_metrics(torch.from_numpy(s), sc)
        for k in METRIC_NAMES:
            assert batch[k][i] == pytest.approx(single[k]), k
    assert np.all(np.diff(batch["etch_depth"]) > 0)


def test_measured_metrics_are_nan_until_their_row_is_sidewall(tiny_scene, make_hole):
    """A width is measured once its row lies at least h_b (1 voxel here) above the floor: top and bottom
    width from a hole 1.5 voxels deep, neck, bowing and neck_depth from 3.5; elsewhere the numbers are
    ``profile_metrics_batch``'s."""
    sc = tiny_scene
    depths = (0.0, 1.2, 1.8, 3.2, 3.8)  # voxels
    states = np.stack([make_hole(sc, 2.0, d) for d in depths])
    measured, filled = measured_profile_metrics(states, sc), profile_metrics_batch(states, sc)
    assert set(measured) == {*METRIC_NAMES, "neck_depth"}
    defined_from = dict(top_width=1.5, bottom_width=1.5, neck_width=3.5, bowing=3.5, neck_depth=3.5)
    for name, values in measured.items():
        for d, value, number in zip(depths, values, filled.get(name, values), strict=True):
            if d < defined_from.get(name, 0.0):
                assert np.isnan(value), (name, d)
            else:
                assert value == number, (name, d)
    # what the NaN replace: the bottom read on the top row, the neck standing in for the top width
    assert filled["bottom_width"][1] == filled["top_width"][1]
    assert filled["neck_width"][3] == filled["top_width"][3]


def test_neck_depth_names_the_row_of_the_neck(tiny_scene, make_hole):
    """The neck is the narrowest row above the bow: a one-row constriction above a bulge is the neck, and
    neck_depth is that row's depth; in a straight hole (no bow) the neck is the first reference row."""
    sc = tiny_scene
    v = sc.voxel_nm
    st = make_hole(sc, 1.5, 14.0, bow=1.5, bow_depth=10.0)  # radius 3 at native z 9..11
    y, x = np.mgrid[0 : sc.ny + 2, 0 : sc.nx + 2] - 1.0  # native coordinates of the padded grid
    r = np.hypot(x - sc.opening_centre[0], y - sc.opening_centre[1])
    z = 15  # native row of the constriction: radius 1
    st[1, z + 1] = np.minimum(st[1, z + 1], (1.0 - r) / sc.d_max_vox)
    m = measured_profile_metrics(st[None], sc)
    assert m["neck_width"][0] == pytest.approx(2.0 * v, abs=1e-3)
    assert m["neck_depth"][0] == pytest.approx((sc.si_top - 0.5 - z) * v)
    assert m["bowing"][0] == pytest.approx(4.0 * v, abs=1e-3)
    straight = measured_profile_metrics(make_hole(sc, 1.5, 14.0)[None], sc)
    assert straight["bowing"][0] == 0.0
    assert straight["neck_depth"][0] == pytest.approx((0.5 + BOW_SKIP_ROWS) * v)


def test_bad_shape(tiny_scene):
    with pytest.raises(ValueError, match="state shape"):
        profile_metrics(np.zeros((2, 3, 3, 3)), tiny_scene)


def test_bowing_is_measured_below_the_rounded_top_rows(tiny_scene, make_hole):
    # Psi rounds the Si/resist corner, so the top Si rows read wider than the hole below them; a bulge
    # deeper down must still count (against the top row it was hidden: widest row minus top width <= 0)
    sc = tiny_scene
    v = sc.voxel_nm
    wide_top = make_hole(sc, 1.5, 14.0, bow=2.0, bow_depth=sc.si_top - 1.0)  # top two rows +2 voxels
    bulge = make_hole(sc, 1.5, 14.0, bow=1.0, bow_depth=12.0)  # +1 voxel around native z = 12
    st = np.maximum(wide_top, bulge)  # union of the two holes (Si SDF is negative inside Si)
    m = profile_metrics(st, sc)
    assert m["top_width"] == pytest.approx(7.0 * v, abs=0.5 * v)
    assert m["neck_width"] == pytest.approx(3.0 * v, abs=0.5 * v)
    assert m["bowing"] == pytest.approx(2.0 * v, abs=0.5 * v)
    # the rounded top alone is not a bow
    assert profile_metrics(wide_top, sc)["bowing"] == pytest.approx(0.0, abs=0.5 * v)


def test_metrics_of_a_quadrant_equal_those_of_its_unfolded_fields(tiny_scene):
    """A symmetric trajectory's quadrant (a quarter-domain rollout) gives the metrics of its full fields:
    the axis lines and the mask-top map are rebuilt by reflection (depth, widths and bowing bit for bit;
    mask loss up to the summation order of its mean)."""
    import torch

    from nemsim.sim.process import initial_state
    from nemsim.symmetry import fold, symmetrize

    g = torch.Generator().manual_seed(11)
    x0 = torch.from_numpy(initial_state(tiny_scene)).float()
    steps = [x0 + 0.02 * k * torch.rand(x0.shape, generator=g) for k in range(6)]  # a hole opening up
    states = symmetrize(torch.stack(steps).clamp(-1, 1))
    full = profile_metrics_batch(states.numpy(), tiny_scene)
    quad = profile_metrics_batch(fold(states).contiguous().numpy(), tiny_scene)
    assert full["etch_depth"][-1] > full["etch_depth"][0]
    for name in METRIC_NAMES:
        np.testing.assert_allclose(quad[name], full[name], rtol=0, atol=1e-9, err_msg=name)


def _half_widths_by_concatenation(lines: np.ndarray, a: float, n: int) -> np.ndarray:
    """The reference of `_half_widths`: each side built as a line (the axis sample first) and scanned."""
    from nemsim.geometry.profile import _first_crossing, _interp_at

    centre = _interp_at(lines, -1, a)[..., None]
    r0, l0 = int(np.floor(a)) + 1, int(np.ceil(a)) - 1
    right = np.concatenate([centre, lines[..., r0 : n + 1]], axis=-1)
    left = np.concatenate([centre, lines[..., l0:0:-1]], axis=-1)
    pos_r = np.concatenate([[a], np.arange(r0, n + 1, dtype=np.float64)])
    pos_l = np.concatenate([[a], np.arange(l0, 0, -1, dtype=np.float64)])
    return (_first_crossing(right, pos_r) - a) + (a - _first_crossing(left, pos_l))


@pytest.mark.parametrize("a", [0.5, 1.0, 1.5, 6.25, 13.0, 13.5, 26.0, 26.5])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_compiled_half_widths_equal_the_scan_of_built_lines(a, dtype):
    """The one-pass widths are bit-identical to scanning lines built by concatenation, NaN, zeros, lines
    without material and axes on and between voxels (at the domain edges too) included."""
    from nemsim.geometry.profile import _half_widths

    rng = np.random.default_rng(7)
    n = 26
    lines = rng.normal(0.1, 0.5, (40, 3, n + 2))
    lines[rng.random(lines.shape) < 0.05] = np.nan
    lines[rng.random(lines.shape) < 0.05] = 0.0
    lines[0] = 1.0  # vacuum only: the domain edge on both sides
    lines[1] = -1.0  # material at the axis
    lines = lines.astype(dtype)
    np.testing.assert_array_equal(_half_widths(lines, a, n), _half_widths_by_concatenation(lines, a, n))


def test_column_crossings_equal_those_of_contiguous_lines():
    """`_first_crossings_columns` on a strided view (rows reversed) equals `_first_crossing` of the columns
    moved last and copied."""
    from nemsim.geometry.profile import _first_crossing, _first_crossings_columns

    rng = np.random.default_rng(3)
    x = rng.normal(0.2, 0.6, (5, 12, 4, 4)).astype(np.float32)
    x[rng.random(x.shape) < 0.05] = np.nan
    x[:, :, 0, 0] = 1.0  # a column without material
    view = x[:, 10:2:-1]  # (5, 8, 4, 4), rows top to bottom, negative stride
    pos = np.arange(10, 2, -1, dtype=np.float64)
    out = np.empty((5, 16))
    _first_crossings_columns(view.reshape(5, 8, -1), pos, out)
    np.testing.assert_array_equal(out.reshape(5, 4, 4), _first_crossing(np.moveaxis(view, 1, -1), pos))
