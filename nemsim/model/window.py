"""Depth window for NEMSim inference: compute only the depth slab that can change ("model only what a scene
needs").

The etch changes the fields only near the interfaces: far below the etch front the silicon is solid (both SDF
channels saturated at ±1) and stays so until the front arrives. A windowed call runs the network on the
suffix slab ``[a, D)`` of the state (the unsaturated band plus a halo, up to the top of the box) and copies
the voxels below ``a`` unchanged.

What ties a voxel to every other one, and how the window keeps it (the layers are kept and fed what they
would see on the whole volume):
  * GroupNorm statistics and the encoder's context pooling z̄ (mean and max over the volume): the window's
    own per-slice sums and maxima plus those of the slices below it, recorded in the last full call;
  * 3x3x3 convolutions see one slice below the window: taken from the last full call's input;
  * MRC (volume-wide normalizations) runs on the full latent grid, the window's latent spliced onto the
    recorded one below it.

A full call ("record") runs the whole state and records those quantities. The recorded values are exact as
long as the state below ``a`` is unchanged (it is copied), but the features there feel the window through
the receptive field and the statistics, so the windowed rollout agrees with the full one only within a
tolerance (``tests/evaluation/test_rollout_window.py``). A new plan is made when the band comes closer than
``halo`` slices to ``a``; ``a`` is then put ``halo + margin`` slices below the band, rounded down to a
multiple of 8 so that every encoder level (1/2, 1/4, 1/8) sees an aligned suffix of its grid.

Why ``rollout(window=...)`` is off by default: on ``small`` the unsaturated band is already about half the
depth and strong recipes etch to the bottom, so the bookkeeping (per-layer sums, concatenations, the spliced
MRC) costs more than the saved convolutions. It can pay where the band is a small part of the depth
(``paper``); a model without volume-wide normalization and pooling would make the window exact.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

ALIGN = 8  # window start multiple: the encoder's coarsest grid is 1/8


@dataclass(frozen=True)
class WindowConfig:
    band_level: float = 0.9  # a depth slice is in the band if any voxel has |x| < band_level
    halo: int = 8  # slices kept between the band and the window start (re-plan when closer)
    margin: int = 8  # extra slices below the band at a re-plan, so plans are rare


@dataclass
class WindowRun:
    """State shared by the windowed layers during one call: the mode (record on a full call, else window)
    and the per-layer records of the last full call. Layers find their records by identity."""

    recording: bool = True
    records: dict[tuple[int, str], Any] = field(default_factory=dict)

    def put(self, module: nn.Module, value: Any, tag: str = "") -> None:
        self.records[(id(module), tag)] = value

    def get(self, module: nn.Module, tag: str = "") -> Any:
        return self.records[(id(module), tag)]


def _offset(full_len: int, crop_len: int) -> int:
    """Offset of a suffix crop of length crop_len in a grid of length full_len."""
    assert 0 <= full_len - crop_len, f"window of {crop_len} slices longer than the recorded grid {full_len}"
    return full_len - crop_len


def window_conv(conv: nn.Conv3d, x: torch.Tensor, run: WindowRun, compute) -> torch.Tensor:
    """A 3x3x3 (stride 1 or 2, padding 1) convolution of a suffix crop x (B, C, Dc, H, W): the slice below
    the crop comes from the recorded full input instead of zero padding. ``compute(x, padding)`` runs the
    convolution with the given padding."""
    if run.recording:
        run.put(conv, x)
        return compute(x, conv.padding)
    full = run.get(conv)  # (B, C, D, H, W) input of the last full call
    o = _offset(full.shape[2], x.shape[2])
    if o == 0:
        return compute(x, conv.padding)
    zero = x.new_zeros(x.shape[0], x.shape[1], 1, *x.shape[3:])
    ext = torch.cat([full[:, :, o - 1:o].to(x.dtype), x, zero], dim=2)  # (B, C, Dc + 2, H, W)
    return compute(ext, (0, *conv.padding[1:]))


def window_group_norm(gn: nn.GroupNorm, x: torch.Tensor, run: WindowRun) -> torch.Tensor:
    """GroupNorm of a suffix crop x (B, C, Dc, H, W) with the statistics of the whole volume: the crop's
    per-slice sums plus the recorded ones below it."""
    B, C, D = x.shape[:3]
    G = gn.num_groups
    xf = x.float()
    # per-slice sums (plain sums: much faster than var_mean on these channels-last tensors)
    s1 = xf.sum(dim=(3, 4)).view(B, G, C // G, D).sum(2)  # (B, G, Dc) Σx
    s2 = xf.square().sum(dim=(3, 4)).view(B, G, C // G, D).sum(2)  # (B, G, Dc) Σx²
    per_slice = x.shape[3] * x.shape[4] * (C // G)
    if run.recording:
        run.put(gn, (s1, s2))
        return F.group_norm(x, G, gn.weight, gn.bias, gn.eps)
    r1, r2 = run.get(gn)
    o = _offset(r1.shape[2], D)
    n = per_slice * (o + D)
    mu = (s1.sum(-1) + r1[:, :, :o].sum(-1)) / n  # (B, G)
    var = ((s2.sum(-1) + r2[:, :, :o].sum(-1)) / n - mu.square()).clamp_min(0)  # (B, G)
    rstd = torch.rsqrt(var + gn.eps)  # (B, G)
    # folded into one per-channel scale and shift: y = x · scale + shift
    scale = rstd.repeat_interleave(C // G, dim=1)  # (B, C)
    shift = -mu.repeat_interleave(C // G, dim=1) * scale  # (B, C)
    if gn.affine:
        scale, shift = scale * gn.weight, shift * gn.weight + gn.bias
    shift, scale = shift[:, :, None, None, None].to(x.dtype), scale[:, :, None, None, None].to(x.dtype)
    return torch.addcmul(shift, x, scale)


def window_pool(encoder: nn.Module, e3: torch.Tensor, run: WindowRun) -> torch.Tensor:
    """[mean, max] over space of the 1/8-grid features e3 (B, C, d, h, w) as over the whole volume:
    (B, 2C)."""
    s = e3.sum(dim=(3, 4))  # (B, C, d)
    m = e3.amax(dim=(3, 4))  # (B, C, d)
    per_slice = e3.shape[3] * e3.shape[4]
    if run.recording:
        run.put(encoder, (s, m), "pool")
        return torch.cat([s.sum(-1) / (per_slice * e3.shape[2]), m.amax(-1)], dim=1)
    rs, rm = run.get(encoder, "pool")
    o = _offset(rs.shape[2], e3.shape[2])
    mean = (s.sum(-1) + rs[:, :, :o].sum(-1)) / (per_slice * (o + e3.shape[2]))  # (B, C)
    mx = m.amax(-1) if o == 0 else torch.maximum(m.amax(-1), rm[:, :, :o].amax(-1))  # (B, C)
    return torch.cat([mean, mx], dim=1)


def window_upsample(encoder: nn.Module, coarse: torch.Tensor, size: tuple[int, int, int],
                    run: WindowRun) -> torch.Tensor:
    """Nearest up-sampling of the 1/8 grid (B, C, d3, h3, w3) to ``size`` on the 1/4 grid with the whole
    volume's depth index map (odd sizes: not a plain 2x, it depends on the full sizes)."""
    if run.recording:
        run.put(encoder, (coarse.shape[2], size[0]), "up")
        return F.interpolate(coarse, size=size, mode="nearest")
    d3, d2 = run.get(encoder, "up")
    o2, o3 = _offset(d2, size[0]), _offset(d3, coarse.shape[2])
    # PyTorch's "nearest": src = floor(dst * (in / out)) in float32, clamped to in - 1
    scale = torch.tensor(d3 / d2, dtype=torch.float32)
    src = torch.clamp((torch.arange(o2, d2, dtype=torch.float32) * scale).floor().long(), max=d3 - 1) - o3
    picked = coarse.index_select(2, src.to(coarse.device))  # (B, C, Dc2, h3, w3)
    return F.interpolate(picked, size=size, mode="nearest")


