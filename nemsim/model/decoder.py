"""State Increment Decoder (eq:decoder, eq:supp_mrc_state_update): Δx = Dec(z̃_{t+1}, b_t, x_t).

The paper fixes only the residual form x̂_{t+1} = x_t + Dec(z̃, b, x). Our decoder is chosen for CPU speed:
no convolution runs at full resolution.

  1/4 grid:  ConvGNAct(C_z -> 24) + one residual block                          h (B, 24, d, h, w)
  1/2 grid:  g = SiLU(up(Conv1x1(h)) + Conv1x1(b) + Conv1x1(unshuffle(x)))       (B, 16, D/2, H/2, W/2)
             Δx' = Conv3x3x3(g) with 2·8 output channels
  full grid: Δx = shuffle(Δx') (each 1/2-grid voxel emits its 2x2x2 block of both channels)

``unshuffle`` / ``shuffle`` are the 3-D space-to-depth / depth-to-space rearrangements (2x2x2 blocks), so x
enters at full detail and Δx has per-voxel values; Conv1x1(unshuffle(x)) runs as the equivalent 2x2x2
stride-2 convolution of x. Up-sampling is nearest-neighbour, after the 1x1x1 mix (they commute). The last
convolution starts at ``out_scale`` (0.1) times its initial weights, zero bias: the initial prediction is
close to persistence while gradients reach every layer.

Optional refinement (``refine`` = n > 0, ``NEMSimConfig.decoder_refine``): n residual blocks
g <- g + GN(Conv(SiLU(GN(Conv(g))))) before the output convolution, since the one 3x3x3 output convolution is
otherwise all the spatial processing at 1/2 resolution and the profile's misses are one-voxel details. They
start as the identity, so a trained model grown by them predicts exactly what it did.

Multi-step output (``steps`` = k > 1, ``NEMSimConfig.steps_per_call``; not in the paper): the k cumulative
residuals from x_t (x̂_{t+j} = x_t + r_j), r_1 = Δx as above and

  E = shuffle(Conv1x1x1(g)) with 2·8·(k-1) output channels        (B, k-1, 2, D, H, W)
  r_j = j · r_1 + E_{j-1},  j = 2..k

linear extrapolation plus a learned per-voxel correction (zero-initialized): the etch front moves at a
roughly steady rate within k steps, and a 1x1x1 head costs a small part of a step where a 3x3x3 one would
cost more than the step. All k residuals come from one 1x1x1 convolution of [g, r_1] (weights [0, I],
[W_E_2, 2I], ..., [W_E_k, kI]). With k = 1 there is no extra head. ``extend_steps`` grows a trained head to
more states per call (fewer calls per rollout), keeping what it predicts for the first k states.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.model.layers import Conv3d, ConvGNAct, ResBlock3d, conv3d


@dataclass(frozen=True)
class DecoderConfig:
    latent_channels: int = 18  # C_z
    skip_channels: int = 12  # channels of b (encoder level 1, 1/2 resolution)
    widths: tuple[int, int] = (24, 16)  # widths at 1/4 and 1/2 resolution
    out_channels: int = 2
    out_scale: float = 0.1  # init scale of the last convolution
    steps: int = 1  # k: cumulative residuals returned per call (k - 1 from the 1x1x1 extra-step head)
    refine: int = 0  # residual blocks on g at 1/2 resolution, identity at initialization (see docstring)


def space_to_depth(x: torch.Tensor) -> torch.Tensor:
    """(B, C, D, H, W) -> (B, 8C, D/2, H/2, W/2): 2x2x2 blocks into channels (C-major)."""
    B, C, D, H, W = x.shape
    x = x.reshape(B, C, D // 2, 2, H // 2, 2, W // 2, 2)  # (B, C, d, 2, h, 2, w, 2)
    return x.permute(0, 1, 3, 5, 7, 2, 4, 6).reshape(B, 8 * C, D // 2, H // 2, W // 2)


def depth_to_space(x: torch.Tensor) -> torch.Tensor:
    """(B, 8C, d, h, w) -> (B, C, 2d, 2h, 2w), the inverse of ``space_to_depth``."""
    B, C8, d, h, w = x.shape
    C = C8 // 8
    x = x.reshape(B, C, 2, 2, 2, d, h, w).permute(0, 1, 5, 2, 6, 3, 7, 4)  # (B, C, d, 2, h, 2, w, 2)
    return x.reshape(B, C, 2 * d, 2 * h, 2 * w)


class ResidualDecoder(nn.Module):
    def __init__(self, cfg: DecoderConfig) -> None:
        super().__init__()
        w4, w2 = cfg.widths
        C = cfg.out_channels
        self.coarse = nn.Sequential(ConvGNAct(cfg.latent_channels, w4), ResBlock3d(w4))
        self.mix_latent = Conv3d(w4, w2, 1, bias=False)
        self.mix_skip = Conv3d(cfg.skip_channels, w2, 1, bias=False)
        self.mix_state = Conv3d(8 * C, w2, 1)
        if cfg.refine < 0:
            raise ValueError(f"decoder refine must be >= 0, got {cfg.refine}")
        # only built when asked: refine = 0 keeps the parameters and state dict of the paper-size decoder
        self.refine = nn.Sequential(*[ResBlock3d(w2, identity_init=True) for _ in range(cfg.refine)]) \
            if cfg.refine else None
        self.out = Conv3d(w2, 8 * C, 3, padding=1)
        with torch.no_grad():
            self.out.weight.mul_(cfg.out_scale)
            self.out.bias.zero_()  # type: ignore[union-attr]
        if cfg.steps < 1:
            raise ValueError(f"decoder steps must be >= 1, got {cfg.steps}")
        self.steps = cfg.steps
        if cfg.steps > 1:
            self.extra = Conv3d(w2, 8 * C * (cfg.steps - 1), 1)  # extra-step corrections E (see docstring)
            nn.init.zeros_(self.extra.weight)
            nn.init.zeros_(self.extra.bias)  # type: ignore[arg-type]
            # (16k, 16) block column [I; 2I; ..; kI]: r_j = j r_1 + E_j (not a parameter, not saved)
            ramp = torch.arange(1, cfg.steps + 1, dtype=torch.float32)[:, None, None] * torch.eye(8 * C)
            self.register_buffer("ramp", ramp.reshape(-1, 8 * C), persistent=False)

    def forward(self, z_next: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Cumulative residuals r (B, k, 2, D, H, W) from z̃ (B, C_z, d, h, w), b (B, 12, D/2, H/2, W/2),
        x (B, 2, D, H, W); r[:, 0] = Δx, the one-step residual."""
        r = self.packed(z_next, b, x)  # (B, 16k, D/2, H/2, W/2)
        out = depth_to_space(r)  # (B, 2k, D, H, W), channel = step * 2 + c
        return out.view(r.shape[0], self.steps, -1, *out.shape[2:])  # (B, k, 2, D, H, W)

    def packed(self, z_next: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``forward`` before the voxel shuffle: (B, 8·2k, D/2, H/2, W/2), channel (2j + c)·8 + 4dz + 2dy + dx
        holds r_{j+1}[c] at voxel (2z + dz, 2y + dy, 2w + dx) (``nemsim.model.unpack`` reads it so)."""
        g, r1 = self._trunk(z_next, b, x)
        if self.steps == 1:
            return r1
        # all k residuals by one 1x1x1 convolution of [g, r_1] (no extra full-size passes): the fused
        # weight's rows for step j are [W_E_j, j I] (for j = 1: [0, I]), its bias [0; b_E]
        w = self.extra.weight.flatten(1)  # (16(k-1), 16)
        fused = torch.cat([torch.cat([torch.zeros_like(w[: r1.shape[1]]), w]), self.ramp], dim=1)  # type: ignore[list-item]  # (16k, 32)
        bias = torch.cat([torch.zeros_like(self.extra.bias[: r1.shape[1]]), self.extra.bias])  # type: ignore[index, list-item]  # (16k,)
        # channels-first, so the GEMM's output is too and the voxel shuffle below is a single copy
        x_in = torch.cat([g.to(r1.dtype), r1], dim=1).contiguous()  # (B, 32, D/2, H/2, W/2)
        return conv3d(x_in, fused.to(r1.dtype)[:, :, None, None, None], bias.to(r1.dtype))  # (B, 16k, ..)

    def _trunk(self, z_next: torch.Tensor, b: torch.Tensor,
               x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The 1/2-grid feature g (B, 16, D/2, H/2, W/2) and the packed one-step residual r_1 (B, 16, ..)."""
        h = self.mix_latent(self.coarse(z_next))  # (B, 16, d, h, w)
        h = upsample2(h, tuple(b.shape[2:]))  # type: ignore[arg-type]  # (B, 16, D/2, H/2, W/2)
        g = F.silu(h + self.mix_skip(b) + self._mix_state(x.to(b.dtype)))  # (B, 16, D/2, H/2, W/2)
        if self.refine is not None:
            g = self.refine(g)  # (B, 16, D/2, H/2, W/2)
        return g, self.out(g)  # r_1: Δx before the voxel shuffle

    def _mix_state(self, x: torch.Tensor) -> torch.Tensor:
        """mix_state(space_to_depth(x)) computed as the equivalent 2x2x2 stride-2 convolution of x
        (same weights viewed as (16, C, 2, 2, 2): no permuted copy of the full-resolution state)."""
        w = self.mix_state.weight  # (16, 8C, 1, 1, 1), channel index c*8 + (dz*4 + dy*2 + dx)
        kernel = w.reshape(w.shape[0], x.shape[1], 2, 2, 2)  # (16, C, 2, 2, 2)
        return conv3d(x, kernel, self.mix_state.bias, stride=2)


def upsample2(h: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Nearest-neighbour up-sampling to ``size``; an exact 2x factor is a broadcast copy (several times
    faster than ``F.interpolate`` on CPU at these sizes, identical values)."""
    B, C, d, hh, w = h.shape
    if size != (2 * d, 2 * hh, 2 * w) or not h.is_contiguous():  # channels-last: interpolate keeps it
        return F.interpolate(h, size=size, mode="nearest")
    h = h[:, :, :, None, :, None, :, None].expand(B, C, d, 2, hh, 2, w, 2)  # (B, C, d, 2, h, 2, w, 2)
    return h.reshape(B, C, *size)


def extend_steps(old: dict[str, torch.Tensor], new: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``old`` (a state dict of k_old states per call) fitted to ``new`` (k_new > k_old): the extra-step head
    keeps its corrections E_2..E_k_old and continues them linearly, E_j = (j - 1) / (k_old - 1) · E_k_old for
    j > k_old (zero when k_old = 1), so the grown model predicts the same first k_old states and extrapolates
    the rest along its own trend (warm start of a model with more states per call). Other tensors are
    returned unchanged; a head that shrinks or has another layout is refused (ValueError)."""
    out = dict(old)
    for suffix in ("decoder.extra.weight", "decoder.extra.bias"):
        name_new = next((n for n in new if n.endswith(suffix)), None)
        if name_new is None:
            continue
        w_new = new[name_new]
        w_old = old.get(name_new)
        if w_old is not None and w_old.shape == w_new.shape:
            continue
        block = 8 * 2  # rows per step: 8 sub-voxels x 2 channels (``packed``)
        n_new = w_new.shape[0] // block + 1
        n_old = 1 if w_old is None else w_old.shape[0] // block + 1
        if n_new <= n_old or (w_old is not None and w_old.shape[1:] != w_new.shape[1:]):
            shape = None if w_old is None else tuple(w_old.shape)
            raise ValueError(f"{name_new}: shape {shape} does not extend to {tuple(w_new.shape)}")
        if w_old is None:
            out[name_new] = torch.zeros_like(w_new)
            continue
        last = w_old[-block:]  # E_k_old
        more = [last * ((j - 1) / (n_old - 1)) for j in range(n_old + 1, n_new + 1)]
        out[name_new] = torch.cat([w_old, *more])
    return out
