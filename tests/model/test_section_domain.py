"""The cross-section model (``domain = "section"``, a trench): hand-checked maps, predictions exactly constant
along the trench and mirrored across it, the folded and full paths agreeing, the fused rollout agreeing with
the pass-by-pass one, and OpenVINO agreeing with PyTorch."""

from __future__ import annotations

import pytest
import torch

from nemsim.evaluation.rollout import rollout
from nemsim.geometry.feature import Feature
from nemsim.inference.runtime import compile_model, openvino_available
from nemsim.scenes import quadrant_size
from nemsim.symmetry import SECTION_ROWS, FieldFold, mirror_pad_x, model_fold, rows_mean_, section_mean

torch.set_num_threads(1)


def _trench_field(n: int, lead: tuple[int, ...] = (3,)) -> torch.Tensor:
    """A field (*lead, n, n) constant along H and mirror-symmetric in W (a trench's), of distinct values."""
    row = torch.arange(quadrant_size(n), dtype=torch.float32)
    row = torch.cat([row, row.flip(0)[n % 2:]])  # mirrored across the centre
    scale = torch.arange(1, 1 + int(torch.tensor(lead).prod()), dtype=torch.float32).reshape(*lead, 1, 1)
    return (scale * row).expand(*lead, n, n).contiguous()


@pytest.mark.parametrize("n", [15, 28, 9])
def test_section_maps_by_hand(n):
    f = FieldFold("section", n)
    c = quadrant_size(n)
    assert f.plane == (SECTION_ROWS, c)
    x = torch.randn(2, 3, n, n, generator=torch.Generator().manual_seed(n))
    s = section_mean(x)
    # the mean over y and the x mirror: constant along H, mirrored in W, and a projection
    assert torch.equal(s, s.flip(-1))
    assert torch.equal(s, s[..., :1, :].expand_as(s))
    torch.testing.assert_close(s[..., 0, :], 0.5 * (x + x.flip(-1)).mean(dim=-2))
    torch.testing.assert_close(section_mean(s), s, atol=1e-6, rtol=0)
    t = _trench_field(n, (2, 3))
    assert f.fold(t).shape == (2, 3, SECTION_ROWS, c)
    assert torch.equal(f.unfold(f.fold(t)), t)  # the round trip, exactly
    out = torch.empty_like(t)
    assert f.unfold(f.fold(t), out) is out and torch.equal(out, t)
    for pad in range(1, c - n % 2 + 1):
        assert torch.equal(mirror_pad_x(f.fold(t), pad, n), t[..., :SECTION_ROWS, : c + pad])
    q = f.fold(t).clone()
    q[..., 1, :] += 1.0
    torch.testing.assert_close(f.finish(q), f.fold(t) + 1.0 / SECTION_ROWS)  # the rows' mean
    rows_mean_(q)  # the same, in place (a rollout's buffer)
    torch.testing.assert_close(q, f.fold(t) + 1.0 / SECTION_ROWS)
    with pytest.raises(ValueError, match="quarter"):
        FieldFold("eighth", n)  # type: ignore[arg-type]


def _section_model(scene, k: int = 3):
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    torch.manual_seed(0)
    cfg = {"steps_per_call": k, "flux_gate": True, "decoder_out_scale": 1.0, "domain": "section"}
    return build_model("nemsim", scene, compile_rules(load_rules()), cfg).eval()


def _trench_x0(scene, batch: int = 2) -> torch.Tensor:
    from nemsim.sim import initial_state

    trench = Feature("trench", 40.0, 80.0).apply(scene)
    return torch.as_tensor(initial_state(trench))[None].repeat(batch, 1, 1, 1, 1)  # (B, 2, D, H, W)