def splice_latent(mrc: nn.Module, z: torch.Tensor, run: WindowRun) -> torch.Tensor:
    """The full latent grid for MRC: the window's latent (a suffix) on top of the recorded one."""
    if run.recording:
        run.put(mrc, z, "z")
        return z
    full = run.get(mrc, "z")  # (B, C_z, d, h, w)
    o = _offset(full.shape[2], z.shape[2])
    return z if o == 0 else torch.cat([full[:, :, :o].to(z.dtype), z], dim=2)


@contextmanager
def attached(model: nn.Module, run: WindowRun) -> Iterator[None]:
    """Attach ``run`` to the encoder's and decoder's windowed layers for one call (not MRC: it runs on the
    full latent grid). Not thread-safe: a model must not serve other calls meanwhile."""
    layers = [m for part in (model.encoder, model.decoder) for m in part.modules() if hasattr(m, "_window")]  # type: ignore[union-attr]
    for m in layers:
        m._window = run
    try:
        yield
    finally:
        for m in layers:
            del m._window  # back to the class default (None)


def band_start(x: torch.Tensor, band_level: float) -> int:
    """First depth slice of x (B, C, D, H, W) with any voxel |x| < band_level (D if none)."""
    inside = (x.abs() < band_level).any(dim=4).any(dim=3).any(dim=1).any(dim=0)  # (D,)
    idx = torch.nonzero(inside)
    return int(idx[0]) if len(idx) else x.shape[2]


