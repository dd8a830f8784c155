"""``nemsim.symmetry`` and the quarter-domain model: hand-checked maps, exact symmetry of every prediction,
the quadrant and full-field paths agreeing, and the OpenVINO runtime matching PyTorch on the quadrant."""

from __future__ import annotations

import pytest
import torch

from nemsim.evaluation.rollout import rollout
from nemsim.inference.runtime import compile_model, openvino_available
from nemsim.scenes import SCENES, Scene, quadrant_size
from nemsim.symmetry import fold, mirror_pad, symmetrize, symmetrize_diagonal_, unfold

torch.set_num_threads(1)


def _images(x: torch.Tensor) -> list[torch.Tensor]:
    """The 8 images of x (..., n, n) under the square's symmetries."""
    out = []
    for t in (x, x.transpose(-1, -2)):
        out += [t, t.flip(-1), t.flip(-2), t.flip(-1).flip(-2)]
    return out


@pytest.mark.parametrize("n", [4, 5, 28, 15])
def test_maps_by_hand(n):
    x = torch.arange(3 * n * n, dtype=torch.float32).reshape(3, n, n)
    s = symmetrize(x)
    torch.testing.assert_close(s, sum(_images(x)) / 8)  # the mean of the 8 images
    for image in _images(s):
        torch.testing.assert_close(image, s)
    c = quadrant_size(n)
    assert fold(s).shape == (3, c, c)
    torch.testing.assert_close(unfold(fold(s), n), s, atol=0, rtol=0)
    out = torch.empty_like(s)
    assert unfold(fold(s), n, out) is out and torch.equal(out, s)
    for pad in range(1, c - n % 2 + 1):
        assert torch.equal(mirror_pad(fold(s), pad, n), unfold(fold(s), n)[..., : c + pad, : c + pad])


def test_unfold_by_hand():
    """n = 4: the quadrant [[a, b], [c, d]] mirrors across the axis between indices 1 and 2; n = 3 shares
    the centre row and column."""
    q = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    assert unfold(q, 4).tolist() == [[1, 2, 2, 1], [3, 4, 4, 3], [3, 4, 4, 3], [1, 2, 2, 1]]
    assert unfold(q, 3).tolist() == [[1, 2, 1], [3, 4, 3], [1, 2, 1]]


def test_scenes_declare_the_square_symmetry():
    for scene in SCENES.values():
        assert scene.symmetry == "d4"
        c = quadrant_size(scene.field_shape[-1])
        assert scene.quarter_state_shape == (2, scene.field_shape[0], c, c)
    with pytest.raises(ValueError, match="symmetry"):
        Scene("x", nx=4, ny=4, nz=8, voxel_nm=1.0, si_top=2, resist_top=4, opening_radius_vox=1.0,
              symmetry="c3")
    off = Scene("off", nx=4, ny=6, nz=8, voxel_nm=1.0, si_top=2, resist_top=4, opening_radius_vox=1.0,
                symmetry="none")
    with pytest.raises(ValueError, match="no quarter domain"):
        _ = off.quarter_state_shape


def _quarter_model(scene, quarter: bool = True):
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    torch.manual_seed(0)
    cfg = {"steps_per_call": 3, "flux_gate": True, "decoder_out_scale": 1.0,
           **({"domain": "quarter"} if quarter else {})}
    return build_model("nemsim", scene, compile_rules(load_rules()), cfg).eval()


def _x0(scene):
    from bench.stress import initial_state

    return torch.as_tensor(initial_state(scene))[None].repeat(2, 1, 1, 1, 1)  # (2, 2, D, H, W)


def test_quarter_rollout_is_exactly_symmetric(tiny_scene):
    model = _quarter_model(tiny_scene)
    assert model.config.full_size == tiny_scene.field_shape[-1]
    x0 = _x0(tiny_scene)
    u = torch.rand(2, 5, 14, generator=torch.Generator().manual_seed(0)) * 2 - 1
    traj = rollout(model, x0, u)
    assert traj.shape == (2, 6, *tiny_scene.state_shape)
    assert torch.equal(traj[:, 0], x0)  # x̂_0 is the given state
    assert (traj[:, -1] - traj[:, 0]).abs().max() > 1e-3  # the model moves the state
    for image in _images(traj[:, 1:]):
        assert torch.equal(image, traj[:, 1:])
    last = rollout(model, x0, u, keep=False)
    torch.testing.assert_close(last, traj[:, -1], atol=0, rtol=0)


def test_quadrant_and_full_paths_agree_on_symmetric_input(tiny_scene):
    """``predict`` on the full symmetric field (folded in, unfolded out) equals the unfolded prediction on
    its quadrant; a rollout from the full field equals the one from the quadrant, unfolded."""
    model = _quarter_model(tiny_scene)
    n = tiny_scene.field_shape[-1]
    x0 = symmetrize(_x0(tiny_scene))
    u = torch.rand(2, 14, generator=torch.Generator().manual_seed(1)) * 2 - 1
    with torch.no_grad():
        cache = model.precompute(u)
        full = model.predict(x0, cache)
        quarter = model.predict(fold(x0).contiguous(), cache)
    assert full.shape[-1] == n and quarter.shape[-1] == quadrant_size(n)
    torch.testing.assert_close(full, unfold(quarter, n), atol=0, rtol=0)
    traj = rollout(model, x0, u, steps=4)
    traj_q = rollout(model, fold(x0).contiguous(), u, steps=4)
    torch.testing.assert_close(traj, unfold(traj_q, n), atol=0, rtol=0)


def test_quarter_model_needs_a_symmetric_scene():
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    off = Scene("off", nx=13, ny=13, nz=33, voxel_nm=8.0, si_top=20, resist_top=30, opening_radius_vox=2.5,
                symmetry="none")
    with pytest.raises(ValueError, match="symmetry"):
        build_model("nemsim", off, compile_rules(load_rules()), {"domain": "quarter"})


@pytest.mark.skipif(not openvino_available(), reason="openvino not installed (nemsim[fast])")
def test_openvino_matches_pytorch_on_the_quadrant(tiny_scene):
    model = _quarter_model(tiny_scene)
    x0 = _x0(tiny_scene)
    u = torch.rand(2, 4, 14, generator=torch.Generator().manual_seed(2)) * 2 - 1
    ref = rollout(model, x0, u)
    rt = compile_model(model, "openvino", "f32")
    assert rt.backend == "openvino"
    out = rollout(rt, x0, u)
    assert (out - ref).abs().max() <= 1e-4
    for image in _images(out[:, 1:]):
        assert torch.equal(image, out[:, 1:])


def test_the_in_place_diagonal_average_is_the_diagonal_symmetrize():
    """``symmetrize_diagonal_`` (the rollout's per-call diagonal mirror, no temporary) gives the same float32
    values as ``symmetrize(x, "diagonal")`` on a whole buffer, on a chunk of a batched trajectory buffer
    (contiguous per batch row only) and on a transposed view (the fallback)."""
    g = torch.Generator().manual_seed(5)
    buf = torch.randn(3, 6, 2, 4, 7, 7, generator=g)
    for view in (buf.clone(), buf.clone()[:, 2:5], buf.clone().transpose(0, 1), buf.clone()[0, 0, 0, 0]):
        want = symmetrize(view, "diagonal")
        assert symmetrize_diagonal_(view) is view
        assert torch.equal(view, want)
        assert torch.equal(view, view.transpose(-1, -2))
