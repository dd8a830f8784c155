"""Monotone projection of rollouts (``nemsim.model.monotone``): no voxel falls more than eps below its
running maximum, on every rollout path; zero flux is still exactly no change."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bench.stress import initial_state
from nemsim.controls import FLUX_INDICES, HIGH, LOW, to_normalized
from nemsim.evaluation.rollout import rollout
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.inference.runtime import compile_model, openvino_available
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.model.monotone import (
    MONOTONE_AXIS_EPS,
    MONOTONE_EPS,
    MonotoneProjection,
    axis_columns,
    eps_field,
    running_max_drop,
)
from nemsim.scenes import SCENES, TINY

T = 12


def _model(rules, **cfg) -> NEMSim:
    """Untrained weights perturbed so every head is non-zero: a rollout that wanders (up and down)."""
    torch.manual_seed(0)
    model = NEMSim(rules, NEMSimConfig(**cfg)).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def _inputs() -> tuple[torch.Tensor, torch.Tensor]:
    """x0 (2, 2, D, H, W) the tiny scene's initial state; u (2, T, 14) a recipe changing at T // 2."""
    x0 = torch.as_tensor(initial_state(TINY))[None].repeat(2, 1, 1, 1, 1).float()
    g = torch.Generator().manual_seed(3)
    u = torch.rand(2, 1, 14, generator=g).repeat(1, T, 1) * 2 - 1  # (2, T, 14)
    u[:, T // 2 :] = torch.rand(2, 1, 14, generator=g) * 2 - 1
    return x0, u


def _worst_fall(traj: torch.Tensor, eps: tuple[float, ...]) -> float:
    """max over voxels and t of (running max over s < t) - eps_c - x_t: > 0 where the bound is broken."""
    prior = torch.cummax(traj, dim=1).values[:, :-1]  # (B, T, 2, D, H, W) max over s <= t - 1
    e = torch.tensor(eps).view(1, 1, -1, 1, 1, 1)
    return float((prior - e - traj[:, 1:]).max())


@pytest.mark.parametrize("k", [1, 3])
def test_rollout_never_falls_below_running_max(rules, k):
    model = _model(rules, steps_per_call=k)
    assert model.config.monotone_eps == MONOTONE_EPS  # on by default
    x0, u = _inputs()
    on = rollout(model, x0, u)
    off = rollout(model, x0, u, monotone=False)
    assert _worst_fall(off, MONOTONE_EPS) > 0.05  # without it these weights do run backwards
    assert _worst_fall(on, MONOTONE_EPS) <= 0.0
    # the first state is the projection of the model's own prediction (nothing else changes)
    floor = x0 - eps_field(x0.shape, MONOTONE_EPS, MONOTONE_AXIS_EPS)
    torch.testing.assert_close(on[:, 1], torch.maximum(off[:, 1], floor))
    assert (on[:, 1:] != off[:, 1:]).any() and torch.equal(on[:, 0], x0)
    assert torch.equal(rollout(model, x0, u, keep=False), on[:, -1])


def test_every_runtime_backend_projects(rules):
    model = _model(rules, steps_per_call=3)
    x0, u = _inputs()
    ref = rollout(model, x0, u)
    backends = ["torch"] + (["openvino"] if openvino_available() else [])
    for backend in backends:
        pred = compile_model(model, backend, "f32")
        with torch.inference_mode():  # as the service calls it
            out = rollout(pred, x0, u)
        assert _worst_fall(out, MONOTONE_EPS) <= 0.0
        assert (out - ref).abs().max() <= 1e-4


def test_zero_flux_is_still_exactly_no_change(rules):
    model = _model(rules, flux_gate=True)
    x0, _ = _inputs()
    raw = 0.5 * (LOW + HIGH)
    raw[list(FLUX_INDICES)] = 0.0
    u = torch.from_numpy(to_normalized(raw[None])).float()  # (1, 14)
    traj = rollout(model, x0[:1], u, 30)
    assert (traj - x0[:1, None]).abs().max() <= 1e-6


def test_config_switches(rules):
    x0, u = _inputs()
    off_cfg = _model(rules, monotone_eps=None)
    on = _model(rules)
    assert torch.equal(rollout(off_cfg, x0, u), rollout(on, x0, u, monotone=False))
    assert torch.equal(rollout(off_cfg, x0, u, monotone=True), rollout(on, x0, u))  # True: MONOTONE_EPS
    # checkpoints written before the key existed load with the projection on
    assert NEMSimConfig.from_dict({"steps_per_call": 3}).monotone_eps == MONOTONE_EPS
    assert NEMSimConfig.from_dict({"monotone_eps": [0.0, 0.1]}).monotone_eps == (0.0, 0.1)
    # states lie in [-1, 1]: a slack of 2 is never active
    wide = _model(rules, monotone_eps=(2.0, 2.0), monotone_axis_eps=None)
    assert torch.equal(rollout(wide, x0, u), rollout(on, x0, u, monotone=False))


def test_projection_keeps_monotone_states_and_rejects_bad_eps():
    g = torch.Generator().manual_seed(0)
    steps = torch.rand(5, 1, 2, 3, 3, 3, generator=g).cumsum(0) * 0.1 - 0.5  # non-decreasing in time
    proj = MonotoneProjection(steps[0], (0.0, 0.0))
    for s in steps[1:]:
        assert torch.equal(proj(s), s)
    assert torch.equal(proj(steps[0]), steps[-1])  # eps = 0: a fall is lifted to the running maximum
    assert np.all(running_max_drop(steps[:, 0].numpy()) == 0)
    with pytest.raises(ValueError, match="one per channel"):
        MonotoneProjection(steps[0], (0.1,))
    with pytest.raises(ValueError, match=">= 0"):
        MonotoneProjection(steps[0], (0.1, -0.1))


def test_axis_columns_are_the_depth_readout():
    """The Si columns the etch depth is read from are exactly ``axis_columns``: changing any other voxel of
    the Si channel leaves the depth as it is; changing an axis voxel at the floor moves it."""
    for scene in SCENES.values():
        ys, xs = axis_columns(*scene.field_shape[1:])
        cx, cy = scene.opening_centre
        assert xs == sorted({int(np.floor(cx + 1)), int(np.ceil(cx + 1))})
        assert ys == sorted({int(np.floor(cy + 1)), int(np.ceil(cy + 1))})
    x = initial_state(TINY).astype(np.float32)  # (2, D, H, W): flat Si surface, depth 0
    base = profile_metrics_batch(x[None], TINY)["etch_depth"][0]
    ys, xs = axis_columns(*x.shape[2:])
    row = TINY.si_top  # the top Si row (padded index)
    off_axis = x.copy()
    keep = np.zeros(x.shape[2:], dtype=bool)
    keep[ys[0] : ys[-1] + 1, xs[0] : xs[-1] + 1] = True
    off_axis[1, row - 3 : row + 3, ~keep] = 1.0  # vacuum everywhere around the axis
    assert profile_metrics_batch(off_axis[None], TINY)["etch_depth"][0] == base
    on_axis = x.copy()
    on_axis[1, row, ys[0] : ys[-1] + 1, xs[0] : xs[-1] + 1] = 0.5  # the axis voxel at the floor etched
    assert profile_metrics_batch(on_axis[None], TINY)["etch_depth"][0] > base


class _Jitter(torch.nn.Module):
    """A stand-in surrogate whose every step adds seeded zero-mean noise: a state that wanders both ways."""

    def __init__(self, **cfg) -> None:
        super().__init__()
        self.config = NEMSimConfig(**cfg)
        self.gen = torch.Generator().manual_seed(11)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return (x + 0.04 * torch.randn(x.shape, generator=self.gen)).clamp(-1, 1)


def test_depth_never_decreases_with_the_axis_projection():
    """With the default axis slack (0) a rollout's etch depth is non-decreasing at every step, whatever the
    network predicts; with the Si slack on the axis too, the same predictions make it fall."""
    x0, u = _inputs()
    tight = _Jitter()
    assert tight.config.monotone_axis_eps == MONOTONE_AXIS_EPS == 0.0
    traj = rollout(tight, x0, u)
    loose = rollout(_Jitter(monotone_axis_eps=None), x0, u)  # the same noise draws
    assert _worst_fall(traj, MONOTONE_EPS) <= 0.0
    falls = []
    for b in range(x0.shape[0]):
        depth = profile_metrics_batch(traj[b], TINY)["etch_depth"]
        assert np.all(np.diff(depth) >= -1e-9)  # nm: only the readout's float64 rounding
        falls.append(np.diff(profile_metrics_batch(loose[b], TINY)["etch_depth"]).min())
    assert min(falls) < -0.05  # nm: the per-channel slack alone lets the depth run backwards


@pytest.mark.parametrize("form", ["vectorized", "cpu", "cpu-slice"])
def test_chunk_projection_equals_state_by_state(form):
    """The projection of a call's n states -- the GPU form (a cumulative maximum) and the CPU's compiled pass,
    on a whole buffer and on a chunk of a batched trajectory buffer -- gives exactly the states and running
    maximum of projecting them one by one; a NaN stays NaN in the states and the running maximum."""
    from nemsim.model.monotone import MonotoneProjection

    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(2, 2, 6, 5, 5, generator=g) * 2 - 1
    buf = torch.rand(2, 6, 2, 6, 5, 5, generator=g) * 2 - 1
    buf[1, 2, 1, 3, 2, 2] = float("nan")
    states = buf[:, 1:5] if form == "cpu-slice" else buf[:, :4].contiguous()
    one, many = MonotoneProjection(x0, (0.05, 0.2), 0.0), MonotoneProjection(x0, (0.05, 0.2), 0.0)
    a = states.clone()
    for j in range(a.shape[1]):
        one.project_(a[:, j])
    b = states.clone() if form != "cpu-slice" else buf.clone()[:, 1:5]
    b = many._project_chunk_vectorized_(b) if form == "vectorized" else many.project_chunk_(b)
    assert torch.equal(a.nan_to_num(9.0), b.nan_to_num(9.0)) and torch.equal(a.isnan(), b.isnan())
    assert torch.equal(one.running_max.nan_to_num(9.0), many.running_max.nan_to_num(9.0))
    assert torch.equal(one.running_max.isnan(), many.running_max.isnan()) and many.running_max.isnan().any()
    assert not torch.equal(a.nan_to_num(9.0), states.nan_to_num(9.0))  # the projection changed something