class DepthWindow:
    """``predict`` of a NEMSim model computed on the depth slab that can change (module docstring).

    ``predict(x, cache)`` -> (B, k, 2, D, H, W) like ``NEMSim.predict``; voxels below the window start are
    copied from x. ``stats()`` reports the calls, the full (re-planning) calls, and the fraction of voxels
    computed (mean over calls of the computed slab's share of the depth).
    """

    def __init__(self, model: nn.Module, cfg: WindowConfig | None = None) -> None:
        if not callable(getattr(model, "predict", None)) or not hasattr(model, "encoder"):
            raise ValueError(f"a depth window needs a NEMSim model (predict, encoder); "
                             f"got {type(model).__name__}")
        self.model, self.cfg = model, cfg or WindowConfig()
        self.run: WindowRun | None = None
        self.start = 0  # a: first computed slice
        self.calls = self.full_calls = 0
        self.computed = 0.0  # Σ over calls of the computed share of the depth

    def predict(self, x: torch.Tensor, cache: dict[str, Any]) -> torch.Tensor:
        B, C, D, H, W = x.shape
        cfg = self.cfg
        lo = band_start(x, cfg.band_level)
        if self.run is None or (self.start > 0 and lo - cfg.halo < self.start):  # (re-)plan: a full call
            self.start = max(0, (lo - cfg.halo - cfg.margin) // ALIGN * ALIGN)
            self.run = WindowRun(recording=True)
            with attached(self.model, self.run):
                out = self.model.predict(x, cache, window=self.run)  # type: ignore[operator]  # (B, k, 2, D, H, W)
            self.run.recording = False
            out[:, :, :, : self.start] = x[:, None, :, : self.start]  # held below the window
            self.full_calls += 1
            share = 1.0
        elif self.start == 0:  # the window is the whole volume: the plain call, no records needed
            out = self.model.predict(x, cache)  # type: ignore[operator]
            share = 1.0
        else:
            with attached(self.model, self.run):
                slab = x[:, :, self.start:]  # (B, 2, D-a, H, W)
                part = self.model.predict(slab, cache, window=self.run)  # type: ignore[operator]  # (B, k, 2, D-a, H, W)
            held = x[:, None, :, : self.start].expand(B, part.shape[1], C, self.start, H, W)
            out = torch.cat([held, part], dim=3)  # (B, k, 2, D, H, W)
            share = (D - self.start) / D
        self.calls += 1
        self.computed += share
        return out

    def stats(self) -> dict[str, float]:
        """{"calls", "full_calls", "fraction_computed", "start"}: fraction_computed is the mean share of the
        voxels computed per call (1.0 = no saving)."""
        return {"calls": self.calls, "full_calls": self.full_calls,
                "fraction_computed": self.computed / max(self.calls, 1), "start": self.start}