def test_section_rollout_is_exactly_a_trench(tiny_scene):
    model = _section_model(tiny_scene)
    n = tiny_scene.field_shape[-1]
    assert model_fold(model) == FieldFold("section", n)
    x0 = _trench_x0(tiny_scene)
    u = torch.rand(2, 5, 14, generator=torch.Generator().manual_seed(0)) * 2 - 1
    traj = rollout(model, x0, u)
    assert traj.shape == (2, 6, *tiny_scene.state_shape)
    assert torch.equal(traj[:, 0], x0)  # x̂_0 is the given state
    assert (traj[:, -1] - traj[:, 0]).abs().max() > 1e-3  # the model moves the state
    pred = traj[:, 1:]
    assert torch.equal(pred, pred[..., :1, :].expand_as(pred))  # constant along the trench
    assert torch.equal(pred, pred.flip(-1))  # mirrored across its axis
    torch.testing.assert_close(rollout(model, x0, u, keep=False), traj[:, -1], atol=0, rtol=0)


def test_section_and_full_paths_agree(tiny_scene):
    """``predict`` on the full trench field equals the unfolded prediction on its cross-section; so do the
    rollouts (up to float rounding)."""
    model = _section_model(tiny_scene)
    f = model_fold(model)
    assert f is not None
    x0 = section_mean(_trench_x0(tiny_scene))
    u = torch.rand(2, 14, generator=torch.Generator().manual_seed(1)) * 2 - 1
    with torch.no_grad():
        cache = model.precompute(u)
        full = model.predict(x0, cache)
        folded = model.predict(f.fold(x0).contiguous(), cache)
    assert folded.shape[-2:] == f.plane
    torch.testing.assert_close(full, f.unfold(folded), atol=0, rtol=0)
    traj = rollout(model, x0, u, steps=4)
    traj_f = rollout(model, f.fold(x0).contiguous(), u, steps=4)
    # the full path averages x0 over the trench's symmetries again: the mean of equal rows, float rounding
    torch.testing.assert_close(traj, f.unfold(traj_f), atol=2e-6, rtol=0)


def test_section_fused_finish_matches_the_pass_by_pass_path(tiny_scene, monkeypatch):
    """The fused writer's row mean and projection give the states of the PyTorch path (float rounding)."""
    from nemsim.model.surrogate import NEMSim

    model = _section_model(tiny_scene, k=2)
    x0 = _trench_x0(tiny_scene)
    u = torch.rand(2, 14, generator=torch.Generator().manual_seed(3)) * 2 - 1
    fused = rollout(model, x0, u, steps=5)
    monkeypatch.setattr(NEMSim, "predict_into", None)  # the pass-by-pass path
    slow = rollout(model, x0, u, steps=5)
    torch.testing.assert_close(fused, slow, atol=2e-6, rtol=0)
    assert torch.equal(fused[:, 1:], fused[:, 1:, ..., :1, :].expand_as(fused[:, 1:]))


def test_line_mode_is_the_periodic_3d_network(tiny_scene, monkeypatch):
    """Line mode (each 3x3x3 kernel summed over y, on two rows) computes exactly what the same network with
    periodic y padding computes on the field repeated to 8 rows (float rounding): the state dict is the
    3-D network's and the cross-section costs one row per grid."""
    import torch.nn.functional as F

    from nemsim.model.layers import Conv3d

    model = _section_model(tiny_scene, k=2)
    f = model_fold(model)
    assert f is not None and f.plane[0] == SECTION_ROWS == 2
    lines = [m for m in model.modules() if isinstance(m, Conv3d) and m.kernel_size == (3, 3, 3)]
    assert lines and all(m.line for m in lines)
    x = f.fold(section_mean(_trench_x0(tiny_scene))).contiguous()  # (2, 2, D, 2, c)
    u = torch.rand(2, 14, generator=torch.Generator().manual_seed(4)) * 2 - 1
    with torch.no_grad():
        cache = model.precompute(u)
        line = model.predict(x, cache)
        assert line.shape == (2, 2, *x.shape[1:])

        def periodic(self, x, padding=None):  # the 3-D convolution with y wrapped around
            if self.kernel_size != (3, 3, 3):
                return F.conv3d(x, self.weight, self.bias, self.stride, self.padding)
            return F.conv3d(F.pad(x, (0, 0, 1, 1, 0, 0), mode="circular"), self.weight, self.bias,
                            self.stride, (1, 0, 1))

        monkeypatch.setattr(Conv3d, "_forward", periodic)
        ref = model.predict(x.repeat(1, 1, 1, 4, 1), cache)  # 8 rows, the same field
    assert ref.shape[-2] == 8
    torch.testing.assert_close(line, ref[..., :2, :], atol=1e-5, rtol=0)
    assert (line - x[:, None]).abs().max() > 1e-3  # the model moves the state


