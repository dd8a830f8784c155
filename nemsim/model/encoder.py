"""State Encoder SE (eq:se): x_t -> (z_t, b_t, z̄_t).

Paper ([supp_training]): three-level 3-D encoder, stem width 12, pyramid widths (12, 18, 24), 18 latent
channels. The paper is silent on where the latent lives and what b_t and z̄_t are; our choices, made for
speed on a CPU ("model only what a scene needs": cost follows the coarse latent, not the full box):

  * stem: stride-2 Conv3x3x3(2 -> 12): every full-resolution voxel is seen, features live at 1/2 resolution
    (no full-resolution feature map is ever computed; the decoder returns to full resolution by a
    voxel shuffle).
  * level 1: Conv(12 -> 12) at 1/2 resolution; its output is the support feature b_t.
  * level 2: stride-2 Conv(12 -> 18) + residual block at 1/4 resolution (e2).
  * level 3: stride-2 Conv(18 -> 24) + three residual blocks at 1/8 resolution (e3): the bulk of the
    encoder's parameters sits where it costs least (a 24 -> 24 3x3x3 convolution costs 8x less here).
  * z_t = Conv1x1x1(e2) + up(Conv1x1x1(e3)), 18 channels: the latent field lives on the 1/4-resolution
    grid (d, h, w); up is nearest-neighbour to e2's size (it commutes with the 1x1x1 convolution).
  * z̄_t = SiLU(Linear([mean, max] of e3 over space)) in R^24, the compact state context.

The input must already be padded so that D, H, W are multiples of 4 (``NEMSim`` does this).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.model.layers import Conv3d, ConvGNAct, ResBlock3d
from nemsim.model.window import window_pool, window_upsample


@dataclass(frozen=True)
class EncoderConfig:
    in_channels: int = 2  # state channels (mask, Si)
    stem: int = 12  # stem width
    widths: tuple[int, int, int] = (12, 18, 24)  # pyramid widths of the three levels
    latent_channels: int = 18  # channels of z_t
    context_dim: int = 24  # size of the compact state context z̄_t

    @property
    def downsample(self) -> int:
        """Spatial factor between the state grid and the latent grid (two stride-2 levels); the state must be
        padded to a multiple of it. Level 3 (1/8) handles odd sizes itself (stride-2 with padding)."""
        return 4


class StateEncoder(nn.Module):
    """SE(x) -> (z (B, C_z, d, h, w), b (B, w1, D/2, H/2, W/2), z̄ (B, K))."""

    _window = None  # a WindowRun while a depth-windowed call runs: pooling and up-sampling as on the volume

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        w1, w2, w3 = cfg.widths
        self.cfg = cfg
        self.stem = ConvGNAct(cfg.in_channels, cfg.stem, stride=2)
        self.level1 = ConvGNAct(cfg.stem, w1)
        self.level2 = nn.Sequential(ConvGNAct(w1, w2, stride=2), ResBlock3d(w2))
        self.level3 = nn.Sequential(
            ConvGNAct(w2, w3, stride=2), ResBlock3d(w3), ResBlock3d(w3), ResBlock3d(w3)
        )
        self.latent_fine = Conv3d(w2, cfg.latent_channels, 1)
        self.latent_coarse = Conv3d(w3, cfg.latent_channels, 1, bias=False)
        self.to_context = nn.Sequential(nn.Linear(2 * w3, cfg.context_dim), nn.SiLU())

    def forward(
        self, x: torch.Tensor, extra: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``extra`` (B, stem, D/2, H/2, W/2), optional: added to the stem's output (the transport input)."""
        B, C, D, H, W = x.shape
        f = self.cfg.downsample
        line = self.stem[0].line  # a cross-section's two rows (line mode, nemsim.model.layers): no H grid
        assert D % f == 0 and W % f == 0 and (H % f == 0 or line), \
            f"encoder input {(D, H, W)} not a multiple of {f}"
        h = self.stem(x)  # (B, stem, D/2, H/2, W/2)
        if extra is not None:
            h = h + extra.to(h.dtype)
        b = self.level1(h)  # (B, w1, D/2, H/2, W/2)
        e2 = self.level2(b)  # (B, w2, d, h, w)
        e3 = self.level3(e2)  # (B, w3, ~d/2, ~h/2, ~w/2)
        coarse = self.latent_coarse(e3)  # (B, C_z, ~d/2, ~h/2, ~w/2)
        if self._window is None:
            up = F.interpolate(coarse, size=tuple(e2.shape[2:]), mode="nearest")  # (B, C_z, d, h, w)
            pooled = torch.cat([e3.mean(dim=(2, 3, 4)), e3.amax(dim=(2, 3, 4))], dim=1)  # (B, 2 w3)
        else:
            up = window_upsample(self, coarse, tuple(e2.shape[2:]), self._window)
            pooled = window_pool(self, e3, self._window)
        z = self.latent_fine(e2) + up  # (B, C_z, d, h, w)
        z_bar = self.to_context(pooled)  # (B, K)
        return z, b, z_bar