def test_section_model_needs_a_square_grid():
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import Scene

    oblong = Scene("oblong", nx=13, ny=9, nz=33, voxel_nm=8.0, si_top=20, resist_top=30,
                   opening_radius_vox=2.5, symmetry="none")
    with pytest.raises(ValueError, match="square grid"):
        build_model("nemsim", oblong, compile_rules(load_rules()), {"domain": "section"})


@pytest.mark.skipif(not openvino_available(), reason="openvino not installed (nemsim[fast])")
def test_openvino_matches_pytorch_on_the_section(tiny_scene):
    model = _section_model(tiny_scene)
    x0 = _trench_x0(tiny_scene)
    u = torch.rand(2, 4, 14, generator=torch.Generator().manual_seed(2)) * 2 - 1
    ref = rollout(model, x0, u)
    rt = compile_model(model, "openvino", "f32")
    out = rollout(rt, x0, u)
    assert (out - ref).abs().max() <= 1e-4
    assert torch.equal(out[:, 1:], out[:, 1:, ..., :1, :].expand_as(out[:, 1:]))


def test_predictor_keeps_a_trench_on_its_cross_section(tiny_section_checkpoint):
    """``rollout(..., quadrant=True)`` of a section checkpoint returns the cross-section (its fold set) whose
    metrics, read from the line profile, equal those of the full fields; unfolded, the same states."""
    import numpy as np

    from nemsim.inference import Predictor
    from nemsim.scenes import TINY
    from service.schemas import array_to_controls, default_controls_raw

    pred = Predictor.from_checkpoint(tiny_section_checkpoint, backend="torch")
    assert pred.scene.kind == "trench" and pred.symmetric_fold is not None
    controls = array_to_controls(default_controls_raw())
    folded = pred.rollout(controls, 10, quadrant=True)
    full = pred.rollout(controls, 10)
    assert folded.fold == pred.symmetric_fold and folded.states.shape == (11, 2, TINY.field_shape[0],
                                                                           *pred.symmetric_fold.plane)
    assert pred.state_shape(quadrant=True) == folded.states.shape[1:]
    np.testing.assert_array_equal(pred.symmetric_fold.unfold(torch.from_numpy(folded.states)).numpy(),
                                  full.states)
    for name, values in full.metrics.items():
        np.testing.assert_array_equal(folded.metrics[name], values, err_msg=name)


def test_shipped_trench_model_etches_narrow_trenches_slower():
    """The shipped cross-section checkpoint runs in line mode and answers like a trench etch: every state
    constant along the line, the depth growing with time, and a narrower trench etching slower (ARDE: the
    simulator's slope is +0.19 nm per nm of width at the centre recipe, benchmarks/small/arde_trench.md)."""
    from pathlib import Path

    import numpy as np

    from nemsim.inference import Predictor
    from nemsim.model.layers import Conv3d
    from service.schemas import array_to_controls, default_controls_raw

    path = Path(__file__).resolve().parents[2] / "checkpoints" / "nemsim-small-trench.pt"
    pred = Predictor.from_checkpoint(path, backend="torch")
    assert pred.symmetric_fold == FieldFold("section", pred.scene.field_shape[-1])
    assert all(m.line for m in pred.model.modules() if isinstance(m, Conv3d) and m.kernel_size == (3, 3, 3))
    controls = array_to_controls(default_controls_raw())
    depth = {}
    for cd in (28.0, 60.0):
        out = pred.rollout(controls, 100, quadrant=True, feature=Feature("trench", cd, 80.0))
        assert out.states.shape[-2] == SECTION_ROWS
        assert np.array_equal(out.states, np.broadcast_to(out.states[..., :1, :], out.states.shape))
        d = np.asarray(out.metrics["etch_depth"])
        assert np.all(np.diff(d) > -0.5) and d[-1] > d[0] + 20.0  # etching, never refilling
        depth[cd] = d[-1]
    assert depth[28.0] < depth[60.0] - 1.0, depth
